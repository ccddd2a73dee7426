"""Stage 1 of diagnose: the session as the fitted baseline model sees it.

From raw logs and the baseline calibration: calibrated ω (rad/s), specific force a (m/s²) and field m
(norm 1) on the IMU clock (mag interpolated onto it), their smoothed derivatives, the rests, and the
attitude obtained by integrating the calibrated gyro (for the re-simulation). Everything is in the
body frame B of the calibration (contract: calibrated = matrix @ (raw − bias)).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..batch.gyro import rodrigues
from ..batch.segment import Interval
from ..io.base import ImuData
from ..model import Calibration, SensorCalibration
from .magcurrent import series_on_clock

Array = NDArray[np.float64]


@dataclass
class Session:
    """One log on a (possibly re-stamped) IMU clock. Arrays are (N,) or (N, 3).

    ``raw_*`` raw samples in input units; ``w``, ``a``, ``m`` calibrated (B frame); ``m`` is NaN where
    the log has no mag sample within reach; ``temp`` °C (NaN if absent); ``rests`` strict rests (rows).
    ``restamped``: the logger's time stamps were burst read times and were replaced by an even clock.
    """

    source: str
    t: Array
    raw_g: Array
    raw_a: Array
    raw_m: Array | None
    temp: Array
    w: Array
    a: Array
    m: Array | None
    rests: list[Interval]
    rate: float
    restamped: bool = False
    notes: list[str] = field(default_factory=list)
    series: dict[str, Array] = field(default_factory=dict)  # current (A) / throttle on the clock t (magcurrent)

    @property
    def n(self) -> int:
        return int(self.t.shape[0])

    @property
    def has_mag(self) -> bool:
        return self.m is not None and bool(np.isfinite(self.m[:, 0]).any())

    @property
    def has_temp(self) -> bool:
        return bool(np.isfinite(self.temp).sum() > 10 and np.nanstd(self.temp) > 0)


def _even_clock(t: Array) -> tuple[Array, bool]:
    """Burst-stamped logs (median period < half the mean period) get an even clock at the mean rate.

    Such loggers stamp the time a buffer was read, not when each sample was taken; the samples of a
    MEMS IMU are evenly spaced by its own oscillator, so the index is the better clock.
    """
    if t.size < 3:
        return t, False
    dt = np.diff(t)
    mean = (t[-1] - t[0]) / (t.size - 1)
    if np.median(dt) < 0.5 * mean:
        return t[0] + np.arange(t.size) * mean, True
    return t, False


def apply_cal(cal: SensorCalibration | None, raw: Array) -> Array:
    return cal.apply(raw) if cal is not None else np.asarray(raw, float).copy()


def prepare(data: ImuData, cal: Calibration, rests: list[Interval]) -> Session:
    """Calibrate one log with the baseline model and put the mag onto the IMU clock (linear interpolation
    inside the mag's time span; NaN outside or across mag gaps longer than 5 mag periods)."""
    t, restamped = _even_clock(np.asarray(data.t_imu, float))
    notes = []
    if restamped:
        notes.append(f"{data.source}: time stamps are burst read times (median period "
                     f"{np.median(np.diff(data.t_imu)) * 1e3:.2f} ms against a mean of "
                     f"{(data.t_imu[-1] - data.t_imu[0]) / (data.n_imu - 1) * 1e3:.2f} ms); the IMU samples were "
                     "re-stamped evenly and the mag mapped onto that clock by its share of the log")
    w = apply_cal(cal.gyro, data.gyro)
    a = apply_cal(cal.accel, data.acc)
    raw_m = m = None
    if data.has_mag and data.n_mag >= 10 and cal.mag is None:
        # an uncalibrated field has no norm or dip to check: the mag's invariants are left out
        notes.append(f"{data.source}: the baseline has no magnetometer calibration; the magnetometer's "
                     "invariants (|m| = 1, dip, m against gyro) are not checked")
    if data.has_mag and data.n_mag >= 10 and cal.mag is not None:
        tm = np.asarray(data.t_mag, float)
        if restamped:
            # the same even re-stamping, mapped by position in the log's original time span
            tm = np.interp(tm, data.t_imu, t)
        mm = cal.mag.apply(data.mag)
        m = np.column_stack([np.interp(t, tm, mm[:, k]) for k in range(3)])
        raw_m = np.column_stack([np.interp(t, tm, data.mag[:, k]) for k in range(3)])
        j = np.searchsorted(tm, t)
        dtm = np.median(np.diff(tm))
        lo = tm[np.clip(j - 1, 0, tm.size - 1)]
        hi = tm[np.clip(j, 0, tm.size - 1)]
        bad = (t < tm[0]) | (t > tm[-1]) | (hi - lo > 5 * dtm)
        m[bad] = np.nan
        raw_m[bad] = np.nan
    rate = (t.size - 1) / (t[-1] - t[0]) if t.size > 1 else float("nan")
    return Session(data.source, t, np.asarray(data.gyro, float), np.asarray(data.acc, float), raw_m,
                   np.asarray(data.temp, float), w, a, m, list(rests), float(rate), restamped, notes,
                   series_on_clock(data, t, restamped))


def smooth(x: Array, width: int) -> Array:
    """Centred moving average over ``width`` samples along axis 0 (edges use the shorter window)."""
    width = max(1, int(width) | 1)
    if width == 1:
        return x.copy()
    k = width // 2
    c = np.cumsum(np.concatenate([np.zeros((1,) + x.shape[1:]), x]), axis=0)
    n = x.shape[0]
    i = np.arange(n)
    lo = np.clip(i - k, 0, n)
    hi = np.clip(i + k + 1, 0, n)
    return (c[hi] - c[lo]) / (hi - lo).reshape((-1,) + (1,) * (x.ndim - 1))


def derivative(x: Array, t: Array, width: int) -> Array:
    """Time derivative of the moving-average-smoothed signal (central differences), unit/s."""
    return np.gradient(smooth(x, width), t, axis=0)


def prefix_products(R: Array) -> Array:
    """Cumulative products R[0] @ R[1] @ … @ R[k] for every k, (N, 3, 3), by a Hillis–Steele scan
    (log₂ N vectorised matmul passes instead of N sequential ones)."""
    P = R.copy()
    s = 1
    n = P.shape[0]
    while s < n:
        P[s:] = P[:-s] @ P[s:]
        s *= 2
    return P


def integrate_attitude(w: Array, t: Array) -> Array:
    """Attitude R(t) (world ← body, R(t₀) = I) from body rates by exact exponential steps
    R_{k+1} = R_k exp([ω̄_k Δt]ₓ) with ω̄ the trapezoid mean rate. (N, 3, 3)."""
    dt = np.diff(t)
    wm = 0.5 * (w[1:] + w[:-1])
    inc = rodrigues(wm * dt[:, None])
    R = np.empty((t.size, 3, 3))
    R[0] = np.eye(3)
    R[1:] = prefix_products(inc)
    return R


def noise_sigma(x: Array) -> Array:
    """Per-axis white-noise σ from the second differences (robust, MAD): the motion of a platform or a
    hand is smooth at the sample rate, so the second difference is noise, var = 6σ²."""
    d2 = x[2:] - 2 * x[1:-1] + x[:-2]
    d2 = d2[np.all(np.isfinite(d2), axis=1)]
    if d2.shape[0] < 10:
        return np.zeros(x.shape[1])
    mad = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0) * 1.4826
    return mad / np.sqrt(6.0)
