"""The body frame B as the online filter sees it, and truth expressed in it.

A common rotation Q of the body frame (every sensor's matrix M → Q M, the attitude R → R Qᵀ) leaves every
reading unchanged (eq. 1 with gravity and the field fixed in the world), so the data alone never fix B. The
batch pipeline fixes it through the platform's rotation axes (the paper's phases); the UKF fixes it by
holding one sensor's alpha (``UKFConfig.gauge_sensor``, the accelerometer by default) at its prior — the
batch's value when initialised from it, 0 on a cold start. To compare a cold-start result with a truth
defined in another B, express the truth in the filter's B first: :func:`align_gauge`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from ..model import Calibration, SensorCalibration, decompose


def align_gauge(cal: Calibration, sensor: str = "accel", alpha: ArrayLike = (0.0, 0.0, 0.0)) -> Calibration:
    """``cal`` with every matrix turned by the one rotation Q that gives ``sensor`` the given alpha.

    Q = exp([q]_x) is found by Gauss–Newton on alpha(Q M_sensor) = alpha (eqs. 3–6 via decompose); biases
    are unchanged (the rotation acts on the calibrated side). Sigma is dropped.
    """
    target = np.asarray(alpha, float)
    ref = cal.sensor(sensor)
    if ref is None:
        raise ValueError(f"align_gauge: the calibration has no {sensor}")
    M_ref = ref.matrix

    def resid(q: np.ndarray) -> np.ndarray:
        return decompose(Rotation.from_rotvec(q).as_matrix() @ M_ref)[1] - target

    from scipy.optimize import least_squares  # lazily: ~0.3 s of every CLI start-up otherwise

    q = least_squares(resid, -(decompose(M_ref)[1] - target), xtol=1e-14, ftol=1e-14).x
    Q = Rotation.from_rotvec(q).as_matrix()
    out = {}
    for s in ("gyro", "accel", "mag"):
        c = cal.sensor(s)
        out[s] = None if c is None else SensorCalibration(c.bias, Q @ c.matrix)
    return cal.replace(**out)
