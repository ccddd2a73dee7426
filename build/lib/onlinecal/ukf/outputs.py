"""What the filter reports: the calibration with σ (:func:`calibration_of`), the model extensions in the
effect vocabulary, per-parameter observability (posterior σ / prior σ) and the motions still missing,
and the trace rows. Pure functions of the state; the filter passes what they read.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..advice import faces_advice, faces_at_rest, missing_faces
from ..model import PARAMS, RAW_UNITS, SENSORS, Calibration, SensorCalibration
from .config import EXTENSIONS
from .layout import AXES, DIP, index
from .state import StateLayout
from .vehicle import MotionCoverage, VehicleDetector, observability_report

Array = NDArray[np.float64]


def calibration_of(x: Array, sig: Array, lay: StateLayout, meta_online: dict[str, Any],
                   extensions: dict[str, Any], init: Calibration | None) -> Calibration:
    """The estimate x (n,) with 1σ ``sig`` (n,) as a Calibration (source "online"): bias, scale, alpha, xi
    per sensor; alphas relative to the gauge sensor's carry its σ (in B). ``meta_online`` goes to
    ``meta.online`` with the dip, the gauge and the extensions' σ and units added. The ``gauge`` field:
    the init's "gyro_phases" where the filter holds that gyro's terms (it keeps the batch's B), else the
    held sensor; the raw units are the init's."""
    sens = {}
    g = lay.gauge
    for s in SENSORS:
        p = {q: x[index(s, q)] for q in PARAMS}
        sg = {q: sig[index(s, q)] for q in PARAMS}
        if g and s != g:
            # alphas are relative to the gauge sensor's (held at its prior): their σ in B includes its σ
            sg["alpha"] = np.hypot(sg["alpha"], sig[index(g, "alpha")])
        sgl = {q: v.tolist() for q, v in sg.items()}
        sens[s] = SensorCalibration.from_params(p["bias"], p["scale"], p["alpha"], p["xi"], sigma=sgl)
    meta = {"online": {
        "dip_deg": math.degrees(x[DIP]), "dip_sigma_deg": math.degrees(sig[DIP]),
        **{k: meta_online[k] for k in ("mag_used", "imu_samples", "blocks")},
        "gauge": {"sensor": g, "terms": list(lay.gauge_terms) if g else []},
        "quantisation": dict(meta_online["quantisation"]),
        "hold_states": sorted(lay.hold_slice),
        "extensions_sigma": extensions_sigma(sig, lay),
        "extensions_unit": {e: EXTENSIONS[e][2] for e in lay.ext_slice},
        "events": meta_online["events"], "nis": meta_online["nis"],
        **({"observability": meta_online["observability"]} if "observability" in meta_online else {}),
    }}
    gauge = g
    if g == "gyro" and init is not None and init.gauge == "gyro_phases" and "xi" in lay.gauge_terms:
        gauge = "gyro_phases"
    units = init.raw_units if init is not None else RAW_UNITS
    return Calibration(gyro=sens["gyro"], accel=sens["accel"], mag=sens["mag"], source="online",
                       meta=meta, extensions=extensions, gauge=gauge, raw_units=units)  # type: ignore[arg-type]


def extensions_of(x: Array, lay: StateLayout, T0: float | None) -> dict[str, Any]:
    """Estimated model extensions in the contract's effect vocabulary (keys of
    :data:`onlinecal.extensions.EXTENSION_KEYS`, accepted by ``validate_extensions`` and ``correct``):
    ``temperature_bias`` {sensor, axis: None, coeff: [3] per axis (unit/°C), T0 (°C, the log's first
    temperature)} — a list when both sensors carry one — and ``g_sensitivity`` {sensor: gyro,
    axis: None, coeff: [3] (rad/s per m/s²)}. Their 1σ are in :func:`extensions_sigma`."""
    out: dict[str, Any] = {}
    for e, sl in lay.ext_slice.items():
        name, sensor = e.split(":")[0], EXTENSIONS[e][0]
        d: dict[str, Any] = {"sensor": sensor, "axis": None, "coeff": [float(v) for v in x[sl]]}
        if name == "temperature_bias":
            d["T0"] = float(T0) if T0 is not None else 25.0
        if name in out:
            out[name] = (out[name] if isinstance(out[name], list) else [out[name]]) + [d]
        else:
            out[name] = d
    return out


def extensions_sigma(sig: Array, lay: StateLayout) -> dict[str, list[float]]:
    """1σ of every extension coefficient, per axis: {``extra_states`` key: [3]}."""
    return {e: [float(v) for v in sig[sl]] for e, sl in lay.ext_slice.items()}


def observability(sig: Array, prior_sigma: Array, lay: StateLayout, excited_ratio: float) -> dict[str, dict[str, Any]]:
    """Per parameter: posterior σ / prior σ and whether it is excited (ratio below ``excited_ratio``)."""
    out = {}
    for i, nm in lay.public():
        ratio = float(sig[i] / prior_sigma[i]) if prior_sigma[i] > 0 else float("nan")
        out[nm] = {"ratio": ratio, "excited": bool(ratio < excited_ratio)}
    return out


_OTHER = {"x": "y or z", "y": "x or z", "z": "x or y"}


def _advice(nm: str, faces: list[str] | None = None, rest_s: float | None = None) -> str | None:
    """The motion that excites parameter ``nm`` (small-angle eqs. 5–6: alpha_k couples the two axes other
    than k; xi_z tilts y towards x, xi_y tilts z towards x, xi_x tilts z towards y). With the data's
    ``faces`` at rest (:func:`onlinecal.advice.faces_at_rest`) an accelerometer bias/scale asks only for the
    faces of its axis the data lacks, and nothing when it holds both; with ``rest_s`` ≥ 10 s at rest the
    gyro bias asks for no more rest (None: no motion would help, the σ did not shrink for another reason)."""
    if nm == "dip":
        return "hold still with the magnetometer calibrated (dip of the field)"
    if nm.startswith("ext."):
        return ("let the temperature change (warm-up) for the temperature coefficients"
                if nm.split(".")[1].startswith("temperature_bias") else
                "turn with gravity along each gyro axis in turn (g-sensitivity)")
    s, p, ax = nm.split(".")
    if s == "gyro" and p == "bias" and rest_s is not None and rest_s >= 10.0:
        return None
    if s == "accel" and p in ("bias", "scale") and faces is not None:
        return faces_advice(missing_faces(faces, [ax]))
    if s == "gyro":
        return {"bias": "hold still (any attitude) for the gyro bias", "scale": f"turn about {ax}",
                "alpha": f"turn about {_OTHER[ax]} (gyro axis alignment)",
                "xi": f"turn about {_OTHER[ax]} (gyro non-orthogonality)"}[p]
    if s == "accel":
        return (f"hold still in another attitude: {ax} up and {ax} down" if p in ("bias", "scale")
                else "hold still in tilted attitudes (between the axes, e.g. 45°)")
    return (f"turn about {_OTHER[ax]} so the field sweeps the {ax} axis (mag)" if p in ("bias", "scale")
            else "rotate through all attitudes (e.g. a tumble) to sweep the field (mag)")


def missing_motion(obs: dict[str, dict[str, Any]], lay: StateLayout,
                   coverage: MotionCoverage | None = None) -> list[str]:
    """What motion is still needed to excite the parameters that are not yet excited (``obs`` from
    :func:`observability`); the held gauge terms need none. With the filter's ``coverage`` the advice
    derives from what the data holds (the faces at rest, the time at rest), never asking for a face or a
    rest the session already has."""
    faces = faces_at_rest(coverage.rest_dirs) if coverage is not None and coverage.rest_dirs else (
        [] if coverage is not None else None)
    rest_s = coverage.rest_s if coverage is not None else None
    held = set()
    if lay.gauge:
        held = {f"{lay.gauge}.{p}.{a}" for p in lay.gauge_terms for a in AXES}
    need: list[str] = []
    for nm, o in obs.items():
        if o["excited"] or nm in held:
            continue
        msg = _advice(nm, faces, rest_s)
        if msg is not None and msg not in need:
            need.append(msg)
    return need


@functools.lru_cache(maxsize=16)
def _trace_columns(names: tuple[str, ...]) -> tuple[NDArray[np.intp], tuple[str, ...]]:
    """The public states' indices (:meth:`.state.StateLayout.public`) and the trace's column names for them
    (``name``, ``name.sigma`` in turn), per layout (issue 15: built once, not at every row)."""
    idx = [i for i, nm in enumerate(names) if i >= 3 and not nm.startswith("hold.")]
    return np.asarray(idx, dtype=np.intp), tuple(k for i in idx for k in (names[i], names[i] + ".sigma"))


def trace_row(t: float, x: Array, sig: Array, lay: StateLayout, nis_last: dict[str, float]) -> dict[str, float]:
    """One trace row: log time t s, every public estimate and its σ (``name.sigma``), the last NIS."""
    row: dict[str, float] = {"t": t}
    idx, cols = _trace_columns(tuple(lay.names))
    vals = np.empty(2 * idx.size)  # estimate and σ in turn, as Python floats at once (issue 15: ~half the cost)
    vals[0::2], vals[1::2] = x[idx], sig[idx]
    row.update(zip(cols, vals.tolist(), strict=True))
    for s, v in nis_last.items():
        row[f"nis.{s}"] = v
    return row


def report_of(lay: StateLayout, sig: Array, prior_sigma: Array, coverage: MotionCoverage,
              vehicle: VehicleDetector, excited_ratio: float, mag_enabled: bool) -> dict[str, Any]:
    """Which public terms of the layout the data determined (posterior σ ``sig`` (n,) against
    ``prior_sigma`` (n,)), which not, why, and what motion would determine them
    (:func:`.vehicle.observability_report`); the gauge sensor's held terms are named as such."""
    held = {f"{lay.gauge}.{p}.{a}" for p in lay.gauge_terms for a in AXES} if lay.gauge else set()
    pub = lay.public()
    idx = [i for i, _ in pub]
    return observability_report(["att.x", "att.y", "att.z"] + [nm for _, nm in pub],
                                np.concatenate([np.zeros(3), sig[idx]]),
                                np.concatenate([np.ones(3), prior_sigma[idx]]),
                                coverage, vehicle, held, lay.gauge, excited_ratio, mag_enabled)


def temp_regressor(T: Array, T0: float | None) -> tuple[Array, float | None]:
    """Regressor T − T0 (°C) (N,) of the temperature extensions for temperatures T (N,) °C, and T0: the
    given one, else the first finite temperature (None while the log has none; the regressor is then 0)."""
    if T0 is None:
        fin = T[np.isfinite(T)]
        if fin.size:
            T0 = float(fin[0])
    if T0 is None:
        return np.zeros_like(T), None
    return np.where(np.isfinite(T), T - T0, 0.0), T0
