"""Motion of a 3-D rotation platform (and of a flying vehicle), evaluated analytically.

The platform is a three-axis gimbal: attitude ``R = Rz(psi) Ry(theta) Rx(phi)`` (world ← body), world
frame z up (ENU), so a level body at rest measures specific force (0, 0, +g). Every segment gives the
Euler angles and their rates in closed form, so the body rate (gyro truth) is exact at any time,
with no numerical integration, and the IMU and magnetometer clocks can be sampled independently.

Body rate from Euler rates (ZYX convention)::

    p = phi' − psi' sin(theta)
    q = theta' cos(phi) + psi' cos(theta) sin(phi)
    r = −theta' sin(phi) + psi' cos(theta) cos(phi)
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..specs import G0 as G0  # the constant is production data (onlinecal.specs); re-exported here

Array = NDArray[np.float64]

# The Earth's rotation rate relative to the stars, 7.292115e-5 rad/s (WGS-84 / IERS nominal mean angular
# velocity; NIMA TR8350.2, 3rd ed., table 3.1). A gyro measures the body's rate in inertial space, so at
# rest it reads this rate projected on its axes — up to 7.3e-5 rad/s, about 1/10 of a MEMS gyro's
# per-sample noise at 200 Hz, but what a long rest averages down to.
OMEGA_EARTH = 7.292115e-5  # rad/s
# Default latitude of the flight profiles: PX4 SITL's default home (47.397742° N, 8.545594° E, Zürich;
# PX4_HOME_LAT), consistent with the simulator's field (onlinecal.specs: 0.48 G, dip 64°, central Europe).
DEFAULT_LATITUDE_DEG = 47.397742


def smoothstep(u: Array) -> tuple[Array, Array, Array]:
    """Quintic 0→1 with zero rate and acceleration at both ends; returns s, ds/du, d²s/du²."""
    u = np.clip(u, 0.0, 1.0)
    s = u**3 * (10 - 15 * u + 6 * u**2)
    ds = 30 * u**2 * (1 - u) ** 2
    dds = 60 * u * (1 - u) * (1 - 2 * u)
    return s, ds, dds


def euler_to_R(ang: Array) -> Array:
    """(N, 3) angles (phi, theta, psi) → (N, 3, 3) rotation matrices R = Rz Ry Rx."""
    ph, th, ps = ang[:, 0], ang[:, 1], ang[:, 2]
    cf, sf, ct, st, cp, sp = np.cos(ph), np.sin(ph), np.cos(th), np.sin(th), np.cos(ps), np.sin(ps)
    R = np.empty((ang.shape[0], 3, 3))
    R[:, 0, 0] = cp * ct
    R[:, 0, 1] = cp * st * sf - sp * cf
    R[:, 0, 2] = cp * st * cf + sp * sf
    R[:, 1, 0] = sp * ct
    R[:, 1, 1] = sp * st * sf + cp * cf
    R[:, 1, 2] = sp * st * cf - cp * sf
    R[:, 2, 0] = -st
    R[:, 2, 1] = ct * sf
    R[:, 2, 2] = ct * cf
    return R


def euler_rates_to_body(ang: Array, rates: Array) -> Array:
    """Body angular rate (N, 3) from Euler angles and their time derivatives (N, 3)."""
    ph, th = ang[:, 0], ang[:, 1]
    dph, dth, dps = rates[:, 0], rates[:, 1], rates[:, 2]
    p = dph - dps * np.sin(th)
    q = dth * np.cos(ph) + dps * np.cos(th) * np.sin(ph)
    r = -dth * np.sin(ph) + dps * np.cos(th) * np.cos(ph)
    return np.stack([p, q, r], axis=1)


# A segment maps local time tau (n,) in [0, T] to (angles (n,3), angle rates (n,3), world accel (n,3)).
SegFn = Callable[[Array], tuple[Array, Array, Array]]


@dataclass
class Segment:
    kind: str  # "hold", "move", "spin", "tumble", "flight"
    T: float
    fn: SegFn
    end: Array  # Euler angles at the end
    axis: int | None = None  # body axis of a spin (0, 1, 2)
    info: dict = field(default_factory=dict)


@dataclass
class MotionSample:
    """Truth at sample times: R (N,3,3) world←body, omega (N,3) rad/s body rate (with the Earth's rate
    where the trajectory's ``earth_rate`` is set: the inertial rate a gyro senses), f (N,3) m/s² specific
    force in body, a_world (N,3) m/s², euler (N,3)."""

    t: Array
    R: Array
    omega: Array
    f: Array
    a_world: Array
    euler: Array


def earth_rate_world(latitude_deg: float) -> Array:
    """The Earth's rotation (3,) rad/s in the local world frame (ENU: x east, y north, z up) at geodetic
    latitude ``latitude_deg``: Ω_E · (0, cos φ, sin φ) — along the Earth's axis, which points north and, in
    the northern hemisphere, up. (In NED it would read Ω_E · (cos φ, 0, −sin φ).) The transport rate of a
    vehicle moving over the curved Earth, v / R_E ≈ 20 / 6.4e6 = 3e-6 rad/s at 20 m/s, and the Coriolis
    acceleration 2 Ω_E × v ≤ 3e-3 m/s² are below every sensor's noise floor here and left out."""
    if not np.isfinite(latitude_deg) or abs(latitude_deg) > 90.0:
        raise ValueError(f"latitude must be within ±90°, not {latitude_deg!r}")
    phi = np.radians(latitude_deg)
    return OMEGA_EARTH * np.array([0.0, np.cos(phi), np.sin(phi)])


def with_earth_rate(m: MotionSample, w_E: Array | None) -> MotionSample:
    """``m`` with the gyro's truth ω replaced by the inertial rate ω + Rᵀ Ω_E (world ``w_E`` (3,) rad/s;
    None: unchanged). R is world ← body, so Rᵀ Ω_E is the Earth's rate on the body axes."""
    if w_E is None:
        return m
    return MotionSample(m.t, m.R, m.omega + np.einsum("nji,j->ni", m.R, np.asarray(w_E, float)), m.f,
                        m.a_world, m.euler)


class Trajectory:
    """A sequence of segments starting at rest at ``start`` Euler angles (rad)."""

    def __init__(self, start: tuple[float, float, float] = (0.0, 0.0, 0.0), g: float = G0) -> None:
        self.segments: list[Segment] = []
        self.start = np.asarray(start, float)
        self.g = g
        self.earth_rate: Array | None = None  # world (3,) rad/s added to the gyro truth (earth_rate_world)

    @property
    def current(self) -> Array:
        return self.segments[-1].end if self.segments else self.start

    @property
    def duration(self) -> float:
        return float(sum(s.T for s in self.segments))

    # -- building blocks --------------------------------------------------------------------
    def hold(self, T: float, **info) -> Trajectory:
        a = self.current.copy()

        def fn(tau: Array) -> tuple[Array, Array, Array]:
            n = tau.shape[0]
            return np.tile(a, (n, 1)), np.zeros((n, 3)), np.zeros((n, 3))

        self.segments.append(Segment("hold", T, fn, a, info=info))
        return self

    def move(self, target_deg: tuple[float, float, float], T: float, **info) -> Trajectory:
        a0 = self.current.copy()
        d = np.radians(target_deg) - a0

        def fn(tau: Array) -> tuple[Array, Array, Array]:
            s, ds, _ = smoothstep(tau / T)
            return a0 + s[:, None] * d, (ds / T)[:, None] * d, np.zeros((tau.shape[0], 3))

        self.segments.append(Segment("move", T, fn, a0 + d, info=info))
        return self

    def spin(self, euler_index: int, turns: float, T: float, body_axis: int, **info) -> Trajectory:
        """Turn one gimbal by ``turns`` revolutions; the caller guarantees the body axis it turns."""
        a0 = self.current.copy()
        d = np.zeros(3)
        d[euler_index] = 2 * np.pi * turns

        def fn(tau: Array) -> tuple[Array, Array, Array]:
            s, ds, _ = smoothstep(tau / T)
            return a0 + s[:, None] * d, (ds / T)[:, None] * d, np.zeros((tau.shape[0], 3))

        self.segments.append(Segment("spin", T, fn, a0 + d, axis=body_axis, info=dict(info, turns=turns)))
        return self

    def tumble(self, T: float, turns: tuple[float, float, float], theta_amp_deg: float, n_theta: int,
               **info) -> Trajectory:
        """Tumbling through all orientations: phi and psi make whole turns, theta swings ±amp."""
        a0 = self.current.copy()
        d = 2 * np.pi * np.asarray(turns, float)
        A = np.radians(theta_amp_deg)

        def fn(tau: Array) -> tuple[Array, Array, Array]:
            s, ds, _ = smoothstep(tau / T)
            w = np.pi * n_theta / T
            ang = a0 + s[:, None] * d
            rate = (ds / T)[:, None] * d
            ang[:, 1] += A * np.sin(w * tau) ** 2
            rate[:, 1] += A * w * np.sin(2 * w * tau)
            return ang, rate, np.zeros((tau.shape[0], 3))

        self.segments.append(Segment("tumble", T, fn, a0 + d, info=info))
        return self

    def flight(self, T: float, rng: np.random.Generator, **info) -> Trajectory:
        """Vehicle-like motion: roll/pitch swings of ±20°, yaw turns, and translational acceleration.

        Sums of sinusoids whose components all vanish at both ends (start and end at rest, level).
        """
        a0 = self.current.copy()
        k = 5
        amp = np.radians(rng.uniform(4, 12, (3, k)))
        amp[2] *= 4  # yaw swings wider than roll/pitch
        n = rng.integers(1, max(2, int(T / 3)), (3, k))
        pos_amp = rng.uniform(0.5, 3.0, (3, k))
        pos_n = rng.integers(1, max(2, int(T / 4)), (3, k))
        yaw_turns = float(rng.integers(1, 4))

        def fn(tau: Array) -> tuple[Array, Array, Array]:
            w = np.pi * n / T  # (3, k)
            arg = tau[:, None, None] * w[None]
            ang = a0 + (amp[None] * np.sin(arg) ** 2).sum(-1)
            rate = (amp[None] * w[None] * np.sin(2 * arg)).sum(-1)
            s, ds, _ = smoothstep(tau / T)
            ang[:, 2] += 2 * np.pi * yaw_turns * s
            rate[:, 2] += 2 * np.pi * yaw_turns * ds / T
            wp = np.pi * pos_n / T
            argp = tau[:, None, None] * wp[None]
            # p = A sin²(w t) → p'' = 2 A w² cos(2 w t)
            acc = (2 * pos_amp[None] * wp[None] ** 2 * np.cos(2 * argp)).sum(-1)
            return ang, rate, acc

        end = a0.copy()
        end[2] += 2 * np.pi * yaw_turns
        self.segments.append(Segment("flight", T, fn, end, info=info))
        return self

    # -- evaluation -------------------------------------------------------------------------
    def bounds(self) -> Array:
        return np.concatenate([[0.0], np.cumsum([s.T for s in self.segments])])

    def evaluate(self, t: Array) -> MotionSample:
        """Truth at times t (N,) s, vectorised per segment."""
        t = np.asarray(t, float)
        b = self.bounds()
        idx = np.clip(np.searchsorted(b, t, side="right") - 1, 0, len(self.segments) - 1)
        ang = np.empty((t.size, 3))
        rate = np.empty((t.size, 3))
        acc = np.empty((t.size, 3))
        for i in np.unique(idx):
            m = idx == i
            a, r, ac = self.segments[i].fn(t[m] - b[i])
            ang[m], rate[m], acc[m] = a, r, ac
        R = euler_to_R(ang)
        omega = euler_rates_to_body(ang, rate)
        f_world = acc + np.array([0.0, 0.0, self.g])
        f = np.einsum("nji,nj->ni", R, f_world)
        return with_earth_rate(MotionSample(t, R, omega, f, acc, ang), self.earth_rate)

    def annotations(self) -> list[dict]:
        """Segment list for the truth file: kind, t0, t1 and, for spins, the body axis."""
        b = self.bounds()
        out = []
        for s, t0, t1 in zip(self.segments, b[:-1], b[1:], strict=True):
            d = {"kind": s.kind, "t0": float(t0), "t1": float(t1)}
            if s.axis is not None:
                d["axis"] = "xyz"[s.axis]
            d.update({k: v for k, v in s.info.items() if isinstance(v, (int, float, str))})
            out.append(d)
        return out


# Orientations of the 12 static positions (paper, Sec. IV), (phi, theta) in deg: the 6 faces, and 6 at
# 45° where gravity in the body lies along (1,1,0), (1,0,1), (0,1,1), (-1,1,0), (1,0,-1), (0,-1,1)/√2,
# so that every cross-term of the accelerometer's ellipsoid is excited with both signs.
STATIC_POSITIONS = [
    (180, 0), (0, -90), (0, 90), (90, 0), (-90, 0), (0, 0),
    (90, -45), (0, -45), (45, 0), (90, 45), (180, -45), (-45, 0),
]


def paper_trajectory(rng: np.random.Generator, spin_T: float = 10.0) -> Trajectory:
    """The paper's calibration session on a 3-D rotation platform (~5 min).

    Gyro-bias rest (30 s) → 12 static positions (6 faces, 6 at 45°, 6 s each, at assorted headings) →
    rotation phases about body x, y and z, each with the axis horizontal and pointing east so that both
    gravity and the magnetic field sweep full circles, two turns forward and two back → a tumbling sphere
    (60 s) → rest.
    """
    tr = Trajectory()
    tr.hold(30.0, label="gyro-bias rest")
    for phi, theta in STATIC_POSITIONS:
        psi = float(rng.uniform(-180, 180))
        tr.move((phi, theta, psi), 2.5, label="to static position").hold(6.0, label="static position")
    # (euler angles at phase start, gimbal index that turns, body axis it turns about)
    phases = [((0, 0, 0), 0, 0), ((0, 0, -90), 1, 1), ((-90, 0, -90), 1, 2)]
    for start, gimbal, axis in phases:
        tr.move(start, 3.0, label="to phase").hold(4.0, label="phase rest")
        tr.spin(gimbal, 2.0, spin_T, axis, label="rotation phase").hold(4.0, label="phase rest")
        tr.spin(gimbal, -2.0, spin_T, axis, label="rotation phase").hold(4.0, label="phase rest")
    tr.move((0, 0, 0), 3.0).hold(3.0, label="rest")
    tr.tumble(60.0, (5.0, 0.0, 3.0), 80.0, 7, label="tumbling sphere")
    tr.hold(6.0, label="final rest")
    return tr


def flight_trajectory(rng: np.random.Generator, duration: float = 300.0) -> Trajectory:
    """A vehicle's flight: rest on the ground (20 s), then manoeuvres in 30-s legs, then rest."""
    tr = Trajectory(start=(0.0, 0.0, float(rng.uniform(-np.pi, np.pi))))
    tr.hold(20.0, label="ground rest")
    remaining = duration - 30.0
    while remaining > 1.0:
        T = min(30.0, remaining)
        tr.flight(T, rng, label="flight")
        remaining -= T
    tr.hold(10.0, label="ground rest")
    return tr
