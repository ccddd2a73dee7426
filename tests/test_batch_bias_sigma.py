"""Issue 13.3: the batch gyro-bias σ covers the rest-to-rest spread where the rests disagree beyond their
noise (a σ is a promise). Truth from the simulator: with a g-sensitivity the bias the gyro shows at each
rest is o + G·f (f the trajectory's specific force there)."""

from __future__ import annotations

import numpy as np
import pytest

from onlinecal.batch.gyro import rest_disagreement
from onlinecal.batch.pipeline import run_batch
from onlinecal.sim import simulate
from onlinecal.sim.effects import parse_effect

# cross-axis g-sensitivity of the size the imu_tk Xsens session shows (mrad/s per g: −2.65, +1.71, …)
GSENS = "g_sensitivity:coeff=0,matrix=0;0;1.3e-4;-2.7e-4;0;1.7e-4;-1.5e-4;-1.7e-4;0"


def test_rest_disagreement_chi2():
    rng = np.random.default_rng(0)
    se = np.full((30, 3), 1e-4)
    agree = rng.normal(0, 1e-4, (30, 3))
    assert not rest_disagreement(agree, se)[2].any()
    spread = agree + np.array([0, 5e-4, 0]) * rng.normal(size=(30, 1))
    assert rest_disagreement(spread, se)[2].tolist() == [False, True, False]
    held = np.zeros((5, 3))
    held[2, 0] = 1e-3  # readings on a lattice (se 0): only a mean that differs counts
    assert rest_disagreement(held, np.zeros((5, 3)))[2].tolist() == [True, False, False]


def test_clean_session_keeps_its_noise_sigma():
    sim = simulate("paper", 3)
    r = run_batch([sim.data])
    assert not any(w.startswith("gyro bias: the") for w in r.warnings)
    sig = np.asarray(r.calibration.gyro.sigma["bias"])
    assert np.all(sig < 2e-5)  # white noise only: the rests agree, σ is the standard error


def test_gsensitive_session_sigma_covers_the_apparent_bias_at_every_rest():
    e = parse_effect(GSENS)
    sim = simulate("paper", 3, effects=[e])
    r = run_batch([sim.data])
    assert any(w.startswith("gyro bias: the") and "widened to the spread" in w for w in r.warnings)
    cal = r.calibration
    sig = np.asarray(cal.gyro.sigma["bias"])
    m = sim.trajectory.evaluate(sim.data.t_imu)
    o = sim.truth.calibration.gyro.bias
    rests = r.segmentations[0].rests
    apparent = np.array([o + e.G() @ m.f[iv.i0:iv.i1].mean(axis=0) for iv in rests])
    spread = apparent.std(axis=0, ddof=1)
    assert sig == pytest.approx(spread, rel=0.1)  # the truth's spread, measured by the rests
    within = (np.abs(cal.gyro.bias - apparent) < 3 * sig).mean(axis=0)
    assert np.all(within >= 0.9), within
    # the former σ (standard error of the rest means) promised far more than the data holds
    old = spread / np.sqrt(len(rests))
    assert np.all((np.abs(cal.gyro.bias - apparent) < 3 * old).mean(axis=0) < 0.6)
