"""diagnose takes the Earth's rotation out before scoring effects (diagnose/analysis.fit_earth_rate): a gyro on
the ground senses Ω_E = 7.29e-5 rad/s fixed in a level frame, which a turning vehicle carries between its
axes — a fixed-wing circuit read it as a gyro bias_drift of 15.7 nats before. The truths here are the
simulator's Earth-rate vector (WGS-84 rate at the profile's latitude) and scipy's constrained minimiser."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import NonlinearConstraint, minimize

from onlinecal.diagnose import diagnose
from onlinecal.diagnose.analysis import _trust_region
from onlinecal.sim import simulate
from onlinecal.specs import OMEGA_EARTH


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_trust_region_matches_scipy(seed: int) -> None:
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((5, 3))
    H = A.T @ A * [1.0, 1e3, 1e6][seed]
    g = rng.standard_normal(3) * [1.0, 10.0, 1e4][seed]
    r = 0.3
    v = _trust_region(H, g, r)
    ref = minimize(lambda x: 0.5 * x @ H @ x - g @ x, np.zeros(3), jac=lambda x: H @ x - g, hess=lambda x: H,
                   method="trust-constr",
                   constraints=[NonlinearConstraint(lambda x: x @ x, -np.inf, r * r)],
                   options={"xtol": 1e-12, "gtol": 1e-12, "maxiter": 5000})
    assert np.linalg.norm(v) <= r * (1 + 1e-9)
    f = 0.5 * v @ H @ v - g @ v
    fr = 0.5 * ref.x @ H @ ref.x - g @ ref.x
    assert f <= fr + 1e-7 * max(1.0, abs(fr))


def test_trust_region_inside_bound_is_the_free_minimum() -> None:
    H = np.diag([2.0, 3.0, 4.0])
    g = np.array([0.02, -0.03, 0.04])
    assert np.allclose(_trust_region(H, g, 1.0), np.linalg.solve(H, g))


@pytest.mark.slow
def test_fixedwing_earth_rate_fitted_and_not_read_as_drift() -> None:
    sm = simulate("fixedwing", 7011, duration=300.0)
    assert sm.truth.earth_rate  # the profile's gyro senses the Earth's rotation
    dg = diagnose([sm.data], check=False, ukf=False, seed=7011)
    assert dg.verdict == "none", [(f.effect, f.sensor, f.score) for f in dg.significant]
    est = np.array(dg.baseline["earth_rate"][0]["rad_s"])
    R0 = sm.trajectory.evaluate(np.array([sm.data.t_imu[0]])).R[0]  # world ← body at the log's first sample
    truth = R0.T @ np.array(sm.truth.earth_rate["world"])
    assert np.linalg.norm(est) <= OMEGA_EARTH * (1 + 1e-9)
    # the fixed-wing turns through every heading: the horizontal part is seen, within a fifth of Ω_E; the
    # vertical part stays along the body's up axis in level flight, where it is one column with the gyro's
    # bias — not determined, and the bound keeps it at its smallest
    up = R0.T @ np.array([0.0, 0.0, 1.0])
    horiz = np.eye(3) - np.outer(up, up)
    assert np.linalg.norm(horiz @ (est - truth)) < 0.2 * OMEGA_EARTH, (est, truth)
    assert np.linalg.norm(horiz @ truth) > 0.6 * OMEGA_EARTH  # (Ω_E cos 47.4°: the check has something to see)


def test_trust_region_with_nothing_to_fit_is_zero() -> None:
    # every gyro-responding row left out (a baseline that meets none of them): no pull, no division by zero
    assert np.array_equal(_trust_region(np.zeros((3, 3)), np.zeros(3), OMEGA_EARTH), np.zeros(3))
