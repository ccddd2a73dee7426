"""Augmented-state UKF (onlinecal.ukf): model layout, accuracy from the batch start, streaming/checkpoint,
degenerate motions, divergence handling, gyro non-orthogonality from rich motion, cold-start gyro."""

from __future__ import annotations

import json

import numpy as np
import pytest

import onlinecal.sim.sensors as simsens
from onlinecal.batch.pipeline import run_batch
from onlinecal.model import PARAMS, SENSORS, Calibration, compose
from onlinecal.sim import simulate
from onlinecal.sim.motion import Trajectory
from onlinecal.ukf import OnlineCalibrator, UKFConfig, replay
from onlinecal.ukf.layout import (
    correction,
    index,
    prefix_products,
    prefix_products_cm,
    rodrigues,
    rodrigues_cm,
    rot_log,
    sensor_model,
)


@pytest.fixture(scope="module")
def paper1():
    sim = simulate("paper", 1)
    return sim, run_batch([sim.data]).calibration


def _errors(cal: Calibration, truth: Calibration):
    for s in SENSORS:
        c, t = cal.sensor(s), truth.sensor(s)
        for p in PARAMS:
            yield s, p, c.params()[p] - t.params()[p], np.asarray(c.sigma[p], float)


def test_layout_matches_model():
    rng = np.random.default_rng(0)
    p = np.concatenate([rng.normal(0, 0.1, 3), 1 + rng.normal(0, 0.1, 3), rng.normal(0, 0.05, 6)])
    o, M = correction(p[None])
    _, Minv = sensor_model(p[None])
    Mt = compose(p[3:6], p[6:9], p[9:12])
    assert np.allclose(M[0], Mt, atol=1e-14) and np.allclose(Minv[0], np.linalg.inv(Mt), atol=1e-13)
    th = rng.normal(0, 0.3, (5, 7, 3))
    R = rodrigues(th)
    assert np.allclose(rodrigues_cm(th.transpose(2, 0, 1)).transpose(2, 3, 0, 1), R, atol=1e-14)
    assert np.allclose(rot_log(R), th, atol=1e-12)
    P = prefix_products_cm(R.transpose(2, 3, 0, 1)).transpose(2, 3, 0, 1)
    assert np.allclose(P, prefix_products(R), atol=1e-13)
    assert np.allclose(P[:, 2], R[:, 0] @ R[:, 1] @ R[:, 2], atol=1e-13)


def test_batch_start_paper_accuracy_and_consistency(paper1):
    """From the batch result: every error ≤ 1.5 × the batch's own error + 1 batch σ, ≥ 95 % inside 3σ."""
    sim, batch = paper1
    res = replay([sim.data], batch)
    truth = sim.truth.calibration
    assert not [e for e in res.events if e["kind"] == "divergence"]
    inside = []
    b_err = {(s, p): e for s, p, e, _ in _errors(batch, truth)}
    b_sig = {(s, p): sg for s, p, _, sg in _errors(batch, truth)}
    for s, p, e, sg in _errors(res.calibration, truth):
        assert np.all(np.abs(e) <= 1.5 * np.abs(b_err[s, p]) + b_sig[s, p]), (s, p, e, b_err[s, p])
        inside += list(np.abs(e) < 3 * sg)
    assert np.mean(inside) >= 0.95
    assert res.nis["mag"]["in_band"] >= 0.8
    # every parameter has its σ, and the JSON round-trips
    cal2 = Calibration.from_json(res.calibration.to_json())
    assert cal2.source == "online"
    for s in SENSORS:
        assert set(PARAMS) <= set(cal2.sensor(s).sigma)


def test_gyro_nonorthogonality_from_rich_motion(paper1):
    """xi_gyr from the paper session's turns and tumble, no rate table: gyro cold (prior σ 0.02 rad)."""
    sim, batch = paper1
    res = replay([sim.data], batch.replace(gyro=None))
    c, t = res.calibration.gyro, sim.truth.calibration.gyro
    err, sig = c.xi - t.xi, np.asarray(c.sigma["xi"])
    assert np.all(np.abs(err) < 3 * sig), (err, sig)
    assert np.all(sig < 1e-3)  # prior 0.02 rad: excited by the motion
    assert np.all(np.abs(err) < 2e-3)
    assert all(res.observability[f"gyro.xi.{a}"]["excited"] for a in "xyz")


def test_cold_gyro_bias_and_scale_within_60s_of_motion(paper1):
    """Cold gyro and accel (mag from the batch): after the 30-s rest and 60 s of motion."""
    sim, batch = paper1
    d = sim.data.slice_imu(0, int(np.searchsorted(sim.data.t_imu, 90.0)))
    res = replay([d], batch.replace(gyro=None, accel=None))
    c, t = res.calibration.gyro, sim.truth.calibration.gyro
    for p in ("bias", "scale"):
        err, sig = c.params()[p] - t.params()[p], np.asarray(c.sigma[p])
        assert np.all(np.abs(err) < 3 * sig), (p, err, sig)
    assert np.all(np.asarray(c.sigma["scale"]) < 0.01)  # from 0.2


def test_streaming_blocks_and_checkpoint_resume():
    """Any block size gives the same answer; a JSON checkpoint mid-stream resumes exactly."""
    sim = simulate("paper", 3, duration=70.0)
    d = sim.data
    ref = replay([d], None)
    cal = OnlineCalibrator(None)
    cal.new_log()
    rng = np.random.default_rng(1)
    i = 0
    while i < d.n_imu:
        n = int(rng.integers(1, 400))
        cal.feed(d.slice_imu(i, i + n))
        i += n
        if i > d.n_imu // 2 and not hasattr(cal, "_resumed"):
            state = json.loads(json.dumps(cal.get_state()))
            cal = OnlineCalibrator.from_state(state)
            cal._resumed = True
    cal.flush()
    a, b = cal.result(), ref.calibration
    for s in SENSORS:
        assert np.allclose(a.sensor(s).matrix, b.sensor(s).matrix, rtol=0, atol=1e-9)
        assert np.allclose(a.sensor(s).bias, b.sensor(s).bias, rtol=0, atol=1e-9)
    assert len(cal.trace_rows()) > 10 and "gyro.scale.x.sigma" in cal.trace_rows()[0]


def _sim_traj(traj: Trajectory, seed: int, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr(simsens, "make_trajectory", lambda profile, rng, duration: traj)
    return simulate("paper", seed)


def _offset_prior(truth: Calibration, seed: int) -> Calibration:
    """The truth moved by 0.8 prior σ in random directions, with that σ: the filter's start."""
    rng = np.random.default_rng(seed)
    sig = {"gyro": {"bias": 2e-3, "scale": 5e-3, "alpha": 5e-3, "xi": 5e-3},
           "accel": {"bias": 0.03, "scale": 3e-3, "alpha": 5e-3, "xi": 5e-3},
           "mag": {"bias": 3e-3, "scale": 0.02, "alpha": 5e-3, "xi": 5e-3}}
    out = {}
    for s in SENSORS:
        p = truth.sensor(s).params()
        new = {k: p[k] + 0.8 * sig[s][k] * np.sign(rng.normal(size=3)) for k in PARAMS}
        out[s] = type(truth.sensor(s)).from_params(new["bias"], new["scale"], new["alpha"], new["xi"],
                                                    sigma={k: [sig[s][k]] * 3 for k in PARAMS})
    return Calibration(source="batch", **out)


@pytest.mark.parametrize("kind", [
    "rest",
    "spin_z",
    pytest.param("constant_rate_x", marks=pytest.mark.xfail(
        reason="known: a constant-rate roll drags xi_gyr.y (alpha_y − xi_y is observable, their sum is "
               "not; the sum moves 3σ) — not fixed yet", strict=False)),
])
def test_degenerate_motion_does_not_drag_unexcited(kind, monkeypatch):
    tr = Trajectory()
    if kind == "rest":
        tr.hold(60.0)
    elif kind == "spin_z":
        tr.hold(5.0).spin(2, 3.0, 40.0, 2).hold(5.0)
    else:  # roll at a constant rate about body x (after a smooth start), axis horizontal
        tr.hold(5.0).spin(0, 0.25, 4.0, 0)
        w = 0.5
        a0 = tr.current.copy()

        def fn(tau, a0=a0, w=w):
            n = tau.shape[0]
            ang = np.tile(a0, (n, 1))
            ang[:, 0] += w * tau
            rate = np.zeros((n, 3))
            rate[:, 0] = w
            return ang, rate, np.zeros((n, 3))

        from onlinecal.sim.motion import Segment

        tr.segments.append(Segment("spin", 40.0, fn, a0 + np.array([w * 40.0, 0, 0]), axis=0))
    sim = _sim_traj(tr, 5, monkeypatch)
    init = _offset_prior(sim.truth.calibration, 5)
    cal = OnlineCalibrator(init, UKFConfig(init_inflation=1.0))
    cal.feed(sim.data)
    cal.flush()
    obs = cal.observability()
    truth = sim.truth.calibration
    n_unexc = 0
    for s in SENSORS:
        for p in PARAMS:
            sl = index(s, p)
            tv = truth.sensor(s).params()[p]
            for k, a in enumerate("xyz"):
                i = sl.start + k
                sig = float(np.sqrt(cal.P[i, i]))
                # consistent everywhere; where the motion does not reach (σ kept above 0.8 of the prior)
                # the estimate stays within one prior σ of where it started
                assert abs(cal.x[i] - tv[k]) < 3 * sig, (s, p, a, cal.x[i] - tv[k], sig)
                if obs[f"{s}.{p}.{a}"]["ratio"] > 0.8:
                    n_unexc += 1
                    assert abs(cal.x[i] - cal.prior_x[i]) <= cal.prior_sigma[i], (s, p, a)
    assert n_unexc >= 10
    assert cal.missing_motion()


def test_divergence_reinitialises(paper1):
    sim, batch = paper1
    d = sim.data
    cal = OnlineCalibrator(batch)
    cal.feed(d.slice_imu(0, 2000))
    cal.P[5, 5] = -1.0  # a covariance that is not positive definite
    cal.feed(d.slice_imu(2000, 2500))
    assert any(e["kind"] == "divergence" for e in cal.events)
    assert np.all(np.linalg.eigvalsh(cal.P) > 0)
    # a mag that suddenly reads a different field: sustained NIS far above the band
    cal2 = OnlineCalibrator(batch)
    bad = d.slice_imu(3000, 9000)
    bad.mag = bad.mag * 1.5
    cal2.feed(d.slice_imu(0, 3000))
    cal2.feed(bad)
    assert any(e["kind"] == "divergence" and "mag" in e["detail"] for e in cal2.events)
