"""The paper's offline pipeline over one or more logs of one sensor unit: segment → mag → accel → gyro.

Data flow: each log is segmented on its own (rests, motions, rotation phases); the fits then pool
every log — a campaign is often several files (statics, turns, a sphere).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..io.base import ImuData
from ..model import Calibration, SensorCalibration
from ..sim.motion import G0
from .ellipsoid import FitError
from .gyro import fit_gyroscope
from .segment import Segmentation, noise_floors, segment
from .sensors import StepReport, distinct_directions, fit_accelerometer, fit_magnetometer, static_means


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


def run_batch(logs: list[ImuData], g: float = G0, seed: int = 0) -> BatchResult:
    """Calibrate gyro, accel and mag from raw logs of one unit (paper Sec. III).

    A sensor whose step cannot run (no mag in the logs, too few attitudes, no rest) is left out with
    a warning naming the step; a result without any sensor raises FitError.
    """
    rng = np.random.default_rng(seed)
    logs = [d for d in logs if d.n_imu > 0]
    if not logs:
        raise FitError("no IMU samples in the logs")
    # Reader warnings carry no file name; with several logs of one unit the user must know which one.
    warnings: list[str] = [w if d.source in w else f"{d.source}: {w}" for d in logs for w in d.warnings]
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
    for s in segs:
        warnings += s.warnings
    warnings = list(dict.fromkeys(warnings))
    steps: dict[str, StepReport] = {}
    mag: SensorCalibration | None = None
    acc: SensorCalibration | None = None
    gyro: SensorCalibration | None = None
    if any(s.data.has_mag for s in segs):
        try:
            mag, steps["mag"] = fit_magnetometer(segs, rng)
        except FitError as e:
            warnings.append(f"mag step skipped: {e}")
    try:
        acc, steps["accel"] = fit_accelerometer(segs, g, rng)
    except FitError as e:
        warnings.append(f"accel step skipped: {e}")
    try:
        gyro, steps["gyro"] = fit_gyroscope(segs, acc, mag, rng)
    except FitError as e:
        warnings.append(f"gyro step skipped: {e}")
    for st in steps.values():
        warnings += st.warnings
    if gyro is None and acc is None and mag is None:
        raise FitError("; ".join(warnings) or "no sensor could be calibrated")
    res = BatchResult(Calibration(gyro=gyro, accel=acc, mag=mag, source="batch"), segs, steps, warnings)
    cal = res.calibration.replace(meta={"batch": res.summary()}, gauge="gyro_phases" if gyro is not None and str(steps["gyro"].figures.get("method", "")).startswith("phases") else None)  # noqa: E501 (B: model.Gauge)
    res.calibration = cal
    return res
