"""Raw-data statistics and detectors of the online filter (onlinecal.ukf.blocks) against plain per-block
loops and constructed signals."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onlinecal.ukf.blocks import (
    RailDetector,
    RestDetector,
    SampleBuffer,
    block_stats,
    cut_blocks,
    third_diff_var,
    value_lattice,
)

rng = np.random.default_rng(11)


def test_cut_blocks_are_L_long_and_end_before_a_gap():
    t = np.arange(100) * 0.01
    t[40:] += 1.0  # a 1-s gap between samples 39 and 40
    b = cut_blocks(t, 10, 0.5, final=False)
    assert b[:4] == [(0, 10), (10, 20), (20, 30), (30, 40)] and b[4] == (40, 50)
    assert all(j - i == 10 for i, j in b)
    assert cut_blocks(t[:95], 10, 0.5, final=True)[-1] == (90, 95)
    assert cut_blocks(t[:95], 10, 0.5, final=False)[-1] == (80, 90)


def test_block_stats_equal_per_block_loops():
    n, L = 95, 10
    t = np.arange(n) * 0.01
    w, a = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    tm = np.arange(0, n * 0.01, 0.02) + 0.003
    m = rng.normal(size=(tm.size, 3))
    bounds = cut_blocks(t, L, 0.5, final=True)
    B = block_stats(t, w, a, tm, m, bounds, None, np.zeros(3), False)
    for k, (i, j) in enumerate(bounds):
        assert np.allclose(B.w_mean[k], w[i:j].mean(0), atol=1e-14) and np.allclose(B.a_std[k], a[i:j].std(0))
        assert np.array_equal(B.w_absmax[k], np.abs(w[i:j]).max(0))
        sel = (tm <= t[j - 1]) & (tm > (t[i - 1] if i else -np.inf))
        assert B.mhi[k] - B.mlo[k] == sel.sum()
        if sel.any():
            assert np.allclose(B.m_mean[k], m[sel].mean(0), atol=1e-14)
    assert np.allclose(B.dt[1:], 0.01) and B.dt[0] == 0.0


def test_third_difference_noise_is_the_white_noise_and_skips_gaps():
    """σ² of white noise on a smooth motion, per segment; a dropped sample inside a segment is skipped."""
    n, sig = 4000, 0.01
    t = np.arange(n) * 0.005
    v = np.column_stack([np.sin(t), np.cos(2 * t), t**2 / 100]) + rng.normal(0, sig, (n, 3))
    seg = np.repeat(np.arange(4), n // 4)
    est = third_diff_var(v, t, seg, 4)
    assert np.all(np.abs(est / sig**2 - 1) < 0.15)
    keep = np.ones(n, bool)
    keep[500::50] = False  # dropped samples: the motion across the hole is not noise
    vv = np.column_stack([np.sin(40 * t), np.cos(40 * t), t])[keep] + rng.normal(0, sig, (keep.sum(), 3))
    est2 = third_diff_var(vv, t[keep], seg[keep], 4)
    assert np.all(np.abs(est2 / sig**2 - 1) < 0.2)


def test_value_lattice():
    q = 1e-3
    v = np.round(rng.normal(0, 0.05, (200, 3)) / q) * q
    assert math.isclose(value_lattice(v), q, rel_tol=1e-6)
    assert value_lattice(rng.normal(size=(200, 3))) == 0.0


def test_rail_is_learnt_from_a_run_across_blocks_and_then_any_hit_counts():
    det = RailDetector()
    rail = 17.4
    w = np.zeros((30, 3))
    a = rng.normal(0, 0.01, (30, 3))
    w[2, 0] = 20.0  # a larger peak first: the recurring-top rule (test_the_top_rule_*) does not take 17.4
    w[10:, 0] = rail  # 20 samples at the rail in this block ...
    clip, ev = det.check(w, a, np.abs(w).max(0), np.abs(a).max(0), {"gyro": 1.0, "accel": 14.7}, 40)
    assert not clip["gyro"] and ev == []
    w2 = np.zeros((30, 3))
    w2[:25, 0] = rail  # ... and 25 more in the next: a run of 45 ≥ 40
    clip, ev = det.check(w2, a, np.abs(w2).max(0), np.abs(a).max(0), {"gyro": 1.0, "accel": 14.7}, 40)
    assert clip["gyro"] and ev and ev[0][0] == "saturation" and det.rail["gyro"][0] == rail
    w3 = np.zeros((30, 3))
    w3[7, 0] = rail  # once learnt, one sample at the rail is clipping
    clip, ev = det.check(w3, a, np.abs(w3).max(0), np.abs(a).max(0), {"gyro": 1.0, "accel": 14.7}, 40)
    assert clip["gyro"] and ev == []  # the stretch goes on: no new event


def test_the_top_rule_learns_a_rail_reached_in_short_stretches_and_not_a_peak():
    """The batch's rule (onlinecal.specs.rail_samples), causally: the largest magnitude recurring in RAIL_SAMPLES
    samples, both signs, in stretches shorter than the run rule's 40, is the rail; a peak reached up to nine
    times, or readings a little below it, are not."""
    det = RailDetector()
    lims = {"gyro": 1.0, "accel": 14.7}
    a = rng.normal(9.8, 0.01, (20, 3))
    top = 4.3657
    clips = []
    for k in range(8):  # stretches of 2 samples at ±top on x, and readings near but below it in between
        w = rng.normal(0, 0.5, (20, 3))
        w[5:7, 0] = top * (-1) ** k
        w[12, 0] = top * 0.999
        clip, ev = det.check(w, a, np.abs(w).max(0), np.abs(a).max(0), lims, 40)
        clips.append((clip["gyro"], [e[0] for e in ev]))
    # 2 per block: the fifth block brings the count to 10
    assert [c for c, _ in clips] == [False] * 4 + [True] * 4
    assert clips[4][1] == ["saturation"] and all(e == [] for _, e in clips[5:])
    assert det.rail["gyro"][0] == pytest.approx(top * (1 - 1e-4)) and det.rail["gyro"][1:] == [math.inf] * 2
    peak = RailDetector()
    for _ in range(9):  # a peak reached nine times: no rail
        w = rng.normal(0, 0.5, (20, 3))
        w[3, 1] = 3.0
        clip, _ = peak.check(w, a, np.abs(w).max(0), np.abs(a).max(0), lims, 40)
        assert not clip["gyro"]
    assert "gyro" not in peak.rail


def test_rest_needs_rest_blocks_still_blocks_in_a_row():
    n = {"gyro": 0.01, "accel": 0.02, "mag": 0.003}
    L, nb = 20, 6
    t = np.arange(L * nb) * 0.01
    w = rng.normal(0, 0.01, (L * nb, 3))
    a = rng.normal(0, 0.02, (L * nb, 3)) + [0, 0, 9.8]
    w[3 * L : 4 * L] += 0.5  # block 3 turns
    B = block_stats(t, w, a, np.zeros(0), np.zeros((0, 3)), cut_blocks(t, L, 0.5, True), None, np.zeros(3), False)
    det = RestDetector()
    rest = [det.update(B, b, n, 2.0, 3) for b in range(nb)]
    assert rest == [False, False, True, False, False, False]
    # block 4's mean is compared with the turning block 3's: not still; block 5 is still again
    assert det.count == 1 and det.still


def test_sample_buffer_round_trip():
    buf = SampleBuffer(np.arange(3.0), np.ones((3, 3)), np.zeros((3, 3)), np.array([20.0, np.nan, 21.0]),
                       np.array([0.5]), np.ones((1, 3)))
    back = SampleBuffer.from_dict(buf.to_dict())
    for f in ("t", "w", "a", "tm", "m"):
        assert np.array_equal(getattr(back, f), getattr(buf, f))
    assert np.array_equal(back.T, buf.T, equal_nan=True)
    buf.drop(2, 1)
    assert buf.t.tolist() == [2.0] and buf.tm.size == 0
