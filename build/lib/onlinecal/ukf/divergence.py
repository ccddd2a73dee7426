"""What the filter restarts from after a divergence (issue 16, item 4): a restart that does not repeat the
same failure.

Before, a divergence restarted every calibration state from the init calibration with the init's σ: a
wrong start (a batch result spoiled by bad data, a calibration of another unit) was re-imposed with the
same confidence, diverged again, and the run ended 100–40 000σ from the truth. Now (pure functions; the
filter calls :func:`plan_restart` and applies its answer):

1. a **widened prior**: the mean is the current estimate or the start (the prior the filter last started
   from), whichever the NIS history supports (:func:`start_supported`), and every σ is at least the cold
   prior's (:func:`cold_prior`), so that the data can pull the state away from a wrong mean;
2. a second divergence within ``ESCALATE_WINDOW_S`` of log time of the previous one: the **cold prior**
   (bias 0, scale 1, angles 0 with ``UKFConfig.cold_sigma``; the magnetometer is fitted from its raw
   samples again), what a start without any calibration uses.

A negative, NaN or infinite NIS (:func:`nis_failure`) is a numerical failure (the innovation covariance
was not positive definite): a divergence too, never a statistic that passes the gate. Each divergence is
one warning (:func:`announce`; the command line prints it as one stderr line) besides its event, and the
health verdict degrades on divergence events (:func:`onlinecal.health.event_checks`).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from ..model import PARAMS, SENSORS
from .config import UKFConfig
from .layout import DIP, N_STATE, SENSOR_SLICE

Array = NDArray[np.float64]

ESCALATE_WINDOW_S = 120.0  # s of log time: a second divergence this soon after one restarts from the cold prior
NIS_NEGATIVE_TOL = -1e-9  # a NIS below this (νᵀS⁻¹ν of a positive definite S is ≥ 0) is a numerical failure
FIRST_WINDOWS = 3  # NIS windows after a start that say whether the data agreed with it


class DivergenceWarning(UserWarning):
    """The online filter diverged and restarted (one per divergence)."""


@dataclass
class DivergenceLog:
    """Log times (s) of the divergences so far (for the escalation), kept across restarts."""

    times: list[float] = field(default_factory=list)

    @property
    def count(self) -> int:
        return len(self.times)


@dataclass(frozen=True)
class Restart:
    """Where the selected states restart: mean ``x`` and 1σ ``sigma`` (k,) each; ``kind`` "widened" or
    "cold"; ``source`` of the mean: "estimate", "start" or "cold"; ``detail`` in words for the event."""

    x: Array
    sigma: Array
    kind: Literal["widened", "cold"]
    source: Literal["estimate", "start", "cold"]
    detail: str


def nis_failure(nis: float) -> str | None:
    """Why a NIS (a float, dimensionless) shows a numerical failure, or None for a usable one.

    νᵀS⁻¹ν of a positive definite S is ≥ 0 and finite: a negative value (S indefinite), NaN or inf (S
    singular, see :func:`.unscented._block_nis`) is no statistic of the data, and would pass both the
    chi-square gate (``nis > gate`` is False) and the windowed divergence test."""
    if math.isnan(nis):
        return "NIS is NaN (numerical failure: innovation covariance not usable)"
    if math.isinf(nis):
        return "NIS is infinite (numerical failure: innovation covariance singular)"
    if nis < NIS_NEGATIVE_TOL:
        return f"NIS is negative ({nis:.3g}; numerical failure: innovation covariance not positive definite)"
    return None


def mag_alone(sensor: str | None, accel_stats: dict[str, Any]) -> bool:
    """Whether a divergence declared by ``sensor`` concerns the magnetometer alone: its NIS ran away while
    the accelerometer's windows were in order (``accel_stats``: the accel's NIS bookkeeping,
    :func:`.health.new_nis_stats`; no window above the divergence level in its current run). A wrong gyro
    scale turns the attitude, so both NIS grow: the magnetometer's may be declared first, but restarting it
    alone would leave the cause and spend the escalation on a second divergence of the accel."""
    return sensor == "mag" and int(accel_stats.get("bad_run", 0)) == 0


def restart_indices(consider: NDArray[np.bool_], mag: bool, mag_only: bool) -> NDArray[np.intp]:
    """Indices of the base states a restart sets: the calibration terms (not the attitude, extensions or
    hold offsets, which restart from their own priors) of every sensor, or, when the magnetometer's NIS
    alone ran away (``mag_only``), of the magnetometer, the dip and the gyro (the magnetometer checks the
    heading, which the gyro's terms integrate: a wrong gyro scale shows first in the magnetometer's NIS);
    the magnetometer's only when ``mag`` (it was calibrated: a cold one still waiting for its fit has
    nothing to restart); never the consider (gauge) states, held at their start. ``consider`` (n,) bool."""
    sensors = ("gyro", "mag") if mag_only else SENSORS
    parts = [np.arange(SENSOR_SLICE[s].start, SENSOR_SLICE[s].stop) for s in sensors if s != "mag" or mag]
    parts += [np.array([DIP])] if mag else []
    idx = np.concatenate(parts).astype(np.intp)
    return idx[~consider[idx]]


def cold_prior(config: UKFConfig, x: Array) -> tuple[Array, Array]:
    """Cold prior mean and σ (40,) of the base states, as a start without calibration has them (bias 0,
    scale 1, angles 0 ± ``config.cold_sigma``; dip 60° ± 30°), except that the magnetometer's bias and scale
    σ are taken relative to the raw field magnitude 1 / mean(scale) of the estimate ``x`` (n,) (the cold
    σ are relative to the field, as :func:`.state.prior` does for an init)."""
    x0 = np.zeros(N_STATE)
    sig = np.zeros(N_STATE)
    for s in SENSORS:
        sl = SENSOR_SLICE[s]
        x0[sl] = np.concatenate([np.zeros(3), np.ones(3), np.zeros(6)])
        sig[sl] = np.repeat([config.cold_sigma[s][p] for p in PARAMS], 3)
    sl = SENSOR_SLICE["mag"]
    k = float(np.mean(x[sl][3:6]))
    if math.isfinite(k) and k > 0:
        sig[sl.start : sl.start + 3] /= k
        sig[sl.start + 3 : sl.start + 6] *= k
    x0[DIP] = math.radians(60.0)
    sig[DIP] = math.radians(30.0)
    return x0, sig


def start_supported(windows: Sequence[Sequence[float]], band_hi: float, factor: float) -> bool:
    """Whether the NIS history supports the start over the current estimate: the first ``FIRST_WINDOWS``
    windows after the start (``windows``: [log time s, window mean NIS] of the sensors concerned, in time
    order) were mostly not far above the band (≤ ``factor`` × ``band_hi``, the divergence test's level).
    Then the data agreed with the start and the state went astray later (bad data, a numerical upset):
    the start is the better mean. Otherwise the start disagreed with the data from the outset: the
    estimate, which the data have pulled from it, is."""
    if not windows:
        return False
    first = sorted(windows, key=lambda w: w[0])[:FIRST_WINDOWS]
    good = sum(1 for w in first if 0.0 <= w[1] <= factor * band_hi)
    return 2 * good > len(first)


def plan_restart(log: DivergenceLog, t: float, x_est: Array, x_start: Array, sig_start: Array, x_cold: Array,
                 sig_cold: Array, windows: Sequence[Sequence[float]], band_hi: float, factor: float,
                 numeric: bool, cover: NDArray[np.bool_]) -> Restart:
    """The restart of the selected states after a divergence at log time ``t`` (s), recorded in ``log``.

    ``x_est`` the current estimate, ``x_start`` / ``sig_start`` the prior the filter last started from,
    ``x_cold`` / ``sig_cold`` the cold prior (:func:`cold_prior`), each (k,) for the same k states;
    ``windows`` the NIS windows since that start (:func:`start_supported`); ``numeric``: the divergence is
    a numerical failure (covariance not positive definite, non-finite state or NIS) rather than the data
    disagreeing with the state — the estimate is then kept as the mean when it is finite. ``cover`` (k,)
    bool: the states whose σ is also widened to reach their cold mean (not the magnetometer's)."""
    prev = log.times[-1] if log.times else None
    log.times.append(float(t))
    if prev is not None and 0.0 <= t - prev <= ESCALATE_WINDOW_S:
        return Restart(x_cold.copy(), sig_cold.copy(), "cold", "cold",
                       f"second divergence within {ESCALATE_WINDOW_S:.0f} s (the last at t = {prev:.1f} s): "
                       "restarted from the cold prior")
    sigma = np.maximum(np.where(np.isfinite(sig_start), sig_start, sig_cold), sig_cold)
    # wide enough to reach the cold prior's mean too (a start at gyro scale 0.5 is 2.5 cold σ from 1): the
    # magnetometer's cold mean (bias 0, scale 1 in raw units) is no value of its raw unit, and is left out
    gap = np.abs(np.where(np.isfinite(x_est), x_est, x_start) - x_cold)
    sigma = np.where(cover, np.maximum(sigma, np.where(np.isfinite(gap), gap, 0.0)), sigma)
    est_ok = bool(np.isfinite(x_est).all())
    if est_ok and (numeric or not start_supported(windows, band_hi, factor)):
        why = ("numerical failure: the estimate kept" if numeric else
               "the NIS disagreed with the start from the outset: restarted from the current estimate")
        return Restart(x_est.copy(), sigma, "widened", "estimate", f"{why}, σ widened to the cold prior's")
    why = ("the NIS agreed with the start before: restarted from the start" if est_ok else
           "the estimate is not finite: restarted from the start")
    return Restart(x_start.copy(), sigma, "widened", "start", f"{why}, σ widened to the cold prior's")


def announce(t: float, why: str, restart: Restart, mag_only: bool) -> None:
    """One warning per divergence (the command line shows each as one line on stderr)."""
    what = "magnetometer" if mag_only else "filter"
    warnings.warn(f"the online {what} diverged at t = {t:.1f} s ({why}); {restart.detail}",
                  DivergenceWarning, stacklevel=3)
