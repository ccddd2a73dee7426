"""SO(3) on the filter's hot path: the few rotation formulas the UKF evaluates per block, vectorised.

Everything outside the hot path uses scipy's :class:`scipy.spatial.transform.Rotation`; these are kept
because they run on stacks of sigma points × samples (component-major, elementwise) where a generic
object would cost more than the filter. Each is tested against scipy (``tests/test_ukf_geometry.py``).

* :func:`rodrigues`, :func:`rodrigues_cm`, :func:`rodrigues1`, :func:`rodrigues_n` — the exponential
  map exp([θ]ₓ) (Rodrigues' formula) for different array layouts;
* :func:`rot_log` — its inverse, the log map, for angles below π;
* :func:`prefix_products`, :func:`prefix_products_cm` — running products of rotation increments;
* :func:`triad` — the attitude from two vector pairs (TRIAD).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def skew(v: Array) -> Array:
    """[v]_x for v (S, 3) → (S, 3, 3)."""
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -v[..., 2], v[..., 1]
    K[..., 1, 0], K[..., 1, 2] = v[..., 2], -v[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -v[..., 1], v[..., 0]
    return K


def rodrigues(theta: Array) -> Array:
    """exp([θ]_x) for θ (..., 3) → (..., 3, 3), exact for any angle (sinc forms, no branch at 0)."""
    a = np.sqrt(np.einsum("...i,...i->...", theta, theta))
    s = np.sinc(a / np.pi)[..., None, None]  # sin(a)/a
    c = (0.5 * np.sinc(a / (2 * np.pi)) ** 2)[..., None, None]  # (1 − cos a)/a²
    K = skew(theta)
    out: Array = np.eye(3) + s * K + c * (K @ K)
    return out


def rot_log(R: Array) -> Array:
    """Rotation vector of R (..., 3, 3) → (..., 3), for angles below π (the inverse of rodrigues)."""
    v = 0.5 * np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                        R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    s = np.sqrt(np.einsum("...i,...i->...", v, v))
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    a = np.arctan2(s, c)
    # a / sin(a), with its series near 0 so that tiny rotations are exact as well
    k = np.where(s > 1e-8, a / np.where(s > 1e-8, s, 1.0), 1.0 + a * a / 6.0)
    out: Array = v * k[..., None]
    return out


def rodrigues_cm(th: Array) -> Array:
    """exp([θ]_x) in component-major layout: θ (3, ...) → R (3, 3, ...).

    R = (1 − c a²) I + s [θ]_x + c θθᵀ with a = |θ|, s = sin a / a, c = (1 − cos a)/a². Component-major
    arrays keep every operation elementwise over all sigma points and samples at once (fast for stacks of
    3×3 matrices, where numpy's batched matmul is slow). Series for s and c when every angle is small.
    """
    a2 = th[0] * th[0] + th[1] * th[1] + th[2] * th[2]
    if float(a2.max(initial=0.0)) < 0.05**2:
        s = 1.0 - a2 / 6.0 + a2 * a2 / 120.0
        c = 0.5 - a2 / 24.0 + a2 * a2 / 720.0
    else:
        a = np.sqrt(a2)
        s = np.sinc(a / np.pi)
        c = 0.5 * np.sinc(a / (2 * np.pi)) ** 2
    d = 1.0 - c * a2
    x, y, z = th[0] * s, th[1] * s, th[2] * s
    cx, cy = c * th[0], c * th[1]
    cxy, cxz, cyz = cx * th[1], cx * th[2], cy * th[2]
    R = np.empty((3, 3) + th.shape[1:])
    R[0, 0], R[1, 1], R[2, 2] = d + cx * th[0], d + cy * th[1], d + c * th[2] * th[2]
    R[0, 1], R[1, 0] = cxy - z, cxy + z
    R[0, 2], R[2, 0] = cxz + y, cxz - y
    R[1, 2], R[2, 1] = cyz - x, cyz + x
    return R


def rodrigues_n(theta: Array) -> Array:
    """exp([θ]_x) (S, 3, 3) for rotation vectors θ (S, 3) (:func:`rodrigues_cm`, transposed back)."""
    out: Array = rodrigues_cm(np.ascontiguousarray(theta.T)).transpose(2, 0, 1)
    return out


def rodrigues1(v: Array) -> Array:
    """exp([v]_x) (3, 3) of one rotation vector v (3,) (Rodrigues' formula, series below 1e-4 rad)."""
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    a2 = x * x + y * y + z * z
    if a2 < 1e-8:
        s, c = 1.0 - a2 / 6.0, 0.5 - a2 / 24.0
    else:
        a = math.sqrt(a2)
        s, c = math.sin(a) / a, (1.0 - math.cos(a)) / a2
    return np.array([[1.0 - c * (y * y + z * z), c * x * y - s * z, c * x * z + s * y],
                     [c * x * y + s * z, 1.0 - c * (x * x + z * z), c * y * z - s * x],
                     [c * x * z - s * y, c * y * z + s * x, 1.0 - c * (x * x + y * y)]])


def prefix_products_cm(dR: Array) -> Array:
    """Running products P_k = dR_1 · dR_2 ⋯ dR_k along the last axis, component-major: (3, 3, S, L).

    Hillis–Steele scan: ⌈log₂ L⌉ vectorised levels (each one einsum over all sigma points and samples),
    so the attitude of every sigma point at every IMU sample of a block comes without a loop over either.
    """
    P = dR.copy()
    L = P.shape[-1]
    shift = 1
    while shift < L:
        # earlier factors on the left; the right-hand side is evaluated before the assignment
        P[..., shift:] = np.einsum("iksl,kjsl->ijsl", P[..., : L - shift], P[..., shift:])
        shift *= 2
    return P


def prefix_products(dR: Array) -> Array:
    """Running products P_k = dR_1 · dR_2 ⋯ dR_k along axis 1 of dR (S, L, 3, 3) → (S, L, 3, 3).

    Hillis–Steele scan: ⌈log₂ L⌉ batched matmuls instead of L sequential ones (the reference for
    :func:`prefix_products_cm`).
    """
    P = dR.copy()
    L = P.shape[1]
    shift = 1
    while shift < L:
        P[:, shift:] = P[:, : L - shift] @ P[:, shift:]  # earlier factors on the left
        shift *= 2
    return P


def triad(b1: Array, b2: Array, w1: Array, w2: Array) -> Array:
    """Rotation R (world ← body) with R b1 = w1 exactly and R b2 as close to w2 as possible (TRIAD)."""

    def frame(u: Array, v: Array) -> Array:
        e1 = u / np.linalg.norm(u)
        e2 = np.cross(e1, v)
        e2 /= np.linalg.norm(e2)
        return np.column_stack([e1, e2, np.cross(e1, e2)])

    out: Array = frame(w1, w2) @ frame(b1, b2).T
    return out


def yaw_rotation(psi: float) -> Array:
    """Rz(ψ) (3, 3): a turn of the world by ψ about its vertical (ENU z)."""
    c, s = math.cos(psi), math.sin(psi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
