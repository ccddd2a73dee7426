"""Closed-form, vectorised split of many correction matrices into (scale, alpha, xi) (eqs. 2–6).

The σ of a fit is found by drawing matrices within the fit's covariance and decomposing each draw;
:func:`onlinecal.model.decompose` solves the 9 equations iteratively (≈ 1 ms, and up to a second for a
badly conditioned draw), which made the σ step the slowest part of a batch (70 s of 96 s on a
simulated flight). The decomposition has a closed form:

``M = S · T_R · A⁻¹`` with A the lower-triangular matrix whose rows are the unit sensing axes (eq. 6),
so ``M⁻¹ S = A T_Rᵀ`` and ``(M⁻¹ S)(M⁻¹ S)ᵀ = A Aᵀ`` has a unit diagonal: with ``B = M⁻¹``,
``(B ∘ B) s² = 1`` — linear in the squared scales. Then ``B S = A T_Rᵀ`` is an LQ factorisation
(QR of its transpose) with A's diagonal positive; alpha from T_R (Z-Y-X), xi from A's rows.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..model import decompose

Array = NDArray[np.float64]


def decompose_many(M: Array) -> tuple[Array, Array]:
    """(scale, alpha, xi) of each matrix of M (N, 3, 3), exact forms of eqs. 2–6.

    Returns (params (N, 9) = scale, alpha, xi in rad; ok (N,) bool). Where most matrices have a negative
    determinant (an inverted axis), those go through :func:`onlinecal.model.decompose` one by one (at most
    256); a minority of such draws, and rows with no real solution (a draw so far off that the squared
    scales come out negative), are marked not ok.
    """
    M = np.asarray(M, float).reshape(-1, 3, 3)
    n = M.shape[0]
    out = np.full((n, 9), np.nan)
    ok = np.zeros(n, bool)
    det = np.linalg.det(M)
    pos = np.isfinite(det) & (det > 0)
    if pos.any():
        Mp = M[pos]
        B = np.linalg.inv(Mp)
        s2 = np.linalg.solve(B * B, np.ones((Mp.shape[0], 3, 1)))[..., 0]
        good = np.all(s2 > 0, axis=1)
        s = np.sqrt(np.where(good[:, None], s2, 1.0))
        X = B * s[:, None, :]  # B S: column j scaled by s_j
        Q, Rt = np.linalg.qr(np.swapaxes(X, 1, 2))  # Xᵀ = Q Rt  →  X = Rtᵀ Qᵀ = A T_Rᵀ
        d = np.sign(np.diagonal(Rt, axis1=1, axis2=2))
        d[d == 0] = 1.0
        A = np.swapaxes(Rt, 1, 2) * d[:, None, :]  # X = (Rtᵀ D)(D Qᵀ): columns flipped, diag(A) > 0
        TR = Q * d[:, None, :]  # T_R = Q with the same columns flipped
        ay = -np.arcsin(np.clip(TR[:, 2, 0], -1.0, 1.0))
        ax = np.arctan2(TR[:, 2, 1], TR[:, 2, 2])
        az = np.arctan2(TR[:, 1, 0], TR[:, 0, 0])
        xz = np.arctan2(A[:, 1, 0], A[:, 1, 1])
        xy = -np.arcsin(np.clip(A[:, 2, 0], -1.0, 1.0))
        xx = np.arctan2(A[:, 2, 1], A[:, 2, 2])
        p = np.column_stack([s, ax, ay, az, xx, xy, xz])
        good &= np.all(np.isfinite(p), axis=1) & (np.linalg.det(TR) > 0)
        idx = np.flatnonzero(pos)
        out[idx[good]] = p[good]
        ok[idx[good]] = True
    neg = np.flatnonzero(np.isfinite(det) & (det < 0))
    if neg.size <= n // 2:
        # A few draws across det = 0 (a σ as large as a scale): not an inverted axis, and the iterative
        # split of each (~1 ms, up to a second near singular) would cost more than the rest together.
        neg = neg[:0]
    for i in neg[:256]:
        try:
            out[i] = np.concatenate(decompose(M[i]))
            ok[i] = True
        except ValueError:
            pass
    return out, ok
