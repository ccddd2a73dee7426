"""Model extensions for ``replay`` and ``run``: a calibration JSON's ``extensions`` (written by ``diagnose``)
applied to the raw data before the UKF sees it, through :func:`onlinecal.extensions.correct` (the inverse of
each effect, Zhang et al. 2014 eq. 1 extended in front of the paper's ``matrix @ (raw − bias)``).

* replay (:func:`prepare`): each whole log is corrected (time offsets resampled, ω̇ from the whole log);
* run (:class:`BlockCorrector`): live blocks arrive ~0.25 s at a time and cannot be resampled cheaply, so
  only the pointwise extensions are applied per block (mag_current is not: the link carries no current or
  throttle series; it is named in the notes, :data:`NOT_LIVE`) — temperature_bias, g_sensitivity,
  scale_nonlinearity, axis_sign, lever_arm (its ω̇ is a Savitzky–Golay derivative within the block, less
  accurate within 0.05 s of the block's ends) and a magnetometer time_offset (a re-stamp); a gyro or
  accelerometer time_offset is refused (:func:`check_live`).

Two extensions do not change the data: bias_drift (a process-noise density, see
:func:`onlinecal.extensions.process_noise`) and saturation (the UKF's own rail detector skips clipped
samples); both are named in the notes.
"""

from __future__ import annotations

from typing import Any, cast

import numpy as np

from .effect_registry import LIVE_POINTWISE, NOT_REMOVABLE  # noqa: F401  (LIVE_POINTWISE re-exported)
from .extensions import correct, validate_extensions
from .io.base import ImuData
from .model import Calibration

NOT_APPLIED = {
    "bias_drift": "bias_drift is a process-noise density for the bias states, not a correction of the data "
                  "(the UKF's own bias random walk applies)",
    "saturation": "saturation is not corrected: the UKF's rail detector skips clipped samples",
}
assert tuple(NOT_APPLIED) == NOT_REMOVABLE
# extensions that need a series a live link does not carry: reported, and the live blocks left as they are
NOT_LIVE = {
    "mag_current": "mag_current is not applied to live blocks: the link carries no battery current or throttle "
                   "series to remove the interference with (replay a log with BAT/CTUN to apply it)",
}


def _ext(cal: Calibration) -> dict[str, Any]:
    """``cal.extensions`` as the dict it is at run time (a frozen ``dict`` subclass; typed ``Mapping``)."""
    return cast(dict[str, Any], cal.extensions)


def _applied(ext: dict[str, list[dict[str, Any]]]) -> list[str]:
    return [n for n in ext if n not in NOT_APPLIED]


def prepare(logs: list[ImuData], cal: Calibration | None) -> tuple[list[ImuData], list[str]]:
    """Apply ``cal.extensions`` to every log (whole-log :func:`~onlinecal.extensions.correct`).

    Returns the corrected logs (the inputs unchanged when there are no extensions) and one note per
    applied or skipped extension. Raises ValueError naming the log and the problem (e.g. a
    temperature_bias extension on a log without a temperature column, a mag_current extension on a log
    without its current or throttle series: ``remove_mag_current`` needs x at every magnetometer sample).
    """
    if cal is None or not cal.extensions:
        return list(logs), []
    ext = validate_extensions(_ext(cal))
    notes = [NOT_APPLIED[n] for n in ext if n in NOT_APPLIED]
    todo = _applied(ext)
    if not todo:
        return list(logs), notes
    out = []
    for d in logs:
        try:
            out.append(correct(d, _ext(cal), calibration=cal))
        except ValueError as e:
            raise ValueError(f"{d.source or 'log'}: {e}") from None
    notes.insert(0, f"extensions applied to the raw data before the filter: {', '.join(todo)}")
    return out, notes


def check_live(cal: Calibration | None) -> list[str]:
    """Which extensions a live run can apply per block; raises ValueError for a gyro or accelerometer
    time_offset (a live block cannot be resampled at shifted instants without holding data back)."""
    if cal is None or not cal.extensions:
        return []
    ext = validate_extensions(_ext(cal))
    for e in ext.get("time_offset", []):
        if e["sensor"] != "mag":
            raise ValueError(f"the {e['sensor']} time_offset extension ({e['seconds']:g} s) cannot be applied to "
                             "live blocks (it needs resampling over the whole log); use replay on a recorded log, "
                             "or an --init calibration without it")
    notes = [NOT_APPLIED[n] for n in ext if n in NOT_APPLIED] + [NOT_LIVE[n] for n in ext if n in NOT_LIVE]
    todo = [n for n in _applied(ext) if n not in NOT_LIVE]
    if todo:
        notes.insert(0, f"extensions applied per live block: {', '.join(todo)}"
                     + (" (lever_arm: ω̇ within each block, approximate at its ends)" if "lever_arm" in ext else ""))
    return notes


class BlockCorrector:
    """Per-block correction for live runs (see the module docstring); ``__call__(block) -> block``.

    A block without temperature readings keeps its raw values for temperature_bias (counted in
    ``skipped_temperature``) rather than stopping the run; an empty IMU block only has its mag re-stamped, and a
    one-sample block skips lever_arm (no derivative).
    """

    def __init__(self, cal: Calibration) -> None:
        check_live(cal)
        self.cal = cal
        self.ext = {k: v for k, v in cal.extensions.items() if k not in NOT_LIVE}
        self._no_temp = {k: v for k, v in self.ext.items() if k != "temperature_bias"}
        self._mag_only = {k: v for k, v in self.ext.items() if k == "time_offset"}
        self.skipped_temperature = 0

    def __call__(self, block: ImuData) -> ImuData:
        if not self.ext:
            return block
        if block.n_imu == 0:
            return correct(block, self._mag_only) if self._mag_only and block.n_mag else block
        ext = self.ext
        if "temperature_bias" in ext and not np.isfinite(np.asarray(block.temp, float)).any():
            self.skipped_temperature += 1
            ext = self._no_temp
        if block.n_imu < 2 and "lever_arm" in ext:  # no derivative from one sample
            ext = {k: v for k, v in ext.items() if k != "lever_arm"}
        return correct(block, ext, calibration=self.cal)


def live_transform(cal: Calibration | None) -> BlockCorrector | None:
    """The per-block correction ``run_live(..., transform=...)`` applies for ``cal``'s extensions, or None when
    none of them changes the data. Raises ValueError as :func:`check_live`."""
    check_live(cal)
    if cal is None or not [n for n in _applied(validate_extensions(_ext(cal))) if n not in NOT_LIVE]:
        return None
    return BlockCorrector(cal)
