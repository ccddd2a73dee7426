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

import json
import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

SCHEMA = "onlinecal.calibration/1"
SENSORS = ("gyro", "accel", "mag")
UNITS = {"gyro": "rad/s", "accel": "m/s^2", "mag": "normalized"}
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
    """Scale matrix S = diag(s_x, s_y, s_z) (eq. 2). Shape (3, 3)."""
    return np.diag(np.asarray(scale, dtype=float))


def T_R(alpha: ArrayLike, exact: bool = True) -> Array:
    """Rotation to the body frame, T_R(alpha) (eqs. 3–5).

    Exact: Rz(alpha_z) @ Ry(alpha_y) @ Rx(alpha_x) (eqs. 3–4), valid for any angle.
    Small-angle (``exact=False``): I + [alpha]_x (eq. 5).
    ``alpha`` shape (3,) in rad; returns (3, 3).
    """
    a = np.asarray(alpha, dtype=float)
    if not exact:
        return np.eye(3) + skew(a)
    cx, cy, cz = np.cos(a)
    sx, sy, sz = np.sin(a)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def axes_matrix(xi: ArrayLike) -> Array:
    """Rows are the unit sensing axes in the orthogonal sensor frame (the inverse of T_N, eq. 6)."""
    xx, xy, xz = np.asarray(xi, dtype=float)
    return np.array(
        [
            [1.0, 0.0, 0.0],
            [math.sin(xz), math.cos(xz), 0.0],
            [-math.sin(xy), math.sin(xx) * math.cos(xy), math.cos(xx) * math.cos(xy)],
        ]
    )


def T_N(xi: ArrayLike, exact: bool = True) -> Array:
    """Non-orthogonality correction T_N(xi) (eq. 6). ``xi`` shape (3,) in rad; returns (3, 3).

    Exact: inverse of :func:`axes_matrix` (lower triangular). Small-angle:
    ``[[1,0,0],[-xi_z,1,0],[xi_y,-xi_x,1]]``.
    """
    x = np.asarray(xi, dtype=float)
    if not exact:
        return np.array([[1.0, 0, 0], [-x[2], 1.0, 0], [x[1], -x[0], 1.0]])
    return np.linalg.inv(axes_matrix(x))


def compose(scale: ArrayLike, alpha: ArrayLike, xi: ArrayLike, exact: bool = True) -> Array:
    """Full correction matrix S · T_R(alpha) · T_N(xi) (eq. 1). Returns (3, 3)."""
    return S_matrix(scale) @ T_R(alpha, exact) @ T_N(xi, exact)


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

    sol = least_squares(resid, x0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    p = sol.x
    return p[:3].copy(), p[3:6].copy(), p[6:].copy()


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
    sigma: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "bias", _as_vec(self.bias, "bias"))
        m = np.array(self.matrix, dtype=float)
        if m.shape != (3, 3) or not np.all(np.isfinite(m)):
            raise ValueError("matrix must be a finite 3x3 array")
        m.setflags(write=False)
        object.__setattr__(self, "matrix", m)
        sig = {k: np.array(v, dtype=float) for k, v in dict(self.sigma).items()}
        object.__setattr__(self, "sigma", sig)

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
        sigma: dict[str, Any] | None = None,
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
        return SensorCalibration(-self.matrix @ self.bias, np.linalg.inv(self.matrix))

    def with_sigma(self, sigma: dict[str, Any]) -> SensorCalibration:
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
    """A whole IMU's calibration (gyro, accel, mag), as in the contract's calibration JSON."""

    gyro: SensorCalibration | None = None
    accel: SensorCalibration | None = None
    mag: SensorCalibration | None = None
    source: str = "batch"
    extensions: dict[str, Any] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    def sensor(self, name: str) -> SensorCalibration | None:
        return {"gyro": self.gyro, "accel": self.accel, "mag": self.mag}[name]

    def replace(self, **kw: Any) -> Calibration:
        d = {
            "gyro": self.gyro,
            "accel": self.accel,
            "mag": self.mag,
            "source": self.source,
            "extensions": self.extensions,
            "meta": self.meta,
        }
        d.update(kw)
        return Calibration(**d)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"schema": SCHEMA, "source": self.source}
        for s in SENSORS:
            c = self.sensor(s)
            if c is not None:
                out[s] = c.to_dict()
        out["extensions"] = self.extensions
        out["units"] = dict(UNITS)
        if self.meta:
            out["meta"] = self.meta
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Calibration:
        if d.get("schema") != SCHEMA:
            raise ValueError(f"schema is {d.get('schema')!r}, expected {SCHEMA!r}")
        kw = {s: SensorCalibration.from_dict(d[s]) for s in SENSORS if d.get(s)}
        return cls(
            source=d.get("source", "batch"),
            extensions=d.get("extensions", {}) or {},
            meta=d.get("meta", {}) or {},
            **kw,
        )

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
        )
