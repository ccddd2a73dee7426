"""The batch's input in bounded memory (issue 16.5): a long log read in blocks and reduced to what the fits need.

The batch's steps (clean, segment, the magnetometer, accelerometer and gyro fits) work on whole arrays and
make temporaries in proportion to them; an hour at 200 Hz held whole costs 1.7× the memory of ten
minutes. This stage stands in front of them. A log of at most ``budget`` IMU samples is read whole, exactly
as :func:`onlinecal.io.read_log` reads it (the reduction is then a no-op). A longer one is read twice, in
blocks, never whole:

1. **Statistics** (pass 1): the log cut into cells of ~0.5 s (the segmenter's window), each cell's
   gyro and accel means and spreads, its turn angle about each raw axis in either direction, and its mean raw
   magnetometer vector: a few numbers per cell, ~0.2 MB for an hour at 200 Hz.
2. **Classification** on the cells, with the segmenter's own tests (:func:`onlinecal.batch.segment.find_statics`:
   noise floors from the low percentile of the windowed spread, the absolute caps, the mean rate near the rest
   bias; and its quasi-static test, which the pipeline falls back to): rest cells and motion cells.
3. **Selection** within the budget: every rest, each trimmed to its first and last ``cap`` seconds (cap ≤ 30 s,
   shortened down to 1 s until the rests fit 3/4 of the budget: the bias fit of eqs. 34–35 and the static means
   of eq. 32 need many rests more than long ones, and the motions either side keep their rest edges); the
   motions between rests, a short one (≤ 60 s) as one span with both of its rests (the rest-to-rest
   integral of eq. 36), a longer one cut into 30 s spans. Spans are chosen greedily for coverage per cell of
   budget first — turn angle about each raw axis in each direction (up to 4π each) and raw magnetometer
   directions on the sphere (24 bins, the mag fit is coverage-weighted by attitude) — then the rest-to-rest
   motions, then the long motions' spans, each evenly in time, to fill the budget (a representative subset:
   drift and temperature over the whole log).
4. **Samples** (pass 2): the kept spans' samples, each contiguous run of kept cells one piece. The pieces go
   to :func:`onlinecal.batch.run_batch` as the logs of one unit (the pipeline pools logs already), so no
   integral or window bridges a dropped stretch.

What was kept is stated ("used N of M motion spans") in a warning and in the batch's ``meta``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..io import BlockJoiner, open_log
from ..io.base import ImuData
from .segment import STILL_ACC_CAP, STILL_GYRO_CAP, WINDOW_S

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

BUDGET = 150_000  # IMU samples given to the batch: 12.5 min at 200 Hz, 25 min at 100 Hz
REST_KEEP_S = 30.0  # a long rest keeps at most its first and last REST_KEEP_S
REST_SHARE = 0.75  # of the budget at most for rests (a long rest's length weighs as its cube in eqs. 34-35)
WHOLE_MOTION_S = 60.0  # a rest-to-rest motion up to this long is kept (or dropped) whole
SPAN_S = 30.0  # a longer motion is cut into spans of this length
TURN_TARGET = 4 * np.pi  # rad of turn per raw axis and direction that counts as covered
MAG_BIN_TARGET = 8  # cells per magnetometer direction bin that count as covered
READ_BLOCK = 1 << 14  # IMU samples per block read (the readers' blocks are transient)
MAG_CELL_DEG = 5.0  # the magnetometer sample's sphere grid (the fit weights 10° cells: four of these each)
MAG_PER_CELL = 16  # raw mag samples kept per cell of the whole log (the fit keeps ≤ 30 per 10° cell)


@dataclass
class Reduction:
    """What the reduction kept of one log (``to_dict`` goes into the batch's ``meta.batch.reduced``)."""

    source: str
    n_imu: int  # IMU samples in the log
    n_kept: int  # IMU samples given to the batch
    spans_used: int  # motion spans kept
    spans_total: int  # motion spans in the log
    rest_s: float  # rest time in the log, s
    rest_kept_s: float  # rest time kept, s
    pieces: int  # contiguous stretches handed to the batch
    budget: int = BUDGET
    mag_total: int = 0  # magnetometer samples in the log
    mag_kept: int = 0  # in the kept stretches and the binned sample of the rest
    covered: dict[str, Any] = field(default_factory=dict)  # turn per axis/direction, mag bins: kept vs log

    def note(self) -> str:
        """The one sentence the batch prints."""
        return (f"{self.source}: long log ({self.n_imu} IMU samples, over the batch's budget of {self.budget}): "
                f"used {self.spans_used} of {self.spans_total} motion spans and {self.rest_kept_s:.0f} of "
                f"{self.rest_s:.0f} s of rest ({self.n_kept} samples in {self.pieces} stretches, chosen to cover "
                f"every turn direction and magnetometer direction the log has, then evenly in time); the magnetometer "
                f"fit sees {self.mag_kept} of {self.mag_total} samples, at most {MAG_PER_CELL} per {MAG_CELL_DEG:.0f}° "
                "cell of field directions over the whole log")

    def to_dict(self) -> dict[str, Any]:
        return {"file": self.source, "imu_samples": self.n_imu, "imu_samples_used": self.n_kept,
                "motion_spans_used": self.spans_used, "motion_spans": self.spans_total,
                "rest_s": self.rest_s, "rest_s_used": self.rest_kept_s, "stretches": self.pieces,
                "mag_samples": self.mag_total, "mag_samples_used": self.mag_kept,
                "coverage": self.covered}


# -- pass 1: cell statistics ---------------------------------------------------------------------------------


@dataclass
class _Cells:
    """Per-cell statistics of a log, cells of ``k`` IMU samples in log order (the last may be shorter).

    i0 (C,) first global IMU row · n (C,) rows · t0/t1 (C,) first/last IMU time s · g_mean (C, 3) rad/s ·
    g_std (C,) and a_std (C,) the per-axis spreads summed as a norm (the segmenter's windowed std) ·
    turn (C, 6) raw turn angle rad about +x, −x, +y, −y, +z, −z · m_sum (C, 3), m_n (C,) raw mag sum and count.
    """

    k: int
    i0: list[Array] = field(default_factory=list)
    n: list[Array] = field(default_factory=list)
    t0: list[Array] = field(default_factory=list)
    t1: list[Array] = field(default_factory=list)
    g_mean: list[Array] = field(default_factory=list)
    g_std: list[Array] = field(default_factory=list)
    a_std: list[Array] = field(default_factory=list)
    turn: list[Array] = field(default_factory=list)
    m_sum: list[Array] = field(default_factory=list)
    m_n: list[Array] = field(default_factory=list)

    def add(self, row0: int, t: Array, gyro: Array, acc: Array, t_mag: Array, mag: Array) -> None:
        """Cells of whole rows (``t.size`` a multiple of ``k`` except for the log's last cell)."""
        n = t.size
        if n == 0:
            return
        k = self.k
        starts = np.arange(0, n, k)
        cnt = np.minimum(k, n - starts)
        self.i0.append((row0 + starts).astype(float))
        self.n.append(cnt.astype(float))
        self.t0.append(t[starts])
        self.t1.append(t[starts + cnt - 1])
        idx = np.repeat(np.arange(starts.size), cnt)

        def mean_std(x: Array) -> tuple[Array, Array]:
            s1 = np.zeros((starts.size, 3))
            s2 = np.zeros((starts.size, 3))
            ref = x[starts][idx]  # each cell's first sample: no cancellation of a large offset
            np.add.at(s1, idx, x - ref)
            np.add.at(s2, idx, (x - ref) ** 2)
            m = s1 / cnt[:, None]
            return m + x[starts], np.linalg.norm(np.sqrt(np.maximum(s2 / cnt[:, None] - m**2, 0.0)), axis=1)

        gm, gs = mean_std(gyro)
        _, as_ = mean_std(acc)
        self.g_mean.append(gm)
        self.g_std.append(gs)
        self.a_std.append(as_)
        dt = np.diff(t, prepend=t[0])
        dt = np.where(dt > 0.2, 0.0, dt)  # no turn across a logger gap
        wdt = gyro * dt[:, None]
        turn = np.zeros((starts.size, 6))
        np.add.at(turn, idx, np.concatenate([np.maximum(wdt, 0), np.maximum(-wdt, 0)], axis=1)[:, [0, 3, 1, 4, 2, 5]])
        self.turn.append(turn)
        ms = np.zeros((starts.size, 3))
        mn = np.zeros(starts.size)
        if t_mag.size:
            j = np.clip(np.searchsorted(t[starts], t_mag, side="right") - 1, 0, starts.size - 1)
            np.add.at(ms, j, mag)
            np.add.at(mn, j, 1.0)
        self.m_sum.append(ms)
        self.m_n.append(mn)

    def arrays(self) -> dict[str, Array]:
        out = {}
        for name in ("i0", "n", "t0", "t1", "g_mean", "g_std", "a_std", "turn", "m_sum", "m_n"):
            parts = getattr(self, name)
            out[name] = np.concatenate(parts) if parts else np.zeros(0)
        return out


# -- classification and selection ---------------------------------------------------------------------------


def _runs(mask: BoolArray) -> list[tuple[int, int]]:
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    d = np.diff(m)
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist(), strict=True))


def still_cells(c: dict[str, Array]) -> BoolArray:
    """(C,) cells at rest or quasi-static, by the segmenter's tests on windowed spreads
    (:func:`onlinecal.batch.segment.find_statics`, strict or relaxed), a little wider: the segmenter decides
    on the kept samples; a cell kept too many costs budget, a rest lost costs a fit its data."""
    gs, as_ = c["g_std"], c["a_std"]
    g_floor = max(float(np.percentile(gs, 5)), 2e-4)
    a_floor = max(float(np.percentile(as_, 5)), 2e-3)
    quiet = (gs < 6 * g_floor + 2e-3) & (as_ < 6 * a_floor + 0.03) & (gs < STILL_GYRO_CAP) & (as_ < STILL_ACC_CAP)
    if not quiet.any():
        return quiet
    bias = np.median(c["g_mean"][quiet], axis=0)
    dev = np.linalg.norm(c["g_mean"] - bias, axis=1)
    strict = quiet & (dev < max(0.03, 10 * g_floor))
    relaxed = (as_ < max(0.25, 4 * a_floor + 0.02)) & (dev < 0.1) & (as_ < STILL_ACC_CAP)
    return strict | relaxed


def _mag_bins(c: dict[str, Array]) -> NDArray[np.intp]:
    """(C,) bin 0..23 of each cell's mean raw field direction (−1 without mag): the dominant axis and its sign
    (6) × the signs of the other two (4), about the centre of the raw samples' box (a rough hard-iron centre:
    enough to tell directions apart)."""
    have = c["m_n"] > 0
    out = np.full(c["m_n"].size, -1, np.intp)
    if have.sum() < 2:
        return out
    m = c["m_sum"][have] / c["m_n"][have, None]
    v = m - 0.5 * (m.min(axis=0) + m.max(axis=0))
    k = np.argmax(np.abs(v), axis=1)
    r = np.arange(v.shape[0])
    sgn = (v[r, k] < 0).astype(np.intp)
    o1, o2 = v[r, (k + 1) % 3] < 0, v[r, (k + 2) % 3] < 0
    out[have] = (2 * k + sgn) * 4 + 2 * o1 + o2
    return out


def select_cells(c: dict[str, Array], budget_cells: int, k: int, rate: float) -> tuple[BoolArray, dict[str, Any]]:
    """(C,) cells to keep within ``budget_cells`` and the figures of what was kept (see the module)."""
    n_cells = c["n"].size
    keep = np.zeros(n_cells, bool)
    cell_s = k / rate
    still = still_cells(c)
    rest_runs = [(a, b) for a, b in _runs(still) if b - a >= 2]
    # every rest (each a static attitude for eq. 32, a bias estimate for eqs. 34-35), each trimmed to its first
    # and last ``cap`` cells: the longest cap (≤ REST_KEEP_S) whose total fits REST_SHARE of the budget
    lens = np.array([b - a for a, b in rest_runs], int)

    def rest_cells(cap: int) -> int:
        return int(np.minimum(lens, 2 * cap).sum())

    rest_budget = int(REST_SHARE * budget_cells)
    cap = max(1, int(round(REST_KEEP_S / cell_s)))
    min_cap = max(1, int(round(1.0 / cell_s)))  # 2 s of each rest at least
    while cap > min_cap and rest_cells(cap) > rest_budget:
        cap = max(min_cap, int(cap * 0.8))
    order = list(range(len(rest_runs)))
    if rest_cells(cap) > rest_budget:
        # more rests than their share of the budget holds even at 2 s each: rests evenly over the log
        n_fit = max(1, (rest_budget) // (2 * cap))
        order = sorted(set(np.linspace(0, len(rest_runs) - 1, min(n_fit, len(rest_runs))).round().astype(int)))
    rest_keep = np.zeros(n_cells, bool)
    for j in order:
        a, b = rest_runs[j]
        if b - a > 2 * cap:
            rest_keep[a:a + cap] = rest_keep[b - cap:b] = True
        else:
            rest_keep[a:b] = True
    keep |= rest_keep
    # motion spans: what lies between rests (with one cell of each flank's rest, so the segmenter sees the edge)
    in_rest = np.zeros(n_cells, bool)
    for a, b in rest_runs:
        in_rest[a:b] = True
    whole = max(1, int(round(WHOLE_MOTION_S / cell_s)))
    span = max(1, int(round(SPAN_S / cell_s)))
    spans: list[tuple[int, int]] = []
    whole_flags: list[bool] = []
    for a, b in _runs(~in_rest):
        if b - a <= whole and a > 0 and b < n_cells:
            spans.append((a, b))
            whole_flags.append(True)
        else:
            cut = [(s, min(b, s + span)) for s in range(a, b, span)]
            spans += cut
            whole_flags += [False] * len(cut)
    sp_whole = np.array(whole_flags, bool)
    turn = c["turn"]
    bins = _mag_bins(c)
    sp_turn = np.array([turn[a:b].sum(axis=0) for a, b in spans]) if spans else np.zeros((0, 6))
    sp_mag = np.zeros((len(spans), 24))
    for j, (a, b) in enumerate(spans):
        bb = bins[a:b]
        sp_mag[j] = np.bincount(bb[bb >= 0], minlength=24)
    sp_len = np.array([b - a + 2 for a, b in spans], int)  # with its two flank cells (below)
    left = budget_cells - int(keep.sum())
    chosen = np.zeros(len(spans), bool)
    got_turn, got_mag = np.zeros(6), np.zeros(24)
    # coverage first: the span that adds most to the uncovered turn directions and field directions per cell
    # of budget it costs (a short transition between two rests turning 90° is worth as much per cell as a
    # rotation phase; the gyro fit needs many transitions, eq. 36 over every rest-to-rest motion)
    while left > 0 and len(spans):
        gain = (np.minimum(sp_turn, np.maximum(TURN_TARGET - got_turn, 0)).sum(axis=1) / TURN_TARGET
                + np.minimum(sp_mag, np.maximum(MAG_BIN_TARGET - got_mag, 0)).sum(axis=1) / MAG_BIN_TARGET)
        gain[chosen | (sp_len > left)] = 0.0
        if gain.max() <= 1e-3:
            break
        j = int(np.argmax(gain / sp_len))
        chosen[j] = True
        got_turn += sp_turn[j]
        got_mag += sp_mag[j]
        left -= int(sp_len[j])
    # then evenly in time: the rest-to-rest motions (each a transition of eq. 36), then the spans of long
    # motions; of each, every m-th of those not yet chosen, m from what the budget still holds
    for kind in (True, False):
        rest_sp = np.flatnonzero(~chosen & (sp_whole == kind))
        if left <= 0 or not rest_sp.size:
            continue
        fits = max(1, int(left // max(1.0, float(sp_len[rest_sp].mean()))))
        pick = rest_sp[np.unique(np.linspace(0, rest_sp.size - 1, min(fits, rest_sp.size)).round().astype(int))]
        for j in pick.tolist():
            if sp_len[j] <= left:
                chosen[j] = True
                left -= int(sp_len[j])
    for j in np.flatnonzero(chosen).tolist():
        a, b = spans[j]
        # a kept span takes one rest cell on either side, so that the segmenter sees the rest it starts from
        keep[max(0, a - 1):min(n_cells, b + 1)] = True
    rest_s = float(sum(c["t1"][b - 1] - c["t0"][a] for a, b in rest_runs))
    rest_kept_s = float(np.sum(np.where(rest_keep, c["n"], 0.0)) / rate)
    all_turn = turn.sum(axis=0)
    kept_turn = turn[keep].sum(axis=0)
    figs = {"spans_used": int(chosen.sum()), "spans_total": len(spans), "rest_s": rest_s, "rest_kept_s": rest_kept_s,
            "covered": {"turn_rad": {"+x -x +y -y +z -z".split()[i]: [round(float(kept_turn[i]), 2),
                                                                         round(float(all_turn[i]), 2)]
                                     for i in range(6)},
                        "mag_bins": [int(np.unique(bins[keep & (bins >= 0)]).size),
                                     int(np.unique(bins[bins >= 0]).size)]}}
    return keep, figs


class MagSample:
    """A bounded sample of a log's raw magnetometer readings binned on the sphere of field directions: at most
    ``per_cell`` per cell of ``cell_deg`` (bottom-k of random keys per cell: a uniform sample of each cell,
    mergeable block by block). The centre the directions are taken about is the raw samples' box centre of the
    first block seen (a rough hard-iron centre: the cells only spread the sample; the fit weights its own)."""

    def __init__(self, cell_deg: float = MAG_CELL_DEG, per_cell: int = MAG_PER_CELL, seed: int = 0) -> None:
        self.cell_deg, self.per_cell = cell_deg, per_cell
        self.rng = np.random.default_rng(seed)
        self.centre: Array | None = None
        self.t, self.m = np.zeros(0), np.zeros((0, 3))
        self.key, self.cell = np.zeros(0), np.zeros(0, np.int64)
        self.n_seen = 0

    def _cells(self, m: Array) -> NDArray[np.int64]:
        assert self.centre is not None
        u = m - self.centre
        u = u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)
        step = np.radians(self.cell_deg)
        ring = np.minimum(((np.arcsin(np.clip(u[:, 2], -1, 1)) + np.pi / 2) / step).astype(np.int64),
                          int(np.ceil(np.pi / step)) - 1)
        n_lon = np.maximum(1, np.round(2 * np.pi * np.cos(-np.pi / 2 + (ring + 0.5) * step) / step)).astype(np.int64)
        col = np.minimum(((np.arctan2(u[:, 1], u[:, 0]) + np.pi) / (2 * np.pi) * n_lon).astype(np.int64), n_lon - 1)
        return ring * 1000 + col

    def add(self, t: Array, m: Array) -> None:
        ok = np.all(np.isfinite(m), axis=1)
        t, m = t[ok], m[ok]
        if t.size == 0:
            return
        self.n_seen += int(ok.size)
        if self.centre is None:
            lo, hi = np.percentile(m, [1, 99], axis=0)
            self.centre = 0.5 * (lo + hi)
        t = np.concatenate([self.t, t])
        m = np.concatenate([self.m, m])
        key = np.concatenate([self.key, self.rng.random(t.size - self.key.size)])
        cell = np.concatenate([self.cell, self._cells(m[self.cell.size:])])
        order = np.lexsort((key, cell))
        cs = cell[order]
        first = np.searchsorted(cs, cs, side="left")  # each sorted entry's rank within its cell
        sel = order[(np.arange(cs.size) - first) < self.per_cell]
        self.t, self.m, self.key, self.cell = t[sel], m[sel], key[sel], cell[sel]

    def outside(self, t_lo: Array, t_hi: Array) -> tuple[Array, Array]:
        """The sample's (t, mag) outside the stretches [t_lo, t_hi) (those are kept whole), in time order."""
        inside = np.zeros(self.t.size, bool)
        j = np.searchsorted(t_lo, self.t, side="right") - 1
        ok = j >= 0
        inside[ok] = self.t[ok] < t_hi[j[ok]]
        o = np.argsort(self.t[~inside], kind="stable")
        return self.t[~inside][o], self.m[~inside][o]


# -- the reader ---------------------------------------------------------------------------------------------


def read_reduced(path: str | Path, acc_scale: float | None = None, gyro_scale: float | None = None,
                 mag_scale: float | None = None, imu: int = 0, budget: int = BUDGET,
                 max_samples: int = READ_BLOCK) -> tuple[list[ImuData], Reduction | None]:
    """The log at ``path`` for the batch in memory bounded by ``budget`` IMU samples (see the module).

    Returns ([the whole log], None) when it holds at most ``budget`` IMU samples — the same ImuData as
    :func:`onlinecal.io.read_log` — and otherwise (the kept stretches, each an ImuData of this log, in time
    order; the :class:`Reduction`). Raises :class:`onlinecal.io.LogError` as the readers do.
    """
    reader = open_log(path, acc_scale, gyro_scale, mag_scale, imu=imu)
    joiner: BlockJoiner | None = BlockJoiner()
    held: list[ImuData] = []  # the blocks while the log may still be short (the joiner holds the same arrays)
    cells: _Cells | None = None
    carry: list[Array] = []  # rows (t, gyro, acc) and mag (t, mag) not yet in a whole cell
    row0 = 0  # global IMU row of carry's first row
    n_total = 0
    msample = MagSample()

    def to_cells(b: ImuData) -> None:
        """The block's whole cells into ``cells``; the rows of a cell not yet complete wait in ``carry``."""
        nonlocal carry, row0
        assert cells is not None
        t, g, a, tm, m = (np.concatenate([c, x]) for c, x in
                          zip(carry, (b.t_imu, b.gyro, b.acc, b.t_mag, b.mag), strict=True))
        whole = (t.size // cells.k) * cells.k
        t_end = t[whole] if whole < t.size else np.inf
        mm = tm < t_end
        if whole:
            cells.add(row0, t[:whole], g[:whole], a[:whole], tm[mm], m[mm])
            row0 += whole
        carry = [t[whole:].copy(), g[whole:].copy(), a[whole:].copy(), tm[~mm], m[~mm]]

    for b in reader.blocks(max_samples):
        n_total += b.n_imu
        msample.add(b.t_mag, b.mag)
        if joiner is not None:
            joiner.add(b)
            held.append(b)
            if n_total <= budget:
                continue
            # over the budget: the blocks held so far become cells one by one, the log is not held any more
            joiner = None
            t_all = [x.t_imu for x in held if x.n_imu]
            rate = (n_total - 1) / max(float(t_all[-1][-1] - t_all[0][0]), 1e-9)
            cells = _Cells(k=max(8, int(round(WINDOW_S * rate))))
            carry = [np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3))]
            del t_all, b
            while held:
                to_cells(held.pop(0))
            continue
        to_cells(b)
        del b
    if joiner is not None:
        return [joiner.result(reader, str(path))], None
    assert cells is not None
    cells.add(row0, *carry)  # the log's last, shorter cell
    c = cells.arrays()
    rate = (n_total - 1) / max(float(c["t1"][-1] - c["t0"][0]), 1e-9)
    keep, figs = select_cells(c, max(1, budget // cells.k), cells.k, rate)
    # kept rows as [i0, i1) runs and their time spans [t0, next run's... first time after) for the mag samples
    runs = _runs(keep)
    i_lo = np.array([int(c["i0"][r0]) for r0, _ in runs])
    i_hi = np.array([int(c["i0"][r1 - 1] + c["n"][r1 - 1]) for _, r1 in runs])
    t_lo = np.array([c["t0"][r0] for r0, _ in runs])
    t_hi = np.array([c["t0"][r1] if r1 < c["t0"].size else np.inf for _, r1 in runs])
    del c
    parts: list[dict[str, list[Array]]] = [{k: [] for k in ("t_imu", "gyro", "acc", "temp", "t_mag", "mag")}
                                           for _ in runs]
    params: dict[str, float] = {}
    reader = open_log(path, acc_scale, gyro_scale, mag_scale, imu=imu)
    g0 = 0
    for b in reader.blocks(max_samples):
        params.update(b.params)
        g1 = g0 + b.n_imu
        for j in np.flatnonzero((i_lo < g1) & (i_hi > g0)):
            s0, s1 = max(0, int(i_lo[j]) - g0), min(b.n_imu, int(i_hi[j]) - g0)
            for k in ("t_imu", "gyro", "acc", "temp"):
                parts[j][k].append(getattr(b, k)[s0:s1].copy())  # a copy: a view would keep the block alive
        if b.n_mag:
            for j in np.flatnonzero((t_lo <= b.t_mag[-1]) & (t_hi > b.t_mag[0])):
                mm = (b.t_mag >= t_lo[j]) & (b.t_mag < t_hi[j])
                parts[j]["t_mag"].append(b.t_mag[mm])
                parts[j]["mag"].append(b.mag[mm])
        g0 = g1
        del b
    t_extra, m_extra = msample.outside(t_lo, t_hi)
    n_mag_kept = sum(int(sum(v.size for v in p["t_mag"])) for p in parts) + t_extra.size
    red = Reduction(str(path), n_total, int(sum(i_hi - i_lo)), figs["spans_used"], figs["spans_total"],
                    figs["rest_s"], figs["rest_kept_s"], len(runs), budget=budget, mag_total=msample.n_seen,
                    mag_kept=n_mag_kept, covered=figs["covered"])
    warnings = [*reader.warnings, red.note()]
    out = []
    for p in parts:
        cols = {k: (np.concatenate(v) if v else np.zeros((0, 3) if k in ("gyro", "acc", "mag") else 0))
                for k, v in p.items()}
        out.append(ImuData(cols["t_imu"], cols["gyro"].reshape(-1, 3), cols["acc"].reshape(-1, 3), cols["temp"],
                           cols["t_mag"], cols["mag"].reshape(-1, 3), str(path), list(warnings), params=params))
    if t_extra.size:
        # the magnetometer elsewhere in the log: a stretch of field readings without IMU samples, which the
        # batch gives to the magnetometer fit only (run_batch: a log with mag and no IMU samples)
        z = np.zeros(0)
        out.append(ImuData(z, np.zeros((0, 3)), np.zeros((0, 3)), z.copy(), t_extra, m_extra, str(path),
                           list(warnings), params=params))
    return out, red
