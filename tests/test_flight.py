"""The online filter in the air (issue 10): flight profiles, the vehicle-acceleration model, observability.

Truth comes from the simulator's vehicle physics (``onlinecal.sim.flight``), never from the filter; the
statistical flight runs are reduced-seed versions of ``benchmarks/flight_stats.py`` and marked slow.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from benchload import benchmark

from onlinecal.sim import simulate
from onlinecal.ukf import replay
from onlinecal.ukf.filter import OnlineCalibrator, UKFConfig
from onlinecal.ukf.vehicle import MotionCoverage, VehicleDetector, observability_text, vehicle_accel_var

ROOT = Path(__file__).resolve().parents[1]


def _flight_stats():
    return benchmark("flight_stats")


# -- unit level -------------------------------------------------------------------------------------

def test_vehicle_detector_vibration_and_linear_acceleration():
    d = VehicleDetector(vibration_sigma=0.3, dev_min=0.5, dev_blocks=5)
    assert d.update(0.02, 0.0, 1.0) is None  # sensor noise of a MEMS part
    for k in range(4):
        assert d.update(float("nan"), 0.8, 2.0 + k) is None  # 4 blocks of deviation: not yet
    assert d.update(0.02, None, 6.0) is None  # a block without the norm test keeps the run
    why = d.update(float("nan"), 0.8, 7.0)
    assert why is not None and "linear acceleration" in why and d.active and d.since == 7.0
    d2 = VehicleDetector()
    assert "vibration" in (d2.update(0.7, None, 3.0) or "")


def test_vehicle_accel_var_is_coloured_not_white():
    """A disturbance correlated over τ carries one σ² measurement per τ: spread over the τ/Δt blocks it
    covers, the information of those blocks together is 1/σ², not τ/Δt times that."""
    s, tau, dt = 3.0, 30.0, 0.1
    v = vehicle_accel_var(s, tau, dt)
    assert v == pytest.approx(s**2 * tau / dt)
    assert (tau / dt) / v == pytest.approx(1 / s**2)
    assert vehicle_accel_var(s, 0.05, 0.1) == pytest.approx(s**2)


def test_motion_coverage_counts_turns_rests_and_field():
    c = MotionCoverage()
    c.add_motion(np.array([0.1, -0.5, 2.0]), 0.5, True)
    c.add_motion(np.array([0.2, 0.0, -1.0]), 0.5, False)
    assert np.allclose(c.max_rate, [0.2, 0.5, 2.0]) and np.allclose(c.angle, [0.15, 0.25, 1.5])
    assert c.flight_s == 0.5
    c.add_rest(np.array([0, 0, 9.8]), 1.0)
    c.add_rest(np.array([0, 0.1, 9.8]), 1.0)  # same attitude (< 20°)
    c.add_rest(np.array([9.8, 0, 0]), 1.0)
    assert len(c.rest_dirs) == 2 and c.gravity_axes() == ["+z", "+x"] and c.rest_s == 3.0
    c.add_field(np.array([[0, 0, 1.0], [0, 0, 2.0], [1.0, 1.0, 1.0]]))
    assert c.mag_dirs.sum() == 2


# -- the filter in flight ------------------------------------------------------------------------------

@pytest.mark.slow
def test_paper_session_is_not_a_vehicle():
    """The platform turns about a fixed point: no vibration, |f| = g. The detector stays off, so the
    accelerometer keeps its full weight in motion (the paper session's figures are unchanged)."""
    sim = simulate("paper", 3, duration=150.0)
    res = replay([sim.data], None)
    assert not any(e["kind"] == "vehicle" for e in res.events)
    obs = res.calibration.meta["online"]["observability"]
    assert obs["vehicle"]["active"] is False


@pytest.mark.slow
def test_vibrating_vehicle_detected_and_not_at_rest():
    """Armed on the ground with rotor vibration: detected at arming; the rest test (spec noise) rejects
    the vibrating stretches, so only the disarmed ones (before arming, after landing) are rests."""
    sim = simulate("multirotor", 4, duration=70.0, imu_rate=200.0)
    res = replay([sim.data], None)
    ev = [e for e in res.events if e["kind"] == "vehicle"]
    armed = sim.truth.vehicle["armed_at"]
    assert len(ev) == 1 and armed <= ev[0]["t"] < armed + 1.0 and "vibration" in ev[0]["detail"]
    cov = res.calibration.meta["online"]["observability"]["coverage"]
    tr = sim.trajectory
    disarmed_s = float(np.sum(~tr.armed)) * tr.dt  # before arming and after landing
    assert disarmed_s - 3.0 < cov["rest_s"] < disarmed_s + 0.5  # the disarmed stretches only


@pytest.mark.slow
def test_observability_report_in_json_and_words(tmp_path):
    """A short multirotor flight: the gyro bias is determined (ground rest), the gyro x/y scale is not,
    and the report says why (rates reached) and which motion would determine it; the JSON carries it."""
    log = tmp_path / "mr.csv"
    r = subprocess.run([sys.executable, "-m", "onlinecal", "simulate", "--out", str(log), "--profile",
                        "multirotor", "--duration", "120", "--rate", "200", "--seed", "5"],
                       capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    out = tmp_path / "cal.json"
    r = subprocess.run([sys.executable, "-m", "onlinecal", "replay", str(log), "--init", "none", "--json", str(out)],
                       capture_output=True, text=True, cwd=ROOT)
    # a clean flight is healthy: the accel NIS band judges the rests (R = the sensor noise), the updates
    # carrying the vehicle-acceleration disturbance are judged one-sided (tests/test_flight_health.py)
    assert r.returncode == 0, r.stderr
    rep = json.loads(out.read_text())["meta"]["online"]["observability"]
    assert {"gyro.bias.x", "gyro.bias.y", "gyro.bias.z"} <= set(rep["determined"])
    und = {u["term"]: u for u in rep["undetermined"]}
    assert "gyro.scale.x" in und and "gyro.scale.y" in und
    assert "°/s" in und["gyro.scale.x"]["reason"] and "360°" in und["gyro.scale.x"]["motion_needed"]
    # the turns were there; what the flight lacked was a still reference for them (session 22: the words had asked
    # for "a full turn about z" of a flight that turned 1783° about z)
    assert "gyro.scale.z" in und and "no turn had a still reference" in und["gyro.scale.z"]["reason"]
    assert "gravity does not see a turn about a vertical z" in und["gyro.scale.z"]["reason"]
    assert "calibrated magnetometer in use" in und["gyro.scale.z"]["motion_needed"]
    assert "thrust" in und["accel.scale.x"]["reason"]  # in flight only rests count for the accel
    assert rep["vehicle"]["active"] is True
    lines = observability_text(rep)
    assert lines[0].startswith("determined by the data:") and any("gyro.scale.x" in ln for ln in lines)
    # every term is in exactly one list
    assert len(rep["determined"]) + len(rep["undetermined"]) == 37  # 36 terms + dip


def test_checkpoint_keeps_vehicle_and_coverage():
    sim = simulate("multirotor", 6, duration=60.0, imu_rate=200.0)
    cal = OnlineCalibrator(None, UKFConfig())
    half = sim.data.n_imu // 2
    cal.feed(sim.data.slice_imu(0, half))
    state = json.loads(json.dumps(cal.get_state()))
    back = OnlineCalibrator.from_state(state)
    assert back._vehicle.active == cal._vehicle.active
    assert back._coverage.to_dict() == cal._coverage.to_dict()


@pytest.mark.slow
def test_flight_cold_start_is_consistent_one_seed():
    """Fast tier: 3 min of multirotor flight at 100 Hz, cold: no term beyond 4σ, no divergence, gyro bias
    within 1e-3 rad/s (the disarmed ground rest), gyro x/y scale not claimed (σ above half its prior)."""
    fs = _flight_stats()
    r = fs.run_flight("multirotor", 11, "cold", minutes=3.0, rate=100.0)
    assert np.abs(r.z).max() < 4.0, fs.NAMES[int(np.argmax(np.abs(r.z)))]
    assert r.divergences == 0
    assert r.gyro_bias_err_60s < 1e-3
    i = fs.NAMES.index("gyro.scale.x")
    assert not r.determined[i] and not r.determined[i + 1]


# -- issue 10's Numbers, reduced seeds (benchmarks/flight_stats.py runs 20 per profile) ---------------

@pytest.mark.slow
@pytest.mark.parametrize("profile", ["multirotor", "fixedwing"])
@pytest.mark.parametrize("start", ["cold", "bench"])
def test_flight_numbers_reduced_seeds(profile, start):
    """10 min at 200 Hz, 2 seeds: ≥ 95 % of the 36 terms within 3σ and none beyond 5σ; no divergence;
    gyro bias within 1e-3 rad/s 60 s after take-off; every determined term (σ < ½ prior) within 3σ."""
    fs = _flight_stats()
    runs = [fs.run_flight(profile, seed, start) for seed in (21, 22)]
    Z = np.array([r.z for r in runs])
    assert np.mean(np.abs(Z) < 3) >= 0.95
    assert np.abs(Z).max() < 5
    assert sum(r.divergences for r in runs) == 0
    assert max(r.gyro_bias_err_60s for r in runs) < 1e-3
    det = np.array([r.determined for r in runs])
    assert np.all(np.abs(Z[det]) < 3)


# -- inter-sensor alignment learnt cold, with an explicit gauge (issue 10 item 4) ---------------------

def _matrix_errors_after_common_rotation(cal, truth) -> dict[str, float]:
    """Relative spectral-norm error of each sensor's matrix after the one rotation Q (orthogonal
    Procrustes over all three) that best maps the truth's body frame onto the estimate's."""
    est = {s: cal.sensor(s).matrix for s in ("gyro", "accel", "mag")}
    tru = {s: truth.sensor(s).matrix for s in est}
    H = sum(tru[s] @ est[s].T for s in est)
    U, _, Vt = np.linalg.svd(H)
    Q = Vt.T @ np.diag([1, 1, np.linalg.det(Vt.T @ U.T)]) @ U.T
    return {s: float(np.linalg.norm(est[s] - Q @ tru[s], 2) / np.linalg.norm(tru[s], 2)) for s in est}


@pytest.mark.parametrize("seed", [31, *(pytest.param(k, marks=pytest.mark.slow) for k in (32, 33))])
def test_paper_cold_start_learns_every_alignment(seed):
    """Cold (--init none) on the paper session: every matrix within 0.5 % of the truth once the common
    rotation is removed, the accelerometer included (was 1.9–2.1 % with the gauge held at the cold prior's
    2°: the others' alignment to it was not learnt). The gauge is recorded: the accelerometer's alpha."""
    sim = simulate("paper", seed)
    res = replay([sim.data], None)
    err = _matrix_errors_after_common_rotation(res.calibration, sim.truth.calibration)
    assert max(err.values()) < 0.005, err
    g = res.calibration.meta["online"]["gauge"]
    assert g["sensor"] == "accel" and g["terms"] == ["alpha"]
    assert np.allclose(res.calibration.accel.alpha, 0.0, atol=1e-6)


def test_vehicle_gyro_samples_not_ahead_of_the_attitude() -> None:
    """The flight simulator holds ω over each 1-ms step; a 100 Hz sample taken on a grid point used to read the
    next step's rate, 0.5 ms ahead of the attitude (diagnose named it as a 0.58 ms time offset on a clean
    flight). Truth here is the trajectory's attitude: the rotation between consecutive samples against the
    trapezoid of the rates sampled with a trial shift s; the best s (vertex of the squared error's parabola)
    is the rate's lead: ~0 as the sensor now samples it."""
    from scipy.spatial.transform import Rotation

    from onlinecal.sim.flight import multirotor_trajectory

    traj = multirotor_trajectory(np.random.default_rng(3), duration=300.0)
    t = np.arange(60.0, 240.0, 0.01)
    R = traj.evaluate(t).R
    dR = Rotation.from_matrix(np.einsum("nji,njk->nik", R[:-1], R[1:])).as_rotvec()
    shifts = np.array([-1e-3, -5e-4, 0.0, 5e-4, 1e-3])

    def lead(rate_at) -> float:
        e2 = []
        for sh in shifts:
            w = rate_at(t + sh)
            e2.append(np.mean((dR - 0.5 * (w[:-1] + w[1:]) * 0.01) ** 2))
        a, b, _ = np.polyfit(shifts, e2, 2)
        return float(-b / (2 * a))

    sampled = lead(lambda tt: traj.evaluate(tt).omega)
    assert abs(sampled) < 1e-4, sampled
    # the old reading (held values: a step function of the shift, so no parabola) fits the attitude worse
    held = traj.omega[np.floor(t / traj.dt + 1e-9).astype(int)]
    w = traj.evaluate(t).omega
    e_held = np.mean((dR - 0.5 * (held[:-1] + held[1:]) * 0.01) ** 2)
    e_now = np.mean((dR - 0.5 * (w[:-1] + w[1:]) * 0.01) ** 2)
    assert e_now < 0.9 * e_held, (e_now, e_held)


def test_no_disarmed_fixed_wing_accelerates_whatever_the_sessions_length() -> None:
    """Session 18: a 60-s fixed-wing was simulated with its approach (15 m/s) commanded from t = 15 s, while it
    still stood disarmed on the runway (take-off at 38 s): up to 3 m/s² of specific force along x with no
    thrust. Now a session shorter than the schedule stops where it is. Physics: a disarmed vehicle on the
    ground measures gravity alone; the 600-s flight (whose schedule fits) is the same as before."""
    for duration in (40.0, 60.0, 103.0, 600.0):
        sim = simulate("fixedwing", 3, duration=duration, imu_rate=100.0)
        tr = sim.trajectory
        t = np.arange(0.0, duration, 0.5)
        disarmed = ~tr.at("armed", t).astype(bool)
        f = tr.evaluate(t).f
        assert disarmed.sum() >= 70
        assert np.abs(f[disarmed, :2]).max() < 1e-6 and np.allclose(f[disarmed, 2], 9.80665, atol=1e-6)
