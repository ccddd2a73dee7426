"""Flight profiles from vehicle physics: a multirotor and a fixed-wing, integrated forward in time.

Each vehicle is a point mass (position, velocity, world frame ENU, z up) driven by the force its
propulsion produces, and a rigid body whose attitude follows an attitude controller (body rate commanded
in proportion to the attitude error, with a first-order rate loop and rate limits). Nothing here is
written from the filter's assumptions: the specific force the accelerometer sees is whatever the vehicle's
forces make it, the body rate whatever the controller commands.

* **Multirotor**: thrust along body z (+ rotor drag ``−k_d · v`` in the body x/y plane: Leishman, Macdonald,
  Beard & McLain, "Quadrotors and accelerometers", IEEE Control Systems 34(1), 2014). To accelerate, the
  controller tilts the thrust vector: desired body z ∥ (a_cmd + g ẑ − drag), heading from a yaw setpoint.
  Velocity setpoints change every leg; a_cmd is a P velocity loop limited to 3 m/s² horizontally.
* **Fixed-wing**: coordinated flight (no sideslip): body x along the air velocity raised by the angle of
  attack, body z in the plane of the velocity and the required specific force, so the specific force stays
  in the body x–z plane and near body z; turns are banked, ψ̇ = g tan φ / V (Beard & McLain, *Small
  Unmanned Aircraft*, 2012, eq. 9.14). Take-off roll, climb, legs of level turns and climbs, descent,
  landing roll.

Both start with a ground rest, disarmed (no vibration), of ``rest_s`` ≥ 30 s, then arm on the ground.

Integration: fixed step ``dt`` (1 kHz) in numba; the body rate is held constant over a step and the
attitude advanced by its exact exponential, so ``evaluate(t)`` (zero-order hold of ω, R_k·exp(ω_k (t − t_k)))
gives an attitude and a gyro truth that agree to machine precision at any sample time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import NDArray

from .motion import G0, MotionSample, with_earth_rate

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

DT = 1e-3  # s, integration step
REST_S = 35.0  # s, disarmed ground rest before take-off (ArduPilot gyro calibration at boot needs ~ a few s)

# Rotor vibration on the accelerometer, per-axis RMS (m/s²) at the logged rate. ArduPilot's VIBE message
# (https://ardupilot.org/copter/docs/common-measuring-vibration.html): "vibration levels below 30 m/s/s are
# normally acceptable. Levels above 30 m/s/s may have problems and levels above 60 m/s/s nearly always have
# problems with position or altitude hold"; well-mounted frames show < 15. VIBE is the standard deviation of
# the raw accel after a 5-Hz high-pass, so it is the RMS of the vibration itself. Healthy default 3 m/s²
# (x, y) and 5 m/s² (z: the rotor plane's axis vibrates most) — a soft-mounted flight controller.
VIBE_HEALTHY = (3.0, 3.0, 5.0)
VIBE_BAD = (25.0, 25.0, 40.0)


@njit(cache=True)
def _expm(w0: float, w1: float, w2: float, h: float) -> Array:  # pragma: no cover - numba
    """exp([ω]× h) by Rodrigues' formula."""
    E = np.eye(3)
    th = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2) * h
    if th < 1e-12:
        return E
    k0, k1, k2 = w0 * h / th, w1 * h / th, w2 * h / th
    K = np.array([[0.0, -k2, k1], [k2, 0.0, -k0], [-k1, k0, 0.0]])
    return E + math.sin(th) * K + (1.0 - math.cos(th)) * (K @ K)


@njit(cache=True)
def _log_vee(Q: Array) -> Array:  # pragma: no cover - numba
    """Rotation vector of a rotation matrix (angle < π)."""
    c = min(1.0, max(-1.0, (Q[0, 0] + Q[1, 1] + Q[2, 2] - 1.0) / 2.0))
    th = math.acos(c)
    v = np.array([Q[2, 1] - Q[1, 2], Q[0, 2] - Q[2, 0], Q[1, 0] - Q[0, 1]])
    if th < 1e-9:
        return v / 2.0
    return v * (th / (2.0 * math.sin(th)))


@njit(cache=True)
def _frame_zx(z: Array, x_hint: Array) -> Array:  # pragma: no cover - numba
    """Rotation (world ← body) with body z along ``z`` and body x as close as possible to ``x_hint``."""
    zz = z / math.sqrt(z[0] ** 2 + z[1] ** 2 + z[2] ** 2)
    y = np.cross(zz, x_hint)
    y = y / math.sqrt(y[0] ** 2 + y[1] ** 2 + y[2] ** 2)
    x = np.cross(y, zz)
    R = np.empty((3, 3))
    R[:, 0], R[:, 1], R[:, 2] = x, y, zz
    return R


@njit(cache=True)
def _integrate(kind: int, cmd: Array, R0: Array, g: float, dt: float, k_att: float, tau_rate: float,
               w_max: Array, k_v: Array, a_max: Array, k_drag: float, alpha_aoa: float
               ) -> tuple[Array, Array, Array, Array, Array, Array]:  # pragma: no cover - numba
    """Forward integration over the command rows ``cmd`` (N, 6): per step the commanded velocity (world,
    3), the yaw setpoint (rad, multirotor) or bank angle (rad, fixed-wing), armed (0/1), on ground (0/1).

    Returns R (N, 3, 3) world←body, ω (N, 3) body rate held over each step, f (N, 3) specific force in
    body, a (N, 3) world acceleration, v (N, 3), thrust (N,) specific thrust m/s².
    """
    n = cmd.shape[0]
    Rs = np.empty((n, 3, 3))
    Ws = np.empty((n, 3))
    Fs = np.empty((n, 3))
    As = np.empty((n, 3))
    Vs = np.empty((n, 3))
    Ts = np.empty(n)
    R = R0.copy()
    w = np.zeros(3)
    v = np.zeros(3)
    ez = np.array([0.0, 0.0, 1.0])
    psi_fw = math.atan2(R0[1, 0], R0[0, 0])  # fixed-wing course
    for k in range(n):
        vc = cmd[k, :3]
        vn = v
        armed = cmd[k, 4] > 0.5
        ground = cmd[k, 5] > 0.5
        # velocity loop → commanded acceleration, limited
        a_cmd = k_v * (vc - v)
        ah = math.hypot(a_cmd[0], a_cmd[1])
        if ah > a_max[0]:
            a_cmd[0] *= a_max[0] / ah
            a_cmd[1] *= a_max[0] / ah
        a_cmd[2] = min(a_max[1], max(-a_max[1], a_cmd[2]))
        if kind == 0:
            # multirotor: rotor drag in the body x/y plane; thrust along body z
            vb = R.T @ v
            drag_b = np.array([-k_drag * vb[0], -k_drag * vb[1], 0.0])
            drag_w = R @ drag_b
            t_vec = a_cmd + g * ez - drag_w
            if ground or not armed:
                t_vec = g * ez  # on the ground: level, the ground carries the weight
            psi = cmd[k, 3]
            Rd = _frame_zx(t_vec, np.array([math.cos(psi), math.sin(psi), 0.0]))
            thrust = float(t_vec @ np.ascontiguousarray(R[:, 2])) if not ground else 0.0
            f_b = drag_b + np.array([0.0, 0.0, thrust])
            if ground:
                f_b = R.T @ (g * ez)  # the ground's reaction: specific force = −gravity
            a = R @ f_b - g * ez
            if ground:
                a = np.zeros(3)
        else:
            # fixed-wing: coordinated flight. State: ground speed sp along the course psi_fw, climb rate
            # v[2]. cmd[k, 0] is the commanded speed, cmd[k, 2] the climb rate, cmd[k, 3] the bank angle.
            sp = math.hypot(v[0], v[1])
            # the turn follows the bank the airframe actually has (roll angle of R), so the lift's
            # horizontal part is the centripetal force: ψ̇ = −g tan φ / V (FLU body, φ > 0 right wing down)
            phi_act = math.atan2(R[2, 1], R[2, 2])
            psi_dot = -g * math.tan(phi_act) / sp if (sp > 1.0 and not ground) else 0.0
            u = np.array([math.cos(psi_fw), math.sin(psi_fw), 0.0])
            lat = np.array([-math.sin(psi_fw), math.cos(psi_fw), 0.0])
            # on the ground: wheel brakes (stronger loop), no vertical motion
            kl = 4.0 * k_v[0] if ground else k_v[0]
            a_long = min(a_max[0], max(-a_max[0], kl * (cmd[k, 0] - sp)))
            if ground and cmd[k, 0] == 0.0 and sp < a_max[0] * dt:
                a_long = -sp / dt
            a_up = 0.0 if ground else min(a_max[1], max(-a_max[1], k_v[2] * (cmd[k, 2] - v[2])))
            a = a_long * u + psi_dot * sp * lat
            a[2] = a_up
            fw = a + g * ez  # specific force, world
            # desired attitude: heading along the course, pitch = flight-path angle + angle of attack
            # (nose up is a negative rotation about body y in this frame), bank as commanded
            th = 0.0 if ground else -(math.atan2(v[2], max(sp, 1.0)) + alpha_aoa)
            ph = 0.0 if ground else cmd[k, 3]
            cp, sp_, ct, st, cf, sf = (math.cos(psi_fw), math.sin(psi_fw), math.cos(th), math.sin(th),
                                       math.cos(ph), math.sin(ph))
            Rd = np.array([[cp * ct, cp * st * sf - sp_ * cf, cp * st * cf + sp_ * sf],
                           [sp_ * ct, sp_ * st * sf + cp * cf, sp_ * st * cf - cp * sf],
                           [-st, ct * sf, ct * cf]])
            thrust = a_long
            f_b = R.T @ fw
            psi_fw += psi_dot * dt
            vn = (sp + a_long * dt) * np.array([math.cos(psi_fw), math.sin(psi_fw), 0.0])
            vn[2] = 0.0 if ground else v[2] + a_up * dt
        # attitude loop: body rate ∝ attitude error, first-order rate response, limits
        e = _log_vee(R.T @ Rd)
        wc = k_att * e
        for i in range(3):
            wc[i] = min(w_max[i], max(-w_max[i], wc[i]))
        w = w + (wc - w) * (dt / tau_rate)
        Rs[k] = R
        Ws[k] = w
        Fs[k] = f_b
        As[k] = a
        Vs[k] = v
        Ts[k] = thrust
        R = R @ _expm(w[0], w[1], w[2], dt)
        if k % 1000 == 0:  # re-orthonormalise (SVD) against round-off
            U, _, Vt = np.linalg.svd(R)
            R = U @ Vt
        if kind == 0:
            v = np.zeros(3) if ground else v + a * dt
        else:
            v = vn
    return Rs, Ws, Fs, As, Vs, Ts


@dataclass
class VehicleTrajectory:
    """A forward-integrated flight on the grid ``t`` (step ``dt``). ``evaluate`` holds ω over each step and
    advances the attitude exactly; the ω and f it reports are sampled between step midpoints (``_at``), so
    a sample is not half a step ahead of the attitude; with
    ``earth_rate`` set, its ω is the inertial rate (+ Rᵀ Ω_E), the attitude stays Earth-fixed."""

    kind: str
    dt: float
    R: Array  # (N, 3, 3) world ← body at grid points
    omega: Array  # (N, 3) rad/s, held over [t_k, t_k+1)
    f: Array  # (N, 3) m/s², specific force in body
    a_world: Array  # (N, 3) m/s²
    v_world: Array  # (N, 3) m/s
    armed: BoolArray  # (N,) bool: motors running (vibration)
    throttle: Array  # (N,) 0..1, drives vibration amplitude and mag interference
    segs: list[dict[str, Any]] = field(default_factory=list)
    g: float = G0
    earth_rate: Array | None = None  # world (3,) rad/s added to the gyro truth (motion.earth_rate_world)

    @property
    def duration(self) -> float:
        return float((self.R.shape[0] - 1) * self.dt)

    def _idx(self, t: Array) -> tuple[NDArray[np.intp], Array]:
        k = np.clip(np.floor(np.asarray(t, float) / self.dt).astype(np.intp), 0, self.R.shape[0] - 1)
        return k, np.asarray(t, float) - k * self.dt

    def _at(self, x: Array, t: Array) -> Array:
        """A quantity held over each step (ω, f: (N, 3)) as a sensor samples it at t: linear between the step
        midpoints. Read as the held value, a sample on a grid point would be the next step's — the rate
        half a step (0.5 ms) ahead of the attitude, which diagnose found as a 0.58 ms magnetometer-to-gyro
        time offset on a clean flight. The attitude stays the exact integral of the held rate."""
        m = np.asarray(t, float) / self.dt - 0.5
        k = np.floor(m).astype(np.intp)
        fr = (m - k)[:, None]
        last = x.shape[0] - 1
        return (1.0 - fr) * x[np.clip(k, 0, last)] + fr * x[np.clip(k + 1, 0, last)]

    def evaluate(self, t: Array) -> MotionSample:
        """Truth at times t (N,) s: R (N,3,3), ω (N,3), f (N,3), a_world (N,3), ZYX Euler angles (N,3)."""
        t = np.asarray(t, float)
        k, h = self._idx(t)
        w = self.omega[k]
        th = np.linalg.norm(w, axis=1) * h
        kk = np.where(th[:, None] > 1e-15, w * (h / np.maximum(th, 1e-300))[:, None], 0.0)
        K = np.zeros((t.size, 3, 3))
        K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -kk[:, 2], kk[:, 1], -kk[:, 0]
        K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = kk[:, 2], -kk[:, 1], kk[:, 0]
        E = np.eye(3) + np.sin(th)[:, None, None] * K + (1 - np.cos(th))[:, None, None] * (K @ K)
        R = self.R[k] @ E
        w = self._at(self.omega, t)
        f = self._at(self.f, t)
        a = np.einsum("nij,nj->ni", R, f) - np.array([0.0, 0.0, self.g])
        eul = np.stack([np.arctan2(R[:, 2, 1], R[:, 2, 2]), -np.arcsin(np.clip(R[:, 2, 0], -1, 1)),
                        np.arctan2(R[:, 1, 0], R[:, 0, 0])], axis=1)
        return with_earth_rate(MotionSample(t, R, w.copy(), f.copy(), a, eul), self.earth_rate)

    def at(self, name: str, t: Array) -> Array:
        """A grid quantity (``armed``, ``throttle``, ``v_world``) at times t (zero-order hold)."""
        k, _ = self._idx(t)
        return np.asarray(getattr(self, name))[k]

    def annotations(self) -> list[dict]:
        return [dict(s) for s in self.segs]


def _legs(rng: np.random.Generator, t0: float, t1: float, lo: float, hi: float) -> list[tuple[float, float]]:
    """Consecutive legs of random length in [lo, hi] s covering [t0, t1)."""
    out, t = [], t0
    while t < t1 - 1e-9:
        T = float(rng.uniform(lo, hi))
        T = min(T, t1 - t) if t1 - (t + T) > lo / 2 else t1 - t
        out.append((t, t + T))
        t += T
    return out


def multirotor_trajectory(rng: np.random.Generator, duration: float = 600.0, rest_s: float = REST_S,
                          dt: float = DT) -> VehicleTrajectory:
    """A multirotor's flight: disarmed rest, arm, climb to ~10 m, legs of constant velocity setpoints
    (0–8 m/s horizontal, ±1.5 m/s vertical) with yaw turns of up to ±180° per leg at ≤ 45°/s, return to a
    hover, descend, land, disarm, rest."""
    n = int(round(duration / dt)) + 1
    t = np.arange(n) * dt
    cmd = np.zeros((n, 6))
    psi0 = float(rng.uniform(-np.pi, np.pi))
    cmd[:, 3] = psi0
    t_arm, t_to = rest_s, rest_s + 3.0
    t_land = duration - 25.0
    t_down = t_land + 10.0
    cmd[:, 4] = (t >= t_arm) & (t < t_down + 2.0)
    cmd[:, 5] = (t < t_to) | (t >= t_down)
    segs: list[dict[str, Any]] = [
        {"kind": "hold", "t0": 0.0, "t1": t_arm, "label": "ground rest (disarmed)"},
        {"kind": "hold", "t0": t_arm, "t1": t_to, "label": "armed on the ground"},
    ]
    climb = (t >= t_to) & (t < t_to + 6.0)
    cmd[climb, 2] = 1.7
    segs.append({"kind": "flight", "t0": t_to, "t1": t_to + 6.0, "label": "take-off"})
    psi = psi0
    for a, b in _legs(rng, t_to + 6.0, t_land, 8.0, 25.0):
        m = (t >= a) & (t < b)
        sp, dirn = float(rng.uniform(0, 8)), float(rng.uniform(-np.pi, np.pi))
        vz = float(rng.choice([0.0, 0.0, rng.uniform(-1.5, 1.5)]))
        cmd[m, 0], cmd[m, 1], cmd[m, 2] = sp * np.cos(dirn), sp * np.sin(dirn), vz
        turn = float(rng.uniform(-np.pi, np.pi))
        rate = np.radians(45.0) * np.sign(turn)
        tt = t[m] - a
        cmd[m, 3] = psi + np.where(np.abs(rate * tt) < abs(turn), rate * tt, turn)
        psi += turn
        segs.append({"kind": "flight", "t0": a, "t1": b, "label": "leg", "speed": sp})
    m = t >= t_land
    cmd[m, 3] = psi
    cmd[(t >= t_land + 4.0) & (t < t_down), 2] = -1.0
    segs.append({"kind": "flight", "t0": t_land, "t1": t_down, "label": "descent and landing"})
    segs.append({"kind": "hold", "t0": t_down, "t1": duration, "label": "ground rest"})
    # on the ground the vehicle stands level at its last heading: the rest is a rest
    R0 = _rz(psi0)
    R, W, F, A, V, T = _integrate(0, cmd, R0, G0, dt, 6.0, 0.03, np.radians([220.0, 220.0, 90.0]),
                                  np.array([1.2, 1.2, 1.5]), np.array([3.0, 2.0]), 0.2, 0.0)
    # when landed, hold the attitude the vehicle came to rest at, with zero rate (the ground holds it)
    throttle = np.where(cmd[:, 4] > 0.5, np.clip(T / G0, 0, 2) * 0.45 + 0.05, 0.0)
    _ground_fix(R, W, F, A, cmd[:, 5] > 0.5, G0)
    return VehicleTrajectory("multirotor", dt, R, W, F, A, V, cmd[:, 4] > 0.5, throttle, segs)


def fixedwing_trajectory(rng: np.random.Generator, duration: float = 600.0, rest_s: float = REST_S,
                         dt: float = DT) -> VehicleTrajectory:
    """A fixed-wing's flight: disarmed rest, engine run-up, take-off roll to 14 m/s, climb, legs of level
    flight, banked turns (±10–30°) and climbs at 16–22 m/s, descent, landing roll, rest."""
    n = int(round(duration / dt)) + 1
    t = np.arange(n) * dt
    cmd = np.zeros((n, 6))
    psi0 = float(rng.uniform(-np.pi, np.pi))
    t_arm, t_roll = rest_s, rest_s + 3.0
    t_air = t_roll + 8.0
    t_app = duration - 45.0
    t_td = duration - 20.0
    cmd[:, 4] = (t >= t_arm) & (t < t_td + 8.0)
    cmd[:, 5] = (t < t_air) | (t >= t_td)
    segs: list[dict[str, Any]] = [
        {"kind": "hold", "t0": 0.0, "t1": t_arm, "label": "ground rest (disarmed)"},
        {"kind": "hold", "t0": t_arm, "t1": t_roll, "label": "engine run-up"},
        {"kind": "flight", "t0": t_roll, "t1": t_air, "label": "take-off roll"},
    ]
    # commands: speed (m/s, along the course) in column 0, climb rate in column 2, bank angle in column 3
    cmd[(t >= t_roll) & (t < t_air), 0] = 14.0
    climb = (t >= t_air) & (t < t_air + 12.0)
    cmd[climb, 0], cmd[climb, 2] = 17.0, 2.5
    segs.append({"kind": "flight", "t0": t_air, "t1": t_air + 12.0, "label": "climb-out"})
    for a, b in _legs(rng, t_air + 12.0, t_app, 10.0, 30.0):
        m = (t >= a) & (t < b)
        cmd[m, 0] = float(rng.uniform(16, 22))
        turn = int(rng.integers(0, 3)) > 0  # two legs in three are turns
        bank = 0.0
        if turn:
            bank = np.radians(float(rng.uniform(10, 30))) * float(rng.choice([-1.0, 1.0]))
            tt = t[m] - a
            # roll in and out over 2 s each (the attitude loop's rate limit shapes it further)
            cmd[m, 3] = bank * np.clip(np.minimum(tt, (b - a) - tt) / 2.0, 0, 1)
        cmd[m, 2] = float(rng.choice([0.0, 0.0, rng.uniform(-2.0, 2.0)]))
        segs.append({"kind": "flight", "t0": a, "t1": b, "label": "turn" if turn else "leg",
                     "bank_deg": float(np.degrees(bank))})
    m = (t >= t_app) & (t < t_td)
    cmd[m, 0], cmd[m, 2] = 15.0, -1.5
    segs.append({"kind": "flight", "t0": t_app, "t1": t_td, "label": "approach"})
    segs.append({"kind": "flight", "t0": t_td, "t1": t_td + 10.0, "label": "landing roll"})
    segs.append({"kind": "hold", "t0": t_td + 10.0, "t1": duration, "label": "ground rest"})
    R, W, F, A, V, T = _integrate(1, cmd, _rz(psi0), G0, dt, 5.0, 0.05, np.radians([90.0, 60.0, 60.0]),
                                  np.array([0.5, 0.5, 0.8]), np.array([3.0, 2.5]), 0.0, np.radians(3.0))
    _ground_fix(R, W, F, A, (cmd[:, 5] > 0.5) & (np.linalg.norm(V, axis=1) == 0.0), G0)
    throttle = np.where(cmd[:, 4] > 0.5, 0.3 + 0.05 * np.clip(A[:, 0] ** 2 + A[:, 1] ** 2, 0, 4), 0.0)
    return VehicleTrajectory("fixedwing", dt, R, W, F, A, V, cmd[:, 4] > 0.5, throttle, segs)


def _rz(psi: float) -> Array:
    c, s = math.cos(psi), math.sin(psi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ground_fix(R: Array, W: Array, F: Array, A: Array, ground: BoolArray, g: float) -> None:
    """On the ground after landing the attitude is whatever it came down at (it is level within the
    controller's lag); rates there are zero and the specific force is −gravity in body (in place)."""
    idx = np.flatnonzero(ground)
    if idx.size == 0:
        return
    W[idx] = 0.0
    # the attitude stops turning: hold each ground stretch at its first attitude
    starts = idx[np.concatenate([[True], np.diff(idx) > 1])]
    for s0 in starts:
        e = s0
        while e < ground.size and ground[e]:
            e += 1
        R[s0:e] = R[s0]
        F[s0:e] = R[s0].T @ np.array([0.0, 0.0, g])
        A[s0:e] = 0.0


def vibration(traj: VehicleTrajectory, t: Array, rms: tuple[float, float, float], seed: int) -> Array:
    """Rotor vibration (N, 3) m/s² at the sample times: a blade-pass tone whose frequency follows the
    rotor speed (∝ √thrust), its first harmonic and a broadband part, scaled so that the per-axis RMS in
    hover is ``rms``; zero while disarmed. Sampled at the log's instants without anti-alias filter, as a
    raw accelerometer log shows it (the tone aliases)."""
    rng = np.random.default_rng([seed & 0xFFFFFFFF, 0x5EB])
    armed = traj.at("armed", t).astype(float)
    thr = traj.at("throttle", t)
    # 10-inch props near hover: ~6000 rpm → 100 Hz rotor, 200 Hz blade pass (2 blades); ∝ √thrust
    f_rot = 100.0 * np.sqrt(np.clip(thr / 0.5, 0.05, 4.0))
    dtt = np.diff(t, prepend=t[0])
    phase = 2 * np.pi * np.cumsum(f_rot * dtt)
    amp = np.sqrt(np.clip(thr / 0.5, 0.0, 4.0))
    out = np.empty((t.size, 3))
    for i in range(3):
        p0, p1 = rng.uniform(0, 2 * np.pi, 2)
        tone = np.sqrt(2) * (0.8 * np.sin(phase + p0) + 0.45 * np.sin(2 * phase + p1))
        broad = 0.4 * rng.normal(0, 1, t.size)
        x = tone + broad  # unit-ish RMS: 0.8² + 0.45² + 0.4² ≈ 1.0
        out[:, i] = rms[i] * x * amp * armed
    return out


def mag_interference(traj: VehicleTrajectory, t: Array, per_throttle: Array) -> Array:
    """Magnetometer interference (N, 3), in units of the field, ∝ throttle (motor current): ArduPilot's
    compassmot measures it per ampere and judges < 30 % of the field at full throttle acceptable
    (https://ardupilot.org/copter/docs/common-compass-setup-advanced.html#compassmot)."""
    return traj.at("throttle", t)[:, None] * np.asarray(per_throttle, float)[None]
