"""Compiled (numba) kernels of the prediction: the attitude of every sigma point through a block of IMU
samples, the sensor model (eqs. 1–6) and the attitude errors — the loop forms of the numpy reference in
:mod:`onlinecal.ukf.propagate` and :mod:`onlinecal.ukf.layout` (backend switch and compilation cache:
:mod:`onlinecal.ukf.kernels`). Results equal the reference within 1e-9 relative (tests/test_speed_kernels.py).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .kernels import _njit

Array = NDArray[np.float64]


# ------------------------------------------------------------------------------------------------
# scalar building blocks (inlined by numba)
@_njit
def _rodrigues_into(x: float, y: float, z: float, out: Array) -> None:
    """exp([θ]_x) of θ = (x, y, z) into out (3, 3): (1 − c a²) I + s [θ]_x + c θθᵀ, s = sin a / a,
    c = (1 − cos a)/a² (the reference :func:`onlinecal.ukf.layout.rodrigues_cm`; series below 0.05 rad,
    where its truncation error, a⁶/5040, is below 4e-12)."""
    a2 = x * x + y * y + z * z
    if a2 < 0.0025:
        s = 1.0 - a2 / 6.0 + a2 * a2 / 120.0
        c = 0.5 - a2 / 24.0 + a2 * a2 / 720.0
    else:
        a = math.sqrt(a2)
        s = math.sin(a) / a
        h = math.sin(0.5 * a) / (0.5 * a)
        c = 0.5 * h * h
    d = 1.0 - c * a2
    out[0, 0] = d + c * x * x
    out[1, 1] = d + c * y * y
    out[2, 2] = d + c * z * z
    cxy, cxz, cyz = c * x * y, c * x * z, c * y * z
    out[0, 1] = cxy - s * z
    out[1, 0] = cxy + s * z
    out[0, 2] = cxz + s * y
    out[2, 0] = cxz - s * y
    out[1, 2] = cyz - s * x
    out[2, 1] = cyz + s * x


@_njit
def _mul33(A: Array, B: Array, out: Array) -> None:
    """out = A @ B for 3×3 (out must not alias A or B)."""
    for i in range(3):
        a0, a1, a2 = A[i, 0], A[i, 1], A[i, 2]
        for j in range(3):
            out[i, j] = a0 * B[0, j] + a1 * B[1, j] + a2 * B[2, j]


# ------------------------------------------------------------------------------------------------
# block propagation (reference: onlinecal.ukf.propagate.propagate_block_numpy)
@_njit
def _calibrated_rates(w: Array, o_g: Array, M_g: Array, b_extra: Array, has_extra: bool, si: int,
                      om: Array) -> None:
    """ω_k = M_g,s (w_k − o_g,s − b_s,k) (eq. 1 on the gyro) of dynamic sigma point ``si`` into om (L + 1, 3)
    rad/s, for the raw rates w (L + 1, 3) (b_extra (S_d, L + 1, 3) read only when has_extra)."""
    for k in range(w.shape[0]):
        u0 = w[k, 0] - o_g[si, 0]
        u1 = w[k, 1] - o_g[si, 1]
        u2 = w[k, 2] - o_g[si, 2]
        if has_extra:
            u0 -= b_extra[si, k, 0]
            u1 -= b_extra[si, k, 1]
            u2 -= b_extra[si, k, 2]
        for i in range(3):
            om[k, i] = M_g[si, i, 0] * u0 + M_g[si, i, 1] * u1 + M_g[si, i, 2] * u2


@_njit
def _integrate(om: Array, dt: Array, c_mag: Array, has_mag: bool, P: Array, Ps: Array, Pm: Array) -> None:
    """The running product P_k = P_k−1 exp([Δθ_k]_x) (P_0 = I) over the L samples, Δθ_k = ½(ω_k−1 + ω_k)Δt_k
    + Δt_k²/12 ω_k−1 × ω_k (trapezoid + two-sample coning), for the calibrated rates om (L + 1, 3) and the
    interval lengths dt (L,) s. Into P (3, 3) = P_L, Ps = Σ_k P_k and Pm = Σ_k c_k P_k (k = 0..L, c_mag
    (L + 1,) read only when has_mag; zero otherwise)."""
    dR = np.empty((3, 3))
    Pn = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            P[i, j] = 1.0 if i == j else 0.0
            Ps[i, j] = 0.0
            Pm[i, j] = (c_mag[0] if i == j else 0.0) if has_mag else 0.0
    for k in range(dt.shape[0]):
        h = dt[k]
        hc = h * h / 12.0
        a0, a1, a2 = om[k, 0], om[k, 1], om[k, 2]
        b0, b1, b2 = om[k + 1, 0], om[k + 1, 1], om[k + 1, 2]
        tx = 0.5 * h * (a0 + b0) + hc * (a1 * b2 - a2 * b1)
        ty = 0.5 * h * (a1 + b1) + hc * (a2 * b0 - a0 * b2)
        tz = 0.5 * h * (a2 + b2) + hc * (a0 * b1 - a1 * b0)
        _rodrigues_into(tx, ty, tz, dR)
        _mul33(P, dR, Pn)
        ck = c_mag[k + 1] if has_mag else 0.0
        for i in range(3):
            for j in range(3):
                P[i, j] = Pn[i, j]
                Ps[i, j] += Pn[i, j]
                Pm[i, j] += ck * Pn[i, j]


@_njit
def _share_mean(X: Array, dyn: NDArray[np.intp], f_body: Array, h_body: Array, Q0: Array, has_mag: bool,
                dip_col: int) -> None:
    """The sigma points outside dyn: the mean's attitude history (f_body of row dyn[0], the mean's
    Σ_k c_k R(t_k) in Q0 (3, 3)) with their own dip (column ``dip_col`` of X)."""
    S = X.shape[0]
    is_dyn = np.zeros(S, np.bool_)
    for si in range(dyn.shape[0]):
        is_dyn[dyn[si]] = True
    s0 = dyn[0]
    for s in range(S):
        if is_dyn[s]:
            continue
        for j in range(3):
            f_body[s, j] = f_body[s0, j]
        if has_mag:
            cd, sd = math.cos(X[s, dip_col]), math.sin(X[s, dip_col])
            for j in range(3):
                h_body[s, j] = cd * Q0[1, j] - sd * Q0[2, j]


@_njit
def _finish_point(X: Array, s: int, si: int, R_nom: Array, P: Array, Ps: Array, Pm: Array, inv_L: float,
                  has_mag: bool, dip_col: int, R_end: Array, f_body: Array, h_body: Array, Q0: Array,
                  R0: Array, Rd: Array, Q: Array) -> None:
    """Dynamic sigma point ``s`` (the ``si``-th) from its block products P, Ps, Pm (3, 3): R0 = R_nom exp([δθ_s]_x),
    its end attitude R0 P into R_end[si], the block's mean gravity direction (row 3 of R0 Ps / L) into f_body[s],
    with the magnetometer its field direction through R0 Pm into h_body[s] (and, for the mean, R0 Pm into Q0).
    R0, Rd, Q (3, 3) are work arrays."""
    _rodrigues_into(X[s, 0], X[s, 1], X[s, 2], Rd)
    _mul33(R_nom, Rd, R0)
    _mul33(R0, P, Rd)
    for i in range(3):
        for j in range(3):
            R_end[si, i, j] = Rd[i, j]
    for j in range(3):
        f_body[s, j] = (R0[2, 0] * Ps[0, j] + R0[2, 1] * Ps[1, j] + R0[2, 2] * Ps[2, j]) * inv_L
    if has_mag:
        _mul33(R0, Pm, Q)
        cd, sd = math.cos(X[s, dip_col]), math.sin(X[s, dip_col])
        for j in range(3):
            h_body[s, j] = cd * Q[1, j] - sd * Q[2, j]
        if si == 0:
            for i in range(3):
                for j in range(3):
                    Q0[i, j] = Q[i, j]


@_njit
def _propagate_points_kernel(X: Array, R_nom: Array, w: Array, dt: Array, c_mag: Array, has_mag: bool,
                             dyn: NDArray[np.intp], o_g: Array, M_g: Array, b_extra: Array, has_extra: bool,
                             dip_col: int) -> tuple[Array, Array, Array]:
    """:func:`propagate_kernel` one dynamic sigma point at a time (its form before issue 15's sixth round),
    kept as the reference of its order of operations: tests/test_speed_fastpath.py compares the two bit for
    bit (compiled on first use: production never calls it). Per dynamic sigma point s (the mean first):
    rates (:func:`_calibrated_rates`), running product P_k (:func:`_integrate`), R0 = R_nom exp([δθ_s]_x).
    Arguments and returns as :func:`propagate_kernel`.
    """
    S, Sd, L = X.shape[0], dyn.shape[0], dt.shape[0]
    R_end = np.empty((Sd, 3, 3))
    f_body = np.empty((S, 3))
    h_body = np.zeros((S, 3))
    Q0 = np.zeros((3, 3))  # the mean's Σ_k c_k R(t_k), for the points outside dyn
    om = np.empty((L + 1, 3))
    P, Ps, Pm = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    R0, Rd, Q = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    inv_L = 1.0 / L
    for si in range(Sd):
        s = dyn[si]
        _calibrated_rates(w, o_g, M_g, b_extra, has_extra, si, om)
        _integrate(om, dt, c_mag, has_mag, P, Ps, Pm)
        _finish_point(X, s, si, R_nom, P, Ps, Pm, inv_L, has_mag, dip_col, R_end, f_body, h_body, Q0, R0, Rd, Q)
    _share_mean(X, dyn, f_body, h_body, Q0, has_mag, dip_col)
    return R_end, f_body, h_body


@_njit
def propagate_kernel(X: Array, R_nom: Array, w: Array, dt: Array, c_mag: Array, has_mag: bool,
                     dyn: NDArray[np.intp], o_g: Array, M_g: Array, b_extra: Array, has_extra: bool,
                     dip_col: int) -> tuple[Array, Array, Array]:
    """Attitude of every dynamic sigma point through one block of L IMU samples, with the block means the
    measurements need; the loop form of :func:`onlinecal.ukf.propagate.propagate_block_numpy`. Per dynamic
    sigma point s (the mean first): rates ω_k = M_g,s (w_k − o_g,s − b_s,k) (eq. 1 on the gyro), the running
    product P_k = P_k−1 exp([Δθ_k]_x) (P_0 = I) over the samples, Δθ_k = ½(ω_k−1 + ω_k)Δt_k + Δt_k²/12
    ω_k−1 × ω_k (trapezoid + two-sample coning), its sums Σ_k P_k and Σ_k c_k P_k, and R0 = R_nom exp([δθ_s]_x).

    Sample-major (issue 15): all dynamic points advance one sample at a time (lanes), the Rodrigues series
    (:func:`_rodrigues_into`, below 0.05 rad) for all of them, then its closed form for the few whose step
    is larger — the same operations on every element as one point at a time
    (:func:`_propagate_points_kernel`), so the same bits, without a branch and a call per point and sample.

    X (S, n); R_nom (3, 3); w (L + 1, 3) rad/s; dt (L,) s; c_mag (L + 1,) mag interpolation weights (read
    only when has_mag); dyn (S_d,) with dyn[0] = 0; o_g (S_d, 3), M_g (S_d, 3, 3); b_extra (S_d, L + 1, 3)
    (read only when has_extra); dip_col the dip's column of X.
    Returns R_end (S_d, 3, 3) = R0 P_L; f_body (S, 3) = mean_k (R0 P_k)ᵀ e_z; h_body (S, 3) =
    (Σ_k c_k R0 P_k)ᵀ h_world(dip) with P_0 = I (zeros when not has_mag). Points outside dyn share the
    mean's attitude history (row 0).
    """
    S, Sd, L = X.shape[0], dyn.shape[0], dt.shape[0]
    Mt = np.empty((9, Sd))
    ot = np.empty((3, Sd))
    for si in range(Sd):
        for i in range(3):
            ot[i, si] = o_g[si, i]
            for j in range(3):
                Mt[3 * i + j, si] = M_g[si, i, j]
    om0 = np.empty((3, Sd))
    om1 = np.empty((3, Sd))
    P = np.empty((9, Sd))
    Ps = np.zeros((9, Sd))
    Pm = np.empty((9, Sd))
    th = np.empty((6, Sd))  # per lane: the step θ (3), |θ|², s = sin a / a, c = (1 − cos a)/a²
    c0 = c_mag[0] if has_mag else 0.0
    for e in range(9):
        diag = e == 0 or e == 4 or e == 8
        for si in range(Sd):
            P[e, si] = 1.0 if diag else 0.0
            Pm[e, si] = (c0 if diag else 0.0) if has_mag else 0.0
    # ω_k = M_g (w_k − o_g) (:func:`_calibrated_rates`), sample 0; then per sample the next and the step
    w0, w1, w2 = w[0, 0], w[0, 1], w[0, 2]
    for si in range(Sd):
        u0 = w0 - ot[0, si]
        u1 = w1 - ot[1, si]
        u2 = w2 - ot[2, si]
        if has_extra:
            u0 -= b_extra[si, 0, 0]
            u1 -= b_extra[si, 0, 1]
            u2 -= b_extra[si, 0, 2]
        for i in range(3):
            om1[i, si] = Mt[3 * i, si] * u0 + Mt[3 * i + 1, si] * u1 + Mt[3 * i + 2, si] * u2
    for k in range(L):
        om0, om1 = om1, om0
        w0, w1, w2 = w[k + 1, 0], w[k + 1, 1], w[k + 1, 2]
        h = dt[k]
        hc = h * h / 12.0
        hh = 0.5 * h
        ck = c_mag[k + 1] if has_mag else 0.0
        for si in range(Sd):
            u0 = w0 - ot[0, si]
            u1 = w1 - ot[1, si]
            u2 = w2 - ot[2, si]
            if has_extra:
                u0 -= b_extra[si, k + 1, 0]
                u1 -= b_extra[si, k + 1, 1]
                u2 -= b_extra[si, k + 1, 2]
            b0 = Mt[0, si] * u0 + Mt[1, si] * u1 + Mt[2, si] * u2
            b1 = Mt[3, si] * u0 + Mt[4, si] * u1 + Mt[5, si] * u2
            b2 = Mt[6, si] * u0 + Mt[7, si] * u1 + Mt[8, si] * u2
            om1[0, si] = b0
            om1[1, si] = b1
            om1[2, si] = b2
            a0, a1, a2 = om0[0, si], om0[1, si], om0[2, si]
            tx = hh * (a0 + b0) + hc * (a1 * b2 - a2 * b1)
            ty = hh * (a1 + b1) + hc * (a2 * b0 - a0 * b2)
            tz = hh * (a2 + b2) + hc * (a0 * b1 - a1 * b0)
            q2 = tx * tx + ty * ty + tz * tz
            th[0, si] = tx
            th[1, si] = ty
            th[2, si] = tz
            th[3, si] = q2
            th[4, si] = 1.0 - q2 / 6.0 + q2 * q2 / 120.0
            th[5, si] = 0.5 - q2 / 24.0 + q2 * q2 / 720.0
        for si in range(Sd):
            q2 = th[3, si]
            if not q2 < 0.0025:
                a = math.sqrt(q2)
                th[4, si] = math.sin(a) / a
                hs = math.sin(0.5 * a) / (0.5 * a)
                th[5, si] = 0.5 * hs * hs
        for si in range(Sd):
            x, y, z, q2, s, c = th[0, si], th[1, si], th[2, si], th[3, si], th[4, si], th[5, si]
            d = 1.0 - c * q2
            r00 = d + c * x * x
            r11 = d + c * y * y
            r22 = d + c * z * z
            cxy, cxz, cyz = c * x * y, c * x * z, c * y * z
            r01 = cxy - s * z
            r10 = cxy + s * z
            r02 = cxz + s * y
            r20 = cxz - s * y
            r12 = cyz - s * x
            r21 = cyz + s * x
            for i in range(3):
                p0, p1, p2 = P[3 * i, si], P[3 * i + 1, si], P[3 * i + 2, si]
                n0 = p0 * r00 + p1 * r10 + p2 * r20
                n1 = p0 * r01 + p1 * r11 + p2 * r21
                n2 = p0 * r02 + p1 * r12 + p2 * r22
                P[3 * i, si] = n0
                P[3 * i + 1, si] = n1
                P[3 * i + 2, si] = n2
                Ps[3 * i, si] += n0
                Ps[3 * i + 1, si] += n1
                Ps[3 * i + 2, si] += n2
                if has_mag:  # (Σ c_k P_k only where the block's mag is used: nothing reads it otherwise)
                    Pm[3 * i, si] += ck * n0
                    Pm[3 * i + 1, si] += ck * n1
                    Pm[3 * i + 2, si] += ck * n2
    R_end = np.empty((Sd, 3, 3))
    f_body = np.empty((S, 3))
    h_body = np.zeros((S, 3))
    Q0 = np.zeros((3, 3))
    R0, Rd, Q = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    Pk, Psk, Pmk = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    inv_L = 1.0 / L
    for si in range(Sd):
        s = dyn[si]
        for i in range(3):
            for j in range(3):
                Pk[i, j] = P[3 * i + j, si]
                Psk[i, j] = Ps[3 * i + j, si]
                Pmk[i, j] = Pm[3 * i + j, si]
        _finish_point(X, s, si, R_nom, Pk, Psk, Pmk, inv_L, has_mag, dip_col, R_end, f_body, h_body, Q0, R0, Rd, Q)
    _share_mean(X, dyn, f_body, h_body, Q0, has_mag, dip_col)
    return R_end, f_body, h_body


_EMPTY1 = np.zeros(1)
_EMPTY3 = np.zeros((1, 1, 3))


def _f64(a: Array) -> Array:
    return np.ascontiguousarray(a, dtype=np.float64)


def propagate_numba(X: Array, R_nom: Array, w: Array, dt: Array, c_mag: Array | None, dyn: NDArray[Any],
                    o_g: Array, M_g: Array, b_extra: Array | None,
                    dip_col: int) -> tuple[Array, Array, Array | None]:
    """:func:`propagate_kernel` with numpy-friendly arguments (None for no mag / no extra bias): (R_end
    (S_d, 3, 3), f_body (S, 3), h_body (S, 3) or None)."""
    has_mag = c_mag is not None
    has_extra = b_extra is not None
    R_end, f_body, h_body = propagate_kernel(
        _f64(X), _f64(R_nom), _f64(w), _f64(dt), _f64(c_mag) if c_mag is not None else _EMPTY1, has_mag,
        np.ascontiguousarray(dyn, dtype=np.intp), _f64(o_g), _f64(M_g),
        _f64(b_extra) if b_extra is not None else _EMPTY3, has_extra, dip_col)
    return R_end, f_body, (h_body if has_mag else None)


# ------------------------------------------------------------------------------------------------
# sensor model (reference: onlinecal.ukf.layout.model_pair, eqs. 1–6)
@_njit
def model_pair_kernel(p: Array) -> tuple[Array, Array, Array]:
    """(o, M, M⁻¹) of the sensor model for N parameter rows p (N, 12) = (o, s, alpha, xi): o (N, 3),
    M = S·T_R(alpha)·T_N(xi) and M⁻¹ = A·T_Rᵀ·S⁻¹ (N, 3, 3); T_R = Rz Ry Rx (eqs. 3–4), A the axes
    matrix of eq. 6 and T_N = A⁻¹ written out (lower triangular)."""
    N = p.shape[0]
    o = np.empty((N, 3))
    M = np.empty((N, 3, 3))
    Mi = np.empty((N, 3, 3))
    TR = np.empty((3, 3))
    A = np.zeros((3, 3))
    Ai = np.zeros((3, 3))
    for n in range(N):
        for i in range(3):
            o[n, i] = p[n, i]
        cf, sf = math.cos(p[n, 6]), math.sin(p[n, 6])
        ct, st = math.cos(p[n, 7]), math.sin(p[n, 7])
        cp, sp = math.cos(p[n, 8]), math.sin(p[n, 8])
        TR[0, 0] = cp * ct
        TR[0, 1] = cp * st * sf - sp * cf
        TR[0, 2] = cp * st * cf + sp * sf
        TR[1, 0] = sp * ct
        TR[1, 1] = sp * st * sf + cp * cf
        TR[1, 2] = sp * st * cf - cp * sf
        TR[2, 0] = -st
        TR[2, 1] = ct * sf
        TR[2, 2] = ct * cf
        sx, sy, sz = math.sin(p[n, 9]), math.sin(p[n, 10]), math.sin(p[n, 11])
        cx, cy, cz = math.cos(p[n, 9]), math.cos(p[n, 10]), math.cos(p[n, 11])
        b, c, d, e, f = sz, cz, -sy, sx * cy, cx * cy
        A[0, 0] = 1.0
        A[1, 0], A[1, 1] = b, c
        A[2, 0], A[2, 1], A[2, 2] = d, e, f
        Ai[0, 0] = 1.0
        Ai[1, 0], Ai[1, 1] = -b / c, 1.0 / c
        Ai[2, 0], Ai[2, 1], Ai[2, 2] = (b * e - c * d) / (c * f), -e / (c * f), 1.0 / f
        for i in range(3):
            si = p[n, 3 + i]
            for j in range(3):
                M[n, i, j] = si * (TR[i, 0] * Ai[0, j] + TR[i, 1] * Ai[1, j] + TR[i, 2] * Ai[2, j])
                Mi[n, i, j] = (A[i, 0] * TR[j, 0] + A[i, 1] * TR[j, 1] + A[i, 2] * TR[j, 2]) / p[n, 3 + j]
    return o, M, Mi


# ------------------------------------------------------------------------------------------------
# rotations (reference: onlinecal.ukf.layout.rot_log)
@_njit
def rot_log_rel_kernel(R: Array) -> Array:
    """Rotation vectors of R[0]ᵀ R[s] for R (S, 3, 3) → (S, 3) (angles below π; a/sin a by its series
    below 1e-8): the attitude error of every propagated sigma point relative to the mean's (row 0)."""
    S = R.shape[0]
    out = np.empty((S, 3))
    D = np.empty((3, 3))
    for s in range(S):
        for i in range(3):
            for j in range(3):
                D[i, j] = R[0, 0, i] * R[s, 0, j] + R[0, 1, i] * R[s, 1, j] + R[0, 2, i] * R[s, 2, j]
        v0 = 0.5 * (D[2, 1] - D[1, 2])
        v1 = 0.5 * (D[0, 2] - D[2, 0])
        v2 = 0.5 * (D[1, 0] - D[0, 1])
        sn = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        cs = 0.5 * (D[0, 0] + D[1, 1] + D[2, 2] - 1.0)
        a = math.atan2(sn, cs)
        k = a / sn if sn > 1e-8 else 1.0 + a * a / 6.0
        out[s, 0], out[s, 1], out[s, 2] = v0 * k, v1 * k, v2 * k
    return out
