import numpy as np

from onlinecal.sim import Truth, simulate
from onlinecal.sim.motion import G0, paper_trajectory


def test_body_rate_matches_attitude_derivative():
    tr = paper_trajectory(np.random.default_rng(3))
    t = np.linspace(0, tr.duration - 0.01, 3000)
    h = 1e-6
    m0, m1 = tr.evaluate(t), tr.evaluate(t + h)
    W = np.einsum("nji,njk->nik", m0.R, (m1.R - m0.R) / h)  # Rᵀ Ṙ = [ω]x
    w = np.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], 1)
    assert np.abs(w - m0.omega).max() < 1e-4


def test_paper_session_structure():
    sim = simulate("paper", 5)
    segs = sim.truth.segments
    spins = [s for s in segs if s["kind"] == "spin"]
    assert sorted({s["axis"] for s in spins}) == ["x", "y", "z"]
    statics = [s for s in segs if s.get("label") == "static position"]
    assert len(statics) == 12
    d = sim.data
    assert abs(d.imu_rate - 100) < 1e-6 and abs(1 / np.median(np.diff(d.t_mag)) - 50) < 1e-6
    assert 280 < d.duration < 330


def test_raw_follows_truth_model_at_rest():
    sim = simulate("paper", 6, noise=0.0)
    cal = sim.truth.calibration
    d = sim.data
    rest = d.t_imu < 29
    f = cal.accel.apply(d.acc[rest])
    assert np.abs(np.linalg.norm(f, axis=1) - G0).max() < 0.01  # quantisation only
    w = cal.gyro.apply(d.gyro[rest])
    assert np.abs(w).max() < 2e-3
    h = cal.mag.apply(d.mag)
    assert np.abs(np.linalg.norm(h, axis=1) - 1).max() < 2e-3


def test_truth_round_trip(tmp_path):
    sim = simulate("flight", 1, duration=60)
    p = tmp_path / "t.json"
    sim.truth.save(p)
    back = Truth.load(p)
    assert back.calibration == sim.truth.calibration and back.profile == "flight"
    # flight has translational acceleration: specific-force norm departs from g
    m = sim.trajectory.evaluate(sim.data.t_imu)
    assert np.abs(np.linalg.norm(m.f, axis=1) - G0).max() > 0.5


def test_seeds_change_the_truth():
    a, b = simulate("paper", 1).truth.calibration, simulate("paper", 2).truth.calibration
    assert not np.allclose(a.gyro.bias, b.gyro.bias)


# -- flight profiles from vehicle physics (issue 10) -------------------------------------------------

def test_vehicle_profiles_physics():
    """Multirotor: specific force near body z (thrust) with linear accelerations up to ~3 m/s²; fixed-wing:
    coordinated turns (no body-y specific force) with the centripetal acceleration of the bank; both
    start with a disarmed rest of ≥ 30 s where the rate is exactly zero and |f| = g."""
    from onlinecal.sim.flight import fixedwing_trajectory, multirotor_trajectory

    for fn in (multirotor_trajectory, fixedwing_trajectory):
        tr = fn(np.random.default_rng(7), 300.0)
        t = np.arange(0, tr.duration, 0.005)
        m = tr.evaluate(t)
        rest = t < 30.0
        assert np.abs(m.omega[rest]).max() == 0.0
        assert np.abs(np.linalg.norm(m.f[rest], axis=1) - G0).max() < 1e-9
        fl = t > 60.0
        a = np.linalg.norm(m.a_world[fl], axis=1)
        assert a.max() > 1.5  # real linear accelerations
        # the specific force is the kinematics: f = Rᵀ (a + g ẑ)
        f = np.einsum("nji,nj->ni", m.R, m.a_world + np.array([0, 0, G0]))
        assert np.abs(f - m.f).max() < 1e-9
        yaw = np.unwrap(m.euler[:, 2])
        assert np.ptp(yaw) > np.pi  # yaw turns
        if tr.kind == "multirotor":
            assert a.max() < 3.6
            # thrust along body z: x/y specific force is rotor drag (≤ k·v) and attitude lag only
            tilt_dir = np.abs(m.f[fl, :2]).max()
            assert tilt_dir < 0.35 * np.abs(m.f[fl, 2]).min()
        else:
            # coordinated flight: the specific force stays in the body x–z plane
            assert np.abs(m.f[fl, 1]).max() < 0.3
            assert np.degrees(np.arccos(np.clip(m.R[fl, 2, 2], -1, 1))).max() > 15  # banked turns


def test_vehicle_rate_matches_attitude():
    from scipy.spatial.transform import Rotation

    from onlinecal.sim.flight import multirotor_trajectory

    # the attitude is the exact integral of a rate held over each 1-ms step; a gyro sample is the rate at t,
    # i.e. the mean over the step-long window centred on t (between step midpoints, not the next step's)
    tr = multirotor_trajectory(np.random.default_rng(3), 200.0)
    t = np.random.default_rng(0).uniform(0.01, tr.duration - 0.01, 3000)
    h = tr.dt / 2
    m0, ma, mb = tr.evaluate(t), tr.evaluate(t - h), tr.evaluate(t + h)
    w = Rotation.from_matrix(np.einsum("nji,njk->nik", ma.R, mb.R)).as_rotvec() / (2 * h)
    assert np.abs(w - m0.omega).max() < 1e-4


def test_vehicle_vibration_and_interference(tmp_path):
    """Healthy vibration: a few m/s² RMS while armed, none before arming; mag interference ∝ throttle."""
    sim = simulate("multirotor", 2, duration=120.0, imu_rate=200.0, noise=0.0)
    sim2 = simulate("multirotor:vibration=0,mag_interference=0.2", 2, duration=120.0, imu_rate=200.0, noise=0.0)
    v = sim.truth.vehicle
    assert v["kind"] == "multirotor" and v["armed_at"] >= 30.0
    cal = sim.truth.calibration
    d, d2 = sim.data, sim2.data
    vib = cal.accel.apply(d.acc) - cal.accel.apply(d2.acc)
    pre = d.t_imu < v["armed_at"] - 0.01
    assert np.abs(vib[pre]).max() < 1e-9
    rms = vib[d.t_imu > 60].std(0)
    assert 1.0 < rms.min() and rms.max() < 10.0  # healthy: below ArduPilot's 15-30 m/s² concern levels
    # interference: the calibrated field's norm departs from 1 only in flight
    h0 = np.linalg.norm(cal.mag.apply(sim.data.mag), axis=1)
    h1 = np.linalg.norm(cal.mag.apply(sim2.data.mag), axis=1)
    assert np.abs(h1 - h0)[d2.t_mag < 30].max() < 1e-9
    assert np.abs(h1 - h0)[d2.t_mag > 60].max() > 0.02


def test_profile_spec_errors():
    import pytest

    from onlinecal.sim import ProfileError, parse_profile

    assert parse_profile("fixedwing:vibration=3") == ("fixedwing", {"vibration": 3.0})
    for bad in ("heli", "multirotor:vib=3", "multirotor:vibration=x", "paper:vibration=1",
                "multirotor:rest=10", "multirotor:vibration=-1"):
        with pytest.raises(ProfileError):
            parse_profile(bad)


def test_motor_lag_is_scipys_first_order_filter():
    # the motors' throttle lag (sim.effects._first_order_lag, compiled so a flight simulation does not import
    # scipy.signal) against scipy.signal.lfilter with the same coefficients and initial state: the same bits,
    # on a random series and on a throttle that steps between two levels
    from scipy.signal import lfilter

    from onlinecal.sim.effects import TAU_MOTOR_S, _first_order_lag

    rng = np.random.default_rng(4)
    a = 1e-3 / (TAU_MOTOR_S + 1e-3)
    for u in (rng.uniform(0, 1, 20000), np.where(rng.uniform(size=20000) > 0.5, 0.7, 0.05)):
        ref = lfilter([a], [1.0, a - 1.0], u, zi=[(1.0 - a) * u[0]])[0]
        got = _first_order_lag(u, a)
        assert np.array_equal(got, ref)
        assert np.ptp(got) > 0.1  # it moved: the comparison is not of two constants
