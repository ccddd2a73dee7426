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
def _expm_into(w0: float, w1: float, w2: float, h: float, E: Array) -> None:  # pragma: no cover - numba
    """E (3, 3) ← exp([ω]× h) by Rodrigues' formula, E = I + sin θ K + (1 − cos θ) K², K = [ω]× h / θ."""
    th = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2) * h
    for i in range(3):
        for j in range(3):
            E[i, j] = 1.0 if i == j else 0.0
    if th < 1e-12:
        return
    k0, k1, k2 = w0 * h / th, w1 * h / th, w2 * h / th
    s, c1 = math.sin(th), 1.0 - math.cos(th)
    # K² = k kᵀ − |k|² I with |k| = 1
    E[0, 0] += c1 * (k0 * k0 - 1.0)
    E[1, 1] += c1 * (k1 * k1 - 1.0)
    E[2, 2] += c1 * (k2 * k2 - 1.0)
    E[0, 1] += -s * k2 + c1 * k0 * k1
    E[1, 0] += s * k2 + c1 * k0 * k1
    E[0, 2] += s * k1 + c1 * k0 * k2
    E[2, 0] += -s * k1 + c1 * k0 * k2
    E[1, 2] += -s * k0 + c1 * k1 * k2
    E[2, 1] += s * k0 + c1 * k1 * k2


@njit(cache=True)
def _log_vee_rel(R: Array, Rd: Array, out: Array) -> None:  # pragma: no cover - numba
    """out (3,) ← the rotation vector of Q = Rᵀ Rd (both (3, 3); angle < π)."""
    q = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            q[i, j] = R[0, i] * Rd[0, j] + R[1, i] * Rd[1, j] + R[2, i] * Rd[2, j]
    c = min(1.0, max(-1.0, (q[0, 0] + q[1, 1] + q[2, 2] - 1.0) / 2.0))
    th = math.acos(c)
    f = 0.5 if th < 1e-9 else th / (2.0 * math.sin(th))
    out[0], out[1], out[2] = (q[2, 1] - q[1, 2]) * f, (q[0, 2] - q[2, 0]) * f, (q[1, 0] - q[0, 1]) * f


@njit(cache=True)
def _frame_zx_into(z0: float, z1: float, z2: float, h0: float, h1: float, h2: float,
                   R: Array) -> None:  # pragma: no cover - numba
    """R (3, 3) ← the rotation (world ← body) with body z along z and body x as close as possible to the hint h."""
    nz = math.sqrt(z0 * z0 + z1 * z1 + z2 * z2)
    z0, z1, z2 = z0 / nz, z1 / nz, z2 / nz
    y0, y1, y2 = z1 * h2 - z2 * h1, z2 * h0 - z0 * h2, z0 * h1 - z1 * h0
    ny = math.sqrt(y0 * y0 + y1 * y1 + y2 * y2)
    y0, y1, y2 = y0 / ny, y1 / ny, y2 / ny
    R[0, 0], R[1, 0], R[2, 0] = y1 * z2 - y2 * z1, y2 * z0 - y0 * z2, y0 * z1 - y1 * z0
    R[0, 1], R[1, 1], R[2, 1] = y0, y1, y2
    R[0, 2], R[1, 2], R[2, 2] = z0, z1, z2


@njit(cache=True)
def _integrate(kind: int, cmd: Array, R0: Array, g: float, dt: float, k_att: float, tau_rate: float,
               w_max: Array, k_v: Array, a_max: Array, k_drag: float, alpha_aoa: float
               ) -> tuple[Array, Array, Array, Array, Array, Array]:  # pragma: no cover - numba
    """Forward integration over the command rows ``cmd`` (N, 6): per step the commanded velocity (world,
    3), the yaw setpoint (rad, multirotor) or bank angle (rad, fixed-wing), armed (0/1), on ground (0/1).

    Returns R (N, 3, 3) world←body, ω (N, 3) body rate held over each step, f (N, 3) specific force in
    body, a (N, 3) world acceleration, v (N, 3), thrust (N,) specific thrust m/s².

    Written out in scalars on a few preallocated 3×3 arrays (no array is made per step: an hour at 1 kHz
    is 3.6 million steps, and the small-array allocations and BLAS calls of the vector form cost ~3 µs
    each, 10 s an hour; the same arithmetic, equal to ~1e-15).
    """
    n = cmd.shape[0]
    Rs = np.empty((n, 3, 3))
    Ws = np.empty((n, 3))
    Fs = np.empty((n, 3))
    As = np.empty((n, 3))
    Vs = np.empty((n, 3))
    Ts = np.empty(n)
    R = R0.copy()
    Rd = np.empty((3, 3))
    E = np.empty((3, 3))
    Rn = np.empty((3, 3))
    e = np.empty(3)
    w = np.zeros(3)
    v = np.zeros(3)
    vn = np.zeros(3)
    f_b = np.empty(3)
    a = np.empty(3)
    psi_fw = math.atan2(R0[1, 0], R0[0, 0])  # fixed-wing course
    for k in range(n):
        armed = cmd[k, 4] > 0.5
        ground = cmd[k, 5] > 0.5
        # velocity loop → commanded acceleration, limited
        ac0, ac1, ac2 = k_v[0] * (cmd[k, 0] - v[0]), k_v[1] * (cmd[k, 1] - v[1]), k_v[2] * (cmd[k, 2] - v[2])
        ah = math.hypot(ac0, ac1)
        if ah > a_max[0]:
            ac0 *= a_max[0] / ah
            ac1 *= a_max[0] / ah
        ac2 = min(a_max[1], max(-a_max[1], ac2))
        if kind == 0:
            # multirotor: rotor drag in the body x/y plane; thrust along body z
            vb0 = R[0, 0] * v[0] + R[1, 0] * v[1] + R[2, 0] * v[2]  # Rᵀ v
            vb1 = R[0, 1] * v[0] + R[1, 1] * v[1] + R[2, 1] * v[2]
            db0, db1 = -k_drag * vb0, -k_drag * vb1
            t0 = ac0 - (R[0, 0] * db0 + R[0, 1] * db1)  # a_cmd + g ẑ − R drag_b
            t1 = ac1 - (R[1, 0] * db0 + R[1, 1] * db1)
            t2 = ac2 + g - (R[2, 0] * db0 + R[2, 1] * db1)
            if ground or not armed:
                t0, t1, t2 = 0.0, 0.0, g  # on the ground: level, the ground carries the weight
            psi = cmd[k, 3]
            _frame_zx_into(t0, t1, t2, math.cos(psi), math.sin(psi), 0.0, Rd)
            thrust = 0.0 if ground else t0 * R[0, 2] + t1 * R[1, 2] + t2 * R[2, 2]
            if ground:
                # the ground's reaction: specific force = −gravity, Rᵀ (g ẑ); no acceleration
                f_b[0], f_b[1], f_b[2] = g * R[2, 0], g * R[2, 1], g * R[2, 2]
                a[0], a[1], a[2] = 0.0, 0.0, 0.0
            else:
                f_b[0], f_b[1], f_b[2] = db0, db1, thrust
                for i in range(3):
                    a[i] = R[i, 0] * f_b[0] + R[i, 1] * f_b[1] + R[i, 2] * f_b[2]
                a[2] -= g
        else:
            # fixed-wing: coordinated flight. State: ground speed sp along the course psi_fw, climb rate
            # v[2]. cmd[k, 0] is the commanded speed, cmd[k, 2] the climb rate, cmd[k, 3] the bank angle.
            sp = math.hypot(v[0], v[1])
            # the turn follows the bank the airframe actually has (roll angle of R), so the lift's
            # horizontal part is the centripetal force: ψ̇ = −g tan φ / V (FLU body, φ > 0 right wing down)
            phi_act = math.atan2(R[2, 1], R[2, 2])
            psi_dot = -g * math.tan(phi_act) / sp if (sp > 1.0 and not ground) else 0.0
            cu, su = math.cos(psi_fw), math.sin(psi_fw)
            # on the ground: wheel brakes (stronger loop), no vertical motion
            kl = 4.0 * k_v[0] if ground else k_v[0]
            a_long = min(a_max[0], max(-a_max[0], kl * (cmd[k, 0] - sp)))
            if ground and cmd[k, 0] == 0.0 and sp < a_max[0] * dt:
                a_long = -sp / dt
            a_up = 0.0 if ground else min(a_max[1], max(-a_max[1], k_v[2] * (cmd[k, 2] - v[2])))
            # along the course u = (cos ψ, sin ψ, 0), across it (−sin ψ, cos ψ, 0)
            a[0] = a_long * cu + psi_dot * sp * -su
            a[1] = a_long * su + psi_dot * sp * cu
            a[2] = a_up
            fw0, fw1, fw2 = a[0], a[1], a[2] + g  # specific force, world
            # desired attitude: heading along the course, pitch = flight-path angle + angle of attack
            # (nose up is a negative rotation about body y in this frame), bank as commanded
            th = 0.0 if ground else -(math.atan2(v[2], max(sp, 1.0)) + alpha_aoa)
            ph = 0.0 if ground else cmd[k, 3]
            cp, sp_, ct, st, cf, sf = cu, su, math.cos(th), math.sin(th), math.cos(ph), math.sin(ph)
            Rd[0, 0], Rd[0, 1], Rd[0, 2] = cp * ct, cp * st * sf - sp_ * cf, cp * st * cf + sp_ * sf
            Rd[1, 0], Rd[1, 1], Rd[1, 2] = sp_ * ct, sp_ * st * sf + cp * cf, sp_ * st * cf - cp * sf
            Rd[2, 0], Rd[2, 1], Rd[2, 2] = -st, ct * sf, ct * cf
            thrust = a_long
            for i in range(3):
                f_b[i] = R[0, i] * fw0 + R[1, i] * fw1 + R[2, i] * fw2
            psi_fw += psi_dot * dt
            spn = sp + a_long * dt
            vn[0], vn[1] = spn * math.cos(psi_fw), spn * math.sin(psi_fw)
            vn[2] = 0.0 if ground else v[2] + a_up * dt
        # attitude loop: body rate ∝ attitude error, first-order rate response, limits
        _log_vee_rel(R, Rd, e)
        for i in range(3):
            wc = min(w_max[i], max(-w_max[i], k_att * e[i]))
            w[i] = w[i] + (wc - w[i]) * (dt / tau_rate)
        Rs[k] = R
        Ws[k] = w
        Fs[k] = f_b
        As[k] = a
        Vs[k] = v
        Ts[k] = thrust
        _expm_into(w[0], w[1], w[2], dt, E)
        for i in range(3):
            for j in range(3):
                Rn[i, j] = R[i, 0] * E[0, j] + R[i, 1] * E[1, j] + R[i, 2] * E[2, j]
        R[:, :] = Rn
        if k % 1000 == 0:  # re-orthonormalise (SVD) against round-off
            U, _, Vt = np.linalg.svd(R)
            R[:, :] = U @ Vt
        if kind == 0:
            if ground:
                v[0], v[1], v[2] = 0.0, 0.0, 0.0
            else:
                for i in range(3):
                    v[i] = v[i] + a[i] * dt
        else:
            v[:] = vn
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


def _span(t: NDArray[np.floating[Any]], a: float, b: float) -> slice:
    """The grid points of the sorted grid t (N,) with a ≤ t < b, as a slice: the mask ``(t >= a) & (t < b)``
    without a pass over the whole grid per leg (an hour's flight has ~200 legs on 3.6 million points)."""
    return slice(int(np.searchsorted(t, a, "left")), int(np.searchsorted(t, b, "left")))


def multirotor_trajectory(rng: np.random.Generator, duration: float = 600.0, rest_s: float = REST_S,
                          dt: float = DT, legs_s: tuple[float, float] = (8.0, 25.0)) -> VehicleTrajectory:
    """A multirotor's flight: disarmed rest, arm, climb to ~10 m, legs of constant velocity setpoints
    (0–8 m/s horizontal, ±1.5 m/s vertical) lasting ``legs_s`` (shortest, longest) s with yaw turns of up to
    ±180° per leg at ≤ 45°/s, return to a hover, descend, land, disarm, rest."""
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
    for a, b in _legs(rng, t_to + 6.0, t_land, *legs_s):
        leg = _span(t, a, b)
        sp, dirn = float(rng.uniform(0, 8)), float(rng.uniform(-np.pi, np.pi))
        vz = float(rng.choice([0.0, 0.0, rng.uniform(-1.5, 1.5)]))
        cmd[leg, 0], cmd[leg, 1], cmd[leg, 2] = sp * np.cos(dirn), sp * np.sin(dirn), vz
        turn = float(rng.uniform(-np.pi, np.pi))
        rate = np.radians(45.0) * np.sign(turn)
        tt = t[leg] - a
        cmd[leg, 3] = psi + np.where(np.abs(rate * tt) < abs(turn), rate * tt, turn)
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
                         dt: float = DT, legs_s: tuple[float, float] = (10.0, 30.0)) -> VehicleTrajectory:
    """A fixed-wing's flight: disarmed rest, engine run-up, take-off roll to 14 m/s, climb, legs lasting
    ``legs_s`` (shortest, longest) s of level flight, banked turns (±10–30°: at the longest, a loiter's circles)
    and climbs at 16–22 m/s, descent, landing roll, rest."""
    n = int(round(duration / dt)) + 1
    t = np.arange(n) * dt
    cmd = np.zeros((n, 6))
    psi0 = float(rng.uniform(-np.pi, np.pi))
    t_arm, t_roll = rest_s, rest_s + 3.0
    t_air = t_roll + 8.0
    # approach and landing in the last 45 s — never before the climb-out ends: a session shorter than its
    # schedule stops where it is (before session 18 a 60-s one commanded the approach on the runway before
    # take-off, the disarmed vehicle accelerating at 3 m/s²)
    t_app = max(duration - 45.0, t_air + 12.0)
    t_td = t_app + 25.0
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
    for a, b in _legs(rng, t_air + 12.0, t_app, *legs_s):
        leg = _span(t, a, b)
        cmd[leg, 0] = float(rng.uniform(16, 22))
        turn = int(rng.integers(0, 3)) > 0  # two legs in three are turns
        bank = 0.0
        if turn:
            bank = np.radians(float(rng.uniform(10, 30))) * float(rng.choice([-1.0, 1.0]))
            tt = t[leg] - a
            # roll in and out over 2 s each (the attitude loop's rate limit shapes it further)
            cmd[leg, 3] = bank * np.clip(np.minimum(tt, (b - a) - tt) / 2.0, 0, 1)
        cmd[leg, 2] = float(rng.choice([0.0, 0.0, rng.uniform(-2.0, 2.0)]))
        segs.append({"kind": "flight", "t0": a, "t1": b, "label": "turn" if turn else "leg",
                     "bank_deg": float(np.degrees(bank))})
    m = (t >= t_app) & (t < t_td)
    cmd[m, 0], cmd[m, 2] = 15.0, -1.5
    for kind, a, b, label in (("flight", t_app, t_td, "approach"), ("flight", t_td, t_td + 10.0, "landing roll"),
                              ("hold", t_td + 10.0, duration, "ground rest")):
        if a < duration:
            segs.append({"kind": kind, "t0": a, "t1": b, "label": label})
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
