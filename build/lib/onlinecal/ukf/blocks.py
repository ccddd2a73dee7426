"""Raw-data statistics of the filter blocks and the detectors that run on raw data alone.

Everything here looks at the samples, never at the filter state: the samples waiting for a full block
(:class:`SampleBuffer`), the cut into filter blocks (:func:`cut_blocks`), the per-block means, spreads and
third-difference noise (:func:`block_stats`, one vectorised pass over all blocks of a ``feed``). The
detectors that judge these statistics (value lattice, rail, rest, held readings) are in :mod:`.detectors`
(re-exported here).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..io.base import ImuData
from . import kernels
from .detectors import HoldTracker as HoldTracker  # re-exported (older imports)
from .detectors import Lattice as Lattice
from .detectors import RailDetector as RailDetector
from .detectors import RestDetector as RestDetector
from .detectors import block_runs
from .detectors import value_lattice as value_lattice

Array = NDArray[np.float64]
Index = NDArray[np.intp]


def third_diff_var(v: Array, t: Array, seg: Index, n_seg: int, min_windows: int = 3) -> Array:
    """Per-segment white-noise variance from third differences: median |Δ³v|² / (3·20·0.789), (n_seg,).

    v (N, 3) samples at times t (N,) s, seg (N,) the segment (filter block) of each sample, ascending.
    Δ³ of white noise on a regular grid has variance 20σ² per axis; a smooth motion's own third
    difference (rate‴·Δt³) is far below it at IMU rates. The median makes it robust to a jerk;
    0.789 = median of χ²(3) / 3. Only windows of 4 samples inside one segment whose 3 intervals agree
    within 1.5× count: across a dropped sample the difference is not the white-noise Δ³ (the motion
    over the missing interval enters it), so a log with gaps would read as noisy. NaN where a segment
    has fewer than ``min_windows`` such windows.
    """
    out = np.full(n_seg, math.nan)
    if v.shape[0] < 4:
        return out
    d3 = (v[3:] - v[:-3]) - 3 * (v[2:-1] - v[1:-2])
    s = np.einsum("ij,ij->i", d3, d3)
    h = np.diff(t)
    h3 = np.stack([h[:-2], h[1:-1], h[2:]])
    ok = (seg[3:] == seg[:-3]) & (h3.max(axis=0) <= 1.5 * h3.min(axis=0))
    if kernels.backend() == "numba":  # the same order statistics per segment, without the sort of the whole feed
        return _seg_median_kernel(s, ok, seg[3:].astype(np.int64), n_seg, min_windows, out)
    sv, sg = s[ok], seg[3:][ok]
    cnt = np.bincount(sg, minlength=n_seg)
    good = cnt >= min_windows
    if not good.any():
        return out
    vals = sv[np.lexsort((sv, sg))]  # grouped by segment (ascending), sorted within
    off = np.concatenate([[0], np.cumsum(cnt)[:-1]])[good]
    c = cnt[good]
    out[good] = 0.5 * (vals[off + (c - 1) // 2] + vals[off + c // 2]) / (3 * 20.0 * 0.7888)
    return out


@kernels._njit
def _seg_median_kernel(s: Array, ok: NDArray[np.bool_], sg: NDArray[np.int64], n_seg: int, min_windows: int,
                       out: Array) -> Array:
    """:func:`third_diff_var`'s per-segment median of the windows ``s`` (M,) kept by ``ok`` (M,), segment ``sg``
    (M,) ascending, into out (n_seg,) (NaN left where fewer than ``min_windows``): each segment's values sorted
    on their own (issue 15: a sort of the whole feed by segment and value, ~9 µs per block, was most of the
    block statistics), the same two order statistics, so the same bits (tests/test_speed_fastpath.py)."""
    M = s.shape[0]
    buf = np.empty(M)
    i = 0
    while i < M:
        g = sg[i]
        j = i
        c = 0
        while j < M and sg[j] == g:
            if ok[j]:
                buf[c] = s[j]
                c += 1
            j += 1
        if c >= min_windows:
            # insertion sort, NaN last as np.sort (a block holds ~17 windows; numba's np.sort cost 2.8 s to
            # compile, this a tenth of it); equal values are equal bits here (sums of squares: no −0.0)
            for a in range(1, c):
                v = buf[a]
                b = a - 1
                while b >= 0 and (buf[b] > v or (buf[b] != buf[b] and v == v)):
                    buf[b + 1] = buf[b]
                    b -= 1
                buf[b + 1] = v
            out[g] = 0.5 * (buf[(c - 1) // 2] + buf[c // 2]) / (3 * 20.0 * 0.7888)
        i = j
    return out


def _seg_mean_std(v: Array, lo: Index, cnt: Index) -> tuple[Array, Array]:
    """Mean and standard deviation (ddof 0) per axis of the segments [lo, lo + cnt) of v (N, 3), which
    follow each other without holes; (n_seg, 3) each, NaN for empty segments. Sums per segment
    (np.add.reduceat), so a segment's figures do not depend on where the buffer it sits in starts."""
    ns = lo.shape[0]
    mean = np.full((ns, 3), math.nan)
    std = np.full((ns, 3), math.nan)
    ne = cnt > 0
    if not ne.any():
        return mean, std
    c_n = cnt[ne]
    s0 = int(lo[ne][0])
    vv = v[s0 : s0 + int(c_n.sum())]
    starts = np.concatenate([[0], np.cumsum(c_n)[:-1]])
    m = np.add.reduceat(vv, starts, axis=0) / c_n[:, None]
    dv = vv - np.repeat(m, c_n, axis=0)
    mean[ne] = m
    std[ne] = np.sqrt(np.add.reduceat(dv * dv, starts, axis=0) / c_n[:, None])
    return mean, std


@dataclass
class Blocks:
    """Raw-data figures of a run of consecutive filter blocks, computed for all of them at once (so the
    per-block work of the filter is only the filter): block b holds IMU samples [lo[b], hi[b]) and mag
    samples [mlo[b], mhi[b]) of the buffers; w_ext (N + 1, 3) the raw rates with the last one filtered
    before them, dt (N,) the length of the interval ending at each IMU sample; per block the means and
    spreads (n_b, 3), the third-difference noise variances (n_b,), the jerk term Σ|Δ²ω·Δt/4|² and its count, the largest
    |reading| per axis; per mag sample its interpolation index into [t_prev, t] and fraction; per block
    the lengths of the first and last runs of identical gyro and accel readings (the rail detector's)."""

    lo: Index
    hi: Index
    mlo: Index
    mhi: Index
    w_ext: Array
    dt: Array
    w_mean: Array
    w_std: Array
    a_mean: Array
    a_std: Array
    m_mean: Array
    m_std: Array
    var3: dict[str, Array]
    jerk: Array
    jerk_n: Array
    w_absmax: Array
    a_absmax: Array
    m_j: Index
    m_frac: Array
    w_runs: Index  # (n_b, 2, 3) the first and last runs of identical readings (.detectors.block_runs)
    a_runs: Index
    # the per-block scalars as Python ints and floats, converted once per feed (issue 15: each numpy scalar
    # read in the per-block Python, int(B.lo[b]) and the like, cost ~0.1 µs; a block made some twenty)
    lo_l: list[int] = field(init=False)
    hi_l: list[int] = field(init=False)
    mlo_l: list[int] = field(init=False)
    mhi_l: list[int] = field(init=False)
    jerk_l: list[float] = field(init=False)
    jerk_n_l: list[float] = field(init=False)
    var3_l: dict[str, list[float]] = field(init=False)
    # the last row of w_ext the Earth's rotation was taken out of (.earth.correct_block; -1: none)
    earth_upto: int = field(init=False)

    def __post_init__(self) -> None:
        self.earth_upto = -1
        self.lo_l, self.hi_l = self.lo.tolist(), self.hi.tolist()
        self.mlo_l, self.mhi_l = self.mlo.tolist(), self.mhi.tolist()
        self.jerk_l, self.jerk_n_l = self.jerk.tolist(), np.asarray(self.jerk_n, dtype=float).tolist()
        self.var3_l = {s: v.tolist() for s, v in self.var3.items()}



def cut_blocks(t: Array, L: int, max_gap: float, final: bool) -> list[tuple[int, int]]:
    """Filter blocks [i, j) of the buffered times t (N,) s: L samples each, cut at a gap longer than
    ``max_gap`` s (the block ends before it); ``final``: the remainder is a (short) block too."""
    n = t.size
    cut = np.flatnonzero(np.diff(t) > max_gap)
    bounds: list[tuple[int, int]] = []
    i = g = 0
    while n - i >= L or (final and n - i > 0):
        j = min(i + L, n)
        while g < cut.size and cut[g] < i:
            g += 1
        if g < cut.size and cut[g] < j - 1:
            j = int(cut[g]) + 1
        bounds.append((i, j))
        i = j
    return bounds


def block_stats(t: Array, w: Array, a: Array, tm: Array, m: Array, bounds: list[tuple[int, int]],
                t_last: float | None, w_last: Array, continues: bool) -> Blocks:
    """Everything the blocks ``bounds`` need from the raw data alone, for all of them at once.

    t (N,) s, w (N, 3) rad/s, a (N, 3) m/s², tm (M,) s, m (M, 3) raw mag: the buffers. ``t_last``,
    ``w_last``: time and raw rate of the last sample already filtered (None: none yet); ``continues``:
    the attitude runs on from it (no gap, attitude initialised), so its mag samples after ``t_last`` belong
    to the first block.
    """
    lo = np.array([b[0] for b in bounds], dtype=np.intp)
    hi = np.array([b[1] for b in bounds], dtype=np.intp)
    nb, end = lo.size, int(hi[-1])
    cnt = hi - lo
    tt, ww, aa = t[:end], w[:end], a[:end]
    seg = np.repeat(np.arange(nb), cnt)
    # mag samples of each block: after the previous block's last sample (for the first block, after
    # the last sample already filtered when the attitude runs on), up to the block's last sample
    mhi = np.searchsorted(tm, tt[hi - 1], side="right")
    m0 = 0
    if continues and t_last is not None:
        m0 = min(int(np.searchsorted(tm, t_last, side="right")), int(mhi[0]))
    mlo = np.concatenate([[m0], mhi[:-1]])
    mcnt = mhi - mlo
    # trapezoid rate and interval ending at each sample (sample 0: from the last one filtered)
    t_prev = t_last if t_last is not None else float(tt[0])
    w_prev = w_last if t_last is not None else ww[0]
    w_ext = np.vstack([w_prev[None], ww])
    t_ext = np.concatenate([[t_prev], tt])
    dt = np.diff(t_ext)
    # jerk term of the trapezoid: Δt·|Δ²ω|/4 at every sample but the block's last
    d2 = (w_ext[2:] - 2 * w_ext[1:-1] + w_ext[:-2]) * (dt[1:, None] / 4)
    e2 = np.concatenate([np.einsum("ij,ij->i", d2, d2), [0.0]])
    e2[hi - 1] = 0.0
    jerk = np.add.reduceat(e2, lo)
    w_mean, w_std = _seg_mean_std(ww, lo, cnt)
    a_mean, a_std = _seg_mean_std(aa, lo, cnt)
    m_mean, m_std = _seg_mean_std(m, mlo, mcnt)
    var3 = {"gyro": third_diff_var(ww, tt, seg, nb), "accel": third_diff_var(aa, tt, seg, nb)}
    mt = tm[m0 : int(mhi[-1])]
    mseg = np.repeat(np.arange(nb), mcnt)
    var3["mag"] = third_diff_var(m[m0 : int(mhi[-1])], mt, mseg, nb)
    # interpolation of each mag sample between the IMU ticks around it (index into t_ext)
    jm = np.clip(np.searchsorted(t_ext, mt, side="left"), lo[mseg] + 1, hi[mseg])
    den = t_ext[jm] - t_ext[jm - 1]
    # two IMU ticks on one stamp: the mag sample sits on the later one (0/0 would put NaN in the weights)
    frac = np.clip(np.divide(mt - t_ext[jm - 1], den, out=np.ones_like(den), where=den > 0), 0.0, 1.0)
    return Blocks(lo, hi, mlo, mhi, w_ext, dt, w_mean, w_std, a_mean, a_std, m_mean, m_std, var3,
                  jerk, 3 * np.maximum(cnt - 1, 0), np.maximum.reduceat(np.abs(ww), lo, axis=0),
                  np.maximum.reduceat(np.abs(aa), lo, axis=0), jm - lo[mseg], frac, block_runs(ww, lo, hi),
                  block_runs(aa, lo, hi))


@dataclass
class SampleBuffer:
    """Samples fed but not yet cut into filter blocks: IMU times t (N,) s, rates w (N, 3), specific force
    a (N, 3), temperature T (N,) °C; mag times tm (M,) s and readings m (M, 3)."""

    t: Array = field(default_factory=lambda: np.zeros(0))
    w: Array = field(default_factory=lambda: np.zeros((0, 3)))
    a: Array = field(default_factory=lambda: np.zeros((0, 3)))
    T: Array = field(default_factory=lambda: np.zeros(0))
    tm: Array = field(default_factory=lambda: np.zeros(0))
    m: Array = field(default_factory=lambda: np.zeros((0, 3)))

    def append(self, block: ImuData) -> None:
        if block.n_imu:
            self.t = np.concatenate([self.t, block.t_imu])
            self.w = np.concatenate([self.w, block.gyro.reshape(-1, 3)])
            self.a = np.concatenate([self.a, block.acc.reshape(-1, 3)])
            self.T = np.concatenate([self.T, np.asarray(block.temp, float).reshape(-1)])
        if block.n_mag:
            self.tm = np.concatenate([self.tm, block.t_mag])
            self.m = np.concatenate([self.m, block.mag.reshape(-1, 3)])

    def drop(self, i: int, k: int) -> None:
        """Forget the first i IMU and k mag samples (filtered)."""
        self.t, self.w, self.a, self.T = self.t[i:], self.w[i:], self.a[i:], self.T[i:]
        self.tm, self.m = self.tm[k:], self.m[k:]

    def to_dict(self) -> dict[str, Any]:
        """JSON-able, with the checkpoint's keys (no temperature: None)."""
        return {"pend_t": self.t.tolist(), "pend_w": self.w.tolist(), "pend_a": self.a.tolist(),
                "pend_T": [None if not math.isfinite(v) else float(v) for v in self.T.tolist()],
                "pend_tm": self.tm.tolist(), "pend_m": self.m.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SampleBuffer:
        return cls(np.asarray(d["pend_t"], float).reshape(-1), np.asarray(d["pend_w"], float).reshape(-1, 3),
                   np.asarray(d["pend_a"], float).reshape(-1, 3),
                   np.array([math.nan if v is None else v for v in d["pend_T"]], float).reshape(-1),
                   np.asarray(d["pend_tm"], float).reshape(-1), np.asarray(d["pend_m"], float).reshape(-1, 3))
