"""Issue 10's last number: on a cold start the determined terms' NEES sits inside its 99 % band.

The gyro of a real vehicle senses the Earth's rotation; the flight profiles now do too
(``onlinecal.sim.motion.earth_rate_world``). The truth for the unit tests is the physics constant and the
trajectory's attitude, never the filter; the band of the slow test is the chi-square quantile of the
determined terms' count, not a figure read off a run.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from benchload import benchmark
from scipy.stats import chi2

from onlinecal.sim import simulate
from onlinecal.sim.motion import earth_rate_world

ROOT = Path(__file__).resolve().parents[1]
OMEGA_E = 7.292115e-5  # rad/s, the Earth's sidereal rotation rate (WGS-84), written out: the test's truth


def test_earth_rate_world_frame_enu():
    """ENU (x east, y north, z up): the Earth's axis points north and, north of the equator, up."""
    for lat in (0.0, 47.4, -35.36, 90.0):
        w = earth_rate_world(lat)
        phi = np.radians(lat)
        assert np.allclose(w, [0.0, OMEGA_E * np.cos(phi), OMEGA_E * np.sin(phi)], rtol=0, atol=1e-18)
        assert np.linalg.norm(w) == pytest.approx(OMEGA_E, rel=1e-12)
    with pytest.raises(ValueError):
        earth_rate_world(91.0)


@pytest.mark.parametrize("profile", ["multirotor", "fixedwing"])
def test_gyro_at_rest_reads_the_earth_rate_in_the_body_frame(profile):
    """During the disarmed ground rest the gyro's truth is Rᵀ Ω_E exactly, and the calibrated raw gyro
    (the truth calibration applied to the simulated readings) averages to it within its standard error;
    without the Earth rate the same readings average to 0, distinguishably on the vertical axis."""
    lat = 47.4
    sim = simulate(profile, 3, duration=40.0, imu_rate=200.0, latitude=lat)
    assert sim.truth.to_dict()["earth_rate"]["latitude_deg"] == lat
    t = sim.data.t_imu
    rest = t < 30.0  # the rest lasts 35 s (REST_S) before arming
    m = sim.trajectory.evaluate(t[rest])
    phi = np.radians(lat)
    w_enu = OMEGA_E * np.array([0.0, np.cos(phi), np.sin(phi)])
    expect = np.einsum("nji,j->ni", m.R, w_enu)  # world → body with the rest's attitude
    assert np.allclose(m.omega, expect, rtol=0, atol=1e-15)
    assert np.allclose(expect, expect[0], atol=1e-15)  # a rest: one attitude
    gyro = sim.truth.calibration.gyro
    assert gyro is not None
    cal = gyro.apply(sim.data.gyro[rest])
    se = sim.truth.noise["gyro"] * np.max(np.abs(gyro.matrix)) * 1.2 / np.sqrt(rest.sum())
    assert np.all(np.abs(cal.mean(axis=0) - expect[0]) < 4 * se), (cal.mean(axis=0), expect[0], se)
    # the level body's z axis reads Ω_E sin φ ≈ 5.4e-5 rad/s: ~6 standard errors — the test can fail
    assert expect[0][2] == pytest.approx(OMEGA_E * np.sin(phi), rel=1e-3)
    off = simulate(profile, 3, duration=40.0, imu_rate=200.0, earth_rate=False)
    assert "earth_rate" not in off.truth.to_dict()
    cal_off = gyro.apply(off.data.gyro[rest])
    assert np.all(np.abs(cal_off.mean(axis=0)) < 4 * se)
    assert abs(cal.mean(axis=0)[2] - cal_off.mean(axis=0)[2]) > 3 * se


def test_paper_profile_has_no_earth_rate_by_default():
    """The paper session keeps its figures (docs/flight.md: with the Earth rate its batch gyro bias error
    grows from ~1e-5 to ~5e-5 rad/s); it can be asked for."""
    assert "earth_rate" not in simulate("paper", 0, duration=20.0).truth.to_dict()
    on = simulate("paper", 0, duration=20.0, earth_rate=True, latitude=-35.36)
    assert on.truth.to_dict()["earth_rate"]["latitude_deg"] == -35.36


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "onlinecal", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=300)


def test_simulate_latitude_option(tmp_path):
    r = _cli("simulate", "--out", str(tmp_path / "a.csv"), "--profile", "multirotor", "--duration", "5",
             "--latitude", "-35.36", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    tr = json.loads((tmp_path / "a.csv.truth.json").read_text())
    assert tr["earth_rate"]["latitude_deg"] == -35.36
    assert np.allclose(tr["earth_rate"]["world"], earth_rate_world(-35.36))
    r = _cli("simulate", "--out", str(tmp_path / "b.csv"), "--profile", "multirotor", "--duration", "5",
             "--latitude", "none", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "earth_rate" not in json.loads((tmp_path / "b.csv.truth.json").read_text())
    r = _cli("simulate", "--out", str(tmp_path / "c.csv"), "--latitude", "91", cwd=tmp_path)
    assert r.returncode == 2 and "--latitude" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert "Traceback" not in r.stderr


@pytest.mark.slow
@pytest.mark.parametrize("profile", ["multirotor", "fixedwing"])
def test_cold_nees_of_determined_terms_inside_99_band(profile):
    """Cold start, 10 min at 200 Hz, 2 seeds: the NEES of the determined terms (σ < ½ prior; the others
    keep the prior, which the simulator's truth is not drawn from), pooled over the seeds, lies inside the
    chi-square 99 % band of its dof. Before the flights' gyro sensed the Earth's rotation it was ~10×
    below (the zero-rate update's allowance for it floored the bias σ). Over the 20 benchmark seeds it is
    at the band's lower edge (multirotor 45.2/77 against 48.8, fixed-wing 37.8/63 against 37.8 in session 7; since
    session 22 the yaw scale is held in a thrust-borne vehicle's motion without the magnetometer and a cold flight
    determines the gyro bias only, 33.5/60 and 33.1/60, conservative: docs/flight.md)."""
    fs = benchmark("flight_stats")
    runs = [fs.run_flight(profile, seed, "cold") for seed in (23, 24)]
    nees = sum(r.nees_determined[0] for r in runs)
    dof = sum(r.nees_determined[1] for r in runs)
    assert dof >= 6  # at least the gyro bias on both seeds
    lo, hi = chi2.ppf([0.005, 0.995], dof)
    assert lo <= nees <= hi, (nees, dof, lo, hi)
    # The prior taken out (onlinecal.testing.nees): never above the band on either profile; inside it on the
    # fixed-wing's two seeds (20 seeds, session 22: 41.5/80 and 41.8/80, below — the gyro bias's Earth-rate floor,
    # docs/flight.md), which two seeds cannot show either way.
    dn = sum(r.data_nees for r in runs)
    dk = sum(r.data_dof for r in runs)
    lo_d, hi_d = chi2.ppf([0.005, 0.995], dk)
    assert dk >= dof and dn <= hi_d, (dn, dk, hi_d)
    if profile == "fixedwing":
        assert lo_d <= dn, (dn, dk, lo_d)


def test_earth_rate_noise_tops_up_the_gyro_bias_and_the_attitude():
    """On a vehicle, Q gains what the unmodelled Earth rate leaves unknown: the gyro bias's variance is
    topped up to the allowance (Ω_E/√3 per axis, raw units) only where the data took it lower, and the
    attitude takes the horizontal part's Ω_E²·(2/3)·τ per second (sizes from the physics constant)."""
    from onlinecal.ukf.config import UKFConfig
    from onlinecal.ukf.layout import ATT, index
    from onlinecal.ukf.vehicle import earth_rate_noise

    sigma = UKFConfig().rest_rate_sigma
    assert sigma == pytest.approx(OMEGA_E / np.sqrt(3), rel=1e-12)
    b = index("gyro", "bias")
    n = b.stop + 30
    P = np.eye(n) * 1e-2
    s_gyr = 1.15
    P[b, b] = np.diag([1e-12, (2 * sigma / s_gyr) ** 2, 1e-10])  # x, z tight; y already wider
    q = earth_rate_noise(np.zeros(n), P, b, s_gyr, (sigma,) * 3, 30.0, 0.05)
    floor = (sigma / s_gyr) ** 2
    assert q[b][0] == pytest.approx(floor - 1e-12) and q[b][1] == 0.0 and q[b][2] == pytest.approx(floor - 1e-10)
    assert np.allclose(q[ATT], OMEGA_E**2 * (2 / 3) * 30.0 * 0.05, rtol=1e-12)
    mask = np.ones(n, bool)
    mask[b], mask[ATT] = False, False
    assert not q[mask].any()
