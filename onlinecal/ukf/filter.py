"""The augmented-state UKF: attitude on the manifold plus every calibration term of the paper's model.

Filter: the scaled unscented transform of Wan & van der Merwe (2000) (:mod:`.unscented`), with the attitude
kept as a nominal rotation plus a 3-vector error in the state (the error-state / manifold treatment of
Crassidis & Markley's USQUE, 2003): sigma points are rotation vectors around the nominal, and after each
update the mean error is folded into the nominal and reset to zero. One filter step covers a block of IMU
samples (``UKFConfig.block_s``): all sigma points are propagated through it at once (:mod:`.propagate`),
then one joint update with the block-mean accelerometer (quasi-static weighting, chi-square gate) and
magnetometer (:mod:`.measurements`). Inside a rest the readings are one measurement applied to the state the
rest began with (:mod:`.rest`). The parts:

* :mod:`.config` settings · :mod:`.state` layout, gauge, prior · :mod:`.blocks` raw-data statistics and
  detectors · :mod:`.noise` R and Q · :mod:`.measurements` h(x) and R · :mod:`.unscented` sigma points and
  the update · :mod:`.attitude_init` attitude and mag start · :mod:`.health` NIS and events ·
  :mod:`.outputs` results · :mod:`.checkpoint` resume.

This module is the orchestration only: it owns the state (x, P, R_nom) and decides which part runs when.
Where the sigma points cannot see a term they get an allowance: δM·δo of the gyro (:func:`.noise.bilinear_var`)
and, in motion, a partial update (``update_damping``, Zanetti 2012). The state can also carry hold offsets
(a log re-quantised on a coarse lattice) and model extensions (``UKFConfig.extra_states``).
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from ..io.base import ImuData
from ..model import SENSORS, Calibration
from . import checkpoint
from .attitude_init import attitude_start, fold_attitude
from .attitude_init import ellipsoid_gn as ellipsoid_gn  # re-exported (older imports)
from .blocks import Blocks, HoldTracker, Lattice, RailDetector, RestDetector, SampleBuffer, block_stats, cut_blocks
from .blocks import third_diff_var as third_diff_var  # re-exported
from .blocks import value_lattice as value_lattice
from .config import EXTENSIONS, MIN_SAMPLES_DETECT, UKFConfig
from .health import EventLog, NisMonitor
from .kernels_unscented import predict_moments, sigma_points, update  # compiled or numpy (ONLINECAL_KERNELS)
from .layout import ATT, AXES, DIP, SENSOR_SLICE, correction, index
from .magstart import MagStart, mag_prior_from_raw
from .measurements import (
    AccelModel,
    MagModel,
    Models,
    Offsets,
    ZeroRateModel,
    gyro_offsets,
    motion_measurements,
    rest_measurements,
)
from .noise import NoiseModel, lattice_plan, raw_field_unit
from .noise import hold_sigma as hold_sigma  # re-exported
from .outputs import (
    calibration_of,
    extensions_of,
    extensions_sigma,
    missing_motion,
    observability,
    report_of,
    temp_regressor,
    trace_row,
)
from .predict import block_process_noise, propagate_sigma_points
from .propagate import sensor_models
from .rest import RestAccumulator
from .state import StateLayout, choose_gauge, grow, initial_state, prior, reset_states
from .unscented import Gating, Measurement, UpdateResult, merwe_weights
from .vehicle import VEHICLE_NOTE, MotionCoverage, VehicleDetector, rest_noise, vehicle_accel_var

Array = NDArray[np.float64]
STATE_SCHEMA = checkpoint.STATE_SCHEMA


class OnlineCalibrator:
    """Streaming augmented-state UKF (see module docstring).

    ``init``: a Calibration to start from (its σ times ``config.init_inflation`` is the prior; missing
    sensors or σ fall back to the cold prior), or None for a cold start: bias 0, scale 1, angles 0 with
    the wide ``config.cold_sigma``. The magnetometer's cold start is a sphere (ellipsoid) fit on buffered
    raw samples once they span enough directions; until then the mag is not used and the yaw is left free.

    ``feed(block)`` takes any block size (a carry-over buffer keeps incomplete filter blocks; memory is
    constant in the log length), ``result()`` gives the current Calibration with σ.
    """

    def __init__(self, init: Calibration | None = None, config: UKFConfig | None = None) -> None:
        self.config = config or UKFConfig()
        self.init = init
        c = self.config
        for e in c.extra_states:
            if e not in EXTENSIONS:
                raise ValueError(f"unknown extra state {e!r} (known: {', '.join(EXTENSIONS)})")
        self._configure()
        self._log = EventLog(c.max_events)
        self._trace: deque[dict[str, float]] = deque(maxlen=c.trace_max_rows)
        self._rate: float | None = None
        self._L = 0
        self._buf = SampleBuffer()  # samples fed, not yet filtered
        self._t_last: float | None = None
        self._w_last = np.zeros(3)
        self._att_ok = False
        self._next_trace = -math.inf
        self._n_imu = 0
        self._n_blocks = 0
        self._lat = Lattice()  # per log: value lattice of each sensor
        self._rails = RailDetector()
        self._T0: float | None = None
        self._vehicle = VehicleDetector(c.vehicle_vibration_sigma, c.vehicle_dev_min)
        if c.vehicle == "vehicle":
            self._vehicle.active, self._vehicle.since, self._vehicle.reason = True, 0.0, "configured"
        self._coverage = MotionCoverage()
        self._reset_calibration()

    def _configure(self) -> None:
        """Everything derived from config and init alone: gates, specs, measurement models, gauge."""
        c = self.config
        self._gates = {"accel": float(chi2.ppf(c.acc_gate_p, 3)), "mag": float(chi2.ppf(c.mag_gate_p, 3))}
        self._specs = c.sensor_specs()
        self._noise = NoiseModel(self._specs)
        self._models = Models(AccelModel(c.gravity, c.acc_dev_gain, c.acc_lever_m), MagModel(),
                              ZeroRateModel(c.rest_rate_sigma))
        self.gauge, self._gauge_terms = choose_gauge(self.init, c)

    # ------------------------------------------------------------------------------------------
    # state
    def _set_layout(self, holds: tuple[str, ...] = ()) -> None:
        c = self.config
        self.lay = StateLayout(c.extra_states, holds, self.gauge, self._gauge_terms)
        self._Wm, self._Wc = merwe_weights(self.lay.n, c.sp_alpha, c.sp_beta, c.sp_kappa)

    @property
    def names(self) -> list[str]:
        return self.lay.names

    @property
    def n(self) -> int:
        return self.lay.n

    @property
    def events(self) -> list[dict[str, Any]]:
        return self._log.events

    def _prior(self) -> tuple[Array, Array]:
        """Prior mean and σ of the 40 base states (:func:`.state.prior`)."""
        return prior(self.init, self.config, self.gauge, self._gauge_terms)

    def _reset_calibration(self) -> None:
        """(Re)start every calibration state from the prior; the attitude restarts on the next block."""
        c = self.config
        self._set_layout()
        self._hold_sigma: dict[str, float] = {}
        self.x, self.P, self.prior_x, self.prior_sigma = initial_state(self.lay, *self._prior())
        self.R_nom = np.eye(3)
        self._mag = MagStart(enabled=self.init is not None and self.init.mag is not None)
        self._att_ok = False
        self._rest_det = RestDetector()
        self._rest_acc: RestAccumulator | None = None
        self._hold_new = False
        self._holds = HoldTracker()
        self._nis = NisMonitor(c.nis_window, c.nis_band_p, c.divergence_factor, c.divergence_windows)
        if self._lat.q is not None:
            self._apply_lattice(tuple(k for k in SENSORS if k in self._lat.q))

    def _add_hold(self, sensor: str, sigma: float) -> None:
        """Append the 3 hold-offset states of ``sensor`` (0 ± sigma), or reset them if present."""
        if sensor not in self.lay.hold_slice:
            self._set_layout(self.lay.holds + (sensor,))
            self.x, self.P, self.prior_x, self.prior_sigma = grow(self.x, self.P, self.prior_x, self.prior_sigma,
                                                                  self.n)
        self._hold_sigma[sensor] = sigma
        self._reset_hold(sensor)

    def _reset_hold(self, sensor: str) -> None:
        sl = self.lay.hold_slice[sensor]
        reset_states(self.x, self.P, sl, 0.0, np.eye(3) * self._hold_sigma[sensor] ** 2)
        self.prior_sigma[sl] = self._hold_sigma[sensor]

    # ------------------------------------------------------------------------------------------
    # noise and lattice (:mod:`.noise`)
    def _spec_noise(self) -> dict[str, float]:
        return self._noise.spec_noise(self._rate, self.x)

    def _cal_rw(self) -> Array:
        """Random-walk variance per second of every state (:meth:`.noise.NoiseModel.cal_rw`)."""
        ext = [(sl, EXTENSIONS[e][1]) for e, sl in self.lay.ext_slice.items()]
        return self._noise.cal_rw(self.n, self.x, ext, self.config.rw_factor)

    def _process_noise(self, dt: float, sigma_gyr: float) -> Array:
        return NoiseModel.process_noise(self._cal_rw(), dt, self._rate, sigma_gyr)

    def _apply_lattice(self, sensors: tuple[str, ...]) -> None:
        """A lattice coarser than the sensor's own ADC is a re-quantisation by the format: its q²/12 joins
        the white noise and, with ``quant_hold``, the held-reading offsets join the state."""
        q = self._lat.q
        assert q is not None
        for s, req, hs in lattice_plan(q, sensors, self._rate or 100.0, self._mag_unit_raw(), self._specs):
            q[s + "_requant"] = req
            if req and self.config.quant_hold:
                first = s not in self.lay.hold_slice
                self._add_hold(s, hs)
                if first and self.init is not None and self.init.sensor(s) is not None:
                    # a bias found from held readings through this format carries the same hold error,
                    # which the init's σ (fitted as if the rounding averaged out) does not include
                    b = index(s, "bias")
                    self.P[b, b] += np.eye(3) * hs**2
                    self.prior_sigma[b] = np.hypot(self.prior_sigma[b], hs)

    def _mag_unit_raw(self) -> float:
        """Raw field magnitude: from the mag scale once known, else the first raw samples' norm."""
        return raw_field_unit(self.x, self._mag.enabled, self._lat.mag_buf)

    # ------------------------------------------------------------------------------------------
    # streaming
    def feed(self, block: ImuData) -> None:
        """Consume a block of any size. IMU samples beyond the last full filter block wait in a buffer."""
        self._buf.append(block)
        self._process()

    def new_log(self) -> None:
        """The next samples start a new log: keep the calibration, restart the attitude and clock."""
        self.flush()
        self._buf = SampleBuffer()
        self._t_last = None
        self._att_ok = False
        self._lat.q = None  # a new log may come in another format: its lattice is detected again
        self._rest_det.reset()

    def flush(self) -> None:
        """Process the IMU samples still buffered as one (short) block; a running rest is closed."""
        self._process(final=True)
        self._end_rest()

    def _start_log(self, final: bool) -> bool:
        """The rate and the value lattice from the log's first samples (a fixed count, so the result does
        not depend on how the log is cut into feed() calls); False while too few samples are in."""
        buf, k = self._buf, MIN_SAMPLES_DETECT
        if buf.t.size < k and not (final and buf.t.size >= 2):
            return False
        if self._rate is None:
            self._rate = float(1.0 / np.median(np.diff(buf.t[:k])))
            self._L = max(1, int(round(self.config.block_s * self._rate)))
        j = int(np.searchsorted(buf.tm, buf.t[min(k, buf.t.size) - 1], side="right"))
        self._apply_lattice(self._lat.detect(buf.w[:k], buf.a[:k], buf.m[:j]))
        self._lat.settle()
        return True

    def _process(self, final: bool = False) -> None:
        if self._lat.q is None and not self._start_log(final):
            return
        buf = self._buf
        bounds = cut_blocks(buf.t, self._L, self.config.max_gap_s, final)
        if not bounds:
            return
        continues = (self._att_ok and self._t_last is not None
                     and buf.t[0] - self._t_last <= self.config.max_gap_s)
        B = block_stats(buf.t, buf.w, buf.a, buf.tm, buf.m, bounds, self._t_last, self._w_last, bool(continues))
        for b in range(len(bounds)):
            self._block(B, b, buf.t, buf.w, buf.a, buf.T, buf.tm, buf.m)
        buf.drop(bounds[-1][1], int(B.mhi[-1]))

    def _block(self, B: Blocks, b: int, t: Array, w: Array, a: Array, T: Array, tm: Array, mm: Array) -> None:
        """One filter block: gap check, lattice of a late mag, rail, then attitude start or filter step."""
        i, j, ml, mh = int(B.lo[b]), int(B.hi[b]), int(B.mlo[b]), int(B.mhi[b])
        tb = t[i:j]
        t0 = self._t_last if self._att_ok and self._t_last is not None else None
        if self._t_last is not None and tb[0] - self._t_last > self.config.max_gap_s:
            self._gap(float(tb[0] - self._t_last), float(tb[0]))
            t0 = None
        tmb, mb = tm[ml:mh], mm[ml:mh]
        if self._lat.late_mag(mb):
            self._apply_lattice(("mag",))
            self._lat.settle()
        clip, events = self._rails.check(w[i:j], a[i:j], B.w_absmax[b], B.a_absmax[b],
                                         self.config.rail_min, self.config.rail_run)
        for kind, detail in events:
            self._event(kind, detail, float(tb[-1]))
        if clip["gyro"]:
            # a clipped gyro turns the attitude by less than the body did: nothing of this block is
            # used, and the attitude restarts from the accel (and mag) once the gyro is off the rail
            self._end_rest()
            self._att_ok = False
        elif t0 is None:
            self._end_rest()
            self._init_attitude(a[i:j], tmb, mb)
        else:
            self._step(B, b, t, a, T, tm, mm, clip)
        self._t_last = float(tb[-1])
        self._w_last = w[j - 1].copy()
        self._n_imu += j - i

    def _gap(self, gap: float, t: float) -> None:
        self._event("gap", f"IMU gap of {gap:.3f} s: attitude restarted, calibration drift "
                           "allowance for the gap added", t)
        self._end_rest()
        self.P[np.diag_indices(self.n)] += self._cal_rw() * gap
        self._att_ok = False
        self._rest_det.reset()

    # ------------------------------------------------------------------------------------------
    # attitude and magnetometer start (:mod:`.attitude_init`)
    def _calibrated(self, sensor: str, raw: Array) -> Array:
        o, M = correction(self.x[None, SENSOR_SLICE[sensor]])
        out: Array = (raw - o[0]) @ M[0].T
        return out

    def _init_attitude(self, a: Array, tm: Array, m: Array) -> None:
        """Attitude from the block's mean accel (roll, pitch) and, where the mag is usable, its field (yaw).

        The attitude comes from these very readings, so its error is a function of the accel (and mag)
        calibration error; rather than model that correlation, it starts with a σ wide enough that the
        missing correlation does not matter: the next updates re-derive the attitude properly."""
        c = self.config
        if m.shape[0]:
            self._mag_collect(tm, m)
        use_mag = self._mag.enabled and m.shape[0] > 0
        h = self._calibrated("mag", m.mean(axis=0)) if use_mag else None
        self.R_nom, P_att, dip = attitude_start(self._calibrated("accel", a.mean(axis=0)), h, float(self.x[DIP]),
                                                self._mag.dip_known, c.att_init_sigma, c.yaw_free_sigma)
        if dip is not None:
            self._set_dip(dip)
        reset_states(self.x, self.P, ATT, 0.0, P_att)
        self._att_ok = True
        self._mag.yaw_free = not use_mag

    def _set_dip(self, dip: float) -> None:
        reset_states(self.x, self.P, DIP, dip, self.config.dip_sigma**2)
        self._mag.dip_known = True

    def _mag_collect(self, tm: Array, m: Array) -> None:
        cold = self.init is None or self.init.mag is None
        if self._mag.collect(tm, m, cold, self.config.mag_buffer_max):
            sl = SENSOR_SLICE["mag"]
            held = (self.x[sl][6:], np.sqrt(np.diag(self.P)[sl][6:])) if self.gauge == "mag" else None
            pr = mag_prior_from_raw(m, self.config.cold_sigma["mag"], held)
            if pr is not None:
                reset_states(self.x, self.P, sl, pr[0], np.diag(pr[1] ** 2))
                self.prior_x[sl], self.prior_sigma[sl] = pr

    def _mag_block(self, tm: Array, m: Array, tl: float) -> tuple[bool, bool]:
        """The mag's part of a block (:class:`.magstart.MagStart`): collect and fit while cold, align the
        yaw after the fit. Returns whether the block's mag is used and whether the mag's state changed
        (which ends a rest)."""
        ms, c = self._mag, self.config
        before = (ms.enabled, ms.align_next)
        n_m = m.shape[0]
        if n_m and not ms.enabled:
            self._mag_collect(tm, m)
            fit = ms.try_fit(tl, c)
            if fit is not None:
                sl = SENSOR_SLICE["mag"]
                reset_states(self.x, self.P, sl, fit.x, np.diag(fit.sigma**2))
                self.prior_sigma[sl] = fit.prior_sigma
                self.prior_x[sl] = self.x[sl]
                self._event("mag_cold_start", fit.detail, tl)
        if ms.enabled and ms.align_next and n_m:
            dip, self.R_nom, self.P = ms.align(self.R_nom, self.P, self._calibrated("mag", m.mean(axis=0)),
                                               c.att_init_sigma**2, ATT)
            self._set_dip(dip)  # (the dip's rows do not enter the attitude block: the order does not matter)
        use_mag = ms.enabled and n_m > 0 and not ms.align_next
        return use_mag, before != (ms.enabled, ms.align_next)

    # ------------------------------------------------------------------------------------------
    # the filter step
    def _step(self, B: Blocks, b: int, t_all: Array, a_all: Array, T_all: Array, tm_all: Array,
              m_all: Array, clip: dict[str, bool]) -> None:
        """One UKF step over block ``b`` of ``B``: IMU samples [lo, hi) of the buffers t (s), a (m/s²),
        T (°C) (the gyro enters through ``B``) and mag samples [mlo, mhi) of tm, m: a rest step inside a
        rest, else predict + update."""
        c = self.config
        i, j, ml, mh = int(B.lo[b]), int(B.hi[b]), int(B.mlo[b]), int(B.mhi[b])
        t, a, T = t_all[i:j], a_all[i:j], T_all[i:j]
        tl = float(t[-1])
        use_mag, mag_changed = self._mag_block(tm_all[ml:mh], m_all[ml:mh], tl)
        spec = self._spec_noise()
        q = self._lat.q or {}
        for kind, detail in self._noise.monitor_all({s: float(B.var3[s][b]) for s in SENSORS}, spec, q,
                                                    c.noise_tau_blocks, c.noise_high, c.noise_low):
            self._event(kind, detail, tl)
        n = self._noise.noise(spec, q)
        held, resets, self._hold_new = self._holds.flags(B, b, n, q, self._rest_det.prev_means,
                                                         tuple(self.lay.hold_slice))
        for s in resets:
            self._reset_hold(s)
        zero_rate = self._rest_det.update(B, b, self._vehicle_rest_noise(B, b, n, tl), c.rest_k,
                                          c.rest_blocks) and self._rest_det.still
        acc = self._rest_acc
        if acc is not None and (not zero_rate or self._hold_new or held != acc.held or mag_changed
                                or use_mag != acc.use_mag):
            self._end_rest()
        if zero_rate:
            self._rest_step(B, b, t, T, n, held, use_mag, clip)
        else:
            self._motion_step(B, b, t, a, T, n, held, use_mag, clip)

    def _offsets(self, sensor: str, held: bool) -> Offsets:
        """The raw-reading offsets of ``sensor`` in the state: hold offset (if ``held``), extensions."""
        ext = self.lay.ext_slice
        return Offsets(hold=self.lay.hold_slice.get(sensor) if held else None,
                       temp=ext.get(f"temperature_bias:{sensor}"),
                       gsens=ext.get("g_sensitivity") if sensor == "gyro" else None)

    def _temp_reg(self, T: Array) -> Array:
        """Regressor T − T0 (°C) of the temperature extensions; 0 where the log has no temperature."""
        reg, self._T0 = temp_regressor(T, self._T0)
        return reg

    def _has_temp(self) -> bool:
        return any(e.startswith("temperature_bias") for e in self.lay.ext_slice)

    def _vehicle_rest_noise(self, B: Blocks, b: int, n: dict[str, float], tl: float) -> dict[str, float]:
        """Feed the vehicle detector (:mod:`.vehicle`) the block's accel vibration; the noise the rest test
        judges against: on a vehicle the spec's, not the vibration-raised level (a vibrating vehicle is
        not at rest, and its accelerometer then measures thrust, not gravity)."""
        if self.config.vehicle == "auto":
            self._vehicle_event(self._vehicle.update(math.sqrt(max(0.0, float(B.var3["accel"][b]))), None, tl), tl)
        return rest_noise(n, self._vehicle, self._noise.high["accel"], self._noise.ratio["accel"])

    def _vehicle_accel(self, M: Array, o: Array, a_mean: Array, sig_mean: float, dt: float, tl: float) -> float:
        """Variance (m/s²)² the vehicle's unknown acceleration adds to a moving block's accel update
        (0 until the data show a vehicle: :class:`.vehicle.VehicleDetector`, fed here the specific-force
        norm's unexplained deviation from g for the sigma points' models M (S, 3, 3), o (S, 3))."""
        c = self.config
        if c.vehicle == "auto" and not self._vehicle.active:
            f_all = np.einsum("sij,sj->si", M, a_mean - o)
            dev = self._models.acc.deviation(f_all, self._Wm, self._Wc, sig_mean)
            self._vehicle_event(self._vehicle.update(math.nan, dev, tl), tl)
        return vehicle_accel_var(c.vehicle_accel_sigma, c.vehicle_accel_tau, dt) if self._vehicle.active else 0.0

    def _vehicle_event(self, why: str | None, tl: float) -> None:
        if why:
            self._event("vehicle", why + VEHICLE_NOTE, tl)

    def _motion_step(self, B: Blocks, b: int, t: Array, a: Array, T: Array, n: dict[str, float],
                     held: dict[str, bool], use_mag: bool, clip: dict[str, bool]) -> None:
        """Predict over the block, then one update with its mean accel (unless clipped) and mag."""
        tl = float(t[-1])
        try:
            X = self._sigma_points()
        except np.linalg.LinAlgError:
            self._diverged("covariance is not positive definite", tl)
            return
        off = self._offsets("gyro", self._rest_det.still)
        extra = gyro_offsets(X[self.lay.dyn_pts], off, self._temp_reg(T) if off.temp is not None else None,
                             self._calibrated("accel", a) if off.gsens is not None else None, T.shape[0])
        pred, sens = propagate_sigma_points(X, self.R_nom, B, b, self.lay.dyn_pts, use_mag, extra)
        dt_blk = float(t[-1] - self._t_last)
        q = block_process_noise(self._process_noise(dt_blk, n["gyro"]), B, b, dt_blk, n["gyro"], self.P)
        x_pred, Y, P_pred = predict_moments(X, self._Wm, self._Wc, q)
        self.R_nom = pred.R_end[0]
        T_reg = float(np.mean(self._temp_reg(T))) if self._has_temp() else 0.0
        rate = float(np.linalg.norm(pred.M_gyr @ (B.w_mean[b] - pred.o_gyr)))
        n_m = int(B.mhi[b] - B.mlo[b])
        S = X.shape[0]
        o, M = sens[0][:S], sens[1][:S]
        var_v = self._vehicle_accel(M, o, B.a_mean[b], n["accel"] / math.sqrt(t.size), dt_blk, tl)
        self._coverage.add_motion(pred.M_gyr @ (B.w_mean[b] - pred.o_gyr), dt_blk, self._vehicle.active)
        if use_mag:
            self._coverage.add_field(self._calibrated("mag", B.m_mean[b]))
        meas = motion_measurements(
            self._models, X, pred.f_body, pred.h_body, sens, None if clip["accel"] else B.a_mean[b],
            B.m_mean[b] if use_mag else None, n["accel"] / math.sqrt(t.size), n["mag"] ** 2 / max(n_m, 1),
            (self._Wm, self._Wc), rate, (self._offsets("accel", held["accel"]), self._offsets("mag", held["mag"])),
            T_reg, var_v)
        if not meas:
            self._commit(x_pred, P_pred, tl)
            return
        # not at rest (rests go to _rest_step): an accel outlier is motion the model lacks, dropped
        # a vehicle-disturbed accel NIS is judged apart, against σ_v² (.health.NisMonitor)
        self._nis.inflated = var_v / self.config.vehicle_accel_sigma**2 if var_v > 0 else 0.0
        res = self._update(Y, x_pred, P_pred, meas, False, tl, damp=self.config.update_damping)
        self._nis.inflated = 0.0
        self._commit(res.x, res.P, tl)

    def _rest_step(self, B: Blocks, b: int, t: Array, T: Array, n: dict[str, float], held: dict[str, bool],
                   use_mag: bool, clip: dict[str, bool]) -> None:
        """A block inside a rest (:mod:`.rest`): the attitude is held (no gyro integration: the gyro's
        reading at rest is its bias, measured by the zero-rate update) and the rest's running means are
        one measurement on the state the rest began with. Ended by :meth:`_end_rest`."""
        tl = float(t[-1])
        if not (np.isfinite(self.P).all() and (self.P.diagonal() > 0).all()):
            # the running rest restarts from its first state, which would hide a broken covariance
            self._rest_acc = None
            self._diverged("non-finite or non-positive variance", tl)
            return
        acc = self._rest_acc
        first = acc is None
        if acc is None:
            acc = self._rest_acc = RestAccumulator.start(self.x, self.P, self.R_nom, held, use_mag)
        dt_blk = float(t[-1] - self._t_last)
        acc.q += self._process_noise(dt_blk, n["gyro"])
        for s, nis in acc.sequential_nis(B, b, n, not clip["accel"], use_mag):
            self._nis_record(s, nis, tl)
        acc.add(B, b, n, not clip["accel"], use_mag, self._temp_reg(T) if self._has_temp() else None)
        if acc.na:
            self._coverage.add_rest(self._calibrated("accel", acc.sa / acc.na), dt_blk)
        x0, P0 = acc.x, acc.P + np.diag(acc.q)
        self.x, self.P, self.R_nom = x0.copy(), P0, acc.R_nom
        try:
            X = self._sigma_points()
        except np.linalg.LinAlgError:
            self._rest_acc = None
            self._diverged("covariance is not positive definite", tl)
            return
        sens = sensor_models(np.concatenate([X[:, SENSOR_SLICE["accel"]], X[:, SENSOR_SLICE["mag"]]]))
        off = (self._offsets("accel", held["accel"]), self._offsets("mag", held["mag"]), self._offsets("gyro", True))
        meas = rest_measurements(self._models, X, self.R_nom, sens, acc, (self._Wm, self._Wc), off,
                                 float(np.mean(self.x[index("gyro", "scale")])))
        res = self._update(X - x0, x0, P0, meas, True, tl, record=first, post=True)
        acc.post = res.post
        self._commit(res.x, res.P, tl)  # a divergence there also ends the running rest (_reset_calibration)

    def _end_rest(self) -> None:
        """Close the running rest (:meth:`_rest_step`): its last state stays."""
        self._rest_acc = None

    def _sigma_points(self) -> Array:
        c = self.config
        return sigma_points(self.x, self.P, c.sp_alpha, c.sp_kappa, self.lay.perm, self.lay.perm_id)

    def _update(self, Y: Array, x_pred: Array, P_pred: Array, meas: list[Measurement], static: bool, t: float,
                record: bool = True, post: bool = False, damp: float = 0.0) -> UpdateResult:
        """:func:`.unscented.update` with this filter's gates and consider states, then the NIS
        bookkeeping in measurement order (``record``: the NIS values enter the windows)."""
        res = update(Y, x_pred, P_pred, meas, self._Wm, self._Wc, Gating(self._gates, static),
                     self.lay.consider, damp, post)
        for s, nis, status in res.nis:
            if status == "drop":
                # motion the model has no term for (linear acceleration): an outlier, not a statistic of
                # the filter's consistency — dropped and counted, kept out of the NIS windows
                self._nis.reject(s)
                continue
            if record:
                self._nis_record(s, nis, t)
            if status == "soft":
                self._nis.reject(s)
        return res

    def _commit(self, x_new: Array, P_new: Array, tl: float) -> None:
        """Take a posterior (x (n,), P (n, n)) as the state after a motion or rest update at log time ``tl`` s:
        fold its attitude error into the nominal (reset, USQUE), forget the heading while nothing sees it,
        and treat a non-finite state or non-positive variance as a divergence instead."""
        c = self.config
        # Without a usable mag nothing sees the heading, exactly (a world-z turn leaves Rᵀe_z alone): it is
        # forgotten, with a diffuse σ (a small one would leak spurious information into the alphas)
        self.R_nom, x_new, P_new = fold_attitude(self.R_nom, x_new, P_new,
                                                 c.yaw_free_sigma**2 if self._mag.yaw_free else None, ATT)
        if (not np.isfinite(x_new).all() or not np.isfinite(P_new).all()
                or not (P_new.diagonal() > 0).all()):
            self._diverged("non-finite state or non-positive variance", tl)
            return
        self.x, self.P = x_new, P_new
        self._n_blocks += 1
        if tl >= self._next_trace:
            self._trace.append(trace_row(tl, self.x, self.sigma(), self.lay,
                                         {s: self._nis.last(s) for s in self._nis.stats}))
            self._next_trace = tl + c.trace_every_s

    # ------------------------------------------------------------------------------------------
    # health (:mod:`.health`)
    def _nis_record(self, sensor: str, nis: float, t: float) -> None:
        why = self._nis.record(sensor, nis, t)
        if why is not None:
            self._diverged(why, t, sensor)

    def _diverged(self, why: str, t: float, sensor: str | None = None) -> None:
        """Re-initialise: only the magnetometer (its terms and the dip, from the init or a new cold fit)
        when its NIS alone ran away, otherwise every calibration state from the init calibration."""
        if sensor != "mag":
            self._event("divergence", why + "; re-initialised from the init calibration", t)
            self._reset_calibration()
            return
        self._event("divergence", why + "; magnetometer re-initialised", t)
        x0, sig0 = self._prior()
        sl = np.r_[np.arange(SENSOR_SLICE["mag"].start, SENSOR_SLICE["mag"].stop), DIP]
        reset_states(self.x, self.P, sl, x0[sl], np.diag(sig0[sl] ** 2))
        self.prior_sigma[sl], self.prior_x[sl] = sig0[sl], x0[sl]
        self._mag.restart(self.init is not None and self.init.mag is not None)
        self._rest_acc = None
        self._att_ok = False  # the heading restarts with the next block
        self._nis.restart("mag")

    def _event(self, kind: str, detail: str, t: float) -> None:
        self._log.add(kind, detail, t)

    def nis_summary(self) -> dict[str, Any]:
        """Per sensor: updates, rejected by the gate, windows, share of window means inside the band."""
        return self._nis.summary(self._log.total)

    # ------------------------------------------------------------------------------------------
    # results (:mod:`.outputs`)
    def sigma(self) -> Array:
        out: Array = np.sqrt(np.clip(np.diag(self.P), 0.0, None))
        return out

    def result(self) -> Calibration:
        """The current estimate as a Calibration (source "online") with 1σ for bias, scale, alpha, xi, and
        the model extensions (``extensions``, the contract's effect keys) with their σ."""
        meta = {"mag_used": bool(self._mag.enabled), "imu_samples": self._n_imu, "blocks": self._n_blocks,
                "quantisation": dict(self._lat.q or {}), "events": list(self.events), "nis": self.nis_summary(),
                "observability": self.observability_report()}
        return calibration_of(self.x, self.sigma(), self.lay, meta, self.extensions(), self.init)

    def extensions(self) -> dict[str, Any]:
        """Estimated model extensions in the effect vocabulary (:func:`.outputs.extensions_of`)."""
        return extensions_of(self.x, self.lay, self._T0)

    def extensions_sigma(self) -> dict[str, list[float]]:
        """1σ of every extension coefficient, per axis: {``extra_states`` key: [3]}."""
        return extensions_sigma(self.sigma(), self.lay)

    def observability(self) -> dict[str, dict[str, Any]]:
        """Per parameter: posterior σ / prior σ and whether it is excited (ratio below ``excited_ratio``)."""
        return observability(self.sigma(), self.prior_sigma, self.lay, self.config.excited_ratio)

    def observability_report(self) -> dict[str, Any]:
        """Which terms the data determined, which not, why, and what motion would determine them
        (:func:`.vehicle.observability_report`), with the motion's coverage and the vehicle detector."""
        return report_of(self.lay, self.sigma(), self.prior_sigma, self._coverage, self._vehicle,
                         self.config.excited_ratio, bool(self._mag.enabled))

    def missing_motion(self) -> list[str]:
        """What motion is still needed to excite the parameters that are not yet excited."""
        return missing_motion(self.observability(), self.lay)

    def trace_rows(self, clear: bool = False) -> list[dict[str, float]]:
        """Trace rows (time, every estimate, its σ, last NIS) every ``trace_every_s``; ``clear`` drains."""
        rows = list(self._trace)
        if clear:
            self._trace.clear()
        return rows

    # ------------------------------------------------------------------------------------------
    # checkpoint / resume (:mod:`.checkpoint`)
    def get_state(self) -> dict[str, Any]:
        """Everything needed to resume, as a JSON-able dict (plain lists and numbers)."""
        return checkpoint.get_state(self)

    def set_state(self, d: dict[str, Any]) -> None:
        """Restore from :meth:`get_state` (the instance's init and config are replaced by the saved ones)."""
        checkpoint.set_state(self, d)

    @classmethod
    def from_state(cls, d: dict[str, Any]) -> OnlineCalibrator:
        checkpoint.check_schema(d)
        obj = cls(None, UKFConfig.from_dict(d["config"]))
        obj.set_state(d)
        return obj


# kept importable from here (tests, benchmarks and diagnose import them from onlinecal.ukf.filter)
__all__ = ["AXES", "EXTENSIONS", "OnlineCalibrator", "UKFConfig", "ellipsoid_gn", "hold_sigma",
           "third_diff_var", "value_lattice"]
