"""The augmented-state UKF: attitude on the manifold plus every calibration term of the paper's model.

Filter: the scaled unscented transform of Wan & van der Merwe (2000) (filterpy's ``MerweScaledSigmaPoints``
weights; the transform itself written out as matrix products), with the attitude kept as a nominal rotation
plus a 3-vector error in the state (the error-state / manifold treatment of Crassidis & Markley's USQUE,
2003): sigma points are rotation vectors around the nominal, and after each update the mean error is folded
into the nominal and reset to zero. The state layout is in :mod:`onlinecal.ukf.layout`, the block
propagation in :mod:`onlinecal.ukf.propagate`.

One filter step covers a block of IMU samples (``UKFConfig.block_s``, 0.1 s by default): all sigma points
are propagated through the whole block at once, then one joint update with the block-mean accelerometer
(weighted by how quasi-static the block is, chi-square gated) and the block-mean magnetometer (at its own
sample times). Everything the blocks need from the raw data alone (means, spreads, noise by third
differences, interpolation weights) is computed for all blocks of a ``feed`` at once.

Inside a rest (raw data still for ``rest_blocks`` blocks) the attitude is held and the rest's readings are
one measurement — running means of accel, mag and the gyro's zero rate — applied to the state as it was when
the rest began (:meth:`OnlineCalibrator._rest_step`): a static pose repeated for seconds then says what one
pose says, not more (a per-block update at a drifting linearisation point claimed more: a cold
accelerometer ended 3–7σ off after 30 s at rest).

Where the sigma points cannot see a term they get an allowance: the product δM·δo of gyro matrix and bias
errors (attitude noise, :meth:`OnlineCalibrator._bilinear_var`), and in motion each update is partial
(``update_damping``: R at least a share of the predicted spread), so that a prior far wider than the
measurement is narrowed over a few blocks, relinearised in between (the recursive update of Zanetti 2012).

Sigma points come from a Cholesky factor taken with the attitude and gyro states first: the offsets of
the other states' rows then leave the attitude and gyro terms at the mean, so those sigma points share
the mean's attitude history — computed once instead of once per point (31 attitude integrations per
block instead of 81; exact, not an approximation: any square root gives a valid sigma-point set).

Beyond the paper's 36 terms the state can carry:

* hold offsets (``hold.<sensor>.<axis>``): when a log's values sit on a lattice coarser than the
  sensor's own ADC (a format that re-quantises, e.g. RAW_IMU in mrad/s and milli-gauss), the mean of a
  *held* reading is off by a quantisation error that averaging does not remove; the state carries it
  (gyro: one offset for the zero-rate reading, shared by every rest; accel, mag: one per hold);
* model extensions (``UKFConfig.extra_states``): a bias that follows a regressor, o(t) = o + K·r(t),
  with r = T − T0 (``temperature_bias:gyro``, ``temperature_bias:accel``) or r = f, the specific force
  (``g_sensitivity``, a diagonal gyro g-sensitivity), reported in ``result().extensions``.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints
from numpy.typing import NDArray
from scipy.stats import chi2

from ..io.base import ImuData
from ..model import PARAMS, SENSORS, Calibration, SensorCalibration, decompose
from ..sim.motion import G0
from ..sim.sensors import ACCEL_SPEC, FIELD_GAUSS, GYRO_SPEC, MAG_SPEC
from .layout import (
    ATT,
    AXES,
    DIP,
    N_STATE,
    NAMES,
    SENSOR_SLICE,
    correction,
    field_world,
    index,
    model_pair,
    rodrigues_cm,
    rot_log,
)
from .propagate import interp_weights, propagate_block
from .vehicle import MotionCoverage, VehicleDetector, observability_report, vehicle_accel_var

Array = NDArray[np.float64]

STATE_SCHEMA = "onlinecal.ukf-state/2"
SPECS = {"gyro": GYRO_SPEC, "accel": ACCEL_SPEC, "mag": MAG_SPEC}
# model extensions: name → (sensor whose bias moves, prior σ of K per axis, unit of K)
EXTENSIONS = {
    "temperature_bias:gyro": ("gyro", 1e-3, "rad/s/°C"),
    "temperature_bias:accel": ("accel", 1e-2, "m/s²/°C"),
    "g_sensitivity": ("gyro", 5e-4, "rad/s per m/s²"),
}
MIN_SAMPLES_DETECT = 64  # IMU samples at the start of a log used for the rate and the value lattice


@dataclass
class UKFConfig:
    """Settings of the online calibrator. Defaults come from the sensor specs, not from any one log."""

    block_s: float = 0.1  # IMU samples per filter step, as a duration
    sp_alpha: float = 0.3  # scaled UT spread (Wan & van der Merwe 2000), β = 2 (Gaussian), κ = 0
    sp_beta: float = 2.0
    sp_kappa: float = 0.0
    gravity: float = G0
    init_inflation: float = 2.0  # σ of an ``init`` calibration is multiplied by this for the prior
    # cold-start prior σ (init=None): wide enough for the paper's errors (Table II: 15 % gyro scale,
    # 0.16 rad/s gyro bias); mag bias and scale relative to the raw field magnitude
    cold_sigma: dict[str, dict[str, float]] = field(default_factory=lambda: {
        "gyro": {"bias": 0.2, "scale": 0.2, "alpha": 0.035, "xi": 0.02},
        "accel": {"bias": 0.5, "scale": 0.05, "alpha": 0.035, "xi": 0.02},
        "mag": {"bias": 0.6, "scale": 0.3, "alpha": 0.05, "xi": 0.035},
    })
    # σ of the mag terms after the cold-start sphere fit (bias relative to the field, scale relative)
    mag_fit_sigma: dict[str, float] = field(default_factory=lambda: {
        "bias": 0.06, "scale": 0.15, "alpha": 0.05, "xi": 0.035})
    # σ of the mag terms after the cold-start ellipsoid fit (bias floor relative to the field, scale
    # relative; alpha: the alignment to B is not in the fit; xi: the symmetric fit mixes it with alpha)
    mag_ellipsoid_sigma: dict[str, float] = field(default_factory=lambda: {
        "bias": 0.005, "scale": 0.02, "alpha": 0.05, "xi": 0.01})
    dip_sigma: float = 0.1  # rad, prior of the dip around its first estimate
    att_init_sigma: float = 0.2  # rad, prior of the attitude taken from the first block's accel (and mag)
    yaw_free_sigma: float = 1.0  # rad, σ of the heading while no mag sees it (diffuse; nothing depends on it)
    # random walk on the calibration states per √s: the white-noise density of the sensor times this
    # (bias) and the density relative to full scale times this (dimensionless terms)
    rw_factor: float = 1e-3
    # quasi-static weighting of the accelerometer (adaptive R): σ² += (k·dev)² + (r ω²)², dev the part of
    # ||a|−g| beyond 3σ of what noise and the calibration's own uncertainty explain
    acc_dev_gain: float = 5.0
    acc_lever_m: float = 0.005
    acc_gate_p: float = 0.999  # chi-square gate on the accel NIS (3 dof)
    mag_gate_p: float = 0.9999  # chi-square gate on the mag NIS: soft (R inflated), never dropped
    nis_window: int = 100  # updates per NIS window
    nis_band_p: float = 0.001  # two-sided probability outside the window band
    divergence_factor: float = 5.0  # window mean NIS > factor × upper band ...
    divergence_windows: int = 3  # ... for this many windows in a row → divergence
    mag_fit_min_samples: int = 100
    mag_fit_min_spread: float = 0.1  # smallest eigenvalue of the scatter of unit field directions (1/3: a sphere)
    # smallest eigenvalue of the *covariance* (centred) of the unit field directions: a flight's yaw turns
    # and ±25° tilts sweep a band (0.001–0.009 over 10 min, multirotor and fixed-wing profiles) on which the
    # centre along the band's axis and that axis' scale trade off against the gyro's x/y scale (a cold fit
    # there ended 30–45σ off); the paper session reaches 0.058 within 60 s, 0.17 by 120 s
    mag_fit_min_cover: float = 0.03
    mag_fit_max_centre_sigma: float = 0.01  # LS σ of the sphere's centre, relative to its radius
    mag_buffer_max: int = 2000
    max_gap_s: float = 0.5  # IMU gap that restarts the attitude
    rest_k: float = 2.0  # rest: per-axis spread below k σ, mean change below 2k σ √(2/L)
    rest_blocks: int = 3  # consecutive still blocks before the zero-rate update applies
    rest_rate_sigma: float = 5e-5  # rad/s, allowance for micro-motion in a rest (zero-rate update)
    trace_every_s: float = 1.0
    trace_max_rows: int = 100_000
    max_events: int = 1000  # events kept (oldest dropped beyond); the count of all is in nis_summary
    # whose alpha defines B (held at its prior as a consider state); "auto": the gyro when ``init`` is a
    # batch result whose gyro came from its rotation phases (the batch's own definition of B), else the
    # init sensor with the tightest alpha σ, else the accelerometer; None: all free
    gauge_sensor: str | None = "auto"
    # which terms of the gauge sensor are held: "alpha", "alpha+xi", or "auto" ("alpha+xi" for a
    # phase-based batch gyro — the phases fix all three axes of B in the gyro, not only a rotation)
    gauge_terms: str = "auto"
    excited_ratio: float = 0.5  # posterior σ / prior σ below this: "excited"
    quant_hold: bool = True  # model the mean error of held readings on a re-quantised lattice
    # measured noise (third differences of the raw samples) above this multiple of the spec's variance
    # (smoothed over noise_tau_blocks blocks) → the sensor's noise is scaled up and an event raised;
    # back below noise_low → back to the spec
    noise_high: float = 4.0
    noise_low: float = 2.0
    noise_tau_blocks: float = 10.0
    # saturation: a reading repeated rail_run times in a row, of magnitude at least rail_min (rad/s,
    # m/s²), is the ADC rail; from then on readings at the rail are clipped
    rail_min: dict[str, float] = field(default_factory=lambda: {"gyro": 1.0, "accel": 14.7})
    rail_run: int = 40
    extra_states: tuple[str, ...] = ()  # model extensions, keys of EXTENSIONS
    # partial update in motion: each measurement's R is at least this share of its predicted spread HPHᵀ,
    # so that one block removes at most 1/(1 + share) of the prior's variance along it (4: a fifth) and
    # the rest comes from the next blocks, linearised at the improved estimate (0: off). Costs nothing once
    # converged (HPHᵀ ≪ R): the 20-seed batch-started figures are the same at 1 and 4. On a cold start it
    # keeps the first large turns from over-narrowing the prior: with the mag from the batch, every gyro
    # and accel bias and scale ends within 3σ after 60 s of motion on 9/12 seeds at 1 (half per block),
    # 12/12 at 4 and at 8, and 12/12 on the 12 further seeds not used to choose it (benchmarks/ukf_stats.py
    # --cold 90 --set update_damping=…)
    update_damping: float = 4.0
    # a vehicle's own acceleration (onlinecal.ukf.vehicle): "auto" detects it from the data (vibration or a
    # specific-force norm away from g), "vehicle" assumes it from the start, "platform" never. Once on,
    # every accelerometer update outside a rest carries an unknown acceleration of σ vehicle_accel_sigma
    # per axis correlated over vehicle_accel_tau s (a multirotor's ≤ 3 m/s² legs, a fixed-wing's turns,
    # g·tan(30°) ≈ 5.7 m/s² for up to 30 s), and rests are judged with the spec noise (vibration cannot pass)
    vehicle: str = "auto"
    vehicle_accel_sigma: float = 3.0
    vehicle_accel_tau: float = 30.0
    vehicle_vibration_sigma: float = 0.3
    vehicle_dev_min: float = 0.5

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["extra_states"] = list(self.extra_states)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> UKFConfig:
        known = {f.name for f in fields(cls)}
        d = {k: v for k, v in d.items() if k in known}  # settings dropped since a state was saved
        if "extra_states" in d:
            d["extra_states"] = tuple(d["extra_states"])
        return cls(**d)


def _given_sigma(cal: SensorCalibration) -> Array:
    """The 12 σ (bias, scale, alpha, xi) a calibration carries, NaN where it has none."""
    out = []
    for p in PARAMS:
        v = np.asarray(cal.sigma.get(p, np.full(3, np.nan)), float).reshape(-1)
        out.append(v if v.shape == (3,) else np.full(3, np.nan))
    sig = np.concatenate(out)
    return np.where(np.isfinite(sig) & (sig > 0), sig, np.nan)


def value_lattice(v: Array) -> float:
    """The quantum q of a sensor's values when every value is an integer multiple of it, else 0.

    v (N, 3) raw readings. q is the smallest step between distinct values on any axis; it counts only
    if all values are multiples of it to 1e-6 (floats from integer counts times a unit factor are).
    """
    v = v[np.all(np.isfinite(v), axis=1)]
    if v.shape[0] < 8:
        return 0.0
    steps = np.concatenate([np.diff(np.unique(v[:, k])) for k in range(3)])
    steps = steps[steps > 0]
    if not steps.size:
        return 0.0
    q = float(steps.min())
    if q <= 1e-9 * max(float(np.abs(v).max()), 1e-300):
        return 0.0
    k = v / q
    return q if float(np.max(np.abs(k - np.round(k)))) < 1e-6 else 0.0


def hold_sigma(q: float, sigma_n: float) -> float:
    """σ of the error of the mean of a held reading re-quantised to q (no averaging removes it).

    A value already quantised by the sensor's ADC and then rounded to a coarser format lattice q is off
    on average by a function of where it sits on the two lattices; white noise σ_n dithers it only
    partly. Bound used: q/√12 · exp(−σ_n/q) (q/√12: no dither). Simulated for sensor lattices of
    0.24–0.53 q and σ_n = 0.3–1.5 q, the rms error stays below this bound (e.g. 0.13 q at σ_n = q/2
    against 0.18 q; ``tests/test_ukf.py::test_hold_sigma_bounds_double_quantisation``).
    """
    if q <= 0:
        return 0.0
    return q / math.sqrt(12.0) * math.exp(-sigma_n / q)


def third_diff_var(v: Array, t: Array, seg: Array, n_seg: int, min_windows: int = 3) -> Array:
    """Per-segment white-noise variance from third differences: median |Δ³v|² / (3·20·0.789), (n_seg,).

    v (N, 3) samples at times t (N,) s, seg (N,) the segment (filter block) of each sample, ascending.
    Δ³ of white noise on a regular grid has variance 20σ² per axis; a smooth motion's own third
    difference (rate‴·Δt³) is far below it at IMU rates. The median makes it robust to a jerk;
    0.789 = median of χ²(3) / 3. Only windows of 4 samples inside one segment whose 3 intervals agree
    within 1.5× count: across a dropped sample the difference is not the white-noise Δ³ (the motion
    over the missing interval enters it), so a log with gaps would read as noisy. NaN where a segment
    has fewer than ``min_windows`` such windows.
    """
    out = np.full(n_seg, math.nan)
    if v.shape[0] < 4:
        return out
    d3 = (v[3:] - v[:-3]) - 3 * (v[2:-1] - v[1:-2])
    s = np.einsum("ij,ij->i", d3, d3)
    h = np.diff(t)
    h3 = np.stack([h[:-2], h[1:-1], h[2:]])
    ok = (seg[3:] == seg[:-3]) & (h3.max(axis=0) <= 1.5 * h3.min(axis=0))
    sv, sg = s[ok], seg[3:][ok]
    cnt = np.bincount(sg, minlength=n_seg)
    good = cnt >= min_windows
    if not good.any():
        return out
    vals = sv[np.lexsort((sv, sg))]  # grouped by segment (ascending), sorted within
    off = np.concatenate([[0], np.cumsum(cnt)[:-1]])[good]
    c = cnt[good]
    out[good] = 0.5 * (vals[off + (c - 1) // 2] + vals[off + c // 2]) / (3 * 20.0 * 0.7888)
    return out


def _seg_mean_std(v: Array, lo: Array, cnt: Array) -> tuple[Array, Array]:
    """Mean and standard deviation (ddof 0) per axis of the segments [lo, lo + cnt) of v (N, 3), which
    follow each other without holes; (n_seg, 3) each, NaN for empty segments. Sums per segment
    (np.add.reduceat), so a segment's figures do not depend on where the buffer it sits in starts."""
    ns = lo.shape[0]
    mean = np.full((ns, 3), math.nan)
    std = np.full((ns, 3), math.nan)
    ne = cnt > 0
    if not ne.any():
        return mean, std
    c_n = cnt[ne]
    s0 = int(lo[ne][0])
    vv = v[s0 : s0 + int(c_n.sum())]
    starts = np.concatenate([[0], np.cumsum(c_n)[:-1]])
    m = np.add.reduceat(vv, starts, axis=0) / c_n[:, None]
    dv = vv - np.repeat(m, c_n, axis=0)
    mean[ne] = m
    std[ne] = np.sqrt(np.add.reduceat(dv * dv, starts, axis=0) / c_n[:, None])
    return mean, std


@dataclass
class _Blocks:
    """Raw-data figures of a run of consecutive filter blocks, computed for all of them at once (so the
    per-block work of the filter is only the filter): block b holds IMU samples [lo[b], hi[b]) and mag
    samples [mlo[b], mhi[b]) of the buffers; w_ext (N + 1, 3) the raw rates with the last one filtered
    before them, dt (N,) the length of the interval ending at each IMU sample; per block the means and
    spreads (n_b, 3), the third-difference noise variances (n_b,), the jerk term Σ|Δ²ω·Δt/4|² and its count, the largest
    |reading| per axis; per mag sample its interpolation index into [t_prev, t] and fraction."""

    lo: Array
    hi: Array
    mlo: Array
    mhi: Array
    w_ext: Array
    dt: Array
    w_mean: Array
    w_std: Array
    a_mean: Array
    a_std: Array
    m_mean: Array
    m_std: Array
    var3: dict[str, Array]
    jerk: Array
    jerk_n: Array
    w_absmax: Array
    a_absmax: Array
    m_j: Array
    m_frac: Array


_IU = np.triu_indices(3)


def ellipsoid_gn(x: Array, o0: Array, M0: Array, max_iter: int = 40,
                 reject_sigma: float = 5.0) -> tuple[Array, Array, Array, float]:
    """Geometric ellipsoid fit ‖M (x − o)‖ = 1 (Zhang et al. eq. 17) by Levenberg–Marquardt with the
    analytic Jacobian; o (3,) and a symmetric M (its 6 upper-triangle entries) as the batch fit has them.

    r_i = ‖y_i‖ − 1 with y_i = M d_i, d_i = x_i − o, n_i = y_i/‖y_i‖: ∂r_i/∂o = −M n_i and
    ∂r_i/∂M_jk = n_j d_k + n_k d_j (j < k), n_j d_j (j = k). x (N, 3) raw samples; o0, M0 the start (a
    sphere fit). One outlier rejection at ``reject_sigma`` × MAD, then a refit. Returns (o, M, cov (9, 9)
    of (o, upper triangle of M) from the Gauss–Newton normal matrix and the residual variance, residual
    rms). A fixed iteration budget keeps the cost bounded (a few ms) where the data do not carry an
    ellipsoid; the caller rejects such fits by their covariance.
    """
    jj, kk = _IU
    off = (jj != kk).astype(float)

    def resid_jac(p: Array, pts: Array) -> tuple[Array, Array]:
        o = p[:3]
        M = np.zeros((3, 3))
        M[_IU] = p[3:]
        M = M + np.triu(M, 1).T
        d = pts - o
        y = d @ M
        ny = np.sqrt(np.einsum("ij,ij->i", y, y))
        nv = y / ny[:, None]
        J = np.empty((pts.shape[0], 9))
        J[:, :3] = -(nv @ M)
        J[:, 3:] = nv[:, jj] * d[:, kk] + off * nv[:, kk] * d[:, jj]
        return ny - 1.0, J

    def solve(p: Array, pts: Array) -> Array:
        lam = 1e-3
        r, J = resid_jac(p, pts)
        cost = float(r @ r)
        for _ in range(max_iter):
            A = J.T @ J
            g = J.T @ r
            try:
                step = np.linalg.solve(A + lam * np.diag(np.diag(A)), -g)
            except np.linalg.LinAlgError:
                break
            p_new = p + step
            r_new, J_new = resid_jac(p_new, pts)
            c_new = float(r_new @ r_new)
            if np.isfinite(c_new) and c_new < cost:
                done = cost - c_new < 1e-12 * cost
                p, r, J, cost = p_new, r_new, J_new, c_new
                lam = max(lam / 10.0, 1e-12)
                if done:
                    break
            else:
                lam *= 10.0
                if lam > 1e8:
                    break
        return p

    p = solve(np.concatenate([o0, M0[_IU]]), x)
    keep = np.ones(x.shape[0], bool)
    if x.shape[0] >= 36:
        r, _ = resid_jac(p, x)
        mad = 1.4826 * float(np.median(np.abs(r - np.median(r))))
        keep = np.abs(r) <= max(reject_sigma * mad, 1e-12)
        if keep.sum() >= 9 and not keep.all():
            p = solve(p, x[keep])
    r, J = resid_jac(p, x[keep])
    s2 = float(r @ r) / max(1, int(keep.sum()) - 9)
    try:
        cov = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        cov = np.full((9, 9), np.inf)
    M = np.zeros((3, 3))
    M[_IU] = p[3:]
    return p[:3], M + np.triu(M, 1).T, cov, math.sqrt(float(np.mean(r * r)))


class OnlineCalibrator:
    """Streaming augmented-state UKF (see module docstring).

    ``init``: a Calibration to start from (its σ times ``config.init_inflation`` is the prior; missing
    sensors or σ fall back to the cold prior), or None for a cold start: bias 0, scale 1, angles 0 with
    the wide ``config.cold_sigma``. The magnetometer's cold start is a sphere fit (centre = hard iron,
    1/radius = scale) on buffered raw samples once they span enough directions; until then the mag is
    not used and the filter's yaw is left free.

    ``feed(block)`` takes any block size (a carry-over buffer keeps incomplete filter blocks; memory is
    constant in the log length), ``result()`` gives the current Calibration with σ.
    """

    def __init__(self, init: Calibration | None = None, config: UKFConfig | None = None) -> None:
        self.config = config or UKFConfig()
        self.init = init
        c = self.config
        for e in c.extra_states:
            if e not in EXTENSIONS:
                raise ValueError(f"unknown extra state {e!r} (known: {', '.join(EXTENSIONS)})")
        self.events: list[dict[str, Any]] = []
        self._n_events = 0
        self._gates = {"accel": float(chi2.ppf(c.acc_gate_p, 3)), "mag": float(chi2.ppf(c.mag_gate_p, 3))}
        self._trace: deque[dict[str, float]] = deque(maxlen=c.trace_max_rows)
        self._rate: float | None = None
        self._L = 0
        self._clear_pending()
        self._t_last: float | None = None
        self._w_last = np.zeros(3)
        self._T_last = math.nan
        self._att_ok = False
        self._next_trace = -math.inf
        self._n_imu = 0
        self._n_blocks = 0
        self._nis: dict[str, dict[str, Any]] = {}
        # per log: value lattice of each sensor (0: none) and whether it is a re-quantisation
        self._q: dict[str, float] | None = None
        self._q_mag_buf: list[list[float]] = []
        self._noise_ratio = {s: 1.0 for s in SENSORS}
        self._noise_high = {s: False for s in SENSORS}
        self._rail: dict[str, list[float]] = {}
        self._run: dict[str, list[tuple[float, int]]] = {}
        self._clip_on = {s: False for s in SENSORS}
        self._T0: float | None = None
        self._vehicle = VehicleDetector(c.vehicle_vibration_sigma, c.vehicle_dev_min)
        if c.vehicle == "vehicle":
            self._vehicle.active, self._vehicle.since, self._vehicle.reason = True, 0.0, "configured"
        self._coverage = MotionCoverage()
        self._reset_calibration()

    # ------------------------------------------------------------------------------------------
    # state layout
    def _build_layout(self, holds: tuple[str, ...] = ()) -> None:
        """Names of the state (the 40 of :mod:`.layout`, then extensions, then hold offsets), the slices
        of the extras, the sigma-point weights and the Cholesky order (attitude-relevant states first)."""
        c = self.config
        names = list(NAMES)
        self._ext_slice: dict[str, slice] = {}
        for e in c.extra_states:
            s0 = len(names)
            names += [f"ext.{e}.{a}" for a in AXES]
            self._ext_slice[e] = slice(s0, s0 + 3)
        self._hold_slice: dict[str, slice] = {}
        for s in holds:
            s0 = len(names)
            names += [f"hold.{s}.{a}" for a in AXES]
            self._hold_slice[s] = slice(s0, s0 + 3)
        self.names = names
        n = len(names)
        self.points = MerweScaledSigmaPoints(n, c.sp_alpha, c.sp_beta, c.sp_kappa)
        self._Wm, self._Wc = self.points.Wm, self.points.Wc
        dyn = np.zeros(n, bool)
        dyn[ATT] = True
        dyn[SENSOR_SLICE["gyro"]] = True
        for e, sl in self._ext_slice.items():
            if EXTENSIONS[e][0] == "gyro":
                dyn[sl] = True
        if "gyro" in self._hold_slice:
            dyn[self._hold_slice["gyro"]] = True  # a held gyro reading is integrated with its offset
        self._perm = np.concatenate([np.flatnonzero(dyn), np.flatnonzero(~dyn)])
        self._perm_id = bool(np.array_equal(self._perm, np.arange(n)))
        nd = int(dyn.sum())
        self._dyn_pts = np.concatenate([[0], np.arange(1, nd + 1), np.arange(n + 1, n + nd + 1)])
        self._consider = self._consider_mask()
        self._q_unit: dict[str, Array] = {}

    @property
    def n(self) -> int:
        return len(self.names)

    def _add_hold(self, sensor: str, sigma: float) -> None:
        """Append the 3 hold-offset states of ``sensor`` (0 ± sigma), or reset them if present."""
        if sensor not in self._hold_slice:
            holds = tuple(self._hold_slice) + (sensor,)
            n0 = self.n
            self._build_layout(holds)
            n1 = self.n
            x = np.zeros(n1)
            x[:n0] = self.x
            P = np.zeros((n1, n1))
            P[:n0, :n0] = self.P
            self.x, self.P = x, P
            self.prior_x = np.concatenate([self.prior_x, np.zeros(n1 - n0)])
            self.prior_sigma = np.concatenate([self.prior_sigma, np.zeros(n1 - n0)])
        self._hold_sigma[sensor] = sigma
        self._reset_hold(sensor)

    def _reset_hold(self, sensor: str) -> None:
        sl = self._hold_slice[sensor]
        self.x[sl] = 0.0
        self.P[sl, :] = 0.0
        self.P[:, sl] = 0.0
        self.P[sl, sl] = np.eye(3) * self._hold_sigma[sensor] ** 2
        self.prior_sigma[sl] = self._hold_sigma[sensor]

    def _consider_mask(self) -> Array:
        """States held at their prior (Schmidt–Kalman consider states): the gauge sensor's alpha (and xi).

        A common rotation of the body frame (every sensor's T_R turned by the same Q, the attitude by Qᵀ)
        leaves every measurement unchanged, so nothing in the data fixes it: B is defined by the prior.
        Left free, a filter linearised at moving estimates gains spurious information along it and drifts
        (seen in cold starts: all three alphas off by the same degrees at 40σ). Holding one sensor's
        alpha at its prior (with its prior σ, as a consider parameter) pins B to that sensor's frame as
        given by ``init`` (the batch's B) or to the sensor itself on a cold start. The batch defines B by
        the platform's three rotation axes as the gyro measured them (its phases): that fixes the gyro's
        alpha *and* xi in B, so for such an init both are held.
        """
        mask = np.zeros(len(self.names), bool)
        g = self.gauge
        if g:
            for p in self._gauge_terms():
                mask[index(g, p)] = True
        return mask

    def _batch_gyro_from_phases(self) -> bool:
        try:
            m = self.init.meta["batch"]["steps"]["gyro"]["figures"]["method"]  # type: ignore[union-attr]
        except (AttributeError, KeyError, TypeError):
            return False
        return isinstance(m, str) and m.startswith("phases") and self.init.gyro is not None  # type: ignore[union-attr]

    def _gauge_terms(self) -> tuple[str, ...]:
        t = self.config.gauge_terms
        if t == "auto":
            return ("alpha", "xi") if self.gauge == "gyro" and self._batch_gyro_from_phases() else ("alpha",)
        return tuple(t.split("+"))

    @property
    def gauge(self) -> str | None:
        """The sensor whose alpha defines B: ``config.gauge_sensor``; for "auto" the gyro of a batch init
        whose gyro came from its phases (the batch's B), else the init sensor with the tightest alpha σ,
        else the accelerometer."""
        g = self.config.gauge_sensor
        if g != "auto":
            return g
        if self._batch_gyro_from_phases():
            return "gyro"
        best, best_s = "accel", math.inf
        if self.init is not None:
            for s in SENSORS:
                cal = self.init.sensor(s)
                if cal is None or "alpha" not in cal.sigma:
                    continue
                v = float(np.mean(np.asarray(cal.sigma["alpha"], float)))
                if np.isfinite(v) and v < best_s:
                    best, best_s = s, v
        return best

    # ------------------------------------------------------------------------------------------
    # priors
    def _prior(self) -> tuple[Array, Array]:
        """Prior mean and σ of the 40 base states from ``init`` (or cold). Attitude entries are filled later."""
        c = self.config
        x = np.zeros(N_STATE)
        sig = np.zeros(N_STATE)
        for s in SENSORS:
            cal = self.init.sensor(s) if self.init is not None else None
            sl = SENSOR_SLICE[s]
            cold = c.cold_sigma[s]
            if cal is None:
                x[sl] = np.concatenate([np.zeros(3), np.ones(3), np.zeros(6)])
                sig[sl] = np.repeat([cold[p] for p in PARAMS], 3)
            else:
                x[sl] = np.concatenate([cal.bias, cal.scale, cal.alpha, cal.xi])
                given = _given_sigma(cal)
                cold_v = np.repeat([cold[p] for p in PARAMS], 3)
                if s == "mag":
                    cold_v[:3] *= float(1.0 / np.mean(cal.scale))  # mag bias σ relative to the raw field
                    cold_v[3:6] *= float(np.mean(cal.scale))
                infl = np.full(12, c.init_inflation)
                if s == self.gauge:
                    # consider states are never updated from the data: no double use to allow for
                    for p in self._gauge_terms():
                        infl[PARAMS.index(p) * 3 : PARAMS.index(p) * 3 + 3] = 1.0
                sig[sl] = np.where(np.isfinite(given), given * infl, cold_v)
        x[DIP] = math.radians(60.0)
        sig[DIP] = math.radians(30.0)
        return x, sig

    def _reset_calibration(self) -> None:
        """(Re)start every calibration state from the prior; the attitude restarts on the next block."""
        self._build_layout()
        self._hold_sigma: dict[str, float] = {}
        x0, sig0 = self._prior()
        n = self.n
        self.x = np.zeros(n)
        sig = np.zeros(n)
        self.x[:N_STATE], sig[:N_STATE] = x0, sig0
        for e, sl in self._ext_slice.items():
            sig[sl] = EXTENSIONS[e][1]
        self.prior_sigma = sig.copy()
        self.prior_x = self.x.copy()
        sig[ATT] = 0.1
        self.P = np.diag(sig**2)
        self.R_nom = np.eye(3)
        self.mag_enabled = self.init is not None and self.init.mag is not None
        self.dip_known = False
        self._mag_buf: list[list[float]] = []
        self._mag_buf_next = -math.inf
        self._mag_fit_next = -math.inf
        self._mag_scale_known = self.mag_enabled
        self._att_ok = False
        self._yaw_free = True
        self._align_yaw_next = False
        self._prev_means: tuple[Any, Any, Any] | None = None
        self._rest_count = 0
        self._still = False
        self._rest_acc: dict[str, Any] | None = None  # the running rest (:meth:`_rest_step`)
        self._hold_new = False
        self._held = {"accel": False, "mag": False}
        self._nis = {s: {"sum": 0.0, "n": 0, "windows": [], "bad_run": 0, "rejected": 0, "updates": 0}
                     for s in ("accel", "mag")}
        if self._q is not None:
            self._apply_lattice(tuple(k for k in SENSORS if k in self._q))

    # ------------------------------------------------------------------------------------------
    # noise
    def _spec_noise(self) -> dict[str, float]:
        """Per-sample σ of the raw readings from the specs (white noise + the sensor's own quantisation)."""
        r = self._rate or 100.0
        s0 = SENSOR_SLICE["mag"].start + 3
        key = (r, float(self.x[s0] + self.x[s0 + 1] + self.x[s0 + 2]))
        if getattr(self, "_spec_key", None) == key:
            return dict(self._spec_cache)
        self._spec_key = key
        self._spec_cache = {
            "gyro": math.hypot(GYRO_SPEC.sigma(r), GYRO_SPEC.lsb / math.sqrt(12)),
            "accel": math.hypot(ACCEL_SPEC.sigma(r), ACCEL_SPEC.lsb / math.sqrt(12)),
            # relative to the field, then in the raw unit (the reader may deliver gauss or milli-gauss)
            "mag": math.hypot(MAG_SPEC.sigma(50.0), MAG_SPEC.lsb / math.sqrt(12)) / FIELD_GAUSS * self._mag_unit(),
        }
        return dict(self._spec_cache)

    def _noise(self, spec: dict[str, float] | None = None) -> dict[str, float]:
        """Per-sample σ used by the filter: the spec's (``spec``, :meth:`_spec_noise`), the format's
        re-quantisation (q²/12, white part) and, where the measured noise is far above the spec, scaled to
        the measured level."""
        n = dict(spec) if spec is not None else self._spec_noise()
        q = self._q or {}
        for s in SENSORS:
            if q.get(s + "_requant"):
                n[s] = math.hypot(n[s], q[s] / math.sqrt(12.0))
            if self._noise_high[s]:
                n[s] *= math.sqrt(self._noise_ratio[s])
        return n

    def _mag_unit(self) -> float:
        """Raw magnitude of the unit field: 1 / mean mag scale."""
        return float(1.0 / np.mean(self.x[SENSOR_SLICE["mag"]][3:6]))

    def _process_noise(self, dt: float, sigma_gyr: float) -> Array:
        """Diagonal of Q for one block lasting ``dt`` s; ``sigma_gyr`` the gyro's per-sample σ (rad/s).

        Attitude: angle random walk of the gyro, σ_gyr/r per sample for the r·dt samples the block spans
        (rad², every axis; by its duration, so that dropped samples do not shrink it).
        Calibration: random walk, density × ``rw_factor`` per √s (bias), density/full-scale × ``rw_factor``
        (dimensionless terms) — a slow drift allowance set from the specs, not tuned per log. Extensions:
        their prior σ × ``rw_factor`` per √s. Hold offsets: none (a held value's error is constant).
        """
        r = self._rate or 100.0
        q = self._cal_rw() * dt
        q[ATT] = dt * r * (sigma_gyr / r) ** 2
        return q

    def _bilinear_var(self) -> Array:
        """Variance (rad²/s², per body axis) of the rate error the unscented transform leaves out: the
        product δM·δo of the gyro's matrix and bias errors in ω = M (w − o) (eq. 1). Its sigma points move
        M or o, never both, so the product — second order, but 0.04 rad/s for a cold start's 20 % × 0.2
        rad/s — is invisible to them; unmodelled, the attitude drift it causes reads as information on the
        scale (a bilinear term linearised at a wrong bias). Σ_j σ²(M_ij) σ²(o_j), with σ(M_ii) the scale's
        σ and σ(M_ij) that of the axis angles; vanishes once the bias is known (a rest)."""
        sig = np.sqrt(np.diag(self.P)[SENSOR_SLICE["gyro"]])
        s_o, s_s = sig[0:3], sig[3:6]
        s_ang = np.maximum(sig[6:9], sig[9:12]).max()
        v_o = s_o * s_o
        return s_s * s_s * v_o + s_ang**2 * (v_o.sum() - v_o)

    def _cal_rw(self) -> Array:
        """Random-walk variance per second of every state (attitude entries 0)."""
        s0 = SENSOR_SLICE["mag"].start + 3
        key = (self.n, round(3.0 / (self.x[s0] + self.x[s0 + 1] + self.x[s0 + 2]), 6))  # the mag unit
        if getattr(self, "_rw_key", None) == key:
            return self._rw_cache
        c = self.config
        q = np.zeros(self.n)
        for s, spec in SPECS.items():
            dens = spec.density if spec.density > 0 else spec.sigma(50.0) / math.sqrt(25.0)
            unit = self._mag_unit() / FIELD_GAUSS if s == "mag" else 1.0
            sl = SENSOR_SLICE[s]
            q[sl.start : sl.start + 3] = (dens * unit * c.rw_factor) ** 2
            q[sl.start + 3 : sl.stop] = (dens / spec.full_scale * c.rw_factor) ** 2
        q[DIP] = (1e-6) ** 2
        for e, sl in self._ext_slice.items():
            q[sl] = (EXTENSIONS[e][1] * c.rw_factor) ** 2
        self._rw_key, self._rw_cache = key, q
        return q

    def _update_noise_level(self, sensor: str, var: float, t: float, spec: float) -> None:
        """Measured per-sample noise ``var`` (third differences of the block, :func:`third_diff_var`)
        against the spec, smoothed over ``noise_tau_blocks``; raises the sensor's noise and says so when
        it is far above, and returns to the spec when it comes back. NaN (too few regular samples): no
        change."""
        if not math.isfinite(var):
            return
        c = self.config
        q = self._q or {}
        if q.get(sensor + "_requant"):
            spec = math.hypot(spec, q[sensor] / math.sqrt(12.0))
        a = 1.0 / c.noise_tau_blocks
        r = (1 - a) * self._noise_ratio[sensor] + a * var / spec**2
        self._noise_ratio[sensor] = r
        if not self._noise_high[sensor] and r > c.noise_high:
            self._noise_high[sensor] = True
            self._event("noise_high", f"{sensor} noise {math.sqrt(r):.2g}× its spec: its weight lowered", t)
        elif self._noise_high[sensor] and r < c.noise_low:
            self._noise_high[sensor] = False
            self._event("noise_normal", f"{sensor} noise back to {math.sqrt(r):.2g}× its spec", t)

    # ------------------------------------------------------------------------------------------
    # quantisation
    def _detect_lattice(self, w: Array, a: Array, m: Array) -> None:
        """Value lattice of gyro, accel (and mag, once it has samples) at the start of a log."""
        self._q = {"gyro": value_lattice(w), "accel": value_lattice(a)}
        self._q_mag_buf = m.tolist()
        if m.shape[0] >= 16:
            self._q["mag"] = value_lattice(m)
        self._apply_lattice(tuple(s for s in SENSORS if s in self._q))
        if "mag" in self._q:
            self._q_mag_buf = []

    def _apply_lattice(self, sensors: tuple[str, ...]) -> None:
        """A lattice coarser than the sensor's own ADC (spec lsb) is a re-quantisation by the format:
        its q²/12 joins the white noise and, with ``quant_hold``, the held-reading offsets join the state."""
        q = self._q
        assert q is not None
        r = self._rate or 100.0
        unit = self._mag_unit_raw()
        own = {"gyro": GYRO_SPEC.lsb, "accel": ACCEL_SPEC.lsb, "mag": MAG_SPEC.lsb / FIELD_GAUSS * unit}
        white = {"gyro": GYRO_SPEC.sigma(r), "accel": ACCEL_SPEC.sigma(r),
                 "mag": MAG_SPEC.sigma(50.0) / FIELD_GAUSS * unit}
        for s in sensors:
            req = q[s] > 1.5 * own[s]
            q[s + "_requant"] = bool(req)
            if req and self.config.quant_hold:
                first = s not in self._hold_slice
                hs = hold_sigma(q[s], white[s])
                self._add_hold(s, hs)
                if first and self.init is not None and self.init.sensor(s) is not None:
                    # a bias found from held readings through this format carries the same hold error,
                    # which the init's σ (fitted as if the rounding averaged out) does not include
                    b = index(s, "bias")
                    self.P[b, b] += np.eye(3) * hs**2
                    self.prior_sigma[b] = np.hypot(self.prior_sigma[b], hs)

    def _mag_unit_raw(self) -> float:
        """Raw field magnitude: from the mag scale once known, else the first raw samples' norm."""
        if self.mag_enabled:
            return self._mag_unit()
        if self._q_mag_buf:
            return float(np.median(np.linalg.norm(np.asarray(self._q_mag_buf), axis=1)))
        return 1.0

    # ------------------------------------------------------------------------------------------
    # streaming
    def feed(self, block: ImuData) -> None:
        """Consume a block of any size. IMU samples beyond the last full filter block wait in a buffer."""
        if block.n_imu:
            self._pend_t = np.concatenate([self._pend_t, block.t_imu])
            self._pend_w = np.concatenate([self._pend_w, block.gyro.reshape(-1, 3)])
            self._pend_a = np.concatenate([self._pend_a, block.acc.reshape(-1, 3)])
            self._pend_T = np.concatenate([self._pend_T, np.asarray(block.temp, float).reshape(-1)])
        if block.n_mag:
            self._pend_tm = np.concatenate([self._pend_tm, block.t_mag])
            self._pend_m = np.concatenate([self._pend_m, block.mag.reshape(-1, 3)])
        self._process()

    def _clear_pending(self) -> None:
        """Empty the buffers of samples fed but not yet cut into filter blocks."""
        self._pend_t = np.zeros(0)
        self._pend_w = np.zeros((0, 3))
        self._pend_a = np.zeros((0, 3))
        self._pend_T = np.zeros(0)
        self._pend_tm = np.zeros(0)
        self._pend_m = np.zeros((0, 3))

    def new_log(self) -> None:
        """The next samples start a new log: keep the calibration, restart the attitude and clock."""
        self.flush()
        self._clear_pending()
        self._t_last = None
        self._att_ok = False
        self._q = None  # a new log may come in another format: its lattice is detected again
        self._prev_means = None
        self._rest_count = 0

    def flush(self) -> None:
        """Process the IMU samples still buffered as one (short) block; a running rest is closed."""
        self._process(final=True)
        self._end_rest()

    def _process(self, final: bool = False) -> None:
        t, w, a, T = self._pend_t, self._pend_w, self._pend_a, self._pend_T
        if self._q is None:
            # the rate and the value lattice come from the log's first samples (a fixed count, so the
            # result does not depend on how the log is cut into feed() calls)
            k = MIN_SAMPLES_DETECT
            if t.size < k and not (final and t.size >= 2):
                return
            if self._rate is None:
                self._rate = float(1.0 / np.median(np.diff(t[:k])))
                self._L = max(1, int(round(self.config.block_s * self._rate)))
            j = int(np.searchsorted(self._pend_tm, t[min(k, t.size) - 1], side="right"))
            self._detect_lattice(w[:k], a[:k], self._pend_m[:j])
        tm, mm = self._pend_tm, self._pend_m
        max_gap = self.config.max_gap_s
        # filter blocks: L samples each, cut at a gap longer than max_gap (the block ends before it)
        L, n = self._L, t.size
        cut = np.flatnonzero(np.diff(t) > max_gap)
        bounds: list[tuple[int, int]] = []
        i = g = 0
        while n - i >= L or (final and n - i > 0):
            j = min(i + L, n)
            while g < cut.size and cut[g] < i:
                g += 1
            if g < cut.size and cut[g] < j - 1:
                j = int(cut[g]) + 1
            bounds.append((i, j))
            i = j
        if not bounds:
            return
        B = self._block_stats(t, w, a, tm, mm, bounds)
        for b, (i, j) in enumerate(bounds):
            tb = t[i:j]
            t0 = self._t_last if self._att_ok and self._t_last is not None else None
            if self._t_last is not None and tb[0] - self._t_last > max_gap:
                gap = float(tb[0] - self._t_last)
                self._event("gap", f"IMU gap of {gap:.3f} s: attitude restarted, calibration drift "
                                   "allowance for the gap added", tb[0])
                self._end_rest()
                self.P[np.diag_indices(self.n)] += self._cal_rw() * gap
                self._att_ok = False
                self._prev_means = None
                self._rest_count = 0
                t0 = None
            ml, mh = int(B.mlo[b]), int(B.mhi[b])
            tmb, mb = tm[ml:mh], mm[ml:mh]
            if self._q is not None and "mag" not in self._q and mb.shape[0]:
                self._q_mag_buf += mb.tolist()
                if len(self._q_mag_buf) >= 16:
                    self._q["mag"] = value_lattice(np.asarray(self._q_mag_buf))
                    self._apply_lattice(("mag",))
                    self._q_mag_buf = []
            clip = self._clipped(w[i:j], a[i:j], float(tb[-1]), B.w_absmax[b], B.a_absmax[b])
            if clip["gyro"]:
                # a clipped gyro turns the attitude by less than the body did: nothing of this block is
                # used, and the attitude restarts from the accel (and mag) once the gyro is off the rail
                self._end_rest()
                self._att_ok = False
            elif t0 is None:
                self._end_rest()
                self._init_attitude(tb, w[i:j], a[i:j], tmb, mb)
            else:
                self._step(B, b, t, a, T, tm, mm, clip)
            self._t_last = float(tb[-1])
            self._w_last = w[j - 1].copy()
            self._n_imu += j - i
        i, k = bounds[-1][1], int(B.mhi[-1])
        self._pend_t, self._pend_w, self._pend_a, self._pend_T = t[i:], w[i:], a[i:], T[i:]
        self._pend_tm, self._pend_m = tm[k:], mm[k:]

    def _block_stats(self, t: Array, w: Array, a: Array, tm: Array, m: Array,
                     bounds: list[tuple[int, int]]) -> _Blocks:
        """Everything the blocks ``bounds`` need from the raw data alone, for all of them at once."""
        lo = np.array([b[0] for b in bounds], dtype=np.intp)
        hi = np.array([b[1] for b in bounds], dtype=np.intp)
        nb, end = lo.size, int(hi[-1])
        cnt = hi - lo
        tt, ww, aa = t[:end], w[:end], a[:end]
        seg = np.repeat(np.arange(nb), cnt)
        # mag samples of each block: after the previous block's last sample (for the first block, after
        # the last sample already filtered when the attitude runs on), up to the block's last sample
        mhi = np.searchsorted(tm, tt[hi - 1], side="right")
        m0 = 0
        if self._att_ok and self._t_last is not None and tt[0] - self._t_last <= self.config.max_gap_s:
            m0 = min(int(np.searchsorted(tm, self._t_last, side="right")), int(mhi[0]))
        mlo = np.concatenate([[m0], mhi[:-1]])
        mcnt = mhi - mlo
        # trapezoid rate and interval ending at each sample (sample 0: from the last one filtered)
        t_prev = self._t_last if self._t_last is not None else float(tt[0])
        w_prev = self._w_last if self._t_last is not None else ww[0]
        w_ext = np.vstack([w_prev[None], ww])
        t_ext = np.concatenate([[t_prev], tt])
        dt = np.diff(t_ext)
        # jerk term of the trapezoid: Δt·|Δ²ω|/4 at every sample but the block's last
        d2 = (w_ext[2:] - 2 * w_ext[1:-1] + w_ext[:-2]) * (dt[1:, None] / 4)
        e2 = np.concatenate([np.einsum("ij,ij->i", d2, d2), [0.0]])
        e2[hi - 1] = 0.0
        jerk = np.add.reduceat(e2, lo)
        w_mean, w_std = _seg_mean_std(ww, lo, cnt)
        a_mean, a_std = _seg_mean_std(aa, lo, cnt)
        m_mean, m_std = _seg_mean_std(m, mlo, mcnt)
        var3 = {"gyro": third_diff_var(ww, tt, seg, nb), "accel": third_diff_var(aa, tt, seg, nb)}
        mt = tm[m0 : int(mhi[-1])]
        mseg = np.repeat(np.arange(nb), mcnt)
        var3["mag"] = third_diff_var(m[m0 : int(mhi[-1])], mt, mseg, nb)
        # interpolation of each mag sample between the IMU ticks around it (index into t_ext)
        jm = np.clip(np.searchsorted(t_ext, mt, side="left"), lo[mseg] + 1, hi[mseg])
        frac = np.clip((mt - t_ext[jm - 1]) / (t_ext[jm] - t_ext[jm - 1]), 0.0, 1.0)
        return _Blocks(lo, hi, mlo, mhi, w_ext, dt, w_mean, w_std, a_mean, a_std, m_mean, m_std, var3,
                       jerk, 3 * np.maximum(cnt - 1, 0), np.maximum.reduceat(np.abs(ww), lo, axis=0),
                       np.maximum.reduceat(np.abs(aa), lo, axis=0), jm - lo[mseg], frac)

    def _clipped(self, w: Array, a: Array, t: float, w_absmax: Array, a_absmax: Array) -> dict[str, bool]:
        """Which sensors read at their ADC rail in this block; an event at the start of every clipped
        stretch. A rail is learnt from ``rail_run`` identical readings in a row (runs carry over block
        boundaries) at a magnitude of at least ``rail_min``: noise makes a reading that is not clipped
        change within a few samples. Once learnt, any reading at the rail counts as clipped.
        ``w_absmax``, ``a_absmax`` (3,) the block's largest |reading| per axis."""
        c = self.config
        out = {"mag": False}
        for s, v, amax in (("gyro", w, w_absmax), ("accel", a, a_absmax)):
            rail = self._rail.get(s)
            hit = rail is not None and bool(np.any(amax >= np.asarray(rail) * (1 - 1e-9)))
            if float(amax.max()) < c.rail_min[s]:
                self._run.pop(s, None)
            else:
                carry = self._run.get(s)
                new_carry = []
                for k in range(3):
                    col = v[:, k]
                    starts = np.concatenate([[0], np.flatnonzero(col[1:] != col[:-1]) + 1])
                    lens = np.diff(np.concatenate([starts, [col.size]]))
                    if carry is not None and col[0] == carry[k][0]:
                        lens[0] += carry[k][1]
                    new_carry.append((float(col[-1]), int(lens[-1])))
                    i = int(np.argmax(lens))
                    val = abs(float(col[starts[i]]))
                    if lens[i] >= c.rail_run and val >= c.rail_min[s]:
                        r = self._rail.setdefault(s, [math.inf] * 3)
                        r[k] = min(r[k], val)
                        hit = True
                self._run[s] = new_carry
            if hit and not self._clip_on[s]:
                what = ("attitude restarted, the block's updates skipped" if s == "gyro"
                        else "its update skipped while clipped")
                self._event("saturation", f"{s} at its rail ±{np.round(self._rail[s], 4).tolist()}: {what}", t)
            self._clip_on[s] = hit
            out[s] = hit
        return out

    # ------------------------------------------------------------------------------------------
    # attitude (re)initialisation
    def _calibrated(self, sensor: str, raw: Array) -> Array:
        o, M = correction(self.x[None, SENSOR_SLICE[sensor]])
        return (raw - o[0]) @ M[0].T

    def _init_attitude(self, t: Array, w: Array, a: Array, tm: Array, m: Array) -> None:
        """Attitude from the block's mean accel (roll, pitch) and, where the mag is usable, its field (yaw).

        TRIAD with the body vectors (gravity, field) against the world ones (e_z, h_world); without a
        calibrated mag the yaw is arbitrary (the body x axis is put east) and left out of the filter.
        """
        c = self.config
        f = self._calibrated("accel", a.mean(axis=0))
        f = f / np.linalg.norm(f)
        if m.shape[0]:
            self._mag_collect(tm, m)
        use_mag = self.mag_enabled and m.shape[0] > 0
        if use_mag:
            h = self._calibrated("mag", m.mean(axis=0))
            h = h / np.linalg.norm(h)
            if not self.dip_known:
                self.x[DIP] = math.asin(float(np.clip(-f @ h, -1, 1)))
                self.P[DIP, :] = 0.0
                self.P[:, DIP] = 0.0
                self.P[DIP, DIP] = c.dip_sigma**2
                self.dip_known = True
            hw = field_world(self.x[DIP : DIP + 1])[0]
        else:
            h = np.array([1.0, 0.0, 0.0]) if abs(f[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
            hw = np.array([1.0, 0.0, 0.0])
        self.R_nom = _triad(f, h, np.array([0.0, 0.0, 1.0]), hw)
        # The attitude was computed from these very readings, so its error is a function of the accel
        # (and mag) calibration error; rather than model that correlation, start with a σ wide enough that
        # the missing correlation does not matter: the next updates re-derive the attitude properly.
        s_rp = c.att_init_sigma
        s_y = c.att_init_sigma if use_mag else c.yaw_free_sigma
        self.x[ATT] = 0.0
        self.P[ATT, :] = 0.0
        self.P[:, ATT] = 0.0
        # σ given about the world axes (tilt, heading), turned into the body-frame error
        self.P[ATT, ATT] = self.R_nom.T @ np.diag([s_rp, s_rp, s_y]) ** 2 @ self.R_nom
        self._att_ok = True
        self._yaw_free = not use_mag

    def _set_yaw_variance(self, P: Array, var: float) -> Array:
        """Remove everything P knows about the heading (rotation about world z) and give it ``var``.

        The error is in the body frame, so the heading is the direction u = R_nomᵀ e_z of the attitude
        error: P ← J P Jᵀ with J = I − u uᵀ on the attitude block, then var · u uᵀ added. J differs from
        the identity only in the attitude block, so only the attitude rows and columns change.
        """
        u = self.R_nom[2, :]  # R_nomᵀ e_z
        J = np.eye(3) - np.outer(u, u)
        P = P.copy()
        P[ATT, :] = J @ P[ATT, :]
        P[:, ATT] = P[:, ATT] @ J.T
        P[ATT, ATT] += var * np.outer(u, u)
        return P

    # ------------------------------------------------------------------------------------------
    # cold-start magnetometer
    def _mag_collect(self, tm: Array, m: Array) -> None:
        """Keep a bounded, time-decimated buffer of raw mag samples for the cold-start sphere fit."""
        if self.mag_enabled:
            return
        if not self._mag_buf and m.shape[0] and (self.init is None or self.init.mag is None):
            self._mag_prior_from_raw(m)
        for ti, mi in zip(tm, m, strict=True):
            if ti >= self._mag_buf_next:
                self._mag_buf.append([float(v) for v in mi])
                self._mag_buf_next = ti + 0.1
        if len(self._mag_buf) > self.config.mag_buffer_max:
            self._mag_buf = self._mag_buf[::2]

    def _mag_prior_from_raw(self, m: Array) -> None:
        """Cold mag prior in the raw unit, from the first samples' field magnitude |m|: scale 1/|m| and
        σ ``cold_sigma`` relative to it (the prior of :meth:`_prior` assumes a unit field). The mag is not
        used before its fit, so this changes only what a flight that never fits it reports: its prior."""
        r = float(np.median(np.linalg.norm(m, axis=1)))
        if not (math.isfinite(r) and r > 0):
            return
        sl = SENSOR_SLICE["mag"]
        cs = self.config.cold_sigma["mag"]
        x = np.concatenate([np.zeros(3), np.full(3, 1.0 / r), np.zeros(6)])
        sig = np.concatenate([np.full(3, cs["bias"] * r), np.full(3, cs["scale"] / r),
                              np.full(3, cs["alpha"]), np.full(3, cs["xi"])])
        self.x[sl] = x
        self.P[sl, :] = 0.0
        self.P[:, sl] = 0.0
        self.P[sl, sl] = np.diag(sig**2)
        self.prior_x[sl], self.prior_sigma[sl] = x, sig

    def _try_mag_fit(self, t: float) -> None:
        """Sphere fit ‖x − o‖ = r (linear least squares) once the samples span enough directions.

        The mag terms then start at o_mag = centre, s_mag = 1/r (all axes), angles 0, with the σ of
        ``config.mag_fit_sigma``; the filter's yaw is aligned to the field and the dip is estimated.
        """
        c = self.config
        if t < self._mag_fit_next or len(self._mag_buf) < c.mag_fit_min_samples:
            return
        self._mag_fit_next = t + 1.0
        x = np.asarray(self._mag_buf)
        m0 = x.mean(axis=0)
        xc = x - m0  # centred for conditioning
        A = np.column_stack([2 * xc, np.ones(x.shape[0])])
        b = (xc**2).sum(axis=1)
        sol, *_ = np.linalg.lstsq(A, b, rcond=None)
        oc = sol[:3]
        r2 = sol[3] + oc @ oc
        if r2 <= 0:
            return
        r = math.sqrt(r2)
        o = m0 + oc
        # usable only when the samples pin the centre down: LS covariance of the centre (the residual
        # includes the soft iron the sphere lacks, so this also rejects a cloud of noise or a flat circle)
        e = b - A @ sol
        s2 = float(e @ e) / max(1, x.shape[0] - 4)
        try:
            cov = s2 * np.linalg.inv(A.T @ A)
        except np.linalg.LinAlgError:
            return
        sig_o = float(np.sqrt(np.max(np.diag(cov)[:3])))
        u = (x - o) / np.linalg.norm(x - o, axis=1)[:, None]
        spread = float(np.linalg.eigvalsh(u.T @ u / u.shape[0])[0])
        cover = float(np.linalg.eigvalsh(np.cov(u.T))[0])
        if (spread < c.mag_fit_min_spread or cover < c.mag_fit_min_cover
                or not sig_o < c.mag_fit_max_centre_sigma * r):
            return
        sl = SENSOR_SLICE["mag"]
        fs = c.mag_fit_sigma
        x_m = np.concatenate([o, np.full(3, 1.0 / r), np.zeros(6)])
        sig = np.concatenate([np.full(3, fs["bias"] * r), np.full(3, fs["scale"] / r),
                              np.full(3, fs["alpha"]), np.full(3, fs["xi"])])
        kind = "sphere"
        # Refine to the full ellipsoid (eq. 17, geometric fit) where the samples carry it: the soft iron
        # then starts near its value and the first mag updates stay in the UKF's near-linear range.
        try:
            o_e, M_e, cov_e, _ = ellipsoid_gn(x, o, np.eye(3) / r)
            sd = np.sqrt(np.clip(np.diag(cov_e), 0, None))
            if (np.all(np.isfinite(sd)) and sd[:3].max() < c.mag_fit_max_centre_sigma * r
                    and sd[3:].max() < 0.01 / r and np.linalg.det(M_e) > 0):
                s_e, a_e, xi_e = decompose(M_e)
                x_m = np.concatenate([o_e, s_e, a_e, xi_e])
                fe = c.mag_ellipsoid_sigma
                sig = np.concatenate([np.maximum(3 * sd[:3], fe["bias"] * r), np.full(3, fe["scale"] / r),
                                      np.full(3, fe["alpha"]), np.full(3, fe["xi"])])
                kind = "ellipsoid"
        except (ValueError, np.linalg.LinAlgError):
            pass
        self.x[sl] = x_m
        self.P[sl, :] = 0.0
        self.P[:, sl] = 0.0
        self.P[sl, sl] = np.diag(sig**2)
        # the cold prior σ of the mag, in the now known raw unit, for the observability ratios
        cs = c.cold_sigma["mag"]
        self.prior_sigma[sl] = np.concatenate([np.full(3, cs["bias"] * r), np.full(3, cs["scale"] / r),
                                               np.full(3, cs["alpha"]), np.full(3, cs["xi"])])
        self.prior_x[sl] = self.x[sl]
        self.mag_enabled = True
        self._mag_buf = []
        self._event("mag_cold_start", f"{kind} fit on {x.shape[0]} samples: |field| {r:.4g} raw, "
                    f"hard iron {np.round(o, 4).tolist()} ± {sig_o:.2g}, direction spread {spread:.3f}", t)
        self._align_yaw_next = True

    def _align_yaw(self, tm: Array, m: Array) -> None:
        """First mag block after the cold fit: dip from the field's world direction, yaw turned to north."""
        h = self._calibrated("mag", m.mean(axis=0))
        hw = self.R_nom @ (h / np.linalg.norm(h))
        self.x[DIP] = math.asin(float(np.clip(-hw[2], -1, 1)))
        psi = math.atan2(hw[0], hw[1])  # turning the world by +psi about z moves hw onto +y
        c, s = math.cos(psi), math.sin(psi)
        Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        self.R_nom = Rz @ self.R_nom
        self.P[DIP, :] = 0.0
        self.P[:, DIP] = 0.0
        self.P = self._set_yaw_variance(self.P, self.config.att_init_sigma**2)
        self.P[DIP, DIP] = self.config.dip_sigma**2
        self.dip_known = True
        self._yaw_free = False
        self._align_yaw_next = False

    # ------------------------------------------------------------------------------------------
    # rest detection
    def _rest_detect(self, B: _Blocks, b: int, n: dict[str, float]) -> bool:
        """True once the raw gyro, accel and mag have stood still (within their noise) for
        ``rest_blocks`` blocks: per-axis spread inside the block and change of the block mean against
        the previous block. Works on raw data, so it needs no calibration; a constant-rate turn about
        the vertical without a magnetometer cannot be told from rest (nothing measures it)."""
        c = self.config
        L = int(B.hi[b] - B.lo[b])
        n_m = int(B.mhi[b] - B.mlo[b])
        gm, am = B.w_mean[b], B.a_mean[b]
        mm = B.m_mean[b] if n_m else None
        k = c.rest_k
        sg, sa = n["gyro"], n["accel"]
        still = L >= 3 and float(B.w_std[b].max()) < k * sg and float(B.a_std[b].max()) < k * sa
        prev = self._prev_means
        if prev is not None and still:
            d = math.sqrt(2.0 / L)
            still = (float(np.abs(gm - prev[0]).max()) < 2 * k * sg * d
                     and float(np.abs(am - prev[1]).max()) < 2 * k * sa * d)
            if still and mm is not None and prev[2] is not None:
                still = float(np.abs(mm - prev[2]).max()) < 2 * k * n["mag"] * math.sqrt(2.0 / n_m)
        self._prev_means = (gm, am, mm if mm is not None else (prev[2] if prev is not None else None))
        self._rest_count = self._rest_count + 1 if still else 0
        self._still = still
        return self._rest_count >= c.rest_blocks

    def _hold_flags(self, B: _Blocks, b: int, n: dict[str, float]) -> dict[str, bool]:
        """Whether this block's accel / mag reading is held (its spread within the noise) and, if the
        reading moved since the previous block, start a new hold offset (a fresh quantisation error).
        Runs before :meth:`_rest_detect` (``_prev_means`` is the previous block's)."""
        out = {"accel": False, "mag": False}
        if not self._hold_slice:
            return out
        prev = self._prev_means
        cnt = {"accel": int(B.hi[b] - B.lo[b]), "mag": int(B.mhi[b] - B.mlo[b])}
        for s, mean, std, pi in (("accel", B.a_mean[b], B.a_std[b], 1), ("mag", B.m_mean[b], B.m_std[b], 2)):
            if s not in self._hold_slice or cnt[s] < 2:
                self._held[s] = False
                continue
            q = (self._q or {}).get(s, 0.0)
            held = bool(np.all(std <= 2.0 * n[s] + 0.5 * q))
            same = (held and self._held[s] and prev is not None and prev[pi] is not None
                    and bool(np.all(np.abs(mean - prev[pi]) < q + 3 * n[s] * math.sqrt(2.0 / cnt[s]))))
            if not same:
                self._reset_hold(s)
                self._hold_new = self._hold_new or held
            self._held[s] = held
            out[s] = held
        return out

    # ------------------------------------------------------------------------------------------
    # the filter step
    def _sigma_points(self) -> Array:
        """Scaled sigma points (2n+1, n) around x, from the Cholesky factor of P in ``self._perm`` order
        (attitude-relevant states first), so that rows past the first n_dyn leave them at the mean."""
        n = self.n
        c = self.config
        lam = c.sp_alpha**2 * (n + c.sp_kappa) - n
        perm = self._perm
        if self._perm_id:
            D = np.linalg.cholesky((lam + n) * self.P).T  # rows: offsets
        else:
            U = np.linalg.cholesky((lam + n) * self.P[np.ix_(perm, perm)]).T  # rows: offsets, permuted
            D = np.empty((n, n))
            D[:, perm] = U
        X = np.empty((2 * n + 1, n))
        X[0] = self.x
        np.add(self.x, D, out=X[1 : n + 1])
        np.subtract(self.x, D, out=X[n + 1 :])
        return X

    def _temp_reg(self, T: Array) -> Array:
        """Regressor T − T0 (°C) of the temperature extensions; 0 where the log has no temperature."""
        if self._T0 is None:
            fin = T[np.isfinite(T)]
            if fin.size:
                self._T0 = float(fin[0])
        if self._T0 is None:
            return np.zeros_like(T)
        return np.where(np.isfinite(T), T - self._T0, 0.0)

    def _gyro_extra(self, Xd: Array, T: Array, a: Array, held: bool) -> Array | None:
        """Extra raw gyro bias (S_d, L + 1, 3) per dynamic sigma point and sample: the extensions' terms and,
        while the gyro reading is held (at rest), its quantisation offset — the same error the
        zero-rate update sees, so that the attitude drift does not read it as bias."""
        ext = self._ext_slice
        hold = held and "gyro" in self._hold_slice
        if "temperature_bias:gyro" not in ext and "g_sensitivity" not in ext and not hold:
            return None
        L = T.shape[0]
        b = np.zeros((Xd.shape[0], L, 3))
        if hold:
            b += Xd[:, self._hold_slice["gyro"]][:, None, :]
        if "temperature_bias:gyro" in ext:
            r = self._temp_reg(T)
            b += Xd[:, ext["temperature_bias:gyro"]][:, None, :] * r[None, :, None]
        if "g_sensitivity" in ext:
            f = self._calibrated("accel", a)  # (L, 3) specific force, m/s²
            b += Xd[:, ext["g_sensitivity"]][:, None, :] * f[None]
        # at the L + 1 rate samples of the propagation: the block's first value serves the sample before it
        return np.concatenate([b[:, :1], b], axis=1)

    def _step(self, B: _Blocks, b: int, t_all: Array, a_all: Array, T_all: Array, tm_all: Array,
              m_all: Array, clip: dict[str, bool]) -> None:
        """One UKF predict + update over block ``b`` of ``B``: IMU samples [lo, hi) of the buffers t (s),
        a (m/s²), T (°C) (the gyro enters through ``B``) and mag samples [mlo, mhi) of tm, m."""
        c = self.config
        i, j, ml, mh = int(B.lo[b]), int(B.hi[b]), int(B.mlo[b]), int(B.mhi[b])
        t, a, T = t_all[i:j], a_all[i:j], T_all[i:j]
        tm, m = tm_all[ml:mh], m_all[ml:mh]
        tl = float(t[-1])
        n_m = mh - ml
        mag_before = (self.mag_enabled, self._align_yaw_next)
        if n_m and not self.mag_enabled:
            self._mag_collect(tm, m)
            self._try_mag_fit(tl)
        if self.mag_enabled and self._align_yaw_next and n_m:
            self._align_yaw(tm, m)
        use_mag = self.mag_enabled and n_m > 0 and not self._align_yaw_next
        spec = self._spec_noise()
        for s in SENSORS:
            self._update_noise_level(s, float(B.var3[s][b]), tl, spec[s])
        n = self._noise(spec)
        self._hold_new = False
        held = self._hold_flags(B, b, n)
        if c.vehicle == "auto":
            why = self._vehicle.update(math.sqrt(float(B.var3["accel"][b])), None, tl)
            if why:
                self._event("vehicle", why + ": vehicle acceleration modelled from here on", tl)
        n_rest = n
        if self._vehicle.active and self._noise_high["accel"]:
            # a vibrating vehicle is not at rest: judge stillness against the sensor's own noise
            n_rest = dict(n, accel=n["accel"] / math.sqrt(self._noise_ratio["accel"]))
        rest = self._rest_detect(B, b, n_rest)
        zero_rate = rest and self._still
        acc = self._rest_acc
        if acc is not None and (not zero_rate or self._hold_new or held != acc["held"]
                                or mag_before != (self.mag_enabled, self._align_yaw_next)
                                or use_mag != acc["use_mag"]):
            self._end_rest()
        if zero_rate:
            self._rest_step(B, b, t, T, n, held, use_mag, clip)
            return
        try:
            X = self._sigma_points()
        except np.linalg.LinAlgError:
            self._diverged("covariance is not positive definite", tl)
            return
        L = t.size
        dyn = self._dyn_pts
        c_mag = None
        if use_mag:
            k0 = ml - int(B.mlo[0])
            c_mag = interp_weights(B.m_j[k0 : k0 + n_m], B.m_frac[k0 : k0 + n_m], L)
        # every sensor's model for every sigma point that needs it, in one evaluation (eqs. 1–6): the
        # gyro's for the dynamic points, the accel's and the mag's for all
        S, Sd = X.shape[0], dyn.shape[0]
        o_all, M_all, Minv_all = model_pair(np.concatenate(
            [X[dyn, SENSOR_SLICE["gyro"]], X[:, SENSOR_SLICE["accel"]], X[:, SENSOR_SLICE["mag"]]]))
        pred = propagate_block(X, self.R_nom, B.w_ext[i : j + 1], B.dt[i:j], c_mag, dyn, (o_all[:Sd], M_all[:Sd]),
                               self._gyro_extra(X[dyn], T, a, self._still))
        R_nom = pred.R_end[0]  # sigma point 0 is the mean (zero attitude error)
        # the other points share the mean's attitude history: their error stays exactly 0
        X[dyn, ATT] = rot_log(R_nom.T @ pred.R_end)
        Wm, Wc = self._Wm, self._Wc
        dt_blk = float(t[-1] - self._t_last)
        q = self._process_noise(dt_blk, n["gyro"])
        # trapezoid error where the rate is not smooth (a jerk, a step): Δt·|Δ²ω|/4 per sample, added to
        # the attitude noise, less what the white noise alone gives (E[Δ²n]² = 6σ²), so that rest and
        # smooth motion add ~0
        if L >= 2:
            noise = float(B.jerk_n[b]) * 6.0 * (n["gyro"] * dt_blk / L / 4) ** 2
            q[ATT] += max(0.0, float(B.jerk[b]) - noise) / 3.0
        q[ATT] += self._bilinear_var() * dt_blk**2
        x_pred = Wm @ X
        Y = X - x_pred
        P_pred = (Y.T * Wc) @ Y  # the unscented transform (Wan & van der Merwe 2000), + Q below
        P_pred.flat[:: P_pred.shape[0] + 1] += q
        self.R_nom = R_nom
        ext = self._ext_slice
        T_reg = float(np.mean(self._temp_reg(T))) if ("temperature_bias:gyro" in ext
                                                      or "temperature_bias:accel" in ext) else 0.0

        # measurements: block means
        zs, Zs, rs, names = [], [], [], []
        a_mean = B.a_mean[b]
        rate = float(np.linalg.norm(pred.M_gyr @ (B.w_mean[b] - pred.o_gyr)))
        # quasi-static weighting: the part of ||f| − g| that neither the noise nor the calibration's own
        # uncertainty (spread of |f| over the sigma points) explains, and the centripetal term of an
        # unknown lever arm, both add to the accel variance (adaptive R). Judged against the calibration's
        # σ, not its mean alone, so that a calibration error is not taken for motion.
        o_a, M_a, Minv_a = o_all[Sd : Sd + S], M_all[Sd : Sd + S], Minv_all[Sd : Sd + S]
        f_all = np.einsum("sij,sj->si", M_a, a_mean - o_a)
        nf = np.sqrt(np.einsum("si,si->s", f_all, f_all))
        nf_mean = float(Wm @ nf)
        var_cal = max(0.0, float(Wc @ (nf - nf_mean) ** 2))
        sig_mean = n["accel"] / math.sqrt(L)
        dev = max(0.0, abs(nf_mean - c.gravity) - 3.0 * math.sqrt(sig_mean**2 + var_cal))
        # |f|² = g² + 2g·a_v + |a|²: a deviation dev of the norm allows a horizontal acceleration of up to
        # √(2g·dev), which the norm does not show otherwise
        var_a = (sig_mean**2 + (c.acc_dev_gain * dev) ** 2 + 2.0 * c.gravity * dev
                 + (c.acc_lever_m * rate**2) ** 2)
        if c.vehicle == "auto":
            why = self._vehicle.update(math.nan, dev, tl)
            if why:
                self._event("vehicle", why + ": vehicle acceleration modelled from here on", tl)
        if self._vehicle.active:
            # outside a rest the specific force is gravity plus the vehicle's unknown acceleration
            var_a += vehicle_accel_var(c.vehicle_accel_sigma, c.vehicle_accel_tau, dt_blk)
        self._coverage.add_motion(pred.M_gyr @ (B.w_mean[b] - pred.o_gyr), dt_blk, self._vehicle.active)
        if use_mag:
            self._coverage.add_field(self._calibrated("mag", B.m_mean[b]))
        if not clip["accel"]:
            Za = np.einsum("sij,sj->si", Minv_a, c.gravity * pred.f_body) + o_a  # eq. 1 inverted
            if held["accel"]:
                Za = Za + X[:, self._hold_slice["accel"]]
            if "temperature_bias:accel" in ext:
                Za = Za + X[:, ext["temperature_bias:accel"]] * T_reg
            zs.append(a_mean)
            Zs.append(Za)
            rs.append(np.full(3, var_a))
            names.append("accel")
        if use_mag and pred.h_body is not None:
            Zm = np.einsum("sij,sj->si", Minv_all[Sd + S :], pred.h_body) + o_all[Sd + S :]  # eq. 1 inverted
            if held["mag"]:
                Zm = Zm + X[:, self._hold_slice["mag"]]
            zs.append(B.m_mean[b])
            Zs.append(Zm)
            rs.append(np.full(3, n["mag"] ** 2 / n_m))
            names.append("mag")
        if not zs:
            x_new, P_new = x_pred, P_pred
        else:
            # not at rest (rests go to _rest_step): an accel outlier is motion the model lacks, dropped
            x_new, P_new = self._update(Y, x_pred, P_pred, zs, Zs, rs, names, False, tl, damp=c.update_damping)
        self._commit(x_new, P_new, tl)

    def _rest_step(self, B: _Blocks, b: int, t: Array, T: Array, n: dict[str, float], held: dict[str, bool],
                   use_mag: bool, clip: dict[str, bool]) -> None:
        """A block inside a rest: the body does not turn, so the block adds nothing but more samples of the
        same static readings. The rest's readings are therefore one measurement — their running means
        (accel, mag, the gyro's zero rate) with σ²/N — applied once to the state as it was when the rest
        began (plus the process noise of the whole rest), re-done every block as N grows. Exact for a
        linear model (the mean is sufficient); for the nonlinear one it keeps the linearisation where a
        single measurement would have it: updating with every block at a drifting linearisation point
        instead gains spurious information from the same static pose (with a cold accelerometer, its scale
        and bias along gravity — o = a − g/s, a curve — ended at 5–18σ after 30 s at rest).

        The attitude is held (no gyro integration: the gyro's reading at rest is its bias, measured by the
        zero-rate update). Ended by :meth:`_end_rest` when the rest ends or anything changes the model."""
        c = self.config
        i, j, ml, mh = int(B.lo[b]), int(B.hi[b]), int(B.mlo[b]), int(B.mhi[b])
        L, n_m = j - i, mh - ml
        tl = float(t[-1])
        if not (np.isfinite(self.P).all() and (self.P.diagonal() > 0).all()):
            # the running rest restarts from its first state, which would hide a broken covariance
            self._rest_acc = None
            self._diverged("non-finite or non-positive variance", tl)
            return
        acc = self._rest_acc
        first = acc is None
        if acc is None:
            acc = self._rest_acc = {
                "x": self.x.copy(), "P": self.P.copy(), "R_nom": self.R_nom.copy(), "q": np.zeros(self.n),
                "held": dict(held), "use_mag": use_mag, "sa": np.zeros(3), "na": 0.0, "sm": np.zeros(3),
                "nm": 0.0, "sw": np.zeros(3), "nw": 0.0, "sT": 0.0, "nT": 0, "post": {}}
        ext = self._ext_slice
        acc["q"] += self._process_noise(float(t[-1] - self._t_last), n["gyro"])
        # this block's innovation against what the rest so far predicts: the sequential NIS (what a
        # per-block filter would record), so that the windows fill and judge as before
        for s_, mean_, ok_, cnt_ in (("accel", B.a_mean[b], not clip["accel"], L), ("mag", B.m_mean[b], use_mag, n_m)):
            post = acc["post"].get(s_)
            if post is not None and ok_ and cnt_:
                nu_ = mean_ - post[0]
                try:
                    self._nis_record(s_, float(nu_ @ np.linalg.solve(post[1] + np.eye(3) * n[s_] ** 2 / cnt_, nu_)), tl)
                except np.linalg.LinAlgError:
                    pass
        # running means weighted by each block's information (the noise level may change within a rest)
        if not clip["accel"]:
            w_ = L / n["accel"] ** 2
            acc["sa"] += B.a_mean[b] * w_
            acc["na"] += w_
        if use_mag:
            w_ = n_m / n["mag"] ** 2
            acc["sm"] += B.m_mean[b] * w_
            acc["nm"] += w_
        w_ = L / n["gyro"] ** 2
        acc["sw"] += B.w_mean[b] * w_
        acc["nw"] += w_
        if "temperature_bias:gyro" in ext or "temperature_bias:accel" in ext:
            acc["sT"] += float(np.sum(self._temp_reg(T)))
            acc["nT"] += L
        T_reg = acc["sT"] / max(acc["nT"], 1)
        x0, P0 = acc["x"], acc["P"] + np.diag(acc["q"])
        self.x, self.P, self.R_nom = x0.copy(), P0, acc["R_nom"]
        try:
            X = self._sigma_points()
        except np.linalg.LinAlgError:
            self._rest_acc = None
            self._diverged("covariance is not positive definite", tl)
            return
        S = X.shape[0]
        Wm, Wc = self._Wm, self._Wc
        R_s = self.R_nom @ _rodrigues_n(X[:, ATT])  # (S, 3, 3) attitude of every sigma point
        o_all, M_all, Minv_all = model_pair(np.concatenate([X[:, SENSOR_SLICE["accel"]], X[:, SENSOR_SLICE["mag"]]]))
        zs, Zs, rs, names = [], [], [], []
        f_cal = None
        if acc["na"]:
            a_mean = acc["sa"] / acc["na"]
            f_all = np.einsum("sij,sj->si", M_all[:S], a_mean - o_all[:S])
            f_cal = f_all[0]
            self._coverage.add_rest(f_cal, float(t[-1] - self._t_last))
            nf = np.sqrt(np.einsum("si,si->s", f_all, f_all))
            nf_mean = float(Wm @ nf)
            var_cal = max(0.0, float(Wc @ (nf - nf_mean) ** 2))
            sig_mean = 1.0 / math.sqrt(acc["na"])
            dev = max(0.0, abs(nf_mean - c.gravity) - 3.0 * math.sqrt(sig_mean**2 + var_cal))
            Za = np.einsum("sij,sj->si", Minv_all[:S], c.gravity * R_s[:, 2, :]) + o_all[:S]
            if held["accel"]:
                Za = Za + X[:, self._hold_slice["accel"]]
            if "temperature_bias:accel" in ext:
                Za = Za + X[:, ext["temperature_bias:accel"]] * T_reg
            zs.append(a_mean)
            Zs.append(Za)
            rs.append(np.full(3, sig_mean**2 + (c.acc_dev_gain * dev) ** 2 + 2.0 * c.gravity * dev))
            names.append("accel")
        if acc["nm"]:
            dip = X[:, DIP]
            h_body = np.cos(dip)[:, None] * R_s[:, 1, :] - np.sin(dip)[:, None] * R_s[:, 2, :]
            Zm = np.einsum("sij,sj->si", Minv_all[S:], h_body) + o_all[S:]
            if held["mag"]:
                Zm = Zm + X[:, self._hold_slice["mag"]]
            zs.append(acc["sm"] / acc["nm"])
            Zs.append(Zm)
            rs.append(np.full(3, 1.0 / acc["nm"]))
            names.append("mag")
        s_gyr = float(np.mean(self.x[index("gyro", "scale")]))
        Zg = X[:, index("gyro", "bias")]
        if "gyro" in self._hold_slice:
            Zg = Zg + X[:, self._hold_slice["gyro"]]
        if "temperature_bias:gyro" in ext:
            Zg = Zg + X[:, ext["temperature_bias:gyro"]] * T_reg
        if "g_sensitivity" in ext and f_cal is not None:
            Zg = Zg + X[:, ext["g_sensitivity"]] * f_cal
        zs.append(acc["sw"] / acc["nw"])
        Zs.append(Zg)
        rs.append(np.full(3, 1.0 / acc["nw"] + (c.rest_rate_sigma / s_gyr) ** 2))
        names.append("rest")
        Y = X - x0
        acc["post"] = {}
        x_new, P_new = self._update(Y, x0, P0, zs, Zs, rs, names, True, tl, record=first, post_out=acc["post"])
        self._commit(x_new, P_new, tl)  # a divergence there also ends the running rest (_reset_calibration)

    def _commit(self, x_new: Array, P_new: Array, tl: float) -> None:
        """Take a posterior (x (n,), P (n, n)) as the state after a motion or rest update at log time ``tl`` s:
        fold its attitude error into the nominal (reset, USQUE), forget the heading while nothing sees it,
        and treat a non-finite state or non-positive variance as a divergence instead."""
        c = self.config
        P_new = 0.5 * (P_new + P_new.T)
        self.R_nom = self.R_nom @ _rodrigues1(x_new[ATT])
        x_new[ATT] = 0.0
        if self._yaw_free:
            # Without a usable mag nothing sees the heading, exactly (a world-z turn leaves Rᵀe_z alone):
            # forget it — marginalise it out and give it back a diffuse σ. A small σ would assert a
            # heading knowledge the data do not hold and leak spurious information into the alphas.
            P_new = self._set_yaw_variance(P_new, c.yaw_free_sigma**2)
        if (not np.isfinite(x_new).all() or not np.isfinite(P_new).all()
                or not (P_new.diagonal() > 0).all()):
            self._diverged("non-finite state or non-positive variance", tl)
            return
        self.x, self.P = x_new, P_new
        self._n_blocks += 1
        if tl >= self._next_trace:
            self._trace_row(tl)
            self._next_trace = tl + c.trace_every_s

    def _end_rest(self) -> None:
        """Close the running rest (:meth:`_rest_step`): its last state stays."""
        self._rest_acc = None

    def _update(self, Y: Array, x_pred: Array, P_pred: Array, zs: list[Array], Zs: list[Array],
                rs: list[Array], names: list[str], static: bool, t: float,
                record: bool = True, post_out: dict[str, Any] | None = None,
                damp: float = 0.0) -> tuple[Array, Array]:
        """Joint UKF update with the stacked measurements; chi-square gating per sensor (accel outside
        a quasi-static block: dropped; otherwise its R inflated to gate size); consider states get no
        gain and the covariance update in Joseph-like form stays the true error covariance for any gain.
        Y (S, n) the sigma points less the predicted mean. ``record``: NIS values enter the windows.
        ``post_out``: gets, per gated sensor, the measurement the posterior predicts and its covariance
        (z + (S − R) S⁻¹ ν and (S − R) − (S − R) S⁻¹ (S − R), linearised), for the next block's NIS."""
        Wm, Wc = self._Wm, self._Wc
        z = np.concatenate(zs)
        Z = np.hstack(Zs)
        r_diag = np.concatenate(rs)
        z_pred = Wm @ Z
        Zc = Z - z_pred
        ZW = Zc * Wc[:, None]
        S_zz = Zc.T @ ZW
        hph = np.diag(S_zz).copy()
        S_zz.flat[:: S_zz.shape[0] + 1] += r_diag
        Pxz = Y.T @ ZW
        nu = z - z_pred
        k_gate = [k for k, s in enumerate(names) if s != "rest"]
        nis_all = [math.inf] * len(names)
        if k_gate:
            S_b = np.stack([S_zz[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] for k in k_gate])
            nu_b = np.stack([nu[3 * k : 3 * k + 3] for k in k_gate])
            try:
                sol = np.linalg.solve(S_b, nu_b[..., None])[..., 0]
                for kk, k in enumerate(k_gate):
                    nis_all[k] = float(nu_b[kk] @ sol[kk])
            except np.linalg.LinAlgError:
                pass
        keep = None
        for k in k_gate:
            s = names[k]
            sl = slice(3 * k, 3 * k + 3)
            nis = nis_all[k]
            gate = self._gates[s]
            if s == "accel" and not static and nis > gate:
                # motion the model has no term for (linear acceleration): an outlier, not a statistic of
                # the filter's consistency — dropped and counted, kept out of the NIS windows
                if keep is None:
                    keep = np.ones(z.size, bool)
                keep[sl] = False
                self._nis[s]["rejected"] += 1
                continue
            if record:
                self._nis_record(s, nis, t)
            if nis > gate:
                # soft gate: inflate R so this update counts no more than a gate-sized one
                self._nis[s]["rejected"] += 1
                S_zz[sl, sl] += np.diag(r_diag[sl] * (nis / gate - 1))
            if post_out is not None:
                Sk = S_zz[sl, sl]
                A = Sk - np.diag(r_diag[sl])
                AS = np.linalg.solve(Sk, A).T  # A S⁻¹ (S, A symmetric)
                post_out[s] = (z_pred[sl] + AS @ nu[sl], A - AS @ A)
        S_gain = S_zz
        if damp > 0:
            # partial update (``UKFConfig.update_damping``): the gain as if R were at least damp·HPHᵀ;
            # gating above and the covariance below use the model's own S, so P stays the covariance of
            # the error left by this (suboptimal) gain
            S_gain = S_zz.copy()
            d = np.diag(S_zz) - hph
            S_gain.flat[:: S_zz.shape[0] + 1] += np.maximum(0.0, damp * hph - d)
        if keep is not None:
            if not keep.any():
                return x_pred, P_pred
            S_zz = S_zz[np.ix_(keep, keep)]
            S_gain = S_gain[np.ix_(keep, keep)] if damp > 0 else S_zz
            Pxz = Pxz[:, keep]
            nu = nu[keep]
        K = np.linalg.solve(S_gain, Pxz.T).T
        # Schmidt ("consider") states: the gauge terms are never updated
        K[self._consider] = 0.0
        x_new = x_pred + K @ nu
        KPzx = K @ Pxz.T
        P_new = P_pred - KPzx - KPzx.T + (K @ S_zz) @ K.T
        return x_new, P_new

    # ------------------------------------------------------------------------------------------
    # consistency
    def _nis_band(self, dof: int = 3) -> tuple[float, float]:
        W = self.config.nis_window
        p = self.config.nis_band_p / 2
        return (float(chi2.ppf(p, W * dof) / W), float(chi2.ppf(1 - p, W * dof) / W))

    def _nis_record(self, sensor: str, nis: float, t: float) -> None:
        """Windowed mean NIS vs its chi-square band; a run of windows far above it is a divergence."""
        st = self._nis[sensor]
        st["sum"] += min(nis, 1e6)
        st["n"] += 1
        st["updates"] += 1
        st["last"] = nis
        if st["n"] < self.config.nis_window:
            return
        mean = st["sum"] / st["n"]
        st["sum"], st["n"] = 0.0, 0
        lo, hi = self._nis_band()
        st["windows"].append([t, mean])
        if len(st["windows"]) > 1000:
            st["windows"] = st["windows"][-1000:]
        if mean > self.config.divergence_factor * hi:
            st["bad_run"] += 1
        else:
            st["bad_run"] = 0
        if st["bad_run"] >= self.config.divergence_windows:
            self._diverged(f"{sensor} NIS window mean {mean:.3g} far above its band [{lo:.3g}, {hi:.3g}] "
                           f"for {st['bad_run']} windows", t, sensor)

    def _diverged(self, why: str, t: float, sensor: str | None = None) -> None:
        """Re-initialise: only the magnetometer (its terms and the dip, from the init or a new cold fit)
        when its NIS alone ran away, otherwise every calibration state from the init calibration."""
        if sensor == "mag":
            self._event("divergence", why + "; magnetometer re-initialised", t)
            x0, sig0 = self._prior()
            sl = np.r_[np.arange(SENSOR_SLICE["mag"].start, SENSOR_SLICE["mag"].stop), DIP]
            self.x[sl] = x0[sl]
            self.P[sl, :] = 0.0
            self.P[:, sl] = 0.0
            self.P[sl, sl] = sig0[sl] ** 2
            self.prior_sigma[sl], self.prior_x[sl] = sig0[sl], x0[sl]
            self.mag_enabled = self.init is not None and self.init.mag is not None
            self.dip_known = False
            self._mag_buf, self._mag_buf_next, self._mag_fit_next = [], -math.inf, -math.inf
            self._align_yaw_next = False
            self._rest_acc = None
            self._att_ok = False  # the heading restarts with the next block
            self._nis["mag"].update({"sum": 0.0, "n": 0, "bad_run": 0})
            return
        self._event("divergence", why + "; re-initialised from the init calibration", t)
        self._reset_calibration()

    def _event(self, kind: str, detail: str, t: float) -> None:
        self._n_events += 1
        self.events.append({"t": float(t), "kind": kind, "detail": detail})
        if len(self.events) > self.config.max_events:
            del self.events[: len(self.events) - self.config.max_events]

    def nis_summary(self) -> dict[str, Any]:
        """Per sensor: updates, rejected by the gate, windows, share of window means inside the band."""
        lo, hi = self._nis_band()
        out: dict[str, Any] = {"band": [lo, hi]}
        for s, st in self._nis.items():
            ws = np.array([w[1] for w in st["windows"]]) if st["windows"] else np.zeros(0)
            out[s] = {
                "updates": st["updates"], "rejected": st["rejected"], "windows": int(ws.size),
                "mean": float(ws.mean()) if ws.size else float("nan"),
                "in_band": float(np.mean((ws >= lo) & (ws <= hi))) if ws.size else float("nan"),
            }
        out["events_total"] = self._n_events
        return out

    # ------------------------------------------------------------------------------------------
    # results
    def sigma(self) -> Array:
        return np.sqrt(np.clip(np.diag(self.P), 0.0, None))

    def result(self) -> Calibration:
        """The current estimate as a Calibration (source "online") with 1σ for bias, scale, alpha, xi, and
        the model extensions (``extensions``, the contract's effect keys) with their σ."""
        sig = self.sigma()
        sens = {}
        g = self.gauge
        for s in SENSORS:
            p = {q: self.x[index(s, q)] for q in PARAMS}
            sg = {q: sig[index(s, q)] for q in PARAMS}
            if g and s != g:
                # alphas are relative to the gauge sensor's (held at its prior): their σ in B includes its σ
                sg["alpha"] = np.hypot(sg["alpha"], sig[index(g, "alpha")])
            sg = {q: v.tolist() for q, v in sg.items()}
            sens[s] = SensorCalibration.from_params(p["bias"], p["scale"], p["alpha"], p["xi"], sigma=sg)
        meta = {"online": {
            "dip_deg": math.degrees(self.x[DIP]), "dip_sigma_deg": math.degrees(sig[DIP]),
            "mag_used": bool(self.mag_enabled), "imu_samples": self._n_imu, "blocks": self._n_blocks,
            "gauge": {"sensor": g, "terms": list(self._gauge_terms()) if g else []},
            "quantisation": {k: v for k, v in (self._q or {}).items()},
            "hold_states": sorted(self._hold_slice),
            "extensions_sigma": self.extensions_sigma(),
            "extensions_unit": {e: EXTENSIONS[e][2] for e in self._ext_slice},
            "events": list(self.events), "nis": self.nis_summary(),
            "observability": self.observability_report(),
        }}
        return Calibration(gyro=sens["gyro"], accel=sens["accel"], mag=sens["mag"], source="online",
                           meta=meta, extensions=self.extensions())

    def extensions(self) -> dict[str, Any]:
        """Estimated model extensions in the contract's effect vocabulary (keys of
        :data:`onlinecal.extensions.EXTENSION_KEYS`, accepted by ``validate_extensions`` and ``correct``):
        ``temperature_bias`` {sensor, axis: None, coeff: [3] per axis (unit/°C), T0 (°C, the log's first
        temperature)} — a list when both sensors carry one — and ``g_sensitivity`` {sensor: gyro,
        axis: None, coeff: [3] (rad/s per m/s²)}. Their 1σ are in :meth:`extensions_sigma`."""
        out: dict[str, Any] = {}
        for e, sl in self._ext_slice.items():
            name, sensor = e.split(":")[0], EXTENSIONS[e][0]
            d: dict[str, Any] = {"sensor": sensor, "axis": None, "coeff": [float(v) for v in self.x[sl]]}
            if name == "temperature_bias":
                d["T0"] = float(self._T0) if self._T0 is not None else 25.0
            if name in out:
                out[name] = (out[name] if isinstance(out[name], list) else [out[name]]) + [d]
            else:
                out[name] = d
        return out

    def extensions_sigma(self) -> dict[str, list[float]]:
        """1σ of every extension coefficient, per axis: {``extra_states`` key: [3]}."""
        sig = self.sigma()
        return {e: [float(v) for v in sig[sl]] for e, sl in self._ext_slice.items()}

    def _public_names(self) -> list[tuple[int, str]]:
        """Calibration terms, dip and extensions (attitude and hold offsets are nuisance states)."""
        return [(i, nm) for i, nm in enumerate(self.names) if i >= 3 and not nm.startswith("hold.")]

    def observability(self) -> dict[str, dict[str, Any]]:
        """Per parameter: posterior σ / prior σ and whether it is excited (ratio below ``excited_ratio``)."""
        sig = self.sigma()
        out = {}
        for i, nm in self._public_names():
            ratio = float(sig[i] / self.prior_sigma[i]) if self.prior_sigma[i] > 0 else float("nan")
            out[nm] = {"ratio": ratio, "excited": bool(ratio < self.config.excited_ratio)}
        return out

    def observability_report(self) -> dict[str, Any]:
        """Determined and undetermined terms, why, and the motion that would determine them
        (:func:`onlinecal.ukf.vehicle.observability_report`)."""
        held = set()
        if self.gauge:
            held = {f"{self.gauge}.{p}.{a}" for p in self._gauge_terms() for a in AXES}
        names = [nm for _, nm in self._public_names()]
        idx = [i for i, _ in self._public_names()]
        return observability_report(["att.x", "att.y", "att.z"] + names,
                                    np.concatenate([np.zeros(3), self.sigma()[idx]]),
                                    np.concatenate([np.ones(3), self.prior_sigma[idx]]),
                                    self._coverage, self._vehicle, held, self.gauge, self.config.excited_ratio)

    def missing_motion(self) -> list[str]:
        """What motion is still needed to excite the parameters that are not yet excited."""
        obs = self.observability()
        need: list[str] = []

        def add(msg: str) -> None:
            if msg not in need:
                need.append(msg)

        other = {"x": "y or z", "y": "x or z", "z": "x or y"}
        # which turns excite a gyro axis-coupling term (small-angle eqs. 5–6): alpha_k couples the two
        # axes other than k; xi_z tilts y towards x, xi_y tilts z towards x, xi_x tilts z towards y
        xi_turn = {"x": "y or z", "y": "x or z", "z": "x or y"}
        held = set()
        if self.gauge:
            held = {f"{self.gauge}.{p}.{a}" for p in self._gauge_terms() for a in AXES}
        for nm, o in obs.items():
            if o["excited"] or nm in held:
                continue
            if nm == "dip":
                add("hold still with the magnetometer calibrated (dip of the field)")
                continue
            if nm.startswith("ext."):
                e = nm.split(".")[1]
                add("let the temperature change (warm-up) for the temperature coefficients"
                    if e.startswith("temperature_bias") else
                    "turn with gravity along each gyro axis in turn (g-sensitivity)")
                continue
            s, p, ax = nm.split(".")
            if s == "gyro":
                if p == "bias":
                    add("hold still (any attitude) for the gyro bias")
                elif p == "scale":
                    add(f"turn about {ax}")
                elif p == "alpha":
                    add(f"turn about {other[ax]} (gyro axis alignment)")
                else:
                    add(f"turn about {xi_turn[ax]} (gyro non-orthogonality)")
            elif s == "accel":
                if p in ("bias", "scale"):
                    add(f"hold still in another attitude: {ax} up and {ax} down")
                else:
                    add("hold still in tilted attitudes (between the axes, e.g. 45°)")
            else:
                if p in ("bias", "scale"):
                    add(f"turn about {other[ax]} so the field sweeps the {ax} axis (mag)")
                else:
                    add("rotate through all attitudes (e.g. a tumble) to sweep the field (mag)")
        return need

    # ------------------------------------------------------------------------------------------
    # trace
    def _trace_row(self, t: float) -> None:
        sig = self.sigma()
        row: dict[str, float] = {"t": t}
        for i, nm in self._public_names():
            row[nm] = float(self.x[i])
            row[nm + ".sigma"] = float(sig[i])
        for s, st in self._nis.items():
            row[f"nis.{s}"] = float(st.get("last", float("nan")))
        self._trace.append(row)

    def trace_rows(self, clear: bool = False) -> list[dict[str, float]]:
        """Trace rows (time, every estimate, its σ, last NIS) every ``trace_every_s``; ``clear`` drains."""
        rows = list(self._trace)
        if clear:
            self._trace.clear()
        return rows

    # ------------------------------------------------------------------------------------------
    # checkpoint / resume
    def get_state(self) -> dict[str, Any]:
        """Everything needed to resume, as a JSON-able dict (plain lists and numbers)."""
        return {
            "schema": STATE_SCHEMA,
            "config": self.config.to_dict(),
            "init": self.init.to_dict() if self.init is not None else None,
            "names": list(self.names), "holds": list(self._hold_slice), "hold_sigma": dict(self._hold_sigma),
            "x": self.x.tolist(), "P": self.P.tolist(), "R_nom": self.R_nom.tolist(),
            "prior_sigma": self.prior_sigma.tolist(), "prior_x": self.prior_x.tolist(),
            "rate": self._rate, "L": self._L,
            "pend_t": self._pend_t.tolist(), "pend_w": self._pend_w.tolist(), "pend_a": self._pend_a.tolist(),
            "pend_T": [_fin(v) for v in self._pend_T.tolist()],
            "pend_tm": self._pend_tm.tolist(), "pend_m": self._pend_m.tolist(),
            "t_last": self._t_last, "w_last": self._w_last.tolist(), "att_ok": self._att_ok,
            "yaw_free": self._yaw_free,
            "align_yaw_next": self._align_yaw_next,
            "mag_enabled": self.mag_enabled, "dip_known": self.dip_known, "mag_buf": self._mag_buf,
            "mag_buf_next": _fin(self._mag_buf_next), "mag_fit_next": _fin(self._mag_fit_next),
            "next_trace": _fin(self._next_trace), "n_imu": self._n_imu, "n_blocks": self._n_blocks,
            "nis": self._nis, "events": self.events, "n_events": self._n_events, "trace": list(self._trace),
            "rest_count": self._rest_count,
            "prev_means": None if self._prev_means is None else [
                None if v is None else np.asarray(v).tolist() for v in self._prev_means],
            "q": self._q, "q_mag_buf": self._q_mag_buf, "held": self._held,
            "noise_ratio": self._noise_ratio, "noise_high": self._noise_high,
            "rail": self._rail, "run": {k: [list(r) for r in v] for k, v in self._run.items()},
            "clip_on": self._clip_on, "T0": self._T0,
            "vehicle": self._vehicle.to_dict(), "coverage": self._coverage.get_state(),
            "rest_acc": None if self._rest_acc is None else {
                **{k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self._rest_acc.items()
                   if k != "post"},
                "post": {k: [v[0].tolist(), v[1].tolist()] for k, v in self._rest_acc["post"].items()}},
        }

    def set_state(self, d: dict[str, Any]) -> None:
        """Restore from :meth:`get_state` (the instance's init and config are replaced by the saved ones)."""
        if d.get("schema") != STATE_SCHEMA:
            raise ValueError(f"not a UKF state (schema {d.get('schema')!r}, expected {STATE_SCHEMA})")
        self.config = UKFConfig.from_dict(d["config"])
        c = self.config
        self._gates = {"accel": float(chi2.ppf(c.acc_gate_p, 3)), "mag": float(chi2.ppf(c.mag_gate_p, 3))}
        self.init = Calibration.from_dict(d["init"]) if d["init"] is not None else None
        self._build_layout(tuple(d["holds"]))
        if list(self.names) != list(d["names"]):
            raise ValueError("UKF state: its state names do not match its config")
        self._hold_sigma = {k: float(v) for k, v in d["hold_sigma"].items()}
        self.x = np.asarray(d["x"], float)
        self.P = np.asarray(d["P"], float)
        self.R_nom = np.asarray(d["R_nom"], float)
        self.prior_sigma = np.asarray(d["prior_sigma"], float)
        self.prior_x = np.asarray(d["prior_x"], float)
        self._rate, self._L = d["rate"], int(d["L"])
        self._pend_t = np.asarray(d["pend_t"], float).reshape(-1)
        self._pend_w = np.asarray(d["pend_w"], float).reshape(-1, 3)
        self._pend_a = np.asarray(d["pend_a"], float).reshape(-1, 3)
        self._pend_T = np.array([math.nan if v is None else v for v in d["pend_T"]], float).reshape(-1)
        self._pend_tm = np.asarray(d["pend_tm"], float).reshape(-1)
        self._pend_m = np.asarray(d["pend_m"], float).reshape(-1, 3)
        self._t_last = d["t_last"]
        self._w_last = np.asarray(d["w_last"], float)
        self._att_ok = bool(d["att_ok"])
        self._yaw_free = bool(d["yaw_free"])
        self._align_yaw_next = bool(d["align_yaw_next"])
        self.mag_enabled = bool(d["mag_enabled"])
        self.dip_known = bool(d["dip_known"])
        self._mag_buf = [list(v) for v in d["mag_buf"]]
        self._mag_buf_next = _unfin(d["mag_buf_next"])
        self._mag_fit_next = _unfin(d["mag_fit_next"])
        self._next_trace = _unfin(d["next_trace"])
        self._n_imu, self._n_blocks = int(d["n_imu"]), int(d["n_blocks"])
        self._nis = d["nis"]
        self.events = list(d["events"])
        self._n_events = int(d["n_events"])
        self._trace = deque(d["trace"], maxlen=c.trace_max_rows)
        self._rest_count = int(d.get("rest_count", 0))
        pm = d.get("prev_means")
        self._prev_means = (None if pm is None
                            else tuple(None if v is None else np.asarray(v, float) for v in pm))
        self._q = d["q"]
        self._q_mag_buf = [list(v) for v in d["q_mag_buf"]]
        self._held = {k: bool(v) for k, v in d["held"].items()}
        self._noise_ratio = {k: float(v) for k, v in d["noise_ratio"].items()}
        self._noise_high = {k: bool(v) for k, v in d["noise_high"].items()}
        self._rail = {k: [float(x) for x in v] for k, v in d["rail"].items()}
        self._run = {k: [(float(r[0]), int(r[1])) for r in v] for k, v in d["run"].items()}
        self._clip_on = {k: bool(v) for k, v in d["clip_on"].items()}
        self._T0 = d["T0"]
        self._T_last = math.nan
        self._vehicle = VehicleDetector(c.vehicle_vibration_sigma, c.vehicle_dev_min)
        self._vehicle.set_state(d.get("vehicle", {}))
        self._coverage = MotionCoverage()
        self._coverage.set_state(d.get("coverage", {}))
        ra = d.get("rest_acc")
        self._rest_acc = None if ra is None else {
            k: (np.asarray(v, float) if k in ("x", "P", "R_nom", "q", "sa", "sm", "sw") else v) for k, v in ra.items()}
        if self._rest_acc is not None:
            self._rest_acc["post"] = {k: (np.asarray(v[0], float), np.asarray(v[1], float))
                                      for k, v in self._rest_acc["post"].items()}

    @classmethod
    def from_state(cls, d: dict[str, Any]) -> OnlineCalibrator:
        obj = cls(None, UKFConfig.from_dict(d["config"]))
        obj.set_state(d)
        return obj


def _fin(v: float) -> float | None:
    return None if not math.isfinite(v) else float(v)


def _unfin(v: float | None) -> float:
    return -math.inf if v is None else float(v)


def _rodrigues_n(theta: Array) -> Array:
    """exp([θ]_x) (S, 3, 3) for rotation vectors θ (S, 3) (:func:`onlinecal.ukf.layout.rodrigues_cm`)."""
    return rodrigues_cm(np.ascontiguousarray(theta.T)).transpose(2, 0, 1)


def _rodrigues1(v: Array) -> Array:
    """exp([v]_x) (3, 3) of one rotation vector v (3,) (Rodrigues' formula, series below 1e-4 rad)."""
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    a2 = x * x + y * y + z * z
    if a2 < 1e-8:
        s, c = 1.0 - a2 / 6.0, 0.5 - a2 / 24.0
    else:
        a = math.sqrt(a2)
        s, c = math.sin(a) / a, (1.0 - math.cos(a)) / a2
    return np.array([[1.0 - c * (y * y + z * z), c * x * y - s * z, c * x * z + s * y],
                     [c * x * y + s * z, 1.0 - c * (x * x + z * z), c * y * z - s * x],
                     [c * x * z - s * y, c * y * z + s * x, 1.0 - c * (x * x + y * y)]])


def _triad(b1: Array, b2: Array, w1: Array, w2: Array) -> Array:
    """Rotation R (world ← body) with R b1 = w1 exactly and R b2 as close to w2 as possible (TRIAD)."""

    def frame(u: Array, v: Array) -> Array:
        e1 = u / np.linalg.norm(u)
        e2 = np.cross(e1, v)
        e2 /= np.linalg.norm(e2)
        return np.column_stack([e1, e2, np.cross(e1, e2)])

    return frame(w1, w2) @ frame(b1, b2).T


__all__ = ["OnlineCalibrator", "UKFConfig", "AXES"]
