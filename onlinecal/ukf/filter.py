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
  :mod:`.outputs` results · :mod:`.checkpoint` resume · :mod:`.stream` the blocks of the buffered samples ·
  :mod:`.start` attitude and magnetometer start · :mod:`.step` the predict/update (or rest) step of a block.

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

from ..io.base import ImuData
from ..model import SENSORS, Calibration
from . import checkpoint, divergence, warmup
from .attitude_init import ellipsoid_gn as ellipsoid_gn  # re-exported (older imports)
from .blocks import SampleBuffer
from .blocks import third_diff_var as third_diff_var  # re-exported
from .config import EXTENSIONS, UKFConfig
from .detectors import HoldTracker, Lattice, RailDetector, RestDetector
from .detectors import value_lattice as value_lattice
from .health import EventLog, NisMonitor, chi2_ppf
from .layout import AXES, SENSOR_SLICE, index
from .learning import Learning
from .magdisturb import MagDisturbanceGate
from .magstart import MagStart
from .measurements import AccelModel, MagModel, Models, ZeroRateModel, misfit_of
from .noise import NoiseModel, lattice_plan, raw_field_unit
from .noise import hold_sigma as hold_sigma  # re-exported
from .outputs import (
    calibration_of,
    extensions_of,
    extensions_sigma,
    missing_motion,
    observability,
    report_of,
)
from .rest import RestAccumulator
from .state import StateLayout, choose_gauge, grow, initial_state, prior, reset_states
from .stream import process
from .unscented import merwe_weights
from .vehicle import OMEGA_E_HORIZONTAL_RMS, MotionCoverage, VehicleDetector

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
        # a first run: the kernels compiled side by side in worker processes, and this one waits for them
        # (.warmup; once per process, a look at the cache's index where it is warm)
        warmup.ensure()
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
        self._vehicle = VehicleDetector.of(c)
        if c.vehicle == "vehicle":
            self._vehicle.active, self._vehicle.since, self._vehicle.reason = True, 0.0, "configured"
        self._coverage = MotionCoverage()
        self._div = divergence.DivergenceLog()  # a step whose update diverged does not commit its posterior
        self._magd = MagDisturbanceGate()  # a stretch of disturbed field is left out of the mag update
        # the accelerometer's and magnetometer's terms are learned in motion only at a new geometry (.learning;
        # checkpointed since schema /5)
        self._learn = Learning(math.radians(c.learn_angle_deg))
        self._reset_calibration()

    def _configure(self) -> None:
        """Everything derived from config and init alone: gates, specs, measurement models, gauge."""
        c = self.config
        self._gates = {"accel": chi2_ppf(c.acc_gate_p, 3), "mag": chi2_ppf(c.mag_gate_p, 3)}
        self._specs = c.sensor_specs()
        self._noise = NoiseModel(self._specs)
        self._models = Models(AccelModel(c.gravity, c.acc_dev_gain, c.acc_lever_m), MagModel(misfit_of(self.init)),
                              ZeroRateModel((c.rest_rate_sigma,) * 3))
        self.gauge, self._gauge_terms = choose_gauge(self.init, c)
        # the Earth-rate allowance (σ rad/s, Ω_h² (rad/s)²): .earth.allowance, per block where the latitude is known
        self._earth = ((c.rest_rate_sigma,) * 3, OMEGA_E_HORIZONTAL_RMS**2)

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
    # streaming (:mod:`.stream` cuts blocks, :mod:`.start` starts the attitude, :mod:`.step` filters a block)
    def feed(self, block: ImuData) -> None:
        """Consume a block of any size. IMU samples beyond the last full filter block wait in a buffer."""
        self._buf.append(block)
        process(self)

    def new_log(self) -> None:
        """The next samples start a new log: keep the calibration, restart the attitude and clock."""
        self.flush()
        self._buf = SampleBuffer()
        self._t_last = None
        self._att_ok = False
        self._next_trace = -math.inf  # each log's clock starts afresh (plots.monotone_time): so does its trace
        self._magd.new_log()
        self._lat.q = None  # a new log may come in another format: its lattice is detected again
        self._rest_det.reset()
        self._learn.reset()

    def flush(self) -> None:
        """Process the IMU samples still buffered as one (short) block; a running rest is closed."""
        process(self, final=True)
        self._end_rest()

    def _end_rest(self) -> None:
        """Close the running rest (:func:`.step.rest_step`): its last state stays."""
        self._rest_acc = None

    # ------------------------------------------------------------------------------------------
    # health (:mod:`.health`)
    def _nis_record(self, sensor: str, nis: float, t: float, inflated: float = 0.0, held: bool = False) -> None:
        why = self._nis.record(sensor, nis, t, inflated, held=held)
        if why is not None:
            self._diverged(why, t, sensor)

    def _diverged(self, why: str, t: float, sensor: str | None = None) -> None:
        """Restart (:func:`.divergence.plan_restart`: a widened prior, the cold prior on a second divergence
        soon after): the magnetometer and gyro terms (:func:`.divergence.restart_indices`) when the
        magnetometer's NIS alone ran away, otherwise every calibration state."""
        mag_only, mag_on = divergence.mag_alone(sensor, self._nis.stats["accel"]), bool(self._mag.enabled)
        sl = divergence.restart_indices(self.lay.consider, mag_on or mag_only, mag_only)
        wins = [w for s in (("mag",) if mag_only else ("accel", "mag")) for w in self._nis.stats[s]["windows"]]
        x_cold, sig_cold = divergence.cold_prior(self.config, self.x)
        r = divergence.plan_restart(self._div, t, self.x[sl], self.prior_x[sl], self.prior_sigma[sl], x_cold[sl],
                                    sig_cold[sl], wins, self._nis.band()[1], self.config.divergence_factor,
                                    "NIS window" not in why, (sl < SENSOR_SLICE["mag"].start))
        self._event("divergence", f"{why}; {r.detail}", t)
        divergence.announce(t, why, r, mag_only)
        if not mag_only:
            self._reset_calibration()
        reset_states(self.x, self.P, sl, r.x, np.diag(r.sigma**2))
        self.prior_sigma[sl], self.prior_x[sl] = r.sigma, r.x
        # the magnetometer stays calibrated unless the restart is cold: then it is fitted from raw samples again
        self._mag.restart(mag_on and r.kind != "cold")
        self._rest_acc = None
        self._learn.reset()
        self._att_ok = False  # the attitude (and heading) restarts with the next block
        self._magd.disarm()
        if mag_only:
            self._nis.restart("mag")
            self._nis.restart("accel")  # its run of bad windows (if any) saw the magnetometer's old state

    def _event(self, kind: str, detail: str, t: float) -> None:
        self._log.add(kind, detail, t)

    def nis_summary(self) -> dict[str, Any]:
        """Per sensor: updates, rejected by the gate, windows, share of window means inside the band."""
        return self._nis.summary(self._log.total)

    # ------------------------------------------------------------------------------------------
    # results (:mod:`.outputs`)
    def sigma(self) -> Array:
        """1σ (n,) of every state: √max(0, P_ii) (np.clip's ufunc without its Python wrapper: the same bits,
        ~3 µs less per block that reads it)."""
        out: Array = np.sqrt(np.maximum(self.P.diagonal(), 0.0))
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
        rep = report_of(self.lay, self.sigma(), self.prior_sigma, self._coverage, self._vehicle,
                        self.config.excited_ratio, bool(self._mag.enabled))
        c = self.config
        known = c.latitude_deg is not None
        rep["earth_rate"] = {"latitude_deg": c.latitude_deg,
                             "latitude_source": c.latitude_source if known else None,
                             "declination_deg": c.declination_deg if known else None,
                             "declination_sigma_deg": c.declination_sigma_deg if known else None,
                             "declination_source": (c.declination_source or ("--declination" if
                                                     c.declination_sigma_deg < 15.0 else "unknown")) if known else None,
                             "heading_known": not self._mag.yaw_free, "allowance_rad_s": list(self._earth[0])}
        return rep

    def missing_motion(self) -> list[str]:
        """What motion is still needed to excite the parameters that are not yet excited."""
        return missing_motion(self.observability(), self.lay, self._coverage)

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
