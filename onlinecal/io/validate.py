"""The input policy every reader shares: which samples are dropped, what is said about it, when a log is
unusable, and how a stream of parsed samples is cut into bounded blocks.

Readers parse their format into raw per-sensor arrays and hand them to a :class:`SampleFilter`, which
drops, per sensor (IMU = gyro+acc+temp, mag):

* samples with a non-finite time or a NaN/inf/missing gyro, acc or mag value,
* all-zero readings (gyro and acc all exactly 0, or mag all exactly 0): a dropped sensor read,
* samples whose time is not strictly greater than the last accepted one (repeats, steps back),
* with ``lookahead`` = W > 0 (the file readers: :data:`LOOKAHEAD`), samples stamped *ahead*: a sample is
  dropped when one of the next W samples lies between the last accepted time and its own time. It is
  then the one out of line (a corrupt stamp, a stretch of records moved in the file), and dropping it
  keeps the samples after it; without this, one stamp corrupted into the future would make every later
  sample "go backwards". So a run of fewer than W samples ahead of a clock that then carries on is
  dropped; a jump forward that the following samples continue from is a real gap and is kept. Before
  the first accepted sample there is no clock to carry on, so only a lone first sample is judged so
  (against the next one): a log starting 5 s, 6 s, 0.1 s, 0.2 s, ... is mostly backwards.

Temperature is optional: a non-finite temperature becomes NaN and never drops a sample. Gaps in time
are kept; with ``gaps=True`` they are counted and told (a silence longer than
max(:data:`GAP_MIN_S`, :data:`GAP_PERIODS` × the sensor's median sample period)). At the end of a log,
:meth:`SampleFilter.flush` releases the samples held back for the look-ahead and
:meth:`SampleFilter.finish` raises :class:`LogError` when there were no IMU samples at all or when more
than half of a sensor's samples were dropped.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from onlinecal.io.base import Array, ImuData, LogError

LOOKAHEAD = 16  # samples a file reader holds back to tell stamps ahead from a real jump
GAP_MIN_S = 1.0  # a silence shorter than this is never told as a gap
GAP_PERIODS = 50  # ... nor one shorter than this many median sample periods

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
    ahead: int = 0
    # Candidates (finite, non-zero) not yet decided, waiting for the look-ahead: times and rows.
    held_t: Array | None = None
    held_r: Array | None = None
    # Gaps: the median sample period (from the first 16 kept intervals) and what was found.
    period: float = float("nan")
    gaps: int = 0
    gap_total: float = 0.0
    gap_longest: float = 0.0
    gap_at: float = float("nan")

    @property
    def dropped(self) -> int:
        return self.nonfinite + self.zero + self.repeat + self.backward + self.ahead

    @property
    def n_held(self) -> int:
        return 0 if self.held_t is None else int(self.held_t.size)


class SampleFilter:
    """Applies the drop policy to one log's samples as they stream in, and words the warnings.

    ``unit`` is what one sample is called in sentences ("rows" for CSV, "messages" for MAVLink logs).
    ``lookahead`` > 0 holds back that many candidate samples per sensor so that a stamp ahead of the
    following samples can be told from a real jump (see the module doc); :meth:`flush` then releases
    them at the end. ``lookahead`` = 0 (a live link, where holding samples back adds latency) decides
    each sample on arrival. ``gaps`` tells silences in a warning.
    ``warnings`` is a live list: it is updated in place (never rebound) so a reader can hand the same
    list object to every block it yields and all of them end up with the final counts.
    """

    def __init__(self, path: str, unit: str = "rows", lookahead: int = 0, gaps: bool = False) -> None:
        self.path = str(path)
        self.unit = unit
        self.lookahead = int(lookahead)
        self.report_gaps = bool(gaps)
        self.imu_state = _SensorState("IMU")
        self.mag_state = _SensorState("mag")
        self.notes: list[str] = []  # reader-specific sentences (truncated line, ignored sources, ...)
        self.warnings: list[str] = []

    # -- per-sensor filtering ---------------------------------------------------------------------
    def imu(self, t: Array, gyro: Array, acc: Array, temp: Array) -> tuple[Array, Array, Array, Array]:
        """Filter IMU samples. t (N,) s, gyro (N, 3), acc (N, 3), temp (N,) → the rows decided as kept
        (with a look-ahead: possibly rows of earlier calls, and without the last ones of this call)."""
        t = np.asarray(t, np.float64).reshape(-1)
        gyro = np.asarray(gyro, np.float64).reshape(-1, 3)
        acc = np.asarray(acc, np.float64).reshape(-1, 3)
        temp = np.asarray(temp, np.float64).reshape(-1)
        temp = np.where(np.isfinite(temp), temp, np.nan)
        tk, rk = self._filter(self.imu_state, t, np.column_stack([gyro, acc, temp]), 6)
        self._update_warnings()
        return tk, rk[:, 0:3], rk[:, 3:6], rk[:, 6]

    def mag(self, t: Array, mag: Array) -> tuple[Array, Array]:
        """Filter mag samples. t (M,) s, mag (M, 3) → the rows decided as kept."""
        t = np.asarray(t, np.float64).reshape(-1)
        mag = np.asarray(mag, np.float64).reshape(-1, 3)
        tk, rk = self._filter(self.mag_state, t, mag, 3)
        self._update_warnings()
        return tk, rk

    def flush(self) -> tuple[tuple[Array, Array, Array, Array], tuple[Array, Array]]:
        """At the end of the log: decide the samples held back for the look-ahead; returns the kept
        (IMU arrays, mag arrays) as :meth:`imu` and :meth:`mag` do."""
        tk, rk = self._filter(self.imu_state, np.zeros(0), np.zeros((0, 7)), 6, final=True)
        tm, rm = self._filter(self.mag_state, np.zeros(0), np.zeros((0, 3)), 3, final=True)
        self._update_warnings()
        return (tk, rk[:, 0:3], rk[:, 3:6], rk[:, 6]), (tm, rm)

    def _filter(self, st: _SensorState, t: Array, rows: Array, ncheck: int,
                final: bool = False) -> tuple[Array, Array]:
        """t (n,), rows (n, k) whose first ``ncheck`` columns are the sensor values → kept (t, rows)."""
        n = t.shape[0]
        st.seen += n
        values = rows[:, :ncheck]
        finite = np.isfinite(t) & np.all(np.isfinite(values), axis=1)
        st.nonfinite += int(n - finite.sum())
        nonzero = np.any(values != 0.0, axis=1)
        st.zero += int(np.count_nonzero(finite & ~nonzero))
        ok = finite & nonzero
        if st.held_t is None:
            st.held_t, st.held_r = np.zeros(0), np.zeros((0, rows.shape[1]))
        T = np.concatenate([st.held_t, t[ok]])
        R = np.concatenate([st.held_r, rows[ok]])
        n_dec = T.size if final else max(0, T.size - self.lookahead)
        last = st.last_t
        keep = self._decide(st, T, n_dec)
        st.held_t, st.held_r = T[n_dec:], R[n_dec:]
        tk = T[:n_dec][keep]
        if self.report_gaps and tk.size:
            self._count_gaps(st, np.diff(tk, prepend=last) if np.isfinite(last) else np.diff(tk), tk)
        return tk, R[:n_dec][keep]

    def _decide(self, st: _SensorState, T: Array, n_dec: int) -> np.ndarray:
        """Which of the first ``n_dec`` candidate times T are kept; T[n_dec:] is look-ahead only.
        Updates the time counts and ``st.last_t``."""
        L = st.last_t
        if n_dec == 0:
            return np.zeros(0, bool)
        D = T[:n_dec]
        if np.all(np.diff(T, prepend=L) > 0):  # the common case: time increasing throughout
            st.last_t = float(D[-1])
            return np.ones(n_dec, bool)
        W = self.lookahead
        if W == 0:
            # Kept times are strictly increasing and a rejected time never exceeds the running maximum,
            # so "last kept" equals the running maximum of all earlier candidate times: vectorised.
            prev = np.maximum.accumulate(np.concatenate([[L], D]))[:-1]
            later = D > prev
            st.repeat += int(np.count_nonzero(D == prev))
            st.backward += int(np.count_nonzero(D < prev))
            st.last_t = max(L, float(D.max()))
            return later
        # With the look-ahead a decision depends on the last kept time, which depends on the decisions
        # before it: sequential. Only chunks where time does not increase get here (damaged data), and
        # the window test is vectorised to a "could be ahead" flag first.
        pad = np.concatenate([T[1:], np.full(W, np.inf)])
        later_min = np.lib.stride_tricks.sliding_window_view(pad, W)[:n_dec].min(axis=1)
        maybe_ahead = (later_min < D).tolist()
        Tl = T.tolist()
        keep = np.zeros(n_dec, bool)
        for i in range(n_dec):
            ti = Tl[i]
            if ti <= L:
                if ti == L:
                    st.repeat += 1
                else:
                    st.backward += 1
            elif maybe_ahead[i] and any(L < x < ti for x in Tl[i + 1:i + 1 + (W if L > -np.inf else 1)]):
                st.ahead += 1
            else:
                keep[i] = True
                L = ti
        st.last_t = L
        return keep

    @staticmethod
    def _count_gaps(st: _SensorState, dt: Array, tk: Array) -> None:
        """dt: intervals ending at the kept times tk (the first from the previous kept time, if any)."""
        if not np.isfinite(st.period) and dt.size >= 16:
            st.period = float(np.median(dt))
        limit = max(GAP_MIN_S, GAP_PERIODS * st.period) if np.isfinite(st.period) else GAP_MIN_S
        big = np.flatnonzero(dt > limit)
        if not big.size:
            return
        st.gaps += int(big.size)
        st.gap_total += float(dt[big].sum())
        k = int(big[np.argmax(dt[big])])
        if dt[k] > st.gap_longest:
            st.gap_longest = float(dt[k])
            st.gap_at = float(tk[k + tk.size - dt.size] - dt[k])  # dt[k] ends at that kept time

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
        if st.ahead:
            out.append(f"dropped {st.ahead} {st.name} {self.unit} stamped ahead of the samples after them "
                       f"(a lone jump forward in time)")
        if st.gaps:
            many = st.gaps > 1
            out.append(f"{st.name} time has {st.gaps} gap{'s' if many else ''} without samples "
                       f"({f'{st.gap_total:.3f} s in all, longest ' if many else ''}{st.gap_longest:.3f} s "
                       f"from t={st.gap_at:.3f} s); kept as {'gaps' if many else 'a gap'}")
        return out

    def _update_warnings(self) -> None:
        self.warnings[:] = self._sentences(self.imu_state) + self._sentences(self.mag_state) + self.notes

    def finish(self) -> None:
        """Raise LogError if the log as a whole is unusable (call once the whole log was seen and
        :meth:`flush` has released the held-back samples)."""
        imu = self.imu_state
        if imu.n_held or self.mag_state.n_held:
            raise RuntimeError("SampleFilter.finish() before flush(): samples still held back")
        if imu.seen == 0:
            raise LogError(self.path, "no IMU samples (gyro and accelerometer) in the log")
        for st in (imu, self.mag_state):
            if st.seen and 2 * st.dropped > st.seen:
                causes = {_NONFINITE: st.nonfinite, _ZERO: st.zero,
                          "time": st.repeat + st.backward + st.ahead}
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
