"""Sample clocks the data support (issue 11): burst-read or jittered stamps replaced by a fitted clock.

Some loggers stamp samples when they read a buffer, not when the sensor sampled them: the MARG set's
MPU6050 at 100 Hz shows a median Δt of 0.9 ms and pauses of ~30 ms (and gaps to 0.37 s followed by a
catch-up burst). Integrating the gyro over such stamps (eq. 36) weighs samples wrongly, and the
magnetometer (its own clock) is matched to the wrong IMU sample. Where the median Δt is below half the
mean period, the stamps are replaced by a clock fitted to them: t_k = t₀ + k·T, one straight line per
stretch between real gaps (a pause longer than ``gap_s`` whose samples are not caught up, i.e. the line
through the samples after it does not continue the one before). The sensor's own rate is then the
inverse slope, and the stamps' scatter about the line is reported.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..io.base import ImuData

Array = NDArray[np.float64]


def is_burst_stamped(t: Array) -> bool:
    """True when the median Δt is below half the mean period (stamps are read times, not sample times)."""
    if t.size < 20 or t[-1] <= t[0]:
        return False
    dt = np.diff(t)
    return bool(np.median(dt) < 0.5 * (t[-1] - t[0]) / (t.size - 1))


def fitted_clock(t: Array, gap_s: float = 1.0) -> tuple[Array, float, int]:
    """A straight-line clock t₀ + k·T through the stamps, one line per stretch between pauses longer
    than ``gap_s``, where the samples after the pause are not caught up (the stamps after it run late of
    the line before by more than half the pause). Returns (clock (N,), stamp RMS scatter about it s,
    number of stretches)."""
    n = t.size
    k = np.arange(n, dtype=float)
    cuts = [0]
    for i in np.flatnonzero(np.diff(t) > gap_s) + 1:
        a = cuts[-1]
        if i - a < 20 or n - i < 20:
            continue
        p = np.polyfit(k[a:i], t[a:i], 1)
        # samples lost in the pause: the next stamps lie late of the earlier line by about the pause
        if np.median(t[i:i + 20] - np.polyval(p, k[i:i + 20])) > 0.5 * (t[i] - t[i - 1]):
            cuts.append(int(i))
    cuts.append(n)
    out = np.empty(n)
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        p = np.polyfit(k[a:b], t[a:b], 1) if b - a >= 2 else np.array([0.0, t[a]])
        out[a:b] = np.polyval(p, k[a:b])
    return out, float(np.sqrt(np.mean((t - out) ** 2))), len(cuts) - 1


def fitted_stamps(source: str, t_imu: Array, t_mag: Array) -> tuple[Array, Array, list[str]]:
    """The IMU and mag stamps of one log (:func:`regularise_clock`'s work on the bare arrays): each that is
    burst-read replaced by its fitted clock, with a sentence per replacement naming ``source``."""
    notes = []
    out = {"IMU": t_imu, "mag": t_mag}
    for name, t in (("IMU", t_imu), ("mag", t_mag)):
        if not is_burst_stamped(t):
            continue
        med = float(np.median(np.diff(t)))
        clk, rms, parts = fitted_clock(t)
        out[name] = clk
        notes.append(f"{source}: {name} time stamps are burst read times (median Δt {1e3 * med:.1f} ms, mean "
                     f"period {1e3 * (t[-1] - t[0]) / (t.size - 1):.1f} ms); a fitted sample clock is used "
                     f"(straight line in the sample index, {parts} stretch{'es' if parts > 1 else ''}; the stamps "
                     f"scatter {1e3 * rms:.1f} ms RMS about it)")
    return out["IMU"], out["mag"], notes


def regularise_clock(d: ImuData) -> tuple[ImuData, list[str]]:
    """``d`` with burst-read IMU and mag stamps replaced by fitted clocks, and a sentence saying so;
    unchanged (and no sentence) when the stamps are sample times."""
    t_imu, t_mag, notes = fitted_stamps(d.source, d.t_imu, d.t_mag)
    if not notes:
        return d, []
    return replace(d, t_imu=t_imu, t_mag=t_mag), notes


def regularise_for_filter(d: ImuData) -> tuple[ImuData, list[str]]:
    """:func:`regularise_clock` for the online filter, which cuts its blocks and integrates the gyro on the
    stamps: a log with clock segments (a reboot, a clock jump: ``ImuData.boundaries``) is left as it is, since
    one fitted line cannot span a jump."""
    if d.boundaries:
        return d, []
    return regularise_clock(d)


class ReclockedReader:
    """A streaming reader (:class:`~onlinecal.io.base.LogReader`) whose burst-read stamps are replaced by the
    fitted clocks of the whole log, as :func:`regularise_clock` does to a log read whole.

    The first block decides: stamps that are sample times (the usual case) stream through in one pass. Burst
    stamps cost a first pass over the log that keeps only the stamps (16 bytes a sample), then the blocks
    stream again with the fitted clock's stamps in place of the read times (``reader.blocks`` reads the file
    afresh on each call). A log with clock segments is left as it is (:func:`regularise_for_filter`).
    ``warnings``: the reader's, then the clock's sentences."""

    def __init__(self, reader: Any) -> None:
        self._reader = reader
        self.path: str = reader.path
        self.notes: list[str] = []

    @property
    def warnings(self) -> list[str]:
        return list(self._reader.warnings) + self.notes

    def blocks(self, max_samples: int = 4096) -> Iterator[ImuData]:
        it = self._reader.blocks(max_samples)
        first = next(it, None)
        if first is None:
            return
        if first.boundaries or not (is_burst_stamped(first.t_imu) or is_burst_stamped(first.t_mag)):
            yield first
            yield from it
            return
        del first
        it.close()
        ti: list[Array] = []
        tm: list[Array] = []
        segmented = False
        for b in self._reader.blocks(max_samples):
            ti.append(b.t_imu)
            tm.append(b.t_mag)
            segmented = segmented or bool(b.boundaries)
        if segmented:
            yield from self._reader.blocks(max_samples)
            return
        t_imu, t_mag, notes = fitted_stamps(self.path, np.concatenate(ti), np.concatenate(tm))
        del ti, tm
        self.notes = notes
        i = m = 0
        for b in self._reader.blocks(max_samples):
            ni, nm = b.t_imu.size, b.t_mag.size
            if i + ni > t_imu.size or m + nm > t_mag.size:
                raise RuntimeError(f"{self.path}: the log read differently on its second pass")
            yield replace(b, t_imu=t_imu[i : i + ni], t_mag=t_mag[m : m + nm])
            i, m = i + ni, m + nm
