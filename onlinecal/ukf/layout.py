"""State layout of the augmented-state UKF and the paper's sensor model vectorised over sigma points.

State vector x (n = 40)::

    x[0:3]     δθ       attitude error, a rotation vector in the body frame around the nominal
                        attitude R_nom (world ← body):  R = R_nom · exp([δθ]_x)            (rad)
    x[3:15]    gyro     o_gyr (3, rad/s), s_gyr (3), alpha_gyr (3, rad), xi_gyr (3, rad)
    x[15:27]   accel    o_acc (3, m/s²), s_acc (3), alpha_acc (3, rad), xi_acc (3, rad)
    x[27:39]   mag      o_mag (3, raw unit), s_mag (3, 1/raw unit), alpha_mag (3, rad), xi_mag (3, rad)
    x[39]      dip      inclination δ of the local field; h_world = (0, cos δ, −sin δ) (ENU, z up)

The error is taken in the body frame because the one unobservable direction of the model — a common
rotation of the body frame B (all three alphas turn by q, the attitude by −q) — is then a constant direction
in the state space, independent of the attitude; with a world-frame error it would turn with the attitude
and the filter would gain spurious information along it (the inconsistency mechanism of Huang et al.'s
observability-constrained EKF). The world frame's heading is arbitrary, so the field's horizontal
direction is fixed to north (+y) and the filter's yaw is measured against it. Calibration terms are the
paper's parameters in their exact forms (eqs. 1–6): ``calibrated = S · T_R(alpha) · T_N(xi) · (raw − o)``.

Note: B cannot be found from the data (a common rotation of every sensor's frame changes no reading); see
:mod:`onlinecal.ukf.gauge` for how the filter pins it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..model import PARAMS, SENSORS
from ..sim.motion import euler_to_R

Array = NDArray[np.float64]

N_STATE = 40
ATT = slice(0, 3)
DIP = 39
SENSOR_SLICE = {"gyro": slice(3, 15), "accel": slice(15, 27), "mag": slice(27, 39)}
PARAM_OFFSET = {"bias": 0, "scale": 3, "alpha": 6, "xi": 9}
AXES = "xyz"


def index(sensor: str, param: str) -> slice:
    """Slice of the state vector holding ``param`` (bias/scale/alpha/xi) of ``sensor``."""
    s0 = SENSOR_SLICE[sensor].start + PARAM_OFFSET[param]
    return slice(s0, s0 + 3)


def state_names() -> list[str]:
    """Name of every state component, e.g. ``gyro.scale.x``; attitude ``att.x``, field ``dip``."""
    names = [f"att.{a}" for a in AXES]
    for s in SENSORS:
        for p in PARAMS:
            names += [f"{s}.{p}.{a}" for a in AXES]
    return names + ["dip"]


NAMES = state_names()


def _axes_and_inverse(xi: Array) -> tuple[Array, Array]:
    """Eq. 6 vectorised: A (rows = unit sensing axes) and T_N = A⁻¹ for xi (S, 3); both (S, 3, 3).

    A = [[1, 0, 0], [b, c, 0], [d, e, f]] with b = sin ξz, c = cos ξz, d = −sin ξy, e = sin ξx cos ξy,
    f = cos ξx cos ξy; its inverse is written out (lower triangular), no batched ``inv`` needed.
    """
    S = xi.shape[0]
    sx, sy, sz = np.sin(xi).T
    cx, cy, cz = np.cos(xi).T
    b, c, d, e, f = sz, cz, -sy, sx * cy, cx * cy
    A = np.zeros((S, 3, 3))
    A[:, 0, 0] = 1.0
    A[:, 1, 0], A[:, 1, 1] = b, c
    A[:, 2, 0], A[:, 2, 1], A[:, 2, 2] = d, e, f
    Ai = np.zeros((S, 3, 3))
    Ai[:, 0, 0] = 1.0
    Ai[:, 1, 0], Ai[:, 1, 1] = -b / c, 1.0 / c
    Ai[:, 2, 0], Ai[:, 2, 1], Ai[:, 2, 2] = (b * e - c * d) / (c * f), -e / (c * f), 1.0 / f
    return A, Ai


def correction(p: Array) -> tuple[Array, Array]:
    """Calibration map of one sensor for every sigma point (eq. 1 with eqs. 2–6, exact forms).

    ``p`` (S, 12) = (o, s, alpha, xi). Returns (o (S, 3), M (S, 3, 3)) with
    ``calibrated = M (raw − o)``, ``M = S · T_R(alpha) · T_N(xi)``.
    """
    o, s, a, xi = p[:, 0:3], p[:, 3:6], p[:, 6:9], p[:, 9:12]
    TR = euler_to_R(a)  # Rz(a_z) Ry(a_y) Rx(a_x), eqs. 3–4
    _, TN = _axes_and_inverse(xi)
    return o, s[:, :, None] * (TR @ TN)


def model_pair(p: Array) -> tuple[Array, Array, Array]:
    """:func:`correction` and :func:`sensor_model` at once (one T_R, one axes matrix): (o, M, M⁻¹).

    ``p`` (S, 12); o (S, 3), M = S·T_R·T_N and M⁻¹ = A·T_Rᵀ·diag(1/s), both (S, 3, 3) (eqs. 1–6).
    """
    o, s, a, xi = p[:, 0:3], p[:, 3:6], p[:, 6:9], p[:, 9:12]
    TR = euler_to_R(a)
    A, TN = _axes_and_inverse(xi)
    return o, s[:, :, None] * (TR @ TN), (A @ TR.transpose(0, 2, 1)) / s[:, None, :]


def sensor_model(p: Array) -> tuple[Array, Array]:
    """Inverse of :func:`correction`, the sensor model itself: ``raw = M⁻¹ c + o``.

    ``p`` (S, 12). Returns (o (S, 3), M⁻¹ (S, 3, 3)) with ``M⁻¹ = T_N⁻¹ T_Rᵀ S⁻¹ = A · T_Rᵀ · diag(1/s)``
    (eq. 6: T_N⁻¹ = A, the axes matrix), exact, with no matrix inversion.
    """
    o, s, a, xi = p[:, 0:3], p[:, 3:6], p[:, 6:9], p[:, 9:12]
    TR = euler_to_R(a)
    A, _ = _axes_and_inverse(xi)
    return o, (A @ TR.transpose(0, 2, 1)) / s[:, None, :]


def field_world(dip: Array) -> Array:
    """Unit field in the world frame (ENU, north +y, pointing down by the dip). dip (S,) → (S, 3)."""
    return np.stack([np.zeros_like(dip), np.cos(dip), -np.sin(dip)], axis=-1)


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
    return np.eye(3) + s * K + c * (K @ K)


def rot_log(R: Array) -> Array:
    """Rotation vector of R (..., 3, 3) → (..., 3), for angles below π (the inverse of rodrigues)."""
    v = 0.5 * np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                        R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    s = np.sqrt(np.einsum("...i,...i->...", v, v))
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    a = np.arctan2(s, c)
    # a / sin(a), with its series near 0 so that tiny rotations are exact as well
    k = np.where(s > 1e-8, a / np.where(s > 1e-8, s, 1.0), 1.0 + a * a / 6.0)
    return v * k[..., None]


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

    Hillis–Steele scan: ⌈log₂ L⌉ batched matmuls instead of L sequential ones, so the attitude of
    every sigma point at every IMU sample of a block comes out of a few vectorised operations.
    """
    P = dR.copy()
    L = P.shape[1]
    shift = 1
    while shift < L:
        P[:, shift:] = P[:, : L - shift] @ P[:, shift:]  # earlier factors on the left
        shift *= 2
    return P
