"""The running rest: a rest's readings as one measurement applied to the state the rest began with.

Inside a rest the body does not turn, so each block adds nothing but more samples of the same static
readings. Their running means (accel, mag, the gyro's zero rate), weighted by each block's information
N/σ² (the noise level may change within a rest), are one measurement applied once to the state as it was
when the rest began (plus the process noise of the whole rest), re-done every block as N grows. Exact for
a linear model (the mean is sufficient); for the nonlinear one it keeps the linearisation where a single
measurement would have it: updating with every block at a drifting linearisation point instead gains
spurious information from the same static pose (with a cold accelerometer, its scale and bias along
gravity — o = a − g/s, a curve — ended at 5–18σ after 30 s at rest).

A rest's mean is only as good as the rest is still. White noise averages down as σ²/N; a reading that
wanders (a bench's micro-tilts, a bias that moves over seconds: the real PX4 log's accelerometer block
means at rest vary 4–16× more about their rest's mean than the noise between neighbouring blocks says) does
not. Each sensor's rest therefore also tests the scatter of its block means about their running mean
against what the block means' noise explains (χ² with 3(k − 1) degrees of freedom for k blocks); where it
is beyond 3σ of that, the excess variance per block is a floor σ_w² that the rest's mean keeps whatever
its length (:meth:`RestAccumulator.info`): its variance 1/N_info + σ_w² instead of 1/N_info.

The gyro's zero rate is a measurement of the bias *at the rest's end* (the state it updates), but the mean
is that of the bias over the rest. Where the bias drifts (:meth:`.noise.NoiseModel.walk_from_rest`: a trend
of the rest's gyro means), the rest's measurement is the trend line at the rest's end instead
(:meth:`RestAccumulator.gyro_mean`), with the variance of that extrapolation and, where the means scatter
about the line beyond their noise (a drift that is not straight), that excess as a floor
(:meth:`RestAccumulator.info`). The mean would state the bias half a rest ago: on the real PX4 log's 54-s
rest, 0.16–0.44 mrad/s from what the gyro reads at the rest's end.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .blocks import Blocks

Array = NDArray[np.float64]
_ARRAYS = ("x", "P", "R_nom", "q", "sa", "sm", "sw", "qa", "qm", "qw", "smt")


def _scatter_step(s: Array, n: float, m: Array, w: float) -> Array:
    """What one more block mean ``m`` (3,) of weight ``w`` adds to the weighted scatter about the running
    mean s/n (West 1979): w·n/(n + w)·(m − s/n)², per axis; w·0 for the first block."""
    if n <= 0.0:
        return np.zeros(3)
    c = w * n / (n + w)
    (mx, my, mz), (sx, sy, sz) = m.tolist(), s.tolist()  # Python floats, then one small array
    return np.array([(mx - sx / n) ** 2 * c, (my - sy / n) ** 2 * c, (mz - sz / n) ** 2 * c])


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
    # the wander test (:meth:`floor`): per axis the information-weighted scatter of the block means about
    # their running mean (3,), and the blocks
    qa: Array = field(default_factory=lambda: np.zeros(3))
    qm: Array = field(default_factory=lambda: np.zeros(3))
    qw: Array = field(default_factory=lambda: np.zeros(3))
    ka: int = 0
    km: int = 0
    kw: int = 0
    # the rest's duration (s) and the gyro bias's random walk in use (rad²/s³, :meth:`info`)
    dur: float = 0.0
    walk: float = 0.0
    # the gyro means' regression on the rest's time (:meth:`trend`): Σ w t, Σ w t², Σ w t m (3,)
    tw: float = 0.0
    ttw: float = 0.0
    smt: Array = field(default_factory=lambda: np.zeros(3))
    skipped: bool = False  # the last block was left out (.detectors.RestDetector.marginal): the next ends the rest

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
            self.qa += _scatter_step(self.sa, self.na, B.a_mean[b], w_)
            self.sa += B.a_mean[b] * w_
            self.na += w_
            self.ka += 1
        if use_mag:
            w_ = n_m / n["mag"] ** 2
            self.qm += _scatter_step(self.sm, self.nm, B.m_mean[b], w_)
            self.sm += B.m_mean[b] * w_
            self.nm += w_
            self.km += 1
        w_ = L / n["gyro"] ** 2
        t_ = self.dur
        self.tw += w_ * t_
        self.ttw += w_ * t_ * t_
        self.smt += B.w_mean[b] * (w_ * t_)
        self.qw += _scatter_step(self.sw, self.nw, B.w_mean[b], w_)
        self.sw += B.w_mean[b] * w_
        self.nw += w_
        self.kw += 1
        if temp_reg is not None:
            self.sT += float(np.sum(temp_reg))
            self.nT += L

    def _sums(self, sensor: str) -> tuple[float, Array, int]:
        if sensor == "accel":
            return self.na, self.qa, self.ka
        if sensor == "mag":
            return self.nm, self.qm, self.km
        return self.nw, self.qw, self.kw

    def floor(self, sensor: str) -> float:
        """The variance σ_w² per axis (the sensor's unit²) by which ``sensor``'s block means scatter about the
        rest's mean beyond their noise; 0 unless the scatter is beyond 3σ of it.

        With information weights w_b = L_b/σ² (the block mean's inverse variance), the weighted scatter
        T = Σ_b w_b |m_b − m̄|² (``qa``, ``qm``, ``qw``: accumulated about the running mean, West's weighted
        update, free of the cancellation of Σ w m² − |Σ w m|²/N) is χ² with 3(k − 1) degrees of freedom for
        k blocks of noise alone; beyond 1 + 3√(2/dof) in T/dof, the excess (T/dof − 1) times the mean block
        variance k/N."""
        n, q, k = self._sums(sensor)
        if k < 3 or n <= 0.0:
            return 0.0
        dof = 3 * (k - 1)
        qx, qy, qz = q.tolist()  # on Python floats: called several times per rest block
        ratio = (qx + qy + qz) / dof
        if not ratio - 1.0 > 3.0 * math.sqrt(2.0 / dof):
            return 0.0
        return (ratio - 1.0) * k / n

    def info(self, sensor: str) -> float:
        """The information of ``sensor``'s rest mean (1/variance per axis): N of its blocks' noise, and with
        a wander floor σ_w² (:meth:`floor`) 1/(1/N + σ_w²) — exactly N where there is none. The gyro's where its
        bias drifts (``walk`` > 0; :meth:`gyro_mean`): 1/(1/N + (T − t̄)²·var(slope) + σ_l²), the trend line's
        value at the rest's end T (t̄ the means' weighted time), σ_l² the scatter about the line beyond the
        noise (:meth:`_line_floor`)."""
        n = self._sums(sensor)[0]
        if sensor == "gyro" and self.walk > 0.0:
            slope, var_s = self.trend()
            if math.isfinite(var_s) and self.kw >= 3:
                lever = self.dur - self.tw / self.nw
                return 1.0 / (1.0 / n + lever * lever * var_s + self._line_floor(slope))
        w = self.floor(sensor)
        return n if w == 0.0 else 1.0 / (1.0 / n + w)

    def gyro_mean(self) -> Array:
        """The gyro's rest measurement (3,) (raw rad/s): the information-weighted mean of its block means, or,
        where the bias drifts (``walk`` > 0), the trend line at the rest's end, mean + slope·(T − t̄)."""
        mean = self.sw / self.nw
        if self.walk > 0.0 and self.kw >= 3:
            slope, var_s = self.trend()
            if math.isfinite(var_s):
                out: Array = mean + slope * (self.dur - self.tw / self.nw)
                return out
        return mean

    def _line_floor(self, slope: Array) -> float:
        """As :meth:`floor` for the gyro, about its trend line (``slope`` (3,)) rather than its mean: the
        weighted scatter about the line is Σw(m − m̄)² − slope²·Σw(t − t̄)² per axis (the regression's
        residual sum), χ² with 3(k − 2) dof for k blocks of noise alone."""
        k = self.kw
        if k < 4 or self.nw <= 0.0:
            return 0.0
        s_tt = self.ttw - self.tw * self.tw / self.nw
        (qx, qy, qz), (bx, by, bz) = self.qw.tolist(), slope.tolist()
        dof = 3 * (k - 2)
        ratio = (max(qx - bx * bx * s_tt, 0.0) + max(qy - by * by * s_tt, 0.0) + max(qz - bz * bz * s_tt, 0.0)) / dof
        if not ratio - 1.0 > 3.0 * math.sqrt(2.0 / dof):
            return 0.0
        return (ratio - 1.0) * k / self.nw

    def trend(self) -> tuple[Array, float]:
        """The gyro block means' weighted least-squares slope on the rest's time (3,) (rad/s per s, raw) and
        its variance per axis under the means' noise (weights w = L/σ², the rest's information): slope =
        (N Σwtm − Σwt Σwm) / D, variance N / D, D = N Σwt² − (Σwt)². Zero slope and infinite variance before
        two blocks at distinct times."""
        D = self.nw * self.ttw - self.tw * self.tw
        if not D > 0.0:
            return np.zeros(3), math.inf
        return (self.nw * self.smt - self.tw * self.sw) / D, self.nw / D

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
        post = {k: (np.asarray(v[0], float), np.asarray(v[1], float)) for k, v in d["post"].items()}
        a = {k: np.asarray(d[k], float) if k in d else np.zeros(3) for k in _ARRAYS}  # the q sums: since issue 10
        return cls(a["x"], a["P"], a["R_nom"], dict(d["held"]), bool(d["use_mag"]), a["q"], a["sa"], float(d["na"]),
                   a["sm"], float(d["nm"]), a["sw"], float(d["nw"]), float(d["sT"]), int(d["nT"]), post,
                   a["qa"], a["qm"], a["qw"], int(d.get("ka", 0)), int(d.get("km", 0)), int(d.get("kw", 0)),
                   float(d.get("dur", 0.0)), float(d.get("walk", 0.0)), float(d.get("tw", 0.0)),
                   float(d.get("ttw", 0.0)), a["smt"], bool(d.get("skipped", False)))

    def sequential_nis(self, B: Blocks, b: int, n: dict[str, float], use_acc: bool,
                       use_mag: bool, mag_misfit: float = 0.0) -> list[tuple[str, float]]:
        """Block ``b``'s innovation against what the rest so far predicts (``post``): the NIS a per-block
        filter would record, per sensor (so that the NIS windows fill and judge as in motion). ``mag_misfit``
        (raw²): the start calibration's misfit beyond the noise (:meth:`.measurements.MagModel.variance`), which
        the rest's prediction does not absorb (it is in R, not in the state)."""
        L, n_m = int(B.hi[b] - B.lo[b]), int(B.mhi[b] - B.mlo[b])
        out = []
        for s, mean, ok, cnt in (("accel", B.a_mean[b], use_acc, L), ("mag", B.m_mean[b], use_mag, n_m)):
            post = self.post.get(s)
            if post is not None and ok and cnt:
                nu = mean - post[0]
                try:
                    var = n[s] ** 2 / cnt + self.floor(s)  # a block also carries the rest's wander
                    if s == "mag":
                        var += mag_misfit
                    out.append((s, float(nu @ np.linalg.solve(post[1] + np.eye(3) * var, nu))))
                except np.linalg.LinAlgError:
                    pass
        return out
