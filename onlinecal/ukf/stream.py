"""Streaming of the online calibrator: the buffered samples cut into filter blocks, each block checked
(gap, late magnetometer lattice, rails) and handed to the attitude start or the filter step.

The buffer keeps incomplete blocks between ``feed()`` calls, so the result does not depend on how a log is
cut (:class:`.blocks.SampleBuffer`); the block statistics are computed for all full blocks at once
(:func:`.blocks.block_stats`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from ..batch.clock import is_burst_stamped
from . import fastpath
from .blocks import Blocks, block_stats, cut_blocks
from .config import MIN_SAMPLES_DETECT
from .start import init_attitude
from .step import step

if TYPE_CHECKING:
    from .filter import OnlineCalibrator

Array = NDArray[np.float64]


def start_log(cal: OnlineCalibrator, final: bool) -> bool:
    """The rate and the value lattice from the log's first samples (a fixed count, so the result does
    not depend on how the log is cut into feed() calls); False while too few samples are in."""
    buf, k = cal._buf, MIN_SAMPLES_DETECT
    if buf.t.size < k and not (final and buf.t.size >= 2):
        return False
    if cal._rate is None:
        t = buf.t[:k]
        med = float(np.median(np.diff(t)))
        cal._rate = 1.0 / med
        if is_burst_stamped(t):
            # read times in bursts (a replay regularises them first; a live source cannot): the median Δt is
            # the burst's, ~10× the rate — the blocks would be 10× too long and the noise per sample wrong
            cal._rate = float((t.size - 1) / (t[-1] - t[0]))
            cal._event("clock", f"IMU stamps come in bursts (median Δt {1e3 * med:.1f} ms "
                       f"against a mean period of {1e3 / cal._rate:.1f} ms): the rate is taken from the mean "
                       "period; the stamps are used as they are", float(t[-1]))
        cal._L = max(1, int(round(cal.config.block_s * cal._rate)))
    j = int(np.searchsorted(buf.tm, buf.t[min(k, buf.t.size) - 1], side="right"))
    cal._apply_lattice(cal._lat.detect(buf.w[:k], buf.a[:k], buf.m[:j]))
    cal._lat.settle()
    return True


def process(cal: OnlineCalibrator, final: bool = False) -> None:
    """Filter every full block of the samples buffered in ``cal`` (``final``: the short tail too), then
    drop them from the buffer; nothing before the log's rate and lattice are known (:func:`start_log`)."""
    if cal._lat.q is None and not start_log(cal, final):
        return
    buf = cal._buf
    bounds = cut_blocks(buf.t, cal._L, cal.config.max_gap_s, final)
    if not bounds:
        return
    continues = (cal._att_ok and cal._t_last is not None
                 and buf.t[0] - cal._t_last <= cal.config.max_gap_s)
    B = block_stats(buf.t, buf.w, buf.a, buf.tm, buf.m, bounds, cal._t_last, cal._w_last, bool(continues))
    # the rail detector depends on the raw data alone: on the fast path, every block of the feed in one compiled
    # pass (None: a block it does not cover, or the reference path: block by block in filter_block)
    rails = (cal._rails.prepass(B, buf.w, buf.a, cal.config.rail_min, cal.config.rail_run) if fastpath.enabled()
             else None)
    for b in range(len(bounds)):
        filter_block(cal, B, b, buf.t, buf.w, buf.a, buf.T, buf.tm, buf.m, rails)
    buf.drop(bounds[-1][1], int(B.mhi[-1]))


def filter_block(cal: OnlineCalibrator, B: Blocks, b: int, t: Array, w: Array, a: Array, T: Array, tm: Array,
                 mm: Array, rails: tuple[list[bool], list[bool], dict[int, list[tuple[str, str]]]] | None = None
                 ) -> None:
    """One filter block: gap check, lattice of a late mag, rail, then attitude start or filter step. ``rails``:
    the rail detector's flags and events of every block of ``B`` (:meth:`.detectors.RailDetector.prepass`),
    or None to run it on this block."""
    i, j, ml, mh = B.lo_l[b], B.hi_l[b], B.mlo_l[b], B.mhi_l[b]
    tb = t[i:j]
    t0 = cal._t_last if cal._att_ok and cal._t_last is not None else None
    if cal._t_last is not None and tb[0] - cal._t_last > cal.config.max_gap_s:
        gap_restart(cal, float(tb[0] - cal._t_last), float(tb[0]))
        t0 = None
    tmb, mb = tm[ml:mh], mm[ml:mh]
    if cal._lat.late_mag(mb):
        cal._apply_lattice(("mag",))
        cal._lat.settle()
    if rails is None:
        clip, events = cal._rails.check(w[i:j], a[i:j], B.w_absmax[b], B.a_absmax[b],
                                        cal.config.rail_min, cal.config.rail_run, (B.w_runs[b], B.a_runs[b]))
    else:
        clip, events = {"mag": False, "gyro": rails[0][b], "accel": rails[1][b]}, rails[2].get(b, [])
    for kind, detail in events:
        cal._event(kind, detail, float(tb[-1]))
    if clip["gyro"]:
        # a clipped gyro turns the attitude by less than the body did: nothing of this block is
        # used, and the attitude restarts from the accel (and mag) once the gyro is off the rail
        cal._end_rest()
        cal._att_ok = False
    elif t0 is None:
        cal._end_rest()
        init_attitude(cal, a[i:j], tmb, mb)
    else:
        step(cal, B, b, t, a, T, tm, mm, clip)
    cal._t_last = float(tb[-1])
    cal._w_last = w[j - 1].copy()
    cal._n_imu += j - i


def gap_restart(cal: OnlineCalibrator, gap: float, t: float) -> None:
    """A gap of ``gap`` s in the IMU stream before log time ``t``: the attitude restarts and the
    calibration states get the random walk of the gap."""
    cal._event("gap", f"IMU gap of {gap:.3f} s: attitude restarted, calibration drift "
               "allowance for the gap added", t)
    cal._end_rest()
    cal.P[np.diag_indices(cal.n)] += cal._cal_rw() * gap
    cal._att_ok = False
    cal._rest_det.reset()
