"""The same model through filterpy's stock ``UnscentedKalmanFilter`` loop: one predict per IMU sample.

Reference for the speed comparison only (``benchmarks/bench_ukf.py``): filterpy calls ``fx``/``hx`` once
per sigma point in a Python loop, and the loop runs once per IMU sample, which is what the block-vectorised
:class:`onlinecal.ukf.OnlineCalibrator` avoids. Same state (:mod:`onlinecal.ukf.layout`), same sensor model,
same body-frame attitude error folded into a nominal after every update; accel update every sample, no mag,
no gating — the bare cost of the per-sample loop.
"""

from __future__ import annotations

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

from ..io.base import ImuData
from ..specs import ACCEL_SPEC, G0, GYRO_SPEC
from .layout import ATT, N_STATE, SENSOR_SLICE, correction, rodrigues, rot_log, sensor_model


class StockUKF:
    """Per-sample UKF on the 40-state model; ``run(data, n)`` processes the first n IMU samples."""

    def __init__(self, x0: np.ndarray, P0: np.ndarray, rate: float, alpha: float = 0.3) -> None:
        pts = MerweScaledSigmaPoints(N_STATE, alpha, 2.0, 0.0)
        self.ukf = UnscentedKalmanFilter(N_STATE, 3, 1.0 / rate, self._hx, self._fx, pts)
        self.ukf.x = x0.copy()
        self.ukf.P = P0.copy()
        sg = GYRO_SPEC.sigma(rate) / rate
        q = np.zeros(N_STATE)
        q[ATT] = sg**2
        q[3:] = 1e-16
        self.ukf.Q = np.diag(q)
        self.ukf.R = np.eye(3) * ACCEL_SPEC.sigma(rate) ** 2
        self.R_nom = np.eye(3)
        self._R_next = np.eye(3)
        self._w = np.zeros(3)

    def _fx(self, x: np.ndarray, dt: float) -> np.ndarray:
        o, M = correction(x[None, SENSOR_SLICE["gyro"]])
        R = self.R_nom @ rodrigues(x[None, ATT])[0] @ rodrigues((M[0] @ (self._w - o[0]))[None] * dt)[0]
        y = x.copy()
        y[ATT] = rot_log(self._R_next.T @ R)
        return y

    def _hx(self, x: np.ndarray) -> np.ndarray:
        R = self._R_next @ rodrigues(x[None, ATT])[0]
        o, Minv = sensor_model(x[None, SENSOR_SLICE["accel"]])
        return Minv[0] @ (G0 * R[2, :]) + o[0]

    def run(self, data: ImuData, n: int) -> None:
        t, w, a = data.t_imu, data.gyro, data.acc
        for k in range(1, min(n, data.n_imu)):
            dt = float(t[k] - t[k - 1])
            self._w = 0.5 * (w[k] + w[k - 1])
            o, M = correction(self.ukf.x[None, SENSOR_SLICE["gyro"]])
            self._R_next = self.R_nom @ rodrigues((M[0] @ (self._w - o[0]))[None] * dt)[0]
            self.ukf.predict(dt=dt)
            self.ukf.update(a[k])
            self.R_nom = self._R_next @ rodrigues(self.ukf.x[None, ATT])[0]
            self.ukf.x[ATT] = 0.0
