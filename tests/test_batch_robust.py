"""Issue 16, batch side: corrupt samples, a magnetic disturbance and a gyro-noise burst in a clean
simulated paper session. The reference is the clean run's own result and σ (not the code's figures)."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest

from onlinecal.batch import run_batch
from onlinecal.batch.clean import noise_bursts
from onlinecal.io.base import ImuData
from onlinecal.sim import simulate


@pytest.fixture(scope="module")
def clean():
    sim = simulate("paper", 3)
    t0 = time.perf_counter()
    res = run_batch([sim.data])
    return sim, res, time.perf_counter() - t0


def _terms(cal):
    out = {}
    for s in ("gyro", "accel", "mag"):
        c = cal.sensor(s)
        p = c.params()
        for k in ("bias", "scale", "alpha", "xi"):
            out[f"{s}.{k}"] = (np.asarray(c.bias if k == "bias" else p[k]), np.asarray(c.sigma[k]))
    return out


def _max_z(ref, res) -> tuple[float, str]:
    a, b = _terms(ref.calibration), _terms(res.calibration)
    z = {k: float(np.max(np.abs(b[k][0] - a[k][0]) / a[k][1])) for k in a}
    k = max(z, key=z.__getitem__)
    return z[k], k


def _run(d: ImuData):
    t0 = time.perf_counter()
    return run_batch([d]), time.perf_counter() - t0


def test_one_gyro_sample_of_1e6_rad_s(clean):
    sim, ref, t_clean = clean
    g = sim.data.gyro.copy()
    g[sim.data.n_imu // 2, 0] = 1e6
    res, t = _run(replace(sim.data, gyro=g))
    z, k = _max_z(ref, res)
    assert z <= 1.0, (z, k)
    assert t < 5 * t_clean + 2.0  # no 55-s slowdown
    assert any("1 gyro and 0 accel samples" in w for w in res.warnings), res.warnings


def test_ten_gyro_samples_of_100_rad_s(clean):
    sim, ref, _ = clean
    rng = np.random.default_rng(7)
    g = sim.data.gyro.copy()
    idx = rng.choice(sim.data.n_imu, 10, replace=False)
    g[idx, rng.integers(0, 3, 10)] = 100.0
    res, _ = _run(replace(sim.data, gyro=g))
    z, k = _max_z(ref, res)
    assert z <= 1.0, (z, k)
    assert any("10 gyro" in w for w in res.warnings), res.warnings


def test_one_bad_mag_sample_keeps_the_mag_calibration(clean):
    sim, ref, _ = clean
    m = sim.data.mag.copy()
    m[m.shape[0] // 3] *= 50
    res, _ = _run(replace(sim.data, mag=m))
    assert res.calibration.mag is not None
    z, k = _max_z(ref, res)
    assert z <= 1.0, (z, k)
    assert any("1 magnetometer samples" in w for w in res.warnings), res.warnings


@pytest.mark.parametrize("during_phase", [False, True])
def test_30s_magnetic_disturbance_is_excluded_and_reported(clean, during_phase):
    sim, ref, _ = clean
    d = sim.data
    t0 = ref.segmentations[0].phases[0].t0 if during_phase else 100.0
    sel = (d.t_mag > t0) & (d.t_mag < t0 + 30)
    m = d.mag.copy()
    # 0.5 G added in a fixed body direction (a motor or a beam moving with the unit); the raw field is 0.44 G
    m[sel] += 0.5 * np.array([0.6, 0.6, 0.53])
    res, _ = _run(replace(d, mag=m))
    w = [x for x in res.warnings if x.startswith("mag:") and "excluded" in x]
    assert w, res.warnings
    n = sum(int(x.split("mag: ")[1].split()[0]) for x in w)  # by norm, and by dip at rests
    assert 0.9 * sel.sum() <= n <= sel.sum() + 10
    assert any(f"{int(t0)}." in x for x in w), w  # the stretch named by its start time
    # every term within 1.5σ of the clean run (with the stretch in, the gyro scale is ~290σ off); the
    # clean run's own error against the truth is up to 4.3σ on accel bias y for this seed, so the clean
    # run, not the truth, is the reference that isolates the disturbance's effect
    z, k = _max_z(ref, res)
    assert z <= 1.5, (z, k)


def test_gyro_noise_burst_in_a_rotation_phase(clean):
    sim, ref, _ = clean
    d = sim.data
    ph = ref.segmentations[0].phases[0]
    sel = (d.t_imu > ph.t0 + 0.5) & (d.t_imu < ph.t0 + 5.5)
    g = d.gyro.copy()
    g[sel] += np.random.default_rng(1).normal(0, 0.3, (int(sel.sum()), 3))
    res, _ = _run(replace(d, gyro=g))
    c, r = res.calibration.gyro, ref.calibration.gyro
    assert np.all(np.abs(c.scale - r.scale) <= np.asarray(r.sigma["scale"])), (c.scale - r.scale, r.sigma["scale"])
    assert any("noise burst" in w for w in res.warnings), res.warnings


def test_noise_burst_detector_finds_the_stretch():
    rng = np.random.default_rng(0)
    t = np.arange(6000) / 100.0
    g = np.column_stack([np.sin(t), np.cos(0.5 * t), 0 * t]) + rng.normal(0, 0.002, (6000, 3))
    g[2000:2500] += rng.normal(0, 0.05, (500, 3))
    b = noise_bursts(g, 100.0)
    assert len(b) == 1 and abs(b[0][0] - 2000) < 30 and abs(b[0][1] - 2500) < 30
