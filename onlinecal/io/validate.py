"""The input policy every reader shares: which samples are dropped, what is said about it, when a log is
unusable, and how a stream of parsed samples is cut into bounded blocks.

Readers parse their format into raw per-sensor arrays and hand them to a :class:`SampleFilter`, which
drops, per sensor (IMU = gyro+acc+temp, mag):

* samples with a non-finite time or a NaN/inf/missing gyro, acc or mag value,
* all-zero readings (gyro and acc all exactly 0, or mag all exactly 0): a dropped sensor read,
* samples whose time is not strictly greater than the last accepted one (repeats, steps back).

Temperature is optional: a non-finite temperature becomes NaN and never drops a sample. Gaps in time
are kept. At the end of a log, :meth:`SampleFilter.finish` raises :class:`LogError` when there were no
IMU samples at all or when more than half of a sensor's samples were dropped.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from onlinecal.io.base import Array, ImuData, LogError

# Reasons a sample is dropped (besides time not increasing), and how each is told.
_NONFINITE = "nonfinite"
_ZERO = "zero"

_PHRASE = {
    _NONFINITE: "with NaN, inf or missing values",
    _ZERO: "of all zeros (sensor dropout)",
}
_DOMINANT = {
    _NONFINITE: "NaN, inf or missing values",
    _ZERO: "all-zero readings (sensor dropout)",
    "time": "timestamps not increasing",
}


def check_file(path: str) -> None:
    """LogError unless ``path`` is a readable, non-empty regular file."""
    try:
        if os.path.isdir(path):
            raise IsADirectoryError(21, "is a directory")
        size = os.path.getsize(path)
        with open(path, "rb"):
            pass
    except OSError as e:
        raise LogError(path, f"cannot open: {e.strerror or e}") from None
    if size == 0:
        raise LogError(path, "empty file")


@dataclass
class _SensorState:
    name: str  # "IMU" or "mag", as it appears in sentences
    seen: int = 0
    last_t: float = -np.inf
    nonfinite: int = 0
    zero: int = 0
    repeat: int = 0
    backward: int = 0

    @property
    def dropped(self) -> int:
        return self.nonfinite + self.zero + self.repeat + self.backward


class SampleFilter:
    """Applies the drop policy to one log's samples as they stream in, and words the warnings.

    ``unit`` is what one sample is called in sentences ("rows" for CSV, "messages" for MAVLink logs).
    ``warnings`` is a live list: it is updated in place (never rebound) so a reader can hand the same
    list object to every block it yields and all of them end up with the final counts.
    """

    def __init__(self, path: str, unit: str = "rows") -> None:
        self.path = str(path)
        self.unit = unit
        self.imu_state = _SensorState("IMU")
        self.mag_state = _SensorState("mag")
        self.notes: list[str] = []  # reader-specific sentences (truncated line, ignored sources, ...)
        self.warnings: list[str] = []

    # -- per-sensor filtering ---------------------------------------------------------------------
    def imu(self, t: Array, gyro: Array, acc: Array, temp: Array) -> tuple[Array, Array, Array, Array]:
        """Filter IMU samples. t (N,) s, gyro (N, 3), acc (N, 3), temp (N,) → the kept rows."""
        t = np.asarray(t, np.float64).reshape(-1)
        gyro = np.asarray(gyro, np.float64).reshape(-1, 3)
        acc = np.asarray(acc, np.float64).reshape(-1, 3)
        temp = np.asarray(temp, np.float64).reshape(-1)
        values = np.concatenate([gyro, acc], axis=1)
        keep = self._filter(self.imu_state, t, values)
        temp = np.where(np.isfinite(temp), temp, np.nan)
        self._update_warnings()
        return t[keep], gyro[keep], acc[keep], temp[keep]

    def mag(self, t: Array, mag: Array) -> tuple[Array, Array]:
        """Filter mag samples. t (M,) s, mag (M, 3) → the kept rows."""
        t = np.asarray(t, np.float64).reshape(-1)
        mag = np.asarray(mag, np.float64).reshape(-1, 3)
        keep = self._filter(self.mag_state, t, mag)
        self._update_warnings()
        return t[keep], mag[keep]

    @staticmethod
    def _filter(st: _SensorState, t: Array, values: Array) -> Array:
        n = t.shape[0]
        st.seen += n
        if n == 0:
            return np.zeros(0, bool)
        finite = np.isfinite(t) & np.all(np.isfinite(values), axis=1)
        st.nonfinite += int(n - finite.sum())
        nonzero = np.any(values != 0.0, axis=1)
        zero = finite & ~nonzero
        st.zero += int(zero.sum())
        ok = finite & nonzero
        # A sample is kept when its time exceeds the last kept one. Kept times are strictly increasing
        # and a rejected time never exceeds the running maximum, so "last kept" equals the running
        # maximum of all earlier candidate times: one vectorised pass instead of a loop.
        tc = t[ok]
        if tc.size:
            prev = np.maximum.accumulate(np.concatenate([[st.last_t], tc]))[:-1]
            later = tc > prev
            st.repeat += int(np.count_nonzero(tc == prev))
            st.backward += int(np.count_nonzero(tc < prev))
            st.last_t = max(st.last_t, float(tc.max()))
            idx = np.flatnonzero(ok)
            ok[idx[~later]] = False
        return ok

    # -- sentences and the verdict ----------------------------------------------------------------
    def note(self, sentence: str) -> None:
        """Add a reader-specific warning sentence (once)."""
        if sentence not in self.notes:
            self.notes.append(sentence)
            self._update_warnings()

    def _sentences(self, st: _SensorState) -> list[str]:
        out = []
        for reason in (_ZERO, _NONFINITE):
            k = getattr(st, reason)
            if k:
                out.append(f"dropped {k} {st.name} {self.unit} {_PHRASE[reason]}")
        if st.repeat or st.backward:
            parts = [f"{st.repeat} repeated"] if st.repeat else []
            if st.backward:
                parts.append(f"{st.backward} going backwards")
            out.append(f"dropped {st.repeat + st.backward} {st.name} {self.unit} whose time did not "
                       f"increase ({', '.join(parts)})")
        return out

    def _update_warnings(self) -> None:
        self.warnings[:] = self._sentences(self.imu_state) + self._sentences(self.mag_state) + self.notes

    def finish(self) -> None:
        """Raise LogError if the log as a whole is unusable (call once the whole log was seen)."""
        imu = self.imu_state
        if imu.seen == 0:
            raise LogError(self.path, "no IMU samples (gyro and accelerometer) in the log")
        for st in (imu, self.mag_state):
            if st.seen and 2 * st.dropped > st.seen:
                causes = {_NONFINITE: st.nonfinite, _ZERO: st.zero, "time": st.repeat + st.backward}
                main = max(causes, key=lambda k: causes[k])
                raise LogError(
                    self.path,
                    f"{_DOMINANT[main]}: {st.dropped} of {st.seen} {st.name} {self.unit} unusable "
                    f"({'; '.join(self._sentences(st))})",
                )


class BlockAssembler:
    """Collects filtered samples and cuts them into ImuData blocks of at most ``max_samples`` IMU samples.

    A block carries the mag samples up to its last IMU time; mag samples after the last IMU sample of
    the log go into the final block. One full block is always held back until more data (or the end)
    arrives, so that final block exists. Memory is bounded by what the reader adds between pops.
    """

    def __init__(self, source: str, warnings: list[str], max_samples: int) -> None:
        if max_samples < 1:
            raise ValueError(f"max_samples must be >= 1, got {max_samples}")
        self.source = source
        self.warnings = warnings
        self.max_samples = int(max_samples)
        self._imu: list[tuple[Array, Array, Array, Array]] = []
        self._mag: list[tuple[Array, Array]] = []
        self._n_imu = 0

    def add(self, imu: tuple[Array, Array, Array, Array] | None = None,
            mag: tuple[Array, Array] | None = None) -> None:
        if imu is not None and imu[0].size:
            self._imu.append(imu)
            self._n_imu += imu[0].size
        if mag is not None and mag[0].size:
            self._mag.append(mag)

    def pop(self, final: bool = False) -> Iterator[ImuData]:
        """Yield the complete blocks (all remaining samples if ``final``)."""
        if self._n_imu <= self.max_samples and not final:
            return
        t = np.concatenate([b[0] for b in self._imu]) if self._imu else np.zeros(0)
        g = np.concatenate([b[1] for b in self._imu]).reshape(-1, 3) if self._imu else np.zeros((0, 3))
        a = np.concatenate([b[2] for b in self._imu]).reshape(-1, 3) if self._imu else np.zeros((0, 3))
        tp = np.concatenate([b[3] for b in self._imu]) if self._imu else np.zeros(0)
        tm = np.concatenate([b[0] for b in self._mag]) if self._mag else np.zeros(0)
        m = np.concatenate([b[1] for b in self._mag]).reshape(-1, 3) if self._mag else np.zeros((0, 3))
        n = t.size
        ms = self.max_samples
        i0 = j0 = 0
        # Full blocks while more than one block's worth remains (the rest waits for more data).
        while n - i0 > ms or (final and i0 < n):
            i1 = min(i0 + ms, n)
            last_block = final and i1 == n
            j1 = tm.size if last_block else int(np.searchsorted(tm, t[i1 - 1], side="right"))
            yield ImuData(t[i0:i1], g[i0:i1], a[i0:i1], tp[i0:i1], tm[j0:j1], m[j0:j1], self.source,
                          self.warnings)
            i0, j0 = i1, j1
        if final and n == 0 and tm.size:
            # Only mag samples left (the IMU-less case ends in LogError from finish() anyway).
            yield ImuData(t, g, a, tp, tm, m, self.source, self.warnings)
            j0 = tm.size
        self._imu = [(t[i0:], g[i0:], a[i0:], tp[i0:])] if i0 < n else []
        self._mag = [(tm[j0:], m[j0:])] if j0 < tm.size else []
        self._n_imu = n - i0
