"""The filter's measurement models, each written once and used by the motion step and the rest step.

Each model is the paper's sensor model inverted (raw = M⁻¹ c + o, eq. 1 with eqs. 2–6) applied to what the
sensor sees in the body frame, evaluated for every sigma point at once (S points: arrays (S, ...)):

* :class:`AccelModel` — specific force of a body at rest, g Rᵀe_z, plus the held-reading offset and the
  temperature-bias extension; its R is the quasi-static weighting (adaptive R, :meth:`AccelModel.variance`);
* :class:`MagModel` — the unit field Rᵀh_world(δ) plus the held-reading offset; R = σ²/N;
* :class:`ZeroRateModel` — the gyro's reading at rest: its bias, plus the hold offset and the extensions'
  terms; R = σ²/N plus an allowance for micro-motion.

The body-frame quantity (gravity direction, field) comes from the caller: in motion the block mean from
the propagation (:func:`.propagate.propagate_block`), at rest the held attitude (:func:`field_body`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .geometry import rodrigues_n
from .layout import ATT, DIP, SENSOR_SLICE, index, sensor_model
from .rest import RestAccumulator
from .unscented import Measurement

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Offsets:
    """Additive raw-reading terms beyond eq. 1, as state slices (None: absent): the offset of a held
    reading (``hold``), a temperature-bias extension (``temp``, times T − T0) and the gyro's
    g-sensitivity (``gsens``, times the specific force)."""

    hold: slice | None = None
    temp: slice | None = None
    gsens: slice | None = None


def _raw(X: Array, sensor: str, v_body: Array, model: tuple[Array, Array] | None) -> Array:
    """M⁻¹ v + o (S, 3) per sigma point (eq. 1 inverted); ``model`` (o (S, 3), M⁻¹ (S, 3, 3)) if already
    evaluated for these points, else from X's terms of ``sensor``."""
    o, Minv = model if model is not None else sensor_model(X[:, SENSOR_SLICE[sensor]])
    out: Array = np.einsum("sij,sj->si", Minv, v_body) + o
    return out


@dataclass(frozen=True)
class AccelModel:
    """Accelerometer at (quasi-)rest: raw = M_acc⁻¹ · g Rᵀe_z + o_acc (eq. 1 inverted, ENU z up).

    ``gravity`` m/s²; ``dev_gain``, ``lever_m`` the quasi-static weighting (:meth:`variance`)."""

    gravity: float
    dev_gain: float
    lever_m: float

    def h(self, X: Array, f_body: Array, off: Offsets = Offsets(), T_reg: float = 0.0,
          model: tuple[Array, Array] | None = None) -> Array:
        """Predicted raw reading (S, 3) m/s² for sigma points X (S, n); f_body (S, 3) the unit direction
        of gravity (Rᵀe_z) in the body frame; ``T_reg`` the temperature regressor T − T0 (°C)."""
        Z = _raw(X, "accel", self.gravity * f_body, model)
        if off.hold is not None:
            Z = Z + X[:, off.hold]
        if off.temp is not None:
            Z = Z + X[:, off.temp] * T_reg
        return Z

    def variance(self, M: Array, o: Array, a_mean: Array, Wm: Array, Wc: Array, sig_mean: float,
                 rate: float = 0.0) -> tuple[float, Array]:
        """Per-axis variance (m/s²)² of a mean reading a_mean (3,) whose noise σ is ``sig_mean``, and the
        specific force M (a − o) (S, 3) per sigma point (M (S, 3, 3), o (S, 3)); ``rate`` rad/s.

        Quasi-static weighting (adaptive R): the part ``dev`` of ||f| − g| that neither the noise nor the
        calibration's own uncertainty (spread of |f| over the sigma points) explains adds (gain·dev)²;
        |f|² = g² + 2g·a_v + |a|², so such a deviation allows a horizontal acceleration of up to √(2g·dev),
        which the norm does not show (2g·dev); the centripetal term of an unknown lever arm adds
        (r ω²)². Judged against the calibration's σ, not its mean alone, so that a calibration error is
        not taken for motion."""
        f_all = np.einsum("sij,sj->si", M, a_mean - o)
        dev = self.deviation(f_all, Wm, Wc, sig_mean)
        g = self.gravity
        var = sig_mean**2 + (self.dev_gain * dev) ** 2 + 2.0 * g * dev
        if rate:
            var = var + (self.lever_m * rate**2) ** 2
        return var, f_all

    def deviation(self, f_all: Array, Wm: Array, Wc: Array, sig_mean: float) -> float:
        """The part of ||f| − g| (m/s²) beyond 3σ of what the noise (σ ``sig_mean``) and the calibration's
        own uncertainty (spread of |f| over the sigma points' specific forces f_all (S, 3)) explain."""
        nf = np.sqrt(np.einsum("si,si->s", f_all, f_all))
        nf_mean = float(Wm @ nf)
        var_cal = max(0.0, float(Wc @ (nf - nf_mean) ** 2))
        return max(0.0, abs(nf_mean - self.gravity) - 3.0 * math.sqrt(sig_mean**2 + var_cal))


@dataclass(frozen=True)
class MagModel:
    """Magnetometer: raw = M_mag⁻¹ · Rᵀh_world(δ) + o_mag (eq. 1 inverted; h_world the unit field).

    ``misfit``: how far the start calibration's own fit left the calibrated field from the unit sphere, beyond
    the sensor's noise — the batch's ``norm_std_percent`` / 100 (:func:`misfit_of`; 0 without one). On a real
    hand-held session the field is not one constant vector (the hand carries the sensor through the room's
    gradients, the session's files were recorded in different places): the MARG set's batch leaves 2.0 % of the
    field, ~5–20× a block mean's noise, and a filter that weighed each block mean by its noise alone read that as
    a wrong calibration (mean NIS ~450, divergences, restarts; docs/results.md). :meth:`variance` adds it."""

    misfit: float = 0.0

    def variance(self, var_mean: float, sig_sample: float, x: Array) -> float:
        """R per axis (raw²) of a mean mag reading whose noise variance is ``var_mean`` (raw²): plus the part of
        the start's misfit ε (relative to the field) that the per-sample noise ``sig_sample`` (raw) does not
        explain, (ε F)² − σ², F = 1 / mean mag scale of x (n,) the field in raw units. A misfit within √2 of
        the noise is the noise (a simulated session's fit): nothing is added. It does not average down over a
        block or a rest, unlike the noise: a place's field error is common to all its samples."""
        if self.misfit <= 0.0:
            return var_mean
        s0 = SENSOR_SLICE["mag"].start + 3
        field = 3.0 / float(x[s0] + x[s0 + 1] + x[s0 + 2])
        extra = (self.misfit * field) ** 2 - sig_sample**2
        return var_mean + extra if extra > sig_sample**2 else var_mean

    def h(self, X: Array, h_body: Array, off: Offsets = Offsets(),
          model: tuple[Array, Array] | None = None) -> Array:
        """Predicted raw reading (S, 3) (raw unit) for sigma points X (S, n); h_body (S, 3) the unit field
        in the body frame (:func:`field_body`)."""
        Z = _raw(X, "mag", h_body, model)
        if off.hold is not None:
            Z = Z + X[:, off.hold]
        return Z


def field_body(R: Array, dip: Array) -> Array:
    """Rᵀ h_world(δ) (S, 3): the unit field (0, cos δ, −sin δ) (ENU, north +y) in the body frame of the
    attitudes R (S, 3, 3) (world ← body), dip δ (S,) rad."""
    out: Array = np.cos(dip)[:, None] * R[:, 1, :] - np.sin(dip)[:, None] * R[:, 2, :]
    return out


def gravity_body(R: Array) -> Array:
    """Rᵀ e_z (S, 3): the unit vertical in the body frame of the attitudes R (S, 3, 3)."""
    return R[:, 2, :]


@dataclass(frozen=True)
class ZeroRateModel:
    """Gyroscope at rest: the raw reading is its bias o_gyr (eq. 1 with ω = 0), plus the hold offset,
    the temperature-bias term and the g-sensitivity K·f. ``rest_rate_sigma`` rad/s per gyro axis: what a gyro at
    rest reads besides its bias (the Earth's rotation, or what is left of it: :func:`.earth.allowance`)."""

    rest_rate_sigma: tuple[float, float, float]

    def h(self, X: Array, off: Offsets = Offsets(), T_reg: float = 0.0, f_cal: Array | None = None) -> Array:
        """Predicted raw rate (S, 3) rad/s for sigma points X (S, n); f_cal (3,) the calibrated specific
        force (m/s²) for the g-sensitivity term (None: that term left out)."""
        Z = X[:, index("gyro", "bias")]
        if off.hold is not None:
            Z = Z + X[:, off.hold]
        if off.temp is not None:
            Z = Z + X[:, off.temp] * T_reg
        if off.gsens is not None and f_cal is not None:
            Z = Z + X[:, off.gsens] * f_cal
        return Z

    def variance(self, info: float, s_gyr: float) -> Array:
        """Per-axis variance (3,) (rad/s)²: 1/info (info = Σ N/σ², the mean's information) plus the
        allowance (rest_rate_sigma / s_gyr)² in raw units (s_gyr the mean gyro scale)."""
        return np.array([1.0 / info + (s / s_gyr) ** 2 for s in self.rest_rate_sigma])





def gyro_offsets(Xd: Array, off: Offsets, temp_reg: Array | None, f: Array | None, L: int) -> Array | None:
    """Extra raw gyro bias (S_d, L + 1, 3) per sigma point of Xd (S_d, n) and rate sample of a block of L
    IMU samples (the block's first value serves the sample before it): the hold offset (a held reading,
    the same error the zero-rate update sees, so that the attitude drift does not read it as bias), the
    temperature term K·(T − T0) (``temp_reg`` (L,) °C) and the g-sensitivity K·f (f (L, 3) m/s²). None
    when the offsets carry no term (the propagation then skips it)."""
    if off.hold is None and off.temp is None and off.gsens is None:
        return None
    b = np.zeros((Xd.shape[0], L, 3))
    if off.hold is not None:
        b += Xd[:, off.hold][:, None, :]
    if off.temp is not None and temp_reg is not None:
        b += Xd[:, off.temp][:, None, :] * temp_reg[None, :, None]
    if off.gsens is not None and f is not None:
        b += Xd[:, off.gsens][:, None, :] * f[None]
    out: Array = np.concatenate([b[:, :1], b], axis=1)
    return out


@dataclass(frozen=True)
class Models:
    """The filter's three measurement models (built once from the config)."""

    acc: AccelModel
    mag: MagModel
    zr: ZeroRateModel


def motion_measurements(mod: Models, X: Array, f_body: Array, h_body: Array | None,
                        sens: tuple[Array, Array, Array], z_acc: Array | None, z_mag: Array | None,
                        sig_acc: float, var_mag: float, W: tuple[Array, Array], rate: float,
                        off: tuple[Offsets, Offsets], T_reg: float, var_vehicle: float = 0.0) -> list[Measurement]:
    """A motion block's measurements for the propagated sigma points X (S, n): the block-mean accel z_acc
    (None: clipped) against g·f_body, the block-mean mag z_mag (None: not used) against h_body (both
    block means of the propagation, (S, 3)). ``sens`` (o, M, M⁻¹) of accel then mag for every point
    ((2S, 3), (2S, 3, 3) ×2); ``sig_acc`` σ of the accel mean (noise only), ``var_mag`` the mag mean's
    variance; W = (Wm, Wc); rate rad/s the block's mean turn rate (lever-arm term); ``off`` the accel's
    and mag's offsets; T_reg the temperature regressor (°C); ``var_vehicle`` (m/s²)² the unknown vehicle
    acceleration's share of the accel variance (:func:`.vehicle.vehicle_accel_var`, 0 off a vehicle)."""
    S = X.shape[0]
    o, M, Minv = sens
    meas = []
    if z_acc is not None:
        var_a, _ = mod.acc.variance(M[:S], o[:S], z_acc, W[0], W[1], sig_acc, rate)
        var_a += var_vehicle
        Za = mod.acc.h(X, f_body, off[0], T_reg, (o[:S], Minv[:S]))
        meas.append(Measurement("accel", z_acc, Za, np.full(3, var_a)))
    if z_mag is not None and h_body is not None:
        Zm = mod.mag.h(X, h_body, off[1], (o[S:], Minv[S:]))
        meas.append(Measurement("mag", z_mag, Zm, np.full(3, var_mag)))
    return meas


def rest_measurements(mod: Models, X: Array, R_nom: Array, sens: tuple[Array, Array, Array],
                      acc: RestAccumulator, W: tuple[Array, Array], off: tuple[Offsets, Offsets, Offsets],
                      s_gyr: float, sig_mag: float, x: Array) -> list[Measurement]:
    """A rest's measurements for the sigma points X (S, n) at the held attitude R_nom · exp([δθ]ₓ): the
    running means of accel and mag (:class:`.rest.RestAccumulator`, where it has them) and the gyro's
    zero rate. ``sens`` (o, M, M⁻¹) of accel then mag for every point; ``off`` the accel's, mag's and
    gyro's offsets; ``s_gyr`` the mean gyro scale; ``sig_mag`` raw the mag's per-sample noise and x (n,) the state
    for :meth:`MagModel.variance`."""
    S = X.shape[0]
    R_s = R_nom @ rodrigues_n(X[:, ATT])  # (S, 3, 3) attitude of every sigma point
    o, M, Minv = sens
    T_reg = acc.T_reg
    meas, f_cal = [], None
    if acc.na:
        a_mean = acc.sa / acc.na
        var_a, f_all = mod.acc.variance(M[:S], o[:S], a_mean, W[0], W[1], 1.0 / math.sqrt(acc.info("accel")))
        f_cal = f_all[0]
        Za = mod.acc.h(X, gravity_body(R_s), off[0], T_reg, (o[:S], Minv[:S]))
        meas.append(Measurement("accel", a_mean, Za, np.full(3, var_a)))
    if acc.nm:
        Zm = mod.mag.h(X, field_body(R_s, X[:, DIP]), off[1], (o[S:], Minv[S:]))
        meas.append(Measurement("mag", acc.sm / acc.nm, Zm,
                                np.full(3, mod.mag.variance(1.0 / acc.info("mag"), sig_mag, x))))
    Zg = mod.zr.h(X, off[2], T_reg, f_cal)
    meas.append(Measurement("rest", acc.gyro_mean(), Zg, mod.zr.variance(acc.info("gyro"), s_gyr)))
    return meas


def misfit_of(init: object) -> float:
    """:attr:`MagModel.misfit` of a start calibration: its batch magnetometer fit's ``norm_std_percent`` / 100
    (``meta.batch.steps.mag.figures``), 0 where it has none (a cold start, a file without the batch's meta)."""
    meta = getattr(init, "meta", None)
    try:
        v = float(meta["batch"]["steps"]["mag"]["figures"]["norm_std_percent"]) / 100.0  # type: ignore[index]
    except (KeyError, TypeError, ValueError):
        return 0.0
    return v if math.isfinite(v) and v > 0.0 else 0.0
