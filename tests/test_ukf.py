"""Augmented-state UKF (onlinecal.ukf): model layout, accuracy from the batch start, streaming/checkpoint,
degenerate motions, divergence handling, gyro non-orthogonality from rich motion, cold-start gyro."""

from __future__ import annotations

import json

import numpy as np
import pytest
from benchload import benchmark

import onlinecal.sim.sensors as simsens
from onlinecal.batch.pipeline import run_batch
from onlinecal.io.base import ImuData
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


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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
    return benchmark("robust_disturbance").offset_prior(truth, seed)


def _ramped_rate(tr: Trajectory, gimbal: int, w: float, T: float, body_axis: int, T_ramp: float = 3.0):
    """A turn of one gimbal whose rate rises smoothly (quintic) to ``w`` rad/s, then stays constant."""
    from onlinecal.sim.motion import Segment, smoothstep

    a0 = tr.current.copy()

    def fn(tau, a0=a0):
        u = np.clip(tau / T_ramp, 0.0, 1.0)
        s, _, _ = smoothstep(u)
        S = 2.5 * u**4 - 3 * u**5 + u**6  # ∫ smoothstep
        ang = np.tile(a0, (tau.shape[0], 1))
        ang[:, gimbal] += np.where(tau < T_ramp, w * T_ramp * S, w * T_ramp * 0.5 + w * (tau - T_ramp))
        rate = np.zeros((tau.shape[0], 3))
        rate[:, gimbal] = w * s
        return ang, rate, np.zeros((tau.shape[0], 3))

    end = a0.copy()
    end[gimbal] += w * (T - T_ramp * 0.5)
    tr.segments.append(Segment("spin", T, fn, end, axis=body_axis))
    return tr


def _translate(tr: Trajectory, T: float, amp: float, yaw_deg: float = 0.0):
    """Horizontal back-and-forth acceleration (amp m/s², 1 Hz·k mix) with, optionally, a yaw swing of
    ``yaw_deg`` (planar motion); no roll or pitch."""
    from onlinecal.sim.motion import Segment

    a0 = tr.current.copy()
    yaw = np.radians(yaw_deg)

    def fn(tau, a0=a0):
        n = tau.shape[0]
        ang = np.tile(a0, (n, 1))
        ang[:, 2] += yaw * np.sin(2 * np.pi * tau / 8.0)
        rate = np.zeros((n, 3))
        rate[:, 2] = yaw * 2 * np.pi / 8.0 * np.cos(2 * np.pi * tau / 8.0)
        acc = np.zeros((n, 3))
        acc[:, 0] = amp * np.sin(2 * np.pi * tau / 2.0)
        acc[:, 1] = 0.5 * amp * np.sin(2 * np.pi * tau / 3.0)
        return ang, rate, acc

    tr.segments.append(Segment("flight", T, fn, a0.copy()))
    return tr


# Yang, Geneva, Zuo, Huang, "Online IMU Intrinsic Calibration: Is It Necessary?", RSS 2020: primitive
# motions that leave IMU intrinsics unobservable. Per motion: the trajectory and gyro scale axes it
# cannot excite (the rate never has a component along them, or only a constant one that the bias
# absorbs), which the filter must report unexcited and leave where they started.
DEGENERATE = {
    "no_rotation": (lambda tr: tr.hold(60.0), "xyz"),
    "pure_translation": (lambda tr: _translate(tr.hold(3.0), 50.0, 2.0), "xyz"),
    "one_axis_vertical": (lambda tr: tr.hold(5.0).spin(2, 3.0, 40.0, 2).hold(5.0), "xy"),
    "one_axis_horizontal": (lambda tr: tr.hold(5.0).spin(0, 1.0, 20.0, 0).spin(0, -1.0, 20.0, 0).hold(5.0), "yz"),
    "constant_rate_roll": (lambda tr: _ramped_rate(tr.hold(5.0), 0, 0.5, 45.0, 0), "yz"),
    "planar": (lambda tr: _translate(tr.hold(3.0), 50.0, 2.0, yaw_deg=60.0), "xy"),
}


@pytest.mark.slow
@pytest.mark.parametrize("kind", list(DEGENERATE))
def test_degenerate_motion_does_not_drag_unexcited(kind, monkeypatch):
    build, unexc_axes = DEGENERATE[kind]
    sim = _sim_traj(build(Trajectory()), 5, monkeypatch)
    init = _offset_prior(sim.truth.calibration, 5)
    cal = OnlineCalibrator(init, UKFConfig(init_inflation=1.0))
    cal.feed(sim.data)
    cal.flush()
    assert not [e for e in cal.events if e["kind"] in ("divergence", "saturation")], cal.events
    obs = cal.observability()
    truth = sim.truth.calibration
    q_rw = cal._cal_rw()  # random-walk variance per second of every state
    n_unexc = 0
    for s in SENSORS:
        for p in PARAMS:
            sl = index(s, p)
            tv = truth.sensor(s).params()[p]
            for k, a in enumerate("xyz"):
                i = sl.start + k
                sig = float(np.sqrt(cal.P[i, i]))
                # consistent everywhere; where the motion does not reach (σ kept above 0.8 of the prior)
                # the estimate moves no more than the information it gained allows: the shift of the mean
                # by Gaussian updates has variance (σ0² + the random walk's q·T) − σ² — 3 of those: at most
                # ~1.8 σ0 at ratio 0.8 — and, for a term the data never touched, a tenth of σ0 (the
                # unscented transform's second-order shift of the mean, which no variance records)
                assert abs(cal.x[i] - tv[k]) < 3 * sig, (s, p, a, cal.x[i] - tv[k], sig)
                ratio = obs[f"{s}.{p}.{a}"]["ratio"]
                if ratio > 0.8:
                    n_unexc += 1
                    gained = cal.prior_sigma[i] ** 2 + q_rw[i] * sim.data.duration - sig**2
                    allowed = max(3 * np.sqrt(max(gained, 0.0)), 0.1 * cal.prior_sigma[i])
                    assert abs(cal.x[i] - cal.prior_x[i]) <= allowed, (s, p, a, ratio)
    # the axes the motion cannot excite are reported unexcited
    for a in unexc_axes:
        assert not obs[f"gyro.scale.{a}"]["excited"], (kind, a, obs[f"gyro.scale.{a}"])
        assert obs[f"gyro.scale.{a}"]["ratio"] > 0.8
    assert n_unexc >= 10
    assert any(f"turn about {a}" in m for m in cal.missing_motion() for a in unexc_axes)


@pytest.mark.slow
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
    bad = d.slice_imu(3000, 20000)  # sustained: beyond the disturbance gate's 45 s (magdisturb.MAX_S)
    bad.mag = bad.mag * 1.5
    cal2.feed(d.slice_imu(0, 3000))
    cal2.feed(bad)
    assert any(e["kind"] == "divergence" and "mag" in e["detail"] for e in cal2.events)


def _consistent_share(cal: Calibration, truth: Calibration) -> float:
    inside = []
    for _, _, e, sg in _errors(cal, truth):
        inside += list(np.abs(e) < 3 * sg)
    return float(np.mean(inside))


def test_hold_sigma_bounds_double_quantisation():
    """The hold bound q/√12·exp(−σ/q) covers the rms mean error of a reading quantised by a sensor lattice
    and re-quantised to q (positions uniform on the lattice), for the sensor lattices and noise it claims."""
    from onlinecal.ukf.filter import hold_sigma

    rng = np.random.default_rng(0)
    q = 1.0
    for a_rel in (0.239, 0.3, 0.533):
        for s_rel in (0.3, 0.5, 1.0):
            n = rng.normal(0, s_rel, 20000)
            err = []
            for x in rng.uniform(0, 10, 60):
                y1 = np.round((x + n) / a_rel) * a_rel
                err.append(np.round(y1 / q).mean() * q - x)
            rms = float(np.sqrt(np.mean(np.square(err))))
            assert rms < hold_sigma(q, s_rel), (a_rel, s_rel, rms, hold_sigma(q, s_rel))
    # and it is not vacuous: without dither it is the uniform error's σ
    assert hold_sigma(1.0, 0.0) == pytest.approx(1 / np.sqrt(12))


def test_value_lattice_detection():
    from onlinecal.ukf.filter import value_lattice

    rng = np.random.default_rng(2)
    v = rng.normal(0, 0.01, (64, 3))
    assert value_lattice(v) == 0.0  # floats: no lattice
    assert value_lattice(np.round(v / 1e-3) * 1e-3) == pytest.approx(1e-3)
    assert value_lattice(np.round(v / 9.80665e-3) * 9.80665e-3) == pytest.approx(9.80665e-3)


@pytest.fixture(scope="module")
def short_paper():
    sim = simulate("paper", 7, duration=150.0)
    return sim, _offset_prior(sim.truth.calibration, 7)


@pytest.mark.slow
def test_saturated_gyro_is_skipped_not_integrated(short_paper):
    """A gyro clipped at ±125 dps (the rotation phases peak at ~2.4 rad/s): the filter learns the rail,
    says so, skips those blocks instead of integrating the clipped rate, and stays consistent."""
    from onlinecal.sim.effects import parse_effect

    _, init = short_paper
    sim = simulate("paper", 7, effects=[parse_effect("saturation:sensor=gyro")])
    assert np.mean(np.abs(sim.data.gyro).max(axis=1) >= 2.18) > 0.005  # the log really is clipped
    res = replay([sim.data], init, UKFConfig(init_inflation=1.0))
    sat = [e for e in res.events if e["kind"] == "saturation"]
    assert sat and "gyro" in sat[0]["detail"]
    assert not [e for e in res.events if e["kind"] == "divergence"]
    truth = sim.truth.calibration
    g = res.calibration.gyro
    assert np.all(np.abs(g.scale - truth.gyro.scale) < 3 * np.asarray(g.sigma["scale"]))
    assert _consistent_share(res.calibration, truth) >= 0.95
    # integrated as if true, the clipped rate would under-turn every peak: compare with the rail ignored. That run
    # diverges (the magnetometer's NIS runs away; until session 17 it also ended with accel terms 17σ off, its
    # 56 % within 3σ: now the gate's drops take the under-turned attitude for unmodelled motion, a vehicle, and
    # hold the accelerometer's terms, so its restarts leave them at a wide σ)
    res_raw = replay([sim.data], init, UKFConfig(init_inflation=1.0, rail_min={"gyro": 1e9, "accel": 1e9}))
    assert [e for e in res_raw.events if e["kind"] == "divergence"]
    assert any(e["kind"] == "vehicle" and "gate dropped" in e["detail"] for e in res_raw.events)


@pytest.mark.slow
def test_tenfold_noise_is_flagged_and_recovered(short_paper):
    """10× noise on every sensor for 20 s: raised as an event, weighted down, back to the spec after."""
    sim, init = short_paper
    d = sim.data
    rng = np.random.default_rng(3)
    m = (d.t_imu > 60) & (d.t_imu < 80)
    mm = (d.t_mag > 60) & (d.t_mag < 80)
    sig = sim.truth.noise
    d2 = d.slice_imu(0, d.n_imu)
    d2.gyro = d.gyro.copy()
    d2.acc = d.acc.copy()
    d2.mag = d.mag.copy()
    d2.gyro[m] += rng.normal(0, np.sqrt(99) * sig["gyro"], (m.sum(), 3))
    d2.acc[m] += rng.normal(0, np.sqrt(99) * sig["accel"], (m.sum(), 3))
    d2.mag[mm] += rng.normal(0, np.sqrt(99) * sig["mag"], (mm.sum(), 3))
    res = replay([d2], init, UKFConfig(init_inflation=1.0))
    kinds = [(e["kind"], e["detail"].split()[0]) for e in res.events]
    for s in ("gyro", "accel"):
        hi = [e["t"] for e in res.events if e["kind"] == "noise_high" and e["detail"].startswith(s)]
        lo = [e["t"] for e in res.events if e["kind"] == "noise_normal" and e["detail"].startswith(s)]
        assert hi and 60 <= hi[0] < 66, kinds
        assert lo and 80 <= lo[-1] < 90 and lo[-1] > hi[-1], kinds
    assert not [e for e in res.events if e["kind"] == "divergence"], kinds
    assert _consistent_share(res.calibration, sim.truth.calibration) >= 0.95


@pytest.mark.slow
def test_long_gap_restarts_attitude_and_recovers(short_paper):
    """5 s without samples mid-session: a gap event, the attitude restarts, the calibration carries on."""
    sim, init = short_paper
    d = sim.data
    i0, i1 = np.searchsorted(d.t_imu, [70.0, 75.0])
    gapped = ImuData.concat([d.slice_imu(0, i0), d.slice_imu(i1, d.n_imu)])
    res = replay([gapped], init, UKFConfig(init_inflation=1.0))
    gaps = [e for e in res.events if e["kind"] == "gap"]
    assert len(gaps) == 1 and 74.9 < gaps[0]["t"] < 75.1
    assert not [e for e in res.events if e["kind"] == "divergence"]
    assert _consistent_share(res.calibration, sim.truth.calibration) >= 0.95
    # after the gap the accel and mag innovations are back in their band (the attitude recovered)
    assert res.nis["mag"]["in_band"] >= 0.8


@pytest.mark.slow
def test_cold_accel_at_one_static_pose_stays_consistent():
    """Cold accelerometer, 30 s of rest in one attitude: one pose says little about the accel (its norm
    along gravity), and the filter must not claim more. Updating with every block at a drifting
    linearisation point claimed it (o = a − g/s is a curve): 3–7σ off on every seed before the rest's
    readings were made one measurement (``OnlineCalibrator._rest_step``)."""
    from scipy.stats import chi2

    for seed in range(4):
        sim = simulate("paper", seed, duration=30.0)
        init = _offset_prior(sim.truth.calibration, seed).replace(accel=None)
        res = replay([sim.data], init, UKFConfig(init_inflation=1.0))
        c, t = res.calibration.accel, sim.truth.calibration.accel
        z = np.concatenate([(c.params()[p] - t.params()[p]) / np.asarray(c.sigma[p]) for p in PARAMS])
        assert np.all(np.abs(z) < 3), (seed, np.round(z, 2))
        assert float(z @ z) < chi2.ppf(0.999, 12), (seed, float(z @ z))


@pytest.mark.slow
def test_noise_monitor_ignores_dropped_samples(short_paper):
    """10 % of the IMU samples dropped at random: the third differences across a missing sample hold the
    motion over it, not noise; they are left out, so no noise event is raised (the full log raises none)
    and the result stays within 1σ of the full log's."""
    sim, init = short_paper
    d = sim.data
    rng = np.random.default_rng(4)
    keep = np.concatenate([[0], 1 + np.flatnonzero(rng.random(d.n_imu - 1) >= 0.1)])
    dropped = ImuData(d.t_imu[keep], d.gyro[keep], d.acc[keep], d.temp[keep], d.t_mag, d.mag)
    full = replay([d], init, UKFConfig(init_inflation=1.0))
    res = replay([dropped], init, UKFConfig(init_inflation=1.0))
    assert not [e for e in full.events if e["kind"].startswith("noise")]
    assert not [e for e in res.events if e["kind"].startswith("noise")], res.events[:4]
    z = []
    for s in SENSORS:
        for p in PARAMS:
            a, b = res.calibration.sensor(s), full.calibration.sensor(s)
            z += list((a.params()[p] - b.params()[p]) / np.asarray(b.sigma[p]))
    assert np.max(np.abs(z)) < 1.0, np.round(np.sort(np.abs(z))[-5:], 2)


def test_coning_term_of_the_attitude_integration():
    """The Δt²/12 ω_k−1 × ω_k term halves the attitude error of a coning motion sampled at 100 Hz (against
    a 20 kHz reference), and propagate_block integrates the same way for every sigma point."""
    from onlinecal.ukf.propagate import propagate_block

    def omega(t):
        return np.stack([2 * np.cos(3 * t), 2 * np.sin(3 * t), 1.0 + 0 * t], -1)

    def integ(rate, corr):
        t = np.linspace(0, 2.0, int(2.0 * rate) + 1)
        w, dt = omega(t), 1.0 / rate
        th = 0.5 * (w[1:] + w[:-1]) * dt + corr * dt * dt / 12 * np.cross(w[:-1], w[1:])
        R = prefix_products(rodrigues(th)[None])[0, -1]
        return R, t, w

    ref = integ(20000, 0)[0]
    err = {c: np.linalg.norm(rot_log(ref.T @ integ(100, c)[0])) for c in (0, 1)}
    assert err[1] < 0.6 * err[0], err
    R1, t, w = integ(100, 1)
    x = np.zeros((3, 40))
    x[:, index("gyro", "scale")] = 1.0
    out = propagate_block(x, np.eye(3), w, np.diff(t), None, np.arange(1),
                          correction(x[:1, 3:15]))
    assert np.allclose(out.R_end[0], R1, atol=1e-12)


EXT_CASES = {
    "temperature_bias:gyro": ("temperature_bias:sensor=gyro,coeff=6e-4", "temperature_bias", "gyro", 6e-4),
    "temperature_bias:accel": ("temperature_bias:sensor=accel,coeff=5e-3", "temperature_bias", "accel", 5e-3),
    "g_sensitivity": ("g_sensitivity:coeff=3e-4", "g_sensitivity", "gyro", 3e-4),
}


@pytest.mark.slow
@pytest.mark.parametrize("ext", list(EXT_CASES))
def test_extension_state_recovers_hidden_effect(ext):
    """An extension state converges to the simulated effect within 3σ (to a few % of it), stays within 3σ
    of zero when the effect is absent, and is reported in the effect vocabulary the rest of the package
    reads (``onlinecal.extensions``) with its σ in the meta."""
    from onlinecal.extensions import validate_extensions
    from onlinecal.sim.effects import parse_effect

    spec, name, sensor, coeff = EXT_CASES[ext]
    for effects, truth in (([parse_effect(spec)], coeff), ([], 0.0)):
        sim = simulate("paper", 3, effects=effects)
        init = _offset_prior(sim.truth.calibration, 3)
        res = replay([sim.data], init, UKFConfig(init_inflation=1.0, extra_states=(ext,)))
        e = res.calibration.extensions[name]
        assert e["sensor"] == sensor and e["axis"] is None
        k = np.asarray(e["coeff"])
        sig = np.asarray(res.calibration.meta["online"]["extensions_sigma"][ext])
        assert np.all(np.abs(k - truth) < 3 * sig), (ext, truth, k, sig)
        assert np.all(sig < 0.1 * coeff)  # resolved, not merely left at its prior
        validate_extensions(res.calibration.extensions)
        cal2 = Calibration.from_json(res.calibration.to_json())
        assert cal2.extensions == res.calibration.extensions


@pytest.mark.slow
def test_cold_gyro_and_accel_within_60s_of_motion_six_seeds():
    """The paper's error magnitudes (15 % gyro scale, 0.16 rad/s gyro bias; accel likewise) from a cold
    start of gyro and accel — prior σ 0.2 and 0.2 rad/s, 0.05 and 0.5 m/s², mag known to a few σ — after
    the 30-s rest and 60 s of turns to static positions: every bias and scale of both within 3σ, and
    resolved (scale σ below 1 %), on each of six seeds."""
    for seed in range(6):
        sim = simulate("paper", seed, duration=90.0)
        init = _offset_prior(sim.truth.calibration, seed).replace(gyro=None, accel=None)
        res = replay([sim.data], init)
        assert not [e for e in res.events if e["kind"] == "divergence"], (seed, res.events)
        for s in ("gyro", "accel"):
            c, t = res.calibration.sensor(s), sim.truth.calibration.sensor(s)
            for p in ("bias", "scale"):
                err, sig = c.params()[p] - t.params()[p], np.asarray(c.sigma[p])
                assert np.all(np.abs(err) < 3 * sig), (seed, s, p, err / sig)
            assert np.all(np.asarray(c.sigma["scale"]) < 0.01), (seed, s, c.sigma["scale"])


@pytest.mark.slow
def test_init_none_all_three_sensors_within_60s_of_motion():
    """``--init none``: nothing from the batch, the mag from its own cold sphere fit (after ~30 s of the
    motion). After the 30-s rest and 60 s of motion every bias and scale of all three sensors is within
    3σ, and every scale resolved to a tenth of its cold prior σ or better (20 % → 2 % gyro, 5 % → 0.5 %
    accel, 30 % → 3 % mag). Over the whole session the mag needs the batch start to stay consistent (see
    the README: 7/12 seeds without it)."""
    for seed in (7, 8):
        sim = simulate("paper", seed, duration=90.0)
        res = replay([sim.data], None)
        assert [e for e in res.events if e["kind"] == "mag_cold_start"], res.events
        assert not [e for e in res.events if e["kind"] == "divergence"], (seed, res.events)
        for s in SENSORS:
            c, t = res.calibration.sensor(s), sim.truth.calibration.sensor(s)
            for p in ("bias", "scale"):
                err, sig = c.params()[p] - t.params()[p], np.asarray(c.sigma[p])
                assert np.all(np.abs(err) < 3 * sig), (seed, s, p, err / sig)
            rel = np.asarray(c.sigma["scale"]) / np.abs(c.scale)
            assert np.all(rel < 0.1 * UKFConfig().cold_sigma[s]["scale"]), (seed, s, rel)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 3, 6])
def test_cold_start_with_batch_mag(seed):
    """Cold gyro and accel, the mag from the batch (a tighter prior than the six-seed test's), after the
    30-s rest and 60 s of motion: every bias and scale within 3σ. These three seeds ended 4–5σ off while
    a block's update could remove half the prior's variance (update_damping 1): the first turns to the
    static positions (up to 180°) under a 20 % gyro-scale prior were narrowed in one linearisation."""
    sim = simulate("paper", seed)
    batch = run_batch([sim.data]).calibration
    d = sim.data.slice_imu(0, int(np.searchsorted(sim.data.t_imu, 90.0)))
    res = replay([d], batch.replace(gyro=None, accel=None))
    assert not [e for e in res.events if e["kind"] == "divergence"], res.events
    for s in ("gyro", "accel"):
        c, t = res.calibration.sensor(s), sim.truth.calibration.sensor(s)
        for p in ("bias", "scale"):
            err, sig = c.params()[p] - t.params()[p], np.asarray(c.sigma[p])
            assert np.all(np.abs(err) < 3 * sig), (s, p, err / sig)
        assert np.all(np.asarray(c.sigma["scale"]) < 0.01), (s, c.sigma["scale"])  # resolved, from 0.2 / 0.05


@pytest.mark.slow
def test_memory_does_not_grow_with_the_log():
    """The filter's retained memory after 400 s of a streamed flight is what it was after 100 s: state,
    buffers and the mag fit's sample store are bounded (the trace is off here; it is capped by
    ``trace_max_rows`` and events by ``max_events``)."""
    import tracemalloc

    sim = simulate("flight", 4, duration=400.0)
    d = sim.data
    cal = OnlineCalibrator(None, UKFConfig(trace_every_s=1e9))
    cal.new_log()
    marks = {int(np.searchsorted(d.t_imu, 100.0)): None, d.n_imu: None}
    tracemalloc.start()
    try:
        i = 0
        while i < d.n_imu:
            j = min(i + 500, d.n_imu)
            cal.feed(d.slice_imu(i, j))
            for m in marks:
                if i < m <= j:
                    marks[m] = tracemalloc.get_traced_memory()[0]
            i = j
    finally:
        tracemalloc.stop()
    early, late = marks.values()
    # measured 119 kB and 118 kB: 4× the log, not 4× the memory
    assert late < 1.5 * early, (early, late)
