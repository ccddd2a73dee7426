"""diagnose's candidate for ``mag_current``: a magnetometer offset proportional to the motor current or the
throttle (the interference ArduPilot's compassmot and PX4's CAL_MAG_COMP measure), fitted from a flight log
that carries the current (DataFlash BAT/CURR ``Curr``) or the throttle (CTUN ``ThO``, RCOU ``C3``).

The model, one convention with the simulator (``sim/effects.py`` MagCurrent), the inverse
(:func:`onlinecal.extensions.remove_mag_current`) and the export: in the **raw** magnetometer frame and unit,
before the hard/soft-iron model (Zhang et al. 2014 eq. 1 extended),

    raw_mag = M⁻¹·c + o + k·x(t),        k (3,) raw unit per A (basis current) or at full throttle (throttle)

so the calibrated field changes by δm = M·k·x(t): three regressor columns (one per raw axis j, the raw change
x(t) on axis j mapped by the baseline's matrix; :func:`onlinecal.diagnose.detectors._raw_cols`) on the
magnetometer's residual channels (kinematic m against the gyro, |m| = 1, the dip). x is centred on its
session mean: the constant part is a hard-iron offset, which the baseline's bias nuisance carries.

**Minimum data**: a magnetometer, a current or throttle series, and that series must vary — its 5–95 %
range at least ``MIN_RELATIVE_RANGE`` of its largest value (and 0.1 of full throttle on that basis). A log
that only hovers (throttle constant) cannot separate the interference from the hard iron: the offset k·x is
then a constant that the bias absorbs, and the candidate is reported untestable with the figures. A flight
with its ground rest (disarmed, x ≈ 0) and a flight at varying power separates it.

Where the log has both, both bases are scored as candidates (``mag_current:current``, ``mag_current:throttle``)
and the one with the larger held-out gain is selected: the current is the physical cause (its field), the
throttle a proxy that drifts with battery voltage; a firmware compensates one basis (COMPASS_MOTCT).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..io.base import ImuData
from ..model import Calibration, SensorCalibration

Array = NDArray[np.float64]

BASES = ("current", "throttle")  # preference order
UNIT = {"current": "A", "throttle": "full throttle"}
MIN_RELATIVE_RANGE = 0.2  # 5–95 % range of x over its largest |x|: below it, x is a constant (hover only)
MIN_THROTTLE_RANGE = 0.1  # of full throttle
REQUIREMENT = ("a magnetometer and a current (BAT/CURR) or throttle (CTUN/RCOU) series that varies: 5–95 % "
               f"range ≥ {MIN_RELATIVE_RANGE:.0%} of its largest value (≥ {MIN_THROTTLE_RANGE:g} of full "
               "throttle); a hover-only log cannot separate it from the hard iron")
EVIDENCE = ("the magnetometer's offset moves with the motor current or throttle (raw frame: coeff per A or at full "
            "throttle), beyond what a constant hard iron absorbs")


def series_on_clock(data: ImuData, t: Array, restamped: bool = False) -> dict[str, Array]:
    """The log's ``current``/``throttle`` series (``ImuData.series``) linearly interpolated onto the session clock
    t (N,) s (the IMU clock, re-stamped evenly when ``restamped``: the series' stamps are mapped the same way).
    Held at the end values outside the series' span; a series of fewer than 2 finite samples is left out."""
    out: dict[str, Array] = {}
    for k in BASES:
        if k not in data.series:
            continue
        ts, xs = (np.asarray(v, float) for v in data.series[k])
        ok = np.isfinite(ts) & np.isfinite(xs)
        if ok.sum() < 2:
            continue
        ts, xs = ts[ok], xs[ok]
        order = np.argsort(ts, kind="stable")
        ts, xs = ts[order], xs[order]
        if restamped and data.n_imu > 1:
            ts = np.interp(ts, np.asarray(data.t_imu, float), t)
        out[k] = np.interp(t, ts, xs)
    return out


def _bases(designs: list[Any]) -> list[str]:
    """The bases every design with a magnetometer carries (current first)."""
    with_mag = [d for d in designs if d.mhat is not None]
    return [b for b in BASES if with_mag and all(b in getattr(d.s, "series", {}) for d in with_mag)]


def _x(d: Any, basis: str) -> Array:
    return np.asarray(d.s.series[basis], float)


def _varies(designs: list[Any], b: str) -> str | None:
    """None when the series b varies enough over the magnetometer's samples, else the figures that fall short."""
    x = np.concatenate([_x(d, b)[np.isfinite(d.s.m).all(axis=1)] for d in designs if d.mhat is not None])
    if x.size < 10:
        return f"{x.size} magnetometer samples"
    lo, hi = np.percentile(x, [5, 95])
    top = float(np.max(np.abs(x)))
    rng = float(hi - lo)
    if top == 0 or rng < MIN_RELATIVE_RANGE * top or (b == "throttle" and rng < MIN_THROTTLE_RANGE):
        return (f"{b} 5–95 % range {lo:.3g}–{hi:.3g} {UNIT[b]} (largest {top:.3g}): the interference would be a "
                "constant offset, inseparable from the hard iron")
    return None


def blocked_reason(designs: list[Any]) -> str | None:
    """Why this data cannot test mag_current (None: it can): no magnetometer, no current/throttle series, or no
    series that varies (hover only: the interference is a constant hard iron)."""
    if not any(d.mhat is not None for d in designs):
        return f"mag_current: needs {REQUIREMENT}; this data has no calibrated magnetometer"
    bases = _bases(designs)
    if not bases:
        return (f"mag_current: needs {REQUIREMENT}; this log carries no current or throttle series "
                "(DataFlash BAT/CURR, CTUN/RCOU)")
    why = [w for w in (_varies(designs, b) for b in bases) if w]
    if len(why) == len(bases):
        return f"mag_current: needs {REQUIREMENT}; this data: {'; '.join(why)}"
    return None


KEYS = tuple(f"mag_current:{b}" for b in BASES)


def untestable_after(dropped: tuple[str, ...], scored: dict[str, Any]) -> str | None:
    """After the adequacy check: the candidate reads the field's kinematics against the gyro (``km``); where the
    baseline does not meet that invariant its rows are left out, and what remains (|m| = 1 and the dip, the dip
    unreliable under thrust) cannot tell an interference from a wrong baseline: mag_current is untestable.
    ``scored``: the candidates built (None when mag_current was not among them)."""
    if not any(k in scored for k in KEYS) or not any(c.startswith("km") for c in dropped):
        return None
    return ("mag_current: needs the magnetometer's kinematic invariant (ṁ = m × ω against the gyro) to hold for "
            "the baseline; this baseline does not meet it (see baseline_inadequate), so an interference cannot be "
            "told from the baseline's own error")


def columns(basis: str) -> Callable[[Any, Calibration], Array]:
    """Response rows (n, 3) of the three raw-frame coefficients k_j on ``basis``: raw change (x(t) − x̄) on mag
    axis j, mapped to the calibrated frame by the baseline's matrix (δm = M·e_j·(x − x̄)). Zeros where the
    design has no magnetometer, no series of the basis, or one that does not vary."""
    def f(d: Any, cal: Calibration) -> Array:
        from .detectors import _raw_cols

        if d.mhat is None or basis not in _bases([d]) or _varies([d], basis):
            return np.zeros((d.y.size, 3))
        x = _x(d, basis)
        ok = np.isfinite(d.s.m).all(axis=1)
        xc = x - (float(x[ok].mean()) if ok.any() else 0.0)
        return _raw_cols(d, cal, "mag", np.repeat(xc[:, None], 3, axis=1))
    return f


def params(basis: str) -> Callable[[Array, Array, list[Any], Calibration], dict[str, Any]]:
    """The spec's keys (``basis``, ``coeff`` (3,) raw unit per A or at full throttle) with ``coeff_sigma``, the
    data's x range and the interference at the largest x as a fraction of the field (the calibrated field's norm
    is 1: |M·k|·x_max)."""
    def f(beta: Array, cov: Array, ds: list[Any], cal: Calibration) -> dict[str, Any]:
        sd = np.maximum(np.sqrt(np.maximum(np.diag(cov), 0.0)), robust_sigma(ds, cal, basis))
        sd = np.hypot(sd, SERIES_REL_SIGMA * float(np.linalg.norm(beta)))
        xs = [_x(d, basis) for d in ds if d.mhat is not None and basis in d.s.series]
        x = np.concatenate(xs) if xs else np.zeros(1)
        M = cal.mag.matrix if cal.mag is not None else np.eye(3)
        return {"sensor": "mag", "axis": None, "basis": basis, "coeff": [float(v) for v in beta],
                "coeff_sigma": [float(v) for v in sd], "unit": f"raw magnetometer unit per {UNIT[basis]}",
                "x_range": [float(np.percentile(x, 5)), float(np.percentile(x, 95))],
                "field_fraction_at_max": float(np.linalg.norm(M @ beta) * np.max(np.abs(x)))}
    return f


MAG_ROWS = ("km_x", "km_y", "km_z", "m_norm")
# Model uncertainty of the series itself, added to σ in quadrature as a share of |k|: a log samples the current
# or throttle at ~10 Hz (ArduPilot BAT/CTUN), so where x changes within 0.1 s its timing is unknown and the
# coefficient inherits the misfit. Measured on simulated flights with a 10-Hz series (benchmarks/
# bench_magcurrent.py, 10 flights, 30 coefficients): the errors are 1.1 % of |k| RMS (max 2.7 %; up to 12 % of
# a small component), RMS 2.1 σ (max 7.3 σ) with the noise σ alone; the share is that measured RMS.
SERIES_REL_SIGMA = 0.01
CLUSTER_S = 10.0  # s: time blocks of the cluster-robust covariance (the scoring's fold length)


def robust_sigma(ds: list[Any], cal: Calibration, basis: str) -> Array:
    """Cluster-robust σ (3,) of the coefficients (Liang & Zeger 1986; White 1980 with clusters): the fit on the
    magnetometer's rows (m against the gyro, |m| = 1) with the baseline's nuisance partialled out
    (Frisch–Waugh), rows whitened by their channel's robust σ, the covariance (X'X)⁻¹ (Σ_c X_c'r_c r_c'X_c)
    (X'X)⁻¹ over CLUSTER_S-long time blocks. The model's own covariance assumes independent rows of the
    channel's noise; the information here sits in the few rows where x changes, where a 10-Hz series' timing
    (linear interpolation between its samples) leaves a misfit the noise σ does not cover — the robust form
    widens σ by what the residuals of those rows actually show. Zeros when nothing can be fitted."""
    from .regressors import SUBCHANNELS, nuisance
    from .score import robust_sigma as channel_sigma

    Xs, ys, cls = [], [], []
    ids = [SUBCHANNELS.index(c) for c in MAG_ROWS]
    for d in ds:
        if d.mhat is None or basis not in _bases([d]):
            continue
        rows = np.isin(d.ch, ids)
        if rows.sum() < 20:
            continue
        N = nuisance(d)[rows]
        X = np.nan_to_num(columns(basis)(d, cal)[rows])
        y = d.y[rows]
        r0 = y - N @ np.linalg.lstsq(N, y, rcond=None)[0]
        w = 1.0 / channel_sigma(r0, d.ch[rows], len(SUBCHANNELS))[d.ch[rows]]
        Nw, Xw, yw = N * w[:, None], X * w[:, None], y * w
        P = np.linalg.lstsq(Nw, np.column_stack([Xw, yw]), rcond=None)[0]
        R = np.column_stack([Xw, yw]) - Nw @ P
        Xs.append(R[:, :3])
        ys.append(R[:, 3])
        cls.append(np.floor(d.t[rows] / CLUSTER_S).astype(int) * 1000 + int(d.sid))
    if not Xs:
        return np.zeros(3)
    X, y, c = np.concatenate(Xs), np.concatenate(ys), np.concatenate(cls)
    A = X.T @ X
    if np.linalg.cond(A) > 1e12:
        return np.zeros(3)
    Ai = np.linalg.inv(A)
    r = y - X @ (Ai @ (X.T @ y))
    _, inv = np.unique(c, return_inverse=True)
    S = np.zeros((inv.max() + 1, 3))
    np.add.at(S, inv, X * r[:, None])
    out: Array = np.sqrt(np.maximum(np.diag(Ai @ (S.T @ S) @ Ai), 0.0))
    return out


def candidates() -> list[Any]:
    """The :class:`onlinecal.diagnose.detectors.Candidate` per basis (registered in ``detectors.candidates``):
    keys ``mag_current:current`` and ``mag_current:throttle`` (the finding's sensor is "mag"). Both are scored;
    the one the data prefers wins the forward selection, and the other then adds nothing."""
    from .detectors import Candidate

    return [Candidate("mag_current", b, False, columns(b), params(b)) for b in BASES]


def extension(p: dict[str, Any]) -> dict[str, Any]:
    """The calibration JSON's ``extensions.mag_current`` entry for a finding's parameters."""
    return {"basis": p["basis"], "coeff": list(p["coeff"]), "coeff_sigma": list(p["coeff_sigma"])}


def interference_free_bias(cal: Calibration, logs: list[ImuData], entry: dict[str, Any]) -> Calibration:
    """The calibration with its magnetometer bias moved to the interference-free hard iron: a baseline fitted on
    data with the interference holds o + k·x̄ (x̄ the mean of x over the log's magnetometer samples), so with the
    extension removing k·x the bias must be o_batch − k·x̄ (else replay starts off by k·x̄)."""
    if cal.mag is None:
        return cal
    b, k = entry["basis"], np.asarray(entry["coeff"], float)
    xs = [np.interp(np.asarray(d.t_mag, float), np.asarray(d.series[b][0], float), np.asarray(d.series[b][1], float))
          for d in logs if b in d.series and d.n_mag and np.asarray(d.series[b][0]).size >= 2]
    if not xs:
        return cal
    xbar = float(np.mean(np.concatenate(xs)))
    return cal.replace(mag=SensorCalibration(cal.mag.bias - k * xbar, cal.mag.matrix, cal.mag.sigma))
