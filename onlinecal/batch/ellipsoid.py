"""Ellipsoid fitting shared by the magnetometer (eqs. 17–24) and the static accelerometer (eq. 32).

A sensor whose calibrated output has constant norm r (the local field, or g at rest) traces the
ellipsoid ``‖M (x − o)‖ = r``. The algebraic fit (SVD of the design matrix D) gives the start; the
geometric fit (Levenberg–Marquardt on eq. 17) refines it. Both leave M's orthogonal factor free,
so M is returned symmetric; the rotation to the body frame is found later (eqs. 25–27).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

_IU = np.triu_indices(3)
_JJ, _KK = _IU
_OFF = (_JJ != _KK).astype(float)


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


def fit_ellipsoid_svd(x: Array, weights: Array | None = None) -> tuple[Array, Array]:
    """Algebraic ellipsoid fit by SVD (eqs. 19–24). x (N, 3), N ≥ 10, not coplanar.

    D has rows ``[x², y², z², 2xy, 2xz, 2yz, 2x, 2y, 2z, 1]`` (eq. 19); d is the right singular
    vector of D for its smallest singular value (eq. 20); A, b, c from d (eqs. 21–22); the centre
    o = −A⁻¹ b and the symmetric correction M = (A / (oᵀAo − c))^½ (eqs. 23–24), so that
    ‖M (x − o)‖ = 1. Returns (o (3,), M (3, 3)). Data are normalised first for conditioning.
    ``weights`` (N,) ≥ 0 scale the rows of D by √w (attitude-coverage weighting).
    """
    x = np.asarray(x, float)
    if weights is not None:
        x = x[np.asarray(weights) > 0]
        weights = np.asarray(weights, float)[np.asarray(weights) > 0]
    if x.shape[0] < 10:
        raise FitError(f"ellipsoid fit needs ≥ 10 points, got {x.shape[0]}")
    m = x.mean(axis=0)
    s = float(np.sqrt(((x - m) ** 2).sum(axis=1).mean())) or 1.0
    u = (x - m) / s
    X, Y, Z = u.T
    D = np.column_stack([X * X, Y * Y, Z * Z, 2 * X * Y, 2 * X * Z, 2 * Y * Z, 2 * X, 2 * Y, 2 * Z,
                         np.ones_like(X)])
    if weights is not None:
        D = D * np.sqrt(weights / weights.max())[:, None]
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
    inliers: BoolArray
    n_params: int


def _resid_jac_full(p: Array, pts: Array, r: float) -> tuple[Array, Array]:
    """Residuals ‖M (x − o)‖ − r (N,) of the full model and their Jacobian (N, 9) for p = (o, upper triangle
    of the symmetric M): with d = x − o, y = M d, n = y/‖y‖, ∂/∂o = −M n and ∂/∂M_jk = n_j d_k + n_k d_j
    (j < k), n_j d_j (j = k)."""
    o = p[:3]
    M = sym_from_vec(p[3:])
    d = pts - o
    y = d @ M
    ny = np.sqrt(np.einsum("ij,ij->i", y, y))
    nv = y / ny[:, None]
    J = np.empty((pts.shape[0], 9))
    J[:, :3] = -(nv @ M)
    J[:, 3:] = nv[:, _JJ] * d[:, _KK] + _OFF * nv[:, _KK] * d[:, _JJ]
    return ny - r, J


def levenberg_marquardt(fun: Callable[[Array], tuple[Array, Array]], p: Array, max_iter: int) -> Array:
    """Minimise ‖r(p)‖² by Levenberg–Marquardt with Marquardt's scaling (damping λ diag(JᵀJ)), from p, at
    most ``max_iter`` steps; ``fun(p)`` gives the residuals r (N,) and their analytic Jacobian (N, P). Stops
    when a step lowers the cost by less than 1e-12 of it, or λ passes 1e8 (no step lowers it)."""
    lam = 1e-3
    r, J = fun(p)
    cost = float(r @ r)
    for _ in range(max_iter):
        A = J.T @ J
        g = J.T @ r
        try:
            step = np.linalg.solve(A + lam * np.diag(np.diag(A)), -g)
        except np.linalg.LinAlgError:
            break
        p_new = p + step
        r_new, J_new = fun(p_new)
        c_new = float(r_new @ r_new)
        if np.isfinite(c_new) and c_new < cost:
            done = cost - c_new < 1e-12 * cost
            p, r, J, cost = p_new, r_new, J_new, c_new
            lam = max(lam / 10.0, 1e-12)
            if done:
                break
        else:
            lam *= 10.0
            if lam > 1e8:
                break
    return p


def psd_excess(c_new: Array, cov: Array) -> Array:
    """The positive part of ``c_new`` − ``cov`` (both (P, P)): what a second covariance estimate adds beyond the
    first, direction by direction (eigen-decomposition of the symmetrised difference, negative parts dropped),
    so that ``cov`` + the excess covers both."""
    d = 0.5 * ((c_new - cov) + (c_new - cov).T)
    ev, V = np.linalg.eigh(d)
    out: Array = (V * np.maximum(ev, 0.0)) @ V.T
    return out


def fit_norm_lm(
    x: Array,
    r: float,
    o0: Array,
    M0: Array,
    model: str = "full",
    reject_sigma: float = 5.0,
    weights: Array | None = None,
    max_iter: int = 200,
    refine: bool = True,
    rounds: int = 2,
) -> NormFit:
    """Geometric fit of ‖M (x − o)‖ = r by Levenberg–Marquardt (eq. 17; eq. 32 for the accelerometer).

    x (N, 3) raw samples; r the calibrated norm (1 for the field, g for gravity). ``model``: ``"full"``
    (o + symmetric M, 9 parameters), ``"diag"`` (o + diagonal M, 6) or ``"bias"`` (o + one common scale,
    4) or ``"offset"`` (o alone, M fixed to M0, 3) — the reduced models serve when the data cannot carry
    all nine. ``weights`` (N,) ≥ 0: each sample's share (e.g. 1 / samples in its attitude bin, so that a
    long rest counts as one attitude); the covariance then uses the effective sample count
    (Σw)² / Σw². Outlier rejection at ``reject_sigma`` × MAD (where the points outnumber the parameters
    fourfold), then a refit; at most ``rounds`` such rounds. The minimiser is :func:`levenberg_marquardt`
    (at most ``max_iter`` steps). This is the package's one eq. 17 fit: the UKF's cold magnetometer start
    (:func:`onlinecal.ukf.attitude_init.ellipsoid_gn`) calls it too. The Jacobian is analytic:
    ∂‖y‖/∂o = −Mᵀy/‖y‖, ∂‖y‖/∂M_jk = (y_j d_k + y_k d_j)/‖y‖ (j ≠ k; y_j d_j/‖y‖ on the diagonal) with
    d = x − o, y = M d. ``refine=False`` keeps (o0, M0) and only
    evaluates the residual and covariance there (for a start that LM would leave along a degenerate valley).
    """
    x = np.asarray(x, float)
    wt = np.ones(x.shape[0]) if weights is None else np.asarray(weights, float)
    if wt.shape != (x.shape[0],) or not np.all(np.isfinite(wt)) or np.any(wt < 0):
        raise ValueError("weights must be (N,) finite and ≥ 0")
    wt = wt / wt.max() if wt.max() > 0 else np.ones_like(wt)

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

    def resid_jac(p: Array, pts: Array) -> tuple[Array, Array]:
        """Unweighted residuals ‖M (x − o)‖ − r (N,) and their Jacobian (N, P)."""
        if model == "full":
            return _resid_jac_full(p, pts, r)
        o, M = unpack(p)
        d = pts - o
        y = d @ M.T
        ny = np.linalg.norm(y, axis=1)
        u = y / np.maximum(ny, 1e-300)[:, None]
        cols = [-(u @ M)]
        if model == "diag":
            cols.append(u * d)
        elif model == "bias":
            cols.append(np.einsum("ij,ij->i", u, d)[:, None])
        return ny - r, np.hstack(cols)

    def solve(p: Array, m: BoolArray) -> Array:
        if not refine:
            return p
        sw, pts = np.sqrt(wt[m]), x[m]

        def fun(q: Array) -> tuple[Array, Array]:
            res, J = resid_jac(q, pts)
            return sw * res, J * sw[:, None]

        return levenberg_marquardt(fun, p, max_iter)

    keep = wt > 0
    px = solve(p0, keep)
    # Outlier rejection only where the data outnumber the parameters well (not on 12 static means).
    for _ in range(rounds if keep.sum() >= 4 * p0.size else 0):
        res = resid_jac(px, x)[0]
        ref = res[wt > 0]
        mad = 1.4826 * np.median(np.abs(ref - np.median(ref)))
        new_keep = (np.abs(res) <= max(reject_sigma * mad, 1e-12)) & (wt > 0)
        if new_keep.sum() < p0.size or np.array_equal(new_keep, keep):
            break
        keep = new_keep
        px = solve(px, keep)
    w_k = wt[keep]
    res, J = resid_jac(px, x[keep])
    if weights is None:
        s2 = float(res @ res) / max(1, int(keep.sum()) - p0.size)
        rms = math.sqrt(float(np.mean(res * res)))
    else:  # the effective sample count (Σw)² / Σw² in place of N
        n_eff = float(w_k.sum() ** 2 / (w_k @ w_k))
        dof = max(1.0, n_eff - p0.size)
        s2 = float((w_k * res) @ res / w_k.sum() * n_eff / dof)
        J = J * np.sqrt(w_k / w_k.sum() * n_eff)[:, None]
        rms = float(np.sqrt(np.average(res**2, weights=w_k)))
    try:
        cov_p: Array = np.asarray(np.linalg.inv(J.T @ J) * s2, float)
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
    o, M = unpack(px)
    return NormFit(o, M, cov_p if model == "full" else T @ cov_p @ T.T, rms, keep, p0.size)


def sphere_bin_weights(u: Array, cell_deg: float = 10.0, per_bin: int | None = None,
                       rng: np.random.Generator | None = None) -> Array:
    """Weight of each direction u (N, 3) so that every occupied cell of a sphere grid counts once.

    The grid has rings of ``cell_deg`` in latitude and about ``cell_deg`` in longitude (equal-ish
    area, as autopilots space their compass samples). Weight = 1 / samples in the cell, so a
    10-minute rest is one attitude, not 60 000 samples. ``per_bin``: at most this many samples per
    cell keep a weight (a deterministic stride within the cell, or random with ``rng``), the others 0
    — bounded work for any log length. Returns (N,) weights.
    """
    u = np.asarray(u, float)
    n = u.shape[0]
    if n == 0:
        return np.zeros(0)
    uu = u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)
    lat = np.arcsin(np.clip(uu[:, 2], -1.0, 1.0))
    lon = np.arctan2(uu[:, 1], uu[:, 0])
    step = np.radians(cell_deg)
    ring = np.minimum(((lat + np.pi / 2) / step).astype(int), int(np.ceil(np.pi / step)) - 1)
    ring_lat = -np.pi / 2 + (ring + 0.5) * step
    n_lon = np.maximum(1, np.round(2 * np.pi * np.cos(ring_lat) / step)).astype(int)
    col = np.minimum(((lon + np.pi) / (2 * np.pi) * n_lon).astype(int), n_lon - 1)
    cell = ring * 1000 + col
    _, inv, cnt = np.unique(cell, return_inverse=True, return_counts=True)
    w = 1.0 / cnt[inv]
    if per_bin is not None:
        order = np.argsort(inv, kind="stable") if rng is None else np.lexsort((np.asarray(rng.random(size=n)), inv))
        starts = np.concatenate([[0], np.cumsum(cnt)[:-1]])
        rank = np.empty(n, int)
        rank[order] = np.arange(n) - np.repeat(starts, cnt)
        c_of = cnt[inv]
        # stride through each cell so that the kept samples span its whole time range
        stride = np.maximum(1, c_of // per_bin)
        kept = (rank % stride == 0) & (rank // stride < per_bin)
        nk = np.bincount(inv, weights=kept.astype(float))
        w = np.where(kept, 1.0 / np.maximum(nk[inv], 1.0), 0.0)
    return w


# Prior on the magnetometer's soft iron where the samples do not determine it (a band of directions):
# M = m̄ (I + E), E symmetric, each diagonal entry of E with σ SOFT_DIAG_SIGMA and each off-diagonal with
# σ SOFT_OFF_SIGMA; m̄ = tr(M)/3 (1 / the field in raw units) and the centre o free. The same σ the online
# filter gives its own sphere fit's scale and non-orthogonality (UKFConfig.mag_fit_sigma: 0.15, 0.035): a
# real compass's axis gains agree within ±10–15 % and its axes are orthogonal within a few degrees.
SOFT_DIAG_SIGMA = 0.15
SOFT_OFF_SIGMA = 0.035


def _soft_iron_prior(p: Array, sig_diag: float, sig_off: float) -> tuple[Array, Array]:
    """Prior residuals (6,) of the soft iron in σ units — (M_jj / m̄ − 1) / σ_diag and M_jk / m̄ / σ_off for
    the upper triangle (j, k) of M, m̄ = tr(M)/3 — and their Jacobian (6, 9) in p = (o, upper triangle of M)."""
    Mv = p[3:]
    diag = _JJ == _KK
    mbar = float(Mv[diag].sum() / 3.0)
    sig = np.where(diag, sig_diag, sig_off)
    ratio = Mv / mbar
    r = (ratio - diag.astype(float)) / sig
    J = np.zeros((6, 9))
    # ∂(M_i / m̄)/∂M_l = δ_il / m̄ − M_i / (3 m̄²) [l on the diagonal]
    J[:, 3:] = (np.eye(6) / mbar - np.outer(Mv, diag.astype(float)) / (3 * mbar * mbar)) / sig[:, None]
    return r, J


def fit_norm_map(x: Array, o0: Array, M0: Array, weights: Array | None = None,
                 sig_diag: float = SOFT_DIAG_SIGMA, sig_off: float = SOFT_OFF_SIGMA,
                 max_iter: int = 200, rounds: int = 6) -> NormFit:
    """Eq. 17 (‖M (x − o)‖ = 1, full model) as a maximum a-posteriori fit with a prior on the soft iron
    (:func:`_soft_iron_prior`: M near a multiple of the identity, diagonal σ ``sig_diag`` relative,
    off-diagonal ``sig_off``), for samples that see the field over part of the sphere only.

    Two departures from :func:`fit_norm_lm`, both for a band of directions (a flight's yaw turns with
    small tilts), where eq. 17's least squares have a valley — the centre along the unseen direction
    trades against the size and the scale along it:

    * the residual is the distance to the ellipsoid in the **raw** unit, to first order
      (‖M (x − o)‖ − 1) / ‖Mᵀ n‖ with n = M (x − o)/‖M (x − o)‖ (the gradient's norm, recomputed each
      round and held within one): the calibrated-unit residual shrinks with M itself, so along the valley
      its least squares slide to a larger ellipsoid (10-min flights: scale 27–66 % low, bias 7–14σ off);
    * the posterior covariance (JᵀWJ/s² + J_pᵀJ_p)⁻¹ keeps the prior's width along the directions the data
      leave free and carries it into the centre through their correlation: σ that cover the extrapolation.

    Where the directions span the sphere the data outweigh the prior a millionfold. s² (one sample's
    residual variance) comes from the fit's own residuals with the effective sample count (Σw)²/Σw², as
    :func:`fit_norm_lm` does. x (N, 3) raw samples (outliers already removed), ``weights`` (N,) ≥ 0
    (attitude bins); (o0 (3,), M0 (3, 3) symmetric) the start. Returns :class:`NormFit` (``rms`` in the raw
    unit) with the posterior covariance of (o, upper triangle of M).
    """
    x = np.asarray(x, float)
    wt = np.ones(x.shape[0]) if weights is None else np.asarray(weights, float)
    keep = wt > 0
    x, wt = x[keep], wt[keep]
    if x.shape[0] < 9:
        raise FitError(f"norm fit (map) needs ≥ 9 points, got {x.shape[0]}")
    n_eff = float(wt.sum() ** 2 / (wt @ wt))
    c = wt / wt.sum() * n_eff  # each sample's share of the effective count
    p = np.concatenate([np.asarray(o0, float), 0.5 * (M0 + M0.T)[_IU]])

    def geo(q: Array) -> Array:
        """(‖M (x − o)‖ − 1) / ‖Mᵀ n‖: the first-order distance to the ellipsoid in the raw unit."""
        M = sym_from_vec(q[3:])
        y = (x - q[:3]) @ M
        ny = np.linalg.norm(y, axis=1)
        g = np.linalg.norm((y / ny[:, None]) @ M, axis=1)
        out: Array = (ny - 1.0) / g
        return out

    def geo_jac(q: Array) -> tuple[Array, Array]:
        # the distance and its Jacobian (N, 9) by central differences: the gradient's norm moves with
        # (o, M) too, and holding it fixed within a step brings back the slide to a larger ellipsoid
        r0 = geo(q)
        J = np.empty((x.shape[0], 9))
        for k in range(9):
            h = 1e-6 * max(abs(float(q[k])), float(np.abs(q[3:]).max()) * 1e-2)
            dq = np.zeros(9)
            dq[k] = h
            J[:, k] = (geo(q + dq) - geo(q - dq)) / (2 * h)
        return r0, J

    def s2_at(q: Array) -> float:
        res = geo(q)
        return max(float(c @ (res * res)) / max(1.0, n_eff - 9.0), 1e-300)

    s2 = s2_at(p)
    for _ in range(rounds):  # s² at the current answer, which depends on it (mildly)
        sw = np.sqrt(c / s2)

        def fun(q: Array, sw: Array = sw) -> tuple[Array, Array]:
            res, J = geo_jac(q)
            rp, Jp = _soft_iron_prior(q, sig_diag, sig_off)
            return np.concatenate([sw * res, rp]), np.vstack([J * sw[:, None], Jp])

        p = levenberg_marquardt(fun, p, max_iter)
        s2_new = s2_at(p)
        done = abs(s2_new / s2 - 1.0) < 0.01
        s2 = s2_new
        if done:
            break
    sw = np.sqrt(c / s2)
    res, J = geo_jac(p)
    _, Jp = _soft_iron_prior(p, sig_diag, sig_off)
    info = (J * sw[:, None]).T @ (J * sw[:, None]) + Jp.T @ Jp
    try:
        cov: Array = np.asarray(np.linalg.inv(info), float)
    except np.linalg.LinAlgError:
        cov = np.full((9, 9), np.inf)
    rms = float(np.sqrt(np.average(res**2, weights=wt)))
    return NormFit(p[:3].copy(), sym_from_vec(p[3:]), cov, rms, keep, 9)


def soft_iron_prior_sigma(M: Array, Q: Array, rng: np.random.Generator, sig_diag: float = SOFT_DIAG_SIGMA,
                          sig_off: float = SOFT_OFF_SIGMA, n: int = 256) -> dict[str, Array]:
    """1σ of the decomposed scale (absolute, raw⁻¹ unit) and ξ (rad) of ``Q · M'`` that the soft-iron prior
    alone allows around the symmetric M (3, 3): Monte Carlo over M' = M + m̄ E, E drawn from the prior
    (m̄ = tr(M)/3), Q (3, 3) the alignment. The reference for "not determined by the data" (posterior σ
    above half of it)."""
    from .decomp import decompose_many

    mbar = float(np.trace(M) / 3.0)
    E = np.zeros((n, 3, 3))
    d = rng.normal(0.0, sig_diag, (n, 3))
    off = rng.normal(0.0, sig_off, (n, 3))
    E[:, [0, 1, 2], [0, 1, 2]] = d
    for k, (i, j) in enumerate(((0, 1), (0, 2), (1, 2))):
        E[:, i, j] = E[:, j, i] = off[:, k]
    par, ok = decompose_many(Q[None] @ (M[None] + mbar * E))
    sd = par[ok].std(axis=0)
    return {"scale": sd[0:3], "xi": sd[6:9]}
