"""Ellipsoid fitting shared by the magnetometer (eqs. 17–24) and the static accelerometer (eq. 32).

A sensor whose calibrated output has constant norm r (the local field, or g at rest) traces the
ellipsoid ``‖M (x − o)‖ = r``. The algebraic fit (SVD of the design matrix D) gives the start; the
geometric fit (Levenberg–Marquardt on eq. 17) refines it. Both leave M's orthogonal factor free,
so M is returned symmetric; the rotation to the body frame is found later (eqs. 25–27).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

Array = NDArray[np.float64]

_IU = np.triu_indices(3)


class FitError(ValueError):
    """Too little or too degenerate data for a fit; the message says which."""


def sym_from_vec(v: Array) -> Array:
    M = np.zeros((3, 3))
    M[_IU] = v
    return M + np.triu(M, 1).T


def sqrtm_spd(A: Array) -> Array:
    w, V = np.linalg.eigh(A)
    if np.any(w <= 0):
        raise FitError("ellipsoid fit is not an ellipsoid (quadratic form not positive definite)")
    return (V * np.sqrt(w)) @ V.T


def fit_ellipsoid_svd(x: Array) -> tuple[Array, Array]:
    """Algebraic ellipsoid fit by SVD (eqs. 19–24). x (N, 3), N ≥ 10, not coplanar.

    D has rows ``[x², y², z², 2xy, 2xz, 2yz, 2x, 2y, 2z, 1]`` (eq. 19); d is the right singular
    vector of D for its smallest singular value (eq. 20); A, b, c from d (eqs. 21–22); the centre
    o = −A⁻¹ b and the symmetric correction M = (A / (oᵀAo − c))^½ (eqs. 23–24), so that
    ‖M (x − o)‖ = 1. Returns (o (3,), M (3, 3)). Data are normalised first for conditioning.
    """
    x = np.asarray(x, float)
    if x.shape[0] < 10:
        raise FitError(f"ellipsoid fit needs ≥ 10 points, got {x.shape[0]}")
    m = x.mean(axis=0)
    s = float(np.sqrt(((x - m) ** 2).sum(axis=1).mean())) or 1.0
    u = (x - m) / s
    X, Y, Z = u.T
    D = np.column_stack([X * X, Y * Y, Z * Z, 2 * X * Y, 2 * X * Z, 2 * Y * Z, 2 * X, 2 * Y, 2 * Z,
                         np.ones_like(X)])
    _, sv, Vt = np.linalg.svd(D, full_matrices=False)
    d = Vt[-1]
    A = np.array([[d[0], d[3], d[4]], [d[3], d[1], d[5]], [d[4], d[5], d[2]]])
    b = d[6:9]
    c = d[9]
    if np.linalg.det(A) < 0 or np.trace(A) < 0:
        A, b, c = -A, -b, -c
    try:
        o_u = -np.linalg.solve(A, b)
    except np.linalg.LinAlgError as e:
        raise FitError("ellipsoid fit is singular (points do not span 3-D)") from e
    k = float(o_u @ A @ o_u - c)
    if k <= 0:
        raise FitError("ellipsoid fit is degenerate")
    M_u = sqrtm_spd(A / k)
    return m + s * o_u, M_u / s


@dataclass
class NormFit:
    """Result of the geometric norm fit: o (3,), symmetric M (3,3), covariance of the 9 parameters
    (o, upper triangle of M), residual RMS (unit of r), the inlier mask and the parameter count."""

    o: Array
    M: Array
    cov: Array
    rms: float
    inliers: Array
    n_params: int


def fit_norm_lm(
    x: Array,
    r: float,
    o0: Array,
    M0: Array,
    model: str = "full",
    reject_sigma: float = 5.0,
) -> NormFit:
    """Geometric fit of ‖M (x − o)‖ = r by Levenberg–Marquardt (eq. 17; eq. 32 for the accelerometer).

    ``model``: ``"full"`` (o + symmetric M, 9 parameters), ``"diag"`` (o + diagonal M, 6) or
    ``"bias"`` (o + one common scale, 4) or ``"offset"`` (o alone, M fixed to M0, 3) — the reduced
    models serve when the data cannot carry all nine. Outlier rejection at ``reject_sigma`` × MAD
    (where the points outnumber the parameters fourfold), then a refit.
    """
    x = np.asarray(x, float)

    def unpack(p: Array) -> tuple[Array, Array]:
        o = p[:3]
        if model == "full":
            return o, sym_from_vec(p[3:9])
        if model == "diag":
            return o, np.diag(p[3:6])
        if model == "offset":
            return o, M0
        return o, np.eye(3) * p[3]

    if model == "full":
        p0 = np.concatenate([o0, M0[_IU]])
    elif model == "diag":
        p0 = np.concatenate([o0, np.diag(M0)])
    elif model == "offset":
        p0 = np.asarray(o0, float).copy()
    else:
        p0 = np.concatenate([o0, [np.trace(M0) / 3]])
    if x.shape[0] < p0.size:
        raise FitError(f"norm fit ({model}) needs ≥ {p0.size} points, got {x.shape[0]}")

    def resid(p: Array, pts: Array) -> Array:
        o, M = unpack(p)
        return np.linalg.norm((pts - o) @ M.T, axis=1) - r

    keep = np.ones(x.shape[0], bool)
    sol = least_squares(resid, p0, args=(x,), method="lm", x_scale="jac")
    # Outlier rejection only where the data outnumber the parameters well (not on 12 static means).
    for _ in range(2 if x.shape[0] >= 4 * p0.size else 0):
        res = resid(sol.x, x)
        mad = 1.4826 * np.median(np.abs(res - np.median(res)))
        new_keep = np.abs(res) <= max(reject_sigma * mad, 1e-12)
        if new_keep.sum() < p0.size or np.array_equal(new_keep, keep):
            break
        keep = new_keep
        sol = least_squares(resid, sol.x, args=(x[keep],), method="lm", x_scale="jac")
    res = resid(sol.x, x[keep])
    dof = max(1, keep.sum() - p0.size)
    s2 = float(res @ res / dof)
    J = sol.jac
    try:
        cov_p = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        cov_p = np.full((p0.size, p0.size), np.inf)
    # Express the covariance in the full 9-parameter layout (o, upper triangle of M).
    T = np.zeros((9, p0.size))
    T[:3, :3] = np.eye(3)
    if model == "full":
        T[3:, 3:] = np.eye(6)
    elif model == "diag":
        for j, idx in enumerate((0, 3, 5)):
            T[3 + idx, 3 + j] = 1
    elif model == "bias":
        T[[3, 6, 8], 3] = 1
    o, M = unpack(sol.x)
    return NormFit(o, M, T @ cov_p @ T.T, float(np.sqrt(np.mean(res**2))), keep, p0.size)
