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
