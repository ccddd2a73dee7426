"""The effects library: what real MEMS sensors do that the paper's model (Zhang et al. 2014, eq. 1) lacks.

Vocabulary, keys, defaults and physics follow the contract's effect table (shared/spec/contract.md and
notes/effects_spec.md). Each effect is a small frozen dataclass with

* ``apply(ctx: SimContext)`` — changes the raw signals of ``onlinecal.sim.sensors.simulate`` in place;
* ``describe() -> dict`` — ``{"effect", "sensor", "axis", **parameters}`` with exactly the spec's keys
  (stored in the truth file; what ``diagnose`` must recover);
* ``stage`` — where in the signal chain it acts. ``simulate`` applies effects by stage (stable within
  a stage), whatever order they were given in, so combinations are well defined:

  ====  ======================================  ===================================================
  0     time_offset                             which instant of the motion a sample holds
  1     lever_arm                               the accelerometer's input (specific force at r)
  --    paper model ``raw = M⁻¹·c + o``          (recomputed for a sensor whose input changed)
  2     temperature_bias, bias_drift,           additive, in raw units, at the sample's stamp
        g_sensitivity, mag_current
  3     scale_nonlinearity                      ``raw ← raw·(1 + c·|raw|)`` on the whole raw value
  --    white noise, ADC quantisation           (``simulate``)
  4     axis_sign                               driver/mounting sign error, after the ADC
  5     saturation                              the ADC rail, after noise: clipped to ±limit
  ====  ======================================  ===================================================

Random numbers: only ``bias_drift`` draws random numbers, and it draws them from its own generator
(``SimContext.child_rng``, seeded by the session seed and the effect's description), never from the
session generator — so a session with effects has exactly the same white-noise draws as the clean
session of the same seed, and ``raw_effect − raw_clean`` is the effect alone (up to quantisation).
"""

from __future__ import annotations

import json
import math
import zlib
from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
from numba import njit
from numpy.typing import NDArray

# the one vocabulary (names, sensors, keys and defaults, inverse, UKF state) and the forward models production
# shares: production owns them, the simulator consumes them
from ..effect_registry import ALL_EFFECTS, AXES, EFFECT_KEYS, EFFECTS, REGISTRY, lever_arm_acceleration

if TYPE_CHECKING:  # runtime import would be circular (sensors imports this module)
    from .sensors import SimContext

Array = NDArray[np.float64]

UNIT = {"gyro": "rad/s", "accel": "m/s^2", "mag": "mag unit"}

# Default saturation limits: ±125 dps (the smallest gyro range of ICM-20602/BMI088-class parts) and ±2 g.
DEFAULT_LIMIT = {"gyro": 2.182, "accel": 19.61}


class EffectError(ValueError):
    """An effect spec (or a combination of effects) that cannot be honoured."""


def _axes(axis: str | None) -> list[int]:
    return [0, 1, 2] if axis is None else [AXES.index(axis)]


def _check_sensor(name: str, sensor: str, allowed: tuple[str, ...]) -> None:
    if sensor not in allowed:
        raise EffectError(f"{name}: sensor must be one of {', '.join(allowed)} (got {sensor!r})")


def _check_axis(name: str, axis: str | None) -> None:
    if axis is not None and axis not in AXES:
        raise EffectError(f"{name}: axis must be x, y, z or all (got {axis!r})")


def _check_num(name: str, key: str, v: float, lo: float | None = None, hi: float | None = None,
               lo_open: bool = False) -> None:
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
        raise EffectError(f"{name}: {key} must be a finite number (got {v!r})")
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise EffectError(f"{name}: {key} must be {'>' if lo_open else '>='} {lo:g} (got {v:g})")
    if hi is not None and v > hi:
        raise EffectError(f"{name}: {key} must be <= {hi:g} (got {v:g})")


class Effect:
    """Base of every effect: ``describe`` from the dataclass fields, a stable identity for child rngs."""

    name: ClassVar[str] = ""
    stage: ClassVar[int] = 2
    sensor: str

    if TYPE_CHECKING:  # a dataclass field in most effects, a read-only property (None) in the others
        @property
        def axis(self) -> str | None: ...

    def params(self) -> dict[str, Any]:
        """The spec's parameter keys (everything but sensor and axis) and their values."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("sensor", "axis")}  # type: ignore[arg-type]

    def describe(self) -> dict[str, Any]:
        """``{"effect": NAME, "sensor": ..., "axis": "x"|"y"|"z"|None, **parameters}`` (spec)."""
        return {"effect": self.name, "sensor": self.sensor, "axis": getattr(self, "axis", None), **self.params()}

    def spec(self) -> str:
        """The ``NAME:key=value,...`` string that :func:`parse_effect` turns back into this effect."""
        kv = []
        for f in fields(self):  # type: ignore[arg-type]
            k, v = f.name, getattr(self, f.name)
            if k == "matrix":  # 9 numbers row by row, ';'-separated (',' separates the keys)
                if v is not None:
                    kv.append("matrix=" + ";".join(repr(float(x)) for r in v for x in r))
                continue
            kv.append(f"{k}={'all' if v is None else v!r}".replace("'", ""))
        return f"{self.name}:{','.join(kv)}"

    def apply(self, ctx: SimContext) -> None:  # pragma: no cover - every subclass overrides
        raise NotImplementedError


@dataclass(frozen=True)
class TemperatureBias(Effect):
    """A bias proportional to the sensor's temperature rise: ``raw_axis += coeff·(T − 25 °C)``.

    The simulator's temperature is replaced by a warm-up with a partial cool-down in the second half,
    so temperature is not a linear function of time (a temperature coefficient is then separable from
    a linear drift)::

        T(t) = 25 + rise·(1 − e^{−t/tau}) − 0.5·rise·(1 − e^{−max(0, t − t_end/2)/tau})      [°C]

    Units: coeff in rad/s/°C (gyro) or m/s²/°C (accel); rise °C; tau s. Real parts (consumer MEMS of
    the ICM-20602/BMI088 class, orders of magnitude): gyro zero-rate tempco 0.01–0.05 dps/°C ≈
    2e-4…9e-4 rad/s/°C; accel zero-g tempco 0.2–1 mg/°C ≈ 2e-3…1e-2 m/s²/°C. A board warms by
    10–20 °C within minutes of power-on.
    """

    name: ClassVar[str] = "temperature_bias"
    stage: ClassVar[int] = 2
    sensor: str = "gyro"
    axis: str | None = None
    coeff: float = 5e-4
    rise: float = 15.0
    tau: float = 90.0

    def __post_init__(self) -> None:
        _check_sensor(self.name, self.sensor, ("gyro", "accel"))
        _check_axis(self.name, self.axis)
        _check_num(self.name, "coeff", self.coeff, -1.0, 1.0)
        _check_num(self.name, "rise", self.rise, -100.0, 100.0)
        _check_num(self.name, "tau", self.tau, 0.0, 1e6, lo_open=True)

    def temperature(self, t: Array, t_end: float) -> Array:
        """T(t) in °C for sample times t (N,) s of a session ending at t_end s."""
        late = np.maximum(0.0, t - t_end / 2)
        return 25.0 + self.rise * (1 - np.exp(-t / self.tau)) - 0.5 * self.rise * (1 - np.exp(-late / self.tau))

    def apply(self, ctx: SimContext) -> None:
        T = self.temperature(ctx.t_imu, float(ctx.t_imu[-1]))
        if ctx.temp_effect is not None and ctx.temp_effect != (self.rise, self.tau):
            raise EffectError("temperature_bias: effects combined in one session must share rise and tau "
                              "(there is one temperature)")
        ctx.temp_effect = (self.rise, self.tau)
        ctx.temp[:] = T
        raw = ctx.raw(self.sensor)
        raw[:, _axes(self.axis)] += self.coeff * (T - 25.0)[:, None]


@dataclass(frozen=True)
class BiasDrift(Effect):
    """Bias instability as a rate random walk: ``raw_axis += b(t)``, ``b(0) = 0``,
    ``b(t_k) − b(t_{k−1}) ~ N(0, density²·(t_k − t_{k−1}))``; independent walks per axis.

    Units: density in rad/s/√s (gyro) or m/s²/√s (accel) — the rate-random-walk coefficient K of an
    Allan-deviation plot (slope +1/2). Real parts (orders of magnitude): consumer MEMS gyros
    K ≈ 1e-5…1e-4 rad/s/√s, accelerometers ≈ 1e-4…1e-3 m/s²/√s.
    The draws come from the effect's own generator (``ctx.child_rng``), not the session's.
    """

    name: ClassVar[str] = "bias_drift"
    stage: ClassVar[int] = 2
    sensor: str = "gyro"
    axis: str | None = None
    density: float = 1e-4

    def __post_init__(self) -> None:
        _check_sensor(self.name, self.sensor, ("gyro", "accel"))
        _check_axis(self.name, self.axis)
        _check_num(self.name, "density", self.density, 0.0, 1.0)

    def walk(self, t: Array, rng: np.random.Generator) -> Array:
        """The random walk b (N, n_axes) at times t (N,), b[0] = 0."""
        ax = _axes(self.axis)
        dt = np.diff(t)
        inc = rng.standard_normal((t.shape[0] - 1, len(ax))) * (self.density * np.sqrt(dt))[:, None]
        return np.vstack([np.zeros((1, len(ax))), np.cumsum(inc, axis=0)])

    def apply(self, ctx: SimContext) -> None:
        b = self.walk(ctx.t_imu, ctx.child_rng(self))
        ctx.raw(self.sensor)[:, _axes(self.axis)] += b
        ctx.note(self, {"walk_final": b[-1].tolist()})


@dataclass(frozen=True)
class GSensitivity(Effect):
    """Gyro output responding to specific force: ``raw_gyro += G·f`` with
    ``G = diag(coeff on the selected axes) + matrix``.

    ``f`` is the true specific force (m/s²) in the body frame B at the gyro's sample instants (the
    centre of rotation, not the accelerometer's lever-arm position). ``coeff`` is the same-axis
    (diagonal) term; ``matrix`` (3×3, row = gyro axis, column = force axis; None = zeros) adds the full
    g-sensitivity matrix as Kalibr's and OpenVINS's IMU models carry it (T_g / "g-sensitivity"), whose
    cross-axis terms dominate on some parts (the imu_tk Xsens session: gyro y ← acc x −2.65 mrad/s per g).
    Units: rad/s per m/s². Real parts (orders of magnitude): consumer MEMS gyros ~0.1 dps/g ≈ 1.8e-4 rad/s
    per m/s², older parts up to ~0.3 dps/g, tactical-grade MEMS < 0.01 dps/g. On the command line the
    matrix is 9 numbers row by row separated by ``;`` (``g_sensitivity:coeff=0,matrix=0;-2.7e-4;...``).
    """

    name: ClassVar[str] = "g_sensitivity"
    stage: ClassVar[int] = 2
    sensor: str = "gyro"
    axis: str | None = None
    coeff: float = 1e-4
    matrix: tuple[tuple[float, ...], ...] | None = None

    def __post_init__(self) -> None:
        _check_sensor(self.name, self.sensor, ("gyro",))
        _check_axis(self.name, self.axis)
        _check_num(self.name, "coeff", self.coeff, -0.1, 0.1)
        if self.matrix is not None:
            m = np.asarray(self.matrix, dtype=float) if _is_numeric_matrix(self.matrix) else None
            if m is None or m.shape != (3, 3) or not np.all(np.isfinite(m)) or np.abs(m).max() > 0.1:
                raise EffectError(f"{self.name}: matrix must be 3×3 finite numbers within ±0.1 (got {self.matrix!r})")
            object.__setattr__(self, "matrix", tuple(tuple(float(v) for v in row) for row in m))

    def G(self) -> Array:
        """The full g-sensitivity matrix (3, 3), rad/s per m/s²."""
        G = np.zeros((3, 3))
        for i in _axes(self.axis):
            G[i, i] = self.coeff
        if self.matrix is not None:
            G = G + np.asarray(self.matrix, float)
        return G

    def params(self) -> dict[str, Any]:
        return {"coeff": self.coeff, "matrix": None if self.matrix is None else [list(r) for r in self.matrix]}

    def apply(self, ctx: SimContext) -> None:
        ctx.gyro += ctx.motion["gyro"].f @ self.G().T


def _is_numeric_matrix(m: Any) -> bool:
    try:
        a = np.asarray(m, dtype=float)
    except (TypeError, ValueError):
        return False
    return a.ndim == 2


@dataclass(frozen=True)
class TimeOffset(Effect):
    """One sensor stamped late (or early): its sample stamped t holds the value at time t − seconds.

    The trajectory is re-evaluated at the shifted instants and the paper model applied again, so the
    effect is exact (no interpolation). ``seconds`` > 0: stamped late; < 0: early. Real systems: an
    I²C magnetometer read through a driver queue lags the SPI IMU by 5–50 ms; a gyro/accel pair from
    two dies with different digital low-pass filters differ by their group delays (a few ms to ~20 ms).
    """

    name: ClassVar[str] = "time_offset"
    stage: ClassVar[int] = 0
    sensor: str = "mag"
    seconds: float = 0.02

    @property
    def axis(self) -> None:
        return None

    def __post_init__(self) -> None:
        _check_sensor(self.name, self.sensor, ("gyro", "accel", "mag"))
        _check_num(self.name, "seconds", self.seconds, -1.0, 1.0)

    def apply(self, ctx: SimContext) -> None:
        t = ctx.t_mag if self.sensor == "mag" else ctx.t_imu
        assert ctx.trajectory is not None, "simulate() sets the trajectory before the effects"
        ctx.motion[self.sensor] = ctx.trajectory.evaluate(t - self.seconds)
        ctx.remodel(self.sensor)


@dataclass(frozen=True)
class Saturation(Effect):
    """Readings clipped at ±limit on every axis of one sensor (the ADC rail), after noise.

    The sensor's ``full_scale`` becomes ``limit`` and the quantised readings are clipped to exactly
    ±limit. Units: limit rad/s (gyro) or m/s² (accel). Real parts: selectable ranges ±125…±2000 dps
    (2.18…34.9 rad/s) and ±2…±16 g; drivers that leave the power-on range (±250 dps, ±2 g) saturate in
    a fast spin or a hard landing. Default ±125 dps / ±2 g.
    """

    name: ClassVar[str] = "saturation"
    stage: ClassVar[int] = 5
    sensor: str = "gyro"
    limit: float | None = None

    @property
    def axis(self) -> None:
        return None

    def __post_init__(self) -> None:
        _check_sensor(self.name, self.sensor, ("gyro", "accel"))
        if self.limit is None:
            object.__setattr__(self, "limit", DEFAULT_LIMIT[self.sensor])
        _check_num(self.name, "limit", self.limit, 0.0, 1e6, lo_open=True)  # type: ignore[arg-type]

    def apply(self, ctx: SimContext) -> None:
        lim = float(self.limit)  # type: ignore[arg-type]
        spec = ctx.specs[self.sensor] = replace(ctx.specs[self.sensor], full_scale=lim)
        # The quantiser clips at lim and rounds, so the top code is lim rounded to the LSB grid; the
        # readings at that code are the clipped ones and read exactly ±lim (the rail).
        top = round(lim / spec.lsb) * spec.lsb if spec.lsb > 0 else lim

        def rail(out: dict[str, Array]) -> None:
            x = out[self.sensor]
            x[:] = np.where(np.abs(x) >= top, np.sign(x) * lim, x)
            ctx.note(self, {"clipped_fraction": float(np.mean(np.any(np.abs(x) >= lim, axis=1)))})

        ctx.post.append(rail)


@dataclass(frozen=True)
class ScaleNonlinearity(Effect):
    """A scale factor that grows with the input: ``raw_i ← raw_i·(1 + coeff·|raw_i|)``.

    Acts on the whole raw value (after the paper model and the additive effects). Units: coeff in
    1/(rad/s) (gyro) or 1/(m/s²) (accel). Real parts (orders of magnitude): consumer MEMS gyros
    specify a scale non-linearity of ~0.1 % of full scale; expressed as this quadratic coefficient
    that is 1e-4…1e-3 per rad/s over a wide range and up to ~5e-3 per rad/s over ±125 dps.
    """

    name: ClassVar[str] = "scale_nonlinearity"
    stage: ClassVar[int] = 3
    sensor: str = "gyro"
    axis: str | None = None
    coeff: float = 2e-3

    def __post_init__(self) -> None:
        _check_sensor(self.name, self.sensor, ("gyro", "accel"))
        _check_axis(self.name, self.axis)
        _check_num(self.name, "coeff", self.coeff, -0.1, 0.1)

    def apply(self, ctx: SimContext) -> None:
        raw = ctx.raw(self.sensor)
        ax = _axes(self.axis)
        x = raw[:, ax]
        if self.coeff < 0 and np.any(1 + 2 * self.coeff * np.abs(x) <= 0):
            raise EffectError(f"scale_nonlinearity: coeff {self.coeff:g} folds the signal over "
                              f"(|raw| up to {np.abs(x).max():.3g}); the map would not be invertible")
        raw[:, ax] = x * (1 + self.coeff * np.abs(x))


@dataclass(frozen=True)
class LeverArm(Effect):
    """Accelerometer at r (m, body frame) from the centre of rotation:
    ``f_meas = f + ω̇×r + ω×(ω×r)`` (tangential + centripetal), before the accelerometer's model.

    ω, ω̇ are the trajectory's body rate and its derivative (central difference of the analytic rate,
    h = 1e-5 s). Real boards: the IMU sits 1–10 cm from a vehicle's or a turntable's rotation centre;
    at 2.5 rad/s and 5 cm the centripetal term is 0.3 m/s² (3 % of g).
    """

    name: ClassVar[str] = "lever_arm"
    stage: ClassVar[int] = 1
    x: float = 0.05
    y: float = 0.03
    z: float = -0.02

    @property
    def sensor(self) -> str:  # type: ignore[override]
        return "accel"

    @property
    def axis(self) -> None:
        return None

    @property
    def r(self) -> Array:
        return np.array([self.x, self.y, self.z])

    def __post_init__(self) -> None:
        for k in ("x", "y", "z"):
            _check_num(self.name, k, getattr(self, k), -1.0, 1.0)

    def params(self) -> dict[str, Any]:
        return {"x": self.x, "y": self.y, "z": self.z}

    @staticmethod
    def acceleration(omega: Array, omega_dot: Array, r: Array) -> Array:
        """ω̇×r + ω×(ω×r), (N, 3) m/s² for ω (N, 3) rad/s, ω̇ (N, 3) rad/s², r (3,) m
        (:func:`onlinecal.effect_registry.lever_arm_acceleration`)."""
        return lever_arm_acceleration(omega, omega_dot, r)

    def apply(self, ctx: SimContext) -> None:
        m = ctx.motion["accel"]
        h = 1e-5
        assert ctx.trajectory is not None, "simulate() sets the trajectory before the effects"
        w_dot = (ctx.trajectory.evaluate(m.t + h).omega - ctx.trajectory.evaluate(m.t - h).omega) / (2 * h)
        ctx.inputs["accel"] = m.f + self.acceleration(m.omega, w_dot, self.r)
        ctx.remodel("accel")


@dataclass(frozen=True)
class AxisSign(Effect):
    """One axis with inverted sign (driver or mounting error): ``raw_axis ← −raw_axis``.

    Applied after the ADC (a driver's sign), so the flipped axis is exactly the negative of the clean
    reading. Real systems: a board rotation parameter or a driver table entry wrong for one axis; the
    result is a left-handed sensor triad (det of the calibration matrix < 0).
    """

    name: ClassVar[str] = "axis_sign"
    stage: ClassVar[int] = 4
    sensor: str = "gyro"
    axis: str | None = "z"

    def __post_init__(self) -> None:
        _check_sensor(self.name, self.sensor, ("gyro", "accel", "mag"))
        _check_axis(self.name, self.axis)

    def params(self) -> dict[str, Any]:
        return {}

    def apply(self, ctx: SimContext) -> None:
        ax = _axes(self.axis)

        def flip(out: dict[str, Array]) -> None:
            out[self.sensor][:, ax] *= -1.0

        ctx.post.append(flip)


EFFECT_CLASSES: dict[str, type[Effect]] = {
    c.name: c for c in (TemperatureBias, BiasDrift, GSensitivity, TimeOffset, Saturation, ScaleNonlinearity,
                        LeverArm, AxisSign)
}
assert tuple(EFFECT_CLASSES) == EFFECTS  # mag_current (a vehicle effect) is added after its class, at the end

# Keys of each effect and their defaults: the registry's EFFECT_KEYS (None: depends on the sensor, see
# DEFAULT_LIMIT; axis None = all); every class has exactly those fields and defaults (checked at the end).
_STR_KEYS = ("sensor", "axis", "basis")


def _value(name: str, key: str, text: str) -> Any:
    if name == "mag_current" and key == "coeff":  # 3 numbers (x;y;z), ';'-separated like the matrix
        try:
            v3 = tuple(float(x) for x in text.split(";"))
        except ValueError:
            raise EffectError(f"{name}: coeff must be 3 numbers separated by ';' (got {text!r})") from None
        if len(v3) != 3:
            raise EffectError(f"{name}: coeff must be 3 numbers separated by ';' (got {len(v3)})")
        return v3
    if key == "matrix":
        try:
            v9 = [float(x) for x in text.split(";")]
        except ValueError:
            raise EffectError(f"{name}: matrix must be 9 numbers separated by ';' (got {text!r})") from None
        if len(v9) != 9:
            raise EffectError(f"{name}: matrix must be 9 numbers separated by ';' (got {len(v9)})")
        return tuple(tuple(v9[3 * i : 3 * i + 3]) for i in range(3))
    if key == "axis":
        return None if text == "all" else text
    if key in ("sensor", "basis"):
        return text
    try:
        v = float(text)
    except ValueError:
        raise EffectError(f"{name}: {key} must be a number (got {text!r})") from None
    if not math.isfinite(v):
        raise EffectError(f"{name}: {key} must be finite (got {text!r})")
    return v


def make_effect(name: str, **params: Any) -> Effect:
    """An effect by name with keyword parameters (spec keys; ``axis="all"`` or None for every axis)."""
    if name not in EFFECT_CLASSES:
        raise EffectError(f"unknown effect {name!r}; known: {', '.join(ALL_EFFECTS)}")
    valid = EFFECT_KEYS[name]
    for k in params:
        if k not in valid:
            raise EffectError(f"{name}: unknown key {k!r} (valid: {', '.join(valid)})")
    if params.get("axis") == "all":
        params["axis"] = None
    for k, v in params.items():
        if k in _STR_KEYS and v is not None and not isinstance(v, str):
            raise EffectError(f"{name}: {k} must be a string (got {v!r})")
        if k not in _STR_KEYS and isinstance(v, int) and not isinstance(v, bool):
            params[k] = float(v)
        if k == "matrix" and isinstance(v, list):
            params[k] = tuple(tuple(r) if isinstance(r, list) else r for r in v)
        if name == "mag_current" and k == "coeff" and isinstance(v, (list, tuple, np.ndarray)):
            params[k] = tuple(v)
    return EFFECT_CLASSES[name](**params)


def parse_effect(spec: str) -> Effect:
    """Parse ``NAME`` or ``NAME:key=value,...`` into an effect (contract). Raises EffectError naming the
    spec and the problem: unknown effect, unknown key (with the valid keys), repeated key, bad value."""
    name, _, rest = spec.strip().partition(":")
    name = name.strip()
    params: dict[str, Any] = {}
    try:
        if name not in EFFECT_CLASSES:
            raise EffectError(f"unknown effect {name!r}; known: {', '.join(ALL_EFFECTS)}")
        for item in (s.strip() for s in rest.split(",")) if rest.strip() else ():
            key, eq, text = item.partition("=")
            key, text = key.strip(), text.strip()
            if not eq or not key or not text:
                raise EffectError(f"{name}: expected key=value, got {item!r}")
            if key not in EFFECT_KEYS[name]:
                raise EffectError(f"{name}: unknown key {key!r} (valid: {', '.join(EFFECT_KEYS[name])})")
            if key in params:
                raise EffectError(f"{name}: key {key!r} given twice")
            params[key] = _value(name, key, text)
        return make_effect(name, **params)
    except EffectError as e:
        raise EffectError(f"effect spec {spec!r}: {e}") from None


def from_describe(d: dict[str, Any]) -> Effect:
    """Inverse of ``describe()`` (e.g. from a truth file); informative extras such as
    ``clipped_fraction`` are ignored."""
    name = d.get("effect")
    if name not in EFFECT_CLASSES:
        raise EffectError(f"unknown effect {name!r}; known: {', '.join(ALL_EFFECTS)}")
    keys = EFFECT_KEYS[name]
    return make_effect(name, **{k: v for k, v in d.items() if k in keys})


def _touches(e: Effect) -> set[tuple[str, int]]:
    ax = [0, 1, 2] if e.axis is None else [AXES.index(e.axis)]
    return {(e.sensor, a) for a in ax}


def check_combination(effects: list[Any] | tuple[Any, ...]) -> None:
    """Effects of one session must not overlap: one effect of each name per sensor axis (a second
    time_offset, saturation or sign flip of the same sensor is ambiguous), and temperature_bias effects
    share rise and tau (there is one temperature). Raises EffectError."""
    seen: dict[tuple[str, str, int], Effect] = {}
    temps = set()
    for e in effects:
        if not isinstance(e, Effect):
            continue
        if isinstance(e, TemperatureBias):
            temps.add((e.rise, e.tau))
        for s, a in _touches(e):
            key = (e.name, s, a)
            if key in seen:
                raise EffectError(f"{e.name}: two effects act on {s} axis {AXES[a]} ({seen[key].spec()} and "
                                  f"{e.spec()})")
            seen[key] = e
    if len(temps) > 1:
        raise EffectError("temperature_bias: effects combined in one session must share rise and tau")


def order_effects(effects: list[Any] | tuple[Any, ...]) -> list[Any]:
    """Effects in signal-chain order (``stage``; stable within a stage) after :func:`check_combination`."""
    check_combination(effects)
    return sorted(effects, key=lambda e: getattr(e, "stage", 2))


def rng_tag(e: Any) -> int:
    """A 32-bit tag of an effect's description (seeds its child generator independently of order)."""
    return zlib.crc32(json.dumps(e.describe(), sort_keys=True).encode())


# -- random effects for hidden-effect tests --------------------------------------------------------

def _session_raw(session: Any, sensor: str) -> Array:
    data = getattr(session, "data", session)
    raw = getattr(data, {"gyro": "gyro", "accel": "acc", "mag": "mag"}[sensor], None)
    if raw is None:
        raise EffectError("saturation: random_effect needs the session (Simulation or ImuData) to set the limit")
    return np.asarray(raw, float)


def random_effect(name: str, rng: np.random.Generator, session: Any = None) -> Effect:
    """An effect of a realistic size, drawn from the spec table's test ranges.

    Magnitudes uniform in the range, signs random where the physics has a sign; axis uniform over
    x, y, z, all (single-axis for axis_sign); sensor where the spec allows a choice:

    * temperature_bias — gyro |coeff| 2e-4…1e-3 rad/s/°C or accel 3e-3…1e-2 m/s²/°C (rise, tau default);
    * bias_drift — gyro density 5e-5…3e-4 rad/s/√s;
    * g_sensitivity — |coeff| 5e-5…5e-4 rad/s per m/s²;
    * time_offset — ±(0.01…0.08) s on gyro, accel or mag;
    * saturation — gyro or accel, limit 0.6…0.9 × the session's peak |raw| over its axes
      (``session``: the clean Simulation or its ImuData of the same profile/seed; required);
    * scale_nonlinearity — gyro coeff 1e-3…5e-3 per rad/s;
    * lever_arm — |r| 0.02…0.1 m in a uniformly random direction;
    * axis_sign — random sensor and axis;
    * mag_current — :func:`random_mag_current` (a vehicle profile is needed to simulate it).
    """
    def sign() -> float:
        return float(rng.choice([-1.0, 1.0]))

    def axis() -> str:
        return str(rng.choice(["x", "y", "z", "all"]))

    if name == "temperature_bias":
        sensor = str(rng.choice(["gyro", "accel"]))
        lo, hi = (2e-4, 1e-3) if sensor == "gyro" else (3e-3, 1e-2)
        return make_effect(name, sensor=sensor, axis=axis(), coeff=sign() * float(rng.uniform(lo, hi)))
    if name == "bias_drift":
        return make_effect(name, sensor="gyro", axis=axis(), density=float(rng.uniform(5e-5, 3e-4)))
    if name == "g_sensitivity":
        return make_effect(name, axis=axis(), coeff=sign() * float(rng.uniform(5e-5, 5e-4)))
    if name == "g_sensitivity_matrix":
        return random_gsens_matrix(rng)
    if name == "time_offset":
        return make_effect(name, sensor=str(rng.choice(["gyro", "accel", "mag"])),
                           seconds=sign() * float(rng.uniform(0.01, 0.08)))
    if name == "saturation":
        sensor = str(rng.choice(["gyro", "accel"]))
        peak = float(np.abs(_session_raw(session, sensor)).max())
        return make_effect(name, sensor=sensor, limit=float(rng.uniform(0.6, 0.9)) * peak)
    if name == "scale_nonlinearity":
        return make_effect(name, sensor="gyro", axis=axis(), coeff=float(rng.uniform(1e-3, 5e-3)))
    if name == "lever_arm":
        u = rng.standard_normal(3)
        r = u / np.linalg.norm(u) * float(rng.uniform(0.02, 0.1))
        return make_effect(name, x=float(r[0]), y=float(r[1]), z=float(r[2]))
    if name == "axis_sign":
        return make_effect(name, sensor=str(rng.choice(["gyro", "accel", "mag"])),
                           axis=str(rng.choice(["x", "y", "z"])))
    if name == "mag_current":
        return random_mag_current(rng)
    raise EffectError(f"unknown effect {name!r}; known: {', '.join(ALL_EFFECTS)}")


def random_gsens_matrix(rng: np.random.Generator) -> GSensitivity:
    """A full 3×3 g-sensitivity as the imu_tk Xsens part shows it: cross-axis terms of 1–3 mrad/s per g
    (1.0e-4…3.1e-4 rad/s per m/s², random signs), same-axis terms under 0.2 mrad/s per g."""
    g = 9.80665
    M = rng.uniform(1e-3, 3e-3, (3, 3)) / g * rng.choice([-1.0, 1.0], (3, 3))
    M[np.diag_indices(3)] = rng.uniform(-2e-4, 2e-4, 3) / g
    return GSensitivity(coeff=0.0, matrix=tuple(tuple(float(v) for v in r) for r in M))


@dataclass(frozen=True)
class MagDisturbance(Effect):
    """A passing magnetic disturbance (issue 16): a field of ``amplitude`` gauss along the unit vector
    ``direction`` of the body frame (a motor, a steel beam or a car passing the unit) is added to the
    magnetometer's input for ``duration`` s from log time ``start`` s.

    Stage 2 (additive, at the sample's stamp): the raw readings gain ``M⁻¹ d`` with d the disturbance in
    the calibrated field's unit (``amplitude / field_gauss``; the paper session's field is 0.48 G, so 0.5 G
    is about the whole field again). Not in the contract's effect vocabulary (no model term inverts it:
    the estimators must leave the stretch out), so :func:`parse_effect` does not know it; pass the object
    to ``simulate(effects=[...])``. The samples it touches are noted (``disturbed_samples``, ``t0``, ``t1``).
    """

    name: ClassVar[str] = "mag_disturbance"
    stage: ClassVar[int] = 2
    sensor: str = "mag"
    start: float = 100.0
    duration: float = 30.0
    amplitude: float = 0.5
    direction: tuple[float, float, float] = (0.0, 0.0, 1.0)
    field_gauss: float = 0.48

    @property
    def axis(self) -> None:
        return None

    def __post_init__(self) -> None:
        _check_sensor(self.name, self.sensor, ("mag",))
        _check_num(self.name, "start", self.start)
        _check_num(self.name, "duration", self.duration, 0.0, None, lo_open=True)
        _check_num(self.name, "amplitude", self.amplitude, 0.0, 100.0)
        _check_num(self.name, "field_gauss", self.field_gauss, 0.0, 10.0, lo_open=True)
        u = np.asarray(self.direction, float)
        if u.shape != (3,) or not np.all(np.isfinite(u)) or np.linalg.norm(u) == 0:
            raise EffectError(f"{self.name}: direction must be 3 finite numbers, not all 0")
        object.__setattr__(self, "direction", tuple(float(v) for v in u / np.linalg.norm(u)))

    def apply(self, ctx: SimContext) -> None:
        on = (ctx.t_mag >= self.start) & (ctx.t_mag < self.start + self.duration)
        d = self.amplitude / self.field_gauss * np.asarray(self.direction)  # calibrated field unit
        assert ctx.truth.mag is not None
        ctx.mag[on] += np.linalg.inv(ctx.truth.mag.matrix) @ d  # raw = M⁻¹ c + o: the linear part
        ctx.note(self, {"disturbed_samples": int(on.sum()), "t0": float(self.start),
                        "t1": float(self.start + self.duration)})


# -- mag_current: magnetometer interference from the motor current (a vehicle effect) --------------------------

# Battery current of the simulated vehicles, A, as a function of throttle (0…1). Momentum theory: rotor power
# ∝ thrust^1.5 (P = T^1.5/√(2ρA)), and ArduPilot's MOT_THST_EXPO makes thrust about linear in throttle, so at
# a constant battery voltage I ≈ I_AVIONICS + I_FULL·throttle^1.5. I_FULL 40 A: a 4S 450–550-size quad, four
# motors of ~10 A at full throttle (hover at throttle ≈ 0.5: ~14 A, as such frames draw); I_AVIONICS 0.5 A
# (flight controller, GPS, receiver, telemetry radio).
I_FULL_A = 40.0
I_AVIONICS_A = 0.5
SERIES_RATE_HZ = 10.0  # ArduPilot logs BAT and CTUN at 10 Hz (copter's 10-Hz loop); the simulator's series rate
# The motors' current follows the throttle command through the rotor's mechanical time constant: 50–150 ms for
# 5–10-inch props on 2-4 kg-thrust motors (ESC step-response measurements, e.g. Bangura & Mahony 2012); 0.1 s.
# (ArduCopter also ramps the take-off over MOT_SPOOL_TIME = 0.5 s; the trajectory's throttle steps instantly.)
TAU_MOTOR_S = 0.1


@njit(cache=True)
def _first_order_lag(u: Array, a: float) -> Array:  # pragma: no cover - numba
    """y[n] = a·u[n] + (1 − a)·y[n−1] (N,), started at rest on u[0] (y[−1] = u[0]): scipy.signal.lfilter([a],
    [1, a − 1], u, zi=[(1 − a)·u[0]]) in the same operations (the same bits; ``tests/test_sim.py``), without
    importing scipy.signal (~1 s of every flight simulation's start)."""
    y = np.empty_like(u)
    z = (1.0 - a) * u[0]
    for n in range(u.shape[0]):
        y[n] = a * u[n] + z
        z = -(a - 1.0) * y[n]
    return y


def motor_throttle(trajectory: Any, t: Array) -> Array:
    """The throttle the motors deliver at times t (N,) s: the trajectory's throttle command through a first-order
    lag of TAU_MOTOR_S on its integration grid, zero-order hold between grid points. This is what the current
    (and so the interference) follows; the simulator logs it as the throttle series as well."""
    u = np.asarray(trajectory.throttle, float)
    a = float(trajectory.dt) / (TAU_MOTOR_S + float(trajectory.dt))  # backward-Euler discretisation
    y = _first_order_lag(u, a) if u.size else u
    k = np.clip(np.floor(np.asarray(t, float) / trajectory.dt).astype(np.intp), 0, max(u.size - 1, 0))
    out: Array = y[k]
    return out


def battery_current(throttle: Array) -> Array:
    """Battery current (A) at throttle (0…1), (N,) → (N,): I_AVIONICS_A + I_FULL_A·throttle^1.5."""
    thr = np.clip(np.asarray(throttle, float), 0.0, 1.0)
    out: Array = I_AVIONICS_A + I_FULL_A * thr ** 1.5
    return out


def vehicle_series(trajectory: Any, duration: float, rate: float = SERIES_RATE_HZ) -> dict[str, tuple[Array, Array]]:
    """The ``throttle`` (0…1) and ``current`` (A) series a flight log carries (CTUN ThO, BAT Curr), sampled at
    ``rate`` Hz over [0, duration] s from a vehicle trajectory's throttle ({} for a trajectory without one)."""
    if not hasattr(trajectory, "throttle") or not hasattr(trajectory, "at"):
        return {}
    t = np.arange(0.0, duration + 1e-9, 1.0 / rate)
    thr = motor_throttle(trajectory, t)
    return {"throttle": (t, thr), "current": (t.copy(), battery_current(thr))}


@dataclass(frozen=True)
class MagCurrent(Effect):
    """Magnetometer interference from the motor current (ArduPilot's compassmot, PX4's CAL_MAG_COMP): the raw
    magnetometer gains ``coeff·x`` with x the battery current (A, ``basis=current``) or the throttle (0…1,
    ``basis=throttle``) at the sample's instant.

    One convention throughout (simulator, ``extensions.remove_mag_current``, diagnose, the export): ``coeff``
    (3,) is in the **raw** magnetometer frame and unit, before the hard- and soft-iron model, raw = M⁻¹·c + o +
    coeff·x (stage 2, additive at the sample's stamp). The export maps it to each firmware's frame (ArduPilot
    adds COMPASS_MOT after its soft iron, PX4 CAL_MAGn_xCOMP before; ``export._compassmot``).
    x comes from the vehicle trajectory's throttle as the motors deliver it (:func:`motor_throttle`, a 0.1-s
    lag; :func:`battery_current` for the current), so the effect needs a vehicle profile (multirotor,
    fixedwing). Real vehicles: compassmot accepts interference up to 30 % of the field at full throttle, 60 %
    is "bad" (ArduPilot compass-setup-advanced); a 40-A quad with the compass on the frame near the power leads
    shows 0.1–0.3 field at full throttle, i.e. ~1e-3…4e-3 G per A in the 0.48-G field.
    On the command line coeff is 3 numbers separated by ``;`` (``mag_current:basis=current,coeff=2e-3;0;-3e-3``).
    """

    name: ClassVar[str] = "mag_current"
    stage: ClassVar[int] = 2
    basis: str = "current"
    coeff: tuple[float, float, float] = (2e-3, -1e-3, 3e-3)

    @property
    def sensor(self) -> str:  # type: ignore[override]
        return "mag"

    @property
    def axis(self) -> None:
        return None

    def __post_init__(self) -> None:
        if self.basis not in ("current", "throttle"):
            raise EffectError(f"{self.name}: basis must be current or throttle (got {self.basis!r})")
        try:
            k = np.asarray(self.coeff, dtype=float)
        except (TypeError, ValueError):
            k = np.zeros(0)
        if k.shape != (3,) or not np.all(np.isfinite(k)) or np.abs(k).max() > 10.0:
            raise EffectError(f"{self.name}: coeff must be 3 finite numbers within ±10 (got {self.coeff!r})")
        object.__setattr__(self, "coeff", tuple(float(v) for v in k))

    def params(self) -> dict[str, Any]:
        return {"basis": self.basis, "coeff": list(self.coeff)}

    def spec(self) -> str:
        return f"{self.name}:basis={self.basis},coeff=" + ";".join(repr(v) for v in self.coeff)

    def x(self, trajectory: Any, t: Array) -> Array:
        """The regressor at times t (N,): throttle (0…1) or battery current (A) of the vehicle."""
        if not hasattr(trajectory, "throttle") or not hasattr(trajectory, "at"):
            raise EffectError(f"{self.name}: needs a vehicle profile (multirotor, fixedwing) for its "
                              f"{self.basis}; this profile has no motors")
        thr = motor_throttle(trajectory, t)
        return thr if self.basis == "throttle" else battery_current(thr)

    def apply(self, ctx: SimContext) -> None:
        x = self.x(ctx.trajectory, ctx.t_mag)
        ctx.mag += x[:, None] * np.asarray(self.coeff)[None, :]


def random_mag_current(rng: np.random.Generator) -> MagCurrent:
    """A motor interference of a realistic size: basis current or throttle, a uniformly random direction in the
    raw frame, 0.05…0.3 of the field at full throttle (the simulator's raw unit is the gauss, its field
    FIELD_GAUSS = 0.48 G; compassmot calls up to 30 % acceptable) — per A for the current basis (÷ I_FULL_A)."""
    from ..specs import FIELD_GAUSS

    u = rng.standard_normal(3)
    k = u / np.linalg.norm(u) * float(rng.uniform(0.05, 0.3)) * FIELD_GAUSS
    basis = str(rng.choice(["current", "throttle"]))
    if basis == "current":
        k = k / I_FULL_A
    return MagCurrent(basis=basis, coeff=(float(k[0]), float(k[1]), float(k[2])))


EFFECT_CLASSES[MagCurrent.name] = MagCurrent
assert tuple(EFFECT_CLASSES) == ALL_EFFECTS
assert all(REGISTRY[n].forward == c.__name__ for n, c in EFFECT_CLASSES.items())
assert {n: {f.name: f.default for f in fields(c)}  # type: ignore[arg-type]
        for n, c in EFFECT_CLASSES.items()} == EFFECT_KEYS
