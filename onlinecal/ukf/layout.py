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
from .geometry import prefix_products, prefix_products_cm, rodrigues, rodrigues_cm, rot_log, skew

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


# the hot-path geometry lives in .geometry; re-exported for propagate.py and older imports
__all__ = ["ATT", "AXES", "DIP", "N_STATE", "NAMES", "PARAM_OFFSET", "SENSOR_SLICE", "correction", "field_world",
           "index", "model_pair", "prefix_products", "prefix_products_cm", "rodrigues", "rodrigues_cm",
           "rot_log", "sensor_model", "skew", "state_names"]
