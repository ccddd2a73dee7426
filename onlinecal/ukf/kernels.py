"""Compiled (numba) kernels of the UKF's per-block work, and the switch between them and the numpy reference.

The numpy functions of :mod:`onlinecal.ukf.propagate` are the reference: every kernel here computes the same
quantity in the same equations, written as loops over sigma points and samples so that one call does a whole
block without going back to the interpreter (the numpy path spends most of a block in dispatch overhead of
dozens of small array operations). Results agree with the reference to rounding (tests/test_speed_kernels.py:
≤ 1e-9 relative); the order of the floating-point operations differs (a sequential product instead of the
reference's log₂-depth scan), so they are not bit-identical.

Backend: ``ONLINECAL_KERNELS=numba|numpy`` in the environment when this module is first imported, or
:func:`set_backend` at run time; ``numba`` is the default where numba imports, else ``numpy`` (another
value: a RuntimeWarning, and the default).

Compilation is cached on disk (``cache=True``). Numba writes its cache next to this file when the package
directory is writable and otherwise in a per-user directory; where neither is writable (a read-only
install, a sandbox without a home), ``NUMBA_CACHE_DIR`` is set here to ``$XDG_CACHE_HOME/onlinecal/numba``
or ``~/.cache/onlinecal/numba`` and, failing those, to a directory under the system's temporary directory,
before numba is imported. A user's own ``NUMBA_CACHE_DIR`` is left alone.
"""

from __future__ import annotations

import contextlib
import math
import os
import tempfile
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

BACKENDS = ("numba", "numpy")


def _writable(d: Path) -> bool:
    """Whether files can be created in d (made if missing)."""
    try:
        d.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=d):
            pass
        return True
    except OSError:
        return False


def _cache_dir() -> str | None:
    """The directory numba's cache should use, or None where numba's own default (next to this file)
    is writable. Only consulted when the user has not set ``NUMBA_CACHE_DIR``."""
    here = Path(__file__).resolve().parent / "__pycache__"
    if _writable(here):
        return None
    xdg = os.environ.get("XDG_CACHE_HOME")
    cands = [Path(xdg)] if xdg else []
    with contextlib.suppress(RuntimeError):
        cands.append(Path.home() / ".cache")
    cands.append(Path(tempfile.gettempdir()) / f"onlinecal-{os.getuid() if hasattr(os, 'getuid') else 'user'}")
    for c in cands:
        d = c / "onlinecal" / "numba"
        if _writable(d):
            return str(d)
    return None


if "NUMBA_CACHE_DIR" not in os.environ:
    _d = _cache_dir()
    if _d is not None:
        os.environ["NUMBA_CACHE_DIR"] = _d

try:
    import numba

    if "numba.core.config" in __import__("sys").modules:  # imported before us: re-read NUMBA_CACHE_DIR
        numba.core.config.reload_config()
    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - numba is a dependency; the numpy path still works without it
    numba = None  # type: ignore[assignment]
    HAVE_NUMBA = False


def _njit(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``numba.njit(cache=True)`` (no parallelism: one core), or the plain function without numba.

    The GIL is kept (no ``nogil``): the kernels are short (tens of µs) and in ``onlinecal run`` a reader
    thread decodes the link; releasing and re-taking the GIL around every kernel call cost more CPU there
    than it saved (bench_live: 7.2 % of a core with nogil, 6.3 % without; the numpy path 6.9–7.3 %)."""
    if not HAVE_NUMBA:
        return fn
    return numba.njit(cache=True)(fn)


_default = "numba" if HAVE_NUMBA else "numpy"
_backend = os.environ.get("ONLINECAL_KERNELS", _default).strip().lower()
if _backend not in BACKENDS:
    # an environment variable is not worth a crash: say so in one line and run on the default
    warnings.warn(f"ONLINECAL_KERNELS={_backend!r} is not one of {', '.join(BACKENDS)}: using {_default}",
                  RuntimeWarning, stacklevel=1)
    _backend = _default
if _backend == "numba" and not HAVE_NUMBA:
    _backend = "numpy"


def backend() -> str:
    """The backend in use: "numba" (compiled kernels) or "numpy" (the reference)."""
    return _backend


def set_backend(name: str) -> str:
    """Switch the backend ("numba" or "numpy"); returns the previous one. "numba" without numba installed
    raises RuntimeError."""
    global _backend
    if name not in BACKENDS:
        raise ValueError(f"kernel backend {name!r}: expected one of {', '.join(BACKENDS)}")
    if name == "numba" and not HAVE_NUMBA:
        raise RuntimeError("kernel backend 'numba' requested but numba is not installed")
    old, _backend = _backend, name
    return old


@contextlib.contextmanager
def use_backend(name: str) -> Iterator[None]:
    """``with use_backend("numpy"): ...`` runs the block on that backend and restores the previous one."""
    old = set_backend(name)
    try:
        yield
    finally:
        set_backend(old)


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
def propagate_kernel(X: Array, R_nom: Array, w: Array, dt: Array, c_mag: Array, has_mag: bool,
                     dyn: NDArray[np.intp], o_g: Array, M_g: Array, b_extra: Array, has_extra: bool,
                     dip_col: int) -> tuple[Array, Array, Array]:
    """Attitude of every dynamic sigma point through one block of L IMU samples, with the block means the
    measurements need; the loop form of :func:`onlinecal.ukf.propagate.propagate_block_numpy`.

    Per dynamic sigma point s (the mean first) and sample k = 1..L:
    ω_k = M_g,s (w_k − o_g,s − b_s,k) (eq. 1 on the gyro), Δθ_k = ½(ω_k−1 + ω_k)Δt_k + Δt_k²/12 ω_k−1 × ω_k
    (trapezoid + two-sample coning), P_k = P_k−1 exp([Δθ_k]_x), R0 = R_nom exp([δθ_s]_x).

    X (S, n); R_nom (3, 3); w (L + 1, 3) rad/s; dt (L,) s; c_mag (L + 1,) mag interpolation weights (read
    only when has_mag); dyn (S_d,) with dyn[0] = 0; o_g (S_d, 3), M_g (S_d, 3, 3); b_extra (S_d, L + 1, 3)
    (read only when has_extra); dip_col the dip's column of X.
    Returns R_end (S_d, 3, 3) = R0 P_L; f_body (S, 3) = mean_k (R0 P_k)ᵀ e_z; h_body (S, 3) =
    (Σ_k c_k R0 P_k)ᵀ h_world(dip) with P_0 = I (zeros when not has_mag). Points outside dyn share the
    mean's attitude history (row 0).
    """
    S = X.shape[0]
    Sd = dyn.shape[0]
    L = dt.shape[0]
    R_end = np.empty((Sd, 3, 3))
    f_body = np.empty((S, 3))
    h_body = np.zeros((S, 3))
    Q0 = np.zeros((3, 3))  # the mean's Σ_k c_k R(t_k), for the points outside dyn
    om = np.empty((L + 1, 3))
    dR = np.empty((3, 3))
    P = np.empty((3, 3))
    Pn = np.empty((3, 3))
    Ps = np.empty((3, 3))  # Σ_k P_k
    Pm = np.empty((3, 3))  # Σ_k c_k P_k (k = 0: identity)
    R0 = np.empty((3, 3))
    Rd = np.empty((3, 3))
    Q = np.empty((3, 3))
    inv_L = 1.0 / L
    for si in range(Sd):
        s = dyn[si]
        # calibrated rates at the L + 1 samples
        for k in range(L + 1):
            u0 = w[k, 0] - o_g[si, 0]
            u1 = w[k, 1] - o_g[si, 1]
            u2 = w[k, 2] - o_g[si, 2]
            if has_extra:
                u0 -= b_extra[si, k, 0]
                u1 -= b_extra[si, k, 1]
                u2 -= b_extra[si, k, 2]
            for i in range(3):
                om[k, i] = M_g[si, i, 0] * u0 + M_g[si, i, 1] * u1 + M_g[si, i, 2] * u2
        for i in range(3):
            for j in range(3):
                P[i, j] = 1.0 if i == j else 0.0
                Ps[i, j] = 0.0
                Pm[i, j] = (c_mag[0] if i == j else 0.0) if has_mag else 0.0
        for k in range(L):
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
    # the points outside dyn: the mean's attitude history, their own dip
    is_dyn = np.zeros(S, np.bool_)
    for si in range(Sd):
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
    return R_end, f_body, h_body


_EMPTY1 = np.zeros(1)
_EMPTY3 = np.zeros((1, 1, 3))


def propagate_numba(X: Array, R_nom: Array, w: Array, dt: Array, c_mag: Array | None, dyn: NDArray[Any],
                    o_g: Array, M_g: Array, b_extra: Array | None,
                    dip_col: int) -> tuple[Array, Array, Array | None]:
    """:func:`propagate_kernel` with numpy-friendly arguments (None for no mag / no extra bias): (R_end
    (S_d, 3, 3), f_body (S, 3), h_body (S, 3) or None)."""
    has_mag = c_mag is not None
    has_extra = b_extra is not None
    R_end, f_body, h_body = propagate_kernel(
        np.ascontiguousarray(X, dtype=np.float64), np.ascontiguousarray(R_nom, dtype=np.float64),
        np.ascontiguousarray(w, dtype=np.float64), np.ascontiguousarray(dt, dtype=np.float64),
        np.ascontiguousarray(c_mag, dtype=np.float64) if has_mag else _EMPTY1, has_mag,
        np.ascontiguousarray(dyn, dtype=np.intp), np.ascontiguousarray(o_g, dtype=np.float64),
        np.ascontiguousarray(M_g, dtype=np.float64),
        np.ascontiguousarray(b_extra, dtype=np.float64) if has_extra else _EMPTY3, has_extra, dip_col)
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


# ------------------------------------------------------------------------------------------------
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
        for i in range(j + 1, n):
            acc = A[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            L[i, j] = acc * inv
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
def unscented_kernel(X: Array, Wm: Array, Wc: Array, q: Array) -> tuple[Array, Array, Array]:
    """Predicted mean x_pred = Σ Wm_s X_s (n,), deviations Y = X − x_pred (S, n) and covariance
    P_pred = Σ Wc_s Y_sᵀ Y_s + diag(q) (n, n) (the unscented transform; q the process noise variances).
    The covariance is one BLAS product (YᵀW)Y, as in the reference."""
    S, n = X.shape
    x_pred = np.zeros(n)
    for s in range(S):
        w = Wm[s]
        for j in range(n):
            x_pred[j] += w * X[s, j]
    Y = np.empty((S, n))
    YW = np.empty((n, S))
    for s in range(S):
        for j in range(n):
            y = X[s, j] - x_pred[j]
            Y[s, j] = y
            YW[j, s] = y * Wc[s]
    P = np.dot(YW, Y)
    for i in range(n):
        P[i, i] += q[i]
    return x_pred, Y, P


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
    Pxz = np.zeros((n, m))
    for s in range(S):
        for i in range(m):
            zi = Z[s, i] - z_pred[i]
            for j in range(i, m):
                S_zz[i, j] += zi * Zc[s, j]
        for i in range(n):
            yi = Y[s, i]
            for j in range(m):
                Pxz[i, j] += yi * Zc[s, j]
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
        for j in range(i, n):
            acc = P_pred[i, j]
            for a in range(m):
                acc += -Kt[a, i] * Pxz[j, a] - Pxz[i, a] * Kt[a, j] + KS[i, a] * Kt[a, j]
            P[i, j] = acc
            P[j, i] = acc
    return x, P, True


@_njit
def update_kernel(Y: Array, x_pred: Array, P_pred: Array, z: Array, Z: Array, r_diag: Array, Wm: Array,
                  Wc: Array, gated: NDArray[np.bool_], droppable: NDArray[np.bool_], gates: Array,
                  consider: NDArray[np.bool_], damp: float,
                  want_post: bool) -> tuple[Array, Array, Array, NDArray[np.int64], Array, Array, bool]:
    """The whole joint UKF update of one block on stacked 3-vector measurements (reference:
    :func:`onlinecal.ukf.unscented.update`), in one call.

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
    n = x_pred.shape[0]
    m = z.shape[0]
    nb = m // 3
    z_pred, S_zz, hph, Pxz, nu, nis = innovation_kernel(Y, Z, z, Wm, Wc, r_diag, gated)
    status = np.full(nb, -1, np.int64)
    post_z = np.zeros((nb, 3))
    post_P = np.zeros((nb, 3, 3))
    keep = np.ones(m, np.bool_)
    n_keep = m
    Sk = np.empty((3, 3))
    A = np.empty((3, 3))
    for k in range(nb):
        if not gated[k]:
            continue
        o = 3 * k
        if droppable[k] and nis[k] > gates[k]:
            status[k] = 2
            keep[o : o + 3] = False
            n_keep -= 3
            continue
        status[k] = 0
        if nis[k] > gates[k]:
            status[k] = 1
            for i in range(3):
                S_zz[o + i, o + i] += r_diag[o + i] * (nis[k] / gates[k] - 1.0)
        if want_post:
            for i in range(3):
                for j in range(3):
                    Sk[i, j] = S_zz[o + i, o + j]
                    A[i, j] = Sk[i, j] - (r_diag[o + i] if i == j else 0.0)
            AS_t, ok = _solve_small(Sk, A)  # S⁻¹ A = (A S⁻¹)ᵀ (S, A symmetric)
            if not ok:
                return x_pred.copy(), P_pred.copy(), nis, status, post_z, post_P, False
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
    if n_keep == 0:
        return x_pred.copy(), P_pred.copy(), nis, status, post_z, post_P, True
    idx = np.empty(n_keep, np.int64)
    c = 0
    for i in range(m):
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
            d = Sz[a, a] - h
            extra = damp * h - d
            if extra > 0.0:
                Sg[a, a] += extra
    Pk = np.empty((n, n_keep))
    for i in range(n):
        for a in range(n_keep):
            Pk[i, a] = Pxz[i, idx[a]]
    nuk = np.empty(n_keep)
    for a in range(n_keep):
        nuk[a] = nu[idx[a]]
    x, P, ok = gain_update_kernel(x_pred, P_pred, Pk, Sz, Sg, nuk, consider)
    return x, P, nis, status, post_z, post_P, ok
