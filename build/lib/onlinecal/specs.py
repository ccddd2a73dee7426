"""Sensor specifications and physical constants: production data, shared by the filter, the batch
pipeline, the diagnosis and the simulator (which synthesises readings from them).

The specs are those of a typical MEMS part (ICM-20602-class IMU, IST8310-class magnetometer); the
filter gets them through :class:`onlinecal.ukf.config.UKFConfig` (``gyro_spec``, ``accel_spec``,
``mag_spec``), so another part is a config change, not a code change.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

G0 = 9.80665  # m/s², standard gravity (the conventional value, CGPM 1901)
FIELD_GAUSS = 0.48  # gauss, local geomagnetic field strength (central Europe)
FIELD_DIP_DEG = 64.0  # deg, its inclination there
OMEGA_EARTH = 7.292115e-5  # rad/s, the Earth's rotation (WGS-84): what a gyro at rest on the ground senses


@dataclass(frozen=True)
class SensorSpec:
    """Noise and ADC of one sensor. ``density`` white-noise density (unit/√Hz); ``lsb`` quantum;
    ``full_scale`` clipping limit (unit); ``floor`` per-sample noise independent of rate."""

    density: float
    lsb: float
    full_scale: float
    floor: float = 0.0

    def sigma(self, rate: float) -> float:
        """Per-sample white-noise σ at ``rate`` Hz (Nyquist bandwidth rate/2)."""
        return float(np.hypot(self.density * np.sqrt(rate / 2.0), self.floor))


# ICM-20602-class: gyro 4 mdps/√Hz at ±1000 dps (16 bit), accel 100 µg/√Hz at ±8 g; mag IST8310-class.
GYRO_SPEC = SensorSpec(density=float(np.radians(0.004)), lsb=float(np.radians(2000 / 65536)),
                       full_scale=float(np.radians(1000)))
ACCEL_SPEC = SensorSpec(density=100e-6 * G0, lsb=16 * G0 / 65536, full_scale=8 * G0)
MAG_SPEC = SensorSpec(density=0.0, lsb=0.0003, full_scale=4.0, floor=0.0006)
SPECS = {"gyro": GYRO_SPEC, "accel": ACCEL_SPEC, "mag": MAG_SPEC}

__all__ = ["ACCEL_SPEC", "FIELD_DIP_DEG", "FIELD_GAUSS", "G0", "GYRO_SPEC", "MAG_SPEC", "SPECS", "SensorSpec"]


RAIL_SAMPLES = 10  # samples at an axis' largest magnitude that make it a rail, not a peak (reached once)
RAIL_TOL = 1e-4  # relative: the two rails of a 16-bit ADC differ by one count (3e-5: −32768 vs 32767); a
# wider tolerance takes a constant-rate turn on a quantised log (1 mrad/s steps in a .tlog) for a rail


def rail_samples(x_abs: np.ndarray, rail_min: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clipped readings of one sensor from its magnitudes ``x_abs`` (N, 3) (|raw|, finite): an axis whose
    largest magnitude exceeds ``rail_min`` (no rail lies below it) and recurs, within :data:`RAIL_TOL`,
    in at least :data:`RAIL_SAMPLES` samples is at its rail — both signs, since |−32768| and |32767|
    counts agree to 3e-5. Returns (top (3,), at (N, 3) samples at the top, rail (3,) axes with a rail)."""
    top = x_abs.max(axis=0) if x_abs.shape[0] else np.zeros(3)
    at = (x_abs >= top * (1 - RAIL_TOL)) & (top > rail_min)
    return top, at, at.sum(axis=0) >= RAIL_SAMPLES
