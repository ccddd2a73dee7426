"""The filter step of an ordinary block in compiled calls (issue 15): a motion block in one, a rest block's
update in one — the largest pieces of the per-block Python that could be moved into numba so far.

:func:`.step.motion_step` on the numba backend makes, per block, some forty small numpy and kernel calls
(sigma points, sensor models, propagation, attitude errors, process noise, moments, the vehicle
deviation, measurements, update, attitude fold, heading marginalisation, checks). For a block without
model extensions and without a gyro hold offset (the ordinary case), :func:`motion_step_fast` replaces them by
one call of :func:`motion_kernel`, which runs

1. :func:`predict_kernel` — sigma points (:func:`.kernels_update.sigma_points_kernel`), eqs. 1–6 for the
   dynamic points' gyro and every point's accel and (where the block uses it) mag
   (:func:`.kernels_propagate.model_pair_kernel`), the propagation
   (:func:`.kernels_propagate.propagate_kernel`), the attitude errors
   (:func:`.kernels_propagate.rot_log_rel_kernel`), the block's process noise
   (:func:`.predict.block_process_noise` with :func:`.noise.bilinear_var`), the unscented moments
   (:func:`.kernels_update.unscented_motion_kernel`: the covariance formed only in the attitude's rows and
   columns, the only ones the motion model moves), the mean's turn rate and the quasi-static deviation of the
   specific force (:meth:`.measurements.AccelModel.deviation`);
2. the motion coverage's maxima and turned angles (:meth:`.vehicle.MotionCoverage.add_motion`) and the
   accel's quasi-static R (with the vehicle's var_v, which Python decides before the call);
3. :func:`update_fold_kernel` — the motion measurements (:func:`.measurements.motion_measurements`: h(x) of
   accel and mag), the gated update (:func:`.kernels_update.update_kernel`) and the USQUE fold of the
   posterior (:func:`.attitude_init.fold_attitude`, :func:`.attitude_init.set_yaw_variance`) with its
   finiteness check.

A block whose specific-force deviation would switch the vehicle detector on (an event, and a new var_v)
stops after 1 and finishes as two calls, the detector between them, as before (:func:`set_merged` ``False``
takes the two calls for every block: the same bits). After the call Python keeps what has state and events:
the NIS bookkeeping (:func:`.step.gated_update`'s loop: windows, divergence) and the commit's trace. A rest
block (:func:`.step.rest_step`) keeps its running means and NIS in Python and hands the update to
:func:`rest_update_kernel` (sigma points, :func:`.measurements.rest_measurements`, the static update with
the posterior's predicted measurements, the fold). The kernels called do the numba path's arithmetic, so the
results equal it to rounding (and the numpy reference within 1e-9 relative: ``tests/test_speed_fastpath.py``).
Blocks with model extensions, a motion block with a held gyro reading or with a clipped accel and no
magnetometer, and everything on the numpy backend take the general path. ``ONLINECAL_FASTPATH=0`` (or
:func:`set_enabled`) turns the fast path off.
"""

from __future__ import annotations

import math
import os
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ..specs import FIELD_GAUSS
from . import kernels
from .divergence import NIS_NEGATIVE_TOL, nis_failure
from .kernels import _njit
from .kernels_propagate import _rodrigues_into, model_pair_kernel, propagate_kernel, rot_log_rel_kernel
from .kernels_unscented import _STATUS, _identity
from .kernels_update import sigma_points_kernel, unscented_motion_kernel, update_kernel
from .layout import DIP, SENSOR_SLICE
from .magdisturb import calibrated_floats
from .unscented import UpdateResult
from .vehicle import FIELD_CELLS

if TYPE_CHECKING:
    from .blocks import Blocks
    from .filter import OnlineCalibrator
    from .rest import RestAccumulator

Array = NDArray[np.float64]

_enabled = os.environ.get("ONLINECAL_FASTPATH", "1").strip() not in ("0", "false", "no", "off")
_G0, _A0, _M0 = SENSOR_SLICE["gyro"].start, SENSOR_SLICE["accel"].start, SENSOR_SLICE["mag"].start
_EMPTY1 = np.zeros(1)
_EMPTY0 = np.zeros(0)
_EMPTY_I = np.zeros(0, dtype=np.intp)


def enabled() -> bool:
    """Whether :func:`motion_step_fast` is used for ordinary blocks on the numba backend."""
    return _enabled and kernels.backend() == "numba"


def set_enabled(on: bool) -> bool:
    """Turn the fast path on or off; returns the previous setting (tests compare both)."""
    global _enabled
    old, _enabled = _enabled, bool(on)
    return old


# ------------------------------------------------------------------------------------------------
# compiled parts
@_njit
def _bilinear_var(P: Array, g0: int) -> Array:
    """:func:`.noise.bilinear_var` (3,) of P (n, n), the gyro's 12 terms from column g0."""
    sig = np.empty(12)
    for i in range(12):
        sig[i] = math.sqrt(P[g0 + i, g0 + i])
    s_ang = max(sig[6], sig[9])
    for i in range(1, 3):
        s_ang = max(s_ang, max(sig[6 + i], sig[9 + i]))
    v_o = np.empty(3)
    for i in range(3):
        v_o[i] = sig[i] * sig[i]
    tot = (v_o[0] + v_o[1]) + v_o[2]
    out = np.empty(3)
    for i in range(3):
        out[i] = sig[3 + i] * sig[3 + i] * v_o[i] + s_ang**2 * (tot - v_o[i])
    return out


@_njit
def block_q_kernel(rw: Array, dt: float, rate: float, sigma_gyr: float, mag_col: int, mag_dens: float,
                   field_gauss: float, rw_factor: float, x: Array, P: Array, earth: bool, bias_col: int,
                   scale_col: int, sigma_rest: Array, tau: float, om2: float, two: float) -> Array:
    """The block's Q diagonal (n,) before the block's own terms: :meth:`.noise.NoiseModel.process_noise` of
    :meth:`.noise.NoiseModel.cal_rw` and, with ``earth`` (a vehicle), :func:`.step.earth_rate_q` — in one pass,
    the same operations in the same order as the Python they replace, so the same bits.

    rw (n,) the cached random-walk vector (:meth:`.noise.NoiseModel.cal_rw`, whose mag-bias entries are set
    here from x: (density · unit/``field_gauss`` · rw_factor)², unit = 1 / mean mag scale; ``mag_col`` the
    mag bias's first column, −1 without a mag spec); dt s the block; ``rate`` Hz; ``sigma_gyr`` rad/s per
    sample; P (n, n) the covariance Q adds to; ``bias_col``, ``scale_col`` the gyro's bias and scale columns;
    ``sigma_rest`` (3,) rad/s per gyro axis, ``tau`` s and ``om2`` = Ω_h² (rad/s)² as :func:`.vehicle.earth_rate_noise`;
    ``two`` = 2.0 at run time (libm's ``pow``, as Python's ``**2``: see :func:`motion_kernel`)."""
    n = rw.shape[0]
    q = np.empty(n)
    for k in range(n):
        q[k] = rw[k] * dt
    if mag_col >= 0:
        s0 = mag_col + 3  # the mag's scale
        unit = 1.0 / (((x[s0] + x[s0 + 1]) + x[s0 + 2]) / 3.0)  # (.noise.mag_unit_of)
        v = math.pow(mag_dens * (unit / field_gauss) * rw_factor, two)
        for k in range(mag_col, mag_col + 3):
            q[k] = v * dt
    att = dt * rate * math.pow(sigma_gyr / rate, two)
    for k in range(3):
        q[k] = att
    if earth:
        s_gyr = ((x[scale_col] + x[scale_col + 1]) + x[scale_col + 2]) / 3.0
        for k in range(bias_col, bias_col + 3):
            v = math.pow(sigma_rest[k - bias_col] / s_gyr, two) - P[k, k]
            q[k] += v if not v <= 0.0 else 0.0
        a = om2 * tau * dt
        for k in range(3):
            q[k] += a
    return q


@_njit
def _rodrigues1(x: float, y: float, z: float) -> Array:
    """:func:`.geometry.rodrigues1` (the fold's formula, series below 1e-4 rad): exp([v]_x) (3, 3)."""
    a2 = x * x + y * y + z * z
    if a2 < 1e-8:
        s, c = 1.0 - a2 / 6.0, 0.5 - a2 / 24.0
    else:
        a = math.sqrt(a2)
        s, c = math.sin(a) / a, (1.0 - math.cos(a)) / a2
    R = np.empty((3, 3))
    R[0, 0], R[0, 1], R[0, 2] = 1.0 - c * (y * y + z * z), c * x * y - s * z, c * x * z + s * y
    R[1, 0], R[1, 1], R[1, 2] = c * x * y + s * z, 1.0 - c * (x * x + z * z), c * y * z - s * x
    R[2, 0], R[2, 1], R[2, 2] = c * x * z - s * y, c * y * z + s * x, 1.0 - c * (x * x + y * y)
    return R


@_njit
def _deviation(f_all: Array, Wm: Array, Wc: Array, sig_mean: float, gravity: float) -> float:
    """:meth:`.measurements.AccelModel.deviation`: ||f| − g| beyond 3σ of noise and calibration spread."""
    S = f_all.shape[0]
    nf = np.empty(S)
    for s in range(S):
        nf[s] = math.sqrt(f_all[s, 0] ** 2 + f_all[s, 1] ** 2 + f_all[s, 2] ** 2)
    nf_mean = 0.0
    for s in range(S):
        nf_mean += Wm[s] * nf[s]
    var_cal = 0.0
    for s in range(S):
        var_cal += Wc[s] * (nf[s] - nf_mean) ** 2
    var_cal = max(0.0, var_cal)
    return max(0.0, abs(nf_mean - gravity) - 3.0 * math.sqrt(sig_mean**2 + var_cal))


@_njit
def _model_pair_shared(p: Array, g1: int, g2: int) -> tuple[Array, Array, Array]:
    """:func:`.kernels_propagate.model_pair_kernel` of the rows p (N, 12), in three groups [0, g1), [g1, g2),
    [g2, N) (one sensor each, the mean's row first), computed once per distinct row: a row equal to its
    group's first in all 12 terms (a sigma point that does not perturb this sensor: 57 of 81 accel or mag
    rows, 7 of 31 dynamic gyro rows) takes that row's (o, M, M⁻¹) — the same inputs through the same
    kernel, so the same bits, at a third of the trigonometry."""
    N = p.shape[0]
    src = np.empty(N, np.intp)
    idx = np.empty(N, np.intp)
    cnt = 0
    for r in range(N):
        base = 0 if r < g1 else (g1 if r < g2 else g2)
        same = r != base
        if same:
            for k in range(12):
                if p[r, k] != p[base, k]:
                    same = False
                    break
        if same:
            src[r] = src[base]
        else:
            idx[cnt] = r
            src[r] = cnt
            cnt += 1
    pd = np.empty((cnt, 12))
    for c in range(cnt):
        for k in range(12):
            pd[c, k] = p[idx[c], k]
    o_d, M_d, Mi_d = model_pair_kernel(pd)
    o = np.empty((N, 3))
    M = np.empty((N, 3, 3))
    Mi = np.empty((N, 3, 3))
    for r in range(N):
        c = src[r]
        for i in range(3):
            o[r, i] = o_d[c, i]
            for j in range(3):
                M[r, i, j] = M_d[c, i, j]
                Mi[r, i, j] = Mi_d[c, i, j]
    return o, M, Mi


@_njit
def predict_kernel(x: Array, P: Array, scale: float, order: NDArray[np.intp], R_nom: Array, w: Array, dt: Array,
                   c_mag: Array, has_mag: bool, dyn: NDArray[np.intp], Wm: Array, Wc: Array, rw: Array, rate: float,
                   sigma_gyr: float, mag_q: bool, mag_dens: float, field_gauss: float, rw_factor: float,
                   earth: bool, sigma_rest: Array, tau: float, om2: float, two: float,
                   q_att_jerk: float, dt_blk: float, w_mean: Array, a_mean: Array, sig_mean: float,
                   gravity: float, g0: int, a0: int, m0: int, dip_col: int
                   ) -> tuple[bool, Array, Array, Array, Array, Array, Array, Array, Array, Array, Array, float]:
    """The prediction of one motion block (:func:`.step.motion_step` up to the measurements), one call.

    x (n,), P (n, n) the state; scale = λ + n; order the Cholesky's state order; R_nom (3, 3); w (L + 1, 3),
    dt (L,), c_mag (L + 1,) (read when has_mag) as :func:`.kernels_propagate.propagate_kernel`; dyn the
    dynamic sigma points; Wm, Wc the weights; rw … two the base process noise's inputs (:func:`block_q_kernel`:
    the cached random walk rw (n,), the rate Hz, the gyro's per-sample σ, whether the mag has a spec (its bias
    columns from m0), its density, the field's gauss, rw_factor, whether the Earth-rate allowance applies (a
    vehicle) with its σ, τ and Ω_h²), to which the trapezoid allowance ``q_att_jerk`` and the bilinear term ×
    dt_blk² are added on the attitude; w_mean (3,) the
    block-mean raw rate; a_mean (3,) the block-mean raw accel, σ ``sig_mean``; g0, a0, m0 the sensors'
    first columns; dip_col the dip's.

    Returns (ok: P positive definite, the propagated sigma points X (S, n), x_pred (n,), Y (S, n),
    P_pred (n, n), R_end of the mean (3, 3), f_body (S, 3), h_body (S, 3), sens_o (2S, 3), sens_Minv
    (2S, 3, 3) of accel then mag (S rows, the accel's, without has_mag), ω of the mean (3,) rad/s, the
    specific force's deviation (m/s², :meth:`.measurements.AccelModel.deviation`)).
    """
    q = block_q_kernel(rw, dt_blk, rate, sigma_gyr, m0 if mag_q else -1, mag_dens, field_gauss, rw_factor, x, P,
                       earth, g0, g0 + 3, sigma_rest, tau, om2, two)
    X, ok = sigma_points_kernel(x, P, scale, order)
    S, Sd = X.shape[0], dyn.shape[0]
    if not ok:
        z3 = np.zeros((1, 3))
        return (False, X, x.copy(), X.copy(), P.copy(), R_nom.copy(), z3, z3.copy(), z3.copy(), np.zeros((1, 3, 3)),
                np.zeros(3), 0.0)
    # the mag's model only where the block uses it (its rows are read by the mag update alone: a log whose
    # magnetometer is not yet started — or has none — skips them, up to half the sensor-model trigonometry)
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
    # no extra offsets: a fresh (mutable) empty array and a run-time bool, the argument types the general path
    # passes, so that numba compiles the kernel once, not again for a frozen global and a literal False (~2.5 s
    # from an empty cache); the same for update_kernel's want_post below (~4.5 s per extra signature)
    R_end, f_body, h_body = propagate_kernel(X, R_nom, w, dt, c_mag, has_mag, dyn, o_g, M_g, np.zeros((1, 1, 3)),
                                             bool(False), dip_col)  # noqa: UP018 (a run-time bool: see above)
    err = rot_log_rel_kernel(R_end)
    for si in range(Sd):
        for k in range(3):
            X[dyn[si], k] = err[si, k]
    # block process noise (.predict.block_process_noise): the trapezoid's allowance, then the bilinear term
    bil = _bilinear_var(P, g0)
    for k in range(3):
        q[k] += q_att_jerk
    for k in range(3):
        q[k] += bil[k] * dt_blk**2
    x_pred, Y, P_pred = unscented_motion_kernel(X, Wm, Wc, q, P)
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
    return (True, X, x_pred, Y, P_pred, R0, f_body, h_body, o_all[Sd:].copy(), Mi_all[Sd:].copy(), om, dev)


@_njit
def motion_measurement_kernel(X: Array, f_body: Array, h_body: Array, sens_o: Array, sens_Minv: Array, z_acc: Array,
                              use_acc: bool, var_a: float, z_mag: Array, use_mag: bool, var_mag: float,
                              hold_acc: int, hold_mag: int, gravity: float, gates: Array
                              ) -> tuple[Array, Array, Array, NDArray[np.bool_], NDArray[np.bool_], Array]:
    """The stacked measurement of a motion block (:func:`.measurements.motion_measurements`) for the propagated
    sigma points X (S, n): accel raw = M⁻¹ g f_body + o (R = var_a per axis, droppable, gate gates[0]) where
    use_acc, then mag raw = M⁻¹ h_body + o (R = var_mag, gate gates[1]) where use_mag, each plus the held
    reading's offset X[:, hold:hold + 3] where hold_acc / hold_mag ≥ 0; sens_o (2S, 3), sens_Minv (2S, 3, 3)
    the accel's rows then the mag's. Returns z (m,), Z (S, m), r (m,), gated, droppable, gates (blocks,)."""
    S = X.shape[0]
    nb = int(use_acc) + int(use_mag)
    z = np.empty(3 * nb)
    Z = np.empty((S, 3 * nb))
    r = np.empty(3 * nb)
    gated = np.ones(nb, np.bool_)
    droppable = np.zeros(nb, np.bool_)
    gk = np.empty(nb)
    k = 0
    if use_acc:
        for s in range(S):
            for i in range(3):
                Z[s, i] = (sens_Minv[s, i, 0] * (gravity * f_body[s, 0]) + sens_Minv[s, i, 1] * (gravity * f_body[s, 1])
                           + sens_Minv[s, i, 2] * (gravity * f_body[s, 2])) + sens_o[s, i]
                if hold_acc >= 0:
                    Z[s, i] = Z[s, i] + X[s, hold_acc + i]
        for i in range(3):
            z[i] = z_acc[i]
            r[i] = var_a
        droppable[0] = True
        gk[0] = gates[0]
        k = 1
    if use_mag:
        c = 3 * k
        for s in range(S):
            t = S + s
            for i in range(3):
                Z[s, c + i] = (sens_Minv[t, i, 0] * h_body[s, 0] + sens_Minv[t, i, 1] * h_body[s, 1]
                               + sens_Minv[t, i, 2] * h_body[s, 2]) + sens_o[t, i]
                if hold_mag >= 0:
                    Z[s, c + i] = Z[s, c + i] + X[s, hold_mag + i]
        for i in range(3):
            z[c + i] = z_mag[i]
            r[c + i] = var_mag
        gk[k] = gates[1]
    return z, Z, r, gated, droppable, gk


@_njit
def update_fold_kernel(X: Array, Y: Array, x_pred: Array, P_pred: Array, f_body: Array, h_body: Array, sens_o: Array,
                       sens_Minv: Array, z_acc: Array, use_acc: bool, var_a: float, z_mag: Array, use_mag: bool,
                       var_mag: float, hold_acc: int, hold_mag: int, gravity: float, Wm: Array, Wc: Array, gates: Array,
                       consider: NDArray[np.bool_], damp: float, R_nom: Array, yaw_var: float
                       ) -> tuple[Array, Array, Array, NDArray[np.int64], bool, Array, bool]:
    """Measurements, update and fold of one motion block, one call.

    The measurements of :func:`.measurements.motion_measurements` for the propagated sigma points X (S, n)
    (accel: raw = M⁻¹ g f_body + o, R = var_a per axis, droppable; mag: raw = M⁻¹ h_body + o, R = var_mag;
    each plus the held reading's offset X[:, hold:hold + 3] where hold_acc / hold_mag ≥ 0; gated by ``gates``
    (accel, mag)), the joint
    update (:func:`.kernels_update.update_kernel`), then the posterior folded (:func:`.attitude_init.fold_attitude`:
    P symmetrised, R = R_nom exp([δθ]_x), δθ = 0; with yaw_var ≥ 0 the heading's variance set to it,
    :func:`.attitude_init.set_yaw_variance`).

    Returns (x (n,), P (n, n) folded, NIS (blocks,), status (blocks,) as update_kernel, whether the solve
    succeeded, R (3, 3), whether x and P are finite with a positive diagonal).
    """
    z, Z, r, gated, droppable, gk = motion_measurement_kernel(X, f_body, h_body, sens_o, sens_Minv, z_acc, use_acc,
                                                              var_a, z_mag, use_mag, var_mag, hold_acc, hold_mag,
                                                              gravity, gates)
    x, P, nis, status, _pz, _pP, ok = update_kernel(Y, x_pred, P_pred, z, Z, r, Wm, Wc, gated, droppable, gk,
                                                    consider, damp, bool(False))  # noqa: UP018 (see predict_kernel)
    xs, Ps, R, fine = fold_kernel(x, P, R_nom, yaw_var)
    return xs, Ps, nis, status, ok, R, fine


@_njit
def interp_weights_kernel(j: NDArray[np.intp], frac: Array, L: int) -> Array:
    """:func:`.propagate.interp_weights` of one block's few mag samples, compiled (issue 15: its two ``bincount``
    calls were ~8 µs a block): c (L + 1,) from the interpolation indices j (M,) in 1..L and fractions frac (M,) —
    the same sums in the same order (``bincount`` adds each sample's weight in turn to 0.0) and the same
    division, so the same bits (tests/test_speed_fastpath.py); M = 0 raises ZeroDivisionError, never a silent NaN."""
    a = np.zeros(L + 1)
    b = np.zeros(L + 1)
    for k in range(j.shape[0]):
        a[j[k]] += frac[k]
        b[j[k] - 1] += 1.0 - frac[k]
    n = j.shape[0]
    c = np.empty(L + 1)
    for k in range(L + 1):
        c[k] = (a[k] + b[k]) / n
    return c


_calibrated_nb = _njit(calibrated_floats)  # eq. 1 on scalars, written once (.magdisturb), compiled for the kernels


@_njit
def field_cell_kernel(p: Array, raw: Array, cells: Array) -> int:
    """The field coverage's cell of a block's mean mag reading raw (3,) (:meth:`.vehicle.MotionCoverage.add_field`,
    which of the 26 unit directions ``cells`` (26, 3) it points into): calibrated with the mag's 12 terms p
    (:func:`.magdisturb.calibrated_floats`, compiled) instead of :func:`.start.calibrated`'s numpy on one row
    (~40 µs a motion block with the mag), then the first of the largest dot products (the cell of the largest
    cosine: a positive factor does not move the argmax; NaN never wins: cell 0, as add_field's division). The
    same field to rounding: only a direction within ~1e-16 of a cell boundary could fall into another cell."""
    h0, h1, h2 = _calibrated_nb(p, raw)
    best, k_best = -math.inf, 0
    for k in range(cells.shape[0]):
        v = cells[k, 0] * h0 + cells[k, 1] * h1 + cells[k, 2] * h2
        if v > best:
            best, k_best = v, k
    return k_best


@_njit
def motion_kernel(x: Array, P: Array, scale: float, order: NDArray[np.intp], R_nom: Array, w: Array, dt: Array,
                  m_j: NDArray[np.intp], m_frac: Array, has_mag: bool, dyn: NDArray[np.intp], Wm: Array, Wc: Array,
                  rw: Array, rate: float,
                  sigma_gyr: float, mag_q: bool, mag_dens: float, field_gauss: float, rw_factor: float,
                  earth: bool, sigma_rest: Array, tau: float, om2: float, q_att_jerk: float, dt_blk: float,
                  w_mean: Array, a_mean: Array, sig_mean: float, gravity: float,
                  g0: int, a0: int, m0: int, dip_col: int, dev_bail: float, use_acc: bool, dev_gain: float,
                  lever_m: float, var_v: float, z_mag: Array, var_mag: float, hold_acc: int, hold_mag: int,
                  gates: Array, consider: NDArray[np.bool_], damp: float, yaw_var: float, max_rate: Array,
                  angle: Array, two: float, mag_dirs: Array, cells: Array) -> tuple[Any, ...]:
    """One ordinary motion block in one call: :func:`predict_kernel`, the accel's quasi-static R
    (:meth:`.measurements.AccelModel.variance`'s terms, with the vehicle's ``var_v`` — an input: Python decides
    it), the motion coverage (:meth:`.vehicle.MotionCoverage.add_motion`'s maxima and turned angles, in place
    in max_rate (3,) and angle (3,) rad/s, rad), then :func:`update_fold_kernel`; with the magnetometer, the
    field's coverage cell marked in mag_dirs (26,) (:func:`field_cell_kernel` on the state before the update,
    ``cells`` (26, 3)) once the update is reached.

    Arguments as the two kernels', but the mag's interpolation weights: the block's mag samples' indices m_j (M,)
    and fractions m_frac (M,) (:func:`interp_weights_kernel`; empty without the magnetometer); ``dev_bail``
    m/s²: a specific-force deviation above it is an event Python must see before the update (the vehicle
    detector switching on, which changes var_v): the call then stops after the prediction. ``two`` = 2.0,
    passed at run time so that the squares are libm's ``pow`` as in the Python they replace (a constant
    exponent compiles to x·x, which differs in the last bit for about one value in a thousand).

    Returns (stage: 0 P not positive definite, 1 stopped after the prediction, 2 done; the prediction
    (X, x_pred, Y, P_pred, f_body, h_body, sens_o, sens_Minv, ω of the mean (3,): None at stage 2); Rs (2, 3, 3):
    R_end of the mean, and at stage 2 the posterior's R; info (7,): the deviation, and at stage 2 whether the
    solve succeeded and x, P are fine (1.0 / 0.0), the NIS of the accel-then-mag blocks (2, as many as used)
    and their status (−1 where absent); the update's x, P (None before stage 2)) — see the two kernels.
    (None, not placeholder arrays, and the small results in two arrays: each array returned costs its
    allocation and boxing, ~1.3 µs.)
    """
    c_mag = interp_weights_kernel(m_j, m_frac, dt.shape[0]) if has_mag else np.zeros(1)
    ok, X, x_pred, Y, P_pred, R0, f_body, h_body, s_o, s_Mi, om, dev = predict_kernel(
        x, P, scale, order, R_nom, w, dt, c_mag, has_mag, dyn, Wm, Wc, rw, rate, sigma_gyr, mag_q, mag_dens,
        field_gauss, rw_factor, earth, sigma_rest, tau, om2, two, q_att_jerk, dt_blk, w_mean, a_mean, sig_mean,
        gravity, g0, a0, m0, dip_col)
    Rs = np.zeros((2, 3, 3))  # R_end of the mean, then the posterior's (one array: each returned one is boxed)
    info = np.zeros(7)  # dev, solved, fine, NIS (2), status (2)
    for i in range(3):
        for k in range(3):
            Rs[0, i, k] = R0[i, k]
    info[0] = dev
    if not ok or dev > dev_bail:
        return (1 if ok else 0, X, x_pred, Y, P_pred, f_body, h_body, s_o, s_Mi, om, Rs, info, None, None)
    rate = math.sqrt(np.dot(om, om))  # (BLAS ddot, as np.dot in Python: the same bits)
    if has_mag:  # the field coverage of the block's mean field, calibrated with the state before the update
        mag_dirs[field_cell_kernel(x[m0 : m0 + 12], z_mag, cells)] = 1.0
    for i in range(3):  # MotionCoverage.add_motion: np.maximum (NaN wins), ∫|ω_i| dt
        r = abs(om[i])
        m = max_rate[i]
        max_rate[i] = r if (r > m or r != r) else m
        angle[i] = angle[i] + r * dt_blk
    var_a = 0.0
    if use_acc:
        var_a = math.pow(sig_mean, two) + math.pow(dev_gain * dev, two) + 2.0 * gravity * dev
        if rate != 0.0:
            var_a = var_a + math.pow(lever_m * math.pow(rate, two), two)
        var_a += var_v
    xs, Ps, nis, status, solved, R_new, fine = update_fold_kernel(
        X, Y, x_pred, P_pred, f_body, h_body, s_o, s_Mi, a_mean, use_acc, var_a, z_mag, has_mag, var_mag, hold_acc,
        hold_mag, gravity, Wm, Wc, gates, consider, damp, R0, yaw_var)
    for i in range(3):
        for k in range(3):
            Rs[1, i, k] = R_new[i, k]
    info[1] = 1.0 if solved else 0.0
    info[2] = 1.0 if fine else 0.0
    info[5] = info[6] = -1.0
    for k in range(nis.shape[0]):
        info[3 + k] = nis[k]
        info[5 + k] = status[k]
    return (2, None, None, None, None, None, None, None, None, None, Rs, info, xs, Ps)


@_njit
def fold_kernel(x: Array, P: Array, R_nom: Array, yaw_var: float) -> tuple[Array, Array, Array, bool]:
    """:func:`.attitude_init.fold_attitude` (USQUE reset) of a posterior x (n,), P (n, n) on R_nom (3, 3):
    P symmetrised, R = R_nom exp([δθ]_x), δθ = 0 (x is not changed: a copy); with yaw_var ≥ 0 the heading's
    knowledge replaced by that variance (:func:`.attitude_init.set_yaw_variance`). Returns (x, P, R, whether
    x and P are finite with a positive diagonal)."""
    n = x.shape[0]
    Ps = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            Ps[i, j] = 0.5 * (P[i, j] + P[j, i])
    Rd = _rodrigues1(x[0], x[1], x[2])
    R = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            R[i, j] = R_nom[i, 0] * Rd[0, j] + R_nom[i, 1] * Rd[1, j] + R_nom[i, 2] * Rd[2, j]
    xs = x.copy()
    xs[0] = 0.0
    xs[1] = 0.0
    xs[2] = 0.0
    if yaw_var >= 0.0:
        u = R[2]
        J = np.empty((3, 3))
        for i in range(3):
            for j in range(3):
                J[i, j] = (1.0 if i == j else 0.0) - u[i] * u[j]
        rows = np.empty((3, n))
        for i in range(3):
            for j in range(n):
                rows[i, j] = J[i, 0] * Ps[0, j] + J[i, 1] * Ps[1, j] + J[i, 2] * Ps[2, j]
        for i in range(3):
            for j in range(n):
                Ps[i, j] = rows[i, j]
        cols = np.empty((n, 3))
        for i in range(n):
            for j in range(3):
                cols[i, j] = Ps[i, 0] * J[j, 0] + Ps[i, 1] * J[j, 1] + Ps[i, 2] * J[j, 2]
        for i in range(n):
            for j in range(3):
                Ps[i, j] = cols[i, j]
        for i in range(3):
            for j in range(3):
                Ps[i, j] += yaw_var * (u[i] * u[j])
    fine = True
    for i in range(n):
        if not math.isfinite(xs[i]) or not Ps[i, i] > 0.0:
            fine = False
        for j in range(n):
            if not math.isfinite(Ps[i, j]):
                fine = False
    return xs, Ps, R, fine


# ------------------------------------------------------------------------------------------------
# the step (Python: what has state and events)
def applies(cal: OnlineCalibrator, held: dict[str, bool], use_mag: bool, clip: dict[str, bool]) -> bool:
    """Whether a block's motion step can take :func:`motion_step_fast`: numba backend, no model extensions,
    no gyro hold offset in the propagation (:func:`.step.offsets` of the gyro while the rest detector says
    still), and at least one measurement (the accel unclipped or the mag used)."""
    lay = cal.lay
    return (enabled() and not lay.ext_slice and not ("gyro" in lay.hold_slice and cal._rest_det.still)
            and not (clip["accel"] and not use_mag))


def _hold_col(cal: OnlineCalibrator, sensor: str, held: dict[str, bool]) -> int:
    """First state column of ``sensor``'s hold offset where its reading is held in this block, else −1."""
    sl = cal.lay.hold_slice.get(sensor) if held[sensor] else None
    return -1 if sl is None else int(sl.start)


def _q_args(cal: OnlineCalibrator) -> tuple[Array, tuple[bool, float, float, float]]:
    """The cached random-walk vector of :meth:`.noise.NoiseModel.cal_rw` (refreshed where its key changed;
    :func:`block_q_kernel` sets its mag-bias entries from the state) and (whether the mag has a spec, its
    density, the field's gauss, rw_factor) — the base Q's inputs; the fast path has no extensions."""
    nm = cal._noise
    c = cal.config
    if nm._rw_key != (cal.lay.n, float(c.rw_factor)) or nm._rw_cache.shape[0] != cal.lay.n:
        cal._cal_rw()
    mag = nm.specs.get("mag")
    return nm._rw_cache, (mag is not None, nm._density(mag) if mag is not None else 0.0, FIELD_GAUSS,
                          float(c.rw_factor))


def _block_consts(cal: OnlineCalibrator) -> tuple[Any, ...]:
    """What a motion block's call takes that changes only with the layout, the noise model, the gates or the
    sigma-point settings: (λ + n, the Cholesky's order, :func:`_q_args`, the gates (accel, mag) as an
    array), kept on the calibrator and rebuilt where any of them changed (issue 15: ~5 µs of Python per
    block, the specs' hashes of the density's cache among them). Not in a checkpoint: a resumed filter
    builds it at its first block."""
    k = cal.__dict__.get("_fast_consts")
    lay, nm, c, g = cal.lay, cal._noise, cal.config, cal._gates
    if nm.q_walk > 0.0 or nm._walk_set:  # the gyro bias's walk measured at rest, in the cached vector in place
        nm.apply_walk(float(c.rw_factor))
    if (k is not None and k[0] is lay and k[1] is nm and k[2] is g and k[3] == (c.sp_alpha, c.sp_kappa, c.rw_factor)
            and k[4] is nm._rw_cache and nm._rw_key == k[5]):
        return k[6]
    nst = lay.n
    lam = c.sp_alpha**2 * (nst + c.sp_kappa) - nst
    order = _identity(nst) if lay.perm_id else np.asarray(lay.perm, dtype=np.intp)
    rw, q_args = _q_args(cal)
    vals = (lam + nst, order, rw, q_args, np.array([g["accel"], g["mag"]]))
    cal.__dict__["_fast_consts"] = (lay, nm, g, (c.sp_alpha, c.sp_kappa, c.rw_factor), nm._rw_cache, nm._rw_key,
                                    vals)
    return vals


def set_merged(on: bool) -> bool:
    """One compiled call per ordinary motion block (:func:`motion_kernel`, the default) or two
    (:func:`predict_kernel`, :func:`update_fold_kernel`: what a block whose prediction raises an event takes);
    returns the previous setting (tests compare both: the same bits)."""
    global _merged
    old, _merged = _merged, bool(on)
    return old


_merged = True
_TWO = 2.0  # the squares' exponent, a run-time value in the kernels (see motion_kernel)


def motion_step_fast(cal: OnlineCalibrator, B: Blocks, b: int, t: Array, n: dict[str, float],
                     held: dict[str, bool], use_mag: bool, clip: dict[str, bool]) -> None:
    """:func:`.step.motion_step` for a block where :func:`applies`: the same steps, in the same order, with
    the arithmetic in :func:`motion_kernel` (one call), or, where the prediction raises an event Python
    must see first (the vehicle detector switching on), in :func:`predict_kernel` and
    :func:`update_fold_kernel` with the detector between them."""
    st = _step_module()
    c = cal.config
    tl = float(t[-1])
    scale, order, rw, q_args, gates = _block_consts(cal)
    i, j = B.lo_l[b], B.hi_l[b]
    L = j - i
    has_mag = bool(use_mag)
    m_j, m_frac = _EMPTY_I, _EMPTY0
    if has_mag:
        k0, n_m0 = B.mlo_l[b] - B.mlo_l[0], B.mhi_l[b] - B.mlo_l[b]
        m_j, m_frac = B.m_j[k0 : k0 + n_m0], B.m_frac[k0 : k0 + n_m0]
    t_last = cal._t_last
    assert t_last is not None  # (a motion step follows a filtered block)
    dt_blk = tl - t_last  # (the numpy subtraction's double)
    s_g = n["gyro"]
    jerk = 0.0
    if L >= 2:
        noise = B.jerk_n_l[b] * 6.0 * (s_g * dt_blk / L / 4) ** 2
        jerk = max(0.0, B.jerk_l[b] - noise) / 3.0
    lay = cal.lay
    sig_mean = n["accel"] / math.sqrt(t.size)
    a_mean = B.a_mean[b]
    use_acc = not clip["accel"]
    n_m = B.mhi_l[b] - B.mlo_l[b]
    var_mag = cal._models.mag.variance(n["mag"] ** 2 / max(n_m, 1), n["mag"], cal.x)
    yaw = c.yaw_free_sigma**2 if cal._mag.yaw_free else -1.0
    hold_a, hold_m = _hold_col(cal, "accel", held), _hold_col(cal, "mag", held)
    mod = cal._models.acc
    veh = cal._vehicle
    if _merged:
        # var_v as the detector stands; a deviation that would switch it on stops the call after the prediction
        var_v = st.vehicle_accel_now(cal, dt_blk)
        feed = c.vehicle == "auto" and not veh.active  # (vehicle_accel_from_dev feeds the detector then)
        cov = cal._coverage
        stage, X, x_pred, Y, P_pred, f_body, h_body, s_o, s_Mi, om, Rs, info, x, P = motion_kernel(
            cal.x, cal.P, scale, order, cal.R_nom, B.w_ext[i : j + 1], B.dt[i:j], m_j, m_frac, has_mag,
            lay.dyn_pts, cal._Wm, cal._Wc, rw, cal._rate or 100.0, s_g, *q_args, veh.active, np.asarray(cal._earth[0]),
            c.vehicle_accel_tau, cal._earth[1], jerk, dt_blk, B.w_mean[b], a_mean, sig_mean, c.gravity,
            _G0, _A0, _M0, DIP, veh.dev_switch_above() if feed else math.inf, use_acc,
            mod.dev_gain, mod.lever_m, var_v, B.m_mean[b], var_mag, hold_a, hold_m, gates,
            motion_consider(cal, has_mag), float(c.update_damping), yaw, cov.max_rate, cov.angle, _TWO,
            cov.mag_dirs, FIELD_CELLS)
        if stage == 0:
            cal._diverged("covariance is not positive definite", tl)
            return
        cal.R_nom = Rs[0]
        dev, solved, fine, nis0, nis1, st0, st1 = info.tolist()
        if stage == 2:
            if feed:  # the detector's run of blocks (dev ≤ dev_bail: it stays off, var_v stands; a var_v that
                # depended on the prediction would break the one call: tests/test_speed_fastpath.py compares it
                # with the two calls bit for bit on a flight whose detector switches on)
                st.vehicle_accel_from_dev(cal, dev, dt_blk, tl)
            if veh.active:  # (MotionCoverage.add_motion's flight time; its maxima, angles and field cell in the kernel)
                cov.flight_s += dt_blk
            _finish_motion(cal, st, x, P, [nis0, nis1], [st0, st1], solved == 1.0, Rs[1], fine == 1.0, use_acc,
                           has_mag, var_v, tl)
            return
    else:
        c_mag = interp_weights_kernel(m_j, m_frac, L) if has_mag else _EMPTY1
        ok, X, x_pred, Y, P_pred, R_end0, f_body, h_body, s_o, s_Mi, om, dev = predict_kernel(
            cal.x, cal.P, scale, order, cal.R_nom, B.w_ext[i : j + 1], B.dt[i:j], c_mag, has_mag,
            lay.dyn_pts, cal._Wm, cal._Wc, rw, cal._rate or 100.0, s_g, *q_args, veh.active, np.asarray(cal._earth[0]),
            c.vehicle_accel_tau, cal._earth[1], _TWO, jerk, dt_blk, B.w_mean[b], a_mean, sig_mean, c.gravity,
            _G0, _A0, _M0, DIP)
        if not ok:
            cal._diverged("covariance is not positive definite", tl)
            return
        cal.R_nom = R_end0
    # two calls: the vehicle detector (and any event it raises) between the prediction and the update
    rate = math.sqrt(float(np.dot(om, om)))  # (np.linalg.norm's arithmetic, without its checks)
    var_v = st.vehicle_accel_from_dev(cal, dev, dt_blk, tl)
    cal._coverage.add_motion(om, dt_blk, veh.active)
    if use_mag:
        cal._coverage.mag_dirs[field_cell_kernel(cal.x[_M0 : _M0 + 12], B.m_mean[b], FIELD_CELLS)] = 1.0
    var_a = 0.0
    if use_acc:
        g = mod.gravity
        var_a = sig_mean**2 + (mod.dev_gain * dev) ** 2 + 2.0 * g * dev
        if rate:
            var_a = var_a + (mod.lever_m * rate**2) ** 2
        var_a += var_v
    x, P, nis, status, solved, R_new, fine = update_fold_kernel(
        X, Y, x_pred, P_pred, f_body, h_body, s_o, s_Mi, a_mean, use_acc, var_a, B.m_mean[b], has_mag, var_mag,
        hold_a, hold_m, c.gravity, cal._Wm, cal._Wc, gates, motion_consider(cal, has_mag), float(c.update_damping),
        cal.R_nom, yaw)
    _finish_motion(cal, st, x, P, nis.tolist(), status.tolist(), solved, R_new, fine, use_acc, has_mag, var_v, tl)


def motion_consider(cal: OnlineCalibrator, mag_in: bool) -> NDArray[np.bool_]:
    """The consider mask of a motion update: the accelerometer's terms held too once a vehicle is detected
    (:attr:`.state.StateLayout.consider_vehicle`) and, on a vehicle detected by its vibration (thrust-borne), the
    magnetometer's soft iron (:attr:`.state.StateLayout.mag_flight_terms`) and, in an update without the
    magnetometer (``mag_in`` False), the gyro's three scales (:attr:`.state.StateLayout.gyro_tilt_terms`), and each
    sensor's whose geometry this block does not learn (:class:`.learning.Learning`, decided by
    :func:`.step.motion_step`)."""
    ha, hm = cal._learn.held
    thrust = soft_iron_held(cal)
    return cal.lay.consider_mask(cal._vehicle.active, ha, hm, thrust and not mag_in, thrust)


def soft_iron_held(cal: OnlineCalibrator) -> bool:
    """Whether a motion update now holds the magnetometer's soft iron (:attr:`.state.StateLayout.mag_flight_terms`):
    on a vehicle detected by its vibration. The one rule for the mask (:func:`motion_consider`) and for the NIS
    bookkeeping's ``held`` count (:meth:`.health.NisMonitor.record`)."""
    return cal._vehicle.vibrating


def _finish_motion(cal: OnlineCalibrator, st: Any, x: Array, P: Array, vals: list[float], codes: list[Any],
                   solved: bool, R_new: Array, fine: bool, use_acc: bool, has_mag: bool, var_v: float,
                   tl: float) -> None:
    """The end of a motion block after its update: the NIS bookkeeping (windows, divergence) and the commit.
    ``vals``, ``codes``: the NIS and status (0 ok, 1 soft, 2 dropped, −1 none) of the accel-then-mag blocks
    used, as Python numbers."""
    if not solved:
        raise np.linalg.LinAlgError("Singular matrix")
    k_div = cal._div.count
    k_v = var_v / cal.config.vehicle_accel_sigma**2 if var_v > 0 else 0.0
    feed_gate = cal.config.vehicle == "auto" and not cal._vehicle.active
    # .step.gated_bookkeeping's loop on the kernel's values as Python numbers, without the
    # UpdateResult it reads them from (issue 15): the same records in the same order
    k = 0
    learn = cal._learn
    for s, on in (("accel", use_acc), ("mag", has_mag)):
        if not on:
            continue
        code, v = codes[k], vals[k]
        k += 1
        if code < 0:
            continue
        if not (v >= NIS_NEGATIVE_TOL and v != math.inf):  # divergence.nis_failure (NaN fails the first)
            cal._diverged(f"{s}: {nis_failure(v)}", tl)
            break
        if s == "accel" and feed_gate:
            st.vehicle_event(cal, cal._vehicle.gate(code == 2, tl), tl)
        if code == 2:  # dropped: counted, out of the windows
            cal._nis.reject(s, k_v)
            continue
        if not learn.holds(s):  # (a held look's NIS is not a new sample: .learning.Learning)
            cal._nis_record(s, v, tl, k_v, s == "mag" and soft_iron_held(cal))
        if code == 1:  # soft-gated
            cal._nis.reject(s, k_v)
    if cal._div.count == k_div:  # else the update declared a divergence: the restarted state stands
        st.commit_folded(cal, R_new, x, P, fine, tl)


_STEP: list[Any] = []


def _step_module() -> Any:
    """:mod:`.step` (which imports this module: looked up once, at the first block)."""
    if not _STEP:
        from . import step

        _STEP.append(step)
    return _STEP[0]


# ------------------------------------------------------------------------------------------------
# the rest step's update (:func:`.step.rest_step` after the running means are formed)
@_njit
def rest_update_kernel(x0: Array, P0: Array, scale: float, order: NDArray[np.intp], R_nom: Array, Wm: Array,
                       Wc: Array, has_acc: bool, a_mean: Array, sig_a: float, has_mag: bool, m_mean: Array,
                       var_mag: float, w_mean: Array, var_rest: Array, hold_acc: int, hold_mag: int, hold_gyr: int,
                       gravity: float, dev_gain: float, gates: Array, consider: NDArray[np.bool_], yaw_var: float,
                       g0: int, a0: int, m0: int, dip_col: int
                       ) -> tuple[bool, Array, Array, Array, NDArray[np.int64], Array, Array, bool, Array, bool]:
    """The rest's measurement on the state the rest began with (:func:`.step.rest_step`), one call.

    Sigma points of (x0 (n,), P0 (n, n)) (scale = λ + n, Cholesky order ``order``), their attitudes
    R_nom exp([δθ]_x), the measurements of :func:`.measurements.rest_measurements` — the rest's mean accel
    a_mean (3,) against g Rᵀe_z with the quasi-static R (noise σ sig_a), where has_acc; its mean mag m_mean
    against Rᵀh_world(dip) with R = var_mag, where has_mag; the mean raw rate w_mean against the gyro bias
    with R = diag(var_rest) (3,) (not gated); each plus its hold offset (column ≥ 0) — the static update with the
    posterior's predicted measurements (:func:`.kernels_update.update_kernel`, want_post), and the fold
    (:func:`fold_kernel`). g0, a0, m0 the sensors' first columns, dip_col the dip's.

    Returns (ok: P0 positive definite, x (n,), P (n, n) folded, NIS, status, post_z, post_P as update_kernel,
    whether the solve succeeded, R (3, 3), whether x and P are finite with a positive diagonal).
    """
    X, ok = sigma_points_kernel(x0, P0, scale, order)
    S, n = X.shape
    nb = int(has_acc) + int(has_mag) + 1
    if not ok:
        return (False, x0.copy(), P0.copy(), np.zeros(nb), np.full(nb, -1, np.int64), np.zeros((nb, 3)),
                np.zeros((nb, 3, 3)), True, R_nom.copy(), False)
    p = np.empty(((2 * S if has_mag else S), 12))  # the mag's rows only where the rest has mag samples
    for s in range(S):
        for k in range(12):
            p[s, k] = X[s, a0 + k]
            if has_mag:
                p[S + s, k] = X[s, m0 + k]
    o, M, Mi = _model_pair_shared(p, S, 2 * S)
    Rs = np.empty((S, 3, 3))
    Rd = np.empty((3, 3))
    for s in range(S):
        _rodrigues_into(X[s, 0], X[s, 1], X[s, 2], Rd)
        for i in range(3):
            for j in range(3):
                Rs[s, i, j] = R_nom[i, 0] * Rd[0, j] + R_nom[i, 1] * Rd[1, j] + R_nom[i, 2] * Rd[2, j]
    z = np.empty(3 * nb)
    Z = np.empty((S, 3 * nb))
    r = np.empty(3 * nb)
    gated = np.ones(nb, np.bool_)
    droppable = np.zeros(nb, np.bool_)
    gk = np.empty(nb)
    k = 0
    if has_acc:
        f_all = np.empty((S, 3))
        for s in range(S):
            for i in range(3):
                f_all[s, i] = (M[s, i, 0] * (a_mean[0] - o[s, 0]) + M[s, i, 1] * (a_mean[1] - o[s, 1])
                               + M[s, i, 2] * (a_mean[2] - o[s, 2]))
        dev = _deviation(f_all, Wm, Wc, sig_a, gravity)
        var_a = sig_a**2 + (dev_gain * dev) ** 2 + 2.0 * gravity * dev
        for s in range(S):
            for i in range(3):
                Z[s, i] = (Mi[s, i, 0] * (gravity * Rs[s, 2, 0]) + Mi[s, i, 1] * (gravity * Rs[s, 2, 1])
                           + Mi[s, i, 2] * (gravity * Rs[s, 2, 2])) + o[s, i]
                if hold_acc >= 0:
                    Z[s, i] = Z[s, i] + X[s, hold_acc + i]
        for i in range(3):
            z[i] = a_mean[i]
            r[i] = var_a
        gk[0] = gates[0]
        k = 1
    if has_mag:
        c = 3 * k
        for s in range(S):
            cd, sd = math.cos(X[s, dip_col]), math.sin(X[s, dip_col])
            t = S + s
            h0 = cd * Rs[s, 1, 0] - sd * Rs[s, 2, 0]
            h1 = cd * Rs[s, 1, 1] - sd * Rs[s, 2, 1]
            h2 = cd * Rs[s, 1, 2] - sd * Rs[s, 2, 2]
            for i in range(3):
                Z[s, c + i] = (Mi[t, i, 0] * h0 + Mi[t, i, 1] * h1 + Mi[t, i, 2] * h2) + o[t, i]
                if hold_mag >= 0:
                    Z[s, c + i] = Z[s, c + i] + X[s, hold_mag + i]
        for i in range(3):
            z[c + i] = m_mean[i]
            r[c + i] = var_mag
        gk[k] = gates[1]
        k += 1
    c = 3 * k
    for s in range(S):
        for i in range(3):
            Z[s, c + i] = X[s, g0 + i]
            if hold_gyr >= 0:
                Z[s, c + i] = Z[s, c + i] + X[s, hold_gyr + i]
    for i in range(3):
        z[c + i] = w_mean[i]
        r[c + i] = var_rest[i]
    gated[k] = False
    gk[k] = np.inf
    Y = np.empty((S, n))
    for s in range(S):
        for j in range(n):
            Y[s, j] = X[s, j] - x0[j]
    x, P, nis, status, post_z, post_P, solved = update_kernel(Y, x0, P0, z, Z, r, Wm, Wc, gated, droppable, gk,
                                                              consider, 0.0, bool(True))  # noqa: UP018 (predict_kernel)
    xs, Ps, R, fine = fold_kernel(x, P, R_nom, yaw_var)
    return (True, xs, Ps, nis, status, post_z, post_P, solved, R, fine)


def rest_applies(cal: OnlineCalibrator) -> bool:
    """Whether a rest block's update can take :func:`rest_update_fast`: numba backend, no model extension
    (temperature and g-sensitivity terms stay on the general path)."""
    return enabled() and not cal.lay.ext_slice


def rest_update_fast(cal: OnlineCalibrator, acc: RestAccumulator, x0: Array, P0: Array, held: dict[str, bool],
                     first: bool, k_div: int, tl: float, sig_mag: float = 0.0) -> None:
    """The end of :func:`.step.rest_step` (sigma points, rest measurements, the gated update, its NIS
    bookkeeping, the fold and commit) with the arithmetic in :func:`rest_update_kernel`; ``k_div`` the
    divergence count before the block, ``first`` whether the rest began with this block (its NIS recorded),
    ``sig_mag`` raw the mag's per-sample noise (:meth:`.measurements.MagModel.variance`)."""
    st = _step_module()
    c = cal.config
    lay = cal.lay
    nst = lay.n
    lam = c.sp_alpha**2 * (nst + c.sp_kappa) - nst
    order = _identity(nst) if lay.perm_id else np.asarray(lay.perm, dtype=np.intp)
    has_acc, has_mag = bool(acc.na), bool(acc.nm)
    a_mean = acc.sa / acc.na if has_acc else np.zeros(3)
    m_mean = acc.sm / acc.nm if has_mag else np.zeros(3)
    s_gyr = float(np.mean(cal.x[SENSOR_SLICE["gyro"].start + 3 : SENSOR_SLICE["gyro"].start + 6]))
    var_rest = cal._models.zr.variance(acc.info("gyro"), s_gyr)
    gyr = cal.lay.hold_slice.get("gyro")
    yaw = c.yaw_free_sigma**2 if cal._mag.yaw_free else -1.0
    mod = cal._models.acc
    ok, x, P, nis, status, post_z, post_P, solved, R_new, fine = rest_update_kernel(
        x0, P0, lam + nst, order, cal.R_nom, cal._Wm, cal._Wc, has_acc, a_mean,
        1.0 / math.sqrt(acc.info("accel")) if has_acc else 1.0, has_mag, m_mean,
        cal._models.mag.variance(1.0 / acc.info("mag"), sig_mag, x0) if has_mag else 1.0,
        acc.gyro_mean(), var_rest, _hold_col(cal, "accel", held), _hold_col(cal, "mag", held),
        -1 if gyr is None else int(gyr.start), mod.gravity, mod.dev_gain,
        np.array([cal._gates["accel"], cal._gates["mag"]]), lay.consider, yaw, _G0, _A0, _M0, DIP)
    if not ok:
        cal._rest_acc = None
        cal._diverged("covariance is not positive definite", tl)
        return
    if not solved:
        raise np.linalg.LinAlgError("Singular matrix")
    res = UpdateResult(x, P)
    names = (["accel"] if has_acc else []) + (["mag"] if has_mag else []) + ["rest"]
    for k, s in enumerate(names):
        if status[k] < 0:
            continue
        res.nis.append((s, float(nis[k]), _STATUS[int(status[k])]))
        if status[k] != 2:
            res.post[s] = (post_z[k], post_P[k])
    st.gated_bookkeeping(cal, res, tl, first, 0.0)
    acc.post = res.post
    if cal._div.count == k_div:  # a divergence in the update also ended the running rest
        st.commit_folded(cal, R_new, x, P, fine, tl)
