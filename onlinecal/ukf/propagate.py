"""Propagation of all sigma points through a block of IMU samples at once, and the measurement models.

Every sigma point carries its own gyroscope calibration, so it integrates its own attitude:

    ω_k = M_gyr (ω_raw,k − o_gyr)                                    (eq. 1 applied to the gyro)
    Δθ_k = ½(ω_k−1 + ω_k) Δt_k + Δt_k²/12 · ω_k−1 × ω_k               (Magnus, rate linear in the interval)
    R(t_k) = R_nom exp([δθ]_x) · exp([Δθ_1]_x) ⋯ exp([Δθ_k]_x)

The second term of Δθ (the two-sample coning correction; Magnus 1954, e.g. Savage, "Strapdown inertial
navigation integration algorithm design", JGCD 21(1), 1998) is the commutation error of a turning rate
axis: without it, the 12 turns to static positions of a 100 Hz paper session leave an attitude error of
~1e-4 rad per turn, which a cold-started filter reads as gyro scale (4σ).

All increments of all sigma points go through one vectorised Rodrigues formula and the running products
through a log₂-depth scan (:func:`onlinecal.ukf.layout.prefix_products_cm`), in component-major arrays
(3, 3, S, L); no Python loop over sigma points or samples. The measurement models are the paper's sensor
model inverted (raw = M⁻¹ c + o, eq. 1) applied to gravity and the field in the body frame:

    acc_raw = M_acc⁻¹ · Rᵀ (0, 0, g) + o_acc        (specific force of a body at rest, ENU z up)
    mag_raw = M_mag⁻¹ · Rᵀ h_world(δ) + o_mag

averaged over the samples of the block (the block mean is what the filter compares with the data). The
mean is linear in R, so the mean attitude over the samples is formed first and used once.

:func:`propagate_block`, :func:`sensor_models` and :func:`attitude_errors` run on the backend of
:mod:`onlinecal.ukf.kernels` (``ONLINECAL_KERNELS``): the compiled loop kernels there by default, or the
numpy functions (:func:`propagate_block_numpy`, :func:`onlinecal.ukf.layout.model_pair`,
:func:`onlinecal.ukf.layout.rot_log`), which are the reference the kernels are tested against.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from . import kernels
from .kernels_propagate import model_pair_kernel, propagate_numba, rot_log_rel_kernel
from .layout import (
    ATT,
    DIP,
    SENSOR_SLICE,
    model_pair,
    prefix_products_cm,
    rodrigues_cm,
    rot_log,
    sensor_model,
)

Array = NDArray[np.float64]


@dataclass
class BlockPrediction:
    """Result of :func:`propagate_block` for S sigma points, S_d of them dynamic (``dyn``).

    R_end (S_d, 3, 3) attitude (world ← body) of the dynamic sigma points at the block's last IMU sample
    (row 0: the mean); f_body (S, 3) mean over the block's IMU samples of Rᵀ e_z (unit, body frame);
    h_body (S, 3) mean over its mag samples of Rᵀ h_world (unit field, body frame) or None when the
    block has no mag sample; o_gyr (3,) and M_gyr (3, 3) the mean's gyro correction (eq. 1).
    """

    R_end: Array
    f_body: Array
    h_body: Array | None
    o_gyr: Array
    M_gyr: Array


def mag_weights(t_prev: float, t: Array, t_mag: Array) -> Array:
    """Weights c (L + 1,) with mean_m R(t_m) ≈ Σ_k c_k R(t_k) (t_0 = t_prev), by linear interpolation.

    Exact when the mag is sampled on IMU ticks; otherwise second order in the rotation per IMU sample
    (the same order as the trapezoid integration).
    """
    t_all = np.concatenate([[t_prev], t])
    L = t.shape[0]
    j = np.clip(np.searchsorted(t_all, t_mag, side="left"), 1, L)  # t_all[j−1] < tm ≤ t_all[j]
    frac = np.clip((t_mag - t_all[j - 1]) / (t_all[j] - t_all[j - 1]), 0.0, 1.0)
    return interp_weights(j, frac, L)


def interp_weights(j: NDArray[Any], frac: Array, L: int) -> Array:
    """c (L + 1,) from the interpolation indices j (M,) in 1..L and fractions frac (M,) of M mag samples:
    sample m sits between IMU ticks j−1 and j (tick 0: the sample before the block) at ``frac``."""
    c = np.bincount(j, weights=frac, minlength=L + 1) + np.bincount(j - 1, weights=1.0 - frac, minlength=L + 1)
    return c / j.shape[0]


def propagate_block(
    X: Array,
    R_nom: Array,
    w: Array,
    dt: Array,
    c_mag: Array | None,
    dyn: NDArray[Any],
    gyro: tuple[Array, Array],
    b_extra: Array | None = None,
    backend: str | None = None,
) -> BlockPrediction:
    """Integrate the attitude of every sigma point over one block of L IMU samples, on ``backend`` (default:
    that of :mod:`onlinecal.ukf.kernels`, ``ONLINECAL_KERNELS``): the compiled kernel
    (:func:`onlinecal.ukf.kernels_propagate.propagate_kernel`) or the numpy reference (:func:`_propagate_numpy`).

    X (S, n) sigma points (δθ in X[:, 0:3], the gyro terms in X[:, 3:15], the dip in X[:, 39]);
    R_nom (3, 3) nominal attitude; w (L + 1, 3) rad/s the raw rates at the block's L samples and the one
    before, dt (L,) s the length of each sample interval; c_mag (L + 1,) the mag interpolation weights of
    :func:`mag_weights` (None: no mag sample in the block).

    ``dyn`` (S_d,) indices of the sigma points that differ from the mean (index 0, listed first) in a
    state the attitude depends on (attitude error, gyro terms, gyro extensions); every other sigma point
    shares the mean's attitude history, which is computed once. ``gyro`` = (o_gyr (S_d, 3), M_gyr (S_d, 3, 3))
    the gyro correction of the dynamic sigma points (:func:`onlinecal.ukf.layout.correction`).
    ``b_extra`` (S_d, L + 1, 3) rad/s an extra raw gyro bias per dynamic sigma point and sample (model
    extensions), or None.
    """
    o_g, M_g = gyro
    if (backend or kernels.backend()) == "numpy":
        R_end, f_body, h_body = _propagate_numpy(X, R_nom, w, dt, c_mag, dyn, o_g, M_g, b_extra)
    else:
        R_end, f_body, h_body = propagate_numba(X, R_nom, w, dt, c_mag, dyn, o_g, M_g, b_extra, DIP)
    return BlockPrediction(R_end, f_body, h_body, o_g[0], M_g[0])


def propagate_block_numpy(X: Array, R_nom: Array, w: Array, dt: Array, c_mag: Array | None, dyn: NDArray[Any],
                          gyro: tuple[Array, Array], b_extra: Array | None = None) -> BlockPrediction:
    """:func:`propagate_block` on the numpy reference, whatever the backend (what the kernels are tested
    against)."""
    return propagate_block(X, R_nom, w, dt, c_mag, dyn, gyro, b_extra, backend="numpy")


def _products(w: Array, dt: Array, o_g: Array, M_g: Array, b_extra: Array | None) -> Array:
    """Running products P_k = exp([Δθ_1]_x) ⋯ exp([Δθ_k]_x) (3, 3, S_d, L) of the dynamic sigma points'
    calibrated rates (eq. 1 on the gyro), Δθ the trapezoid plus the two-sample coning term."""
    u = w[None] - o_g[:, None]
    if b_extra is not None:
        u = u - b_extra
    om = np.einsum("sij,slj->isl", M_g, u)  # calibrated rate, component-major (3, S_d, L + 1)
    o0, o1 = om[..., :-1], om[..., 1:]
    theta = (0.5 * dt) * (o0 + o1)
    h = dt * dt / 12.0
    theta[0] += h * (o0[1] * o1[2] - o0[2] * o1[1])
    theta[1] += h * (o0[2] * o1[0] - o0[0] * o1[2])
    theta[2] += h * (o0[0] * o1[1] - o0[1] * o1[0])
    P: Array = prefix_products_cm(rodrigues_cm(theta))
    return P


def _mag_means(X: Array, dyn: NDArray[Any], R0: Array, P: Array, c_mag: Array) -> Array:
    """h_body (S, 3): mean over the block's mag samples of R(t_m)ᵀ h_world(dip) per sigma point, from the
    start attitudes R0 (3, 3, S_d), the running products P (3, 3, S_d, L) and the weights c_mag (L + 1,)."""
    # mean over the mag samples of R(t_m): c_0 R0 + Σ_k c_k R0 P_k  (S_d, 3, 3)
    Pm = np.einsum("ijsl,l->ijs", P, c_mag[1:])
    Pm[0, 0] += c_mag[0]
    Pm[1, 1] += c_mag[0]
    Pm[2, 2] += c_mag[0]
    Q = np.einsum("iks,kjs->sij", R0, Pm)
    dip = X[:, DIP]
    hw = np.zeros((X.shape[0], 3))  # unit field in the world frame, :func:`onlinecal.ukf.layout.field_world`
    hw[:, 1] = np.cos(dip)
    hw[:, 2] = -np.sin(dip)
    h_body: Array = hw @ Q[0]
    h_body[dyn] = np.einsum("sj,sjk->sk", hw[dyn], Q)
    return h_body


def _propagate_numpy(X: Array, R_nom: Array, w: Array, dt: Array, c_mag: Array | None, dyn: NDArray[Any],
                     o_g: Array, M_g: Array, b_extra: Array | None) -> tuple[Array, Array, Array | None]:
    """The numpy reference of :func:`propagate_block` (arguments there, gyro = (o_g, M_g)): (R_end, f_body,
    h_body or None)."""
    P = _products(w, dt, o_g, M_g, b_extra)  # (3, 3, S_d, L)
    # right (body-frame) error around the nominal, component-major (3, 3, S_d)
    R0 = np.einsum("ij,jks->iks", R_nom, rodrigues_cm(np.ascontiguousarray(X[dyn][:, ATT].T)))
    R_end = np.einsum("iks,kjs->sij", R0, P[..., -1])
    # mean over the block of R_kᵀ e_z = (row z of R0 · mean_k P_k)ᵀ
    f_d = np.einsum("ks,kjsl->sj", R0[2], P) * (1.0 / P.shape[-1])
    # sigma points outside dyn share the mean's attitude history (row 0)
    f_body = np.empty((X.shape[0], 3))
    f_body[:] = f_d[0]
    f_body[dyn] = f_d
    h_body = None if c_mag is None else _mag_means(X, dyn, R0, P, c_mag)
    return R_end, f_body, h_body


def predict_raw(X: Array, sensor: str, v_body: Array) -> Array:
    """Raw reading predicted by the sensor model (eq. 1 inverted): ``M⁻¹ v + o`` per sigma point.

    X (S, 40); v_body (S, 3) the calibrated quantity in the body frame (m/s² for accel, unit field for
    mag). Returns (S, 3) in the sensor's raw unit.
    """
    o, Minv = sensor_model(X[:, SENSOR_SLICE[sensor]])
    return np.einsum("sij,sj->si", Minv, v_body) + o


def sensor_models(p: Array) -> tuple[Array, Array, Array]:
    """(o (N, 3), M (N, 3, 3), M⁻¹ (N, 3, 3)) of eq. 1 with eqs. 2–6 for N parameter rows p (N, 12), on
    the kernel backend (:func:`onlinecal.ukf.kernels_propagate.model_pair_kernel`, or the numpy reference
    :func:`onlinecal.ukf.layout.model_pair`)."""
    if kernels.backend() == "numpy":
        return model_pair(p)
    out: tuple[Array, Array, Array] = model_pair_kernel(np.ascontiguousarray(p, dtype=np.float64))
    return out


def attitude_errors(R_end: Array) -> Array:
    """Rotation vectors (S_d, 3) of R_end[0]ᵀ R_end[s] for R_end (S_d, 3, 3): each propagated sigma
    point's attitude relative to the mean's (row 0), on the kernel backend (numpy reference:
    :func:`onlinecal.ukf.layout.rot_log`)."""
    if kernels.backend() == "numpy":
        out: Array = rot_log(R_end[0].T @ R_end)
        return out
    out = rot_log_rel_kernel(np.ascontiguousarray(R_end, dtype=np.float64))
    return out
