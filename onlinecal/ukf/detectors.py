"""Detectors that run on the raw data alone: the value lattice of a log, the ADC rail, rests, held readings.

Each detector keeps its own small state (a dataclass, so the checkpoint saves it field by field) and returns
flags and events; the filter decides what to do with them. They read the block statistics of
:mod:`.blocks`, never the filter state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ..specs import RAIL_SAMPLES, RAIL_TOL

if TYPE_CHECKING:
    from .blocks import Blocks

Array = NDArray[np.float64]


def value_lattice(v: Array) -> float:
    """The quantum q of a sensor's values when every value is an integer multiple of it, else 0.

    v (N, 3) raw readings. q is the smallest step between distinct values on any axis; it counts only
    if all values are multiples of it to 1e-6 (floats from integer counts times a unit factor are).
    """
    v = v[np.all(np.isfinite(v), axis=1)]
    if v.shape[0] < 8:
        return 0.0
    steps = np.concatenate([np.diff(np.unique(v[:, k])) for k in range(3)])
    steps = steps[steps > 0]
    if not steps.size:
        return 0.0
    q = float(steps.min())
    if q <= 1e-9 * max(float(np.abs(v).max()), 1e-300):
        return 0.0
    k = v / q
    return q if float(np.max(np.abs(k - np.round(k)))) < 1e-6 else 0.0


def _runs(col: Array, carry: tuple[float, int] | None) -> tuple[Array, Array]:
    """Starts and lengths of the runs of identical values in col (N,); the first run continues ``carry``
    (value, length) from the previous block when the value is the same."""
    starts = np.concatenate([[0], np.flatnonzero(col[1:] != col[:-1]) + 1])
    lens = np.diff(np.concatenate([starts, [col.size]]))
    if carry is not None and col[0] == carry[0]:
        lens[0] += carry[1]
    return starts, lens


def _saturation_event(s: str, rail: list[float]) -> tuple[str, str]:
    """The event at the start of a clipped stretch of sensor ``s`` with its learnt rail (3,)."""
    what = "attitude restarted, the block's updates skipped" if s == "gyro" else "its update skipped while clipped"
    return "saturation", f"{s} at its rail ±{np.round(rail, 4).tolist()}: {what}"


def _short_block_runs(v: Array, carry: list[tuple[float, int]] | None, rail_run: int, rail_min: float
                      ) -> tuple[list[tuple[float, int]], list[tuple[int, float]]]:
    """:func:`_runs` for the three axes of a block v (L, 3), 2 ≤ L < ``rail_run``, in one pass of numpy
    (issue 15: 1.2 µs per IMU sample in three passes of the per-axis runs). A run inside such a block is
    shorter than ``rail_run``, so only the first, continuing the carry (value, length) per axis, can reach
    it, and it is then the longest (the one the per-axis rule looks at). Returns the new carry per axis
    (last value, length of the last run) and the axes (k, |value|) whose first run is a rail: ``rail_run``
    long and at least ``rail_min`` in magnitude — the per-axis rule's decisions."""
    L = v.shape[0]
    ch = v[1:] != v[:-1]  # (L - 1, 3): where a new run starts (NaN ≠ NaN, as in _runs)
    anych = ch.any(axis=0).tolist()
    first = (ch.argmax(axis=0) + 1).tolist()
    last = (ch[::-1].argmax(axis=0) + 1).tolist()
    v0, v1 = v[0].tolist(), v[-1].tolist()
    new_carry, axes = [], []
    for k in range(3):
        f = first[k] if anych[k] else L
        if carry is not None and v0[k] == carry[k][0]:
            f += carry[k][1]
        new_carry.append((float(v1[k]), last[k] if anych[k] else f))
        if f >= rail_run and abs(float(v0[k])) >= rail_min:
            axes.append((k, abs(float(v0[k]))))
    return new_carry, axes


def block_runs(v: Array, lo: NDArray[np.intp], hi: NDArray[np.intp]) -> NDArray[np.intp]:
    """Per block [lo[b], hi[b]) of v (N, 3) and axis, where its first and last runs of identical values end
    (the rows of :func:`_short_block_runs`, for all blocks of a feed at once; issue 15): (n_b, 2, 3) —
    [b, 0, k] the length of the first run (L where the block holds one value), [b, 1, k] that of the last
    (−1 where the block holds one value). NaN ≠ NaN, as in :func:`_runs`."""
    nb = lo.shape[0]
    out = np.empty((nb, 2, 3), np.intp)
    L = hi - lo
    if nb == 0:
        return out
    s0, end = int(lo[0]), int(hi[-1])
    ch = v[s0 + 1 : end] != v[s0 : end - 1]  # ch[p − s0]: a new run starts at sample p + 1
    for k in range(3):
        P = np.flatnonzero(ch[:, k]) + s0
        i1 = np.searchsorted(P, lo, side="left")  # the first change at or after lo
        f_ok = i1 < P.size
        f_ok[f_ok] = P[i1[f_ok]] <= hi[f_ok] - 2
        out[:, 0, k] = np.where(f_ok, P[np.minimum(i1, max(P.size - 1, 0))] - lo + 1 if P.size else 0, L)
        i2 = np.searchsorted(P, hi - 1, side="left") - 1  # the last change at or before hi − 2
        l_ok = i2 >= 0
        l_ok[l_ok] = P[i2[l_ok]] >= lo[l_ok]
        out[:, 1, k] = np.where(l_ok, hi - 1 - P[np.maximum(i2, 0)] if P.size else 0, -1)
    return out


def _short_runs_given(runs: NDArray[np.intp], v0: list[float], v1: list[float], L: int,
                      carry: list[tuple[float, int]] | None, rail_run: int, rail_min: float
                      ) -> tuple[list[tuple[float, int]], list[tuple[int, float]]]:
    """:func:`_short_block_runs` from the block's precomputed :func:`block_runs` row ``runs`` (2, 3), its
    first and last readings v0, v1 (3 Python floats each) and its length L: the same carry and axes."""
    first, last = runs[0].tolist(), runs[1].tolist()
    new_carry, axes = [], []
    for k in range(3):
        f = first[k]
        if carry is not None and v0[k] == carry[k][0]:
            f += carry[k][1]
        new_carry.append((float(v1[k]), last[k] if last[k] >= 0 else f))
        if f >= rail_run and abs(float(v0[k])) >= rail_min:
            axes.append((k, abs(float(v0[k]))))
    return new_carry, axes


@dataclass
class RailDetector:
    """The ADC rail of gyro and accel, learnt from the data. A rail is ``rail_run`` identical readings in a
    row (runs carry over block boundaries) at a magnitude of at least ``rail_min``: noise makes a reading
    that is not clipped change within a few samples. Once learnt, any reading at the rail counts as
    clipped. State: the learnt rail per sensor and axis, the open runs, whether a clipped stretch is on.

    A rail is also learnt the batch's way (:func:`onlinecal.specs.rail_samples`), causally: an axis whose largest
    magnitude so far, above ``rail_min``, has recurred within :data:`~onlinecal.specs.RAIL_TOL` in
    :data:`~onlinecal.specs.RAIL_SAMPLES` samples (:meth:`_top_block`; state ``top``, ``n_top``). A hand that
    tumbles a ±250 °/s gyro past its range clips it in short stretches — MARG's tilt-sphere: 271 samples at the rail
    in 32 stretches, none 40 long — which the run rule never learnt: the clipped readings went into the filter as
    rates, the lost rotation into the gyro scale (x 1.042 ± 0.001 on that file alone, session 16)."""

    rail: dict[str, list[float]] = field(default_factory=dict)
    run: dict[str, list[tuple[float, int]]] = field(default_factory=dict)
    clip_on: dict[str, bool] = field(default_factory=lambda: {"gyro": False, "accel": False, "mag": False})
    top: dict[str, list[float]] = field(default_factory=dict)
    n_top: dict[str, list[int]] = field(default_factory=dict)

    def _top_block(self, s: str, v: Array, am: list[float], rail_min: float) -> list[tuple[int, float]]:
        """The recurring-top rule for one block of sensor ``s`` (v (L, 3) raw, ``am`` its largest |reading| per
        axis as Python floats): per axis the running largest magnitude ``top`` and the samples within RAIL_TOL
        of it ``n_top`` (from when the top last rose beyond the tolerance; counted only above ``rail_min``).
        Returns the axes whose rail this block makes known: (axis, rail = top·(1 − RAIL_TOL), both signs).
        A block below its axes' top·(1 − RAIL_TOL) changes nothing (the vectorised screen of :meth:`prepass`
        relies on it)."""
        top = self.top.setdefault(s, [0.0, 0.0, 0.0])
        cnt = self.n_top.setdefault(s, [0, 0, 0])
        rail = self.rail.get(s)
        out = []
        for k in range(3):
            x = am[k]
            if not x >= top[k] * (1.0 - RAIL_TOL):  # (NaN: nothing)
                continue
            new = max(top[k], x)
            lim = new * (1.0 - RAIL_TOL)
            if lim > top[k]:  # the top rose beyond the tolerance: the earlier samples are not at it
                cnt[k] = 0
            top[k] = new
            if x >= rail_min:
                cnt[k] += int(np.count_nonzero(np.abs(v[:, k]) >= lim))
                if cnt[k] >= RAIL_SAMPLES and (rail is None or not rail[k] <= lim):
                    out.append((k, lim))
        return out

    def check(self, w: Array, a: Array, w_absmax: Array, a_absmax: Array, rail_min: dict[str, float],
              rail_run: int, runs: tuple[NDArray[np.intp], NDArray[np.intp]] | None = None
              ) -> tuple[dict[str, bool], list[tuple[str, str]]]:
        """Which sensors read at their rail in this block (w, a (L, 3) raw; ``*_absmax`` (3,) the block's
        largest |reading| per axis), and the events (kind, detail) at the start of a clipped stretch.
        ``runs``: the block's :func:`block_runs` rows (2, 3) for w and a, computed over the feed (the same
        decisions as from w and a; issue 15)."""
        out = {"mag": False}
        events: list[tuple[str, str]] = []
        for s, v, amax, rr in (("gyro", w, w_absmax, None if runs is None else runs[0]),
                               ("accel", a, a_absmax, None if runs is None else runs[1])):
            rail = self.rail.get(s)
            am = amax.tolist()  # Python floats: the same comparisons (a NaN fails each, as np.any/np.max's)
            hit = rail is not None and any(x >= r * (1 - 1e-9) for x, r in zip(am, rail, strict=True))
            for k, val in self._top_block(s, v, am, rail_min[s]):
                r = self.rail.setdefault(s, [math.inf] * 3)
                r[k] = min(r[k], val)
                hit = True
            if _all_below(am, rail_min[s]):
                self.run.pop(s, None)
            else:
                carry = self.run.get(s)
                if 1 < v.shape[0] < rail_run:  # the usual block: only the run continuing the carry can be a rail
                    if rr is not None:
                        self.run[s], axes = _short_runs_given(rr, v[0].tolist(), v[-1].tolist(), v.shape[0], carry,
                                                              rail_run, rail_min[s])
                    else:
                        self.run[s], axes = _short_block_runs(v, carry, rail_run, rail_min[s])
                    for k, val in axes:
                        r = self.rail.setdefault(s, [math.inf] * 3)
                        r[k] = min(r[k], val)
                        hit = True
                    if hit and not self.clip_on[s]:
                        events.append(_saturation_event(s, self.rail[s]))
                    self.clip_on[s] = hit
                    out[s] = hit
                    continue
                new_carry = []
                for k in range(3):
                    col = v[:, k]
                    starts, lens = _runs(col, None if carry is None else carry[k])
                    new_carry.append((float(col[-1]), int(lens[-1])))
                    i = int(np.argmax(lens))
                    val = abs(float(col[starts[i]]))
                    if lens[i] >= rail_run and val >= rail_min[s]:
                        r = self.rail.setdefault(s, [math.inf] * 3)
                        r[k] = min(r[k], val)
                        hit = True
                self.run[s] = new_carry
            if hit and not self.clip_on[s]:
                events.append(_saturation_event(s, self.rail[s]))
            self.clip_on[s] = hit
            out[s] = hit
        return out, events


    def prepass(self, B: Blocks, w: Array, a: Array, rail_min: dict[str, float], rail_run: int
                ) -> tuple[list[bool], list[bool], dict[int, list[tuple[str, str]]]] | None:
        """:meth:`check` for every block of ``B`` at once (the buffers w, a (N, 3) raw), in one compiled call per
        sensor (:func:`.kernels_detectors.rail_pass_kernel`; issue 15), where every block is a usual one
        (1 < L < ``rail_run``; else None and nothing is changed: the caller checks block by block). Returns the
        gyro's and the accel's clip flag per block and the events per block index; the detector's state is
        that after the last block (the blocks are then filtered in order, each taking its row)."""
        L = B.hi - B.lo
        if not L.size or not bool(((L > 1) & (L < rail_run)).all()):
            return None
        from .kernels_detectors import rail_pass_kernel

        hits: list[list[bool]] = []
        events: dict[int, list[tuple[str, str]]] = {}
        lo, hi = B.lo, B.hi
        for s, v, amax, rr in (("gyro", w, B.w_absmax, B.w_runs), ("accel", a, B.a_absmax, B.a_runs)):
            am = np.ascontiguousarray(amax)
            # the recurring-top rule (:meth:`_top_block`) on the blocks that reach their axis' running top (the
            # top before each block: fmax ignores NaN, as the rule does); the others change nothing
            top0 = np.array(self.top.get(s, [0.0, 0.0, 0.0]))
            before = np.fmax.accumulate(np.vstack([top0[None, :], am]), axis=0)[:-1]
            learn: dict[int, list[tuple[int, float]]] = {}
            for b in np.flatnonzero((am >= before * (1.0 - RAIL_TOL)).any(axis=1)).tolist():
                got = self._top_block(s, v[lo[b] : hi[b]], am[b].tolist(), float(rail_min[s]))
                if got:
                    learn[b] = got
            learnt = s in self.rail
            rail = np.array(self.rail[s] if learnt else [math.inf] * 3, dtype=float)
            carry = self.run.get(s)
            cv = np.array([c[0] for c in carry] if carry is not None else [0.0] * 3, dtype=float)
            cn = np.array([c[1] for c in carry] if carry is not None else [0] * 3, dtype=np.intp)
            has_carry, clip_on = carry is not None, self.clip_on[s]
            hit_all: list[bool] = []
            # one call over the feed; where the top rule learns a rail, the call stops after that block and the
            # rail joins before the next (at most once per axis in a log)
            b0 = 0
            for b_end in [*sorted(learn), len(L) - 1]:
                if b_end < b0:
                    continue
                sl = slice(b0, b_end + 1)
                was_on = clip_on
                hit, ev, rail_at, learnt, has_carry, clip_on = rail_pass_kernel(
                    am[sl], np.ascontiguousarray(rr[sl]), v[lo[sl]], v[hi[sl] - 1], L[sl], rail, learnt, cv, cn,
                    has_carry, clip_on, float(rail_min[s]), int(rail_run))
                hl = hit.tolist()
                evs = np.flatnonzero(ev).tolist()
                if b_end in learn:  # as check(): the block reads at the rail, its event with the rail then known
                    if not learnt:
                        learnt = True
                        rail[:] = math.inf
                    for k, val in learn[b_end]:
                        rail[k] = min(rail[k], val)
                    prev_on = hl[-2] if len(hl) > 1 else was_on
                    if not prev_on and (len(hl) - 1) not in evs:
                        evs.append(len(hl) - 1)
                    rail_at[len(hl) - 1] = rail
                    hl[-1] = True
                    clip_on = True
                for e in evs:
                    events.setdefault(b0 + e, []).append(_saturation_event(s, rail_at[e].tolist()))
                hit_all += hl
                b0 = b_end + 1
            if learnt:
                self.rail[s] = rail.tolist()
            if has_carry:
                self.run[s] = list(zip(cv.tolist(), cn.tolist(), strict=True))
            else:
                self.run.pop(s, None)
            self.clip_on[s] = bool(clip_on)
            hits.append(hit_all)
        return hits[0], hits[1], events


def _all_below(v: list[float], bound: float) -> bool:
    """float(np.max(v)) < bound for a few Python floats v (False where one is NaN, as np.max's NaN)."""
    return all(x < bound for x in v)


def _all_diff_below(u: list[float], v: list[float], bound: float) -> bool:
    """float(np.abs(u − v).max()) < bound for two lists of Python floats (False where a difference is NaN)."""
    return all(abs(x - y) < bound for x, y in zip(u, v, strict=True))


def _still(B: Blocks, b: int, n: dict[str, float], nm: dict[str, float], k: float, prev: tuple[Any, ...] | None,
           f: float = 1.0) -> bool:
    """The rest detector's still test of block ``b`` (:class:`RestDetector`): per-axis spread below k σ (``n``),
    and, against the previous block's means ``prev`` (none: the spread alone), the change of the means below
    2k σ √(2/L) (``nm``, the σ of a block mean); the accel's and mag's bounds × ``f`` (:meth:`RestDetector.
    marginal`; 1 for the test itself — the same products, so the same decisions). On Python floats (issue 15):
    "max over the axes < bound" as "every axis < bound" (a NaN fails both), the differences the same
    subtractions: the same decisions at a third of numpy's per-call cost."""
    L = B.hi_l[b] - B.lo_l[b]
    if not (L >= 3 and _all_below(B.w_std[b].tolist(), k * n["gyro"])
            and _all_below(B.a_std[b].tolist(), f * k * n["accel"])):
        return False
    if prev is None:
        return True
    d = math.sqrt(2.0 / L)
    if not (_all_diff_below(B.w_mean[b].tolist(), prev[0].tolist(), 2 * k * nm["gyro"] * d)
            and _all_diff_below(B.a_mean[b].tolist(), prev[1].tolist(), f * 2 * k * nm["accel"] * d)):
        return False
    n_m = B.mhi_l[b] - B.mlo_l[b]
    if n_m and prev[2] is not None:
        return _all_diff_below(B.m_mean[b].tolist(), prev[2].tolist(), f * 2 * k * nm["mag"] * math.sqrt(2.0 / n_m))
    return True


@dataclass
class RestDetector:
    """Rest from raw data: gyro, accel and mag still (within their noise) for ``rest_blocks`` blocks.

    Still: per-axis spread inside the block below k σ and the change of the block mean against the
    previous block below 2k σ √(2/L). Needs no calibration; a constant-rate turn about the vertical without
    a magnetometer cannot be told from rest (nothing measures it). State: the previous block's means, the
    count of still blocks in a row, whether the last block was still."""

    prev_means: tuple[Any, ...] | None = None
    count: int = 0
    still: bool = False

    def reset(self) -> None:
        """A new log, a gap: the previous means no longer compare."""
        self.prev_means = None
        self.count = 0

    def update(self, B: Blocks, b: int, n: dict[str, float], k: float, rest_blocks: int,
               n_mean: dict[str, float] | None = None) -> bool:
        """Judge block ``b`` of ``B`` with the per-sample noise σ ``n``; True once in a rest. ``n_mean``: the σ
        whose σ²/L is a block mean's variance (:meth:`.noise.NoiseModel.for_means`; correlated samples
        average down less), for the change of the means; ``n`` where not given."""
        n_m = B.mhi_l[b] - B.mlo_l[b]
        gm, am = B.w_mean[b], B.a_mean[b]
        mm = B.m_mean[b] if n_m else None
        prev = self.prev_means
        still = _still(B, b, n, n if n_mean is None else n_mean, k, prev)
        self.prev_means = (gm, am, mm if mm is not None else (prev[2] if prev is not None else None))
        self.count = self.count + 1 if still else 0
        self.still = still
        return self.count >= rest_blocks

    def marginal(self, B: Blocks, b: int, n: dict[str, float], n_mean: dict[str, float] | None, k: float,
                 prev: tuple[Any, ...], f: float = 2.0) -> bool:
        """Whether block ``b`` (judged not still by :meth:`update`) is a lone accelerometer or magnetometer
        excursion that a running rest may leave out instead of ending (:func:`.step.step`): its gyro passes the
        still test as it is (the body did not turn: the held attitude stays right through the block), its
        accel and mag pass it with their bounds × ``f``, against the block before it (``prev``: its means) — a
        tap on the bench, a tail of the noise's distribution. On the real PX4 log, 7 such blocks (accel mean
        changes 4.0–7.3 of the bound's unit, spreads 2.1–2.3) cut its 60-s rest into 12 rests, each a fresh
        measurement of the same pose (docs/flight.md)."""
        return _still(B, b, n, n if n_mean is None else n_mean, k, prev, f)


@dataclass
class HoldTracker:
    """Whether the accel / mag reading of a block is *held* (its spread within the noise, on a re-quantised
    lattice) and whether it is the same hold as the previous block's. A new hold needs a fresh hold-offset
    state (a fresh quantisation error); :meth:`flags` says which."""

    held: dict[str, bool] = field(default_factory=lambda: {"accel": False, "mag": False})

    def flags(self, B: Blocks, b: int, n: dict[str, float], q: dict[str, Any], prev: tuple[Any, ...] | None,
              sensors: tuple[str, ...]) -> tuple[dict[str, bool], list[str], bool]:
        """Held flags of block ``b``, the sensors whose hold offset restarts, and whether a held reading
        started anew. ``prev``: the previous block's means (:attr:`RestDetector.prev_means`, read before
        the rest detector sees this block); ``sensors``: those with hold states; ``q`` the lattices."""
        out = {"accel": False, "mag": False}
        resets: list[str] = []
        new = False
        if not sensors:
            return out, resets, new
        cnt = {"accel": B.hi_l[b] - B.lo_l[b], "mag": B.mhi_l[b] - B.mlo_l[b]}
        for s, mean, std, pi in (("accel", B.a_mean[b], B.a_std[b], 1), ("mag", B.m_mean[b], B.m_std[b], 2)):
            if s not in sensors or cnt[s] < 2:
                self.held[s] = False
                continue
            qs = q.get(s, 0.0)
            held = bool(np.all(std <= 2.0 * n[s] + 0.5 * qs))
            same = (held and self.held[s] and prev is not None and prev[pi] is not None
                    and bool(np.all(np.abs(mean - prev[pi]) < qs + 3 * n[s] * math.sqrt(2.0 / cnt[s]))))
            if not same:
                resets.append(s)
                new = new or held
            self.held[s] = held
            out[s] = held
        return out, resets, new


@dataclass
class Lattice:
    """The value lattice of the current log per sensor (``q``: quantum, 0: none; ``<sensor>_requant``: a
    re-quantisation by the format, set by the filter), detected on its first samples; the mag's once 16
    of its samples are in (``mag_buf``, also the raw field's scale until then). None until a log has started."""

    q: dict[str, Any] | None = None
    mag_buf: list[list[float]] = field(default_factory=list)

    def detect(self, w: Array, a: Array, m: Array) -> tuple[str, ...]:
        """Lattices of the first samples w, a (and m, if 16 or more); the sensors found."""
        self.q = {"gyro": value_lattice(w), "accel": value_lattice(a)}
        self.mag_buf = m.tolist()
        if m.shape[0] >= 16:
            self.q["mag"] = value_lattice(m)
        return tuple(s for s in ("gyro", "accel", "mag") if s in self.q)

    def settle(self) -> None:
        """Drop the mag samples once its lattice is known (after the filter has used them for the unit)."""
        if self.q is not None and "mag" in self.q:
            self.mag_buf = []

    def late_mag(self, m: Array) -> bool:
        """Collect mag samples m (M, 3) until 16 are in; True when the mag's lattice was just found (the
        samples stay until :meth:`settle`)."""
        if self.q is None or "mag" in self.q or not m.shape[0]:
            return False
        self.mag_buf += m.tolist()
        if len(self.mag_buf) < 16:
            return False
        self.q["mag"] = value_lattice(np.asarray(self.mag_buf))
        return True
