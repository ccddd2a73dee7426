"""The paper's offline pipeline over one or more logs of one sensor unit: segment → mag → accel → gyro.

Data flow: each log is segmented on its own (rests, motions, rotation phases); the fits then pool
every log — a campaign is often several files (statics, turns, a sphere).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..io.base import ImuData
from ..model import Calibration, SensorCalibration
from ..specs import G0
from .clean import clean_log
from .clock import regularise_clock
from .ellipsoid import FitError
from .gyro import fit_gyroscope
from .segment import Segmentation, noise_floors, segment
from .sensors import (
    StepReport,
    dip_outliers,
    distinct_directions,
    fit_accelerometer,
    fit_magnetometer,
    mag_to_accel_rotation,
    static_means,
)


def _drop_sigma(c: SensorCalibration, st: StepReport | None) -> SensorCalibration:
    """``c`` without σ for the terms its step lists as undetermined."""
    und = set(st.figures.get("undetermined", [])) if st is not None else set()
    if not und:
        return c
    return SensorCalibration(c.bias, c.matrix, {k: v for k, v in c.sigma.items() if k not in und and k != "matrix"})


def _rotated_sigma(sigma: Mapping[str, Any], extra_deg: float) -> dict[str, Any]:
    """σ of a sensor whose frame was turned by a rotation known to ``extra_deg`` (1σ): alpha widened."""
    out = {k: np.asarray(v, float) for k, v in sigma.items()}
    if "alpha" in out:
        out["alpha"] = np.hypot(out["alpha"], np.radians(extra_deg))
    return out


@dataclass
class BatchResult:
    calibration: Calibration
    segmentations: list[Segmentation]
    steps: dict[str, StepReport]
    warnings: list[str] = field(default_factory=list)

    def summary(self) -> dict:
        return {
            "files": [s.data.source for s in self.segmentations],
            "segments": [
                {"file": s.data.source, "statics": len(s.statics), "motions": len(s.motions),
                 "phases": "".join("xyz"[p.axis] for p in s.phases)}
                for s in self.segmentations
            ],
            "steps": {k: v.to_dict() for k, v in self.steps.items()},
            "warnings": self.warnings,
        }


def run_batch(logs: list[ImuData], g: float = G0, seed: int = 0, reduced: Sequence[Any] = (),
              latitude_deg: float | None = None) -> BatchResult:
    """Calibrate gyro, accel and mag from raw logs of one unit (paper Sec. III).

    A sensor whose step cannot run (no mag in the logs, too few attitudes, no rest) is left out with
    a warning naming the step; a result without any sensor raises FitError. ``reduced``: the
    :class:`~onlinecal.batch.reduce.Reduction` of each long log whose kept stretches are among ``logs``
    (:func:`~onlinecal.batch.reduce.read_reduced`), stated in ``meta.batch.reduced``. ``latitude_deg``: where
    the logs were recorded (a log's GPS, ``--latitude``): the gyro bias at rest without the Earth rotation's
    vertical part (:func:`~onlinecal.batch.gyro.gyro_bias_cumsum`), as the filter told it reads its gyro.
    """
    rng = np.random.default_rng(seed)
    # Field readings without IMU samples (a long log's magnetometer sample outside its kept stretches,
    # onlinecal.batch.reduce): for the magnetometer fit only.
    mag_only = [clean_log(d).data for d in logs if d.n_imu == 0 and d.n_mag > 0]
    logs = [d for d in logs if d.n_imu > 0]
    if not logs:
        raise FitError("no IMU samples in the logs")
    # Reader warnings carry no file name; with several logs of one unit the user must know which one.
    warnings: list[str] = [w if d.source in w else f"{d.source}: {w}" for d in logs for w in d.warnings]
    clocked = [regularise_clock(d) for d in logs]
    logs = [c[0] for c in clocked]
    for _, notes in clocked:
        warnings += notes
    cleaned = [clean_log(d) for d in logs]
    logs = [c.data for c in cleaned]
    for cl in cleaned:
        warnings += cl.warnings
    floors = noise_floors(logs)
    segs = [segment(d, floors) for d in logs]
    # Too few true rests (hand-held campaigns): fall back to quasi-static rests for the fits that need
    # attitudes and rest-to-rest motions; the gyro bias keeps the strict rests.
    a_means, _ = static_means(segs)
    if a_means.shape[0] == 0 or distinct_directions(a_means) < 9:
        with_rest = [s for s in segs if s.statics]
        bias = np.median(np.concatenate([s.data.gyro[i.i0:i.i1] for s in with_rest for i in s.statics]),
                         axis=0) if with_rest else None
        relaxed = [segment(d, floors, relaxed=True, bias=bias) for d in logs]
        ra, _ = static_means(relaxed)
        if ra.shape[0] and distinct_directions(ra) > (distinct_directions(a_means) if a_means.size else 0):
            warnings.append(
                f"only {distinct_directions(a_means) if a_means.size else 0} distinct attitudes at rest: "
                f"accelerometer and gyro-scale steps use quasi-static rests ({distinct_directions(ra)} "
                "attitudes; accel std < 0.25 m/s², rate < 0.1 rad/s)")
            for s_strict, s_rel in zip(segs, relaxed, strict=True):
                s_rel.bias_rests = s_strict.statics
            segs = relaxed
    for s, cl in zip(segs, cleaned, strict=True):
        s.bursts = cl.bursts
        warnings += s.warnings
    warnings = list(dict.fromkeys(warnings))
    steps: dict[str, StepReport] = {}
    mag: SensorCalibration | None = None
    acc: SensorCalibration | None = None
    gyro: SensorCalibration | None = None
    mag_segs = [Segmentation(d, [], [], [], float("nan"), float("nan"), np.zeros(3), float("nan"))
                for d in mag_only]
    if any(s.data.has_mag for s in segs):
        try:
            mag, steps["mag"] = fit_magnetometer(segs + mag_segs, rng)
        except FitError as e:
            warnings.append(f"mag step skipped: {e}")
    try:
        acc, steps["accel"] = fit_accelerometer(segs, g, rng)
    except FitError as e:
        warnings.append(f"accel step skipped: {e}")
    if acc is not None and mag is not None:
        n_dip, where = dip_outliers(segs, acc, mag)
        if n_dip:
            warnings.append(f"mag: {n_dip} samples at {len(where)} rest(s) whose field direction disagrees with "
                            "the others (a disturbance) excluded and the magnetometer refitted: "
                            + "; ".join(where[:5]))
            first = steps["mag"]
            try:
                mag, steps["mag"] = fit_magnetometer(segs + mag_segs, rng)
                steps["mag"].warnings[:0] = first.warnings
                steps["mag"].figures["outliers"] += first.figures["outliers"] + n_dip
            except FitError as e:
                mag = None
                warnings.append(f"mag step skipped: {e}")
    mag_ref = mag if mag is not None and not (steps["mag"].figures.get("degenerate")
                                              or steps["mag"].figures.get("partial_coverage")) else None
    if acc is not None and mag_ref is not None and len(steps["mag"].figures.get("aligned_axes", "")) < 2:
        # The phases could not put the magnetometer on the accelerometer's axes (eqs. 25–27): the
        # constant angle between gravity and the field at quasi-static attitudes can, at any angle.
        try:
            P, figs = mag_to_accel_rotation(segs, acc, mag_ref, g)
            mag = mag_ref = SensorCalibration(mag_ref.bias, P @ mag_ref.matrix,
                                              _rotated_sigma(mag_ref.sigma, figs["sigma_deg"]))
            steps["mag"].figures["to_accel_rotation"] = figs
            # its alignment is now that of the accelerometer (whose own alpha may stay undetermined)
            steps["mag"].figures["undetermined"] = [u for u in steps["mag"].figures.get("undetermined", [])
                                                    if u != "alpha"]
            warnings.append(f"mag: rotation phases could not align the magnetometer to the other sensors; its frame "
                            f"is turned by {figs['angle_deg']:.1f}° (σ {figs['sigma_deg']:.2f}°) onto the "
                            f"accelerometer's, from the gravity-field angle at {figs['attitude_cells']} quasi-static "
                            "attitudes")
        except FitError as e:
            warnings.append(f"mag: not aligned to the accelerometer ({e}); the two frames may differ")
    try:
        gyro, steps["gyro"] = fit_gyroscope(segs, acc, mag_ref, rng, g, latitude_deg)
    except FitError as e:
        warnings.append(f"gyro step skipped: {e}")
    for st in steps.values():
        warnings += st.warnings
    undetermined = [f"{k}.{p}" for k, st in steps.items() for p in st.figures.get("undetermined", [])]
    # A term that the data could not determine carries no σ (contract: σ where known) — never a guess
    # presented as a result; meta.batch.undetermined lists it.
    gyro, acc, mag = (None if c is None else _drop_sigma(c, steps.get(n)) for c, n in
                      ((gyro, "gyro"), (acc, "accel"), (mag, "mag")))
    if gyro is None and acc is None and mag is None:
        raise FitError("; ".join(warnings) or "no sensor could be calibrated")
    res = BatchResult(Calibration(gyro=gyro, accel=acc, mag=mag, source="batch"), segs, steps, warnings)
    summary = res.summary()
    summary["undetermined"] = undetermined  # terms whose value is NOT a calibration (σ absent)
    if reduced:
        summary["reduced"] = [r.to_dict() for r in reduced]
    # B (model.Gauge) is the gyro's rotation-phase frame where the phase method gave the gyro matrix
    phases = gyro is not None and str(steps["gyro"].figures.get("method", "")).startswith("phases")
    cal = res.calibration.replace(meta={"batch": summary}, gauge="gyro_phases" if phases else None)
    res.calibration = cal
    return res
