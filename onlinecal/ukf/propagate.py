"""Propagation of all sigma points through a block of IMU samples at once, and the measurement models.

Every sigma point carries its own gyroscope calibration, so it integrates its own attitude:

    Δθ_k = M_gyr (½(ω_raw,k−1 + ω_raw,k) − o_gyr) · Δt_k          (eq. 1 applied to the gyro, trapezoid)
    R(t_k) = R_nom exp([δθ]_x) · exp([Δθ_1]_x) ⋯ exp([Δθ_k]_x)

All increments of all sigma points go through one vectorised Rodrigues formula and the running products
through a log₂-depth scan (:func:`onlinecal.ukf.layout.prefix_products_cm`), in component-major arrays
(3, 3, S, L); no Python loop over sigma points or samples. The measurement models are the paper's sensor
model inverted (raw = M⁻¹ c + o, eq. 1) applied to gravity and the field in the body frame:

    acc_raw = M_acc⁻¹ · Rᵀ (0, 0, g) + o_acc        (specific force of a body at rest, ENU z up)
    mag_raw = M_mag⁻¹ · Rᵀ h_world(δ) + o_mag

averaged over the samples of the block (the block mean is what the filter compares with the data). The
mean is linear in R, so the mean attitude over the samples is formed first and used once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .layout import (
    ATT,
    DIP,
    SENSOR_SLICE,
    correction,
    field_world,
    prefix_products_cm,
    rodrigues,
    rodrigues_cm,
    sensor_model,
)

Array = NDArray[np.float64]


@dataclass
class BlockPrediction:
    """Result of :func:`propagate_block` for S sigma points.

    R_end (S, 3, 3) attitude (world ← body) at the block's last IMU sample; f_body (S, 3) mean over the
    block's IMU samples of Rᵀ e_z (unit, body frame); h_body (S, 3) mean over its mag samples of
    Rᵀ h_world (unit field, body frame) or None when the block has no mag sample.
    """

    R_end: Array
    f_body: Array
    h_body: Array | None


def mag_weights(t_prev: float, t: Array, t_mag: Array) -> Array:
    """Weights c (L + 1,) with mean_m R(t_m) ≈ Σ_k c_k R(t_k) (t_0 = t_prev), by linear interpolation.

    Exact when the mag is sampled on IMU ticks; otherwise second order in the rotation per IMU sample
    (the same order as the trapezoid integration).
    """
    t_all = np.concatenate([[t_prev], t])
    L = t.shape[0]
    j = np.clip(np.searchsorted(t_all, t_mag, side="left"), 1, L)  # t_all[j−1] < tm ≤ t_all[j]
    frac = np.clip((t_mag - t_all[j - 1]) / (t_all[j] - t_all[j - 1]), 0.0, 1.0)
    c = np.zeros(L + 1)
    np.add.at(c, j, frac)
    np.add.at(c, j - 1, 1.0 - frac)
    return c / t_mag.shape[0]


def propagate_block(
    X: Array,
    R_nom: Array,
    t_prev: float,
    w_prev: Array,
    t: Array,
    w: Array,
    t_mag: Array,
    dyn: Array | None = None,
    b_extra: Array | None = None,
) -> BlockPrediction:
    """Integrate the attitude of every sigma point over one block of IMU samples.

    X (S, n) sigma points (δθ in X[:, 0:3], the gyro terms in X[:, 3:15], the dip in X[:, 39]);
    R_nom (3, 3) nominal attitude; t_prev (s), w_prev (3,) rad/s the last sample before the block;
    t (L,) s, w (L, 3) raw gyro in rad/s; t_mag (M,) s mag sample times in (t_prev, t[-1]].

    ``dyn`` (S_d,) indices of the sigma points that differ from the mean (index 0, listed first) in a
    state the attitude depends on (attitude error, gyro terms, gyro extensions); every other sigma point
    shares the mean's attitude history, which is computed once. ``b_extra`` (S_d, L, 3) rad/s an extra
    raw gyro bias per dynamic sigma point and sample (model extensions), or None.
    """
    Xd = X if dyn is None else X[dyn]
    o_g, M_g = correction(Xd[:, SENSOR_SLICE["gyro"]])
    w_all = np.vstack([w_prev[None], w])
    dt = np.diff(np.concatenate([[t_prev], t]))
    w_mid = 0.5 * (w_all[1:] + w_all[:-1])  # (L, 3) trapezoid: second order in Δt
    u = w_mid[None] - o_g[:, None]
    if b_extra is not None:
        u = u - b_extra
    # θ[:, s, k] = M_s (w_mid_k − o_s) Δt_k, component-major (3, S, L)
    theta = np.einsum("sij,slj->isl", M_g, u) * dt
    P = prefix_products_cm(rodrigues_cm(theta))  # (3, 3, S_d, L)
    R0 = R_nom @ rodrigues(Xd[:, ATT])  # (S_d, 3, 3) right (body-frame) error around the nominal
    R_end = R0 @ P[..., -1].transpose(2, 0, 1)
    # mean over the block of R_kᵀ e_z = (row z of R0 · mean_k P_k)ᵀ
    f_body = np.einsum("sk,kjs->sj", R0[:, 2, :], P.mean(axis=-1))
    Q = None
    if t_mag.size:
        c = mag_weights(t_prev, t, t_mag)
        Pm = np.einsum("ijsl,l->sij", P, c[1:])
        Pm[:, 0, 0] += c[0]
        Pm[:, 1, 1] += c[0]
        Pm[:, 2, 2] += c[0]
        Q = R0 @ Pm  # mean over the mag samples of R(t_m), (S_d, 3, 3)
    if dyn is not None:
        full = np.zeros(X.shape[0], dtype=np.intp)  # sigma points outside dyn share the mean's (row 0)
        full[dyn] = np.arange(dyn.shape[0])
        R_end, f_body = R_end[full], f_body[full]
        Q = None if Q is None else Q[full]
    h_body = None if Q is None else np.einsum("sj,sjk->sk", field_world(X[:, DIP]), Q)
    return BlockPrediction(R_end, f_body, h_body)


def predict_raw(X: Array, sensor: str, v_body: Array) -> Array:
    """Raw reading predicted by the sensor model (eq. 1 inverted): ``M⁻¹ v + o`` per sigma point.

    X (S, 40); v_body (S, 3) the calibrated quantity in the body frame (m/s² for accel, unit field for
    mag). Returns (S, 3) in the sensor's raw unit.
    """
    o, Minv = sensor_model(X[:, SENSOR_SLICE[sensor]])
    return np.einsum("sij,sj->si", Minv, v_body) + o
