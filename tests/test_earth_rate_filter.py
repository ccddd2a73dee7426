"""The filter told where it is (``UKFConfig.latitude_deg``, ``replay --latitude``) takes the Earth's rotation out of
the gyro (onlinecal.ukf.earth). The truths: the simulator's Earth-rate vector (onlinecal.sim.motion, written from the
WGS-84 rate and the latitude, not from the filter's module) and its gyro bias; without the latitude the filter's
bias carries the rate's projection (Ω_E sin φ ≈ 5.4e-5 rad/s on a level body's z at 47.4°)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from onlinecal.sim import simulate
from onlinecal.sim.motion import DEFAULT_LATITUDE_DEG
from onlinecal.sim.motion import earth_rate_world as sim_earth_rate_world
from onlinecal.ukf import UKFConfig, replay
from onlinecal.ukf.earth import allowance, earth_rate_world
from onlinecal.ukf.vehicle import OMEGA_E_HORIZONTAL_RMS

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from flight_stats import NAMES, run_flight  # noqa: E402

BIAS = [NAMES.index(f"gyro.bias.{a}") for a in "xyz"]


@pytest.mark.parametrize("lat", [-90.0, -33.9, 0.0, 47.397742, 64.1, 90.0])
def test_north_up_components_match_the_simulator(lat: float) -> None:
    """(north, up) against the simulator's ENU vector (0, Ω cos φ, Ω sin φ) — east is zero."""
    n, u = earth_rate_world(lat)
    ref = sim_earth_rate_world(lat)
    assert ref[0] == pytest.approx(0.0, abs=1e-20)
    assert n == pytest.approx(ref[1], rel=1e-12, abs=1e-20) and u == pytest.approx(ref[2], rel=1e-12, abs=1e-20)


def test_allowance_shrinks_with_what_is_known() -> None:
    """Unknown latitude: Ω_E/√3 on every axis (as before); known, heading held: the declination's share across
    north; known, no heading: a level body's x/y carry the horizontal part's half each, z only the floor — the
    diagonal of the level plane's covariance h²/2 (I − u uᵀ) at any tilt (checked against it here)."""
    c = UKFConfig()
    assert allowance(None, True, c.rest_rate_sigma, 15.0) == ((c.rest_rate_sigma,) * 3, OMEGA_E_HORIZONTAL_RMS**2)
    h = 7.292115e-5 * math.cos(math.radians(47.4))
    s_d = h * math.radians(15.0)
    s_head, om2_head = allowance(47.4, True, c.rest_rate_sigma, 15.0, [0.0, 0.0, 1.0])
    assert s_head == pytest.approx((s_d,) * 3) and om2_head == pytest.approx(s_d**2)
    s_level, om2_free = allowance(47.4, False, c.rest_rate_sigma, 15.0, [0.0, 0.0, 1.0])
    assert om2_free == pytest.approx(h**2)
    assert s_level == pytest.approx((math.sqrt(h**2 / 2 + s_d**2),) * 2 + (s_d,))
    u = np.array([0.3, -0.2, 0.9])
    u /= np.linalg.norm(u)
    s_tilt, _ = allowance(47.4, False, c.rest_rate_sigma, 15.0, u.tolist())
    ref = np.diag(h**2 / 2 * (np.eye(3) - np.outer(u, u))) + s_d**2
    assert np.allclose(np.square(s_tilt), ref, rtol=1e-12)
    assert max(s_head) < min(s_level[:2]) and max(s_level) < c.rest_rate_sigma
    with pytest.raises(ValueError, match="latitude"):
        UKFConfig(latitude_deg=91.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bench_started_flight_bias_with_and_without_latitude(seed: int) -> None:
    """Two-minute multirotor flights from a bench calibration (the flight's gyro senses the Earth's rotation at
    47.4°): told the latitude, every gyro bias axis ends within 1.5e-5 rad/s and 3σ of the simulator's, and the
    bias 60 s after take-off within 2e-5; not told, the z axis carries the vertical part (> 3e-5 off), as its
    σ allows (within 3σ: the allowance is the promise)."""
    told = run_flight("multirotor", seed, "bench", minutes=2.0, config=UKFConfig(latitude_deg=DEFAULT_LATITUDE_DEG))
    blind = run_flight("multirotor", seed, "bench", minutes=2.0)
    assert np.all(np.abs(told.err[BIAS]) < 1.5e-5), told.err[BIAS]
    assert np.all(np.abs(told.z[BIAS]) < 3.0), told.z[BIAS]
    assert told.gyro_bias_err_60s < 2e-5
    assert abs(blind.err[BIAS][2]) > 3e-5, blind.err[BIAS]
    assert np.all(np.abs(blind.z[BIAS]) < 3.0)
    assert told.verdict == "ok" and blind.verdict == "ok"


def test_latitude_on_the_command_line(tmp_path: Path) -> None:
    """``replay --latitude`` reaches the filter (the JSON's observability records it, the bias z moves by about
    the vertical part against a replay without it); a latitude beyond ±90° is one line, exit 2; a fleet refuses it."""
    log = tmp_path / "f.tlog"
    r = subprocess.run([sys.executable, "-m", "onlinecal", "simulate", "--out", str(log), "--profile", "multirotor",
                        "--seed", "5", "--duration", "90"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    out = {}
    for name, extra in (("blind", []), ("told", ["--latitude", str(DEFAULT_LATITUDE_DEG)])):
        js = tmp_path / f"{name}.json"
        r = subprocess.run([sys.executable, "-m", "onlinecal", "replay", str(log), "--init", "none", "--json", str(js),
                            *extra], capture_output=True, text=True, timeout=300)
        assert r.returncode in (0, 1), r.stderr
        out[name] = json.loads(js.read_text())
        assert "the Earth's rotation is " + ("taken out" if extra else "not taken out") in r.stdout
        # a cold flight never holds a heading: the words say the bias's σ then carries one rest's horizontal share
        assert ("vertical part only: no heading" in r.stdout and "the gyro bias's σ is then conservative" in r.stdout
                ) == bool(extra), r.stdout[-2000:]
    e = out["told"]["meta"]["online"]["observability"]["earth_rate"]
    assert e["latitude_deg"] == pytest.approx(DEFAULT_LATITUDE_DEG)
    assert out["blind"]["meta"]["online"]["observability"]["earth_rate"]["latitude_deg"] is None
    dz = out["blind"]["gyro"]["bias"][2] - out["told"]["gyro"]["bias"][2]
    up = 7.292115e-5 * math.sin(math.radians(DEFAULT_LATITUDE_DEG))
    assert 0.7 * up < dz < 1.3 * up, (dz, up)  # a level multirotor: the vertical part on z, cos(tilt) ≈ 1
    r = subprocess.run([sys.executable, "-m", "onlinecal", "replay", str(log), "--init", "none", "--latitude", "95"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "Traceback" not in r.stderr and "latitude" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    r = subprocess.run([sys.executable, "-m", "onlinecal", "replay", str(log), "--init", "none", "--declination", "3"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "--declination needs --latitude" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "onlinecal", "replay", str(log), "--jobs", "1", "--latitude", "10"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "--latitude" in r.stderr and "Traceback" not in r.stderr


def test_replay_with_latitude_none_is_the_default() -> None:
    """latitude_deg None changes nothing (tests/… bits_ukf shows it bit for bit on five logs; here one)."""
    sim = simulate("multirotor", 7, duration=40.0, imu_rate=100.0, mag_rate=50.0)
    a = replay([sim.data], None, None)
    b = replay([sim.data], None, UKFConfig(latitude_deg=None))
    assert np.array_equal(a.calibration.to_dict()["gyro"]["bias"], b.calibration.to_dict()["gyro"]["bias"])


@pytest.mark.parametrize("seed", [0, 1])
def test_declination_places_true_north(seed: int) -> None:
    """The simulator's field 12° east of true north (the Earth's axis stays on true north): told D = +12° ± 1°
    the bench-started flight's gyro bias ends within 1e-5 rad/s and 3σ on every axis; told the wrong sign,
    −12° ± 1°, the horizontal bias error is at least twice as large (Ω_E cos φ · 2 sin 12° ≈ 2e-5 across north
    is put into the bias)."""
    def run(d: float) -> tuple[np.ndarray, np.ndarray]:
        cfg = UKFConfig(latitude_deg=DEFAULT_LATITUDE_DEG, declination_deg=d, declination_sigma_deg=1.0)
        r = run_flight("multirotor", seed, "bench", minutes=2.0, config=cfg, declination=12.0)
        return r.err[BIAS], r.z[BIAS]

    err, z = run(12.0)
    bad, _ = run(-12.0)
    assert np.all(np.abs(err) < 1e-5) and np.all(np.abs(z) < 3.0), (err, z)
    assert np.linalg.norm(bad[:2]) > 2.0 * np.linalg.norm(err[:2]), (bad, err)


def test_simulate_declination_on_the_command_line(tmp_path: Path) -> None:
    """``simulate --declination 12`` writes a truth whose field is 12° east of true north (ENU: its horizontal
    part's azimuth atan2(east, north)), the Earth's rotation still on true north; a declination beyond ±180° is
    one line, exit 2."""
    log = tmp_path / "d.csv"
    r = subprocess.run([sys.executable, "-m", "onlinecal", "simulate", "--out", str(log), "--profile", "multirotor",
                        "--duration", "40", "--declination", "12"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    truth = json.loads((tmp_path / "d.csv.truth.json").read_text())
    h = truth["field_world"]
    assert math.degrees(math.atan2(h[0], h[1])) == pytest.approx(12.0, abs=1e-9)
    w = truth["earth_rate"]["world"]
    assert w[0] == pytest.approx(0.0, abs=1e-20) and w[1] > 0
    r = subprocess.run([sys.executable, "-m", "onlinecal", "simulate", "--out", str(tmp_path / "e.csv"),
                        "--declination", "200"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "Traceback" not in r.stderr and "declination" in r.stderr


def test_batch_takes_the_vertical_part_out_of_its_gyro_bias() -> None:
    """The batch told the latitude (a log's GPS or ``--latitude``): a vehicle's ground rest, one attitude, reads
    bias + Ω_E sin φ along up; eqs. 34–35 took it for bias (gyro.bias.z off by ~5.4e-5 on every flight). Told,
    the removed vector is Ω_E sin φ along the accelerometer's up, z's error falls to the noise and its σ from
    the Earth-rate allowance to that noise; every axis stays within 3σ. On the paper session the first long
    rest carries most of the weight of eqs. 34–35 (a rest's weight grows as its length cubed), so the faces do
    not cancel it: there too the vertical part goes and the told batch is within 3σ."""
    from onlinecal.batch import run_batch

    up = 7.292115e-5 * math.sin(math.radians(DEFAULT_LATITUDE_DEG))
    z_told = []
    for seed in (2, 3, 4):
        sim = simulate("multirotor", seed, duration=120.0, imu_rate=200.0, mag_rate=50.0)
        truth = np.asarray(sim.truth.calibration.gyro.bias)
        told = run_batch([sim.data], latitude_deg=DEFAULT_LATITUDE_DEG)
        blind = run_batch([sim.data])
        gt, gb = told.calibration.gyro, blind.calibration.gyro
        err_t, err_b = np.asarray(gt.bias) - truth, np.asarray(gb.bias) - truth
        sig_t, sig_b = np.asarray(gt.sigma["bias"]), np.asarray(gb.sigma["bias"])
        assert 0.7 * up < err_b[2] < 1.3 * up, err_b  # the vertical part, taken for bias
        assert sig_t[2] < 0.5 * sig_b[2], (sig_t, sig_b)
        z_told.append(abs(err_t[2]))
        assert np.all(np.abs(err_t) < 3 * sig_t), (err_t, sig_t)
        removed = np.asarray(told.steps["gyro"].figures["earth_rate_removed"]["rad_s"])
        assert np.linalg.norm(removed) == pytest.approx(up, rel=0.01) and removed[2] > 0.99 * up
    assert np.mean(z_told) < 0.4 * up, z_told  # blind: ~up on every seed
    paper = simulate("paper", 5, earth_rate=True, latitude=DEFAULT_LATITUDE_DEG)
    told = run_batch([paper.data], latitude_deg=DEFAULT_LATITUDE_DEG)
    blind = run_batch([paper.data])
    truth = np.asarray(paper.truth.calibration.gyro.bias)
    err, err_b = np.asarray(told.calibration.gyro.bias) - truth, np.asarray(blind.calibration.gyro.bias) - truth
    # the first rest is level: its vertical part (z) goes, its horizontal part (north: y) stays, covered by σ
    assert abs(err[2]) < 0.3 * abs(err_b[2]) and abs(err_b[2]) > 0.7 * up, (err, err_b)
    assert np.all(np.abs(err) < 3 * np.asarray(told.calibration.gyro.sigma["bias"]))
