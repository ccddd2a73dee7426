"""Where the time goes inside ``fastpath.motion_kernel`` (issue 15, eighth round): its stages timed with a compiled
copy that runs the same sub-kernels on the same arguments in the same order, one stage repeated ``--reps`` times
and the others once; a stage's cost is the difference from the copy that repeats none, over reps − 1 (so each
stage is timed on its own, not as the small difference of two long runs). The arguments are those of real blocks:
every 10th call of the 10-min benchmark flight's fast-path replay (the one ``bench_ukf.py`` times), captured as the
replay runs.

    PYTHONPATH=. python benchmarks/prof_motion_kernel.py [--reps 20] [--passes 5] [--minutes 10]

Prints per stage the best (over passes) µs per block and per IMU sample, and, for comparison, ``motion_kernel``
itself called from Python on the same arguments (its dispatch and the boxing of its results included).
"""

from __future__ import annotations

import argparse
import math
import os
import time
from typing import Any

for _v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numba  # noqa: E402
import numpy as np  # noqa: E402

from onlinecal.sim import simulate  # noqa: E402
from onlinecal.ukf import fastpath, replay  # noqa: E402
from onlinecal.ukf.fastpath import (  # noqa: E402
    _bilinear_var,
    _deviation,
    _model_pair_shared,
    block_q_kernel,
    fold_kernel,
    motion_measurement_kernel,
)
from onlinecal.ukf.kernels_propagate import propagate_kernel, rot_log_rel_kernel  # noqa: E402
from onlinecal.ukf.kernels_update import (  # noqa: E402
    _gate,
    _kept,
    gain_update_kernel,
    innovation_kernel,
    sigma_points_kernel,
)

try:  # (the eighth round's; before it, the full transform: so the profile also runs on earlier commits)
    from onlinecal.ukf.kernels_update import unscented_motion_kernel
except ImportError:  # pragma: no cover - an earlier commit's package on PYTHONPATH
    from onlinecal.ukf.kernels_update import unscented_kernel

    @numba.njit
    def unscented_motion_kernel(X: Any, Wm: Any, Wc: Any, q: Any, P: Any) -> Any:
        return unscented_kernel(X, Wm, Wc, q)

STAGES = ["block Q", "sigma points (scale·P, Cholesky, X)",
          "sensor models (gather, distinct rows, model_pair)", "propagation through the block's samples",
          "attitude errors (rot_log_rel) + block Q's bilinear term", "unscented transform (x_pred, Y, P_pred)",
          "ω of the mean, specific force, deviation", "measurement predictions Z (accel, mag)",
          "innovation statistics (z_pred, S_zz, Pxz, NIS)", "gate, kept components, gain + covariance",
          "fold (P symmetrised, R, yaw variance, finiteness)"]

@numba.njit
def stages(rep: int, reps: int, x: Any, P: Any, scale: float, order: Any, R_nom: Any, w: Any, dt: Any, c_mag: Any,
           has_mag: bool, dyn: Any, Wm: Any, Wc: Any, rw: Any, rate: float, sigma_gyr: float, mag_q: bool,
           mag_dens: float, field_gauss: float, rw_factor: float, earth: bool, sigma_rest: float, tau: float,
           om2: float, q_att_jerk: float, dt_blk: float, w_mean: Any, a_mean: Any, sig_mean: float, gravity: float,
           g0: int, a0: int, m0: int, dip_col: int, use_acc: bool, var_a: float, z_mag: Any, var_mag: float,
           hold_acc: int, hold_mag: int, gates: Any, consider: Any, damp: float, yaw_var: float, two: float) -> float:
    """motion_kernel's work, its stages in order (see STAGES), stage ``rep`` (1-based; 0: none) ``reps`` times and
    the others once; a checksum (so nothing is optimised away). var_a: the accel's R as the block's motion_kernel
    formed it."""
    chk = 0.0
    for _ in range(reps if rep == 1 else 1):  # stage 1
        q = block_q_kernel(rw, dt_blk, rate, sigma_gyr, m0 if mag_q else -1, mag_dens, field_gauss, rw_factor, x, P,
                           earth, g0, g0 + 3, sigma_rest, tau, om2, two)
        chk += q[0]
    for _ in range(reps if rep == 2 else 1):  # stage 2
        X, ok = sigma_points_kernel(x, P, scale, order)
        chk += X[1, 1]
    for _ in range(reps if rep == 3 else 1):  # stage 3
        S, Sd = X.shape[0], dyn.shape[0]
        p = np.empty((Sd + (2 * S if has_mag else S), 12))
        for si in range(Sd):
            for k in range(12):
                p[si, k] = X[dyn[si], g0 + k]
        for s in range(S):
            for k in range(12):
                p[Sd + s, k] = X[s, a0 + k]
                if has_mag:
                    p[Sd + S + s, k] = X[s, m0 + k]
        o_all, M_all, Mi_all = _model_pair_shared(p, Sd, Sd + S)
        o_g = o_all[:Sd].copy()
        M_g = M_all[:Sd].copy()
        chk += M_g[1, 1, 1]
    for _ in range(reps if rep == 4 else 1):  # stage 4
        R_end, f_body, h_body = propagate_kernel(X, R_nom, w, dt, c_mag, has_mag, dyn, o_g, M_g, np.zeros((1, 1, 3)),
                                                 bool(False), dip_col)  # noqa: UP018
        chk += f_body[1, 1]
    for _ in range(reps if rep == 5 else 1):  # stage 5
        err = rot_log_rel_kernel(R_end)
        for si in range(Sd):
            for k in range(3):
                X[dyn[si], k] = err[si, k]
        bil = _bilinear_var(P, g0)
        for k in range(3):
            q[k] += q_att_jerk
        for k in range(3):
            q[k] += bil[k] * dt_blk**2
        chk += X[1, 0]
    for _ in range(reps if rep == 6 else 1):  # stage 6
        x_pred, Y, P_pred = unscented_motion_kernel(X, Wm, Wc, q, P)
        chk += P_pred[1, 1]
    for _ in range(reps if rep == 7 else 1):  # stage 7
        om = np.empty(3)
        for i in range(3):
            om[i] = (M_g[0, i, 0] * (w_mean[0] - o_g[0, 0]) + M_g[0, i, 1] * (w_mean[1] - o_g[0, 1])
                     + M_g[0, i, 2] * (w_mean[2] - o_g[0, 2]))
        f_all = np.empty((S, 3))
        for s in range(S):
            r = Sd + s
            for i in range(3):
                f_all[s, i] = (M_all[r, i, 0] * (a_mean[0] - o_all[r, 0]) + M_all[r, i, 1] * (a_mean[1] - o_all[r, 1])
                               + M_all[r, i, 2] * (a_mean[2] - o_all[r, 2]))
        dev = _deviation(f_all, Wm, Wc, sig_mean, gravity)
        R0 = R_end[0].copy()
        sens_o = o_all[Sd:].copy()
        sens_Minv = Mi_all[Sd:].copy()
        chk += dev + om[0] + R0[0, 0]
    for _ in range(reps if rep == 8 else 1):  # stage 8
        nb = int(use_acc) + int(has_mag)
        z, Z, rr, gated, droppable, gk = motion_measurement_kernel(X, f_body, h_body, sens_o, sens_Minv, a_mean,
                                                                   use_acc, var_a, z_mag, has_mag, var_mag, hold_acc,
                                                                   hold_mag, gravity, gates)
        chk += Z[1, 1]
    for _ in range(reps if rep == 9 else 1):  # stage 9
        z_pred, S_zz, hph, Pxz, nu, nis = innovation_kernel(Y, Z, z, Wm, Wc, rr, gated)
        chk += Pxz[1, 1]
    for _ in range(reps if rep == 10 else 1):  # stage 10
        status = np.full(nb, -1, np.int64)
        post_z = np.zeros((nb, 3))
        post_P = np.zeros((nb, 3, 3))
        keep = np.ones(z.shape[0], np.bool_)
        _gate(S_zz, rr, z_pred, nu, nis, gated, droppable, gk, False, keep, status, post_z, post_P)
        n_keep = 0
        for i in range(keep.shape[0]):
            n_keep += keep[i]
        if n_keep == 0:
            xu, Pu = x_pred.copy(), P_pred.copy()
        else:
            Sz, Sg, Pk, nuk = _kept(S_zz, hph, Pxz, nu, keep, damp)
            xu, Pu, ok2 = gain_update_kernel(x_pred, P_pred, Pk, Sz, Sg, nuk, consider)
        chk += Pu[1, 1]
    for _ in range(reps if rep == 11 else 1):  # stage 11
        xs, Ps, Rn, fine = fold_kernel(xu, Pu, R0, yaw_var)
        chk += Ps[1, 1] + Rn[0, 0]

    return chk

def capture(minutes: float) -> tuple[list[tuple[Any, ...]], int]:
    """Every 10th motion_kernel call's arguments (copies) over the flight's fast-path replay."""
    d = simulate("flight", 0, duration=60 * minutes, imu_rate=200).data
    orig = fastpath.motion_kernel
    calls: list[tuple[Any, ...]] = []
    cnt = [0]

    def wrap(*a: Any) -> Any:
        if cnt[0] % 10 == 0:
            calls.append(tuple(v.copy() if isinstance(v, np.ndarray) else v for v in a))
        cnt[0] += 1
        return orig(*a)

    fastpath.motion_kernel = wrap
    try:
        replay([d], None)
    finally:
        fastpath.motion_kernel = orig
    return calls, cnt[0]

def stage_args(a: tuple[Any, ...]) -> tuple[Any, ...]:
    """motion_kernel's arguments → stages' (after stop, reps): var_a formed as motion_kernel forms it."""
    (x, P, scale, order, R_nom, w, dt, c_mag, has_mag, dyn, Wm, Wc, rw, rate, sigma_gyr, mag_q, mag_dens,
     field_gauss, rw_factor, earth, sigma_rest, tau, om2, q_att_jerk, dt_blk, w_mean, a_mean, sig_mean, gravity,
     g0, a0, m0, dip_col, dev_bail, use_acc, dev_gain, lever_m, var_v, z_mag, var_mag, hold_acc, hold_mag, gates,
     consider, damp, yaw_var, max_rate, angle, two) = a
    var_a = sig_mean**2 + var_v  # (a representative R: the stages' cost does not depend on its value)
    return (x, P, scale, order, R_nom, w, dt, c_mag, has_mag, dyn, Wm, Wc, rw, rate, sigma_gyr, mag_q, mag_dens,
            field_gauss, rw_factor, earth, sigma_rest, tau, om2, q_att_jerk, dt_blk, w_mean, a_mean, sig_mean,
            gravity, g0, a0, m0, dip_col, use_acc, var_a, z_mag, var_mag, hold_acc, hold_mag, gates, consider,
            damp, yaw_var, two)

def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--passes", type=int, default=5)
    ap.add_argument("--minutes", type=float, default=10.0)
    args = ap.parse_args()
    calls, n_calls = capture(args.minutes)
    sa = [stage_args(a) for a in calls]
    L = float(np.mean([a[6].shape[0] for a in calls]))
    n_mag = sum(bool(a[8]) for a in calls)
    print(f"{len(calls)} blocks captured (every 10th of {n_calls} motion_kernel calls), mean {L:.1f} samples per "
          f"block, {n_mag} with the magnetometer; {args.reps} repetitions per call, best of {args.passes} passes")
    K = len(STAGES)
    for k in range(K + 1):  # compile
        stages(k, 2, *sa[0])
    best = [math.inf] * (K + 1)
    full = math.inf
    for _ in range(args.passes):
        for k in range(K + 1):
            c0 = time.process_time()
            for a in sa:
                stages(k, args.reps, *a)
            best[k] = min(best[k], (time.process_time() - c0) / len(sa))
        c0 = time.process_time()
        for a in calls:  # motion_kernel itself, from Python (coverage arrays copied: it writes them)
            b = list(a)
            b[-3], b[-2] = a[-3].copy(), a[-2].copy()
            fastpath.motion_kernel(*b)
        full = min(full, (time.process_time() - c0) / len(calls))
    print(f"{'stage':62s} {'µs/block':>9s} {'µs/sample':>10s}")
    tot = 0.0
    for k, name in enumerate(STAGES, start=1):
        d = (best[k] - best[0]) / (args.reps - 1)
        tot += d
        print(f"  {k:2d} {name:58s} {1e6 * d:9.2f} {1e6 * d / L:10.3f}")
    print(f"     {'sum of the stages':58s} {1e6 * tot:9.2f} {1e6 * tot / L:10.3f}")
    print(f"     {'the copy, each stage once (called from Python)':58s} {1e6 * best[0]:9.2f} {1e6 * best[0] / L:10.3f}")
    print(f"     {'motion_kernel itself (called from Python)':58s} {1e6 * full:9.2f} {1e6 * full / L:10.3f}")
    print(f"load average {os.getloadavg()[0]:.1f} at the end, on {os.cpu_count()} cores")

if __name__ == "__main__":
    main()
