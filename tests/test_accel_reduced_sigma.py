"""The accelerometer's σ from a reduced static fit (session 16): with fewer than 9 distinct rest attitudes the fit
(eq. 32) holds the matrix, or part of it, fixed; its σ must carry that assumption. Before, MARG set 1's three rests
gave a bias of ±1e-16 m/s² and a common scale of ±4e-7 — σ of an assumption, not of the data. The truths here are
drawn by the test (a sensor with scale errors and non-orthogonality within the prior) and the measured set."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from onlinecal.batch import run_batch
from onlinecal.batch.ellipsoid import fit_norm_lm
from onlinecal.batch.sensors import ACC_PRIOR_SIGMA, reduced_model_cov
from onlinecal.io import read_log
from onlinecal.specs import G0
from onlinecal.ukf.config import UKFConfig

MARG = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "marg-set1"


def test_the_prior_is_the_online_filters_cold_prior() -> None:
    cold = UKFConfig().cold_sigma["accel"]
    assert {k: cold[k] for k in ACC_PRIOR_SIGMA} == ACC_PRIOR_SIGMA


def _rests(rng: np.random.Generator, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Raw static means of a sensor drawn within the prior: raw = M⁻¹ g u + o, M = I + E (E symmetric, diagonal σ
    of the scale prior, off-diagonal half the ξ prior), o within 0.2 m/s². Returns (means (K, 3), o)."""
    E = np.diag(rng.normal(0.0, ACC_PRIOR_SIGMA["scale"], 3))
    off = rng.normal(0.0, ACC_PRIOR_SIGMA["xi"] / 2.0, 3)
    E[0, 1] = E[1, 0] = off[0]
    E[0, 2] = E[2, 0] = off[1]
    E[1, 2] = E[2, 1] = off[2]
    o = rng.normal(0.0, 0.2, 3)
    u = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    raw = (np.linalg.inv(np.eye(3) + E) @ (G0 * u).T).T + o + rng.normal(0.0, 3e-4, u.shape)
    return raw, o


@pytest.mark.parametrize("model, dirs", [
    ("offset", [[0, 0, 1], [-1, 0, 0], [0, 1, 0]]),  # MARG's three rests
    ("bias", [[0, 0, 1], [-1, 0, 0], [0, 1, 0], [0, 0, -1]]),
    ("diag", [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]),
])
def test_the_bias_sigma_covers_the_error_of_the_fixed_terms(model: str, dirs: list[list[float]]) -> None:
    rng = np.random.default_rng(16)
    d = np.asarray(dirs, float)
    z = []
    for _ in range(200):
        raw, o = _rests(rng, d)
        M0 = np.eye(3) * G0 / np.linalg.norm(raw, axis=1).mean()
        fit = fit_norm_lm(raw, G0, np.zeros(3), M0, model=model)
        cov = reduced_model_cov(raw, G0, fit, model, np.full(d.shape[0], 3e-4**2 / 3))
        sig = np.sqrt(np.diag(cov)[:3])
        z.append((fit.o - o) / sig)
    z = np.array(z)
    # a σ is a promise: the normalised errors scatter as N(0, 1) (99 % band of their RMS over 600 values), and
    # the fit's own σ alone would put them hundreds of σ out for "offset"
    rms = float(np.sqrt(np.mean(z**2)))
    assert 0.4 < rms < 1.3, rms  # measured: offset 0.84, bias 0.82, diag 0.57
    assert float(np.mean(np.abs(z) > 3.0)) < 0.02


def test_three_rests_on_measured_data_claim_no_accelerometer_calibration() -> None:
    logs = [read_log(p) for p in sorted(MARG.glob("*.csv"))]
    res = run_batch(logs)
    acc = res.calibration.accel
    assert acc is not None
    und = res.calibration.meta["batch"]["undetermined"]
    for term in ("bias", "scale", "xi"):
        assert f"accel.{term}" in und
        assert term not in acc.sigma  # no σ: a start value, not a calibration (the JSON's sigma leaves it out)
    assert any("not determined by the data" in w and "accel.bias" in w for w in res.warnings)
    # the gyro and the magnetometer keep their σ
    assert res.calibration.gyro is not None and "scale" in res.calibration.gyro.sigma
