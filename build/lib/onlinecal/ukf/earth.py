"""The Earth's rotation in the gyro: taken out of the raw rates where the latitude is known, else an allowance.

A gyro at rest reads its bias plus Ω_E = 7.292115e-5 rad/s (the sidereal rate, WGS-84) projected on its
axes: in the filter's world frame (ENU, north +y, :func:`.measurements.field_body`) that is
Ω_E · (0, cos φ, sin φ) at latitude φ. The model of eq. 1 has no such term. Without the latitude the filter
can only widen its σ for it (:attr:`.config.UKFConfig.rest_rate_sigma` on the zero-rate update and as the
gyro-bias floor in flight, Ω_h² on the attitude: :func:`.vehicle.earth_rate_noise`); with it
(:attr:`.config.UKFConfig.latitude_deg`) the rate is subtracted from each block's raw gyro samples before
the filter sees them (:func:`correct_block`), and the allowance shrinks to what is still unknown
(:func:`allowance`):

* the vertical part Ω_E sin φ needs the tilt only, which the accelerometer gives: always taken out;
* the horizontal part Ω_E cos φ points to true north; the filter's heading is magnetic (the field's
  horizontal part is its +y), so it is taken out only once a magnetometer holds the heading, along true
  north as the declination D puts it (:attr:`.config.UKFConfig.declination_deg`, east positive: 0 where not
  given); the error of that D leaves Ω_E cos φ · sin(ΔD) across north — an allowance of Ω_E cos φ · σ_D
  (:attr:`.config.UKFConfig.declination_sigma_deg`: 15° unknown, 1° given).
  Without a heading the horizontal part stays an allowance: Ω_E cos φ on the attitude, and on the bias
  per axis its share of the level plane at a heading the filter does not know (:func:`allowance`).

The subtraction uses the state's estimate: ω_E in the body frame at the block's middle, from the nominal
attitude at its start turned by half the block's mean rate (to first order; the block's own turn, 0.05 rad
either side at 1 rad/s in a 0.1-s block, averages out to first order, and the second order is ~1e-7 rad/s),
into raw units through the estimated M⁻¹ (eq. 1). The estimate's own errors (attitude ~1e-2 rad, scale and
angles ~1e-3 once determined) move a 7.3e-5 rad/s vector by ≲ 7e-7 rad/s, below the declination's
allowance (1.3e-5 rad/s at 47° and σ_D = 15°; 8.6e-7 at 1°).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from ..specs import OMEGA_EARTH as OMEGA_E
from .layout import SENSOR_SLICE, index
from .propagate import sensor_models
from .vehicle import OMEGA_E_HORIZONTAL_RMS

if TYPE_CHECKING:
    from .blocks import Blocks
    from .filter import OnlineCalibrator

Array = NDArray[np.float64]
_GYR_BIAS, _GYR_SCALE = index("gyro", "bias"), index("gyro", "scale")
_GYR = SENSOR_SLICE["gyro"]


def earth_rate_world(latitude_deg: float) -> tuple[float, float]:
    """(north, up) components rad/s of the Earth's rotation at ``latitude_deg`` in a local level frame:
    Ω_E cos φ, Ω_E sin φ (the east component is zero)."""
    phi = math.radians(latitude_deg)
    return OMEGA_E * math.cos(phi), OMEGA_E * math.sin(phi)


def allowance(latitude_deg: float | None, heading_known: bool, rest_rate_sigma: float,
              declination_sigma_deg: float, up_body: list[float] | None = None
              ) -> tuple[tuple[float, float, float], float]:
    """What the Earth's rotation still leaves unknown: (σ (3,) rad/s per gyro axis on the zero-rate update and
    as the in-flight bias floor, Ω_h² (rad/s)² the horizontal rate error turning the attitude).

    ``latitude_deg`` None: nothing is taken out, ``rest_rate_sigma`` (Ω_E/√3, an unknown latitude) on every axis
    and :data:`.vehicle.OMEGA_E_HORIZONTAL_RMS`² as before. Known, with ``heading_known`` (a magnetometer holds
    the heading): the declination's error across north, s_D = Ω_E cos φ·σ_D, for both. Known, no heading:
    the horizontal part h = Ω_E cos φ at a heading nobody knows lies in the level plane, so per body axis k
    its variance is h²/2 · (1 − u_k²) (``up_body`` u (3,), the world's up in the body frame: Rᵀe_z) — nothing
    on a level body's z, whose vertical part is taken out — plus s_D² (the same floor as with a heading);
    h² on the attitude."""
    if latitude_deg is None:
        return (rest_rate_sigma,) * 3, OMEGA_E_HORIZONTAL_RMS**2
    north, _ = earth_rate_world(latitude_deg)
    s_d = north * math.radians(declination_sigma_deg)
    if heading_known:
        return (s_d,) * 3, s_d * s_d
    u = up_body if up_body is not None else [0.0, 0.0, 0.0]
    h2 = 0.5 * north * north
    s = tuple(math.sqrt(h2 * max(0.0, 1.0 - uk * uk) + s_d * s_d) for uk in u)
    return (s[0], s[1], s[2]), north * north


def correct_block(cal: OnlineCalibrator, B: Blocks, b: int) -> None:
    """Take the Earth's rotation out of block ``b`` of ``B`` in place (module docstring): its raw rates
    w_ext (the rows of its samples, and the sample before them where a block before did not already) and
    its mean raw rate w_mean[b]; nothing where the latitude is not configured or the attitude not started."""
    lat = cal.config.latitude_deg
    if lat is None or not cal._att_ok:
        return
    north, up = earth_rate_world(lat)
    if cal._mag.yaw_free:
        north = 0.0  # the heading is unknown: only the vertical part (the tilt is known)
    # true north in the filter's world (its +y is magnetic north, D east of true north): (−sin D, cos D, 0)
    D = math.radians(cal.config.declination_deg)
    ve, vn = -north * math.sin(D), north * math.cos(D)
    R = cal.R_nom.tolist()  # world ← body: the body vector is Rᵀ v, v = (ve, vn, up)
    v = [R[0][k] * ve + R[1][k] * vn + R[2][k] * up for k in range(3)]
    x = cal.x
    o = x[_GYR_BIAS].tolist()
    s = x[_GYR_SCALE].tolist()
    if not min(s) > 0.0:  # a state gone wrong (a divergence handles it): no correction through a bad scale
        return
    i, j = B.lo_l[b], B.hi_l[b]
    wm = B.w_mean[b].tolist()
    half = 0.5 * float(B.dt[i:j].sum())
    th = [(wm[k] - o[k]) * s[k] * half for k in range(3)]  # the body's turn to the block's middle
    # a world-fixed vector seen from a body turned by θ: v − θ × v (first order)
    vm = [v[0] - (th[1] * v[2] - th[2] * v[1]), v[1] - (th[2] * v[0] - th[0] * v[2]),
          v[2] - (th[0] * v[1] - th[1] * v[0])]
    # into raw units through the gyro's whole M⁻¹ (eq. 1; its small angles, ~1e-2 rad, would otherwise leave
    # ~7e-7 rad/s, about the allowance of a declination known to 1°)
    Minv = sensor_models(x[None, _GYR])[2][0]
    e = Minv @ np.array(vm)
    first = max(i, B.earth_upto + 1)  # w_ext row k is the sample before sample k of the buffer
    B.w_ext[first : j + 1] -= e
    B.w_mean[b] -= e
    B.earth_upto = j
