"""The sensor error model of Zhang, Höflinger & Reindl (2014), eqs. 1–10.

One place owns the model; the batch pipeline, the simulator and the UKF all use it.

Per sensor (gyroscope, accelerometer, magnetometer)::

    calibrated = S · T_R(alpha) · T_N(xi) · (raw − o)          (eq. 1, with eqs. 2–6)

* ``o`` (3,)        bias, in the sensor's input unit;
* ``S`` = diag(s)   scale factors (eq. 2);
* ``T_R(alpha)``    rotation from the (orthogonalised) sensor frame to the body frame B (eqs. 3–5),
                    exact form ``Rz(alpha_z) Ry(alpha_y) Rx(alpha_x)``; for small angles
                    ``I + [alpha]_x`` (eq. 5);
* ``T_N(xi)``       non-orthogonality (eq. 6): the inverse of the matrix whose rows are the unit sensing
                    axes expressed in an orthogonal frame whose x axis is the sensor's x axis and whose
                    xy plane holds the sensor's y axis.  ``xi_z`` tilts the y axis towards x, ``xi_y`` and
                    ``xi_x`` tilt the z axis towards -x and y.  Small-angle form
                    ``[[1,0,0],[-xi_z,1,0],[xi_y,-xi_x,1]]``.

``matrix = S · T_R · T_N`` is the full correction; the outward convention is
``calibrated = matrix @ (raw − bias)`` (contract). Every 3×3 matrix with positive determinant has
exactly one such decomposition near the identity; :func:`decompose` finds it.

Angles are radians throughout.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np
from numpy.typing import ArrayLike, NDArray

SCHEMA = "onlinecal.calibration/2"
SCHEMAS_READ = (SCHEMA, "onlinecal.calibration/1")  # /1: no gauge, raw_units or health (migrated on load)
SENSORS = ("gyro", "accel", "mag")
UNITS = {"gyro": "rad/s", "accel": "m/s^2", "mag": "normalized"}  # calibrated (output) units
# raw (input) units the biases are in: the readers' conventions (gyro and accel converted by the format;
# the mag as the format delivers it — gauss for .tlog and .bin, the file's own unit for CSV)
RAW_UNITS = {"gyro": "rad/s", "accel": "m/s^2", "mag": "as read"}
# which frame B the calibration's alphas are relative to (eqs. 3–5; B is not observable from the data):
# "accel" the accelerometer's frame, "gyro" the gyro's, "gyro_phases" the platform's rotation axes as the gyro
# measured them (the batch's phase method, eqs. 28–31), "mag" the magnetometer's, "vehicle" a frame given
# from outside (mounting); None: not fixed
Gauge = Literal["accel", "gyro", "gyro_phases", "mag", "vehicle"]
GAUGES: tuple[str, ...] = get_args(Gauge)
PARAMS = ("bias", "scale", "alpha", "xi")

Array = NDArray[np.float64]


def skew(v: ArrayLike) -> Array:
    """Cross-product matrix [v]_x, shape (..., 3, 3) for v of shape (..., 3)."""
    v = np.asarray(v, dtype=float)
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def S_matrix(scale: ArrayLike) -> Array:
    """Scale matrix S = diag(s_x, s_y, s_z) (eq. 2): scale (..., 3) → (..., 3, 3)."""
    s = np.asarray(scale, dtype=float)
    out: Array = s[..., :, None] * np.eye(3)
    return out


def T_R(alpha: ArrayLike, exact: bool = True) -> Array:
    """Rotation to the body frame, T_R(alpha) (eqs. 3–5): alpha (..., 3) rad → (..., 3, 3).

    Exact: Rz(alpha_z) @ Ry(alpha_y) @ Rx(alpha_x) (eqs. 3–4), valid for any angle, multiplied out
    (one closed form for any number of leading axes: the UKF evaluates it for all sigma points at once).
    Small-angle (``exact=False``): I + [alpha]_x (eq. 5).
    """
    a = np.asarray(alpha, dtype=float)
    if not exact:
        out: Array = np.eye(3) + skew(a)
        return out
    cf, sf = np.cos(a[..., 0]), np.sin(a[..., 0])
    ct, st = np.cos(a[..., 1]), np.sin(a[..., 1])
    cp, sp = np.cos(a[..., 2]), np.sin(a[..., 2])
    R = np.empty(a.shape[:-1] + (3, 3))
    R[..., 0, 0] = cp * ct
    R[..., 0, 1] = cp * st * sf - sp * cf
    R[..., 0, 2] = cp * st * cf + sp * sf
    R[..., 1, 0] = sp * ct
    R[..., 1, 1] = sp * st * sf + cp * cf
    R[..., 1, 2] = sp * st * cf - cp * sf
    R[..., 2, 0] = -st
    R[..., 2, 1] = ct * sf
    R[..., 2, 2] = ct * cf
    return R


def _axes_and_inverse(xi: ArrayLike) -> tuple[Array, Array]:
    """Eq. 6: A (rows = unit sensing axes) and T_N = A⁻¹ for xi (..., 3); both (..., 3, 3).

    A = [[1, 0, 0], [b, c, 0], [d, e, f]] with b = sin ξz, c = cos ξz, d = −sin ξy, e = sin ξx cos ξy,
    f = cos ξx cos ξy; its inverse is written out (lower triangular), no matrix inversion.
    """
    x = np.asarray(xi, dtype=float)
    sx, sy, sz = np.sin(x[..., 0]), np.sin(x[..., 1]), np.sin(x[..., 2])
    cx, cy, cz = np.cos(x[..., 0]), np.cos(x[..., 1]), np.cos(x[..., 2])
    b, c, d, e, f = sz, cz, -sy, sx * cy, cx * cy
    A = np.zeros(x.shape[:-1] + (3, 3))
    A[..., 0, 0] = 1.0
    A[..., 1, 0], A[..., 1, 1] = b, c
    A[..., 2, 0], A[..., 2, 1], A[..., 2, 2] = d, e, f
    Ai = np.zeros(x.shape[:-1] + (3, 3))
    Ai[..., 0, 0] = 1.0
    Ai[..., 1, 0], Ai[..., 1, 1] = -b / c, 1.0 / c
    Ai[..., 2, 0], Ai[..., 2, 1], Ai[..., 2, 2] = (b * e - c * d) / (c * f), -e / (c * f), 1.0 / f
    return A, Ai


def axes_matrix(xi: ArrayLike) -> Array:
    """Rows are the unit sensing axes in the orthogonal sensor frame (the inverse of T_N, eq. 6):
    xi (..., 3) → (..., 3, 3)."""
    return _axes_and_inverse(xi)[0]


def T_N(xi: ArrayLike, exact: bool = True) -> Array:
    """Non-orthogonality correction T_N(xi) (eq. 6): xi (..., 3) rad → (..., 3, 3).

    Exact: inverse of :func:`axes_matrix` (lower triangular, written out). Small-angle:
    ``[[1,0,0],[-xi_z,1,0],[xi_y,-xi_x,1]]``.
    """
    x = np.asarray(xi, dtype=float)
    if not exact:
        out = np.zeros(x.shape[:-1] + (3, 3))
        out[..., 0, 0] = out[..., 1, 1] = out[..., 2, 2] = 1.0
        out[..., 1, 0], out[..., 2, 0], out[..., 2, 1] = -x[..., 2], x[..., 1], -x[..., 0]
        return out
    return _axes_and_inverse(x)[1]


def compose(scale: ArrayLike, alpha: ArrayLike, xi: ArrayLike, exact: bool = True) -> Array:
    """Full correction matrix S · T_R(alpha) · T_N(xi) (eq. 1): each argument (..., 3) → (..., 3, 3)."""
    s = np.asarray(scale, dtype=float)
    out: Array = s[..., :, None] * (T_R(alpha, exact) @ T_N(xi, exact))
    return out


def model_matrices(p: ArrayLike) -> tuple[Array, Array, Array]:
    """The correction and the sensor model at once from the paper's 12 parameters (eqs. 1–6).

    p (..., 12) = (o, s, alpha, xi). Returns o (..., 3), M = S·T_R·T_N and M⁻¹ = A·T_Rᵀ·diag(1/s)
    (..., 3, 3) each (T_N⁻¹ = A, the axes matrix): ``calibrated = M (raw − o)``, ``raw = M⁻¹ c + o``,
    with one T_R and one axes matrix and no matrix inversion.
    """
    q = np.asarray(p, dtype=float)
    o, s, a, xi = q[..., 0:3], q[..., 3:6], q[..., 6:9], q[..., 9:12]
    TR = T_R(a)
    A, TN = _axes_and_inverse(xi)
    return o, s[..., :, None] * (TR @ TN), (A @ np.swapaxes(TR, -1, -2)) / s[..., None, :]


def _euler_zyx(R: Array) -> Array:
    """Angles (alpha_x, alpha_y, alpha_z) with R = Rz Ry Rx."""
    ay = -math.asin(max(-1.0, min(1.0, R[2, 0])))
    ax = math.atan2(R[2, 1], R[2, 2])
    az = math.atan2(R[1, 0], R[0, 0])
    return np.array([ax, ay, az])


def decompose(matrix: ArrayLike) -> tuple[Array, Array, Array]:
    """Split a correction matrix into (scale, alpha, xi) with matrix = S T_R(alpha) T_N(xi), exact forms.

    Inverse of :func:`compose` (eqs. 2–6). A matrix with negative determinant (an axis whose sign is
    inverted) gets a negative scale on that axis. The start point comes from the polar decomposition, so
    large rotations (a sensor mounted at 90°) decompose as well as small ones; the 9 equations in
    9 unknowns are then solved to machine precision by Gauss–Newton (scipy least_squares).
    """
    M = np.asarray(matrix, dtype=float)
    if M.shape != (3, 3) or not np.all(np.isfinite(M)):
        raise ValueError("matrix must be a finite 3x3 array")
    det = np.linalg.det(M)
    if det == 0:
        raise ValueError("matrix is singular")
    if det < 0:
        # An inverted axis (mounting or driver error): a negative scale on the axis whose flip leaves
        # the smallest rotation.
        best = None
        for k in range(3):
            F = np.eye(3)
            F[k, k] = -1.0
            s, a, x = decompose(F @ M)
            if best is None or np.linalg.norm(a) < np.linalg.norm(best[1]):
                s = s.copy()
                s[k] = -s[k]
                best = (s, a, x)
        assert best is not None
        return best
    U, _, Vt = np.linalg.svd(M)
    R0 = U @ Vt
    x0 = np.concatenate([np.linalg.norm(M, axis=1), _euler_zyx(R0), np.zeros(3)])

    def resid(p: Array) -> Array:
        return (compose(p[:3], p[3:6], p[6:]) - M).ravel()

    from scipy.optimize import least_squares  # lazily: ~0.3 s of every CLI start-up otherwise

    sol = least_squares(resid, x0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    p = sol.x
    return p[:3].copy(), p[3:6].copy(), p[6:].copy()


class FrozenDict(dict[str, Any]):
    """A dict that refuses every change (a calibration's meta, sigma, extensions). Still a ``dict`` (JSON,
    ``isinstance`` checks and equality work as before); pickles and copies as itself."""

    def _immutable(self, *a: Any, **k: Any) -> None:
        raise TypeError("calibration data are immutable: build a new one with replace()")

    __setitem__ = __delitem__ = clear = pop = popitem = setdefault = update = _immutable  # type: ignore[assignment]
    __ior__ = _immutable  # type: ignore[assignment]

    def __reduce__(self) -> tuple[Any, ...]:
        return (FrozenDict, (dict(self),))

    def __hash__(self) -> int:  # type: ignore[override]
        return id(self)


class FrozenList(list[Any]):
    """A list that refuses every change (see :class:`FrozenDict`)."""

    def _immutable(self, *a: Any, **k: Any) -> None:
        raise TypeError("calibration data are immutable: build a new one with replace()")

    __setitem__ = __delitem__ = append = extend = insert = pop = remove = clear = sort = reverse = _immutable
    __iadd__ = __imul__ = _immutable  # type: ignore[assignment]

    def __reduce__(self) -> tuple[Any, ...]:
        return (FrozenList, (list(self),))

    def __hash__(self) -> int:  # type: ignore[override]
        return id(self)


def freeze(v: Any) -> Any:
    """Deep immutable copy: mappings → :class:`FrozenDict`, lists/tuples → :class:`FrozenList`, arrays →
    read-only copies; other values as they are."""
    if isinstance(v, Mapping):
        return FrozenDict({k: freeze(x) for k, x in v.items()})
    if isinstance(v, (list, tuple)):
        return FrozenList(freeze(x) for x in v)
    if isinstance(v, np.ndarray):
        a = v.copy()
        a.setflags(write=False)
        return a
    return v


def thaw(v: Any) -> Any:
    """Plain, mutable, JSON-able copy of a :func:`freeze`-d value (arrays → lists)."""
    if isinstance(v, Mapping):
        return {k: thaw(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [thaw(x) for x in v]
    if isinstance(v, np.ndarray):
        return v.tolist()
    return v


def _as_vec(x: ArrayLike, name: str) -> Array:
    a = np.array(x, dtype=float).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be 3 finite numbers")
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class SensorCalibration:
    """One sensor's calibration: ``calibrated = matrix @ (raw − bias)``.

    Immutable value object. ``bias`` (3,) in the raw unit; ``matrix`` (3, 3); ``sigma`` maps a
    parameter name (``bias``, ``scale``, ``alpha``, ``xi``, ``matrix``) to its 1σ, where known.
    ``scale``, ``alpha`` and ``xi`` are the paper's decomposition (eqs. 2–6) of ``matrix``.
    """

    bias: Array
    matrix: Array
    sigma: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "bias", _as_vec(self.bias, "bias"))
        m = np.array(self.matrix, dtype=float)
        if m.shape != (3, 3) or not np.all(np.isfinite(m)):
            raise ValueError("matrix must be a finite 3x3 array")
        m.setflags(write=False)
        object.__setattr__(self, "matrix", m)
        sig = {}
        for k, v in dict(self.sigma).items():
            a = np.array(v, dtype=float)
            a.setflags(write=False)
            sig[k] = a
        object.__setattr__(self, "sigma", FrozenDict(sig))

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def identity(cls) -> SensorCalibration:
        return cls(np.zeros(3), np.eye(3))

    @classmethod
    def from_params(
        cls,
        bias: ArrayLike = (0, 0, 0),
        scale: ArrayLike = (1, 1, 1),
        alpha: ArrayLike = (0, 0, 0),
        xi: ArrayLike = (0, 0, 0),
        exact: bool = True,
        sigma: Mapping[str, Any] | None = None,
    ) -> SensorCalibration:
        """Build from the paper's parameters (eq. 1)."""
        return cls(np.asarray(bias, float), compose(scale, alpha, xi, exact), sigma or {})

    # -- decomposition ------------------------------------------------------------------------
    @cached_property
    def _params(self) -> tuple[Array, Array, Array]:
        return decompose(self.matrix)

    @property
    def scale(self) -> Array:
        return self._params[0]

    @property
    def alpha(self) -> Array:
        return self._params[1]

    @property
    def xi(self) -> Array:
        return self._params[2]

    def params(self) -> dict[str, Array]:
        """All parameters as a dict of (3,) arrays: bias, scale, alpha, xi."""
        return {"bias": self.bias, "scale": self.scale, "alpha": self.alpha, "xi": self.xi}

    # -- use ----------------------------------------------------------------------------------
    def apply(self, raw: ArrayLike) -> Array:
        """Calibrate: ``matrix @ (raw − bias)`` for raw of shape (..., 3)."""
        return (np.asarray(raw, dtype=float) - self.bias) @ self.matrix.T

    def inv(self) -> SensorCalibration:
        """The sensor model itself: the map calibrated → raw, ``raw = M⁻¹ c + o``.

        It is again of the form ``M' (c − o')`` with ``M' = M⁻¹`` and ``o' = −M o``.
        """
        return SensorCalibration(-self.matrix @ self.bias, np.asarray(np.linalg.inv(self.matrix), float))

    def with_sigma(self, sigma: Mapping[str, Any]) -> SensorCalibration:
        return SensorCalibration(self.bias, self.matrix, sigma)

    def matrix_rel_error(self, other: SensorCalibration) -> float:
        """‖M − M_other‖_F / ‖M_other‖_F."""
        return float(np.linalg.norm(self.matrix - other.matrix) / np.linalg.norm(other.matrix))

    # -- serialisation ------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "bias": self.bias.tolist(),
            "matrix": self.matrix.tolist(),
            "scale": self.scale.tolist(),
            "alpha": self.alpha.tolist(),
            "xi": self.xi.tolist(),
            "sigma": {k: np.asarray(v).tolist() for k, v in self.sigma.items()},
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SensorCalibration:
        """Inverse of :meth:`to_dict`; ``matrix`` and ``bias`` are authoritative."""
        if "matrix" in d:
            m = d["matrix"]
        else:
            m = compose(d.get("scale", (1, 1, 1)), d.get("alpha", (0, 0, 0)), d.get("xi", (0, 0, 0)))
        return cls(d["bias"], m, d.get("sigma", {}) or {})

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, SensorCalibration):
            return NotImplemented
        return (
            np.array_equal(self.bias, other.bias)
            and np.array_equal(self.matrix, other.matrix)
            and self.sigma.keys() == other.sigma.keys()
            and all(np.array_equal(self.sigma[k], other.sigma[k]) for k in self.sigma)
        )

    def __repr__(self) -> str:
        return (
            f"SensorCalibration(bias={np.round(self.bias, 6).tolist()}, "
            f"scale={np.round(self.scale, 6).tolist()}, alpha={np.round(self.alpha, 6).tolist()}, "
            f"xi={np.round(self.xi, 6).tolist()})"
        )


@dataclass(frozen=True, eq=False)
class Calibration:
    """A whole IMU's calibration (gyro, accel, mag), as in the contract's calibration JSON.

    An immutable value: ``extensions``, ``meta`` and ``health`` are deep-frozen on construction
    (:func:`freeze`), changes go through :meth:`replace`. ``gauge`` (:data:`Gauge`) says which frame B the
    alphas are relative to — set by whoever fixed it (the batch: its method; the UKF: its consider states),
    read by the UKF to decide which terms to hold. ``raw_units``: the units of the raw readings the biases are
    in. ``health``: the filter's health summary, optional (filled by ``onlinecal run``/``replay``).
    """

    gyro: SensorCalibration | None = None
    accel: SensorCalibration | None = None
    mag: SensorCalibration | None = None
    source: str = "batch"
    extensions: Mapping[str, Any] = field(default_factory=dict)
    meta: Mapping[str, Any] = field(default_factory=dict)
    gauge: Gauge | None = None
    raw_units: Mapping[str, str] = field(default_factory=lambda: dict(RAW_UNITS))
    health: Mapping[str, Any] | None = None

    def __post_init__(self) -> None:
        if self.gauge is not None and self.gauge not in GAUGES:
            raise ValueError(f"gauge {self.gauge!r} is not one of {', '.join(GAUGES)}")
        object.__setattr__(self, "extensions", freeze(self.extensions or {}))
        object.__setattr__(self, "meta", freeze(self.meta or {}))
        object.__setattr__(self, "raw_units", freeze(self.raw_units or RAW_UNITS))
        object.__setattr__(self, "health", None if self.health is None else freeze(self.health))

    def sensor(self, name: str) -> SensorCalibration | None:
        return {"gyro": self.gyro, "accel": self.accel, "mag": self.mag}[name]

    def replace(self, **kw: Any) -> Calibration:
        return dataclasses.replace(self, **kw)

    def to_dict(self) -> dict[str, Any]:
        """The contract's JSON object (schema /2): plain, mutable copies of every field."""
        out: dict[str, Any] = {"schema": SCHEMA, "source": self.source}
        for s in SENSORS:
            c = self.sensor(s)
            if c is not None:
                out[s] = c.to_dict()
        out["extensions"] = thaw(self.extensions)
        out["units"] = dict(UNITS)
        out["raw_units"] = thaw(self.raw_units)
        out["gauge"] = self.gauge
        if self.health is not None:
            out["health"] = thaw(self.health)
        if self.meta:
            out["meta"] = thaw(self.meta)
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Calibration:
        """Inverse of :meth:`to_dict`; reads schema /2 and /1 (:data:`SCHEMAS_READ`)."""
        if d.get("schema") not in SCHEMAS_READ:
            raise ValueError(f"schema is {d.get('schema')!r}, expected one of {', '.join(SCHEMAS_READ)}")
        sens = {s: SensorCalibration.from_dict(d[s]) if d.get(s) else None for s in SENSORS}
        meta = d.get("meta", {}) or {}
        gauge = d.get("gauge") if d["schema"] == SCHEMA else _gauge_of_v1(meta)
        return cls(sens["gyro"], sens["accel"], sens["mag"], source=d.get("source", "batch"),
                   extensions=d.get("extensions", {}) or {}, meta=meta, gauge=gauge,
                   raw_units=d.get("raw_units") or RAW_UNITS, health=d.get("health"))

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_json(cls, text: str) -> Calibration:
        return cls.from_dict(json.loads(text))

    def save(self, path: str | Path) -> None:
        """Write atomically (temp file then rename) so a crash never leaves half a calibration."""
        from .files import atomic_write, dumps  # the package's one writer and strict-JSON sanitiser

        atomic_write(path, dumps(self.to_dict()) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        return cls.from_json(Path(path).read_text())

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Calibration):
            return NotImplemented
        return (
            self.gyro == other.gyro
            and self.accel == other.accel
            and self.mag == other.mag
            and self.source == other.source
            and self.extensions == other.extensions
            and self.gauge == other.gauge
            and self.raw_units == other.raw_units
            and self.health == other.health
        )


def _gauge_of_v1(meta: Mapping[str, Any]) -> Gauge | None:
    """Migration of a schema /1 file, which had no gauge field: a batch result whose gyro came from its
    rotation phases defined B by them ("gyro_phases"); otherwise unknown (None). Only for /1 files — /2
    files carry the field, and nothing else reads the report's wording."""
    try:
        method = meta["batch"]["steps"]["gyro"]["figures"]["method"]
    except (KeyError, TypeError):
        return None
    return "gyro_phases" if isinstance(method, str) and method.startswith("phases") else None
