"""Stage 2b of diagnose: the same session re-simulated through the fitted baseline model.

Motion as estimated (attitude integrated from the calibrated, smoothed gyro; rests held still), the same
clocks and temperature column, gravity and field fixed in the world frame at their session means, the
fitted model inverted (raw = M⁻¹·c + o, eq. 1) and white noise of each raw axis's measured σ (second
differences, :func:`.motion.noise_sigma`). No effect is put in: the re-simulation is what "the paper's
model is right" looks like for this motion, and serves as the parametric-bootstrap null of every
detector statistic and as the "simulated" side of the measured-against-simulated comparison.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..io.base import ImuData
from ..model import Calibration
from .motion import Session, noise_sigma

Array = NDArray[np.float64]


def resimulate(s: Session, clean: dict[str, Array], cal: Calibration, data: ImuData,
               rng: np.random.Generator, extra: dict[str, Array] | None = None) -> ImuData:
    """Raw ImuData of the re-simulated session (IMU on the session's clock, mag on the log's mag clock).

    ``clean``: the design's noise-free signals (``w`` rad/s, ``R`` attitude, ``a``/``m`` for the world
    vectors); ``extra``: optional raw-unit additions per sensor ("gyro"/"accel", (N, 3)) — an extension's
    effect, to check that the extended simulator reproduces what the baseline got wrong.
    """
    R = clean["R"]
    w = clean["w"]
    aw = np.einsum("nij,nj->ni", R, clean["a"])
    aw = aw[np.isfinite(aw).all(axis=1)]
    g_W = aw.mean(axis=0) if aw.size else np.array([0.0, 0.0, 9.80665])
    a = np.einsum("nji,j->ni", R, g_W)
    raw_g = cal.gyro.inv().apply(w) if cal.gyro is not None else w.copy()
    raw_a = cal.accel.inv().apply(a) if cal.accel is not None else a.copy()
    if extra:
        raw_g = raw_g + extra.get("gyro", 0.0)
        raw_a = raw_a + extra.get("accel", 0.0)
    sg, sa = noise_sigma(s.raw_g), noise_sigma(s.raw_a)
    raw_g = raw_g + rng.standard_normal(raw_g.shape) * sg
    raw_a = raw_a + rng.standard_normal(raw_a.shape) * sa
    t_mag = np.zeros(0)
    mag = np.zeros((0, 3))
    if s.has_mag and "m" in clean and data.n_mag > 10:
        mw = np.einsum("nij,nj->ni", R, clean["m"])
        mw = mw[np.isfinite(mw).all(axis=1)]
        h_W = mw.mean(axis=0) if mw.size else np.array([0.0, 0.44, -0.9])
        m = np.einsum("nji,j->ni", R, h_W)
        t_mag = np.asarray(data.t_mag, float)
        tm = np.interp(t_mag, data.t_imu, s.t) if s.restamped else t_mag
        mi = np.column_stack([np.interp(tm, s.t, m[:, k]) for k in range(3)])
        raw_m = cal.mag.inv().apply(mi) if cal.mag is not None else mi
        sm = noise_sigma(np.asarray(data.mag, float))
        mag = raw_m + rng.standard_normal(raw_m.shape) * sm
        t_mag = tm
    return ImuData(s.t.copy(), raw_g, raw_a, s.temp.copy(), t_mag, mag, f"resim:{s.source}",
                   series=dict(data.series))  # the same current/throttle: the null of the mag_current candidate
