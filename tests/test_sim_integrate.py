"""The flight simulator's integrator (onlinecal/sim/flight.py::_integrate, written out in scalars and compiled)
against the same dynamics in their vector form, plain numpy (the form the integrator had before session 14):
both vehicles, every branch (disarmed, armed on the ground, flight, the fixed-wing's take-off roll and brakes),
equal to rounding."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onlinecal.sim import flight
from onlinecal.sim.motion import G0


def _expm(w0: float, w1: float, w2: float, h: float) -> np.ndarray:
    """exp([ω]× h) by Rodrigues' formula."""
    E = np.eye(3)
    th = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2) * h
    if th < 1e-12:
        return E
    k0, k1, k2 = w0 * h / th, w1 * h / th, w2 * h / th
    K = np.array([[0.0, -k2, k1], [k2, 0.0, -k0], [-k1, k0, 0.0]])
    return E + math.sin(th) * K + (1.0 - math.cos(th)) * (K @ K)


def _log_vee(Q: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix (angle < π)."""
    c = min(1.0, max(-1.0, (Q[0, 0] + Q[1, 1] + Q[2, 2] - 1.0) / 2.0))
    th = math.acos(c)
    v = np.array([Q[2, 1] - Q[1, 2], Q[0, 2] - Q[2, 0], Q[1, 0] - Q[0, 1]])
    if th < 1e-9:
        return v / 2.0
    return v * (th / (2.0 * math.sin(th)))


def _frame_zx(z: np.ndarray, x_hint: np.ndarray) -> np.ndarray:
    """Rotation (world ← body) with body z along ``z`` and body x as close as possible to ``x_hint``."""
    zz = z / math.sqrt(z[0] ** 2 + z[1] ** 2 + z[2] ** 2)
    y = np.cross(zz, x_hint)
    y = y / math.sqrt(y[0] ** 2 + y[1] ** 2 + y[2] ** 2)
    x = np.cross(y, zz)
    R = np.empty((3, 3))
    R[:, 0], R[:, 1], R[:, 2] = x, y, zz
    return R


def _integrate_ref(kind: int, cmd: np.ndarray, R0: np.ndarray, g: float, dt: float, k_att: float, tau_rate: float,
               w_max: np.ndarray, k_v: np.ndarray, a_max: np.ndarray, k_drag: float, alpha_aoa: float
               ) -> tuple[np.ndarray, ...]:
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


def _commands(kind: int, n: int, seed: int) -> np.ndarray:
    """Command rows (n, 6) that visit every branch: disarmed on the ground, armed on the ground, airborne legs
    with changing setpoints, and (fixed-wing) a braked stop on the ground at the end."""
    rng = np.random.default_rng(seed)
    cmd = np.zeros((n, 6))
    k = np.arange(n)
    cmd[:, 4] = k >= n // 10
    cmd[:, 5] = (k < n // 5) | (k >= 9 * n // 10)
    for a in range(n // 5, 9 * n // 10, n // 10):
        b = a + n // 10
        if kind == 0:
            cmd[a:b, 0], cmd[a:b, 1], cmd[a:b, 2] = rng.uniform(-8, 8), rng.uniform(-8, 8), rng.uniform(-1.5, 1.5)
            cmd[a:b, 3] = rng.uniform(-np.pi, np.pi)
        else:
            cmd[a:b, 0], cmd[a:b, 2] = rng.uniform(16, 22), rng.uniform(-2, 2)
            cmd[a:b, 3] = np.radians(rng.uniform(-30, 30))
    if kind == 1:
        cmd[n // 10 : n // 5, 0] = 14.0  # the take-off roll
    return cmd


@pytest.mark.parametrize("kind", [0, 1])
def test_compiled_integrator_equals_the_vector_form(kind: int) -> None:
    n = 6000  # 6 s at 1 kHz: ground, flight and ground again (an SVD re-orthonormalisation every 1000 steps)
    cmd = _commands(kind, n, 7 + kind)
    R0 = np.array([[math.cos(0.3), -math.sin(0.3), 0.0], [math.sin(0.3), math.cos(0.3), 0.0], [0.0, 0.0, 1.0]])
    if kind == 0:
        args = (G0, 1e-3, 6.0, 0.03, np.radians([220.0, 220.0, 90.0]), np.array([1.2, 1.2, 1.5]),
                np.array([3.0, 2.0]), 0.2, 0.0)
    else:
        args = (G0, 1e-3, 5.0, 0.05, np.radians([90.0, 60.0, 60.0]), np.array([0.5, 0.5, 0.8]),
                np.array([3.0, 2.5]), 0.0, np.radians(3.0))
    got = flight._integrate(kind, cmd, R0, *args)
    ref = _integrate_ref(kind, cmd, R0, *args)
    moved = np.abs(ref[1]).max(axis=0)
    assert moved.min() > 0.05  # the commands turned the vehicle about every axis (a test of something)
    for name, g, r in zip(("R", "omega", "f", "a", "v", "thrust"), got, ref, strict=True):
        scale = max(1.0, float(np.abs(r).max()))
        assert np.abs(g - r).max() <= 1e-11 * scale, name
