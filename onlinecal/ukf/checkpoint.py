"""Checkpoint of the online calibrator: everything needed to resume, as a JSON-able dict.

Generic over the filter's parts: each part is a dataclass (:mod:`.blocks`, :mod:`.noise`, :mod:`.health`,
:mod:`.rest`, :mod:`.vehicle`, :mod:`.magstart` …) serialised field by field (:func:`encode`), so a field
added to a part is saved and restored without touching this module. numpy arrays keep their shape and
dtype, tuples stay tuples, and non-finite floats (JSON has none) are tagged; every float round-trips
bit-exactly through JSON. Schema /2 (the hand-mapped keys) and /3 (without the divergence history and the
magnetic-disturbance gate, which then restart fresh, as they did) still load.

Schema /4 saves the divergence history (:class:`.divergence.DivergenceLog`: the log times of the divergences,
which decide whether the next one escalates to the cold prior) and the magnetic-disturbance gate
(:class:`.magdisturb.MagDisturbanceGate`: armed, inside a stretch since when, blocks left out), so a run
resumed right after a divergence or inside a disturbance goes on as an uninterrupted run would (issue 16).
Their fields are checked on load (:func:`check_parts`): a damaged value is refused, never half-used.

Schema /5 saves the learning gates (:class:`.learning.Learning`: the reading each of the accelerometer and the
magnetometer last learned its terms at), so a resumed run learns at the blocks an uninterrupted one would; a /4
or /3 checkpoint resumes with them fresh (its first motion block learns).
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from typing import Any

import numpy as np

from ..model import Calibration
from ..specs import SensorSpec
from .attitude_init import MagCollector
from .blocks import SampleBuffer
from .config import UKFConfig
from .detectors import HoldTracker, Lattice, RailDetector, RestDetector
from .divergence import DivergenceLog
from .health import EventLog, NisMonitor, none_to_inf
from .learning import LEARNED, Learning, LearningGate
from .magdisturb import MagDisturbanceGate
from .magstart import MagStart
from .noise import NoiseModel
from .rest import RestAccumulator
from .vehicle import MotionCoverage, VehicleDetector

STATE_SCHEMA = "onlinecal.ukf-state/5"
SCHEMA_V4 = "onlinecal.ukf-state/4"
SCHEMA_V3 = "onlinecal.ukf-state/3"
SCHEMA_V2 = "onlinecal.ukf-state/2"

# the parts a checkpoint may construct (by class name; nothing else is ever instantiated from a file)
PARTS: dict[str, type] = {c.__name__: c for c in (
    SampleBuffer, Lattice, RailDetector, RestDetector, HoldTracker, NisMonitor, EventLog, NoiseModel,
    SensorSpec, VehicleDetector, MotionCoverage, RestAccumulator, MagStart, MagCollector, DivergenceLog,
    MagDisturbanceGate, Learning, LearningGate)}

# the filter's attributes that change while it runs, besides x and P (plain lists at the top level);
# everything else follows from config, init and holds
STATE_ATTRS = ("R_nom", "prior_x", "prior_sigma", "_hold_sigma", "_rate", "_L", "_buf", "_t_last",
               "_w_last", "_att_ok", "_next_trace", "_n_imu", "_n_blocks", "_nis", "_log", "_trace",
               "_rest_det", "_lat", "_holds", "_hold_new", "_noise", "_rails", "_T0", "_vehicle", "_coverage",
               "_rest_acc", "_mag", "_div", "_magd", "_learn")
# added in schema /4: absent from a /3 checkpoint, and then started fresh (as /3 always did)
ATTRS_V4 = ("_div", "_magd")
# added in schema /5: absent from a /4 or /3 checkpoint, and then started fresh (its next motion block learns)
ATTRS_V5 = ("_learn",)


def _float(v: float) -> Any:
    return v if math.isfinite(v) else {"__f__": repr(v)}


def encode(v: Any) -> Any:
    """A JSON-able image of ``v``: dataclasses of :data:`PARTS` by their fields, arrays with shape and
    dtype, tuples and deques tagged, non-finite floats as ``{"__f__": "inf"}``."""
    t = type(v)
    if t is float:  # the bulk (trace rows, NIS windows): the fast path first
        return v if math.isfinite(v) else {"__f__": repr(v)}
    if t is str or t is int or t is bool or v is None:
        return v
    if t is list:
        return [encode(x) for x in v]
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        name = type(v).__name__
        if PARTS.get(name) is not type(v):
            raise TypeError(f"checkpoint: {name} is not a registered part")
        return {"__dc__": name, **{f.name: encode(getattr(v, f.name)) for f in dataclasses.fields(v)}}
    if isinstance(v, np.ndarray):
        flat = v.ravel().tolist()
        if v.dtype.kind == "f" and not np.isfinite(v).all():
            flat = [_float(x) for x in flat]
        return {"__nd__": flat, "shape": list(v.shape), "dtype": v.dtype.str}
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return _float(float(v))
    if isinstance(v, tuple):
        return {"__tuple__": [encode(x) for x in v]}
    if isinstance(v, deque):
        return {"__deque__": [encode(x) for x in v], "maxlen": v.maxlen}
    if isinstance(v, list):
        return [encode(x) for x in v]
    if isinstance(v, dict):
        if not all(isinstance(k, str) for k in v):
            raise TypeError("checkpoint: a dict with non-string keys")
        return {k: encode(x) for k, x in v.items()}
    if v is None or isinstance(v, str):
        return v
    raise TypeError(f"checkpoint: cannot encode a {type(v).__name__}")


def decode(v: Any) -> Any:
    """The inverse of :func:`encode`."""
    t = type(v)
    if t is list:
        return [decode(x) for x in v]
    if t is not dict:
        return v
    if "__f__" in v:
        return float(v["__f__"])
    if "__nd__" in v:
        flat = v["__nd__"]
        if any(type(x) is dict for x in flat):
            flat = [float(x["__f__"]) if type(x) is dict else x for x in flat]
        return np.array(flat, dtype=np.dtype(v["dtype"])).reshape(v["shape"])
    if "__tuple__" in v:
        return tuple(decode(x) for x in v["__tuple__"])
    if "__deque__" in v:
        return deque((decode(x) for x in v["__deque__"]), maxlen=v["maxlen"])
    if "__dc__" in v:
        cls = PARTS.get(v["__dc__"])
        if cls is None:
            raise ValueError(f"UKF state: unknown part {v['__dc__']!r}")
        return cls(**{k: decode(x) for k, x in v.items() if k != "__dc__"})
    return {k: decode(x) for k, x in v.items()}


def get_state(f: Any) -> dict[str, Any]:
    """The state of the calibrator ``f`` (plain lists and numbers): its config, init and layout, then
    :data:`STATE_ATTRS` by :func:`encode`."""
    return {"schema": STATE_SCHEMA, "config": f.config.to_dict(),
            "init": f.init.to_dict() if f.init is not None else None,
            "names": list(f.names), "holds": list(f.lay.hold_slice),
            "x": f.x.tolist(), "P": f.P.tolist(),  # plain (n,), (n, n): what a reader checks first
            "state": {a: encode(getattr(f, a)) for a in STATE_ATTRS}}


def check_schema(d: Any) -> str:
    """The checkpoint's schema; ValueError naming it unless it is one this version reads."""
    schema = d.get("schema") if isinstance(d, dict) else None
    if schema not in (STATE_SCHEMA, SCHEMA_V4, SCHEMA_V3, SCHEMA_V2):
        raise ValueError(f"not a UKF state (schema {schema!r}, expected {STATE_SCHEMA}, {SCHEMA_V4}, {SCHEMA_V3} "
                         f"or {SCHEMA_V2})")
    return str(schema)


def set_state(f: Any, d: dict[str, Any]) -> None:
    """Restore the calibrator ``f`` from :func:`get_state` (its init and config are replaced); a
    checkpoint of schema /2 is read by its own mapping."""
    schema = check_schema(d)
    f.config = UKFConfig.from_dict(d["config"])
    f.init = Calibration.from_dict(d["init"]) if d["init"] is not None else None
    f._configure()
    f._set_layout(tuple(d["holds"]))
    if list(f.names) != list(d["names"]):
        raise ValueError("UKF state: its state names do not match its config")
    if schema == SCHEMA_V2:
        _set_state_v2(f, d)
        return
    st = d["state"]
    if not isinstance(st, dict):
        raise ValueError("UKF state: 'state' is not an object")
    optional = {STATE_SCHEMA: (), SCHEMA_V4: ATTRS_V5}.get(schema, ATTRS_V4 + ATTRS_V5)
    missing = [a for a in STATE_ATTRS if a not in st and a not in optional]
    if missing:
        raise ValueError(f"UKF state: {len(missing)} part(s) missing ({', '.join(missing[:4])})")
    f.x, f.P = np.asarray(d["x"], float).reshape(f.n), np.asarray(d["P"], float).reshape(f.n, f.n)
    for a in STATE_ATTRS:
        if a in st:
            setattr(f, a, decode(st[a]))
    check_parts(f)


def _is_real(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def check_parts(f: Any) -> None:
    """ValueError naming the field unless the divergence history and the disturbance gate of ``f`` are
    what the filter writes: a DivergenceLog of finite, non-decreasing log times; a MagDisturbanceGate of
    bools, counts ≥ 0 and times (``since``/``agreed_since`` NaN when unset, ``last_bad`` −inf when unset)."""
    div, gate = f._div, f._magd
    if type(div) is not DivergenceLog:
        raise ValueError(f"UKF state: the divergence history is a {type(div).__name__}, not a DivergenceLog")
    times = div.times
    if not isinstance(times, list) or not all(_is_real(t) and math.isfinite(t) for t in times):
        raise ValueError("UKF state: divergence times are not a list of finite numbers")
    if any(b < a for a, b in zip(times, times[1:], strict=False)):
        raise ValueError("UKF state: divergence times go backwards")
    div.times = [float(t) for t in times]
    if type(gate) is not MagDisturbanceGate:
        raise ValueError(f"UKF state: the disturbance gate is a {type(gate).__name__}, not a MagDisturbanceGate")
    for name in ("active", "armed"):
        if type(getattr(gate, name)) is not bool:
            raise ValueError(f"UKF state: disturbance gate field {name!r} is not true/false")
    for name in ("excluded", "stretches"):
        v = getattr(gate, name)
        if type(v) is not int or v < 0:
            raise ValueError(f"UKF state: disturbance gate field {name!r} is not a count")
    for name in ("since", "agreed_since", "last_bad"):
        v = getattr(gate, name)
        if not _is_real(v) or (name == "last_bad" and v == math.inf) or (name != "last_bad" and math.isinf(v)):
            raise ValueError(f"UKF state: disturbance gate field {name!r} is not a log time")
        setattr(gate, name, float(v))
    if gate.active and math.isnan(gate.since):
        raise ValueError("UKF state: disturbance gate active without its start time")
    check_learning(f)


def check_learning(f: Any) -> None:
    """ValueError naming the field unless ``f._learn`` is a :class:`.learning.Learning` of the filter's angle:
    a gate per learned sensor, each anchor None or three finite numbers, ``held`` two bools."""
    lrn = f._learn
    if type(lrn) is not Learning:
        raise ValueError(f"UKF state: the learning gates are a {type(lrn).__name__}, not a Learning")
    angle = math.radians(f.config.learn_angle_deg)
    if not isinstance(lrn.gates, dict) or sorted(lrn.gates) != sorted(LEARNED):
        raise ValueError("UKF state: the learning gates are not one per accelerometer and magnetometer")
    for s, g in lrn.gates.items():
        if type(g) is not LearningGate or not _is_real(g.angle) or float(g.angle) != angle:
            raise ValueError(f"UKF state: the {s} learning gate is not one of the config's angle")
        a = g.anchor
        if a is not None and not (isinstance(a, np.ndarray) and a.shape == (3,) and a.dtype.kind == "f"
                                  and np.isfinite(a).all()):
            raise ValueError(f"UKF state: the {s} learning gate's anchor is not three finite numbers")
    if not (isinstance(lrn.held, tuple) and len(lrn.held) == 2 and all(type(h) is bool for h in lrn.held)):
        raise ValueError("UKF state: the learning gates' 'held' is not two true/false values")
    lrn.angle = angle


def _set_state_v2(f: Any, d: dict[str, Any]) -> None:
    """Restore the calibrator ``f`` from a checkpoint of schema /2 (the hand-mapped keys of the parts)."""
    c = f.config
    f._hold_sigma = {k: float(v) for k, v in d["hold_sigma"].items()}
    f.x = np.asarray(d["x"], float)
    f.P = np.asarray(d["P"], float)
    f.R_nom = np.asarray(d["R_nom"], float)
    f.prior_sigma = np.asarray(d["prior_sigma"], float)
    f.prior_x = np.asarray(d["prior_x"], float)
    f._rate, f._L = d["rate"], int(d["L"])
    f._buf = SampleBuffer.from_dict(d)
    f._t_last = d["t_last"]
    f._w_last = np.asarray(d["w_last"], float)
    f._att_ok = bool(d["att_ok"])
    f._mag = MagStart(bool(d["mag_enabled"]), bool(d["dip_known"]),
                      MagCollector(np.asarray(d["mag_buf"], float).reshape(-1, 3), none_to_inf(d["mag_buf_next"])),
                      none_to_inf(d["mag_fit_next"]), bool(d["align_yaw_next"]), bool(d["yaw_free"]))
    f._next_trace = none_to_inf(d["next_trace"])
    f._n_imu, f._n_blocks = int(d["n_imu"]), int(d["n_blocks"])
    f._nis = NisMonitor(c.nis_window, c.nis_band_p, c.divergence_factor, c.divergence_windows)
    f._nis.stats = d["nis"]
    f._log.max_events = c.max_events
    f._log.events = list(d["events"])
    f._log.total = int(d["n_events"])
    f._trace = deque(d["trace"], maxlen=c.trace_max_rows)
    pm = d.get("prev_means")
    prev = None if pm is None else (*(None if v is None else np.asarray(v, float) for v in pm),)
    f._rest_det = RestDetector(prev, int(d.get("rest_count", 0)))
    f._lat = Lattice(d["q"], [list(v) for v in d["q_mag_buf"]])
    f._holds = HoldTracker({k: bool(v) for k, v in d["held"].items()})
    f._noise.ratio = {k: float(v) for k, v in d["noise_ratio"].items()}
    f._noise.high = {k: bool(v) for k, v in d["noise_high"].items()}
    f._rails = RailDetector({k: [float(x) for x in v] for k, v in d["rail"].items()},
                            {k: [(float(r[0]), int(r[1])) for r in v] for k, v in d["run"].items()},
                            {k: bool(v) for k, v in d["clip_on"].items()})
    f._T0 = d["T0"]
    f._vehicle = VehicleDetector.of(c)
    f._vehicle.set_state(d.get("vehicle", {}))
    f._coverage = MotionCoverage()
    f._coverage.set_state(d.get("coverage", {}))
    ra = d.get("rest_acc")
    f._rest_acc = None if ra is None else RestAccumulator.from_dict(ra)
