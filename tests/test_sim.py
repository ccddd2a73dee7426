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
