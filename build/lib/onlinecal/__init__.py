"""onlinecal: IMU calibration after Zhang, Höflinger & Reindl (IEEE Sensors J. 2014), offline and online.

Stages, one module each, data flowing one way: ``io`` (read) → ``batch.segment`` (segment) →
``batch`` (fit, the paper's eqs. 17–36) → ``ukf`` (filter) → ``report``. ``model`` owns the sensor
error model (eqs. 1–10); ``sim`` makes sessions with known truth.
"""

from .model import Calibration, SensorCalibration

__version__ = "0.1.0"
__all__ = ["Calibration", "SensorCalibration", "__version__"]
