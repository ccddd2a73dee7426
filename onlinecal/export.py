"""Vehicle parameters from a calibration: ArduPilot ``.parm`` and PX4 (QGroundControl ``.params``).

onlinecal's convention is ``c = M (raw − b)`` with a full 3×3 ``M = S·T_R·T_N`` (Zhang et al. 2014,
eqs. 1–6). Each firmware applies a narrower model, read from its source (not from memory):

ArduPilot
    * compass — ``AP_Compass_Backend::correct_field`` (libraries/AP_Compass/AP_Compass_Backend.cpp),
      applied to the field in milligauss *after* ``rotate_field`` (COMPASS_ORIENT for an external
      compass)::

          mag += COMPASS_OFS;  mag *= COMPASS_SCALE (if within its limits);
          mag  = [[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z], [ODI_Y, ODI_Z, DIA_Z]] @ mag

      The offset is *added* and the soft-iron matrix is *symmetric*.
    * accelerometer — ``AP_InertialSensor_Backend::_rotate_and_correct_accel``::

          accel -= INS_ACCOFFS;  accel.{x,y,z} *= INS_ACCSCAL_{X,Y,Z}       (m/s², no cross terms)

    * gyroscope — ``AP_InertialSensor_Backend::_rotate_and_correct_gyro``: ``gyro -= INS_GYROFFS`` (rad/s,
      no scale at all).

PX4 (src/lib/sensor_calibration/{Accelerometer,Gyroscope,Magnetometer}.hpp, ``Correct``; parameter
names from src/modules/sensors/module.yaml, built by ``GetCalibrationParamsVector3f`` in Utilities.cpp
as ``CAL_<SENSOR><n>_<AXIS><TYPE>``)::

    accel = R · ((data − CAL_ACC0_{X,Y,Z}OFF) ∘ CAL_ACC0_{X,Y,Z}SCALE)          m/s²
    gyro  = R · (data − CAL_GYRO0_{X,Y,Z}OFF)                                  rad/s
    mag   = R · (W · (data − CAL_MAG0_{X,Y,Z}OFF))                              gauss
            W = [[XSCALE, XODIAG, YODIAG], [XODIAG, YSCALE, ZODIAG], [YODIAG, ZODIAG, ZSCALE]]

(``R`` the board rotation or, for an external sensor, ``CAL_<S>0_ROT``; PX4 subtracts the offset and
applies the rotation *after* the calibration, ArduPilot adds the compass offset and rotates *before*.)

What neither can express is returned, not hidden: for each sensor the matrix ``E`` with
``c_fw / field_scale = E @ c`` (``E = I`` when the firmware can express the calibration exactly), and
figures of the worst error it leaves (:class:`Dropped`).

* Magnetometer: ``M`` is split by the polar decomposition ``M = U·W`` (``W`` symmetric positive
  definite, ``U`` orthogonal). The firmware takes ``W`` and drops ``U``, so its output is the onlinecal
  output rotated by the constant ``Uᵀ``: the field norm is kept exactly and the only error is a frame
  rotation of ``angle(U)`` — a heading error of up to that angle. When ``U`` is closest to one of the
  firmware's 90° mounting rotations other than none, that rotation is written (COMPASS_ORIENT /
  CAL_MAG0_ROT) and only the remainder is dropped.
* Accelerometer: only the diagonal survives. The per-axis scale is the least-squares best over all
  directions of the specific force, ``s_i = K_ii / ‖K_i‖²`` with ``K = M⁻¹`` (minimises
  ``E_u ‖diag(s) M⁻¹ u − u‖²`` over unit ``u``); misalignment and non-orthogonality are dropped.
* Gyroscope: only the bias survives; scale, misalignment and non-orthogonality are dropped.

Units: the magnetometer output is not normalised by the firmware; ``W`` is scaled to determinant 1 so
the firmware's field has the raw field's geometric-mean radius ``r = |det M|^(-1/3)`` (in mG for
ArduPilot, gauss for PX4) — a physically plausible field strength that the firmware's field-length
checks accept — and ``field_scale = r``. COMPASS_SCALE is written as 1 (a stale value would otherwise
multiply the field).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .model import Calibration

Array = NDArray[np.float64]

FORMATS = ("ardupilot", "px4")

# Gauss per unit of the raw magnetometer values in the calibration. The .tlog and .bin readers
# convert milligauss to gauss, so "gauss" is the default; a CSV may hold any fixed unit.
MAG_UNITS = {"gauss": 1.0, "mgauss": 1e-3, "uT": 1e-2, "nT": 1e-5, "T": 1e4}

# MAV_PARAM_TYPE of the values written (QGroundControl checks it against the vehicle's own type).
MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9
INT32_PARAMS = frozenset({"COMPASS_ORIENT", "CAL_MAG0_ROT"})

# ArduPilot: AP_COMPASS_OFFSETS_MAX_DEFAULT (AP_Compass.cpp); INS_ACCSCAL @Range 0.8 1.2.
AP_COMPASS_OFFSETS_MAX = 1800.0
AP_ACCSCAL_RANGE = (0.8, 1.2)
# PX4 module.yaml: CAL_ACC0_XSCALE, CAL_MAG0_XSCALE min 0.1 max 3.0.
PX4_SCALE_RANGE = (0.1, 3.0)

# The mounting rotations that are multiples of 90°, as (roll, pitch, yaw) in degrees. ArduPilot's
# enum Rotation (AP_Math/rotations.h, COMPASS_ORIENT @Values) and PX4's (lib/conversion/rotation.h,
# CAL_MAG0_ROT values in module.yaml) agree on these numbers; both apply v' = Rz(yaw) Ry(pitch) Rx(roll) v
# (e.g. ArduPilot ROTATION_ROLL_90_YAW_90: roll first, then yaw).
ROTATIONS_90: dict[int, tuple[int, int, int]] = {
    0: (0, 0, 0), 2: (0, 0, 90), 4: (0, 0, 180), 6: (0, 0, 270),
    8: (180, 0, 0), 10: (180, 0, 90), 12: (0, 180, 0), 14: (180, 0, 270),
    16: (90, 0, 0), 18: (90, 0, 90), 20: (270, 0, 0), 22: (270, 0, 90),
    24: (0, 90, 0), 25: (0, 270, 0), 26: (0, 180, 90), 27: (0, 180, 270),
    28: (90, 90, 0), 29: (180, 90, 0), 30: (270, 90, 0), 31: (90, 180, 0),
    32: (270, 180, 0), 33: (90, 270, 0), 34: (180, 270, 0), 35: (270, 270, 0),
    36: (90, 180, 90), 37: (90, 0, 270),
}


class ExportError(ValueError):
    """The calibration cannot be turned into vehicle parameters (message says why)."""


def rotation_matrix(index: int) -> Array:
    """Matrix of firmware rotation ``index`` (a key of :data:`ROTATIONS_90`): Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = (math.radians(a) for a in ROTATIONS_90[index])
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    # Exact zeros and ±1 so the written orientation carries no rounding of its own.
    return np.round(Rz @ Ry @ Rx, 12) + 0.0


def rotation_angle(R: Array) -> float:
    """Angle (rad) of a proper rotation matrix."""
    return float(math.acos(max(-1.0, min(1.0, (np.trace(R) - 1.0) / 2.0))))


def polar_right(M: Array) -> tuple[Array, Array]:
    """``M = U W`` with ``W`` symmetric positive definite and ``U`` orthogonal (det U = sign det M)."""
    Uu, sv, Vt = np.linalg.svd(M)
    W = Vt.T @ np.diag(sv) @ Vt
    U = Uu @ Vt
    return U, 0.5 * (W + W.T)


def _fibonacci_sphere(n: int) -> Array:
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _angle_between(u: Array, v: Array) -> Array:
    """Angle (rad) between rows of u and v, stable for small angles (atan2 of |u×v| and u·v)."""
    return np.arctan2(np.linalg.norm(np.cross(u, v), axis=-1), np.einsum("...i,...i->...", u, v))


def max_angle_error(E: Array, n: int = 20000) -> float:
    """Largest angle (rad) between ``E u`` and ``u`` over all unit ``u``: grid, then local refinement."""
    U = _fibonacci_sphere(n)
    ang = _angle_between(U @ E.T, U)
    k = int(np.argmax(ang))

    def neg(x: Array) -> float:
        u = x / np.linalg.norm(x)
        return -float(_angle_between((E @ u)[None], u[None])[0])

    best = float(ang[k])
    from scipy.optimize import minimize  # lazily: ~0.3 s of every CLI start-up otherwise

    res = minimize(neg, U[k], method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-14, "maxiter": 2000})
    return max(best, -float(res.fun))


@dataclass(frozen=True)
class Dropped:
    """What the firmware cannot express of one sensor's calibration.

    ``E`` (3, 3): the firmware's output divided by ``field_scale`` is ``E @ c`` for onlinecal's calibrated
    ``c`` (``E = I`` when nothing is dropped). Figures over all directions of ``c``:
    ``max_angle_deg`` the largest angle between the two outputs, ``max_rel_error`` the largest
    ``‖E c − c‖ / ‖c‖`` (σ_max(E − I)), ``max_norm_rel_error`` the largest relative change of the norm
    (max(|σ_max(E) − 1|, |1 − σ_min(E)|)), ``rotation_deg`` the angle of E's orthogonal polar factor.
    """

    sensor: str
    E: Array
    field_scale: float
    what: str
    max_angle_deg: float
    max_rel_error: float
    max_norm_rel_error: float
    rotation_deg: float

    @classmethod
    def from_E(cls, sensor: str, E: Array, field_scale: float, what: str) -> Dropped:
        sv = np.linalg.svd(E, compute_uv=False)
        U, _ = polar_right(E)
        rot = rotation_angle(U) if np.linalg.det(U) > 0 else math.pi
        return cls(
            sensor, E, float(field_scale), what,
            math.degrees(max_angle_error(E)),
            float(np.linalg.norm(E - np.eye(3), 2)),
            float(max(abs(sv[0] - 1.0), abs(1.0 - sv[-1]))),
            math.degrees(rot),
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "E": self.E.tolist(), "field_scale": self.field_scale, "what": self.what,
            "max_angle_deg": self.max_angle_deg, "max_rel_error": self.max_rel_error,
            "max_norm_rel_error": self.max_norm_rel_error, "rotation_deg": self.rotation_deg,
        }

    @property
    def exact(self) -> bool:
        return bool(np.allclose(self.E, np.eye(3), rtol=0, atol=1e-9))


@dataclass
class Export:
    """Parameters (firmware order), their MAV_PARAM_TYPEs, what was dropped, and warnings."""

    fmt: str
    params: dict[str, float]
    types: dict[str, int]
    dropped: dict[str, Dropped] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    mag_unit: str = "gauss"
    withheld: dict[str, str] = field(default_factory=dict)  # name -> why it was not written
    origin: dict[str, str] = field(default_factory=dict)  # name -> where its value came from
    composed: bool = False  # composed with the onboard parameters (--onboard)

    def report(self) -> dict[str, Any]:
        """The JSON sidecar: parameters, where each came from, what was withheld, dropped parts, warnings."""
        return {
            "schema": "onlinecal.export/1", "format": self.fmt, "mag_unit": self.mag_unit,
            "params": dict(self.params), "origin": dict(self.origin), "withheld": dict(self.withheld),
            "composed_with_onboard": self.composed,
            "dropped": {k: v.to_dict() for k, v in self.dropped.items()},
            "warnings": list(self.warnings),
        }


def _best_orientation(M: Array, fmt: str) -> tuple[int, Array, Array, Array]:
    """Mounting rotation R_k, soft-iron W_k and dropped rotation Q for ``M`` (ArduPilot or PX4 order).

    ArduPilot rotates before calibrating: ``c_fw = W (R_k raw + ofs)``; with ``M R_kᵀ = U W``,
    ``c = U c_fw``. PX4 rotates after: ``c_fw = R_k W (raw − off)``; with ``R_kᵀ M = U W``,
    ``c = R_k U R_kᵀ c_fw``. The k with the smallest dropped angle wins (none on a tie).
    """
    best: tuple[float, int, Array, Array, Array] | None = None
    for k in ROTATIONS_90:
        R = rotation_matrix(k)
        Mk = M @ R.T if fmt == "ardupilot" else R.T @ M
        U, W = polar_right(Mk)
        Q = U if fmt == "ardupilot" else R @ U @ R.T
        ang = rotation_angle(Q)
        if best is None or ang < best[0] - 1e-9:
            best = (ang, k, R, W, Q)
    assert best is not None
    return best[1], best[2], best[3], best[4]


def export_calibration(cal: Calibration, fmt: str, mag_unit: str = "gauss",
                       onboard: dict[str, float] | None = None, force: bool = False,
                       health: dict[str, Any] | None = None) -> Export:
    """Map ``cal`` to the parameters of ``fmt`` (``ardupilot`` or ``px4``), with what is dropped.

    Raw values are taken to be what the firmware's correction receives with its own calibration at
    the defaults (offsets 0, scales 1, soft-iron identity, orientation none): gyro rad/s, accel m/s²,
    mag in ``mag_unit`` (a key of :data:`MAG_UNITS`) — unless ``onboard`` gives the parameters that were
    in effect when the data were logged: the data were then already corrected by them, and the export
    writes the composition (:func:`compose_onboard`) instead of applying a correction twice.

    Guard (:func:`guard`): a parameter whose term's σ exceeds :data:`SIGMA_MAX`, that the data did not
    determine, or whose sensor the health verdict (``health``, else :func:`onlinecal.health.assess` of
    ``cal``) names as degraded or failed, is not written (the vehicle keeps its value) and is listed in
    ``withheld`` with the reason — unless ``force``.
    """
    if fmt not in FORMATS:
        raise ExportError(f"unknown format {fmt!r} (ardupilot, px4)")
    if mag_unit not in MAG_UNITS:
        raise ExportError(f"unknown magnetometer unit {mag_unit!r} ({', '.join(MAG_UNITS)})")
    if cal.gyro is None and cal.accel is None and cal.mag is None:
        raise ExportError("the calibration has no sensor to export")
    fitted = cal
    composed = False
    pre_warnings: list[str] = []
    if onboard:
        cal, pre_warnings = compose_onboard(cal, onboard, fmt, mag_unit)
        composed = True
    ap = fmt == "ardupilot"
    params: dict[str, float] = {}
    types: dict[str, int] = {}
    dropped: dict[str, Dropped] = {}
    warnings: list[str] = []

    def put(name: str, value: float, typ: int = MAV_PARAM_TYPE_REAL32) -> None:
        # float32 (what the firmware stores) overflows to inf beyond 3.4e38: refuse far earlier
        if not math.isfinite(value) or abs(value) > 1e30:
            raise ExportError(f"{name} would be {value}: the calibration is degenerate")
        params[name] = float(value)
        types[name] = typ

    def put3(fmt_name: str, v: Array) -> None:
        for ax, x in zip("XYZ", v, strict=True):
            put(fmt_name.format(ax), float(x))

    # -- magnetometer -------------------------------------------------------------------------------
    mag_block: dict[str, float] = {}
    if cal.mag is not None:
        M = cal.mag.matrix
        if np.linalg.det(M) <= 0:
            raise ExportError("the magnetometer matrix has a non-positive determinant (an inverted axis): "
                              "neither firmware has a parameter for a reflection; fix the axis sign first")
        to_fw = MAG_UNITS[mag_unit] * (1e3 if ap else 1.0)  # raw unit -> mG (ArduPilot) or gauss (PX4)
        k, R, W, Q = _best_orientation(M, fmt)
        r_raw = abs(np.linalg.det(M)) ** (-1.0 / 3.0)
        W_fw = W * r_raw  # acts on the field in firmware units: W_fw (to_fw h) = to_fw r_raw W h
        field_scale = r_raw * to_fw
        b = cal.mag.bias * to_fw
        before = len(params)
        if ap:
            put3("COMPASS_OFS_{}", -(R @ b))
            if k != 0:
                put("COMPASS_ORIENT", float(k), MAV_PARAM_TYPE_INT32)
            put3("COMPASS_DIA_{}", np.diag(W_fw))
            put3("COMPASS_ODI_{}", np.array([W_fw[0, 1], W_fw[0, 2], W_fw[1, 2]]))
            put("COMPASS_SCALE", 1.0)
        else:
            if k != 0:
                put("CAL_MAG0_ROT", float(k), MAV_PARAM_TYPE_INT32)
            put3("CAL_MAG0_{}OFF", b)
            put3("CAL_MAG0_{}SCALE", np.diag(W_fw))
            put3("CAL_MAG0_{}ODIAG", np.array([W_fw[0, 1], W_fw[0, 2], W_fw[1, 2]]))
        mag_block = {n: params.pop(n) for n in list(params)[before:]}
        unit = "mG" if ap else "gauss"
        what = ("the magnetometer's rotation to the body frame (T_R, and the antisymmetric part of T_N): "
                f"the firmware's field is the calibrated field turned by the constant rotation E, "
                f"norm {field_scale:.4g} {unit}")
        dropped["mag"] = Dropped.from_E("mag", Q.T, field_scale, what)
        if k != 0:
            rot_name = "COMPASS_ORIENT" if ap else "CAL_MAG0_ROT"
            warnings.append(f"mag: the sensor is mounted at {ROTATIONS_90[k]} (roll, pitch, yaw deg) to the "
                            f"calibration frame; {rot_name} = {k} is written, which the firmware applies to "
                            "external compasses only and which assumes the data were read with orientation none")
        if ap and np.linalg.norm(b) > AP_COMPASS_OFFSETS_MAX:
            warnings.append(f"mag: offsets of {np.linalg.norm(b):.0f} mG exceed COMPASS_OFFS_MAX's default "
                            f"{AP_COMPASS_OFFSETS_MAX:.0f}; the pre-arm check will refuse them")
        if not ap and not (PX4_SCALE_RANGE[0] <= np.diag(W_fw).min() and np.diag(W_fw).max() <= PX4_SCALE_RANGE[1]):
            warnings.append(f"mag: CAL_MAG0_*SCALE outside PX4's range {PX4_SCALE_RANGE}")

    # -- motor interference (a mag_current extension: compassmot) ----------------------------------
    mot_block, mot_withheld, mot_origin, mot_warn = _compassmot(fitted, cal, fmt, mag_unit, composed, onboard,
                                                                None if cal.mag is None else (W_fw, R))
    warnings += mot_warn

    # -- accelerometer ----------------------------------------------------------------------------
    acc_block: dict[str, float] = {}
    if cal.accel is not None:
        K = np.linalg.inv(cal.accel.matrix)
        s = np.diag(K) / np.einsum("ij,ij->i", K, K)  # least squares over all force directions
        before = len(params)
        if ap:
            put3("INS_ACCSCAL_{}", s)
            put3("INS_ACCOFFS_{}", cal.accel.bias)
            lo, hi = AP_ACCSCAL_RANGE
        else:
            put3("CAL_ACC0_{}OFF", cal.accel.bias)
            put3("CAL_ACC0_{}SCALE", s)
            lo, hi = PX4_SCALE_RANGE
        acc_block = {n: params.pop(n) for n in list(params)[before:]}
        if s.min() < lo or s.max() > hi:
            warnings.append(f"accel: scale factors {np.round(s, 4).tolist()} outside the firmware's range [{lo}, {hi}]")
        dropped["accel"] = Dropped.from_E(
            "accel", np.diag(s) @ K, 1.0,
            "the accelerometer's misalignment (T_R) and non-orthogonality (T_N); only per-axis scale is kept")

    # -- gyroscope --------------------------------------------------------------------------------
    gyr_block: dict[str, float] = {}
    if cal.gyro is not None:
        before = len(params)
        put3("INS_GYROFFS_{}" if ap else "CAL_GYRO0_{}OFF", cal.gyro.bias)
        gyr_block = {n: params.pop(n) for n in list(params)[before:]}
        dropped["gyro"] = Dropped.from_E(
            "gyro", np.asarray(np.linalg.inv(cal.gyro.matrix), float), 1.0,
            "the gyroscope's scale, misalignment and non-orthogonality; only the bias is kept")
        warnings.append("gyro: the firmware re-estimates its gyro offsets at every boot (ArduPilot INS_GYR_CAL, "
                        "PX4's gyro calibration at start-up), overwriting these unless that is turned off")

    # Firmware order: ArduPilot groups as Mission Planner and MAVProxy list them (COMPASS_ before INS_,
    # within a group by var_info index: OFS 1, ORIENT 8, DIA 24, ODI 25, SCALE 40; ACCSCAL, ACCOFFS,
    # GYROFFS); PX4 as module.yaml defines them (ACC, GYRO, MAG).
    blocks = [mag_block, acc_block, gyr_block] if ap else [acc_block, gyr_block, mag_block]
    ordered: dict[str, float] = {}
    for blk in blocks:
        ordered.update(blk)
    for n in mot_block:  # COMPASS_MOTCT and CAL_MAG_COMP_TYP are enumerations
        types[n] = MAV_PARAM_TYPE_INT32 if n in ("COMPASS_MOTCT", "CAL_MAG_COMP_TYP") else MAV_PARAM_TYPE_REAL32

    for name, d in dropped.items():
        if not d.exact:
            warnings.append(f"{name}: dropped {d.what}; worst direction error {d.max_angle_deg:.3f}°, "
                            f"worst relative error {100 * d.max_rel_error:.3f} %")
    if set(cal.extensions) - {"mag_current"}:
        warnings.append(f"extensions {sorted(set(cal.extensions) - {'mag_current'})} have no firmware parameter "
                        "and are not exported")
    if not ap:
        warnings.append("PX4 applies CAL_<S>0_* only if CAL_<S>0_ID holds the sensor's device id; this file does "
                        "not set the ids (calibrate once in QGroundControl so slot 0 belongs to this sensor)")
    withheld = {} if force else guard(fitted, list(ordered), health)
    if force and guard(fitted, list(ordered), health):
        warnings.append("--force: parameters the σ or the health verdict do not support are written anyway")
    origin = {n: _origin(n, fitted, composed, onboard) for n in ordered}
    # the motor-interference block after the field's own (firmware order: COMPASS_MOT after COMPASS_OFS..SCALE;
    # PX4's CAL_MAGn_xCOMP after CAL_MAGn_*), guarded by its own σ (force writes it anyway)
    if mot_block:
        at = list(ordered).index(next(reversed(mag_block))) + 1 if mag_block else len(ordered)
        items = list(ordered.items())
        ordered = dict(items[:at] + list(mot_block.items()) + items[at:])
        origin.update(mot_origin)
        if not force:
            withheld.update(mot_withheld)
        elif mot_withheld:
            warnings.append("--force: motor-interference parameters their σ does not support are written anyway")
    kept = {n: v for n, v in ordered.items() if n not in withheld}
    if not any(c.sigma for c in (fitted.gyro, fitted.accel, fitted.mag) if c is not None):
        warnings.append("the calibration carries no σ: nothing could be checked against its uncertainty")
    return Export(fmt, kept, {n: types[n] for n in kept}, dropped, pre_warnings + warnings, mag_unit,
                  withheld, origin, composed)


# -- motor interference: a mag_current extension as COMPASS_MOT* / CAL_MAGn_xCOMP -------------------------

MOT_MIN_SIGMAS = 3.0  # a coefficient vector written only when some component is ≥ this many σ from zero


def _compassmot(fitted: Calibration, cal: Calibration, fmt: str, mag_unit: str, composed: bool,
                onboard: dict[str, float] | None, mag_frame: tuple[Array, Array] | None
                ) -> tuple[dict[str, float], dict[str, str], dict[str, str], list[str]]:
    """The autopilot's motor-interference parameters for ``fitted``'s ``mag_current`` extension (raw = true
    + k·x, x current in A or throttle 0…1; :func:`onlinecal.extensions.compassmot_params` for units and sign).

    Where each firmware adds its term: ArduPilot after offsets and soft iron, in the rotated frame
    (AP_Compass_Backend::correct_field: ``mag = DIA/ODI·(rot·raw + OFS) + MOT·x``), so its COMPASS_MOT is
    −W·R·k with the exported soft iron W and orientation R (``mag_frame``, in mG); PX4 in the raw frame
    before offset and scale (calibration::Magnetometer::Correct: ``rot·(scale·(raw + COMP·x − off))``), so
    CAL_MAGn_xCOMP is −k in gauss (per kA). Returns (params, withheld name → why, origin, warnings).
    A coefficient with ``coeff_sigma`` none of whose components reaches MOT_MIN_SIGMAS σ is withheld; so
    is one fitted on data the onboard parameters had already corrected (its frame is not the raw one)."""
    from .extensions import compassmot_params, validate_extensions

    if not fitted.extensions or "mag_current" not in fitted.extensions:
        return {}, {}, {}, []
    entries = validate_extensions({"mag_current": fitted.extensions["mag_current"]})["mag_current"]
    if mag_frame is None:
        return {}, {}, {}, ["mag_current: the calibration has no magnetometer; COMPASS_MOT/CAL_MAG*_COMP not written"]
    W_fw, R = mag_frame
    params: dict[str, float] = {}
    withheld: dict[str, str] = {}
    origin: dict[str, str] = {}
    warnings: list[str] = []
    if len({e["basis"] for e in entries}) > 1:
        raise ExportError("mag_current: entries on both current and throttle; the firmware takes one basis "
                          "(COMPASS_MOTCT / CAL_MAG_COMP_TYP)")
    for e in entries:
        k = np.asarray(e["coeff"], float)
        k_fw = W_fw @ (R @ k) if fmt == "ardupilot" else k  # the frame the firmware adds its term in
        p = compassmot_params(k_fw, e["basis"], MAG_UNITS[mag_unit], e["instance"])[fmt]
        unit = "A" if e["basis"] == "current" else "full throttle"
        sig = e.get("coeff_sigma")
        src = (f"mag_current.coeff {np.array2string(k, precision=5, separator=', ')} {mag_unit} per {unit}"
               + (f" ± {np.array2string(np.asarray(sig), precision=2, separator=', ')}" if sig is not None
                  else " (σ unknown)") + f" ({fitted.source})")
        why = None
        if composed:
            why = ("mag_current was fitted on data the onboard parameters had already corrected; its frame is not "
                   "the raw one the firmware adds COMPASS_MOT/CAL_MAG_COMP in (refit on uncorrected data)")
        elif sig is not None and not np.any(np.abs(k) >= MOT_MIN_SIGMAS * np.asarray(sig, float)):
            why = (f"mag_current.coeff is within {MOT_MIN_SIGMAS:g} σ of zero on every axis: no interference "
                   "the data could tell from noise")
        for n, v in p.items():
            params[n] = v
            origin[n] = src
            if why:
                withheld[n] = why
    if sig is None:
        warnings.append("mag_current: the coefficient carries no σ; COMPASS_MOT/CAL_MAG_COMP written unchecked")
    if composed and onboard and any(abs(v) > 0 for n, v in onboard.items()
                                    if n.startswith("COMPASS_MOT") or n.endswith("COMP")):
        warnings.append("mag_current: the onboard parameters already hold a motor compensation")
    return params, withheld, origin, warnings


# -- guard, origin, composition with the onboard parameters ----------------------------------------

# Largest 1σ with which a term is written (units of the calibration: rad/s, m/s², the field's unit for
# the magnetometer after its matrix, rad): beyond, the value is noise and the vehicle's own is as good.
SIGMA_MAX = {("gyro", "bias"): 0.01, ("accel", "bias"): 0.05, ("accel", "scale"): 0.01,
             ("mag", "bias"): 0.05, ("mag", "scale"): 0.05, ("mag", "xi"): 0.05, ("mag", "alpha"): 0.05}


def param_terms(name: str) -> tuple[str, list[tuple[str, int | None]]]:
    """The sensor and the calibration terms ``(param, axis index or None for all)`` a firmware parameter is
    computed from (either format)."""
    n = name.upper()
    ax = {"X": 0, "Y": 1, "Z": 2}
    if n.startswith(("COMPASS_", "CAL_MAG0_")):
        if "OFS" in n or n.endswith("OFF"):
            k = n[-1] if n.startswith("COMPASS_") else n[len("CAL_MAG0_")]
            return "mag", [("bias", ax[k]), ("scale", None)]
        return "mag", [("scale", None), ("xi", None), ("alpha", None)]
    sensor = "gyro" if ("GYR" in n) else "accel"
    k = n[-1] if n.startswith("INS_") else n[len("CAL_ACC0_") if sensor == "accel" else len("CAL_GYRO0_")]
    if "SCAL" in n:
        return sensor, [("scale", ax[k])]
    return sensor, [("bias", ax[k])]


def guard(cal: Calibration, names: Sequence[str], health: dict[str, Any] | None = None) -> dict[str, str]:
    """name → why, for each parameter of ``names`` the calibration does not support (see
    :func:`export_calibration`). ``health``: a stored verdict (its reasons are added to a fresh
    :func:`onlinecal.health.assess` of ``cal``)."""
    from .health import assess

    fresh = assess(cal)
    reasons = list(fresh["reasons"]) + [r for r in (health or {}).get("reasons", []) if r not in fresh["reasons"]]
    verdict = fresh["verdict"] if not health else max(
        (fresh["verdict"], str(health.get("verdict", "ok"))), key=("ok", "degraded", "failed").index)
    undetermined = set(fresh["checks"].get("undetermined", [])) | set(
        ((health or {}).get("checks") or {}).get("undetermined") or [])
    motion_only = set(fresh["checks"].get("motion_only", [])) | set(
        ((health or {}).get("checks") or {}).get("motion_only") or [])
    by_sensor = {s: [r for r in reasons if r.startswith(f"{s}:")] for s in ("gyro", "accel", "mag")}
    general = [r for r in reasons if not any(r.startswith(f"{s}:") for s in ("gyro", "accel", "mag"))]
    out: dict[str, str] = {}
    for name in names:
        sensor, terms = param_terms(name)
        c = cal.sensor(sensor)
        if c is None:
            continue
        if by_sensor[sensor]:
            out[name] = f"health: {by_sensor[sensor][0]}"
            continue
        if verdict == "failed" and general:
            out[name] = f"health failed: {general[0]}"
            continue
        for p, i in terms:
            keys = {f"{sensor}.{p}"} | ({f"{sensor}.{p}.{a}" for a in "xyz"} if i is None
                                        else {f"{sensor}.{p}.{'xyz'[i]}"})
            if keys & undetermined:
                out[name] = f"{sorted(keys & undetermined)[0]} was not determined by the data"
                break
            if keys & motion_only:
                out[name] = (f"{sorted(keys & motion_only)[0]} was determined through motion alone (no rest with its "
                             "axis up and down): it holds only if the motion carried no linear acceleration")
                break
            lim = SIGMA_MAX.get((sensor, p))
            sig = c.sigma.get(p)
            if lim is None or not c.sigma:
                continue  # no σ at all: nothing to check against (said once in the warnings)
            if sig is None:
                out[name] = f"{sensor}.{p} has no σ (the fit did not determine it)"
                break
            v = np.asarray(sig, float).reshape(-1)[: 3]
            v = v if i is None else v[i : i + 1]
            if p == "bias" and sensor == "mag":
                v = v * float(np.abs(np.diag(c.matrix)).mean())  # in units of the local field
            if p == "scale" and sensor == "mag":
                v = v / np.abs(c.scale[: v.size] if i is None else c.scale[i : i + 1])  # relative
            if not np.all(np.isfinite(v)) or np.any(v > lim):
                worst = float(np.nanmax(v)) if np.any(np.isfinite(v)) else float("nan")
                axis = "" if i is None else "." + "xyz"[i]
                out[name] = (f"{sensor}.{p}{axis} σ {worst:.3g} above {lim:g}"
                             f"{' (relative)' if (sensor, p) == ('mag', 'scale') else ''}: not determined well enough")
                break
    return out


def _origin(name: str, cal: Calibration, composed: bool, onboard: dict[str, float] | None) -> str:
    """One phrase: the calibration terms behind ``name``, their values and σ, and the composition."""
    sensor, terms = param_terms(name)
    c = cal.sensor(sensor)
    src = f"{cal.source}"
    if c is None:
        return src
    bits = []
    for p, i in terms[:1]:
        val = np.asarray(c.params()[p])
        sig = c.sigma.get(p)
        if i is None:
            bits.append(f"{sensor}.{p} {np.array2string(val, precision=5, separator=', ')}")
        else:
            sg = f" ± {float(np.asarray(sig).reshape(-1)[i]):.2g}" if sig is not None else " (σ unknown)"
            bits.append(f"{sensor}.{p}.{'xyz'[i]} {float(val[i]):+.6g}{sg}")
    out = f"{', '.join(bits)} ({src})"
    if composed:
        out += "; composed with the onboard parameters" + (f" ({name} was {onboard[name]:g})"
                                                          if onboard and name in onboard else "")
    return out


def _diag_or(d: dict[str, float], names: Sequence[str], default: float, zero_is_default: bool = False) -> Array:
    v = np.array([float(d.get(n, default)) for n in names])
    if zero_is_default:
        v[v == 0] = default
    return v


def _symmetric(dia: Array, odi: Array) -> Array:
    """The firmware's symmetric soft-iron matrix from its diagonal (DIA/SCALE) and off-diagonal (ODI/ODIAG:
    xy, xz, yz) parameters — the same layout in ArduPilot and PX4 (module doc)."""
    return np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])


def firmware_correction(onboard: dict[str, float], fmt: str, mag_unit: str = "gauss") -> dict[str, Any]:
    """The correction the firmware applied with ``onboard`` parameters, per sensor, as
    ``(f, F)`` with ``corrected = F (raw − f)`` in the calibration's raw units (see the module doc for each
    firmware's formula). Sensors with no parameter in ``onboard`` are absent."""
    from .model import SensorCalibration

    out: dict[str, Any] = {}
    k = MAG_UNITS[mag_unit] * (1e3 if fmt == "ardupilot" else 1.0)  # raw unit -> firmware unit
    if fmt == "ardupilot":
        if any(n.startswith("INS_ACC") for n in onboard):
            off = _diag_or(onboard, [f"INS_ACCOFFS_{a}" for a in "XYZ"], 0.0)
            sc = _diag_or(onboard, [f"INS_ACCSCAL_{a}" for a in "XYZ"], 1.0, zero_is_default=True)
            out["accel"] = SensorCalibration(off, np.diag(sc))
        if any(n.startswith("INS_GYROFFS") for n in onboard):
            out["gyro"] = SensorCalibration(_diag_or(onboard, [f"INS_GYROFFS_{a}" for a in "XYZ"], 0.0), np.eye(3))
        if any(n.startswith("COMPASS_") for n in onboard):
            ofs = _diag_or(onboard, [f"COMPASS_OFS_{a}" for a in "XYZ"], 0.0)
            dia = _diag_or(onboard, [f"COMPASS_DIA_{a}" for a in "XYZ"], 1.0, zero_is_default=True)
            odi = _diag_or(onboard, [f"COMPASS_ODI_{a}" for a in "XYZ"], 0.0)
            W = _symmetric(dia, odi)
            cs = float(onboard.get("COMPASS_SCALE", 1.0)) or 1.0
            out["mag"] = SensorCalibration(-ofs / k, cs * W)  # W (raw·k + OFS) / k = W (raw − (−OFS/k))
    else:
        if any(n.startswith("CAL_ACC0_") for n in onboard):
            off = _diag_or(onboard, [f"CAL_ACC0_{a}OFF" for a in "XYZ"], 0.0)
            sc = _diag_or(onboard, [f"CAL_ACC0_{a}SCALE" for a in "XYZ"], 1.0, zero_is_default=True)
            out["accel"] = SensorCalibration(off, np.diag(sc))
        if any(n.startswith("CAL_GYRO0_") for n in onboard):
            out["gyro"] = SensorCalibration(_diag_or(onboard, [f"CAL_GYRO0_{a}OFF" for a in "XYZ"], 0.0), np.eye(3))
        if any(n.startswith("CAL_MAG0_") for n in onboard):
            off = _diag_or(onboard, [f"CAL_MAG0_{a}OFF" for a in "XYZ"], 0.0)
            dia = _diag_or(onboard, [f"CAL_MAG0_{a}SCALE" for a in "XYZ"], 1.0, zero_is_default=True)
            odi = _diag_or(onboard, [f"CAL_MAG0_{a}ODIAG" for a in "XYZ"], 0.0)
            W = _symmetric(dia, odi)
            out["mag"] = SensorCalibration(off / k, W)
    return out


def compose_onboard(cal: Calibration, onboard: dict[str, float], fmt: str,
                    mag_unit: str = "gauss") -> tuple[Calibration, list[str]]:
    """The calibration of the *raw* sensor, from ``cal`` fitted on data the firmware had already corrected
    with ``onboard``: with the firmware's ``corrected = F (raw − f)`` and ``c = M (corrected − b)``,
    ``c = (M F) (raw − (f + F⁻¹ b))``. σ are carried over unchanged (F is within a few % of I for any
    working calibration, so they change by as much). Returns the composed calibration and warnings."""
    fw = firmware_correction(onboard, fmt, mag_unit)
    warnings: list[str] = []
    rot = onboard.get("COMPASS_ORIENT" if fmt == "ardupilot" else "CAL_MAG0_ROT", 0)
    if rot:
        warnings.append(f"onboard mag orientation {rot:g} is not composed (taken as applied outside the data)")
    kw: dict[str, Any] = {}
    for s in ("gyro", "accel", "mag"):
        c, f = cal.sensor(s), fw.get(s)
        if c is None or f is None:
            continue
        if abs(np.linalg.det(f.matrix)) < 1e-9:
            raise ExportError(f"the onboard {s} parameters form a singular correction")
        kw[s] = type(c)(f.bias + np.linalg.solve(f.matrix, c.bias), c.matrix @ f.matrix, c.sigma)
    if not kw:
        warnings.append("--onboard holds no calibration parameter of this format: nothing to compose with")
    return cal.replace(**kw), warnings


def vehicle_params(cal: Calibration, fmt: str, mag_unit: str = "gauss",
                   health: dict[str, Any] | None = None) -> dict[str, float]:
    """The firmware parameters for ``cal`` in ``fmt`` (``ardupilot`` | ``px4``), in the firmware's order;
    ``health``: the result's verdict (its named sensors' parameters withheld, :func:`guard`).

    See :func:`export_calibration` (and the module docstring) for the conventions and what is dropped.
    """
    return export_calibration(cal, fmt, mag_unit, health=health).params


def format_value(x: float) -> str:
    """Shortest text that reads back as the same float32 (the firmware stores float32)."""
    f32 = float(np.float32(x))
    for digits in range(6, 10):
        t = f"{f32:.{digits}g}"
        if float(np.float32(float(t))) == f32:
            return t
    return repr(f32)  # pragma: no cover - 9 significant digits always round-trip a float32


def write_parm(
    params: dict[str, float],
    path: str | Path,
    fmt: str,
    header: Sequence[str] = (),
    types: dict[str, int] | None = None,
) -> None:
    """Write ``params`` as a parameter file of ``fmt``, atomically (temp file then rename).

    * ``ardupilot``: ``NAME VALUE`` per line, ``#`` comments — the format MAVProxy's ``param load``
      (pymavlink ``MAVParmDict.load``: whitespace or comma separated, two fields) and Mission Planner read.
    * ``px4``: QGroundControl's ``.params`` (``ParameterManager::writeParametersToStream``): ``#`` header
      lines, then ``vehicle-id<TAB>component-id<TAB>NAME<TAB>VALUE<TAB>MAV_PARAM_TYPE`` (1, 1, type 9 =
      REAL32, 6 = INT32).
    """
    from .files import atomic_write

    atomic_write(path, render_parm(params, fmt, header, types))


def render_parm(
    params: dict[str, float], fmt: str, header: Sequence[str] = (), types: dict[str, int] | None = None
) -> str:
    """The text :func:`write_parm` writes."""
    if fmt not in FORMATS:
        raise ExportError(f"unknown format {fmt!r} (ardupilot, px4)")
    types = types or {}
    comments = [f"# {h}" if h else "#" for h in header]
    if fmt == "ardupilot":
        lines = comments + [f"{n:<16} {format_value(v)}" for n, v in params.items()]
    else:
        lines = ["# Onboard parameters for Vehicle 1", "#", *comments, *(["#"] if comments else []),
                 "# Vehicle-Id Component-Id Name Value Type"]
        for n, v in params.items():
            t = types.get(n, MAV_PARAM_TYPE_INT32 if n in INT32_PARAMS else MAV_PARAM_TYPE_REAL32)
            val = str(int(round(v))) if t == MAV_PARAM_TYPE_INT32 else format_value(v)
            lines.append(f"1\t1\t{n}\t{val}\t{t}")
    return "\n".join(lines) + "\n"


def header_lines(exp: Export, source: str) -> list[str]:
    """Comment lines for the file: where it came from, per parameter where its value came from, what
    was withheld (kept at the vehicle's value) and why, and what the firmware cannot express."""
    out = [f"onlinecal export --format {exp.fmt} of {source} (mag raw unit: {exp.mag_unit})"
           + ("; composed with the onboard parameters given" if exp.composed else "")]
    for n in exp.params:
        if n in exp.origin:
            out.append(f"{n}: from {exp.origin[n]}")
    for n, why in exp.withheld.items():
        out.append(f"{n}: NOT WRITTEN (the vehicle keeps its value): {why}")
    for name, d in exp.dropped.items():
        if d.exact:
            out.append(f"{name}: expressed exactly")
        else:
            out.append(f"{name}: DROPPED {d.what}")
            out.append(f"{name}:   worst direction error {d.max_angle_deg:.4f} deg, worst relative error "
                       f"{100 * d.max_rel_error:.4f} %")
    return out
