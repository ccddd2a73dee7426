"""Validated loading of calibration JSON files (``onlinecal.calibration/1``), the simulator's truth files
(``onlinecal.truth/1``, whose ``calibration`` key is one) and onboard parameter files (.parm/.params).

Every problem becomes a :class:`CalFileError` whose message names the file and the field
(``cal.json: gyro.matrix: singular (det 0)``), never a traceback: a list, a string or null where an object
belongs, duplicate keys, non-finite numbers, matrices of the wrong shape or singular, σ of the wrong shape
or negative, biases beyond any sensor's range, a directory, a file that is not UTF-8 text.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from .model import SCHEMA, SCHEMAS_READ, SENSORS, Calibration

TRUTH_SCHEMA = "onlinecal.truth/1"
# Schemas this reader accepts for a calibration (the /2 of the typed health field reads the same keys).
CAL_SCHEMAS = SCHEMAS_READ
MAX_BYTES = 64 * 1024 * 1024  # a calibration is a few kB; anything this large is not one
# Largest |bias| any sensor's raw unit can hold plausibly (rad/s, m/s², gauss or a CSV's fixed unit such as
# µT or counts): beyond it the number is junk, and a filter started from it never converges.
BIAS_LIMIT = {"gyro": 100.0, "accel": 1000.0, "mag": 1e6}
# |det matrix| outside this range: a scale of 1e-4 … 1e4 on every axis; beyond, the matrix is degenerate.
DET_RANGE = (1e-12, 1e12)
SIGMA_KEYS = {"bias": (3,), "scale": (3,), "alpha": (3,), "xi": (3,), "matrix": (3, 3)}


class CalFileError(ValueError):
    """A calibration, truth, checkpoint or parameter file that cannot be used (message names file and field)."""


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    keys = [k for k, _ in pairs]
    dup = sorted({k for k in keys if keys.count(k) > 1})
    if dup:
        raise _Dup(dup[0])
    return dict(pairs)


class _Dup(ValueError):
    pass


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not a JSON number")


def read_json(path: str | Path) -> Any:
    """Parse a JSON file strictly (no duplicate keys, no NaN/Infinity) or raise :class:`CalFileError`."""
    p = Path(path)
    if p.is_dir():
        raise CalFileError(f"{path}: is a directory, not a JSON file")
    if not p.exists():
        raise CalFileError(f"{path}: no such file")
    if not p.is_file():
        raise CalFileError(f"{path}: not a regular file")
    try:
        size = p.stat().st_size
        if size > MAX_BYTES:
            raise CalFileError(f"{path}: {size} bytes is far too large for a calibration JSON")
        text = p.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise CalFileError(f"{path}: not a calibration JSON (not UTF-8 text at byte {e.start})") from None
    except OSError as e:
        raise CalFileError(f"{path}: cannot read ({e.strerror or e})") from None
    try:
        return json.loads(text, object_pairs_hook=_no_duplicates, parse_constant=_reject_constant)
    except _Dup as e:
        raise CalFileError(f"{path}: duplicate key {e.args[0]!r}") from None
    except json.JSONDecodeError as e:
        raise CalFileError(f"{path}: not a calibration JSON (invalid JSON: {e.msg} at line {e.lineno} "
                           f"column {e.colno})") from None
    except (ValueError, RecursionError) as e:
        raise CalFileError(f"{path}: not a calibration JSON (invalid JSON: {e})") from None


def _array(path: str, field: str, v: Any, shape: tuple[int, ...], unknown_ok: bool = False) -> np.ndarray:
    """``v`` as a float array of ``shape``, every entry finite (``unknown_ok``: a JSON null, an unknown σ
    as strict JSON writes NaN, reads as NaN)."""
    if unknown_ok and isinstance(v, list):
        v = [(math.nan if x is None else [math.nan if y is None else y for y in x] if isinstance(x, list) else x)
             for x in v]
    try:
        a = np.array(v, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise CalFileError(f"{path}: {field}: expected {_shape_words(shape)}, got {_short(v)}") from None
    if a.shape != shape:
        raise CalFileError(f"{path}: {field}: expected {_shape_words(shape)}, got shape {a.shape}")
    if not np.all(np.isfinite(a) | (unknown_ok & np.isnan(a))):
        raise CalFileError(f"{path}: {field}: holds a non-finite number")
    return a


def _shape_words(shape: tuple[int, ...]) -> str:
    return "3 numbers" if shape == (3,) else "a 3×3 array of numbers"


def _short(v: Any) -> str:
    t = json.dumps(v) if not isinstance(v, float) or math.isfinite(v) else str(v)
    return t if len(t) <= 40 else t[:37] + "..."


def validate_sensor(path: str, s: str, d: Any) -> dict[str, Any]:
    """Check one sensor's object (bias, matrix or scale/alpha/xi, sigma); returns it cleaned."""
    if not isinstance(d, dict):
        raise CalFileError(f"{path}: {s}: expected an object, got {_short(d)}")
    if "bias" not in d:
        raise CalFileError(f"{path}: {s}.bias: missing")
    bias = _array(path, f"{s}.bias", d["bias"], (3,))
    if np.abs(bias).max() > BIAS_LIMIT[s]:
        raise CalFileError(f"{path}: {s}.bias: {np.abs(bias).max():.3g} is beyond any {s}'s range "
                           f"(|bias| ≤ {BIAS_LIMIT[s]:g})")
    out: dict[str, Any] = {"bias": bias.tolist()}
    if "matrix" in d:
        M = _array(path, f"{s}.matrix", d["matrix"], (3, 3))
    else:
        from .model import compose

        parts = {k: _array(path, f"{s}.{k}", d.get(k, dflt), (3,))
                 for k, dflt in (("scale", (1, 1, 1)), ("alpha", (0, 0, 0)), ("xi", (0, 0, 0)))}
        M = compose(parts["scale"], parts["alpha"], parts["xi"])
    det = abs(float(np.linalg.det(M)))
    if not DET_RANGE[0] <= det <= DET_RANGE[1]:
        raise CalFileError(f"{path}: {s}.matrix: singular or degenerate (|det| {det:.3g})")
    if np.linalg.cond(M) > 1e6:
        raise CalFileError(f"{path}: {s}.matrix: nearly singular (condition number {np.linalg.cond(M):.3g})")
    out["matrix"] = M.tolist()
    sig = d.get("sigma", {})
    if sig is None:
        sig = {}
    if not isinstance(sig, dict):
        raise CalFileError(f"{path}: {s}.sigma: expected an object, got {_short(sig)}")
    clean = {}
    for k, v in sig.items():
        if k not in SIGMA_KEYS:
            continue  # σ of a derived figure this version does not use: ignored, as the contract allows
        a = _array(path, f"{s}.sigma.{k}", v, SIGMA_KEYS[k], unknown_ok=True)
        if np.any(a < 0):
            raise CalFileError(f"{path}: {s}.sigma.{k}: negative σ")
        clean[k] = a.tolist()
    out["sigma"] = clean
    return out


def calibration_from_obj(obj: Any, path: str = "calibration") -> Calibration:
    """A :class:`Calibration` from a parsed calibration or truth JSON, validated (see the module doc)."""
    if not isinstance(obj, dict):
        raise CalFileError(f"{path}: not a calibration JSON (expected a JSON object, got {_short(obj)})")
    if obj.get("schema") == TRUTH_SCHEMA:  # the simulator's truth file: its calibration is the truth
        inner = obj.get("calibration")
        if not isinstance(inner, dict):
            raise CalFileError(f"{path}: calibration: missing in the truth file")
        return calibration_from_obj(inner, path)
    schema = obj.get("schema")
    if schema not in CAL_SCHEMAS:
        raise CalFileError(f"{path}: not a calibration JSON (schema {_short(schema)}, expected {SCHEMA!r} "
                           f"or a {TRUTH_SCHEMA!r} file)")
    sensors = {s: validate_sensor(path, s, obj[s]) for s in SENSORS if obj.get(s) is not None}
    if not sensors:
        raise CalFileError(f"{path}: holds no sensor (gyro, accel or mag)")
    for key, typ in (("extensions", dict), ("meta", dict), ("source", str)):
        if key in obj and obj[key] is not None and not isinstance(obj[key], typ):
            raise CalFileError(f"{path}: {key}: expected {'an object' if typ is dict else 'a string'}, "
                               f"got {_short(obj[key])}")
    if obj.get("extensions"):
        from .extensions import validate_extensions

        try:
            validate_extensions(obj["extensions"])
        except (ValueError, TypeError, KeyError) as e:
            raise CalFileError(f"{path}: extensions: {e}") from None
    d = {**obj, **sensors}  # the schema as read: /1 is migrated by Calibration.from_dict
    meta = obj.get("meta")
    if obj.get("health") is None and isinstance(meta, dict) and isinstance(meta.get("health"), dict):
        d["health"] = meta["health"]  # an older file kept the verdict in meta: it becomes the typed field
    try:
        return Calibration.from_dict(d)
    except (ValueError, TypeError, KeyError) as e:  # pragma: no cover - the checks above come first
        raise CalFileError(f"{path}: {e}") from None


def load_calibration(path: str | Path) -> Calibration:
    """Read and validate a calibration JSON (or a simulator truth file) at ``path``."""
    return calibration_from_obj(read_json(path), str(path))


_PARM_LINE = re.compile(r"^\s*([A-Za-z][A-Za-z0-9_]{0,31})[\s,]+([-+0-9.eE]+)\s*$")


def load_onboard_params(path: str | Path) -> dict[str, float]:
    """Parameters from an ArduPilot ``.parm`` (``NAME VALUE`` or ``NAME,VALUE``) or a QGroundControl
    ``.params`` file (``vehicle<TAB>component<TAB>NAME<TAB>VALUE<TAB>type``); ``#`` lines are comments.

    Raises :class:`CalFileError` naming the file and the line for a line that is neither."""
    p = Path(path)
    if p.is_dir() or not p.is_file():
        raise CalFileError(f"{path}: {'is a directory' if p.is_dir() else 'no such file'}")
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise CalFileError(f"{path}: cannot read as text ({e})") from None
    out: dict[str, float] = {}
    for i, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        f = s.split("\t")
        if len(f) == 5:
            name, val = f[2], f[3]
        else:
            m = _PARM_LINE.match(s)
            if not m:
                raise CalFileError(f"{path}: line {i}: not 'NAME VALUE' nor a QGroundControl .params row")
            name, val = m.group(1), m.group(2)
        try:
            x = float(val)
        except ValueError:
            raise CalFileError(f"{path}: line {i}: {name}: {val!r} is not a number") from None
        if not math.isfinite(x):
            raise CalFileError(f"{path}: line {i}: {name}: not a finite number")
        out[name] = x
    if not out:
        raise CalFileError(f"{path}: holds no parameter")
    return out
