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

* impossible readings, beyond any sensor's range or physics: |gyro| > :data:`GYRO_MAX` rad/s or
  |acc| > :data:`ACC_MAX` m/s² (50 g; a rail-clipped sample of a real part is far inside both and kept), or a
  magnetometer norm more than :data:`MAG_FACTOR` times the log's median norm (the unit of a magnetometer
  is the format's, so the test is relative; there is no lower limit: a hard-iron offset as large as the
  field legitimately brings the raw norm near 0). Counted in a warning (the command line prefixes
  every reader warning with its file).

Clock segments (file readers, ``lookahead`` > 0): a run of at least ``lookahead`` samples in increasing
order, all more than :data:`RESTART_BEHIND_S` behind the last accepted time, is a restarted clock (a vehicle
reboot), not a stretch of stray stamps, when it starts back near zero (under :data:`RESTART_FRACTION` of
the last stamp) after at least ``lookahead`` accepted samples: it and what follows are shifted onto the time line
:data:`SEGMENT_GAP_S` after the last accepted sample (the same shift for every sensor) and a *boundary* is
recorded (``SampleFilter.boundaries``, carried on ImuData). An IMU jump forward by more than
max(:data:`JUMP_MIN_S`, 10 × the longest gap seen before) is a boundary too (no shift needed). The block
assembler cuts blocks at boundaries and drops the mag samples that lie inside an IMU gap longer than
max(:data:`MAG_GAP_MIN_S`, 5 IMU periods): the attitude cannot be carried across such a gap, so those
samples are not used to update across it (counted in a warning).

Temperature is optional: a non-finite temperature becomes NaN and never drops a sample. Gaps in time
are kept; with ``gaps=True`` they are counted and told (a silence longer than
max(:data:`GAP_MIN_S`, :data:`GAP_PERIODS` × the sensor's median sample period)). At the end of a log,
:meth:`SampleFilter.flush` releases the samples held back for the look-ahead and
:meth:`SampleFilter.finish` raises :class:`LogError` when there were no IMU samples at all or when more
than half of a sensor's samples were dropped.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from onlinecal.io.base import Array, ImuData, LogError

LOOKAHEAD = 16  # samples a file reader holds back to tell stamps ahead from a real jump
GYRO_MAX = 50.0  # rad/s: no vehicle turns this fast (2.9e3 °/s; MEMS gyro ranges end at 35 rad/s)
ACC_MAX = 50.0 * 9.80665  # m/s²: 50 g; consumer IMU ranges end at 16-32 g
MAG_FACTOR = 10.0  # a raw magnetometer norm 10x the log's median is no field plus offset on Earth
RESTART_BEHIND_S = 1.0  # a run this far behind the last accepted time may be a restarted clock
RESTART_FRACTION = 0.25  # ... and back near zero: under this fraction of the last raw stamp
SEGMENT_GAP_S = 2.0  # where a restarted clock's samples are put: this long after the last accepted one
JUMP_MIN_S = 10.0  # an IMU jump forward shorter than this is a gap, never a clock segment
MAG_GAP_MIN_S = 0.5  # mag samples inside an IMU gap longer than this are not used (the UKF's max_gap_s)
GAP_MIN_S = 1.0  # a silence shorter than this is never told as a gap
GAP_PERIODS = 50  # ... nor one shorter than this many median sample periods

# Reasons a sample is dropped (besides time not increasing), and how each is told.
_NONFINITE = "nonfinite"
_ZERO = "zero"
_IMPOSSIBLE = "impossible"

_PHRASE = {
    _NONFINITE: "with NaN, inf or missing values",
    _ZERO: "of all zeros (sensor dropout)",
}
_DOMINANT = {
    _NONFINITE: "NaN, inf or missing values",
    _ZERO: "all-zero readings (sensor dropout)",
    _IMPOSSIBLE: "impossible readings (beyond any sensor's range)",
    "time": "timestamps not increasing",
}


PROBE_BYTES = 4 << 20  # a log whose first 4 MiB hold no valid record is refused without reading on


def check_file(path: str) -> None:
    """LogError unless ``path`` is a readable, non-empty regular file.

    Checked with ``stat`` before any ``open``: opening a FIFO would wait for a writer, and a device such as
    /dev/zero never ends."""
    try:
        st = os.stat(path)
        if stat.S_ISDIR(st.st_mode):
            raise IsADirectoryError(21, "is a directory")
        if not stat.S_ISREG(st.st_mode):
            kind = ("a FIFO (named pipe)" if stat.S_ISFIFO(st.st_mode) else "a device" if
                    stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode) else "a socket" if
                    stat.S_ISSOCK(st.st_mode) else "not a regular file")
            raise LogError(path, f"not a regular file ({kind}); a log must be a file")
        with open(path, "rb"):
            pass
    except OSError as e:
        raise LogError(path, f"cannot open: {e.strerror or e}") from None
    if st.st_size == 0:
        raise LogError(path, "empty file")


def probe_head(path: str, valid: Callable[[bytes], bool], problem: str) -> None:
    """LogError unless ``valid`` finds a record in the first :data:`PROBE_BYTES` of ``path``: a file of
    zeros or noise (a pre-allocated logger file, a wrong file) is refused in a fraction of a second
    instead of being scanned to its end. ``problem``: the message, where ``{span}`` becomes "its N bytes"
    or "its first 4 MiB"."""
    with open(path, "rb") as f:
        head = f.read(PROBE_BYTES)
    if not valid(head):
        size = os.path.getsize(path)
        span = f"its {size} bytes" if size <= PROBE_BYTES else f"its first {PROBE_BYTES >> 20} MiB"
        if not head.strip(b"\0"):
            span += " (all zero bytes)"
        raise LogError(path, problem.format(span=span))


@dataclass
class _SensorState:
    name: str  # "IMU" or "mag", as it appears in sentences
    seen: int = 0
    kept: int = 0
    last_t: float = -np.inf
    nonfinite: int = 0
    zero: int = 0
    impossible: int = 0
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
    # Clock segments: the shift in force (s, added to every time read) and the restarts applied.
    offset: float = 0.0
    restarts: int = 0
    mag_ref: float = float("nan")  # median magnetometer norm (the plausibility reference)
    examples: list[float] = field(default_factory=list)  # times of the first impossible samples

    @property
    def dropped(self) -> int:
        return self.nonfinite + self.zero + self.impossible + self.repeat + self.backward + self.ahead

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

    def __init__(self, path: str, unit: str = "rows", lookahead: int = 0, gaps: bool = False,
                 limits: bool = True) -> None:
        self.path = str(path)
        self.limits = bool(limits)  # the absolute gyro/acc limits (off when the user's scales set the units)
        self.unit = unit
        self.lookahead = int(lookahead)
        self.report_gaps = bool(gaps)
        self.imu_state = _SensorState("IMU")
        self.mag_state = _SensorState("mag")
        self.notes: list[str] = []  # reader-specific sentences (truncated line, ignored sources, ...)
        self.warnings: list[str] = []
        self.boundaries: list[dict[str, Any]] = []  # clock segments, live list (see the module doc)
        self._shifts: list[float] = []  # total time shift after the k-th restart, shared by the sensors

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
        bad = ok & ~self._plausible(st, values, ok)
        if bad.any():
            st.impossible += int(bad.sum())
            st.examples.extend(t[bad][: max(0, 3 - len(st.examples))].tolist())
            ok &= ~bad
        if st.held_t is None:
            st.held_t, st.held_r = np.zeros(0), np.zeros((0, rows.shape[1]))
        T = np.concatenate([st.held_t, t[ok] + st.offset])
        R = np.concatenate([st.held_r, rows[ok]])
        kept_t: list[Array] = []
        kept_r: list[Array] = []
        while True:
            last = st.last_t
            n_dec = T.size if final else max(0, T.size - self.lookahead)
            keep, restart = self._decide(st, T, n_dec)
            upto = n_dec if restart is None else restart
            tk, rk = T[:upto][keep], R[:upto][keep]
            if st is self.imu_state and self.lookahead and tk.size:
                self._jumps(st, tk, last)  # before the gaps count this very jump as one seen
            if self.report_gaps and tk.size:
                self._count_gaps(st, np.diff(tk, prepend=last) if np.isfinite(last) else np.diff(tk), tk)
            kept_t.append(tk)
            kept_r.append(rk)
            st.kept += int(tk.size)
            if restart is None:
                break
            T = T[restart:] + self._restart(st, float(T[restart]))
            R = R[restart:]
        st.held_t, st.held_r = T[n_dec:], R[n_dec:]
        return np.concatenate(kept_t), np.concatenate(kept_r)

    def _plausible(self, st: _SensorState, values: Array, ok: np.ndarray) -> np.ndarray:
        """Which rows are physically possible (see the module doc); only rows with ``ok`` are judged."""
        if st is self.imu_state:
            if not self.limits:
                return np.ones(values.shape[0], bool)
            g = np.linalg.norm(values[:, 0:3], axis=1)
            a = np.linalg.norm(values[:, 3:6], axis=1)
            return ~ok | ((g <= GYRO_MAX) & (a <= ACC_MAX))
        norm = np.linalg.norm(values, axis=1)
        ref = st.mag_ref
        if not np.isfinite(ref):
            cand = norm[ok]
            if cand.size < 5:
                return np.ones(values.shape[0], bool)
            ref = float(np.median(cand))
            if cand.size >= 16:
                st.mag_ref = ref
        if not ref > 0:
            return np.ones(values.shape[0], bool)
        return ~ok | (norm <= MAG_FACTOR * ref)

    def _restart(self, st: _SensorState, t_first: float) -> float:
        """A restarted clock seen by sensor ``st`` whose first new sample is at ``t_first`` (with the shift in
        force): the shift to add from here on. The first sensor to see the k-th restart decides the shift
        and records the boundary; the other sensor's k-th restart takes the same shift."""
        raw = t_first - st.offset
        if len(self._shifts) <= st.restarts:
            total = st.last_t + SEGMENT_GAP_S - raw
            self._shifts.append(total)
            self.boundaries.append({"t": st.last_t + SEGMENT_GAP_S / 2, "cause": "clock restart",
                                    "before_s": st.last_t - st.offset, "after_s": raw, "shift_s": total})
            self._update_warnings()
        total = self._shifts[st.restarts]
        delta = total - st.offset
        st.offset = total
        st.restarts += 1
        return delta

    def _jumps(self, st: _SensorState, tk: Array, last: float) -> None:
        """IMU jumps forward far beyond the gaps seen so far: clock segments (no shift needed)."""
        dt = np.diff(tk, prepend=last) if np.isfinite(last) else np.diff(tk)
        before = tk[tk.size - dt.size:] - dt
        limit = max(JUMP_MIN_S, 10.0 * st.gap_longest if np.isfinite(st.gap_longest) else 0.0)
        for k in np.flatnonzero(dt > limit):
            t0, t1 = float(before[k]), float(before[k] + dt[k])
            self.boundaries.append({"t": 0.5 * (t0 + t1), "cause": "clock jump", "before_s": t0 - st.offset,
                                    "after_s": t1 - st.offset, "shift_s": st.offset})
            self._update_warnings()

    def _decide(self, st: _SensorState, T: Array, n_dec: int) -> tuple[np.ndarray, int | None]:
        """Which of the first ``n_dec`` candidate times T are kept; T[n_dec:] is look-ahead only.
        Updates the time counts and ``st.last_t``. With a look-ahead, a restarted clock at index i < n_dec
        (see the module doc) ends the decision there: returns (keep for T[:i], i); else (keep, None)."""
        L = st.last_t
        if n_dec == 0:
            return np.zeros(0, bool), None
        D = T[:n_dec]
        if np.all(np.diff(T, prepend=L) > 0):  # the common case: time increasing throughout
            st.last_t = float(D[-1])
            return np.ones(n_dec, bool), None
        W = self.lookahead
        if W == 0:
            # Kept times are strictly increasing and a rejected time never exceeds the running maximum,
            # so "last kept" equals the running maximum of all earlier candidate times: vectorised.
            prev = np.maximum.accumulate(np.concatenate([[L], D]))[:-1]
            later = D > prev
            st.repeat += int(np.count_nonzero(D == prev))
            st.backward += int(np.count_nonzero(D < prev))
            st.last_t = max(L, float(D.max()))
            return later, None
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
            if (ti < L - RESTART_BEHIND_S and st.kept + int(keep[:i].sum()) >= self.lookahead
                    and self._restarts_here(Tl, i, L, st.offset, n_dec == T.size)):
                st.last_t = L
                return keep[:i], i
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
        return keep, None

    def _restarts_here(self, Tl: list[float], i: int, L: float, offset: float, final: bool) -> bool:
        """Does a restarted clock begin at Tl[i]: back near zero (its raw stamp under :data:`RESTART_FRACTION`
        of the last one), and the look-ahead window from it (all of it, or at the end of the log at least 2
        samples) strictly increasing and all far behind L? A smaller step back is a clock correction:
        its overlap is dropped as samples going backwards."""
        w = Tl[i:i + self.lookahead]
        if len(w) < (2 if final else self.lookahead):
            return False
        if not w[0] - offset < RESTART_FRACTION * (L - offset):
            return False
        return all(a < b for a, b in zip(w, w[1:], strict=False)) and w[-1] < L - RESTART_BEHIND_S

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

    def note_counted(self, key: str, template: str, count: int) -> None:
        """A sentence with a running count (``template`` has one ``{}``), replaced as the count grows."""
        if not hasattr(self, "_counted"):
            self._counted: dict[str, int] = {}
        sentence = template.format(count)
        if key in self._counted:
            self.notes[self._counted[key]] = sentence
        else:
            self._counted[key] = len(self.notes)
            self.notes.append(sentence)
        self._update_warnings()

    def _sentences(self, st: _SensorState) -> list[str]:
        out = []
        for reason in (_ZERO, _NONFINITE):
            k = getattr(st, reason)
            if k:
                out.append(f"dropped {k} {st.name} {self.unit} {_PHRASE[reason]}")
        if st.impossible:
            what = (f"|gyro| > {GYRO_MAX:g} rad/s or |acc| > {ACC_MAX / 9.80665:g} g" if st is self.imu_state
                    else f"norm over {MAG_FACTOR:g}x the median {st.mag_ref:.4g}")
            at = ", ".join(f"{x:.3f}" for x in st.examples)
            out.append(f"dropped {st.impossible} {st.name} {self.unit} with impossible values ({what}; first at "
                       f"t={at} s)")
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

    def _boundary_sentences(self) -> list[str]:
        out = []
        for b in self.boundaries:
            if b["cause"] == "clock restart":
                out.append(f"the log's clock restarted at t={b['before_s']:.3f} s (back to {b['after_s']:.3f} s: a "
                           f"reboot?): a new segment from t={b['t']:.3f} s on the shifted time line (attitude "
                           f"restarted, calibration carried over)")
            else:
                out.append(f"the log's clock jumped forward from t={b['before_s']:.3f} s to {b['after_s']:.3f} s: "
                           f"a new segment (attitude restarted, calibration carried over)")
        return out

    def _update_warnings(self) -> None:
        self.warnings[:] = (self._sentences(self.imu_state) + self._sentences(self.mag_state)
                            + self._boundary_sentences() + self.notes)

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
                causes = {_NONFINITE: st.nonfinite, _ZERO: st.zero, _IMPOSSIBLE: st.impossible,
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

    With ``filt`` (the reader's :class:`SampleFilter`): blocks are cut at its clock-segment boundaries (the
    block after one carries it in ``boundaries``), and mag samples inside an IMU gap longer than
    max(:data:`MAG_GAP_MIN_S`, 5 IMU periods) are dropped (counted in a warning): the attitude is not
    carried across such a gap, so they cannot update across it.
    """

    def __init__(self, source: str, warnings: list[str], max_samples: int, filt: SampleFilter | None = None) -> None:
        if max_samples < 1:
            raise ValueError(f"max_samples must be >= 1, got {max_samples}")
        self.source = source
        self.warnings = warnings
        self.max_samples = int(max_samples)
        self.filt = filt
        self._imu: list[tuple[Array, Array, Array, Array]] = []
        self._mag: list[tuple[Array, Array]] = []
        self._n_imu = 0
        self._last_t = -np.inf  # last IMU time handed on
        self._mag_in_gap = 0
        self._gap_limit = MAG_GAP_MIN_S
        self.params: dict[str, float] = {}  # copied onto every block (the reader fills it when it knows them)
        self.series: dict[str, tuple[Array, Array]] = {}  # put on the final block only

    def add(self, imu: tuple[Array, Array, Array, Array] | None = None,
            mag: tuple[Array, Array] | None = None) -> None:
        if imu is not None and imu[0].size:
            self._imu.append(imu)
            self._n_imu += imu[0].size
        if mag is not None and mag[0].size:
            self._mag.append(mag)

    def _mag_keep(self, t_ext: Array, tm: Array) -> np.ndarray:
        """Mask of the mag times ``tm`` not inside an IMU gap (t_ext: the IMU times around them, in order)."""
        if self.filt is None or not tm.size or t_ext.size < 2:
            return np.ones(tm.size, bool)
        period = self.filt.imu_state.period
        if np.isfinite(period):
            self._gap_limit = max(MAG_GAP_MIN_S, 5.0 * period)
        k = np.searchsorted(t_ext, tm, side="right")
        inside = (k > 0) & (k < t_ext.size)
        kk = np.clip(k, 1, t_ext.size - 1)
        gap = t_ext[kk] - t_ext[kk - 1]
        drop = inside & (gap > self._gap_limit) & (tm > t_ext[kk - 1])  # strictly inside: an end is IMU time
        if drop.any():
            self._mag_in_gap += int(drop.sum())
            self.filt.note_counted("mag_in_gap", f"dropped {{}} mag samples inside IMU gaps longer than "
                                   f"{self._gap_limit:.3g} s (not used to update across the gap)", self._mag_in_gap)
        return ~drop

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
        cuts = sorted(float(b["t"]) for b in self.filt.boundaries) if self.filt is not None else []
        bounds = list(self.filt.boundaries) if self.filt is not None else []
        n = t.size
        ms = self.max_samples
        i0 = j0 = 0
        # Full blocks while more than one block's worth remains (the rest waits for more data).
        while n - i0 > ms or (final and i0 < n):
            i1 = min(i0 + ms, n)
            # A boundary after this block's first sample ends the block before it.
            inner = [c for c in cuts if t[i0] < c <= t[i1 - 1]]
            if inner:
                i1 = int(np.searchsorted(t, inner[0]))
            last_block = final and i1 == n
            if last_block:
                j1 = tm.size
            elif inner:
                j1 = int(np.searchsorted(tm, inner[0]))
            else:
                j1 = int(np.searchsorted(tm, t[i1 - 1], side="right"))
            starts = [b for b in bounds if self._last_t < b["t"] <= t[i0]]
            t_ext = np.concatenate([[self._last_t], t[i0:min(i1 + 1, n)]]) if np.isfinite(self._last_t) \
                else t[i0:min(i1 + 1, n)]
            keep = self._mag_keep(t_ext, tm[j0:j1])
            yield ImuData(t[i0:i1], g[i0:i1], a[i0:i1], tp[i0:i1], tm[j0:j1][keep], m[j0:j1][keep], self.source,
                          self.warnings, [dict(b) for b in starts], self.params,
                          self.series if last_block else {})
            self._last_t = float(t[i1 - 1])
            i0, j0 = i1, j1
        if final and n == 0 and (tm.size or self.series):
            # Only mag samples left (the IMU-less case ends in LogError from finish() anyway).
            yield ImuData(t, g, a, tp, tm, m, self.source, self.warnings, [], self.params, self.series)
            j0 = tm.size
        self._imu = [(t[i0:], g[i0:], a[i0:], tp[i0:])] if i0 < n else []
        self._mag = [(tm[j0:], m[j0:])] if j0 < tm.size else []
        self._n_imu = n - i0
