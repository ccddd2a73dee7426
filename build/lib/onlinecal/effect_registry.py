"""The effect vocabulary in one place: what each effect of the contract is, which sensors it may act on, how
the simulator makes it, how an extension undoes it, which UKF state carries it and whether a live run can
apply it block by block.

The simulator (``sim/effects.py``), the extensions (:mod:`onlinecal.extensions`), live/replay
(:mod:`onlinecal.apply_ext`) and ``diagnose`` read this table instead of keeping their own lists. It imports
nothing from the package, so every layer (production and simulator) may import it; the simulator consumes
it, never the reverse. Besides the table: the keys of each effect's spec with their defaults
(:data:`EFFECT_KEYS`, the contract's effect table) and the forward models production needs to undo an
effect (:func:`lever_arm_acceleration`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
AXES: tuple[str, ...] = ("x", "y", "z")


@dataclass(frozen=True)
class EffectInfo:
    """One effect of the vocabulary.

    ``sensors``: the sensors it may act on (first = default); ``required``: extension keys that must be given
    (a missing coefficient must not silently become the simulator's default); ``forward``: the simulator's
    class (in ``sim/effects.py``); ``inverse``: how :func:`onlinecal.extensions.correct` undoes it
    ("pointwise", "resample", "none" — not removable from the data); ``ukf_state``: the UKF extension state
    that can estimate it instead (``sensor`` → state name), if any; ``live``: a live run can apply it block by
    block; ``diagnosed``: ``diagnose`` has a candidate for it.
    """

    name: str
    sensors: tuple[str, ...]
    required: tuple[str, ...]
    forward: str
    inverse: str
    ukf_state: tuple[tuple[str, str], ...] = ()
    live: bool = False
    diagnosed: bool = True
    meaning: str = ""
    vehicle: bool = False  # needs a vehicle's current or throttle series (a flight profile, a flight log)


REGISTRY: dict[str, EffectInfo] = {e.name: e for e in (
    EffectInfo("temperature_bias", ("gyro", "accel"), ("coeff",), "TemperatureBias", "pointwise",
               (("gyro", "temperature_bias:gyro"), ("accel", "temperature_bias:accel")), live=True,
               meaning="a bias that moves with the sensor's temperature"),
    EffectInfo("bias_drift", ("gyro", "accel"), ("density",), "BiasDrift", "none",
               meaning="a bias that wanders with time (random walk / instability)"),
    EffectInfo("g_sensitivity", ("gyro",), ("coeff",), "GSensitivity", "pointwise",
               (("gyro", "g_sensitivity"),), live=True,
               meaning="gyro output that responds to specific force (full 3×3 with the matrix key)"),
    EffectInfo("time_offset", ("mag", "gyro", "accel"), ("sensor", "seconds"), "TimeOffset", "resample",
               meaning="one sensor's samples stamped late or early against another's"),
    EffectInfo("saturation", ("gyro", "accel"), ("sensor", "limit"), "Saturation", "none",
               meaning="readings clipped at a range limit"),
    EffectInfo("scale_nonlinearity", ("gyro", "accel"), ("coeff",), "ScaleNonlinearity", "pointwise", live=True,
               meaning="a scale factor that changes with the magnitude of the input"),
    EffectInfo("lever_arm", ("accel",), ("x", "y", "z"), "LeverArm", "pointwise", live=True,
               meaning="accelerometer away from the centre of rotation (centripetal and tangential terms)"),
    EffectInfo("axis_sign", ("gyro", "accel", "mag"), ("sensor", "axis"), "AxisSign", "pointwise", live=True,
               meaning="an axis whose sign is inverted against the other sensors (mounting or driver error)"),
    EffectInfo("mag_current", ("mag",), ("coeff", "basis"), "MagCurrent", "pointwise", vehicle=True,
               meaning="a magnetometer offset proportional to the motor current or the throttle (compassmot)"),
)}

# EFFECTS: the effects any session can carry (the paper's platform included); VEHICLE_EFFECTS need a
# vehicle's current or throttle series (simulate --profile multirotor|fixedwing, a flight log with BAT/CTUN);
# ALL_EFFECTS: the whole vocabulary (simulate --effect, extensions, diagnose's findings)
EFFECTS: tuple[str, ...] = tuple(n for n, e in REGISTRY.items() if not e.vehicle)
VEHICLE_EFFECTS: tuple[str, ...] = tuple(n for n, e in REGISTRY.items() if e.vehicle)
ALL_EFFECTS: tuple[str, ...] = EFFECTS + VEHICLE_EFFECTS
SENSORS_OF: dict[str, tuple[str, ...]] = {n: e.sensors for n, e in REGISTRY.items()}
REQUIRED: dict[str, tuple[str, ...]] = {n: e.required for n, e in REGISTRY.items()}
# (effect, sensor) → the UKF extension state that estimates it
UKF_STATE: dict[tuple[str, str], str] = {(n, s): st for n, e in REGISTRY.items() for s, st in e.ukf_state}
LIVE_POINTWISE: tuple[str, ...] = tuple(n for n, e in REGISTRY.items() if e.live)
NOT_REMOVABLE: tuple[str, ...] = tuple(n for n, e in REGISTRY.items() if e.inverse == "none")

# Keys of each effect's spec and their defaults (the contract's effect table). None: depends on the sensor
# (saturation's limit) or all axes (axis); g_sensitivity's matrix None: diagonal only. The simulator's
# effect classes have exactly these fields and defaults (checked where they are defined, sim/effects.py).
EFFECT_KEYS: dict[str, dict[str, Any]] = {
    "temperature_bias": {"sensor": "gyro", "axis": None, "coeff": 0.0005, "rise": 15.0, "tau": 90.0},
    "bias_drift": {"sensor": "gyro", "axis": None, "density": 0.0001},
    "g_sensitivity": {"sensor": "gyro", "axis": None, "coeff": 0.0001, "matrix": None},
    "time_offset": {"sensor": "mag", "seconds": 0.02},
    "saturation": {"sensor": "gyro", "limit": None},
    "scale_nonlinearity": {"sensor": "gyro", "axis": None, "coeff": 0.002},
    "lever_arm": {"x": 0.05, "y": 0.03, "z": -0.02},
    "axis_sign": {"sensor": "gyro", "axis": "z"},
    # raw = true + coeff·x: coeff (3,) raw magnetometer unit per A (basis current) or at full throttle
    "mag_current": {"basis": "current", "coeff": (2e-3, -1e-3, 3e-3)},
}
assert tuple(EFFECT_KEYS) == ALL_EFFECTS


def lever_arm_acceleration(omega: Array, omega_dot: Array, r: Array) -> Array:
    """Specific force added at an accelerometer r (3,) m from the centre of rotation (lever_arm's forward
    model): ω̇×r + ω×(ω×r) (tangential + centripetal), (N, 3) m/s² for ω (N, 3) rad/s, ω̇ (N, 3) rad/s²."""
    out: Array = np.cross(omega_dot, r) + np.cross(omega, np.cross(omega, r))
    return out
