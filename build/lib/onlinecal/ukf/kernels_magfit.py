"""The magnetometer cold fit's three acceptance figures in one compiled pass (issue 15): a screen in front of
:func:`.attitude_init.fit_mag_cold`.

A flight whose field directions stay in a band (they never span 3-D) keeps the cold-start buffer full
(2000 samples) and has the fit tried once a second for its whole log, refused every time — on the
benchmark flight by its direction cover, 0.2–0.4 of the bound. The numpy fit (lstsq, inverse, the unit
directions, two eigenvalue problems) costs ~300 µs a try at 2000 samples; :func:`mag_fit_figures` forms the
same figures in one loop over the samples (~15 µs): the sphere's normal equations A'A, A'b with A = [2 xc, 1],
b = |xc|² (xc the samples less their mean, as the fit), the residual, the centre's LS σ from (A'A)⁻¹, the
unit directions about the fitted centre, and the smallest eigenvalues of their mean square and of their
covariance. The fit is skipped only where one figure is beyond its bound by more than ``SCREEN_MARGIN``
(1 %: the screen's figures agree with the fit's to ~1e-10 relative, ``tests/test_speed_magfit.py``); anywhere
near a bound, and wherever the screen cannot judge (singular or ill-conditioned normal matrix, a non-positive
radius, NaN), the fit runs as before. So the decisions are the fit's, and every accepted fit is computed by
:func:`.attitude_init.fit_mag_cold` itself: its result is unchanged bit for bit. The numpy backend (the
reference) does not use the screen.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from .kernels import _njit

Array = NDArray[np.float64]

SCREEN_MARGIN = 0.01  # relative: a figure must fail its bound by more than this for the fit to be skipped


@_njit
def _solve4(A: Array, B: Array) -> tuple[bool, Array]:
    """A (4, 4) X = B (4, k) by Gaussian elimination with partial pivoting; (False, _) where a pivot is below
    1e-13 of the largest diagonal entry (the screen then does not judge)."""
    M = A.copy()
    X = B.copy()
    n = 4
    big = 0.0
    for i in range(n):
        big = max(big, abs(M[i, i]))
    for col in range(n):
        p = col
        for r in range(col + 1, n):
            if abs(M[r, col]) > abs(M[p, col]):
                p = r
        if not abs(M[p, col]) > 1e-13 * big:
            return False, X
        if p != col:
            for j in range(n):
                M[col, j], M[p, j] = M[p, j], M[col, j]
            for j in range(X.shape[1]):
                X[col, j], X[p, j] = X[p, j], X[col, j]
        for r in range(col + 1, n):
            f = M[r, col] / M[col, col]
            for j in range(col, n):
                M[r, j] -= f * M[col, j]
            for j in range(X.shape[1]):
                X[r, j] -= f * X[col, j]
    for col in range(n - 1, -1, -1):
        for j in range(X.shape[1]):
            s = X[col, j]
            for k in range(col + 1, n):
                s -= M[col, k] * X[k, j]
            X[col, j] = s / M[col, col]
    return True, X


@_njit
def mag_fit_figures(x: Array) -> tuple[bool, float, float, float]:
    """The acceptance figures of :func:`.attitude_init.fit_mag_cold` for raw samples x (N, 3), N ≥ 5:
    (judged, σ of the centre / radius, spread, cover) — spread the smallest eigenvalue of the unit
    directions' mean square uᵀu/N, cover that of their covariance (N − 1 normalised, ``np.cov``).
    ``judged`` False where the normal matrix is singular or the radius² not positive (the figures are then
    meaningless)."""
    N = x.shape[0]
    m0 = np.zeros(3)
    for i in range(N):
        for k in range(3):
            m0[k] += x[i, k]
    for k in range(3):
        m0[k] /= N
    AtA = np.zeros((4, 4))
    Atb = np.zeros((4, 1))
    for i in range(N):
        a0, a1, a2 = 2.0 * (x[i, 0] - m0[0]), 2.0 * (x[i, 1] - m0[1]), 2.0 * (x[i, 2] - m0[2])
        b = 0.25 * (a0 * a0 + a1 * a1 + a2 * a2)
        AtA[0, 0] += a0 * a0
        AtA[0, 1] += a0 * a1
        AtA[0, 2] += a0 * a2
        AtA[0, 3] += a0
        AtA[1, 1] += a1 * a1
        AtA[1, 2] += a1 * a2
        AtA[1, 3] += a1
        AtA[2, 2] += a2 * a2
        AtA[2, 3] += a2
        Atb[0, 0] += a0 * b
        Atb[1, 0] += a1 * b
        Atb[2, 0] += a2 * b
        Atb[3, 0] += b
    AtA[3, 3] = N
    for i in range(4):
        for j in range(i):
            AtA[i, j] = AtA[j, i]
    rhs = np.zeros((4, 5))
    for i in range(4):
        rhs[i, 0] = Atb[i, 0]
        rhs[i, 1 + i] = 1.0
    ok, sol = _solve4(AtA, rhs)
    if not ok:
        return False, math.nan, math.nan, math.nan
    oc0, oc1, oc2, d = sol[0, 0], sol[1, 0], sol[2, 0], sol[3, 0]
    r2 = d + oc0 * oc0 + oc1 * oc1 + oc2 * oc2
    if not r2 > 0:
        return False, math.nan, math.nan, math.nan
    r = math.sqrt(r2)
    o0, o1, o2 = m0[0] + oc0, m0[1] + oc1, m0[2] + oc2
    ee = 0.0
    S = np.zeros((3, 3))
    us = np.zeros(3)
    for i in range(N):
        c0, c1, c2 = x[i, 0] - m0[0], x[i, 1] - m0[1], x[i, 2] - m0[2]
        e = (c0 * c0 + c1 * c1 + c2 * c2) - (2.0 * c0 * oc0 + 2.0 * c1 * oc1 + 2.0 * c2 * oc2 + d)
        ee += e * e
        v0, v1, v2 = x[i, 0] - o0, x[i, 1] - o1, x[i, 2] - o2
        nv = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        if not nv > 0:  # a sample on the centre: the fit's directions are not defined there
            return False, math.nan, math.nan, math.nan
        u0, u1, u2 = v0 / nv, v1 / nv, v2 / nv
        us[0] += u0
        us[1] += u1
        us[2] += u2
        S[0, 0] += u0 * u0
        S[0, 1] += u0 * u1
        S[0, 2] += u0 * u2
        S[1, 1] += u1 * u1
        S[1, 2] += u1 * u2
        S[2, 2] += u2 * u2
    s2 = ee / max(1, N - 4)
    var_o = max(sol[0, 1], max(sol[1, 2], sol[2, 3]))
    sig_o = math.sqrt(s2 * var_o) if var_o > 0 else math.nan
    for i in range(3):
        for j in range(i):
            S[i, j] = S[j, i]
    C = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            C[i, j] = (S[i, j] - us[i] * us[j] / N) / (N - 1)
            S[i, j] = S[i, j] / N
    spread = np.linalg.eigvalsh(S)[0]
    cover = np.linalg.eigvalsh(C)[0]
    return True, sig_o / r, spread, cover


def fit_refused(x: Array, max_centre_sigma: float, min_spread: float, min_cover: float) -> bool:
    """True where the screen finds the cold fit certain to be refused: one figure of
    :func:`mag_fit_figures` beyond its bound by more than ``SCREEN_MARGIN`` (the fit's own tests: σ of the
    centre < max_centre_sigma × radius, spread ≥ min_spread, cover ≥ min_cover). False where the fit should
    run (it decides)."""
    if x.shape[0] < 5:
        return False
    judged, sig_r, spread, cover = mag_fit_figures(np.ascontiguousarray(x, dtype=np.float64))
    if not judged:
        return False
    k = 1.0 + SCREEN_MARGIN
    return bool(sig_r > max_centre_sigma * k or spread * k < min_spread or cover * k < min_cover)
