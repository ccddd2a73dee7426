"""The running rest: a rest's readings as one measurement applied to the state the rest began with.

Inside a rest the body does not turn, so each block adds nothing but more samples of the same static
readings. Their running means (accel, mag, the gyro's zero rate), weighted by each block's information
N/σ² (the noise level may change within a rest), are one measurement applied once to the state as it was
when the rest began (plus the process noise of the whole rest), re-done every block as N grows. Exact for
a linear model (the mean is sufficient); for the nonlinear one it keeps the linearisation where a single
measurement would have it: updating with every block at a drifting linearisation point instead gains
spurious information from the same static pose (with a cold accelerometer, its scale and bias along
gravity — o = a − g/s, a curve — ended at 5–18σ after 30 s at rest).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .blocks import Blocks

Array = NDArray[np.float64]
_ARRAYS = ("x", "P", "R_nom", "q", "sa", "sm", "sw")


@dataclass
class RestAccumulator:
    """The state at the rest's start (x (n,), P (n, n), R_nom (3, 3)), the process noise since (q (n,)),
    the held flags and mag use it was opened with, the information-weighted sums of the means (sa, sm,
    sw (3,)) and their information (na, nm, nw), the temperature regressor's sum and count (sT, nT), and
    ``post``: per sensor the measurement the last posterior predicts and its covariance (for the next
    block's NIS)."""

    x: Array
    P: Array
    R_nom: Array
    held: dict[str, bool]
    use_mag: bool
    q: Array = field(default_factory=lambda: np.zeros(0))
    sa: Array = field(default_factory=lambda: np.zeros(3))
    na: float = 0.0
    sm: Array = field(default_factory=lambda: np.zeros(3))
    nm: float = 0.0
    sw: Array = field(default_factory=lambda: np.zeros(3))
    nw: float = 0.0
    sT: float = 0.0
    nT: int = 0
    post: dict[str, tuple[Array, Array]] = field(default_factory=dict)

    @classmethod
    def start(cls, x: Array, P: Array, R_nom: Array, held: dict[str, bool], use_mag: bool) -> RestAccumulator:
        return cls(x.copy(), P.copy(), R_nom.copy(), dict(held), use_mag, np.zeros(x.shape[0]))

    def add(self, B: Blocks, b: int, n: dict[str, float], use_acc: bool, use_mag: bool,
            temp_reg: Array | None) -> None:
        """Add block ``b`` of ``B`` with per-sample σ ``n``; ``temp_reg`` (L,) its temperature regressor
        (None: no temperature extension)."""
        L = int(B.hi[b] - B.lo[b])
        n_m = int(B.mhi[b] - B.mlo[b])
        if use_acc:
            w_ = L / n["accel"] ** 2
            self.sa += B.a_mean[b] * w_
            self.na += w_
        if use_mag:
            w_ = n_m / n["mag"] ** 2
            self.sm += B.m_mean[b] * w_
            self.nm += w_
        w_ = L / n["gyro"] ** 2
        self.sw += B.w_mean[b] * w_
        self.nw += w_
        if temp_reg is not None:
            self.sT += float(np.sum(temp_reg))
            self.nT += L

    @property
    def T_reg(self) -> float:
        """Mean temperature regressor over the rest (°C); 0 without one."""
        return self.sT / max(self.nT, 1)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able (plain lists and numbers)."""
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "post"}
        d = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in d.items()}
        d["post"] = {k: [v[0].tolist(), v[1].tolist()] for k, v in self.post.items()}
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RestAccumulator:
        a = {k: np.asarray(d[k], float) for k in _ARRAYS}
        post = {k: (np.asarray(v[0], float), np.asarray(v[1], float)) for k, v in d["post"].items()}
        return cls(a["x"], a["P"], a["R_nom"], dict(d["held"]), bool(d["use_mag"]), a["q"], a["sa"], float(d["na"]),
                   a["sm"], float(d["nm"]), a["sw"], float(d["nw"]), float(d["sT"]), int(d["nT"]), post)

    def sequential_nis(self, B: Blocks, b: int, n: dict[str, float], use_acc: bool,
                       use_mag: bool) -> list[tuple[str, float]]:
        """Block ``b``'s innovation against what the rest so far predicts (``post``): the NIS a per-block
        filter would record, per sensor (so that the NIS windows fill and judge as in motion)."""
        L, n_m = int(B.hi[b] - B.lo[b]), int(B.mhi[b] - B.mlo[b])
        out = []
        for s, mean, ok, cnt in (("accel", B.a_mean[b], use_acc, L), ("mag", B.m_mean[b], use_mag, n_m)):
            post = self.post.get(s)
            if post is not None and ok and cnt:
                nu = mean - post[0]
                try:
                    out.append((s, float(nu @ np.linalg.solve(post[1] + np.eye(3) * n[s] ** 2 / cnt, nu))))
                except np.linalg.LinAlgError:
                    pass
        return out
