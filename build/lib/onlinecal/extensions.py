"""Model extensions: the inverse of each effect of the vocabulary (:mod:`onlinecal.effect_registry`; the
simulator's forward models are in ``sim/effects.py``), applied to RAW data before
the paper's model ``calibrated = matrix @ (raw − bias)`` (Zhang et al. 2014, eq. 1).

A calibration JSON may carry ``"extensions": {"<effect>": {...}}`` (contract; ``Calibration.extensions``)
with the same keys as the effect spec (``onlinecal.effect_registry.EFFECT_KEYS``) plus:

* ``temperature_bias``: ``T0`` (°C, default 25), the temperature at which the bias is the paper
  model's bias; ``rise`` and ``tau`` describe a simulated session and are accepted but unused;
* coefficient keys (``coeff``, ``density``) may be a list of 3 (per axis) when the axis is all;
* the value of an effect may be a list of such dicts (e.g. temperature_bias on gyro and on accel);
* informative keys of the simulator's truth (``clipped_fraction``, ``walk_final``) are ignored.

What each extension does, in the order :func:`correct` applies them (the reverse of the simulator's
signal chain, the ``sim/effects.py`` module docstring):

====================  ==========================================================================
axis_sign             ``raw_axis ← −raw_axis`` (the flip is its own inverse)
mag_current           ``raw_mag −= coeff·x``, x the log's ``current`` (A) or ``throttle`` (0…1) series
                      (``ImuData.series``) interpolated onto the mag's stamps; raw frame, before the
                      hard/soft iron (:func:`remove_mag_current`); refused on a log without that series
scale_nonlinearity    exact inverse of ``y = x(1 + c|x|)``: ``x = sign(y)·2|y| / (1 + √(1 + 4c|y|))``
temperature_bias      ``raw_axis −= coeff·(T − T0)``, T the log's temperature column (°C)
time_offset           mag: re-stamped ``t_mag − seconds``; gyro/accel share the IMU clock, so the
                      sensor is resampled (cubic spline) at ``t_imu + seconds`` instead
lever_arm             ``raw_acc −= M_acc⁻¹·(ω̇×r + ω×(ω×r))``, ω = the calibrated gyro, ω̇ its
                      Savitzky–Golay derivative (cubic, 0.1 s window); needs the calibration
g_sensitivity         ``raw_gyro −= G·f``, G = diag(coeff) + matrix (3×3, the full g-sensitivity;
                      row = gyro axis, column = force axis), f = the calibrated (and lever-arm corrected)
                      accelerometer in the body frame, m/s² — the effect adds coeff·f_true(B) to the
                      gyro's raw value in rad/s, so the correction is in raw gyro units with f in B;
                      needs the calibration's accelerometer
bias_drift            not removable sample by sample: :func:`process_noise` gives the rate random walk
                      for the UKF's bias states; correct() leaves the data
saturation            not removable: :func:`clipped_mask` marks samples at the rail so filters can
                      skip or de-weight them; correct() leaves the data
====================  ==========================================================================

Combinations of a gyro time_offset with g_sensitivity, or of lever_arm with g_sensitivity, are
corrected to first order (f and ω are taken from the other, corrected sensor; the lever arm is removed
twice, the second time with the g-corrected gyro). Everything acts on a whole log; on a block of a
log, the derivative and resampling are approximate within 0.1 s of the block's ends.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import CubicSpline

from .effect_registry import ALL_EFFECTS, AXES, EFFECT_KEYS, EFFECTS, REQUIRED, SENSORS_OF, lever_arm_acceleration
from .io.base import ImuData
from .model import Calibration

Array = NDArray[np.float64]

# Keys each extension accepts: the effect's spec keys, plus T0 for temperature_bias.
EXTENSION_KEYS: dict[str, tuple[str, ...]] = {
    n: tuple(EFFECT_KEYS[n]) + (("T0",) if n == "temperature_bias" else ()) for n in EFFECTS
}
# Keys that must be present (a missing coefficient must not silently become the simulator's default).
# (g_sensitivity: coeff, or the full matrix instead)
INFORMATIVE = ("effect", "clipped_fraction", "walk_final")
# sensors each effect may act on, and the keys that must be present: the registry's
PER_AXIS = ("coeff", "density")  # keys that may be a list of 3 when axis is all
SAVGOL_WINDOW_S = 0.1


def _num(name: str, key: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValueError(f"extension {name}: {key} must be a finite number (got {v!r})")
    return float(v)


def _entry(name: str, d: Any) -> dict[str, Any]:
    if not isinstance(d, dict):
        raise ValueError(f"extension {name}: expected an object of parameters, got {type(d).__name__}")
    keys = EXTENSION_KEYS[name]
    for k in d:
        if k not in keys and k not in INFORMATIVE:
            raise ValueError(f"extension {name}: unknown key {k!r} (valid: {', '.join(keys)})")
    if d.get("effect", name) != name:
        raise ValueError(f"extension {name}: entry says effect {d['effect']!r}")
    for k in REQUIRED[name]:
        if k not in d and not (name == "g_sensitivity" and k == "coeff" and d.get("matrix") is not None):
            raise ValueError(f"extension {name}: missing key {k!r}")
    defaults = EFFECT_KEYS[name]
    sensor = d.get("sensor", defaults.get("sensor", "accel"))
    if sensor not in SENSORS_OF[name]:
        raise ValueError(f"extension {name}: sensor must be one of {', '.join(SENSORS_OF[name])} (got {sensor!r})")
    axis = d.get("axis", defaults.get("axis"))
    axis = None if axis == "all" else axis
    if axis is not None and axis not in AXES:
        raise ValueError(f"extension {name}: axis must be x, y, z, all or null (got {axis!r})")
    out: dict[str, Any] = {"sensor": sensor, "axis": axis}
    sel = np.zeros(3) if axis is not None else np.ones(3)
    if axis is not None:
        sel[AXES.index(axis)] = 1.0
    out["sel"] = sel.astype(bool)
    for k in keys:
        if k in ("sensor", "axis") or k not in d:
            continue
        v = d[k]
        if k == "matrix" and v is None:  # a diagonal-only description (the simulator's truth)
            continue
        if k == "matrix":
            try:
                m = np.asarray(v, dtype=float)
            except (TypeError, ValueError):
                m = np.zeros(0)
            if m.shape != (3, 3) or not np.all(np.isfinite(m)):
                raise ValueError(f"extension {name}: matrix must be 3×3 finite numbers (got {v!r})")
            out[k] = m
            continue
        if k in PER_AXIS and isinstance(v, (list, tuple)):
            if axis is not None or len(v) != 3:
                raise ValueError(f"extension {name}: {k} may be a list of 3 only with axis all")
            out[k] = np.array([_num(name, k, x) for x in v])
        elif k in PER_AXIS:
            out[k] = _num(name, k, v) * sel
        else:
            out[k] = _num(name, k, v)
    if name == "temperature_bias":
        out.setdefault("T0", 25.0)
    if name == "g_sensitivity":
        out.setdefault("coeff", np.zeros(3))
        out["G"] = np.diag(out["coeff"]) + out.get("matrix", np.zeros((3, 3)))
    if name == "bias_drift" and np.any(out["density"] < 0):
        raise ValueError("extension bias_drift: density must be >= 0")
    if name == "saturation" and out["limit"] <= 0:
        raise ValueError("extension saturation: limit must be > 0")
    return out


def validate_extensions(extensions: dict[str, Any] | None) -> dict[str, list[dict[str, Any]]]:
    """Check a calibration's ``extensions`` and normalise it: ``{effect: [entry, ...]}`` where each entry
    has ``sensor``, ``axis`` (None = all), ``sel`` (3,) bool axis mask, per-axis keys as (3,) arrays
    (zero off the axis) and the other numbers as floats. Raises ValueError naming the effect and key."""
    if not extensions:
        return {}
    if not isinstance(extensions, dict):
        raise ValueError(f"extensions must be an object, got {type(extensions).__name__}")
    out: dict[str, list[dict[str, Any]]] = {}
    for name, v in extensions.items():
        if name == "mag_current":  # keys of its own (coeff a list of 3, basis, σ, compass instance)
            out[name] = [_mag_current_entry(d) for d in (v if isinstance(v, list) else [v])]
            continue
        if name not in EXTENSION_KEYS:
            raise ValueError(f"unknown extension {name!r}; known: {', '.join(ALL_EFFECTS)}")
        items = v if isinstance(v, list) else [v]
        out[name] = [_entry(name, d) for d in items]
    return out


def extensions_from_effects(effects: list[dict[str, Any]]) -> dict[str, Any]:
    """The extensions dict that undoes simulated effects (``Truth.effects`` / ``describe()`` dicts);
    temperature_bias gets T0 = 25 °C, the simulator's reference temperature."""
    out: dict[str, Any] = {}
    for d in effects:
        keys = ("basis", "coeff") if d["effect"] == "mag_current" else EXTENSION_KEYS[d["effect"]]
        e = {k: v for k, v in d.items() if k in keys}
        if d["effect"] == "temperature_bias":
            e["T0"] = 25.0
        out.setdefault(d["effect"], []).append(e)
    return {k: v[0] if len(v) == 1 else v for k, v in out.items()}


def uninvert_nonlinearity(y: Array, coeff: Array) -> Array:
    """Exact inverse of ``y = x·(1 + c·|x|)`` per axis (closed form of the quadratic, cancellation-free):
    ``x = sign(y)·2|y| / (1 + √(1 + 4c|y|))``. y (N, 3), coeff (3,); where 1 + 4c|y| < 0 (beyond the
    turning point of a negative c) the turning point is returned."""
    a = np.abs(y)
    disc = np.maximum(1.0 + 4.0 * coeff * a, 0.0)
    return np.sign(y) * 2.0 * a / (1.0 + np.sqrt(disc))


def smoothed_derivative(t: Array, x: Array, window_s: float = SAVGOL_WINDOW_S) -> Array:
    """dx/dt (N, 3) by a cubic Savitzky–Golay filter over ``window_s`` seconds (uniform sampling
    assumed at the median step)."""
    n = x.shape[0]
    dt = float(np.median(np.diff(t)))
    w = max(5, int(round(window_s / dt)) | 1)
    if n < w:
        return np.gradient(x, t, axis=0)
    from scipy.signal import savgol_filter  # here: scipy.signal takes ~1 s to import, and only this needs it

    return savgol_filter(x, w, 3, deriv=1, delta=dt, axis=0)


def _shift(t: Array, x: Array, seconds: float) -> Array:
    """Values at t + seconds (cubic spline; ends held), i.e. the readings whose stamps were late by
    ``seconds`` brought back to their true instants."""
    q = np.clip(t + seconds, t[0], t[-1])
    return CubicSpline(t, x, axis=0)(q)


def _temperature(data: ImuData) -> Array:
    T = np.asarray(data.temp, float)
    ok = np.isfinite(T)
    if not ok.any():
        raise ValueError("extension temperature_bias needs the log's temperature column, which is empty")
    if not ok.all():
        T = np.interp(data.t_imu, data.t_imu[ok], T[ok])
    return T


def _lever(data_t: Array, gyro: Array, cal: Calibration, r: Array) -> Array:
    """M_acc⁻¹·(ω̇×r + ω×(ω×r)) in raw accelerometer units, ω from the calibrated gyro."""
    assert cal.gyro is not None and cal.accel is not None
    w = cal.gyro.apply(gyro)
    a = lever_arm_acceleration(w, smoothed_derivative(data_t, w), r)
    return a @ np.linalg.inv(cal.accel.matrix).T


def correct(data: ImuData, extensions: dict[str, Any] | None, calibration: Calibration | None = None) -> ImuData:
    """Remove each extension's effect from RAW data (order and conventions: module docstring).

    ``data`` raw readings (rad/s, m/s², mag unit, °C); ``extensions`` a calibration's extensions dict;
    ``calibration`` the paper-model calibration, needed only for lever_arm (gyro and accel) and
    g_sensitivity (accel). Returns a new ImuData (the input is not changed); bias_drift and saturation
    leave the values as they are (see :func:`process_noise`, :func:`clipped_mask`).
    """
    ext = validate_extensions(extensions)
    raw = {"gyro": np.array(data.gyro, float), "accel": np.array(data.acc, float), "mag": np.array(data.mag, float)}
    t_mag = np.array(data.t_mag, float)
    needs = [n for n in ("lever_arm", "g_sensitivity") if n in ext]
    if needs and (calibration is None or calibration.accel is None
                  or ("lever_arm" in ext and calibration.gyro is None)):
        raise ValueError(f"extension {needs[0]} needs the calibration (gyro and accel) to be corrected")
    for e in ext.get("axis_sign", []):
        raw[e["sensor"]][:, e["sel"]] *= -1.0
    for e in ext.get("mag_current", []):
        if not data.n_mag:
            continue
        if e["basis"] not in data.series:
            raise ValueError(f"a mag_current extension ({e['basis']}) on a log without a {e['basis']} series")
        ts, xs = data.series[e["basis"]]
        raw["mag"] = remove_mag_current(raw["mag"], np.interp(data.t_mag, ts, xs), e["coeff"])
    for e in ext.get("scale_nonlinearity", []):
        x = raw[e["sensor"]]
        x[:] = np.where(e["sel"], uninvert_nonlinearity(x, e["coeff"]), x)
    if ext.get("temperature_bias"):
        T = _temperature(data)
        for e in ext["temperature_bias"]:
            raw[e["sensor"]] -= e["coeff"] * (T - e["T0"])[:, None]
    for e in ext.get("time_offset", []):
        if e["sensor"] == "mag":
            t_mag = t_mag - e["seconds"]
        elif data.n_imu > 1:
            raw[e["sensor"]] = _shift(data.t_imu, raw[e["sensor"]], e["seconds"])
    lever = ext.get("lever_arm", [])
    r = np.array([[e["x"], e["y"], e["z"]] for e in lever]).sum(0) if lever else None
    acc0 = raw["accel"].copy()
    if r is not None and calibration is not None:
        raw["accel"] = acc0 - _lever(data.t_imu, raw["gyro"], calibration, r)
    if ext.get("g_sensitivity") and calibration is not None and calibration.accel is not None:
        f = calibration.accel.apply(raw["accel"])
        for e in ext["g_sensitivity"]:
            raw["gyro"] -= f @ e["G"].T
        if r is not None:  # second pass: the lever arm with the g-corrected gyro
            raw["accel"] = acc0 - _lever(data.t_imu, raw["gyro"], calibration, r)
    # the log's boundaries, parameters and series (current, throttle) travel with the corrected data
    return ImuData(np.array(data.t_imu, float), raw["gyro"], raw["accel"], np.array(data.temp, float), t_mag,
                   raw["mag"], data.source, list(data.warnings), list(data.boundaries), dict(data.params),
                   dict(data.series))


def process_noise(extensions: dict[str, Any] | None) -> dict[str, Array]:
    """Rate-random-walk densities (unit/s/√s, per axis) of the bias_drift extensions, for the UKF:
    over a step Δt the raw-unit bias state of that sensor gains variance ``density²·Δt``.
    Returns ``{"gyro": (3,), "accel": (3,)}`` (zeros where no drift is declared)."""
    out = {"gyro": np.zeros(3), "accel": np.zeros(3)}
    for e in validate_extensions(extensions).get("bias_drift", []):
        out[e["sensor"]] = np.sqrt(out[e["sensor"]] ** 2 + e["density"] ** 2)
    return out


def clipped_mask(data: ImuData, extensions: dict[str, Any] | None, rtol: float = 1e-3) -> dict[str, NDArray[np.bool_]]:
    """Per saturated sensor, an (N, 3) mask of readings at the rail: ``|raw| ≥ limit·(1 − rtol)``
    (rtol absorbs a log format's rounding, e.g. RAW_IMU's milli-units). Filters skip or de-weight
    these samples; a sensor without a saturation extension is absent from the dict."""
    out: dict[str, NDArray[np.bool_]] = {}
    for e in validate_extensions(extensions).get("saturation", []):
        x = data.gyro if e["sensor"] == "gyro" else data.acc
        out[e["sensor"]] = np.abs(np.asarray(x, float)) >= e["limit"] * (1 - rtol)
    return out


def gsens_matrix(entry: dict[str, Any]) -> Array:
    """The full g-sensitivity G (3, 3; rad/s per m/s², raw gyro ← body specific force) of one calibration
    JSON ``g_sensitivity`` entry: diag(coeff on its axes) + matrix."""
    return np.asarray(validate_extensions({"g_sensitivity": entry})["g_sensitivity"][0]["G"], float)


# -- mag_current: magnetometer interference from motor current or throttle (compassmot) ---------------------
# The effect: raw_mag += k·x, with x the battery current (A) or the throttle (0…1) at the mag's sample instants
# and k (3,) in the magnetometer's raw unit per A (or at full throttle), in the raw frame before the hard/soft
# iron (the simulator's MagCurrent, diagnose's candidate in diagnose/magcurrent.py, the export all use this
# one convention). The series come from the log (ImuData.series: DataFlash BAT/CURR, CTUN/RCOU).
MAG_CURRENT_BASES = ("throttle", "current")


MAG_CURRENT_KEYS = ("effect", "sensor", "axis", "coeff", "basis", "coeff_sigma", "instance")


def _mag_current_entry(d: Any) -> dict[str, Any]:
    """One ``mag_current`` extension entry: ``coeff`` (3,) raw magnetometer unit per A (basis "current") or
    at full throttle (basis "throttle"), raw = true + coeff·x; optional ``coeff_sigma`` (3,) and compass
    ``instance`` (1–3, default 1); ``sensor`` "mag", ``axis`` null."""
    name = "mag_current"
    if not isinstance(d, dict):
        raise ValueError(f"extension {name}: expected an object of parameters, got {type(d).__name__}")
    for k in d:
        if k not in MAG_CURRENT_KEYS:
            raise ValueError(f"extension {name}: unknown key {k!r} (valid: {', '.join(MAG_CURRENT_KEYS)})")
    if d.get("effect", name) != name or d.get("sensor", "mag") != "mag" or d.get("axis") not in (None, "all"):
        raise ValueError(f"extension {name}: acts on the magnetometer, all axes (sensor mag, axis null)")
    if d.get("basis") not in MAG_CURRENT_BASES:
        raise ValueError(f"extension {name}: basis must be one of {', '.join(MAG_CURRENT_BASES)} "
                         f"(got {d.get('basis')!r})")
    out: dict[str, Any] = {"sensor": "mag", "axis": None, "sel": np.ones(3, bool), "basis": d["basis"]}
    for k in ("coeff", "coeff_sigma"):
        if k not in d:
            if k == "coeff":
                raise ValueError(f"extension {name}: missing key 'coeff'")
            continue
        v = d[k]
        if not isinstance(v, (list, tuple)) or len(v) != 3:
            raise ValueError(f"extension {name}: {k} must be a list of 3 numbers (got {v!r})")
        out[k] = np.array([_num(name, k, x) for x in v])
    inst = d.get("instance", 1)
    if isinstance(inst, bool) or inst not in (1, 2, 3):
        raise ValueError(f"extension {name}: instance must be 1, 2 or 3 (got {inst!r})")
    out["instance"] = int(inst)
    return out


def remove_mag_current(mag: Array, x: Array, coeff: Array) -> Array:
    """Inverse of the mag_current effect: ``raw_mag − k·x`` for mag (N, 3) raw, x (N,) current (A) or throttle
    (0…1) at the same instants, coeff k (3,) raw unit per A or at full throttle."""
    return np.asarray(mag, float) - np.asarray(x, float)[:, None] * np.asarray(coeff, float)[None, :]


def compassmot_params(coeff: Array, basis: str, gauss_per_unit: float,
                      instance: int = 1) -> dict[str, dict[str, float]]:
    """The autopilots' motor-interference parameters for a mag_current coefficient k (raw = true + k·x).

    Both autopilots *add* their parameter times x to the reading (ArduPilot: ``cmag = mag + COMPASS_MOT·x``,
    pymavlink's magfit_compassmot and ArduCopter's compassmot; PX4: ``mag + CAL_MAGn_xCOMP·x``), so the
    parameter is −k in their units:

    * ArduPilot ``COMPASS_MOT{,2,3}_X/Y/Z`` in milligauss per A (current) or milligauss at full throttle,
      ``COMPASS_MOTCT`` 1 = throttle, 2 = current;
    * PX4 ``CAL_MAG{n−1}_XCOMP/YCOMP/ZCOMP`` in gauss per kA (current) or gauss at full throttle,
      ``CAL_MAG_COMP_TYP`` 1 = throttle, 2 = current.

    ``basis``: "throttle" or "current"; ``gauss_per_unit``: the gauss of one raw magnetometer unit (1 for a log
    in gauss, 1e-3 for milligauss, 0.01 for µT); ``instance``: compass 1, 2 or 3.
    Returns ``{"ardupilot": {...}, "px4": {...}}``. Raises ValueError for an unknown basis or instance.
    """
    if basis not in MAG_CURRENT_BASES:
        raise ValueError(f"mag_current basis must be one of {', '.join(MAG_CURRENT_BASES)} (got {basis!r})")
    if instance not in (1, 2, 3):
        raise ValueError(f"compass instance must be 1, 2 or 3 (got {instance!r})")
    k = np.asarray(coeff, float).reshape(3) * float(gauss_per_unit)  # gauss per A, or gauss at full throttle
    ap_name = "COMPASS_MOT" + ("" if instance == 1 else str(instance))
    ap = {f"{ap_name}_{ax}": float(-1e3 * k[i]) for i, ax in enumerate("XYZ")}
    ap["COMPASS_MOTCT"] = 2.0 if basis == "current" else 1.0
    px_scale = 1e3 if basis == "current" else 1.0  # gauss per kA = 1e3 × gauss per A
    px = {f"CAL_MAG{instance - 1}_{ax}COMP": float(-px_scale * k[i]) for i, ax in enumerate("XYZ")}
    px["CAL_MAG_COMP_TYP"] = 2.0 if basis == "current" else 1.0
    return {"ardupilot": ap, "px4": px}
