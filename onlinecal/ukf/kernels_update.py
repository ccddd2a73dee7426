"""Compiled (numba) kernels of the unscented transform and the update: sigma points (Cholesky), predicted
moments, innovation statistics, gating and the Schmidt/Joseph gain update of one block — the loop forms of
:mod:`onlinecal.ukf.unscented` (the numpy reference; backend switch and compilation cache:
:mod:`onlinecal.ukf.kernels`). Results equal the reference within 1e-9 relative (tests/test_speed_kernels.py).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from .kernels import _njit

Array = NDArray[np.float64]


# the unscented transform and the update (reference: OnlineCalibrator._sigma_points, _step, _update)
@_njit
def cholesky_kernel(A: Array) -> tuple[Array, bool]:
    """Lower Cholesky factor L (n, n) of a symmetric A = L Lᵀ, and whether A was positive definite (a
    non-positive or non-finite pivot: False, L incomplete) — LAPACK potrf's condition."""
    n = A.shape[0]
    L = np.zeros((n, n))
    for j in range(n):
        d = A[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        if not d > 0.0:  # also catches NaN
            return L, False
        ljj = math.sqrt(d)
        L[j, j] = ljj
        inv = 1.0 / ljj
        # eight rows at once (issue 15; four before its eighth round): independent subtraction chains, each in
        # its own order (k ascending, as one row alone), so the same bits; one chain alone waits on each
        # subtraction
        i = j + 1
        while i + 7 < n:
            a0, a1, a2, a3 = A[i, j], A[i + 1, j], A[i + 2, j], A[i + 3, j]
            a4, a5, a6, a7 = A[i + 4, j], A[i + 5, j], A[i + 6, j], A[i + 7, j]
            for k in range(j):
                ljk = L[j, k]
                a0 -= L[i, k] * ljk
                a1 -= L[i + 1, k] * ljk
                a2 -= L[i + 2, k] * ljk
                a3 -= L[i + 3, k] * ljk
                a4 -= L[i + 4, k] * ljk
                a5 -= L[i + 5, k] * ljk
                a6 -= L[i + 6, k] * ljk
                a7 -= L[i + 7, k] * ljk
            L[i, j], L[i + 1, j], L[i + 2, j], L[i + 3, j] = a0 * inv, a1 * inv, a2 * inv, a3 * inv
            L[i + 4, j], L[i + 5, j], L[i + 6, j], L[i + 7, j] = a4 * inv, a5 * inv, a6 * inv, a7 * inv
            i += 8
        while i + 3 < n:
            a0, a1, a2, a3 = A[i, j], A[i + 1, j], A[i + 2, j], A[i + 3, j]
            for k in range(j):
                ljk = L[j, k]
                a0 -= L[i, k] * ljk
                a1 -= L[i + 1, k] * ljk
                a2 -= L[i + 2, k] * ljk
                a3 -= L[i + 3, k] * ljk
            L[i, j], L[i + 1, j], L[i + 2, j], L[i + 3, j] = a0 * inv, a1 * inv, a2 * inv, a3 * inv
            i += 4
        while i < n:
            acc = A[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            L[i, j] = acc * inv
            i += 1
    return L, True


@_njit
def sigma_points_kernel(x: Array, P: Array, scale: float, perm: NDArray[np.intp]) -> tuple[Array, bool]:
    """Scaled sigma points X (2n + 1, n): x, x + D_r, x − D_r, the rows D_r of the Cholesky factor of
    scale·P taken in ``perm`` order (U = chol(scale·P[perm][:, perm])ᵀ, D[:, perm] = U), and whether scale·P
    was positive definite. Wan & van der Merwe (2000), scale = λ + n."""
    n = x.shape[0]
    A = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            A[i, j] = scale * P[perm[i], perm[j]]
    L, ok = cholesky_kernel(A)
    X = np.empty((2 * n + 1, n))
    for j in range(n):
        X[0, j] = x[j]
    for r in range(n):
        for c in range(n):
            pc = perm[c]
            u = L[c, r]  # U[r, c] = Lᵀ
            X[1 + r, pc] = x[pc] + u
            X[1 + n + r, pc] = x[pc] - u
    return X, ok


@_njit
def _mean_deviation(X: Array, Wm: Array) -> tuple[Array, Array]:
    """The sigma points' weighted mean x = Σ Wm_s X_s (n,), summed over s in ascending order, and their
    deviations Y = X − x (S, n): the first half of both unscented transforms below."""
    S, n = X.shape
    x_pred = np.zeros(n)
    for s in range(S):
        w = Wm[s]
        for j in range(n):
            x_pred[j] += w * X[s, j]
    Y = np.empty((S, n))
    for s in range(S):
        for j in range(n):
            Y[s, j] = X[s, j] - x_pred[j]
    return x_pred, Y


@_njit
def unscented_kernel(X: Array, Wm: Array, Wc: Array, q: Array) -> tuple[Array, Array, Array]:
    """Predicted mean x_pred = Σ Wm_s X_s (n,), deviations Y = X − x_pred (S, n) and covariance
    P_pred = Σ Wc_s Y_sᵀ Y_s + diag(q) (n, n) (the unscented transform; q the process noise variances).
    The covariance is one BLAS product (YᵀW)Y, as in the reference."""
    S, n = X.shape
    x_pred, Y = _mean_deviation(X, Wm)
    YW = np.empty((n, S))
    for s in range(S):
        for j in range(n):
            YW[j, s] = Y[s, j] * Wc[s]
    P = np.dot(YW, Y)
    for i in range(n):
        P[i, i] += q[i]
    return x_pred, Y, P


@_njit
def unscented_motion_kernel(X: Array, Wm: Array, Wc: Array, q: Array, P: Array) -> tuple[Array, Array, Array]:
    """:func:`unscented_kernel` of a motion block's propagated sigma points X (S, n), drawn from (x, P) with P
    (n, n): x_pred (n,) and Y (S, n) as there (the same loops, the same bits), P_pred (n, n) computed only where
    the prediction moved the points — the attitude's rows and columns 0–2, Σ_s Wc_s Y_s,a Y_s,j; the rest is
    P + diag(q).

    Issue 15, eighth round: the prediction changes only the attitude columns of X (the calibration terms, the
    dip and the hold offsets are constants of the motion model), where every other column is x ± the Cholesky
    factor's rows, whose weighted outer products sum to P (Σ_r 2 Wc_r u_r u_rᵀ = P, Wc_r = 1 / (2(λ + n)), the
    mean's term zero): the reference's full product recomputes P there to rounding (a difference of
    ~1e-16 · σ_i σ_j), at 40 × 40 × 81 multiply-adds of the block's 416 kflop; this forms 3 × 40 × 81."""
    S, n = X.shape
    x_pred, Y = _mean_deviation(X, Wm)
    P_pred = np.empty((n, n))
    for i in range(3, n):
        for j in range(3, n):
            P_pred[i, j] = P[i, j]
    yw = np.empty((3, S))
    for s in range(S):
        for a in range(3):
            yw[a, s] = Y[s, a] * Wc[s]
    # each P_pred[a, j] summed over s in ascending order from 0.0, one sigma point at a time (issue 15, ninth
    # round: the inner loop along a row of Y, its additions independent; the same bits as four columns at once
    # with s inner; the kernel 18.3 → 17.0 µs on the benchmark flight's blocks, interleaved, best of 30)
    acc = np.zeros((3, n))
    for s in range(S):
        for a in range(3):
            v = yw[a, s]
            for j in range(n):
                acc[a, j] += v * Y[s, j]
    for a in range(3):
        for j in range(n):
            P_pred[a, j] = acc[a, j]
    for a in range(3):  # symmetric: the attitude's columns from its rows (its 3 × 3 block from the upper triangle)
        for j in range(a + 1, n):
            P_pred[j, a] = P_pred[a, j]
    for i in range(n):
        P_pred[i, i] += q[i]
    return x_pred, Y, P_pred


@_njit
def innovation_kernel(Y: Array, Z: Array, z: Array, Wm: Array, Wc: Array, r_diag: Array,
                      gated: NDArray[np.bool_]) -> tuple[Array, Array, Array, Array, Array, Array]:
    """Statistics of the stacked measurement for the UKF update: z_pred = Σ Wm_s Z_s (m,),
    S_zz = Σ Wc_s Zc_sᵀ Zc_s + diag(r) (m, m), hph = diag of its first term (m,), Pxz = Σ Wc_s Y_sᵀ Zc_s
    (n, m), ν = z − z_pred (m,), and the NIS νᵀ S⁻¹ ν of every consecutive 3-block k with gated[k] (m/3,)
    (+inf for the others, and for all if a gated block of S is singular). Y (S, n) sigma deviations from
    the predicted mean, Z (S, m) predicted readings."""
    S, m = Z.shape
    n = Y.shape[1]
    z_pred = np.zeros(m)
    for s in range(S):
        for j in range(m):
            z_pred[j] += Wm[s] * Z[s, j]
    Zc = np.empty((S, m))
    for s in range(S):
        for j in range(m):
            Zc[s, j] = (Z[s, j] - z_pred[j]) * Wc[s]
    S_zz = np.zeros((m, m))
    Pxz = np.empty((n, m))
    for s in range(S):
        for i in range(m):
            zi = Z[s, i] - z_pred[i]
            for j in range(i, m):
                S_zz[i, j] += zi * Zc[s, j]
    # Pxz[i, j] = Σ_s Y[s, i] Zc[s, j], s ascending from 0, accumulated in place one sigma point at a time into
    # its transpose (m, n): the inner loop runs along a row of Y, its additions independent of each other (issue
    # 15, ninth round: the same bits as four rows i at once with s inner, which loaded Y down its columns; the
    # kernel 15.3 → 11.9 µs on the benchmark flight's accel-only blocks, interleaved, best of 30)
    PxzT = np.zeros((m, n))
    for s in range(S):
        for j in range(m):
            zc = Zc[s, j]
            for i in range(n):
                PxzT[j, i] += Y[s, i] * zc
    for i in range(n):
        for j in range(m):
            Pxz[i, j] = PxzT[j, i]
    hph = np.empty(m)
    for i in range(m):
        hph[i] = S_zz[i, i]
        S_zz[i, i] += r_diag[i]
        for j in range(i + 1, m):
            S_zz[j, i] = S_zz[i, j]
    nu = z - z_pred
    nb = m // 3
    nis = np.full(nb, np.inf)
    B = np.empty((3, 3))
    for k in range(nb):
        if not gated[k]:
            continue
        for i in range(3):
            for j in range(3):
                B[i, j] = S_zz[3 * k + i, 3 * k + j]
        sol, ok = _solve_small(B, nu[3 * k : 3 * k + 3].copy().reshape(3, 1))
        if not ok:
            nis[:] = np.inf
            break
        nis[k] = nu[3 * k] * sol[0, 0] + nu[3 * k + 1] * sol[1, 0] + nu[3 * k + 2] * sol[2, 0]
    return z_pred, S_zz, hph, Pxz, nu, nis


@_njit
def _solve_small(A: Array, B: Array) -> tuple[Array, bool]:
    """A⁻¹ B (m, k) by Gaussian elimination with partial pivoting (numpy.linalg.solve's LU), and whether A
    was non-singular (an exactly zero pivot: False)."""
    m = A.shape[0]
    k = B.shape[1]
    U = A.copy()
    X = B.copy()
    for c in range(m):
        piv = c
        best = abs(U[c, c])
        for r in range(c + 1, m):
            if abs(U[r, c]) > best:
                best, piv = abs(U[r, c]), r
        if best == 0.0 or not np.isfinite(best):
            return X, False
        if piv != c:
            for j in range(m):
                U[c, j], U[piv, j] = U[piv, j], U[c, j]
            for j in range(k):
                X[c, j], X[piv, j] = X[piv, j], X[c, j]
        inv = 1.0 / U[c, c]
        for r in range(c + 1, m):
            f = U[r, c] * inv
            if f != 0.0:
                for j in range(c, m):
                    U[r, j] -= f * U[c, j]
                for j in range(k):
                    X[r, j] -= f * X[c, j]
    for c in range(m - 1, -1, -1):
        inv = 1.0 / U[c, c]
        for j in range(k):
            acc = X[c, j]
            for i in range(c + 1, m):
                acc -= U[c, i] * X[i, j]
            X[c, j] = acc * inv
    return X, True


@_njit
def gain_update_kernel(x_pred: Array, P_pred: Array, Pxz: Array, S_zz: Array, S_gain: Array, nu: Array,
                       consider: NDArray[np.bool_]) -> tuple[Array, Array, bool]:
    """The update with gain K = Pxz S_gain⁻¹ (n, m), its rows of the consider states zeroed (Schmidt):
    x = x_pred + K ν, P = P_pred − K Pxzᵀ − Pxz Kᵀ + K S_zz Kᵀ (the Joseph-like form, the error covariance
    for any gain), and whether S_gain was non-singular."""
    n, m = Pxz.shape
    Kt, ok = _solve_small(S_gain, Pxz.T.copy())  # S_gain Kᵀ = Pxzᵀ (S_gain symmetric)
    if not ok:
        return x_pred.copy(), P_pred.copy(), False
    for i in range(n):
        if consider[i]:
            for j in range(m):
                Kt[j, i] = 0.0
    x = x_pred.copy()
    for i in range(n):
        acc = 0.0
        for j in range(m):
            acc += Kt[j, i] * nu[j]
        x[i] += acc
    # K S_zz (n, m)
    KS = np.zeros((n, m))
    for i in range(n):
        for a in range(m):
            kia = Kt[a, i]
            if kia != 0.0:
                for b in range(m):
                    KS[i, b] += kia * S_zz[a, b]
    P = np.empty((n, n))
    for i in range(n):
        # four entries (i, j) at once (issue 15): independent chains, each summed over a in its own order (the
        # same bits as one at a time)
        j = i
        while j + 3 < n:
            c0, c1, c2, c3 = P_pred[i, j], P_pred[i, j + 1], P_pred[i, j + 2], P_pred[i, j + 3]
            for a in range(m):
                kai, pia, ksa = Kt[a, i], Pxz[i, a], KS[i, a]
                c0 += -kai * Pxz[j, a] - pia * Kt[a, j] + ksa * Kt[a, j]
                c1 += -kai * Pxz[j + 1, a] - pia * Kt[a, j + 1] + ksa * Kt[a, j + 1]
                c2 += -kai * Pxz[j + 2, a] - pia * Kt[a, j + 2] + ksa * Kt[a, j + 2]
                c3 += -kai * Pxz[j + 3, a] - pia * Kt[a, j + 3] + ksa * Kt[a, j + 3]
            P[i, j], P[i, j + 1], P[i, j + 2], P[i, j + 3] = c0, c1, c2, c3
            P[j, i], P[j + 1, i], P[j + 2, i], P[j + 3, i] = c0, c1, c2, c3
            j += 4
        while j < n:
            acc = P_pred[i, j]
            for a in range(m):
                acc += -Kt[a, i] * Pxz[j, a] - Pxz[i, a] * Kt[a, j] + KS[i, a] * Kt[a, j]
            P[i, j] = acc
            P[j, i] = acc
            j += 1
    return x, P, True


@_njit
def _gate(S_zz: Array, r_diag: Array, z_pred: Array, nu: Array, nis: Array, gated: NDArray[np.bool_],
          droppable: NDArray[np.bool_], gates: Array, want_post: bool, keep: NDArray[np.bool_],
          status: NDArray[np.int64], post_z: Array, post_P: Array) -> bool:
    """Gate every 3-block k of the stacked measurement (see :func:`update_kernel`): drop (status 2, keep
    False) a droppable one above its gate, inflate the R of another above it to the gate's size in S_zz
    (status 1, soft gate), else status 0; with want_post its posterior measurement prediction into
    post_z[k] (3,), post_P[k] (3, 3). False if a 3×3 block of S was singular."""
    Sk = np.empty((3, 3))
    A = np.empty((3, 3))
    for k in range(nis.shape[0]):
        if not gated[k]:
            continue
        o = 3 * k
        if droppable[k] and nis[k] > gates[k]:
            status[k] = 2
            keep[o : o + 3] = False
            continue
        status[k] = 0
        if nis[k] > gates[k]:
            status[k] = 1
            for i in range(3):
                S_zz[o + i, o + i] += r_diag[o + i] * (nis[k] / gates[k] - 1.0)
        if not want_post:
            continue
        for i in range(3):
            for j in range(3):
                Sk[i, j] = S_zz[o + i, o + j]
                A[i, j] = Sk[i, j] - (r_diag[o + i] if i == j else 0.0)
        AS_t, ok = _solve_small(Sk, A)  # S⁻¹ A = (A S⁻¹)ᵀ (S, A symmetric)
        if not ok:
            return False
        for i in range(3):
            acc = z_pred[o + i]
            for j in range(3):
                acc += AS_t[j, i] * nu[o + j]
            post_z[k, i] = acc
            for j in range(3):
                acc = A[i, j]
                for q in range(3):
                    acc -= AS_t[q, i] * A[q, j]
                post_P[k, i, j] = acc
    return True


@_njit
def _kept(S_zz: Array, hph: Array, Pxz: Array, nu: Array, keep: NDArray[np.bool_],
          damp: float) -> tuple[Array, Array, Array, Array]:
    """The kept components of the measurement: S_zz (k, k), the gain's S (k, k) (damped: each diagonal
    entry at least its HPHᵀ part plus damp·HPHᵀ, Zanetti's partial update), Pxz (n, k) and ν (k,)."""
    n_keep = 0
    for i in range(keep.shape[0]):
        n_keep += keep[i]
    idx = np.empty(n_keep, np.int64)
    c = 0
    for i in range(keep.shape[0]):
        if keep[i]:
            idx[c] = i
            c += 1
    Sz = np.empty((n_keep, n_keep))
    Sg = np.empty((n_keep, n_keep))
    for a in range(n_keep):
        for b in range(n_keep):
            Sz[a, b] = S_zz[idx[a], idx[b]]
            Sg[a, b] = Sz[a, b]
        if damp > 0.0:
            h = hph[idx[a]]
            extra = damp * h - (Sz[a, a] - h)
            if extra > 0.0:
                Sg[a, a] += extra
    Pk = np.empty((Pxz.shape[0], n_keep))
    for i in range(Pxz.shape[0]):
        for a in range(n_keep):
            Pk[i, a] = Pxz[i, idx[a]]
    nuk = np.empty(n_keep)
    for a in range(n_keep):
        nuk[a] = nu[idx[a]]
    return Sz, Sg, Pk, nuk


@_njit
def update_kernel(Y: Array, x_pred: Array, P_pred: Array, z: Array, Z: Array, r_diag: Array, Wm: Array,
                  Wc: Array, gated: NDArray[np.bool_], droppable: NDArray[np.bool_], gates: Array,
                  consider: NDArray[np.bool_], damp: float,
                  want_post: bool) -> tuple[Array, Array, Array, NDArray[np.int64], Array, Array, bool]:
    """The whole joint UKF update of one block on stacked 3-vector measurements (reference:
    :func:`onlinecal.ukf.unscented.update`), in one call: :func:`innovation_kernel`, :func:`_gate`,
    :func:`_kept`, :func:`gain_update_kernel`.

    Y (S, n), x_pred (n,), P_pred (n, n): the predicted sigma deviations, mean, covariance; z (m,) the
    readings, Z (S, m) their prediction per sigma point, r_diag (m,) the diagonal of R (m = 3 × blocks).
    Per 3-block k: gated[k] whether it is chi-square gated, droppable[k] whether a NIS above gates[k] drops
    it (an accel in motion) instead of inflating its R to the gate's size (soft gate). consider (n,) the
    Schmidt states (zero gain); damp the partial-update share (gain as if R ≥ damp·HPHᵀ; gating and P use
    the model's S). want_post: per gated block the measurement the posterior predicts, z_pred + A S⁻¹ ν,
    and its covariance A − A S⁻¹ A with A = S − R.

    Returns x (n,), P (n, n), NIS (blocks,) (+inf where not gated), status (blocks,) (−1 not gated, 0 ok,
    1 soft-gated, 2 dropped), post_z (blocks, 3), post_P (blocks, 3, 3), and False if a matrix to be
    solved was singular (x, P then the prediction).
    """
    nb = z.shape[0] // 3
    z_pred, S_zz, hph, Pxz, nu, nis = innovation_kernel(Y, Z, z, Wm, Wc, r_diag, gated)
    status = np.full(nb, -1, np.int64)
    post_z = np.zeros((nb, 3))
    post_P = np.zeros((nb, 3, 3))
    keep = np.ones(z.shape[0], np.bool_)
    if not _gate(S_zz, r_diag, z_pred, nu, nis, gated, droppable, gates, want_post, keep, status, post_z,
                 post_P):
        return x_pred.copy(), P_pred.copy(), nis, status, post_z, post_P, False
    n_keep = 0
    for i in range(keep.shape[0]):
        n_keep += keep[i]
    if n_keep == 0:
        return x_pred.copy(), P_pred.copy(), nis, status, post_z, post_P, True
    Sz, Sg, Pk, nuk = _kept(S_zz, hph, Pxz, nu, keep, damp)
    x, P, ok = gain_update_kernel(x_pred, P_pred, Pk, Sz, Sg, nuk, consider)
    return x, P, nis, status, post_z, post_P, ok
