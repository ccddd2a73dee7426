"""The prediction of a motion block, as pure functions: every sigma point through the block's IMU samples
(:func:`propagate_sigma_points`, around :func:`.propagate.propagate_block`) and the block's process noise
(:func:`block_process_noise`)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .blocks import Blocks
from .layout import ATT, SENSOR_SLICE
from .noise import bilinear_var
from .propagate import BlockPrediction, attitude_errors, interp_weights, propagate_block, sensor_models

Array = NDArray[np.float64]


def propagate_sigma_points(X: Array, R_nom: Array, B: Blocks, b: int, dyn: NDArray[np.intp], use_mag: bool,
                           gyro_extra: Array | None) -> tuple[BlockPrediction, tuple[Array, Array, Array]]:
    """Every sigma point of X (S, n) through block ``b`` of ``B`` from the nominal attitude R_nom (3, 3); X's
    attitude errors (in place) become those at the block's end, relative to the mean's (the points outside
    ``dyn`` share the mean's attitude history: their error stays 0). ``gyro_extra`` (S_d, L + 1, 3) the
    extra raw gyro bias of the dynamic points (:func:`.measurements.gyro_offsets`) or None. Returns the
    prediction and (o, M, M⁻¹) of accel then mag for every point ((2S, 3), (2S, 3, 3) ×2): one evaluation
    of eqs. 1–6 together with the gyro's for the dynamic points."""
    i, j = int(B.lo[b]), int(B.hi[b])
    c_mag = None
    if use_mag:
        k0, n_m = int(B.mlo[b]) - int(B.mlo[0]), int(B.mhi[b] - B.mlo[b])
        c_mag = interp_weights(B.m_j[k0 : k0 + n_m], B.m_frac[k0 : k0 + n_m], j - i)
    Sd = dyn.shape[0]
    o_all, M_all, Minv_all = sensor_models(np.concatenate(
        [X[dyn, SENSOR_SLICE["gyro"]], X[:, SENSOR_SLICE["accel"]], X[:, SENSOR_SLICE["mag"]]]))
    pred = propagate_block(X, R_nom, B.w_ext[i : j + 1], B.dt[i:j], c_mag,
                           dyn,
                           (o_all[:Sd], M_all[:Sd]), gyro_extra)
    X[dyn, ATT] = attitude_errors(pred.R_end)  # sigma point 0 is the mean
    return pred, (o_all[Sd:], M_all[Sd:], Minv_all[Sd:])


def block_process_noise(q: Array, B: Blocks, b: int, dt_blk: float, sigma_gyr: float, P: Array) -> Array:
    """Q (n,) of block ``b`` lasting dt_blk s: the base ``q`` (:meth:`.noise.NoiseModel.process_noise`, changed
    in place), plus on the attitude the trapezoid's error where the rate is not smooth (Δt·|Δ²ω|/4 per
    sample, less the white noise's own E[Δ²n]² = 6σ² for the gyro's per-sample σ ``sigma_gyr``, so that rest
    and smooth motion add ~0), plus the bilinear allowance of the covariance P (:func:`.noise.bilinear_var`)."""
    L = int(B.hi[b] - B.lo[b])
    if L >= 2:
        noise = float(B.jerk_n[b]) * 6.0 * (sigma_gyr * dt_blk / L / 4) ** 2
        q[ATT] += max(0.0, float(B.jerk[b]) - noise) / 3.0
    q[ATT] += bilinear_var(P) * dt_blk**2
    return q
