"""Sensor synthesis: the paper's error model (``onlinecal.model``) applied to the platform's motion.

raw = calibration.inv().apply(truth) + white noise, then ADC quantisation and range clipping of a
typical MEMS part (ICM-20602-class IMU, IST8310-class magnetometer). Effects from the contract's
vocabulary (``onlinecal.sim.effects``) act in signal-chain order (``stage``): on the motion a sensor
samples (time_offset, lever_arm), on the raw signals between the model and the noise (the others), or on
the quantised readings (axis_sign, saturation). They never draw from the session's generator, so a
session with effects has the clean session's noise draws; without effects the output is unchanged.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..io.base import ImuData
from ..model import Calibration, SensorCalibration
from ..specs import ACCEL_SPEC, FIELD_DIP_DEG, FIELD_GAUSS, GYRO_SPEC, MAG_SPEC, SensorSpec  # noqa: F401 (re-export)
from .effects import order_effects, vehicle_series
from .flight import (
    VIBE_HEALTHY,
    VehicleTrajectory,
    fixedwing_trajectory,
    mag_interference,
    multirotor_trajectory,
    vibration,
)
from .motion import (
    DEFAULT_LATITUDE_DEG,
    G0,
    MotionSample,
    Trajectory,
    earth_rate_world,
    flight_trajectory,
    paper_trajectory,
)

Array = NDArray[np.float64]
TRUTH_SCHEMA = "onlinecal.truth/1"

# The paper's gyroscope figures (Table II): bias rad/s and scale (calibrated = S · raw).
PAPER_GYRO_BIAS = (0.0027, 0.1605, 0.0660)
PAPER_GYRO_SCALE = (1.1526, 1.1327, 1.1425)


def field_world(dip_deg: float = FIELD_DIP_DEG, declination_deg: float = 0.0) -> Array:
    """Unit magnetic field in the world frame (ENU: true north along y, dip downwards; its horizontal part
    ``declination_deg`` east of true north)."""
    d, D = np.radians(dip_deg), np.radians(declination_deg)
    return np.array([np.sin(D) * np.cos(d), np.cos(D) * np.cos(d), -np.sin(d)])


def paper_truth(rng: np.random.Generator) -> Calibration:
    """Errors of the paper's magnitudes, perturbed per seed so no test can pass on one fixed answer.

    Gyro bias and scale as in the paper (±5 %), misalignments of about a degree, large hard iron
    (about half the field) and soft iron (±10 % scale, ~1° non-orthogonality).
    """
    deg = np.pi / 180

    def around(v: tuple[float, ...], rel: float) -> Array:
        return np.asarray(v) * (1 + rng.uniform(-rel, rel, 3))

    gyro = SensorCalibration.from_params(
        around(PAPER_GYRO_BIAS, 0.05), around(PAPER_GYRO_SCALE, 0.01),
        rng.normal(0, 1.0, 3) * deg, rng.normal(0, 0.5, 3) * deg,
    )
    accel = SensorCalibration.from_params(
        rng.uniform(-0.4, 0.4, 3), 1 + rng.uniform(-0.03, 0.03, 3),
        rng.normal(0, 1.0, 3) * deg, rng.normal(0, 0.5, 3) * deg,
    )
    soft = np.array([1.08, 0.91, 1.03]) * (1 + rng.uniform(-0.03, 0.03, 3))
    mag = SensorCalibration.from_params(
        rng.uniform(-0.25, 0.25, 3), 1.0 / (FIELD_GAUSS * soft),
        rng.normal(0, 1.5, 3) * deg, rng.normal(0, 1.0, 3) * deg,
    )
    return Calibration(gyro=gyro, accel=accel, mag=mag, source="truth")


@dataclass
class Truth:
    """What the simulator knows and the estimators must find."""

    calibration: Calibration
    profile: str
    seed: int
    imu_rate: float
    mag_rate: float
    gravity: float = G0
    field_world: list[float] = field(default_factory=lambda: field_world().tolist())
    field_gauss: float = FIELD_GAUSS
    noise: dict[str, float] = field(default_factory=dict)
    segments: list[dict] = field(default_factory=list)
    effects: list[dict] = field(default_factory=list)
    vehicle: dict[str, Any] = field(default_factory=dict)  # flight profiles: vibration, interference, times
    earth_rate: dict[str, Any] = field(default_factory=dict)  # {"latitude_deg", "world"} where the gyro sees it

    def to_dict(self) -> dict[str, Any]:
        return {
            "schema": TRUTH_SCHEMA,
            "profile": self.profile,
            "seed": self.seed,
            "imu_rate": self.imu_rate,
            "mag_rate": self.mag_rate,
            "gravity": self.gravity,
            "field_world": list(self.field_world),
            "field_gauss": self.field_gauss,
            "noise": self.noise,
            "segments": self.segments,
            "effects": self.effects,
            **({"vehicle": self.vehicle} if self.vehicle else {}),
            **({"earth_rate": self.earth_rate} if self.earth_rate else {}),
            "calibration": self.calibration.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Truth:
        if d.get("schema") != TRUTH_SCHEMA:
            raise ValueError(f"not a truth file (schema {d.get('schema')!r})")
        kw = {k: d[k] for k in ("profile", "seed", "imu_rate", "mag_rate", "gravity", "field_world",
                                 "field_gauss", "noise", "segments", "effects", "vehicle", "earth_rate") if k in d}
        return cls(calibration=Calibration.from_dict(d["calibration"]), **kw)

    def save(self, path: str | Path) -> None:
        from ..files import atomic_write  # the package's one writer

        atomic_write(path, json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> Truth:
        return cls.from_dict(json.loads(Path(path).read_text()))


@dataclass
class SimContext:
    """Everything an effect may read or change, per clock. Raw arrays are modified in place.

    ``motion`` holds, per sensor, the truth at the instants that sensor's samples hold (a time_offset
    re-evaluates it); ``inputs`` an input that replaces the motion's (the lever-arm specific force);
    :meth:`remodel` re-applies the paper model to them. ``post`` are callables run on the noisy,
    quantised readings ``{"gyro", "accel", "mag"}`` (sign errors, the ADC rail). ``info`` collects
    informative figures per effect (merged into the truth file's effect entries).
    """

    t_imu: Array
    t_mag: Array
    motion_imu: MotionSample
    motion_mag: MotionSample
    gyro: Array  # raw, before noise
    acc: Array
    mag: Array
    temp: Array
    truth: Calibration
    rng: np.random.Generator
    imu_rate: float
    mag_rate: float
    specs: dict[str, SensorSpec]
    noise_scale: dict[str, float] = field(default_factory=lambda: {"gyro": 1.0, "accel": 1.0, "mag": 1.0})
    seed: int = 0
    trajectory: Trajectory | VehicleTrajectory | None = None
    h_W: Array | None = None  # unit field in the world frame
    motion: dict[str, MotionSample] = field(default_factory=dict)
    inputs: dict[str, Array] = field(default_factory=dict)
    post: list[Callable[[dict[str, Array]], None]] = field(default_factory=list)
    info: dict[int, dict[str, Any]] = field(default_factory=dict)
    temp_effect: tuple[float, float] | None = None  # (rise, tau) of the temperature_bias that set temp

    def __post_init__(self) -> None:
        for k, m in (("gyro", self.motion_imu), ("accel", self.motion_imu), ("mag", self.motion_mag)):
            self.motion.setdefault(k, m)

    def raw(self, sensor: str) -> Array:
        """The raw (N, 3) array of ``sensor`` (gyro, accel, mag), modified in place by effects."""
        return {"gyro": self.gyro, "accel": self.acc, "mag": self.mag}[sensor]

    def remodel(self, sensor: str) -> None:
        """Raw = the truth model's inverse (paper eq. 1, ``raw = M⁻¹ c + o``) of the sensor's input:
        ``inputs[sensor]`` if set, else the motion's body rate, specific force or body-frame field."""
        m = self.motion[sensor]
        if sensor in self.inputs:
            c = self.inputs[sensor]
        elif sensor == "gyro":
            c = m.omega
        elif sensor == "accel":
            c = m.f
        else:
            h_W = field_world() if self.h_W is None else self.h_W
            c = np.einsum("nji,j->ni", m.R, h_W)
        cal = self.truth.sensor(sensor)
        assert cal is not None
        self.raw(sensor)[:] = cal.inv().apply(c)

    def child_rng(self, effect: Any) -> np.random.Generator:
        """A generator of the effect's own, independent of the session's noise draws: seeded by the
        session seed and a CRC of the effect's description."""
        from .effects import rng_tag

        return np.random.default_rng([int(self.seed) & 0xFFFFFFFF, rng_tag(effect)])

    def note(self, effect: Any, figures: dict[str, Any]) -> None:
        self.info.setdefault(id(effect), {}).update(figures)


def sample_times(duration: float, imu_rate: float, mag_rate: float) -> tuple[Array, Array]:
    """IMU ticks at ``imu_rate``; mag on every k-th IMU tick if the rates divide, else on its own clock."""
    t_imu = np.arange(int(np.floor(duration * imu_rate)) + 1) / imu_rate
    k = imu_rate / mag_rate
    if abs(k - round(k)) < 1e-9:
        t_mag = t_imu[1 :: int(round(k))]
    else:
        t_mag = 0.0037 + np.arange(int(np.floor((duration - 0.0037) * mag_rate)) + 1) / mag_rate
    return t_imu, t_mag


def quantise(x: Array, spec: SensorSpec) -> Array:
    y = np.clip(x, -spec.full_scale, spec.full_scale)
    return np.round(y / spec.lsb) * spec.lsb if spec.lsb > 0 else y


PROFILES = ("paper", "flight", "multirotor", "fixedwing")
VEHICLES = ("multirotor", "fixedwing")
# per-axis RMS vibration (m/s²) of a fixed-wing's engine/propeller, about half a multirotor's (one
# propeller, stiffer airframe); same ArduPilot VIBE scale as :data:`onlinecal.sim.flight.VIBE_HEALTHY`
VIBE_FIXEDWING = (1.5, 1.5, 2.5)


GPS_RATE_HZ = 5.0  # a u-blox M8's default navigation rate (ArduPilot GPS_RATE_MS 200)
DEFAULT_LONGITUDE_DEG = 8.545594  # PX4 SITL's default home (PX4_HOME_LON), with motion.DEFAULT_LATITUDE_DEG
EARTH_RADIUS_M = 6_371_000.0  # mean radius: metres to degrees over a flight's few hundred metres


def home_declination(latitude: float = DEFAULT_LATITUDE_DEG, longitude: float = DEFAULT_LONGITUDE_DEG) -> float:
    """The World Magnetic Model's declination (deg) at the simulated home on the date the writers put on a log
    (``io.base.WRITE_EPOCH_US``)."""
    from ..io.base import WRITE_EPOCH_US, decimal_year
    from ..place import wmm_declination

    return wmm_declination(latitude, longitude, decimal_year(WRITE_EPOCH_US * 1e-6)).deg


def gps_series(trajectory: Any, duration: float, latitude: float, longitude: float = DEFAULT_LONGITUDE_DEG,
               rate: float = GPS_RATE_HZ) -> dict[str, tuple[Array, Array]]:
    """The ``latitude``/``longitude`` series (deg) a GPS receiver logs at ``rate`` Hz over [0, duration] s: the
    home position (``latitude``, ``longitude``) moved by the vehicle's flown path (its world velocity integrated;
    ENU, east and north), or the home position throughout for a trajectory without a velocity (a bench)."""
    t = np.arange(0.0, duration + 1e-9, 1.0 / rate)
    east = north = np.zeros(t.size)
    v = getattr(trajectory, "v_world", None)
    if v is not None:
        pos = np.vstack([np.zeros(3), np.cumsum(v[:-1] * trajectory.dt, axis=0)])
        k = np.clip(np.rint(t / trajectory.dt).astype(np.intp), 0, pos.shape[0] - 1)
        east, north = pos[k, 0], pos[k, 1]
    lat = latitude + np.degrees(north / EARTH_RADIUS_M)
    lon = longitude + np.degrees(east / (EARTH_RADIUS_M * max(np.cos(np.radians(latitude)), 1e-6)))
    return {"latitude": (t, lat), "longitude": (t.copy(), lon)}


class ProfileError(ValueError):
    """An unknown profile or profile option (the message names it)."""


def parse_profile(spec: str) -> tuple[str, dict[str, float]]:
    """``NAME[:key=value,...]`` → (name, options). Vehicle options: ``vibration`` (RMS m/s² on body z at
    hover, x/y 0.6 of it; 0 off), ``mag_interference`` (field units per unit throttle, along body
    (0.3, −0.2, 0.9)), ``rest`` (s of disarmed ground rest before arming, ≥ 30), ``legs`` (s, ≥ 12: the longest
    leg of the flight, the legs then lasting legs/3 to legs; by default 8–25 s for a multirotor, 10–30 s for a
    fixed-wing, whose turns at legs=180 are loiters of up to three minutes at one bank)."""
    name, _, rest = spec.partition(":")
    if name not in PROFILES:
        raise ProfileError(f"unknown profile {name!r} ({', '.join(PROFILES)})")
    opts: dict[str, float] = {}
    if rest:
        if name not in VEHICLES:
            raise ProfileError(f"profile {name!r} takes no options ({spec!r})")
        for kv in rest.split(","):
            k, eq, v = kv.partition("=")
            if k not in ("vibration", "mag_interference", "rest", "legs") or not eq:
                raise ProfileError(f"{spec!r}: unknown option {kv!r} (vibration=, mag_interference=, rest=, legs=)")
            try:
                opts[k] = float(v)
            except ValueError as e:
                raise ProfileError(f"{spec!r}: {k} must be a number, not {v!r}") from e
            if not np.isfinite(opts[k]) or opts[k] < 0:
                raise ProfileError(f"{spec!r}: {k} must be finite and ≥ 0")
        if opts.get("rest", 30.0) < 30.0:
            raise ProfileError(f"{spec!r}: the ground rest must last at least 30 s")
        if opts.get("legs", 30.0) < 12.0:
            raise ProfileError(f"{spec!r}: the longest leg must last at least 12 s (a turn rolls in and out over 4 s)")
    return name, opts


def make_trajectory(profile: str, rng: np.random.Generator, duration: float | None,
                    rest_s: float | None = None, legs_s: float | None = None) -> Trajectory | VehicleTrajectory:
    if profile == "paper":
        return paper_trajectory(rng)
    if profile == "flight":
        return flight_trajectory(rng, duration or 300.0)
    kw: dict[str, Any] = {"rest_s": rest_s} if rest_s else {}
    if legs_s:
        kw["legs_s"] = (legs_s / 3.0, legs_s)
    if profile == "multirotor":
        return multirotor_trajectory(rng, duration or 600.0, **kw)
    if profile == "fixedwing":
        return fixedwing_trajectory(rng, duration or 600.0, **kw)
    raise ProfileError(f"unknown profile {profile!r} ({', '.join(PROFILES)})")


@dataclass
class Simulation:
    data: ImuData
    truth: Truth
    trajectory: Trajectory | VehicleTrajectory


def simulate(
    profile: str = "paper",
    seed: int = 0,
    duration: float | None = None,
    imu_rate: float = 100.0,
    mag_rate: float = 50.0,
    effects: list[Any] | tuple[Any, ...] = (),
    truth: Calibration | None = None,
    noise: float = 1.0,
    latitude: float = DEFAULT_LATITUDE_DEG,
    earth_rate: bool | None = None,
    declination: float | None = None,
    gps: bool = False,
) -> Simulation:
    """Simulate a session. Returns raw data (ImuData), the truth and the trajectory.

    ``profile``: ``paper``, ``flight`` or a vehicle, ``multirotor`` / ``fixedwing`` with options
    (:func:`parse_profile`: ``multirotor:vibration=30,mag_interference=0.2``); ``declination`` (deg, east
    positive; None: 0, or with ``gps`` the World Magnetic Model's at the home and the written logs' date, so
    that the place the log states and its field agree) turns the field's horizontal part from true north (the
    Earth's rotation stays on true north;
    the truth file's ``field_world`` records it); a vehicle's rotor vibration
    (healthy by default) is added to the accelerometer's specific force while armed, and its interference
    to the magnetometer's field, both before the sensor model (they are physical inputs).
    ``duration`` cuts the paper profile (or sets the flight length); ``noise`` scales every sensor's
    noise; ``gps`` adds the position a GPS receiver logs (:func:`gps_series`; it needs the Earth's rotation in the
    gyro, a vehicle's default or ``earth_rate=True``, since a replay told the latitude takes it out); ``effects``
    are objects with ``apply(ctx: SimContext)`` and ``describe() -> dict``
    (``onlinecal.sim.effects.parse_effect`` makes them from ``NAME:key=value`` strings).
    """
    name, opts = parse_profile(profile)
    rng = np.random.default_rng(seed)
    cal = truth if truth is not None else paper_truth(rng)
    # (the rest option only when given: tests replace make_trajectory with a 3-argument stand-in)
    traj = make_trajectory(name, rng, duration, **({"rest_s": opts["rest"]} if "rest" in opts else {}),
                           **({"legs_s": opts["legs"]} if "legs" in opts else {}))
    w_E = earth_rate_world(latitude)  # validates the latitude whether or not it is used
    if earth_rate if earth_rate is not None else name in VEHICLES:
        traj.earth_rate = w_E  # every evaluation (time_offset and lever_arm re-evaluate) includes it
    elif gps:
        raise ProfileError("a GPS position with a gyro that does not sense the Earth's rotation would tell a replay "
                           "to take out what is not there: give the latitude (earth_rate) with gps")
    T = traj.duration if duration is None else min(duration, traj.duration)
    t_imu, t_mag = sample_times(T, imu_rate, mag_rate)
    mi, mm = traj.evaluate(t_imu), traj.evaluate(t_mag)
    if declination is None:
        declination = home_declination(latitude) if gps else 0.0
    h_W = field_world(declination_deg=declination)
    h_B = np.einsum("nji,j->ni", mm.R, h_W)
    vehicle: dict[str, Any] = {}
    if isinstance(traj, VehicleTrajectory):
        base = VIBE_HEALTHY if name == "multirotor" else VIBE_FIXEDWING
        vib_rms = tuple(float(v) for v in base) if "vibration" not in opts else (
            0.6 * opts["vibration"], 0.6 * opts["vibration"], opts["vibration"])
        if max(vib_rms) > 0:
            vib = vibration(traj, t_imu, vib_rms, seed)  # type: ignore[arg-type]
            mi = MotionSample(mi.t, mi.R, mi.omega, mi.f + vib, mi.a_world, mi.euler)
        k_mag = opts.get("mag_interference", 0.0)
        mag_dir = np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9])
        if k_mag > 0:
            h_B = h_B + mag_interference(traj, t_mag, k_mag * mag_dir)
        armed = traj.armed
        i_arm = int(np.argmax(armed)) if armed.any() else -1
        vehicle = {"kind": name, "vibration_rms": list(vib_rms), "mag_interference_per_throttle":
                   (k_mag * mag_dir).tolist(), "armed_at": traj.dt * i_arm if i_arm >= 0 else None,
                   "takeoff_at": next((s["t0"] for s in traj.segs if s["kind"] == "flight"), None)}
    assert cal.gyro is not None and cal.accel is not None and cal.mag is not None
    temp = 25.0 + 5.0 * (1 - np.exp(-t_imu / 120.0))
    ctx = SimContext(
        t_imu, t_mag, mi, mm,
        cal.gyro.inv().apply(mi.omega), cal.accel.inv().apply(mi.f), cal.mag.inv().apply(h_B), temp,
        cal, rng, imu_rate, mag_rate, {"gyro": GYRO_SPEC, "accel": ACCEL_SPEC, "mag": MAG_SPEC},
        seed=seed, trajectory=traj, h_W=h_W,
    )
    for eff in order_effects(effects):
        eff.apply(ctx)
    sp = ctx.specs
    sig = {
        "gyro": sp["gyro"].sigma(imu_rate) * noise * ctx.noise_scale["gyro"],
        "accel": sp["accel"].sigma(imu_rate) * noise * ctx.noise_scale["accel"],
        "mag": sp["mag"].sigma(mag_rate) * noise * ctx.noise_scale["mag"],
    }
    out = {
        "gyro": quantise(ctx.gyro + rng.normal(0, sig["gyro"], ctx.gyro.shape), sp["gyro"]),
        "accel": quantise(ctx.acc + rng.normal(0, sig["accel"], ctx.acc.shape), sp["accel"]),
        "mag": quantise(ctx.mag + rng.normal(0, sig["mag"], ctx.mag.shape), sp["mag"]),
    }
    for hook in ctx.post:
        hook(out)
    tmp = np.round((ctx.temp + rng.normal(0, 0.02, ctx.temp.shape)) * 100) / 100
    data = ImuData(ctx.t_imu, out["gyro"], out["accel"], tmp, ctx.t_mag, out["mag"], f"sim:{profile}:{seed}",
                   series=vehicle_series(traj, T))  # a vehicle's throttle and current as its log carries them
    if gps:
        data.series.update(gps_series(traj, T, latitude))
    tr = Truth(
        cal, profile, seed, imu_rate, mag_rate, noise=sig, segments=traj.annotations(),
        effects=[{**e.describe(), **ctx.info.get(id(e), {})} for e in effects], field_world=h_W.tolist(),
        vehicle=vehicle,
        earth_rate={} if getattr(traj, "earth_rate", None) is None else {
            "latitude_deg": float(latitude), "world": np.asarray(traj.earth_rate).tolist()},
    )
    return Simulation(data, tr, traj)
