"""The scaled unscented transform and the Kalman update, as pure functions of (x, P, ...).

Sigma points and weights are those of Wan & van der Merwe (2000), as filterpy's
``MerweScaledSigmaPoints`` has them (its weights' arithmetic, compared with it bit for bit in
``tests/test_ukf_parts.py``; the points written out so that the factor can be taken in any state order).
The update is the textbook UKF update (Särkkä, *Bayesian Filtering and Smoothing*, alg. 8.3 / filterpy's
``UnscentedKalmanFilter.update``) on stacked measurements, with

* per-sensor chi-square gating (:class:`Gating`: dropped, or R inflated to the gate's size),
* Schmidt–Kalman consider states (zero gain; the Joseph-like covariance update keeps P the true error
  covariance for any gain),
* damping (the gain of a partial update, Zanetti 2012's recursive update).

Nothing here touches a filter object: each function returns what it computed, and the caller books it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def merwe_weights(n: int, alpha: float, beta: float, kappa: float) -> tuple[Array, Array]:
    """Mean and covariance weights (2n + 1,) each of the scaled unscented transform: λ = α²(n + κ) − n,
    W_i = 1/(2(n + λ)), Wm_0 = λ/(n + λ), Wc_0 = Wm_0 + 1 − α² + β — filterpy's
    ``MerweScaledSigmaPoints._compute_weights``, operation for operation (importing filterpy costs every
    start-up ~1 s: its ``kalman`` package pulls in scipy.stats)."""
    lambda_ = alpha**2 * (n + kappa) - n
    c = 0.5 / (n + lambda_)
    Wc = np.full(2 * n + 1, c)
    Wm = np.full(2 * n + 1, c)
    Wc[0] = lambda_ / (n + lambda_) + (1 - alpha**2 + beta)
    Wm[0] = lambda_ / (n + lambda_)
    return Wm, Wc


def sigma_points(x: Array, P: Array, alpha: float, kappa: float, perm: NDArray[np.intp],
                 perm_id: bool) -> Array:
    """Scaled sigma points X (2n + 1, n) around x (n,) with covariance P (n, n): x, x + D_i, x − D_i with
    D the rows of the upper Cholesky factor of (λ + n) P, λ = α²(n + κ) − n.

    The factor is taken in ``perm`` order (``perm_id``: the identity): with the attitude-relevant states
    first, rows past the first n_dyn leave those states at the mean. Any square root gives a valid set;
    with ``perm_id`` these are exactly filterpy's points. Raises ``np.linalg.LinAlgError`` when P is not
    positive definite.
    """
    n = x.shape[0]
    lam = alpha**2 * (n + kappa) - n
    if perm_id:
        D = np.linalg.cholesky((lam + n) * P).T  # rows: offsets
    else:
        U = np.linalg.cholesky((lam + n) * P[np.ix_(perm, perm)]).T  # rows: offsets, permuted
        D = np.empty((n, n))
        D[:, perm] = U
    X = np.empty((2 * n + 1, n))
    X[0] = x
    np.add(x, D, out=X[1 : n + 1])
    np.subtract(x, D, out=X[n + 1 :])
    return X


def predict_moments(X: Array, Wm: Array, Wc: Array, q: Array) -> tuple[Array, Array, Array]:
    """Unscented transform of propagated sigma points X (2n + 1, n): mean x (n,), deviations Y = X − x,
    covariance P = Σ Wc Y Yᵀ + diag(q) (q (n,) the process noise)."""
    x_pred = Wm @ X
    Y = X - x_pred
    P_pred = (Y.T * Wc) @ Y
    P_pred.flat[:: P_pred.shape[0] + 1] += q
    return x_pred, Y, P_pred


@dataclass
class Measurement:
    """One 3-vector measurement of a stacked update: observed z (3,), its prediction per sigma point
    Z (2n + 1, 3), the diagonal of R (3,), and the name of the sensor (``accel``, ``mag``, ``rest``)."""

    name: str
    z: Array
    Z: Array
    r: Array


@dataclass
class Gating:
    """Chi-square gates per sensor (3 dof) and whether the block is static (a rest).

    In motion an accel NIS above its gate is motion the model lacks (linear acceleration): the accel is
    dropped. Otherwise a NIS above the gate inflates R so that the update counts no more than a gate-sized
    one (soft gate). ``rest`` measurements are never gated."""

    gates: dict[str, float]
    static: bool


@dataclass
class UpdateResult:
    """What :func:`update` did: the posterior, and per gated sensor (in measurement order) its NIS and
    whether it was dropped or inflated; ``post`` per gated sensor the measurement the posterior predicts
    and its covariance (for the next block's NIS at a rest)."""

    x: Array
    P: Array
    nis: list[tuple[str, float, str]] = field(default_factory=list)  # (sensor, NIS, "ok"|"soft"|"drop")
    post: dict[str, tuple[Array, Array]] = field(default_factory=dict)


def update(Y: Array, x_pred: Array, P_pred: Array, meas: list[Measurement], Wm: Array, Wc: Array,
           gating: Gating, consider: NDArray[np.bool_], damp: float = 0.0,
           want_post: bool = False) -> UpdateResult:
    """Joint UKF update with the stacked measurements ``meas``.

    Y (2n + 1, n) the sigma points less the predicted mean x_pred (n,), P_pred (n, n). Per gated sensor
    its NIS ν S⁻¹ ν against ``gating``; consider states (``consider`` (n,) bool) get zero gain; the
    covariance update P − K Pzxᵀ − Pzx Kᵀ + K S Kᵀ is the error covariance for any gain. ``damp`` > 0:
    the gain is computed as if R were at least damp × HPHᵀ (a partial update: the mean moves at most
    1/(1 + damp) of the way), while the gating and P use the model's S (P keeps at least
    damp²/(1 + damp)² of the prior's variance along a measurement).
    ``want_post``: per gated sensor z + (S − R) S⁻¹ ν and (S − R) − (S − R) S⁻¹ (S − R) (linearised).
    """
    names = [m.name for m in meas]
    z = np.concatenate([m.z for m in meas])
    Z = np.hstack([m.Z for m in meas])
    r_diag = np.concatenate([m.r for m in meas])
    z_pred = Wm @ Z
    Zc = Z - z_pred
    ZW = Zc * Wc[:, None]
    S_zz = Zc.T @ ZW
    hph = np.diag(S_zz).copy()
    S_zz.flat[:: S_zz.shape[0] + 1] += r_diag
    Pxz = Y.T @ ZW
    nu = z - z_pred
    k_gate = [k for k, s in enumerate(names) if s != "rest"]
    nis_all = _block_nis(S_zz, nu, k_gate, len(names))
    res = UpdateResult(x_pred, P_pred)
    keep = _gate(res, names, nis_all, gating, S_zz, r_diag, z_pred, nu, want_post)
    S_gain = S_zz
    if damp > 0:
        S_gain = S_zz.copy()
        d = np.diag(S_zz) - hph
        S_gain.flat[:: S_zz.shape[0] + 1] += np.maximum(0.0, damp * hph - d)
    if keep is not None:
        if not keep.any():
            return res
        S_zz = S_zz[np.ix_(keep, keep)]
        S_gain = S_gain[np.ix_(keep, keep)] if damp > 0 else S_zz
        Pxz = Pxz[:, keep]
        nu = nu[keep]
    K = np.linalg.solve(S_gain, Pxz.T).T
    K[consider] = 0.0  # Schmidt ("consider") states: never updated
    res.x = x_pred + K @ nu
    KPzx = K @ Pxz.T
    res.P = P_pred - KPzx - KPzx.T + (K @ S_zz) @ K.T
    return res


def _gate(res: UpdateResult, names: list[str], nis_all: list[float], gating: Gating, S_zz: Array, r_diag: Array,
          z_pred: Array, nu: Array, want_post: bool) -> NDArray[np.bool_] | None:
    """Chi-square gate of each gated 3-block of the stacked measurement (all but "rest"), recorded in
    ``res.nis`` as (sensor, NIS, "ok" | "soft" | "drop"): a moving accel block over its gate is dropped, any
    other over its gate has its R inflated in ``S_zz`` (in place) to the gate's size. With ``want_post``,
    ``res.post`` gets each gated block's linearised posterior (see :func:`update`). Returns the mask of the
    measurement rows kept (None: all)."""
    keep = None
    for k, s in enumerate(names):
        if s == "rest":
            continue
        sl = slice(3 * k, 3 * k + 3)
        nis = nis_all[k]
        gate = gating.gates[s]
        if s == "accel" and not gating.static and nis > gate:
            if keep is None:
                keep = np.ones(nu.size, bool)
            keep[sl] = False
            res.nis.append((s, nis, "drop"))
            continue
        res.nis.append((s, nis, "soft" if nis > gate else "ok"))
        if nis > gate:
            S_zz[sl, sl] += np.diag(r_diag[sl] * (nis / gate - 1))
        if want_post:
            Sk = S_zz[sl, sl]
            A = Sk - np.diag(r_diag[sl])
            AS = np.linalg.solve(Sk, A).T  # A S⁻¹ (S, A symmetric)
            res.post[s] = (z_pred[sl] + AS @ nu[sl], A - AS @ A)
    return keep


def _block_nis(S_zz: Array, nu: Array, k_gate: list[int], m: int) -> list[float]:
    """NIS of each 3-block k in ``k_gate`` of the stacked innovation ν with covariance S; inf elsewhere
    (and for all when a block of S is singular)."""
    nis_all = [math.inf] * m
    if k_gate:
        S_b = np.stack([S_zz[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] for k in k_gate])
        nu_b = np.stack([nu[3 * k : 3 * k + 3] for k in k_gate])
        try:
            sol = np.linalg.solve(S_b, nu_b[..., None])[..., 0]
            for kk, k in enumerate(k_gate):
                nis_all[k] = float(nu_b[kk] @ sol[kk])
        except np.linalg.LinAlgError:
            pass
    return nis_all
