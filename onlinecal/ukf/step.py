"""The filter step of the online calibrator: predict over a block and update (motion), or the rest update.

:func:`step` decides per block (noise monitor, hold offsets, rest detector) between :func:`motion_step`
(sigma points propagated through the block, :mod:`.predict`; one joint update with the block-mean accel and
mag, :func:`.measurements.motion_measurements`) and :func:`rest_step` (the rest's running means as one
measurement on the state the rest began with, :mod:`.rest`). :func:`gated_update` is
:func:`.unscented.update` with the filter's gates and NIS bookkeeping; :func:`commit` takes the posterior
(attitude fold, USQUE) or declares a divergence.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ..model import SENSORS
from . import divergence, earth, fastpath
from .attitude_init import fold_attitude
from .blocks import Blocks
from .kernels_unscented import predict_moments_motion, sigma_points, update  # compiled or numpy (ONLINECAL_KERNELS)
from .layout import ATT, SENSOR_SLICE, index
from .magdisturb import calibrated_floats, nis_in_order
from .measurements import Offsets, ZeroRateModel, gyro_offsets, motion_measurements, rest_measurements
from .outputs import temp_regressor, trace_row
from .predict import block_process_noise, propagate_sigma_points
from .propagate import sensor_models
from .rest import RestAccumulator
from .start import calibrated, mag_block
from .unscented import Gating, Measurement, UpdateResult
from .vehicle import VEHICLE_NOTE, earth_rate_noise, rest_noise, vehicle_accel_var

if TYPE_CHECKING:
    from .filter import OnlineCalibrator

Array = NDArray[np.float64]
_GYR_BIAS, _GYR_SCALE = index("gyro", "bias"), index("gyro", "scale")
_ACC_BIAS, _MAG_BIAS = index("accel", "bias"), index("mag", "bias")
_ACC = SENSOR_SLICE["accel"]
_UNJUDGED: Array = np.empty(0)  # the σ handed to the disturbance gate for a block it does not judge


def step(cal: OnlineCalibrator, B: Blocks, b: int, t_all: Array, a_all: Array, T_all: Array, tm_all: Array,
         m_all: Array, clip: dict[str, bool]) -> None:
    """One UKF step over block ``b`` of ``B``: IMU samples [lo, hi) of the buffers t (s), a (m/s²),
    T (°C) (the gyro enters through ``B``) and mag samples [mlo, mhi) of tm, m: a rest step inside a
    rest, else predict + update."""
    c = cal.config
    i, j, ml, mh = B.lo_l[b], B.hi_l[b], B.mlo_l[b], B.mhi_l[b]
    t, a, T = t_all[i:j], a_all[i:j], T_all[i:j]
    tl = float(t[-1])
    use_mag, mag_changed = mag_block(cal, tm_all[ml:mh], m_all[ml:mh], tl)
    if mag_changed:
        cal._learn.reset("mag")
    if c.latitude_deg is not None:  # (after mag_block: it may have turned the heading to north)
        earth.correct_block(cal, B, b)
        earth_allowance(cal)
    # σ is read only where the block's field is judged (a used mag with samples): not computed otherwise
    sig = cal.sigma() if use_mag and mh > ml else _UNJUDGED
    use_mag = cal._magd.gate(use_mag, cal.x, sig, m_all[ml:mh], a, tl, c.gravity, cal._event,
                             nis_in_order(cal._nis.stats, cal._nis.band()[1]),  # a magnetic disturbance
                             accel_is_gravity=not cal._vehicle.active, means=(B.m_mean[b], B.a_mean[b]))
    spec = cal._spec_noise()
    q = cal._lat.q or {}
    turn = turning(cal, B, b)
    var3 = {s: math.nan if turn else B.var3_l[s][b] for s in SENSORS}  # NaN: the monitor leaves its level
    for kind, detail in cal._noise.monitor_all(var3, spec, q, c.noise_tau_blocks, c.noise_high, c.noise_low):
        cal._event(kind, detail, tl)
    n = cal._noise.noise(spec, q)
    held, resets, cal._hold_new = cal._holds.flags(B, b, n, q, cal._rest_det.prev_means,
                                                   tuple(cal.lay.hold_slice))
    for s in resets:
        cal._reset_hold(s)
    n_mean = cal._noise.for_means(n)
    det = cal._rest_det
    prev, was_still, count = det.prev_means, det.still, det.count
    n_rest = vehicle_rest_noise(cal, B, b, n, tl, turn)
    n_det = n_mean if n_rest is n else None
    zero_rate = det.update(B, b, n_rest, c.rest_k, c.rest_blocks, n_det) and det.still
    skip = False
    acc = cal._rest_acc
    if (not zero_rate and acc is not None and was_still and not acc.skipped and prev is not None
            and not (cal._hold_new or held != acc.held or mag_changed or use_mag != acc.use_mag)
            and det.marginal(B, b, n_rest, n_det, c.rest_k, prev)):
        # one block a little beyond the noise inside a rest: left out, the rest goes on (RestDetector.marginal);
        # the detector judges the next block against the block before this one
        det.prev_means, det.count, det.still = prev, count, True
        zero_rate = skip = True
    if was_still and det.still and prev is not None and not skip:
        block_mean_noise(cal, B, b, prev, n, tl)
        n_mean = cal._noise.for_means(n)
    n = n_mean
    if acc is not None and (not zero_rate or cal._hold_new or held != acc.held or mag_changed
                            or use_mag != acc.use_mag):
        cal._end_rest()
    if zero_rate:
        rest_step(cal, B, b, t, T, n, held, use_mag, clip, skip)
    else:
        motion_step(cal, B, b, t, a, T, n, held, use_mag, clip)


def block_mean_noise(cal: OnlineCalibrator, B: Blocks, b: int, prev: tuple[Any, ...], n: dict[str, float],
                     tl: float) -> None:
    """Two consecutive still blocks (the previous one's means ``prev``, block ``b`` of ``B``): their means'
    difference, per sensor, to the block-mean noise factor (:meth:`.noise.NoiseModel.rest_pair`) against
    the per-sample σ ``n`` the filter uses; both blocks taken at this block's sample count (1/L₁ + 1/L₂ =
    2/L), as the rest detector's bound on the change of the means takes them."""
    L, n_m = B.hi_l[b] - B.lo_l[b], B.mhi_l[b] - B.mlo_l[b]
    pairs = [("gyro", B.w_mean[b], prev[0], L), ("accel", B.a_mean[b], prev[1], L)]
    if n_m and prev[2] is not None:
        pairs.append(("mag", B.m_mean[b], prev[2], n_m))
    for s, mean, before, cnt in pairs:
        ev = cal._noise.rest_pair(s, mean, before, 2.0 / cnt, n[s])
        if ev is not None:
            cal._event(ev[0], ev[1], tl)


def offsets(cal: OnlineCalibrator, sensor: str, held: bool) -> Offsets:
    """The raw-reading offsets of ``sensor`` in the state: hold offset (if ``held``), extensions."""
    ext = cal.lay.ext_slice
    return Offsets(hold=cal.lay.hold_slice.get(sensor) if held else None,
                   temp=ext.get(f"temperature_bias:{sensor}"),
                   gsens=ext.get("g_sensitivity") if sensor == "gyro" else None)


def temp_reg(cal: OnlineCalibrator, T: Array) -> Array:
    """Regressor T − T0 (°C) of the temperature extensions; 0 where the log has no temperature."""
    reg, cal._T0 = temp_regressor(T, cal._T0)
    return reg


def has_temp(cal: OnlineCalibrator) -> bool:
    return any(e.startswith("temperature_bias") for e in cal.lay.ext_slice)


def turning(cal: OnlineCalibrator, B: Blocks, b: int) -> bool:
    """Whether block ``b`` of ``B`` turns too fast for its third differences to measure noise
    (ω_q = :attr:`.config.UKFConfig.noise_rate_max`, rad/s). Either test:

    * its mean raw rate less the gyro bias is above ω_q by more than 3σ of the bias (so a cold start's wide
      bias judges only the fast turns);
    * its rate varies within the block: the spread's Σσ² (rad/s)² above ω_q² + 2 × what the gyro's own
      measured noise gives (3 × its third-difference variance; twice it, for the spread's scatter over
      ~20 samples). It needs no bias: a hand's turn onset, whose mean is still small, shows here (Ferraris
      at 3.6 s: mean 0.38 rad/s, spread 0.58, the bias's σ 0.2 on a cold start); vibration, whose third
      differences read at least its variance, does not.

    Never on a vehicle detected by its vibration (:attr:`.vehicle.VehicleDetector.vibrating`), which is its
    accelerometer's noise at any rate; a vehicle detected by a linear acceleration (a hand's push, too) is
    judged as before."""
    if cal._vehicle.vibrating:
        return False
    wq = cal.config.noise_rate_max
    s = B.w_std[b]
    spread = float(s[0]) ** 2 + float(s[1]) ** 2 + float(s[2]) ** 2
    if spread > wq * wq + 6.0 * B.var3_l["gyro"][b]:  # NaN noise: not decided here
        return True
    i = _GYR_BIAS.start
    x, P, w = cal.x, cal.P, B.w_mean[b]
    wx, wy, wz = float(w[0]) - float(x[i]), float(w[1]) - float(x[i + 1]), float(w[2]) - float(x[i + 2])
    sig = math.sqrt(max(0.0, float(P[i, i]) + float(P[i + 1, i + 1]) + float(P[i + 2, i + 2])))
    return math.sqrt(wx * wx + wy * wy + wz * wz) > wq + 3.0 * sig


def vehicle_rest_noise(cal: OnlineCalibrator, B: Blocks, b: int, n: dict[str, float], tl: float,
                       turn: bool = False) -> dict[str, float]:
    """Feed the vehicle detector (:mod:`.vehicle`) the block's accel vibration (none in a block that
    is ``turn``-ing, :func:`turning`); the noise the rest test judges against: on a vehicle the spec's, not
    the vibration-raised level (a vibrating vehicle is not at rest, and its accelerometer then measures
    thrust, not gravity)."""
    if cal.config.vehicle == "auto":
        vib = math.nan if turn else math.sqrt(max(0.0, B.var3_l["accel"][b]))
        vehicle_event(cal, cal._vehicle.update(vib, None, tl), tl)
    return rest_noise(n, cal._vehicle, cal._noise.high["accel"], cal._noise.ratio["accel"])


def vehicle_accel(cal: OnlineCalibrator, M: Array, o: Array, a_mean: Array, sig_mean: float, dt: float,
                  tl: float) -> float:
    """Variance (m/s²)² the vehicle's unknown acceleration adds to a moving block's accel update
    (0 until the data show a vehicle: :class:`.vehicle.VehicleDetector`, fed here the specific-force
    norm's unexplained deviation from g for the sigma points' models M (S, 3, 3), o (S, 3))."""
    c = cal.config
    if c.vehicle == "auto" and not cal._vehicle.active:
        f_all = np.einsum("sij,sj->si", M, a_mean - o)
        dev = cal._models.acc.deviation(f_all, cal._Wm, cal._Wc, sig_mean)
        vehicle_event(cal, cal._vehicle.update(math.nan, dev, tl), tl)
    return vehicle_accel_var(c.vehicle_accel_sigma, c.vehicle_accel_tau, dt) if cal._vehicle.active else 0.0


def vehicle_accel_from_dev(cal: OnlineCalibrator, dev: float, dt: float, tl: float) -> float:
    """:func:`vehicle_accel` with the specific force's deviation ``dev`` (m/s²) already computed
    (:func:`.fastpath.predict_kernel`)."""
    c = cal.config
    if c.vehicle == "auto" and not cal._vehicle.active:
        vehicle_event(cal, cal._vehicle.update(math.nan, dev, tl), tl)
    return vehicle_accel_now(cal, dt)


def vehicle_accel_now(cal: OnlineCalibrator, dt: float) -> float:
    """The variance (m/s²)² of :func:`vehicle_accel` as the vehicle detector stands (a block that does not
    switch it on: :func:`.fastpath.motion_kernel` takes it as an input)."""
    c = cal.config
    return vehicle_accel_var(c.vehicle_accel_sigma, c.vehicle_accel_tau, dt) if cal._vehicle.active else 0.0


def vehicle_event(cal: OnlineCalibrator, why: str | None, tl: float) -> None:
    if why:
        cal._event("vehicle", why + VEHICLE_NOTE, tl)


def earth_allowance(cal: OnlineCalibrator) -> None:
    """The Earth-rate allowance of this block (:func:`.earth.allowance`: it shrinks once a heading is held)
    into ``cal._earth`` and the zero-rate model."""
    c = cal.config
    cal._earth = earth.allowance(c.latitude_deg, not cal._mag.yaw_free, c.rest_rate_sigma, c.declination_sigma_deg,
                                 cal.R_nom[2].tolist())
    if cal._models.zr.rest_rate_sigma != cal._earth[0]:
        cal._models = replace(cal._models, zr=ZeroRateModel(cal._earth[0]))


def earth_rate_q(cal: OnlineCalibrator, q: Array, dt_blk: float) -> Array:
    """The block's Q diagonal ``q`` (n,) with, on a vehicle, what the Earth's rotation (which the gyro model
    lacks) leaves unknown (:func:`.vehicle.earth_rate_noise`, in place); both motion paths call it (the
    compiled one before its kernel adds the block's own terms: the terms are additive)."""
    if cal._vehicle.active:
        sx, sy, sz = cal.x[_GYR_SCALE].tolist()  # np.mean of three, ((a + b) + c) / 3, on Python floats
        earth_rate_noise(q, cal.P, _GYR_BIAS, (sx + sy + sz) / 3.0, cal._earth[0],
                         cal.config.vehicle_accel_tau, dt_blk, cal._earth[1])
    return q


def motion_step(cal: OnlineCalibrator, B: Blocks, b: int, t: Array, a: Array, T: Array, n: dict[str, float],
                held: dict[str, bool], use_mag: bool, clip: dict[str, bool]) -> None:
    """Predict over the block, then one update with its mean accel (unless clipped) and mag; the magnetometer's
    terms and the accelerometer's learned only at a new geometry (:class:`.learning.Learning`)."""
    x = cal.x
    cal._learn.decide(None if clip["accel"] or cal._vehicle.active else (B.a_mean[b], x[_ACC_BIAS]),
                      (B.m_mean[b], x[_MAG_BIAS]) if use_mag else None)
    if fastpath.applies(cal, held, use_mag, clip):  # an ordinary block: two compiled calls (.fastpath)
        fastpath.motion_step_fast(cal, B, b, t, n, held, use_mag, clip)
        return
    tl = float(t[-1])
    try:
        X = sigma_points_of(cal)
    except np.linalg.LinAlgError:
        cal._diverged("covariance is not positive definite", tl)
        return
    off = offsets(cal, "gyro", cal._rest_det.still)
    extra = gyro_offsets(X[cal.lay.dyn_pts], off, temp_reg(cal, T) if off.temp is not None else None,
                         calibrated(cal, "accel", a) if off.gsens is not None else None, T.shape[0])
    pred, sens = propagate_sigma_points(X, cal.R_nom, B, b, cal.lay.dyn_pts, use_mag, extra)
    dt_blk = float(t[-1] - cal._t_last)
    q = earth_rate_q(cal, block_process_noise(cal._process_noise(dt_blk, n["gyro"]), B, b, dt_blk, n["gyro"],
                                              cal.P), dt_blk)
    x_pred, Y, P_pred = predict_moments_motion(X, cal._Wm, cal._Wc, q, cal.P)
    cal.R_nom = pred.R_end[0]
    T_reg = float(np.mean(temp_reg(cal, T))) if has_temp(cal) else 0.0
    rate = float(np.linalg.norm(pred.M_gyr @ (B.w_mean[b] - pred.o_gyr)))
    n_m = int(B.mhi[b] - B.mlo[b])
    S = X.shape[0]
    o, M = sens[0][:S], sens[1][:S]
    var_v = vehicle_accel(cal, M, o, B.a_mean[b], n["accel"] / math.sqrt(t.size), dt_blk, tl)
    cal._coverage.add_motion(pred.M_gyr @ (B.w_mean[b] - pred.o_gyr), dt_blk, cal._vehicle.active)
    if use_mag:
        cal._coverage.add_field(calibrated(cal, "mag", B.m_mean[b]))
    meas = motion_measurements(
        cal._models, X, pred.f_body, pred.h_body, sens, None if clip["accel"] else B.a_mean[b],
        B.m_mean[b] if use_mag else None, n["accel"] / math.sqrt(t.size),
        cal._models.mag.variance(n["mag"] ** 2 / max(n_m, 1), n["mag"], cal.x),
        (cal._Wm, cal._Wc), rate, (offsets(cal, "accel", held["accel"]), offsets(cal, "mag", held["mag"])),
        T_reg, var_v)
    if not meas:
        commit(cal, x_pred, P_pred, tl)
        return
    # not at rest (rests go to rest_step): an accel outlier is motion the model lacks, dropped
    k = cal._div.count
    # a vehicle-disturbed accel NIS is judged apart, against σ_v² (.health.NisMonitor)
    k_v = var_v / cal.config.vehicle_accel_sigma**2 if var_v > 0 else 0.0
    res = gated_update(cal, Y, x_pred, P_pred, meas, False, tl, damp=cal.config.update_damping, inflated=k_v)
    if cal._div.count == k:  # else the update declared a divergence: the restarted state stands
        commit(cal, res.x, res.P, tl)


def rest_step(cal: OnlineCalibrator, B: Blocks, b: int, t: Array, T: Array, n: dict[str, float], held: dict[str, bool],
              use_mag: bool, clip: dict[str, bool], skip: bool = False) -> None:
    """A block inside a rest (:mod:`.rest`): the attitude is held (no gyro integration: the gyro's
    reading at rest is its bias, measured by the zero-rate update) and the rest's running means are
    one measurement on the state the rest began with. Ended by :meth:`_end_rest`. ``skip``: a lone block a
    little beyond the noise (:meth:`.detectors.RestDetector.marginal`), left out of the means and the NIS:
    the rest's measurement is applied again with its process noise one block longer, as for any rest block
    (whose gyro passed the same still test: the attitude is held)."""
    tl = float(t[-1])
    if not (np.isfinite(cal.P).all() and (cal.P.diagonal() > 0).all()):
        # the running rest restarts from its first state, which would hide a broken covariance
        cal._rest_acc = None
        cal._diverged("non-finite or non-positive variance", tl)
        return
    acc = cal._rest_acc
    first = acc is None
    if acc is None:
        acc = cal._rest_acc = RestAccumulator.start(cal.x, cal.P, cal.R_nom, held, use_mag)
    dt_blk = float(t[-1] - cal._t_last)
    acc.q += cal._process_noise(dt_blk, n["gyro"])
    acc.dur += dt_blk
    acc.skipped = skip
    k = cal._div.count
    if not skip:  # a skipped block adds its time (its process noise) and nothing else: no NIS, no means
        misfit = cal._models.mag.variance(0.0, n["mag"], acc.x) if use_mag else 0.0
        for s, nis in acc.sequential_nis(B, b, n, not clip["accel"], use_mag, misfit):
            cal._nis_record(s, nis, tl)
        if cal._div.count != k:
            return  # a divergence: the restarted state stands (not the rest's first state)
        acc.add(B, b, n, not clip["accel"], use_mag, temp_reg(cal, T) if has_temp(cal) else None)
        # with a temperature state the model has a term for a warm-up drift
        if cal.config.measure_bias_walk and "temperature_bias:gyro" not in cal.lay.ext_slice:
            slope, var_slope = acc.trend()
            ev = cal._noise.walk_from_rest(slope, var_slope, acc.dur, acc.kw)
            if ev is not None:
                cal._event(ev[0], ev[1], tl)
            acc.walk = cal._noise.q_walk
    if acc.na:
        a_mean = acc.sa / acc.na
        if not skip:
            cal._coverage.add_rest_lazy(calibrated_floats(cal.x[_ACC].tolist(), a_mean.tolist()), dt_blk,
                                        lambda: calibrated(cal, "accel", a_mean))
        # the rest's means are one measurement at its geometry: motion there has nothing new for those terms
        cal._learn.seen("accel", a_mean)
    if use_mag and acc.nm:
        cal._learn.seen("mag", acc.sm / acc.nm)
    x0, P0 = acc.x, acc.P + np.diag(acc.q)
    cal.x, cal.P, cal.R_nom = x0.copy(), P0, acc.R_nom
    if fastpath.rest_applies(cal):  # the rest's update in one compiled call (.fastpath)
        fastpath.rest_update_fast(cal, acc, x0, P0, held, first, k, tl, n["mag"])
        return
    try:
        X = sigma_points_of(cal)
    except np.linalg.LinAlgError:
        cal._rest_acc = None
        cal._diverged("covariance is not positive definite", tl)
        return
    sens = sensor_models(np.concatenate([X[:, SENSOR_SLICE["accel"]], X[:, SENSOR_SLICE["mag"]]]))
    off = (offsets(cal, "accel", held["accel"]), offsets(cal, "mag", held["mag"]), offsets(cal, "gyro", True))
    meas = rest_measurements(cal._models, X, cal.R_nom, sens, acc, (cal._Wm, cal._Wc), off,
                             float(np.mean(cal.x[index("gyro", "scale")])), n["mag"], x0)
    res = gated_update(cal, X - x0, x0, P0, meas, True, tl, record=first, post=True)
    acc.post = res.post
    if cal._div.count == k:  # a divergence in the update also ended the running rest
        commit(cal, res.x, res.P, tl)


def sigma_points_of(cal: OnlineCalibrator) -> Array:
    c = cal.config
    return sigma_points(cal.x, cal.P, c.sp_alpha, c.sp_kappa, cal.lay.perm, cal.lay.perm_id)


def gated_update(cal: OnlineCalibrator, Y: Array, x_pred: Array, P_pred: Array, meas: list[Measurement],
                 static: bool, t: float, record: bool = True, post: bool = False, damp: float = 0.0,
                 inflated: float = 0.0) -> UpdateResult:
    """:func:`.unscented.update` with this filter's gates and consider states (in motion
    :func:`.fastpath.motion_consider`'s), then the NIS bookkeeping in measurement order (``record``: the NIS
    values enter the windows; ``inflated`` = k > 0: the accel R carried the vehicle disturbance,
    :meth:`.health.NisMonitor.record`)."""
    consider = cal.lay.consider if static else fastpath.motion_consider(cal, any(m.name == "mag" for m in meas))
    res = update(Y, x_pred, P_pred, meas, cal._Wm, cal._Wc, Gating(cal._gates, static), consider, damp, post)
    gated_bookkeeping(cal, res, t, record, inflated, motion=not static)
    return res


def gated_bookkeeping(cal: OnlineCalibrator, res: UpdateResult, t: float, record: bool, inflated: float,
                      motion: bool = False) -> None:
    """The NIS bookkeeping of :func:`gated_update` for its result ``res``, in measurement order; in ``motion``
    each accel update's drop (or not) also goes to the vehicle detector (:meth:`.vehicle.VehicleDetector.gate`:
    linear accelerations the norm test missed)."""
    feed_gate = motion and cal.config.vehicle == "auto" and not cal._vehicle.active
    for s, nis, status in res.nis:
        fail = divergence.nis_failure(nis)
        if fail is not None:  # passes both the gate and the windows otherwise
            cal._diverged(f"{s}: {fail}", t)
            return
        if s == "accel" and feed_gate:
            vehicle_event(cal, cal._vehicle.gate(status == "drop", t), t)
        if status == "drop":
            # motion the model has no term for (linear acceleration): an outlier, not a statistic of
            # the filter's consistency — dropped and counted, kept out of the NIS windows
            cal._nis.reject(s, inflated)
            continue
        if record and not (motion and cal._learn.holds(s)):
            # (a held look's NIS is not a new sample: .learning.Learning; a thrust-borne vehicle's motion holds the
            # magnetometer's soft iron: .state.StateLayout.mag_flight_terms)
            cal._nis_record(s, nis, t, inflated, motion and s == "mag" and fastpath.soft_iron_held(cal))
        if status == "soft":
            cal._nis.reject(s, inflated)


def commit(cal: OnlineCalibrator, x_new: Array, P_new: Array, tl: float) -> None:
    """Take a posterior (x (n,), P (n, n)) as the state after a motion or rest update at log time ``tl`` s:
    fold its attitude error into the nominal (reset, USQUE), forget the heading while nothing sees it,
    and treat a non-finite state or non-positive variance as a divergence instead."""
    c = cal.config
    # Without a usable mag nothing sees the heading, exactly (a world-z turn leaves Rᵀe_z alone): it is
    # forgotten, with a diffuse σ (a small one would leak spurious information into the alphas)
    R, x_new, P_new = fold_attitude(cal.R_nom, x_new, P_new,
                                    c.yaw_free_sigma**2 if cal._mag.yaw_free else None, ATT)
    fine = bool(np.isfinite(x_new).all() and np.isfinite(P_new).all() and (P_new.diagonal() > 0).all())
    commit_folded(cal, R, x_new, P_new, fine, tl)


def commit_folded(cal: OnlineCalibrator, R: Array, x_new: Array, P_new: Array, fine: bool, tl: float) -> None:
    """:func:`commit` after the fold (R (3, 3), x, P folded; ``fine``: finite with a positive diagonal)."""
    c = cal.config
    cal.R_nom = R
    if not fine:
        cal._diverged("non-finite state or non-positive variance", tl)
        return
    cal.x, cal.P = x_new, P_new
    cal._n_blocks += 1
    if tl >= cal._next_trace:
        cal._trace.append(trace_row(tl, cal.x, cal.sigma(), cal.lay,
                                    {s: cal._nis.last(s) for s in cal._nis.stats}))
        cal._next_trace = tl + c.trace_every_s
