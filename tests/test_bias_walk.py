"""The gyro bias's random walk measured at rest (issue 10, real logs): a freshly powered unit's bias drifts
while it warms up, beyond the spec's allowance, and a rest's mean then states the bias at the rest's end more
precisely than it is known.

Truths from elsewhere: white block means (no trend to find), a linear drift injected at a known rate (the
walk it implies in closed form, r²T), and the real PX4 log (``../shared/data/px4-ulog/sample.ulg``): the
bias its raw gyro reads over its last seconds at rest."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from onlinecal.io import read_log
from onlinecal.specs import SensorSpec
from onlinecal.ukf import replay
from onlinecal.ukf.layout import SENSOR_SLICE
from onlinecal.ukf.noise import NoiseModel
from onlinecal.ukf.rest import RestAccumulator

SAMPLE = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "px4-ulog" / "sample.ulg"
needs_data = pytest.mark.skipif(not SAMPLE.is_file(), reason="shared/data/px4-ulog/sample.ulg not present")


def _run_rest(means: np.ndarray, L: int, sigma: float, dt: float, nm: NoiseModel) -> tuple[RestAccumulator, int]:
    """Feed gyro block means (k, 3) of L samples of per-sample σ ``sigma`` through a running rest and the
    walk test, as the rest step does; returns the rest and the number of switch-on events."""
    class B:  # the fields of .blocks.Blocks that RestAccumulator.add reads
        lo = np.arange(means.shape[0]) * L
        hi = lo + L
        mlo = mhi = lo
        a_mean = np.zeros_like(means)
        w_mean = means
        m_mean = np.zeros_like(means)
    acc = RestAccumulator.start(np.zeros(3), np.eye(3), np.eye(3), {}, False)
    on = 0
    for b in range(means.shape[0]):
        if b:  # the block-mean noise's pairs, as the filter takes them (the walk waits until κ is decided)
            nm.rest_pair("gyro", means[b], means[b - 1], 2.0 / L, sigma)
        acc.dur += dt
        acc.add(B, b, {"accel": 1.0, "gyro": sigma, "mag": 1.0}, False, False, None)
        ev = nm.walk_from_rest(*acc.trend(), acc.dur, acc.kw)
        on += ev is not None and "raised" in ev[1]
        acc.walk = nm.q_walk
    return acc, on


def test_white_rests_keep_the_spec_walk() -> None:
    """60 white rests of 60 s (600 blocks): the walk ends at 0 on every one, and the test (re-taken at every
    block) switches on in a few at most."""
    L, sigma, switched = 25, 6e-4, 0
    for seed in range(60):
        rng = np.random.default_rng(seed)
        nm = NoiseModel({})
        means = rng.normal(size=(600, 3)) * sigma / np.sqrt(L) + [1e-3, -2e-3, 3e-3]
        acc, on = _run_rest(means, L, sigma, 0.1, nm)
        assert nm.q_walk == 0.0 and acc.walk == 0.0
        switched += on
    assert switched <= 3


def test_a_linear_drift_gives_the_walk_that_covers_it() -> None:
    """A drift of r rad/s per s over a 60-s rest: the walk is r²T within 25 %, and the rest's gyro measurement
    is the bias at the rest's end (within 3 of its σ), where the rest's mean is (rT/2) away, many σ."""
    L, sigma, k, dt = 25, 6e-4, 600, 0.1
    r = np.array([5e-6, 1e-5, 1.1e-5])  # the real PX4 log's rest, rad/s per s
    rng = np.random.default_rng(7)
    t = (np.arange(k) + 1) * dt
    b0 = np.array([1e-3, -2e-3, 3e-3])
    means = rng.normal(size=(k, 3)) * sigma / np.sqrt(L) + b0 + np.outer(t, r)
    nm = NoiseModel({})
    acc, on = _run_rest(means, L, sigma, dt, nm)
    T = k * dt
    assert on == 1
    assert nm.q_walk == pytest.approx(np.mean(r**2) * T, rel=0.25)
    end = b0 + r * T
    sd = 1.0 / np.sqrt(acc.info("gyro"))
    assert np.all(np.abs(acc.gyro_mean() - end) <= 3 * sd), (acc.gyro_mean() - end, sd)
    assert np.all(np.abs(acc.sw / acc.nw - end) > 10 * sd)  # the mean states the bias half a rest ago


def test_the_walk_raises_only_the_gyro_bias_random_walk_and_never_lowers_it() -> None:
    spec = SensorSpec(density=1e-4, full_scale=35.0, lsb=1e-5)
    nm = NoiseModel({"gyro": spec, "accel": spec, "mag": spec})
    x = np.zeros(60)
    x[SENSOR_SLICE["mag"].start + 3 : SENSOR_SLICE["mag"].start + 6] = 1.0
    before = nm.cal_rw(60, x, [], 1e-3).copy()
    gb = SENSOR_SLICE["gyro"].start
    nm.q_walk = 1e-9
    raised = nm.cal_rw(60, x, [], 1e-3).copy()
    assert np.all(raised[gb : gb + 3] == 1e-9) and before[gb] == pytest.approx((1e-4 * 1e-3) ** 2)
    others = np.ones(60, bool)
    others[gb : gb + 3] = False
    assert np.array_equal(raised[others], before[others])
    nm.q_walk = 1e-20  # below the spec's: the spec's stands
    assert nm.cal_rw(60, x, [], 1e-3)[gb] == before[gb]
    nm.q_walk = 0.0
    assert np.array_equal(nm.cal_rw(60, x, [], 1e-3), before)


@needs_data
def test_real_px4_log_ends_with_the_bias_its_last_seconds_read() -> None:
    """The log ends with ~22 s at rest: its raw gyro's mean over the last 5 s is the bias there (plus the Earth's
    rate, ≤ 7.3e-5 rad/s on any axis, and the mean's noise). Before the walk the filter's final bias was the
    mean over the rests (z 4–18 against it: σ 19 µrad/s, the bias 0.08–0.34 mrad/s away); now it is within 3σ.
    Also the drift is in the data, not in the filter (the last 5 s against the first 5 s of the rest)."""
    d = read_log(SAMPLE)
    t = d.t_imu - d.t_imu[0]
    i8 = int(np.searchsorted(t, 8.0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        whole = replay([d], None).calibration
    assert any(e["kind"] == "bias_walk" for e in whole.meta["online"]["events"])
    n5 = int(5.0 * 250)
    w = d.gyro
    drift = w[-n5:].mean(axis=0) - w[i8 : i8 + n5].mean(axis=0)
    assert np.all(np.abs(drift) > 2e-4)
    end = w[-n5:].mean(axis=0)
    # the mean's own σ: the samples' σ over √N, × √3 for the low-pass filter's correlated samples (κ ≤ 3 here)
    s_end = w[-n5:].std(axis=0) / np.sqrt(n5) * np.sqrt(3.0)
    b, s = np.array(whole.gyro.bias), np.array(whole.to_dict()["gyro"]["sigma"]["bias"])
    assert np.all(np.abs(b - end) <= 3 * np.hypot(s, s_end) + 7.3e-5), (b - end, s)


@needs_data
def test_real_px4_first_half_predicts_the_bias_of_the_second() -> None:
    """Out of fit: the first 30 s of the rest alone, replayed, state the bias at their end and, with the walk
    they measured, how far it may move; the second 30 s, replayed apart, end 31 s later. Before the walk
    (the spec's random walk) they disagreed by z 4.6–10.5; the first half's walk over the gap covers them."""
    from onlinecal.ukf import OnlineCalibrator
    from onlinecal.ukf.layout import index

    d = read_log(SAMPLE)
    t = d.t_imu - d.t_imu[0]
    i8, i38 = int(np.searchsorted(t, 8.0)), int(np.searchsorted(t, 38.0))
    gb = index("gyro", "bias")
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i, j in ((i8, i38), (i38, d.n_imu)):
            f = OnlineCalibrator(None)
            f.new_log()
            f.feed(d.slice_imu(i, j))
            f.flush()
            out.append((f.x[gb].copy(), np.diag(f.P)[gb].copy(), f._noise.q_walk, float(t[j - 1])))
    (b1, v1, q1, t1), (b2, v2, _, t2) = out
    assert q1 > 0.0  # the first half measured its drift
    z = (b2 - b1) / np.sqrt(v1 + v2 + q1 * (t2 - t1))
    assert np.all(np.abs(z) <= 3.0), z


@needs_data
def test_a_checkpoint_taken_with_the_walk_on_resumes_bit_identically() -> None:
    """The walk and the running rest's trend sums travel in the checkpoint (schema /4, fields with defaults):
    cut 40 s into the PX4 log (inside its rest, the walk on), through strict JSON, resumed, the same bits."""
    import json

    from onlinecal.ukf import OnlineCalibrator

    d = read_log(SAMPLE)
    cuts = list(range(0, d.n_imu, 997)) + [d.n_imu]
    k = int(np.searchsorted(cuts, np.searchsorted(d.t_imu - d.t_imu[0], 40.0)))

    def feed(cal: OnlineCalibrator, cs: list[int]) -> None:
        for i, j in zip(cs[:-1], cs[1:], strict=True):
            cal.feed(d.slice_imu(i, j))

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = OnlineCalibrator(None)
        ref.new_log()
        feed(ref, cuts)
        ref.flush()
        cal = OnlineCalibrator(None)
        cal.new_log()
        feed(cal, cuts[: k + 1])
        assert cal._noise.q_walk > 0.0 and cal._rest_acc is not None and cal._rest_acc.walk > 0.0
        res = OnlineCalibrator.from_state(json.loads(json.dumps(cal.get_state(), allow_nan=False)))
        assert res._noise.q_walk == cal._noise.q_walk and res._rest_acc.ttw == cal._rest_acc.ttw
        feed(res, cuts[k:])
        res.flush()
    assert np.array_equal(res.x, ref.x) and np.array_equal(res.P, ref.P)
    assert res.events == ref.events
