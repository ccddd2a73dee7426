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

from ..model import PARAMS, SENSORS, model_matrices
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


def model_pair(p: Array) -> tuple[Array, Array, Array]:
    """(o, M, M⁻¹) of the sensor terms p (S, 12) for every sigma point: :func:`onlinecal.model.model_matrices`
    (eqs. 1–6; the model has one owner, which broadcasts over leading axes)."""
    return model_matrices(p)


def correction(p: Array) -> tuple[Array, Array]:
    """(o (S, 3), M (S, 3, 3)) with ``calibrated = M (raw − o)`` for p (S, 12) (eq. 1)."""
    o, M, _ = model_matrices(p)
    return o, M


def sensor_model(p: Array) -> tuple[Array, Array]:
    """(o (S, 3), M⁻¹ (S, 3, 3)) with ``raw = M⁻¹ c + o`` for p (S, 12) (eq. 1 inverted, no inversion)."""
    o, _, Minv = model_matrices(p)
    return o, Minv


def field_world(dip: Array) -> Array:
    """Unit field in the world frame (ENU, north +y, pointing down by the dip). dip (S,) → (S, 3)."""
    return np.stack([np.zeros_like(dip), np.cos(dip), -np.sin(dip)], axis=-1)


# the hot-path geometry lives in .geometry; re-exported for propagate.py and older imports
__all__ = ["ATT", "AXES", "DIP", "N_STATE", "NAMES", "PARAM_OFFSET", "SENSOR_SLICE", "correction", "field_world",
           "index", "model_pair", "prefix_products", "prefix_products_cm", "rodrigues", "rodrigues_cm",
           "rot_log", "sensor_model", "skew", "state_names"]
