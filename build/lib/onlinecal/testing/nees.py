"""NEES with the prior taken out: the consistency of what the *data* told a filter, where the truth is not
a draw from the filter's prior.

The normalised estimation error squared, NEES = eᵀ P⁻¹ e, is χ²(n) only when the truth is a draw from the
filter's prior (Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to Tracking and Navigation*,
2001, §5.4). A simulated unit is one fixed calibration, and a cold prior (σ of 20 % on a gyro scale) or an
allowance (σ 0.05 rad on a mag alignment) is far wider than that unit's offset from the prior mean: every
term left at its prior then reads z ≪ 1. Restricting the NEES to the terms whose σ fell below half their
prior does not remove this where a determined term is *correlated* with undetermined ones: the part of its
posterior σ that the wide prior of its partners lends it is not matched by an error of that size (issue 10:
bench-started fixed-wing flights, whose bench prior is the batch's σ × 2, read 97.8 for 139 dof per term,
below the band [99.8, 185.7]; with the prior taken out 158.6 for 171, inside [127.1, 222.4]).

The prior is taken out in its own whitened coordinates (u = D⁻¹(x − x₀), D = diag of the prior σ, the prior
then N(0, I)). With A = D⁻¹ P D⁻¹ = V diag(a) Vᵀ the posterior there, the information the data added along
the eigenvector v_k is 1/a_k − 1, and the estimate the data alone give along it, with its variance, is

    d_k = (v_k · u) / (1 − a_k),    var d_k = a_k / (1 − a_k)

(information form of the Kalman update, I_post = I_prior + I_data, applied per direction; exact for a
linear-Gaussian model with constant parameters). Directions with a_k < ``ratio`` (posterior variance
below that share of the prior's: the per-term rule's ½ σ is a ratio of ¼) are *determined*; over them

    NEES_data = Σ_k (d_k − v_k · u_true)² (1 − a_k) / a_k  ~  χ²(#determined)

whatever the truth's offset from the prior mean. For the UKF this holds to the extent the problem is linear
over the posterior's spread and the parameters' random walk is small against their σ; a process noise on a
term makes its prior's information decay, and the prior is then taken out too fully (the NEES reads high).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True)
class DataNees:
    """The prior-free NEES (``nees``) over ``dof`` determined directions; ``a`` the posterior-to-prior
    variance ratio of every direction (ascending), ``terms`` how much each term (index into the inputs)
    weighs in the determined directions (Σ over them of v_ki², 0–1)."""

    nees: float
    dof: int
    a: Array
    terms: Array


def data_only_nees(x_post: ArrayLike, P_post: ArrayLike, x_prior: ArrayLike, prior_var: ArrayLike,
                   truth: ArrayLike, ratio: float = 0.25) -> DataNees:
    """NEES of the data's own estimate on the directions the data determined (module doc).

    x_post (n,), P_post (n, n): the filter's final estimate; x_prior (n,), prior_var (n,): its (diagonal)
    prior as applied; truth (n,). All in the same units. ``ratio``: a direction is determined where its
    posterior variance is below ``ratio`` × the prior's (whitened)."""
    x, P, x0, v0, t = (np.asarray(a, float) for a in (x_post, P_post, x_prior, prior_var, truth))
    n = x.shape[0]
    if P.shape != (n, n) or x0.shape != (n,) or v0.shape != (n,) or t.shape != (n,):
        raise ValueError(f"data_only_nees: shapes {x.shape}, {P.shape}, {x0.shape}, {v0.shape}, {t.shape}")
    if not (v0 > 0).all():
        raise ValueError("data_only_nees: every prior variance must be positive")
    d = np.sqrt(v0)
    A = P / np.outer(d, d)
    a, V = np.linalg.eigh(0.5 * (A + A.T))
    u, u_true = (x - x0) / d, (t - x0) / d
    det = a < ratio
    if not det.any():
        return DataNees(0.0, 0, a, np.zeros(n))
    ak, Vk = a[det], V[:, det]
    est = (Vk.T @ u) / (1.0 - ak)
    err = est - Vk.T @ u_true
    nees = float(np.sum(err**2 * (1.0 - ak) / ak))
    return DataNees(nees, int(det.sum()), a, np.sum(Vk**2, axis=1))
