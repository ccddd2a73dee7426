"""The prior-free NEES (onlinecal.testing.nees) on a linear-Gaussian problem whose exact posterior is the
textbook Kalman update, with a fixed truth that is *not* a draw from the (wide) prior — the situation of a
simulated unit under a cold prior (issue 10)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from onlinecal.testing.nees import data_only_nees


def _problem() -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Six terms: 0–1 seen only as a sum and a weak difference, 2 well, 3–5 weakly or not at all."""
    H = np.array([[1.0, 1.0, 0, 0, 0, 0], [0.05, -0.05, 0, 0, 0, 0], [0, 0, 1.0, 0.3, 0, 0],
                  [0, 0, 0, 0.02, 0.02, 0]])
    prior_sd = np.array([1.0, 1.0, 0.5, 2.0, 1.0, 0.7])
    truth = np.array([0.05, -0.03, 0.02, 0.1, -0.05, 0.01])  # far inside the prior: not a draw from it
    return H, prior_sd, truth, 0.02


def _posterior(H: np.ndarray, prior_sd: np.ndarray, y: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray]:
    P0 = np.diag(prior_sd**2)
    S = H @ P0 @ H.T + r**2 * np.eye(H.shape[0])
    K = P0 @ H.T @ np.linalg.inv(S)
    return K @ y, (np.eye(6) - K @ H) @ P0  # x0 = 0


def test_data_only_nees_is_chi2_where_the_per_term_nees_reads_low() -> None:
    rng = np.random.default_rng(7)
    H, sd, truth, r = _problem()
    vals, dofs, per_term, per_dof = [], [], [], []
    for _ in range(400):
        y = H @ truth + r * rng.normal(size=H.shape[0])
        x, P = _posterior(H, sd, y, r)
        d = data_only_nees(x, P, np.zeros(6), sd**2, truth)
        vals.append(d.nees)
        dofs.append(d.dof)
        det_terms = np.sqrt(np.diag(P)) < 0.5 * sd
        z = (x - truth) / np.sqrt(np.diag(P))
        per_term.append(float(np.sum(z[det_terms] ** 2)))
        per_dof.append(int(det_terms.sum()))
    assert len(set(dofs)) == 1 and dofs[0] == 3  # sum of 0–1, term 2 and the 2–3 mix
    total, k = float(np.sum(vals)), int(np.sum(dofs))
    lo, hi = chi2.ppf([0.005, 0.995], k)
    assert lo <= total <= hi, (total, k, lo, hi)
    # the per-term NEES over the "determined" terms of the same runs is far below its band: terms 0 and 1
    # are determined as a sum, their σ each carries the wide prior of the undetermined difference
    pt, pk = float(np.sum(per_term)), int(np.sum(per_dof))
    assert pt < chi2.ppf(0.005, pk), (pt, pk)


def test_a_truth_drawn_from_the_prior_gives_the_same_nees_as_the_full_one_in_expectation() -> None:
    """Where the truth *is* a draw from the prior the ordinary NEES over all terms is χ²(6); the data-only
    one is χ²(dof) as well (it does not depend on where the truth lies)."""
    rng = np.random.default_rng(11)
    H, sd, _, r = _problem()
    full, data, k = 0.0, 0.0, 0
    for _ in range(400):
        truth = sd * rng.normal(size=6)
        y = H @ truth + r * rng.normal(size=H.shape[0])
        x, P = _posterior(H, sd, y, r)
        e = x - truth
        full += float(e @ np.linalg.solve(P, e))
        d = data_only_nees(x, P, np.zeros(6), sd**2, truth)
        data += d.nees
        k += d.dof
    assert chi2.ppf(0.005, 6 * 400) <= full <= chi2.ppf(0.995, 6 * 400)
    assert chi2.ppf(0.005, k) <= data <= chi2.ppf(0.995, k)


def test_a_sure_wrong_estimate_reads_high() -> None:
    """An estimate moved by 5σ of the data along a determined direction reads far above χ²."""
    rng = np.random.default_rng(3)
    H, sd, truth, r = _problem()
    y = H @ truth + r * rng.normal(size=H.shape[0])
    x, P = _posterior(H, sd, y, r)
    x_bad = x + 5 * np.sqrt(P[2, 2]) * np.eye(6)[2]
    assert data_only_nees(x_bad, P, np.zeros(6), sd**2, truth).nees > chi2.ppf(0.999, 3)


def test_bad_shapes_and_priors_are_refused() -> None:
    with pytest.raises(ValueError, match="shapes"):
        data_only_nees(np.zeros(3), np.eye(2), np.zeros(3), np.ones(3), np.zeros(3))
    with pytest.raises(ValueError, match="positive"):
        data_only_nees(np.zeros(2), np.eye(2), np.zeros(2), np.array([1.0, 0.0]), np.zeros(2))
