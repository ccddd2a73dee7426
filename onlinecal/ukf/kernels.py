"""Compiled (numba) kernels of the UKF's per-block work, and the switch between them and the numpy reference.

The numpy functions of :mod:`onlinecal.ukf.propagate` are the reference: every kernel here computes the same
quantity in the same equations, written as loops over sigma points and samples so that one call does a whole
block without going back to the interpreter (the numpy path spends most of a block in dispatch overhead of
dozens of small array operations). Results agree with the reference to rounding (tests/test_speed_kernels.py:
≤ 1e-9 relative); the order of the floating-point operations differs (a sequential product instead of the
reference's log₂-depth scan), so they are not bit-identical.

Backend: ``ONLINECAL_KERNELS=numba|numpy`` in the environment when this module is first imported, or
:func:`set_backend` at run time; ``numba`` is the default where numba imports, else ``numpy``.

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
    numba = None
    HAVE_NUMBA = False


def _njit(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``numba.njit(cache=True)`` (no parallelism: one core), or the plain function without numba."""
    if not HAVE_NUMBA:
        return fn
    return numba.njit(cache=True, nogil=True)(fn)  # type: ignore[no-any-return]


_backend = os.environ.get("ONLINECAL_KERNELS", "numba" if HAVE_NUMBA else "numpy").strip().lower()
if _backend not in BACKENDS:
    raise ValueError(f"ONLINECAL_KERNELS={_backend!r}: expected one of {', '.join(BACKENDS)}")
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


def propagate_numba(X: Array, R_nom: Array, w: Array, dt: Array, c_mag: Array | None, dyn: NDArray[np.intp],
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
