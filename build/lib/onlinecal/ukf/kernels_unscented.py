"""The unscented transform and the update of :mod:`onlinecal.ukf.unscented` on the kernel backend.

Same signatures and results as the numpy functions there (the reference); with the backend "numba"
(:mod:`onlinecal.ukf.kernels`) each is one compiled call: :func:`sigma_points` (Cholesky factor in the
filter's state order, :func:`~onlinecal.ukf.kernels_update.sigma_points_kernel`), :func:`predict_moments`
(:func:`~onlinecal.ukf.kernels_update.unscented_kernel`) and :func:`update` (gating, damping, Schmidt gain and the
covariance update of one block in :func:`~onlinecal.ukf.kernels_update.update_kernel`). With the backend "numpy"
they are the reference functions themselves.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from . import kernels, unscented
from .kernels_update import sigma_points_kernel, unscented_kernel, unscented_motion_kernel, update_kernel
from .unscented import Gating, Measurement, UpdateResult

Array = NDArray[np.float64]
_STATUS = {0: "ok", 1: "soft", 2: "drop"}
_IDENTITY: dict[int, NDArray[np.intp]] = {}


def _identity(n: int) -> NDArray[np.intp]:
    """0..n−1 as an index array (kept: the state order of the Cholesky factor when no permutation)."""
    if n not in _IDENTITY:
        _IDENTITY[n] = np.arange(n, dtype=np.intp)
    return _IDENTITY[n]


def sigma_points(x: Array, P: Array, alpha: float, kappa: float, perm: NDArray[np.intp],
                 perm_id: bool) -> Array:
    """:func:`onlinecal.ukf.unscented.sigma_points` (X (2n + 1, n)); raises ``np.linalg.LinAlgError``
    when P is not positive definite."""
    if kernels.backend() == "numpy":
        return unscented.sigma_points(x, P, alpha, kappa, perm, perm_id)
    n = x.shape[0]
    lam = alpha**2 * (n + kappa) - n
    order = _identity(n) if perm_id else np.asarray(perm, dtype=np.intp)
    X, ok = sigma_points_kernel(x, P, lam + n, order)
    if not ok:
        raise np.linalg.LinAlgError("Matrix is not positive definite")
    out: Array = X
    return out


def predict_moments(X: Array, Wm: Array, Wc: Array, q: Array) -> tuple[Array, Array, Array]:
    """:func:`onlinecal.ukf.unscented.predict_moments`: (x_pred (n,), Y (2n + 1, n), P_pred (n, n))."""
    if kernels.backend() == "numpy":
        return unscented.predict_moments(X, Wm, Wc, q)
    out: tuple[Array, Array, Array] = unscented_kernel(
        np.ascontiguousarray(X, dtype=np.float64), Wm, Wc, np.ascontiguousarray(q, dtype=np.float64))
    return out


def predict_moments_motion(X: Array, Wm: Array, Wc: Array, q: Array, P: Array) -> tuple[Array, Array, Array]:
    """:func:`predict_moments` of a motion block's sigma points X (2n + 1, n), drawn from (x, P) and propagated
    (only their attitude columns moved): on the numpy backend the reference itself; compiled,
    :func:`~onlinecal.ukf.kernels_update.unscented_motion_kernel` (P_pred's other entries P + diag(q), equal to
    the reference's sum to rounding)."""
    if kernels.backend() == "numpy":
        return unscented.predict_moments(X, Wm, Wc, q)
    out: tuple[Array, Array, Array] = unscented_motion_kernel(
        np.ascontiguousarray(X, dtype=np.float64), Wm, Wc, np.ascontiguousarray(q, dtype=np.float64),
        np.ascontiguousarray(P, dtype=np.float64))
    return out


def update(Y: Array, x_pred: Array, P_pred: Array, meas: list[Measurement], Wm: Array, Wc: Array,
           gating: Gating, consider: NDArray[np.bool_], damp: float = 0.0,
           want_post: bool = False) -> UpdateResult:
    """:func:`onlinecal.ukf.unscented.update` (same arguments, same :class:`UpdateResult`)."""
    if kernels.backend() == "numpy":
        return unscented.update(Y, x_pred, P_pred, meas, Wm, Wc, gating, consider, damp, want_post)
    names = [m.name for m in meas]
    k = len(meas)
    gated = np.empty(k, np.bool_)
    droppable = np.empty(k, np.bool_)
    gates = np.empty(k)
    for i, s in enumerate(names):
        gated[i] = s != "rest"
        droppable[i] = s == "accel" and not gating.static
        gates[i] = gating.gates[s] if gated[i] else np.inf
    x, P, nis, status, post_z, post_P, ok = update_kernel(
        Y, x_pred, P_pred, np.concatenate([m.z for m in meas]), np.hstack([m.Z for m in meas]),
        np.concatenate([m.r for m in meas]), Wm, Wc, gated, droppable, gates, consider, float(damp),
        bool(want_post))
    if not ok:
        raise np.linalg.LinAlgError("Singular matrix")
    res = UpdateResult(x, P)
    for k, s in enumerate(names):
        if status[k] < 0:
            continue
        res.nis.append((s, float(nis[k]), _STATUS[int(status[k])]))
        if want_post and status[k] != 2:
            res.post[s] = (post_z[k], post_P[k])
    return res
