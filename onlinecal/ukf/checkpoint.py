"""Checkpoint of the online calibrator: everything needed to resume, as a JSON-able dict."""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from ..model import Calibration
from .attitude_init import MagCollector
from .blocks import HoldTracker, Lattice, RailDetector, RestDetector, SampleBuffer
from .config import UKFConfig
from .health import NisMonitor, finite_or_none, none_to_inf
from .magstart import MagStart
from .rest import RestAccumulator
from .vehicle import MotionCoverage, VehicleDetector

STATE_SCHEMA = "onlinecal.ukf-state/2"


def get_state(f: Any) -> dict[str, Any]:
    """The state of the calibrator ``f`` (plain lists and numbers)."""
    rd = f._rest_det
    return {
        "schema": STATE_SCHEMA,
        "config": f.config.to_dict(),
        "init": f.init.to_dict() if f.init is not None else None,
        "names": list(f.names), "holds": list(f.lay.hold_slice), "hold_sigma": dict(f._hold_sigma),
        "x": f.x.tolist(), "P": f.P.tolist(), "R_nom": f.R_nom.tolist(),
        "prior_sigma": f.prior_sigma.tolist(), "prior_x": f.prior_x.tolist(),
        "rate": f._rate, "L": f._L,
        **f._buf.to_dict(),
        "t_last": f._t_last, "w_last": f._w_last.tolist(), "att_ok": f._att_ok,
        "yaw_free": f._mag.yaw_free,
        "align_yaw_next": f._mag.align_next,
        "mag_enabled": f._mag.enabled, "dip_known": f._mag.dip_known, "mag_buf": f._mag.buf.buf.tolist(),
        "mag_buf_next": finite_or_none(f._mag.buf.next_t), "mag_fit_next": finite_or_none(f._mag.fit_next),
        "next_trace": finite_or_none(f._next_trace), "n_imu": f._n_imu, "n_blocks": f._n_blocks,
        "nis": f._nis.stats, "events": f._log.events, "n_events": f._log.total, "trace": list(f._trace),
        "rest_count": rd.count,
        "prev_means": None if rd.prev_means is None else [
            None if v is None else np.asarray(v).tolist() for v in rd.prev_means],
        "q": f._lat.q, "q_mag_buf": f._lat.mag_buf, "held": f._holds.held,
        "noise_ratio": f._noise.ratio, "noise_high": f._noise.high,
        "rail": f._rails.rail, "run": {k: [list(r) for r in v] for k, v in f._rails.run.items()},
        "clip_on": f._rails.clip_on, "T0": f._T0,
        "rest_acc": None if f._rest_acc is None else f._rest_acc.to_dict(),
        "vehicle": f._vehicle.to_dict(), "coverage": f._coverage.get_state(),
    }


def set_state(f: Any, d: dict[str, Any]) -> None:
    """Restore the calibrator ``f`` from :func:`get_state` (its init and config are replaced)."""
    if d.get("schema") != STATE_SCHEMA:
        raise ValueError(f"not a UKF state (schema {d.get('schema')!r}, expected {STATE_SCHEMA})")
    f.config = UKFConfig.from_dict(d["config"])
    c = f.config
    f.init = Calibration.from_dict(d["init"]) if d["init"] is not None else None
    f._configure()
    f._set_layout(tuple(d["holds"]))
    if list(f.names) != list(d["names"]):
        raise ValueError("UKF state: its state names do not match its config")
    f._hold_sigma = {k: float(v) for k, v in d["hold_sigma"].items()}
    f.x = np.asarray(d["x"], float)
    f.P = np.asarray(d["P"], float)
    f.R_nom = np.asarray(d["R_nom"], float)
    f.prior_sigma = np.asarray(d["prior_sigma"], float)
    f.prior_x = np.asarray(d["prior_x"], float)
    f._rate, f._L = d["rate"], int(d["L"])
    f._buf = SampleBuffer.from_dict(d)
    f._t_last = d["t_last"]
    f._w_last = np.asarray(d["w_last"], float)
    f._att_ok = bool(d["att_ok"])
    f._mag = MagStart(bool(d["mag_enabled"]), bool(d["dip_known"]),
                      MagCollector(np.asarray(d["mag_buf"], float).reshape(-1, 3), none_to_inf(d["mag_buf_next"])),
                      none_to_inf(d["mag_fit_next"]), bool(d["align_yaw_next"]), bool(d["yaw_free"]))
    f._next_trace = none_to_inf(d["next_trace"])
    f._n_imu, f._n_blocks = int(d["n_imu"]), int(d["n_blocks"])
    f._nis = NisMonitor(c.nis_window, c.nis_band_p, c.divergence_factor, c.divergence_windows)
    f._nis.stats = d["nis"]
    f._log.max_events = c.max_events
    f._log.events = list(d["events"])
    f._log.total = int(d["n_events"])
    f._trace = deque(d["trace"], maxlen=c.trace_max_rows)
    pm = d.get("prev_means")
    prev = None if pm is None else (*(None if v is None else np.asarray(v, float) for v in pm),)
    f._rest_det = RestDetector(prev, int(d.get("rest_count", 0)))
    f._lat = Lattice(d["q"], [list(v) for v in d["q_mag_buf"]])
    f._holds = HoldTracker({k: bool(v) for k, v in d["held"].items()})
    f._noise.ratio = {k: float(v) for k, v in d["noise_ratio"].items()}
    f._noise.high = {k: bool(v) for k, v in d["noise_high"].items()}
    f._rails = RailDetector({k: [float(x) for x in v] for k, v in d["rail"].items()},
                            {k: [(float(r[0]), int(r[1])) for r in v] for k, v in d["run"].items()},
                            {k: bool(v) for k, v in d["clip_on"].items()})
    f._T0 = d["T0"]
    f._vehicle = VehicleDetector(c.vehicle_vibration_sigma, c.vehicle_dev_min)
    f._vehicle.set_state(d.get("vehicle", {}))
    f._coverage = MotionCoverage()
    f._coverage.set_state(d.get("coverage", {}))
    ra = d.get("rest_acc")
    f._rest_acc = None if ra is None else RestAccumulator.from_dict(ra)
