"""Batch magnetometer on part of the sphere (issue 12): σ that cover the extrapolation, and the health verdict
that judges the terms by them (ok with the undetermined terms named; not ok where the σ do not cover).

The truth comes from the simulator's truth file (sim.truth), never from the fit."""

from __future__ import annotations

import numpy as np
import pytest

from onlinecal.batch.ellipsoid import (
    SOFT_DIAG_SIGMA,
    fit_ellipsoid_svd,
    fit_norm_lm,
    fit_norm_map,
    sphere_bin_weights,
)
from onlinecal.health import COVERAGE_MIN, assess, mag_coverage
from onlinecal.model import Calibration, SensorCalibration


def _band(seed: int, n: int = 6000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw magnetometer samples of a unit field at dip 60° seen by a body yawing through every heading with
    tilts up to ±20° (a flight's band of directions), a soft/hard iron of a real compass's size and 0.2 %
    noise. Returns (raw (n, 3), o (3,), symmetric M (3, 3))."""
    rng = np.random.default_rng(seed)
    dip = np.radians(60)
    f_w = np.array([np.cos(dip), 0.0, -np.sin(dip)])
    yaw = rng.uniform(-np.pi, np.pi, n)
    roll, pitch = np.radians(rng.uniform(-20, 20, (2, n)))
    cy, sy, cr, sr, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    # body-frame field: R(yaw, pitch, roll)ᵀ f_w, Z-Y-X
    Rz = np.stack([np.stack([cy, -sy, 0 * cy], -1), np.stack([sy, cy, 0 * cy], -1),
                   np.stack([0 * cy, 0 * cy, 1 + 0 * cy], -1)], -2)
    Ry = np.stack([np.stack([cp, 0 * cp, sp], -1), np.stack([0 * cp, 1 + 0 * cp, 0 * cp], -1),
                   np.stack([-sp, 0 * cp, cp], -1)], -2)
    Rx = np.stack([np.stack([1 + 0 * cr, 0 * cr, 0 * cr], -1), np.stack([0 * cr, cr, -sr], -1),
                   np.stack([0 * cr, sr, cr], -1)], -2)
    R = Rz @ Ry @ Rx
    h = np.einsum("nji,j->ni", R, f_w)
    soft = np.diag([1.0, 1.0, 1.0]) + np.array([[0.08, 0.02, 0.01], [0.02, -0.07, 0.015], [0.01, 0.015, 0.05]])
    M = soft * 2.1  # raw unit ≈ 0.48 G field
    o = np.array([0.12, -0.17, 0.23])
    raw = h @ np.linalg.inv(M).T + o + rng.normal(0, 0.002 / 2.1, (n, 3))
    return raw, o, M


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_map_fit_sigma_covers_the_band_extrapolation(seed):
    """On a band of directions (coverage < 40 %), the MAP fit (eq. 17 + soft-iron prior, raw-unit residual)
    puts the truth's centre within 5σ on every axis, and its σ along the unseen direction is wider than
    along the seen ones (the prior's width carried into the centre)."""
    raw, o, M = _band(seed)
    assert mag_coverage((raw - o) @ M.T) < COVERAGE_MIN
    w = sphere_bin_weights(raw - raw.mean(0), per_bin=30)
    o0, M0 = fit_ellipsoid_svd(raw, w)  # the algebraic start (eqs. 19-24), as the batch starts it
    fit = fit_norm_map(raw, o0, M0, weights=sphere_bin_weights((raw - o0) @ M0.T, per_bin=30))
    sig = np.sqrt(np.diag(fit.cov)[:3])
    z = np.abs(fit.o - o) / sig
    assert np.all(z < 5), (z, fit.o - o, sig)
    assert sig[2] > 2 * max(sig[0], sig[1]), sig  # z (the vertical: a band's unseen direction) widest
    # the size is pinned by the circle the band traces: the mean scale within the prior's width
    assert abs(np.trace(fit.M) / np.trace(M) - 1) < SOFT_DIAG_SIGMA


def _flight_batch(profile: str, seed: int):
    from onlinecal.batch import run_batch
    from onlinecal.sim import simulate

    sim = simulate(profile, seed)
    return sim, run_batch([sim.data])


def _mag_z(est: SensorCalibration, truth: SensorCalibration, undetermined: list[str]) -> dict[str, float]:
    """|est − truth| / σ of every determined magnetometer term with a σ."""
    out = {}
    for p in ("bias", "scale", "alpha", "xi"):
        sig = est.sigma.get(p)
        if sig is None or f"mag.{p}" in undetermined:
            continue
        for i, a in enumerate("xyz"):
            if f"mag.{p}.{a}" not in undetermined:
                out[f"mag.{p}.{a}"] = abs(float(est.params()[p][i] - truth.params()[p][i])) / float(sig[i])
    return out


def _check_flight(profile: str, seed: int) -> None:
    sim, b = _flight_batch(profile, seed)
    cal = b.calibration
    raw = {"gyro": sim.data.gyro, "accel": sim.data.acc}
    h = assess(cal, mag_raw=sim.data.mag, raw=raw)
    assert h["checks"]["mag_coverage"] < COVERAGE_MIN  # a flight's band: the case at hand
    und = h["checks"]["undetermined"]
    z = _mag_z(cal.mag, sim.truth.calibration.mag, und)
    assert {"mag.bias.x", "mag.bias.y", "mag.bias.z"} <= set(z), z  # the centre is determined, with σ
    assert max(z.values()) < 5, z
    # the frame's rotation is not seen without rotation phases: alpha and ξ named, not given as a result
    assert "mag.alpha" in und and "mag.xi" in und
    assert h["verdict"] == "ok", h["reasons"]
    assert any("extrapolated" in n for n in h["notes"]), h["notes"]
    assert not any(r.startswith("mag:") for r in h["reasons"])


def test_flight_batch_mag_sigma_covers_the_truth():
    """A 10-min fixed-wing flight (22–31 % of the field directions): every determined batch mag term within
    5σ of the simulator's truth, the verdict ok, the extrapolation said in a note. Before: bias z 7.5σ off
    (seed 0) and the batch degraded on coverage alone."""
    _check_flight("fixedwing", 0)


@pytest.mark.slow
@pytest.mark.parametrize(("profile", "seed"), [("multirotor", 0), ("multirotor", 1), ("multirotor", 2),
                                               ("fixedwing", 1), ("fixedwing", 2)])
def test_flight_batch_mag_sigma_covers_the_truth_more_seeds(profile, seed):
    """As above on more seeds (before: multirotor seed 1 bias z 12σ off, fixed-wing seeds 1–2 6.5σ and
    4.5σ; all degraded on coverage alone)."""
    _check_flight(profile, seed)


@pytest.mark.slow
@pytest.mark.parametrize(("profile", "seed"), [("multirotor", 1), ("fixedwing", 0)])
def test_health_not_ok_where_the_mag_sigma_do_not_cover(profile, seed):
    """The other direction: the same flight's magnetometer from the plain least-squares fit of eq. 17 (σ
    from its linearised covariance: they do not cover the extrapolation) is > 5σ off the truth, and the
    verdict is not ok (degraded on coverage: those σ carry no prior)."""
    from onlinecal.batch.sensors import propagate_sigma

    sim, b = _flight_batch(profile, seed)
    x = sim.data.mag
    lo, hi = np.percentile(x, [1, 99], axis=0)
    w = sphere_bin_weights(x - 0.5 * (lo + hi), per_bin=30)
    fit = fit_norm_lm(x, 1.0, b.calibration.mag.bias, np.eye(3) * float(np.mean(b.calibration.mag.scale)),
                      weights=w)
    sig = propagate_sigma(fit.o, fit.M, fit.cov, np.eye(3), 0.0, np.random.default_rng(0))
    plain = SensorCalibration(fit.o, fit.M, {"bias": sig["bias"]})
    meta = {k: v for k, v in b.calibration.meta.items() if k != "batch"}  # no prior-fit record
    cal = Calibration(b.calibration.gyro, b.calibration.accel, plain, meta=meta)
    z = _mag_z(plain, sim.truth.calibration.mag, [])
    assert max(z.values()) > 5, z  # bad
    h = assess(cal, mag_raw=x, raw={"gyro": sim.data.gyro, "accel": sim.data.acc})
    assert h["verdict"] != "ok" and any("directions" in r for r in h["reasons"]), h
