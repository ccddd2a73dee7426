"""The augmented-state UKF: attitude on the manifold plus every calibration term of the paper's model.

Filter: the scaled unscented transform of Wan & van der Merwe (2000) (filterpy's ``MerweScaledSigmaPoints``
and ``unscented_transform``), with the attitude kept as a nominal rotation plus a 3-vector error in the
state (the error-state / manifold treatment of Crassidis & Markley's USQUE, 2003): sigma points are rotation
vectors around the nominal, and after each update the mean error is folded into the nominal and reset to
zero. The state layout is in :mod:`onlinecal.ukf.layout`, the block propagation in
:mod:`onlinecal.ukf.propagate`.

One filter step covers a block of IMU samples (``UKFConfig.block_s``, 0.1 s by default): all sigma points
are propagated through the whole block at once, then one joint update with the block-mean accelerometer
(weighted by how quasi-static the block is, chi-square gated) and the block-mean magnetometer (at its own
sample times) follows.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, unscented_transform
from numpy.typing import NDArray
from scipy.stats import chi2

from ..batch.ellipsoid import FitError, fit_norm_lm
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
    rodrigues,
    rot_log,
)
from .propagate import predict_raw, propagate_block

Array = NDArray[np.float64]

STATE_SCHEMA = "onlinecal.ukf-state/1"


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
    # quasi-static weighting of the accelerometer (adaptive R): σ² += (k·||a|−g|)² + (r ω²)²
    acc_dev_gain: float = 5.0
    acc_lever_m: float = 0.005
    static_rate: float = 0.1  # rad/s: below this and ...
    static_dev: float = 0.1  # m/s²: ... below this the block counts as quasi-static
    acc_gate_p: float = 0.999  # chi-square gate on the accel NIS (3 dof)
    mag_gate_p: float = 0.9999  # chi-square gate on the mag NIS: soft (R inflated), never dropped
    nis_window: int = 100  # updates per NIS window
    nis_band_p: float = 0.001  # two-sided probability outside the window band
    divergence_factor: float = 5.0  # window mean NIS > factor × upper band ...
    divergence_windows: int = 3  # ... for this many windows in a row → divergence
    mag_fit_min_samples: int = 100
    mag_fit_min_spread: float = 0.05  # smallest eigenvalue of the scatter of unit field directions
    mag_fit_max_centre_sigma: float = 0.01  # LS σ of the sphere's centre, relative to its radius
    mag_buffer_max: int = 2000
    max_gap_s: float = 0.5  # IMU gap that restarts the attitude
    rest_k: float = 2.0  # rest: per-axis spread below k σ, mean change below 2k σ √(2/L)
    rest_blocks: int = 3  # consecutive still blocks before the zero-rate update applies
    rest_rate_sigma: float = 5e-5  # rad/s, allowance for micro-motion in a rest (zero-rate update)
    trace_every_s: float = 1.0
    trace_max_rows: int = 100_000
    gauge_sensor: str | None = "auto"  # whose alpha defines B (held at its prior); None: all free
    excited_ratio: float = 0.5  # posterior σ / prior σ below this: "excited"

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> UKFConfig:
        return cls(**d)


def _sqrt_upper(P: Array) -> Array:
    """Matrix U with Uᵀ U = P (rows are the sigma-point offsets filterpy expects)."""
    return np.linalg.cholesky(P).T


def _given_sigma(cal: SensorCalibration) -> Array:
    """The 12 σ (bias, scale, alpha, xi) a calibration carries, NaN where it has none."""
    out = []
    for p in PARAMS:
        v = np.asarray(cal.sigma.get(p, np.full(3, np.nan)), float).reshape(-1)
        out.append(v if v.shape == (3,) else np.full(3, np.nan))
    sig = np.concatenate(out)
    return np.where(np.isfinite(sig) & (sig > 0), sig, np.nan)


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
        self.points = MerweScaledSigmaPoints(N_STATE, c.sp_alpha, c.sp_beta, c.sp_kappa,
                                             sqrt_method=_sqrt_upper)
        self.events: list[dict[str, Any]] = []
        self._gates = {"accel": float(chi2.ppf(c.acc_gate_p, 3)), "mag": float(chi2.ppf(c.mag_gate_p, 3))}
        self._consider = self._consider_mask()
        self._trace: deque[dict[str, float]] = deque(maxlen=c.trace_max_rows)
        self._rate: float | None = None
        self._L = 0
        self._pend_t = np.zeros(0)
        self._pend_w = np.zeros((0, 3))
        self._pend_a = np.zeros((0, 3))
        self._pend_tm = np.zeros(0)
        self._pend_m = np.zeros((0, 3))
        self._t_last: float | None = None
        self._w_last = np.zeros(3)
        self._att_ok = False
        self._next_trace = -math.inf
        self._n_imu = 0
        self._n_blocks = 0
        self._nis: dict[str, dict[str, Any]] = {}
        self._reset_calibration()

    def _consider_mask(self) -> Array:
        """States held at their prior (Schmidt–Kalman consider states): the gauge sensor's alpha.

        A common rotation of the body frame (every sensor's T_R turned by the same Q, the attitude by Qᵀ)
        leaves every measurement unchanged, so nothing in the data fixes it: B is defined by the prior.
        Left free, a filter linearised at moving estimates gains spurious information along it and drifts
        (seen in cold starts: all three alphas off by the same degrees at 40σ). Holding one sensor's
        alpha at its prior (with its prior σ, as a consider parameter) pins B to that sensor's frame as
        given by ``init`` (the batch's B) or to the sensor itself on a cold start.
        """
        mask = np.zeros(N_STATE, bool)
        g = self.gauge
        if g:
            mask[index(g, "alpha")] = True
        return mask

    @property
    def gauge(self) -> str | None:
        """The sensor whose alpha defines B: ``config.gauge_sensor``, or for "auto" the init sensor with the
        tightest alpha σ (the one that carries B, e.g. the batch's mag), else the accelerometer."""
        g = self.config.gauge_sensor
        if g != "auto":
            return g
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
        """Prior mean and σ of the whole state from ``init`` (or cold). Attitude entries are filled later."""
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
                sig[sl] = np.where(np.isfinite(given), given * c.init_inflation, cold_v)
        x[DIP] = math.radians(60.0)
        sig[DIP] = math.radians(30.0)
        return x, sig

    def _reset_calibration(self) -> None:
        """(Re)start every calibration state from the prior; the attitude restarts on the next block."""
        self.x, sig = self._prior()
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
        self._nis = {s: {"sum": 0.0, "n": 0, "windows": [], "bad_run": 0, "rejected": 0, "updates": 0}
                     for s in ("accel", "mag")}

    # ------------------------------------------------------------------------------------------
    # noise
    def _noise(self) -> dict[str, float]:
        """Per-sample σ of the raw readings from the specs (white noise + quantisation)."""
        r = self._rate or 100.0
        mag_unit = self._mag_unit()
        return {
            "gyro": math.hypot(GYRO_SPEC.sigma(r), GYRO_SPEC.lsb / math.sqrt(12)),
            "accel": math.hypot(ACCEL_SPEC.sigma(r), ACCEL_SPEC.lsb / math.sqrt(12)),
            # relative to the field, then in the raw unit (the reader may deliver gauss or milli-gauss)
            "mag": math.hypot(MAG_SPEC.sigma(50.0), MAG_SPEC.lsb / math.sqrt(12)) / FIELD_GAUSS * mag_unit,
        }

    def _mag_unit(self) -> float:
        """Raw magnitude of the unit field: 1 / mean mag scale."""
        return float(1.0 / np.mean(self.x[SENSOR_SLICE["mag"]][3:6]))

    def _process_noise(self, dt: float, L: int) -> Array:
        """Q for one block of ``L`` samples lasting ``dt`` s.

        Attitude: angle random walk of the gyro, σ_gyr·Δt per sample, L samples (rad²), in every axis.
        Calibration: random walk, density × ``rw_factor`` per √s (bias), density/full-scale × ``rw_factor``
        (dimensionless terms) — a slow drift allowance set from the specs, not tuned per log.
        """
        c = self.config
        r = self._rate or 100.0
        n = self._noise()
        q = np.zeros(N_STATE)
        q[ATT] = L * (n["gyro"] / r) ** 2
        specs = {"gyro": GYRO_SPEC, "accel": ACCEL_SPEC, "mag": MAG_SPEC}
        for s, spec in specs.items():
            dens = spec.density if spec.density > 0 else spec.sigma(50.0) / math.sqrt(25.0)
            unit = self._mag_unit() / FIELD_GAUSS if s == "mag" else 1.0
            sl = SENSOR_SLICE[s]
            q[sl.start : sl.start + 3] = (dens * unit * c.rw_factor) ** 2 * dt
            q[sl.start + 3 : sl.stop] = (dens / spec.full_scale * c.rw_factor) ** 2 * dt
        q[DIP] = (1e-6) ** 2 * dt
        return np.diag(q)

    # ------------------------------------------------------------------------------------------
    # streaming
    def feed(self, block: ImuData) -> None:
        """Consume a block of any size. IMU samples beyond the last full filter block wait in a buffer."""
        if block.n_imu:
            self._pend_t = np.concatenate([self._pend_t, block.t_imu])
            self._pend_w = np.concatenate([self._pend_w, block.gyro.reshape(-1, 3)])
            self._pend_a = np.concatenate([self._pend_a, block.acc.reshape(-1, 3)])
        if block.n_mag:
            self._pend_tm = np.concatenate([self._pend_tm, block.t_mag])
            self._pend_m = np.concatenate([self._pend_m, block.mag.reshape(-1, 3)])
        self._process()

    def new_log(self) -> None:
        """The next samples start a new log: keep the calibration, restart the attitude and clock."""
        self.flush()
        self._pend_t = np.zeros(0)
        self._pend_w = np.zeros((0, 3))
        self._pend_a = np.zeros((0, 3))
        self._pend_tm = np.zeros(0)
        self._pend_m = np.zeros((0, 3))
        self._t_last = None
        self._att_ok = False

    def flush(self) -> None:
        """Process the IMU samples still buffered as one (short) block."""
        self._process(final=True)

    def _process(self, final: bool = False) -> None:
        t, w, a = self._pend_t, self._pend_w, self._pend_a
        if self._rate is None:
            if t.size < 10 and not (final and t.size >= 2):
                return
            self._rate = float(1.0 / np.median(np.diff(t)))
            self._L = max(1, int(round(self.config.block_s * self._rate)))
        L = self._L
        tm, mm = self._pend_tm, self._pend_m
        i = 0
        n = t.size
        max_gap = self.config.max_gap_s
        while n - i >= L or (final and n - i > 0):
            j = min(i + L, n)
            tb = t[i:j]
            t0 = self._t_last if self._att_ok and self._t_last is not None else None
            gaps = np.diff(tb) > max_gap
            if t0 is not None and tb[0] - t0 > max_gap:
                self._event("gap", f"IMU gap of {tb[0] - t0:.3f} s: attitude restarted", tb[0])
                self._att_ok = False
                t0 = None
            if gaps.any():
                j = i + int(np.argmax(gaps)) + 1  # process up to the gap
                tb = t[i:j]
            # mag samples belonging to this block
            k = int(np.searchsorted(tm, tb[-1], side="right"))
            lo = 0
            if t0 is not None:
                lo = int(np.searchsorted(tm, t0, side="right"))
            tmb, mb = tm[lo:k], mm[lo:k]
            tm, mm = tm[k:], mm[k:]
            if t0 is None:
                self._init_attitude(tb, w[i:j], a[i:j], tmb, mb)
            else:
                self._step(tb, w[i:j], a[i:j], tmb, mb)
            self._t_last = float(tb[-1])
            self._w_last = w[j - 1].copy()
            self._n_imu += j - i
            i = j
        self._pend_t, self._pend_w, self._pend_a = t[i:], w[i:], a[i:]
        self._pend_tm, self._pend_m = tm, mm

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
        error: P ← J P Jᵀ with J = I − u uᵀ on the attitude block, then var · u uᵀ added.
        """
        u = self.R_nom[2, :]  # R_nomᵀ e_z
        J = np.eye(N_STATE)
        J[ATT, ATT] -= np.outer(u, u)
        P = J @ P @ J.T
        P[ATT, ATT] += var * np.outer(u, u)
        return P

    # ------------------------------------------------------------------------------------------
    # cold-start magnetometer
    def _mag_collect(self, tm: Array, m: Array) -> None:
        """Keep a bounded, time-decimated buffer of raw mag samples for the cold-start sphere fit."""
        if self.mag_enabled:
            return
        for ti, mi in zip(tm, m, strict=True):
            if ti >= self._mag_buf_next:
                self._mag_buf.append([float(v) for v in mi])
                self._mag_buf_next = ti + 0.1
        if len(self._mag_buf) > self.config.mag_buffer_max:
            self._mag_buf = self._mag_buf[::2]

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
        if spread < c.mag_fit_min_spread or not sig_o < c.mag_fit_max_centre_sigma * r:
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
            fit = fit_norm_lm(x, 1.0, o, np.eye(3) / r, model="full")
            sd = np.sqrt(np.clip(np.diag(fit.cov), 0, None))
            if (np.all(np.isfinite(sd)) and sd[:3].max() < c.mag_fit_max_centre_sigma * r
                    and sd[3:].max() < 0.01 / r and np.linalg.det(fit.M) > 0):
                s_e, a_e, xi_e = decompose(fit.M)
                x_m = np.concatenate([fit.o, s_e, a_e, xi_e])
                fe = c.mag_ellipsoid_sigma
                sig = np.concatenate([np.maximum(3 * sd[:3], fe["bias"] * r), np.full(3, fe["scale"] / r),
                                      np.full(3, fe["alpha"]), np.full(3, fe["xi"])])
                kind = "ellipsoid"
        except (FitError, ValueError, np.linalg.LinAlgError):
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
    def _rest_detect(self, w: Array, a: Array, m: Array, n: dict[str, float]) -> bool:
        """True once the raw gyro, accel and mag have stood still (within their noise) for
        ``rest_blocks`` blocks: per-axis spread inside the block and change of the block mean against
        the previous block. Works on raw data, so it needs no calibration; a constant-rate turn about
        the vertical without a magnetometer cannot be told from rest (nothing measures it)."""
        c = self.config
        L = w.shape[0]
        gm, am = w.mean(axis=0), a.mean(axis=0)
        mm = m.mean(axis=0) if m.shape[0] else None
        k = c.rest_k
        sg, sa = n["gyro"], n["accel"]
        still = (L >= 3 and bool(np.all(w.std(axis=0) < k * sg)) and bool(np.all(a.std(axis=0) < k * sa)))
        prev = self._prev_means
        if prev is not None and still:
            d = math.sqrt(2.0 / L)
            still = bool(np.all(np.abs(gm - prev[0]) < 2 * k * sg * d)
                         and np.all(np.abs(am - prev[1]) < 2 * k * sa * d))
            if still and mm is not None and prev[2] is not None:
                sm = self._mag_noise_raw()
                still = bool(np.all(np.abs(mm - prev[2]) < 2 * k * sm * math.sqrt(2.0 / m.shape[0])))
        self._prev_means = (gm, am, mm if mm is not None else (prev[2] if prev is not None else None))
        self._rest_count = self._rest_count + 1 if still else 0
        return self._rest_count >= c.rest_blocks

    def _mag_noise_raw(self) -> float:
        """Per-sample σ of the raw mag: from the spec relative to the field, in the raw unit (once known)."""
        return self._noise()["mag"]

    # ------------------------------------------------------------------------------------------
    # the filter step
    def _step(self, t: Array, w: Array, a: Array, tm: Array, m: Array) -> None:
        """One UKF predict + update over the IMU block t (L,), w (L, 3), a (L, 3) and mag samples tm (M,)."""
        c = self.config
        if m.shape[0] and not self.mag_enabled:
            self._mag_collect(tm, m)
            self._try_mag_fit(float(t[-1]))
        if self.mag_enabled and self._align_yaw_next and m.shape[0]:
            self._align_yaw(tm, m)
        use_mag = self.mag_enabled and m.shape[0] > 0 and not self._align_yaw_next
        try:
            X = self.points.sigma_points(self.x, self.P)
        except np.linalg.LinAlgError:
            self._diverged("covariance is not positive definite", float(t[-1]))
            return
        L = t.size
        pred = propagate_block(X, self.R_nom, float(self._t_last), self._w_last, t, w,
                               tm if use_mag else np.zeros(0))
        R_nom = pred.R_end[0]  # sigma point 0 is the mean (zero attitude error)
        X = X.copy()
        X[:, ATT] = rot_log(R_nom.T @ pred.R_end)
        Wm, Wc = self.points.Wm, self.points.Wc
        dt_blk = float(t[-1] - self._t_last)
        x_pred, P_pred = unscented_transform(X, Wm, Wc, self._process_noise(dt_blk, L))
        self.R_nom = R_nom

        # measurements: block means
        n = self._noise()
        zs, Zs, rs, names = [], [], [], []
        a_mean = a.mean(axis=0)
        o_ga, M_ga = correction(np.stack([self.x[SENSOR_SLICE["gyro"]], self.x[SENSOR_SLICE["accel"]]]))
        f_cal = M_ga[1] @ (a_mean - o_ga[1])
        rate = float(np.linalg.norm(M_ga[0] @ (w.mean(axis=0) - o_ga[0])))
        # quasi-static weighting: the deviation of |a| from g beyond what the noise explains, and the
        # centripetal term of an unknown lever arm, both add to the accel variance (adaptive R)
        sig_mean = n["accel"] / math.sqrt(L)
        dev = max(0.0, abs(float(np.linalg.norm(f_cal)) - c.gravity) - 3.0 * sig_mean)
        var_a = sig_mean**2 + (c.acc_dev_gain * dev) ** 2 + (c.acc_lever_m * rate**2) ** 2
        rest = self._rest_detect(w, a, m, n)
        static = rest or (rate < c.static_rate and dev < c.static_dev)
        zs.append(a_mean)
        Zs.append(predict_raw(X, "accel", c.gravity * pred.f_body))
        rs.append(np.full(3, var_a))
        names.append("accel")
        if use_mag and pred.h_body is not None:
            zs.append(m.mean(axis=0))
            Zs.append(predict_raw(X, "mag", pred.h_body))
            rs.append(np.full(3, n["mag"] ** 2 / m.shape[0]))
            names.append("mag")
        if rest:
            # zero-rate pseudo-measurement (the paper's bias from rests, eqs. 34–35, done online): at rest
            # the raw gyro reads its bias, raw = M⁻¹·0 + o — linear in o, independent of M
            s_gyr = float(np.mean(self.x[index("gyro", "scale")]))
            zs.append(w.mean(axis=0))
            Zs.append(X[:, index("gyro", "bias")])
            rs.append(np.full(3, n["gyro"] ** 2 / L + (c.rest_rate_sigma / s_gyr) ** 2))
            names.append("rest")
        z = np.concatenate(zs)
        Z = np.concatenate(Zs, axis=1)
        r_diag = np.concatenate(rs)
        z_pred, S_zz = unscented_transform(Z, Wm, Wc, np.diag(r_diag))
        Pxz = (X - x_pred).T @ (Wc[:, None] * (Z - z_pred))
        nu = z - z_pred
        keep = np.ones(z.size, bool)
        for k, s in enumerate(names):
            sl = slice(3 * k, 3 * k + 3)
            try:
                nis = float(nu[sl] @ np.linalg.solve(S_zz[sl, sl], nu[sl]))
            except np.linalg.LinAlgError:
                nis = math.inf
            if s == "rest":
                continue
            self._nis_record(s, nis, float(t[-1]))
            gate = self._gates[s]
            if nis > gate:
                if s == "accel" and not static:
                    keep[sl] = False
                    self._nis[s]["rejected"] += 1
                else:
                    # soft gate: inflate R so this update counts no more than a gate-sized one
                    infl = nis / gate
                    S_zz[sl, sl] += np.diag(r_diag[sl] * (infl - 1))
                    self._nis[s]["rejected"] += 1
        if keep.any():
            S_k = S_zz[np.ix_(keep, keep)]
            Pxz_k = Pxz[:, keep]
            K = np.linalg.solve(S_k, Pxz_k.T).T
            # Schmidt ("consider") states: the gauge sensor's alpha is never updated; the covariance
            # update in the form valid for any gain keeps P the true error covariance
            K[self._consider] = 0.0
            x_new = x_pred + K @ nu[keep]
            KPzx = K @ Pxz_k.T
            P_new = P_pred - KPzx - KPzx.T + K @ S_k @ K.T
        else:
            x_new, P_new = x_pred, P_pred
        P_new = 0.5 * (P_new + P_new.T)
        # fold the attitude error into the nominal (reset, USQUE)
        self.R_nom = self.R_nom @ rodrigues(x_new[ATT])
        x_new[ATT] = 0.0
        if self._yaw_free:
            # Without a usable mag nothing sees the heading, exactly (a world-z turn leaves Rᵀe_z alone):
            # forget it — marginalise it out and give it back a diffuse σ. A small σ would assert a
            # heading knowledge the data do not hold and leak spurious information into the alphas.
            P_new = self._set_yaw_variance(P_new, c.yaw_free_sigma**2)
        if not np.all(np.isfinite(x_new)) or not np.all(np.isfinite(P_new)) or np.any(np.diag(P_new) <= 0):
            self._diverged("non-finite state or non-positive variance", float(t[-1]))
            return
        self.x, self.P = x_new, P_new
        self._n_blocks += 1
        if t[-1] >= self._next_trace:
            self._trace_row(float(t[-1]))
            self._next_trace = float(t[-1]) + c.trace_every_s

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
                           f"for {st['bad_run']} windows", t)

    def _diverged(self, why: str, t: float) -> None:
        self._event("divergence", why + "; re-initialised from the init calibration", t)
        self._reset_calibration()

    def _event(self, kind: str, detail: str, t: float) -> None:
        self.events.append({"t": float(t), "kind": kind, "detail": detail})

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
        return out

    # ------------------------------------------------------------------------------------------
    # results
    def sigma(self) -> Array:
        return np.sqrt(np.clip(np.diag(self.P), 0.0, None))

    def result(self) -> Calibration:
        """The current estimate as a Calibration (source "online") with 1σ for bias, scale, alpha, xi."""
        sig = self.sigma()
        sens = {}
        for s in SENSORS:
            p = {q: self.x[index(s, q)] for q in PARAMS}
            sg = {q: sig[index(s, q)] for q in PARAMS}
            g = self.gauge
            if g and s != g:
                # alphas are relative to the gauge sensor's (held at its prior): their σ in B includes its σ
                sg["alpha"] = np.hypot(sg["alpha"], sig[index(g, "alpha")])
            sg = {q: v.tolist() for q, v in sg.items()}
            sens[s] = SensorCalibration.from_params(p["bias"], p["scale"], p["alpha"], p["xi"], sigma=sg)
        meta = {"online": {
            "dip_deg": math.degrees(self.x[DIP]), "dip_sigma_deg": math.degrees(sig[DIP]),
            "mag_used": bool(self.mag_enabled), "imu_samples": self._n_imu, "blocks": self._n_blocks,
            "events": list(self.events), "nis": self.nis_summary(),
        }}
        return Calibration(gyro=sens["gyro"], accel=sens["accel"], mag=sens["mag"], source="online",
                           meta=meta)

    def observability(self) -> dict[str, dict[str, Any]]:
        """Per parameter: posterior σ / prior σ and whether it is excited (ratio below ``excited_ratio``)."""
        sig = self.sigma()
        out = {}
        for i, nm in enumerate(NAMES):
            if i < 3:
                continue
            ratio = float(sig[i] / self.prior_sigma[i]) if self.prior_sigma[i] > 0 else float("nan")
            out[nm] = {"ratio": ratio, "excited": bool(ratio < self.config.excited_ratio)}
        return out

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
        for nm, o in obs.items():
            if o["excited"]:
                continue
            if nm == "dip":
                add("hold still with the magnetometer calibrated (dip of the field)")
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
        for i, nm in enumerate(NAMES):
            if i < 3:
                continue
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
            "x": self.x.tolist(), "P": self.P.tolist(), "R_nom": self.R_nom.tolist(),
            "prior_sigma": self.prior_sigma.tolist(), "prior_x": self.prior_x.tolist(),
            "rate": self._rate, "L": self._L,
            "pend_t": self._pend_t.tolist(), "pend_w": self._pend_w.tolist(), "pend_a": self._pend_a.tolist(),
            "pend_tm": self._pend_tm.tolist(), "pend_m": self._pend_m.tolist(),
            "t_last": self._t_last, "w_last": self._w_last.tolist(), "att_ok": self._att_ok,
            "yaw_free": self._yaw_free,
            "align_yaw_next": self._align_yaw_next,
            "mag_enabled": self.mag_enabled, "dip_known": self.dip_known, "mag_buf": self._mag_buf,
            "mag_buf_next": _fin(self._mag_buf_next), "mag_fit_next": _fin(self._mag_fit_next),
            "next_trace": _fin(self._next_trace), "n_imu": self._n_imu, "n_blocks": self._n_blocks,
            "nis": self._nis, "events": self.events, "trace": list(self._trace),
            "rest_count": self._rest_count,
            "prev_means": None if self._prev_means is None else [
                None if v is None else np.asarray(v).tolist() for v in self._prev_means],
        }

    def set_state(self, d: dict[str, Any]) -> None:
        """Restore from :meth:`get_state` (the instance's init and config are replaced by the saved ones)."""
        if d.get("schema") != STATE_SCHEMA:
            raise ValueError(f"not a UKF state (schema {d.get('schema')!r})")
        self.config = UKFConfig.from_dict(d["config"])
        c = self.config
        self.points = MerweScaledSigmaPoints(N_STATE, c.sp_alpha, c.sp_beta, c.sp_kappa,
                                             sqrt_method=_sqrt_upper)
        self._gates = {"accel": float(chi2.ppf(c.acc_gate_p, 3)), "mag": float(chi2.ppf(c.mag_gate_p, 3))}
        self._consider = self._consider_mask()
        self.init = Calibration.from_dict(d["init"]) if d["init"] is not None else None
        self._consider = self._consider_mask()
        self.x = np.asarray(d["x"], float)
        self.P = np.asarray(d["P"], float)
        self.R_nom = np.asarray(d["R_nom"], float)
        self.prior_sigma = np.asarray(d["prior_sigma"], float)
        self.prior_x = np.asarray(d["prior_x"], float)
        self._rate, self._L = d["rate"], int(d["L"])
        self._pend_t = np.asarray(d["pend_t"], float).reshape(-1)
        self._pend_w = np.asarray(d["pend_w"], float).reshape(-1, 3)
        self._pend_a = np.asarray(d["pend_a"], float).reshape(-1, 3)
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
        self._trace = deque(d["trace"], maxlen=c.trace_max_rows)
        self._rest_count = int(d.get("rest_count", 0))
        pm = d.get("prev_means")
        self._prev_means = (None if pm is None
                            else tuple(None if v is None else np.asarray(v, float) for v in pm))

    @classmethod
    def from_state(cls, d: dict[str, Any]) -> OnlineCalibrator:
        obj = cls(None, UKFConfig.from_dict(d["config"]))
        obj.set_state(d)
        return obj


def _fin(v: float) -> float | None:
    return None if not math.isfinite(v) else float(v)


def _unfin(v: float | None) -> float:
    return -math.inf if v is None else float(v)


def _triad(b1: Array, b2: Array, w1: Array, w2: Array) -> Array:
    """Rotation R (world ← body) with R b1 = w1 exactly and R b2 as close to w2 as possible (TRIAD)."""

    def frame(u: Array, v: Array) -> Array:
        e1 = u / np.linalg.norm(u)
        e2 = np.cross(e1, v)
        e2 /= np.linalg.norm(e2)
        return np.column_stack([e1, e2, np.cross(e1, e2)])

    return frame(w1, w2) @ frame(b1, b2).T


__all__ = ["OnlineCalibrator", "UKFConfig", "AXES"]
