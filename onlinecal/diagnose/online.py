"""diagnose, the UKF stage: the augmented-state UKF (:func:`onlinecal.ukf.replay`) run once from the batch
baseline and once with the chosen extension, and its innovation consistency compared.

The statistic is the UKF's windowed NIS (normalised innovation squared, ν'S⁻¹ν, 3 dof per accelerometer or
magnetometer update; Bar-Shalom, Li & Kirubarajan 2001, Sec. 5.4): the mean over ``nis_window`` updates
has a chi-square band (``nis_summary()["band"]``, per update); a model that misses an effect shows window
means above it. The extended run corrects the data by the extension (:func:`onlinecal.extensions.correct`)
or, where the UKF carries a matching state (``UKFConfig.extra_states``), estimates it as a state instead.
"""

from __future__ import annotations

from dataclasses import fields
from typing import Any

import numpy as np

from ..effect_registry import UKF_STATE
from ..io.base import ImuData
from ..model import Calibration
from ..specs import G0

# extension (effect, sensor) → the UKF's extra state estimating it (onlinecal.ukf.filter.EXTENSIONS)
STATE_OF = UKF_STATE
# not corrected in the data: axis_sign is already undone before the baseline is fitted; bias_drift and
# saturation have no pointwise inverse (the filter's bias random walk and rail detector cover them)
NOT_CORRECTED = ("axis_sign", "bias_drift", "saturation")


def _available_states() -> tuple[str, ...]:
    from ..ukf import filter as uf

    if "extra_states" not in {f.name for f in fields(uf.UKFConfig)}:
        return ()
    return tuple(getattr(uf, "EXTENSIONS", {}))


def nis_stats(nis: dict[str, Any]) -> dict[str, Any]:
    """From ``OnlineResult.nis``: per sensor the mean of the window-mean NIS (per update, 3 dof; expected 3),
    the band of a window mean, the share of windows outside it and above it (model error, what an extension
    can remove; below it R is larger than the innovations), and the pooled figures over the sensors."""
    band = [float(v) for v in nis.get("band", [np.nan, np.nan])]
    out: dict[str, Any] = {"band": band, "sensors": {}}
    tot_w = 0
    s_mean = s_out = s_above = 0.0
    for s in ("accel", "mag"):
        st = nis.get(s)
        if not isinstance(st, dict) or not st.get("windows"):
            continue
        w = int(st["windows"])
        outside = 1.0 - float(st["in_band"])
        above = float(st.get("above_band", float("nan")))
        out["sensors"][s] = {"nis_mean": float(st["mean"]), "outside_band": outside, "above_band": above,
                             "windows": w, "updates": int(st["updates"]), "rejected": int(st["rejected"])}
        tot_w += w
        s_mean += w * float(st["mean"])
        s_out += w * outside
        s_above += w * above
    out["nis_mean"] = s_mean / tot_w if tot_w else float("nan")
    out["outside_band"] = s_out / tot_w if tot_w else float("nan")
    out["above_band"] = s_above / tot_w if tot_w else float("nan")
    out["events"] = int(nis.get("events_total", 0))
    return out


def run_ukf(logs: list[ImuData], cal: Calibration, extensions: dict[str, Any] | None = None,
            g: float = G0) -> dict[str, Any]:
    """One UKF replay over ``logs`` from ``cal`` (the batch baseline), with ``extensions`` (the calibration
    JSON's format) applied: matched to UKF extra states where available, else corrected in the data.
    ``g`` (m/s²) the local gravity the baseline was fitted to: the filter's accelerometer update compares
    |a| with it, so a filter run on the standard 9.80665 against a batch fitted to another g sees a constant
    norm error of their difference in every update (imu_tk Xsens, g = 9.81744: 0.011 m/s², several times the
    accelerometer's noise, mean NIS 8.4 instead of 3.2).

    Returns {nis_mean, outside_band, band, sensors: {accel|mag: ...}, events, extra_states, corrected,
    wall_s, online_extensions} or {"error": message} when the filter cannot run on these logs.
    """
    from ..extensions import correct, validate_extensions
    from ..ukf import UKFConfig, replay

    ext = validate_extensions(extensions)
    avail = _available_states()
    states: list[str] = []
    rest: dict[str, Any] = {}
    for name, entries in ext.items():
        kept = []
        for e, raw in zip(entries, _raw_entries(extensions, name), strict=True):
            st = STATE_OF.get((name, e["sensor"]))
            if name == "g_sensitivity" and raw.get("matrix") is not None:
                st = None  # the filter's g_sensitivity state is diagonal: a full matrix is applied to the data
            if st in avail:
                states.append(st)
            elif name not in NOT_CORRECTED:
                kept.append(raw)
        if kept:
            rest[name] = kept[0] if len(kept) == 1 else kept
    try:
        data = [correct(d, rest, calibration=cal) for d in logs] if rest else logs
        # the bias walk measured at rest off: it would absorb a warm-up drift as noise, the model error that
        # this stage is there to show (docs/flight.md); so is the vehicle detector's drop rule, which would take
        # a model error's outliers for a vehicle's acceleration and move their NIS out of the band's judgement
        cfg = UKFConfig(gravity=g, extra_states=tuple(dict.fromkeys(states)), measure_bias_walk=False,
                        vehicle_gate_drops=0)
        res = replay(data, cal, cfg)
    except Exception as e:  # noqa: BLE001 - the UKF stage informs; the batch diagnosis stands without it
        return {"error": f"{type(e).__name__}: {e}"}
    out = nis_stats(res.nis)
    out.update({"extra_states": list(dict.fromkeys(states)), "corrected": sorted(rest), "wall_s": res.wall_s,
                "online_extensions": res.calibration.extensions})
    return out


def _raw_entries(extensions: dict[str, Any] | None, name: str) -> list[dict[str, Any]]:
    v = (extensions or {})[name]
    return list(v) if isinstance(v, list) else [v]
