"""Attitude and magnetometer start of the online calibrator (:class:`.filter.OnlineCalibrator`).

The attitude starts from a block's mean accel (roll, pitch) and, once the magnetometer is usable, its field
(yaw, :func:`.attitude_init.attitude_start`); a cold magnetometer is collected and fitted
(:class:`.magstart.MagStart`, eq. 17) before it enters the filter. These functions read and set the
calibrator's state (x, P, R_nom, the mag start); the maths is in :mod:`.attitude_init` and :mod:`.magstart`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from .attitude_init import attitude_start
from .layout import ATT, DIP, SENSOR_SLICE, correction
from .magstart import mag_prior_from_raw
from .state import reset_states

if TYPE_CHECKING:
    from .filter import OnlineCalibrator

Array = NDArray[np.float64]


def calibrated(cal: OnlineCalibrator, sensor: str, raw: Array) -> Array:
    """``raw`` readings (..., 3) of ``sensor`` corrected with the current estimate (eqs. 1–6 inverted)."""
    o, M = correction(cal.x[None, SENSOR_SLICE[sensor]])
    out: Array = (raw - o[0]) @ M[0].T
    return out


def init_attitude(cal: OnlineCalibrator, a: Array, tm: Array, m: Array) -> None:
    """Attitude from the block's mean accel (roll, pitch) and, where the mag is usable, its field (yaw).

    The attitude comes from these very readings, so its error is a function of the accel (and mag)
    calibration error; rather than model that correlation, it starts with a σ wide enough that the
    missing correlation does not matter: the next updates re-derive the attitude properly."""
    c = cal.config
    if m.shape[0]:
        mag_collect(cal, tm, m)
    use_mag = cal._mag.enabled and m.shape[0] > 0
    h = calibrated(cal, "mag", m.mean(axis=0)) if use_mag else None
    cal.R_nom, P_att, dip = attitude_start(calibrated(cal, "accel", a.mean(axis=0)), h, float(cal.x[DIP]),
                                           cal._mag.dip_known, c.att_init_sigma, c.yaw_free_sigma)
    if dip is not None:
        set_dip(cal, dip)
    reset_states(cal.x, cal.P, ATT, 0.0, P_att)
    cal._att_ok = True
    cal._mag.yaw_free = not use_mag


def set_dip(cal: OnlineCalibrator, dip: float) -> None:
    reset_states(cal.x, cal.P, DIP, dip, cal.config.dip_sigma**2)
    cal._mag.dip_known = True


def mag_collect(cal: OnlineCalibrator, tm: Array, m: Array) -> None:
    cold = cal.init is None or cal.init.mag is None
    if cal._mag.collect(tm, m, cold, cal.config.mag_buffer_max):
        sl = SENSOR_SLICE["mag"]
        held = (cal.x[sl][6:], np.sqrt(np.diag(cal.P)[sl][6:])) if cal.gauge == "mag" else None
        pr = mag_prior_from_raw(m, cal.config.cold_sigma["mag"], held)
        if pr is not None:
            reset_states(cal.x, cal.P, sl, pr[0], np.diag(pr[1] ** 2))
            cal.prior_x[sl], cal.prior_sigma[sl] = pr


def mag_block(cal: OnlineCalibrator, tm: Array, m: Array, tl: float) -> tuple[bool, bool]:
    """The mag's part of a block (:class:`.magstart.MagStart`): collect and fit while cold, align the
    yaw after the fit. Returns whether the block's mag is used and whether the mag's state changed
    (which ends a rest)."""
    ms, c = cal._mag, cal.config
    before = (ms.enabled, ms.align_next)
    n_m = m.shape[0]
    if n_m and not ms.enabled:
        mag_collect(cal, tm, m)
        fit = ms.try_fit(tl, c)
        if fit is not None:
            sl = SENSOR_SLICE["mag"]
            reset_states(cal.x, cal.P, sl, fit.x, np.diag(fit.sigma**2))
            cal.prior_sigma[sl] = fit.prior_sigma
            cal.prior_x[sl] = cal.x[sl]
            cal._event("mag_cold_start", fit.detail, tl)
    if ms.enabled and ms.align_next and n_m:
        dip, cal.R_nom, cal.P = ms.align(cal.R_nom, cal.P, calibrated(cal, "mag", m.mean(axis=0)),
                                         c.att_init_sigma**2, ATT)
        set_dip(cal, dip)  # (the dip's rows do not enter the attitude block: the order does not matter)
    use_mag = ms.enabled and n_m > 0 and not ms.align_next
    return use_mag, before != (ms.enabled, ms.align_next)
