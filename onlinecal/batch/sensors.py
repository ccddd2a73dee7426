"""Magnetometer (eqs. 17–27) and accelerometer (eq. 32 + eqs. 25–27) calibration from segmented logs."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..model import SensorCalibration, decompose
from .align import phase_plane_normal, rotation_to_axes
from .ellipsoid import FitError, NormFit, fit_ellipsoid_svd, fit_norm_lm, sqrtm_spd, sym_from_vec
from .segment import Phase, Segmentation, moving_std

Array = NDArray[np.float64]


@dataclass
class StepReport:
    """What one step did, for the batch report: figures and warnings."""

    name: str
    figures: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"figures": self.figures, "warnings": list(self.warnings)}


def sqrt_psd(cov: Array) -> Array:
    """L with L Lᵀ = cov for a symmetric positive semi-definite cov (reduced fits are singular)."""
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    return V * np.sqrt(np.clip(w, 0.0, None))


def propagate_sigma(
    o: Array, M: Array, cov9: Array, Q: Array, sig_align: float, rng: np.random.Generator, n: int = 64
) -> dict[str, list[float]]:
    """1σ of bias, scale, alpha, xi for ``Q · M`` by Monte Carlo over the fit covariance (o, upper
    triangle of symmetric M) and an isotropic alignment error of ``sig_align`` rad."""
    if not np.all(np.isfinite(cov9)):
        return {"bias": np.sqrt(np.abs(np.diag(cov9))[:3]).tolist()}
    L = sqrt_psd(cov9)
    p0 = np.concatenate([o, M[np.triu_indices(3)]])
    draws = []
    for _ in range(n):
        p = p0 + L @ rng.standard_normal(9)
        a = rng.normal(0, sig_align, 3)
        Ra = np.eye(3) + np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        try:
            s, al, xi = decompose(Ra @ Q @ sym_from_vec(p[3:]))
        except ValueError:
            continue
        draws.append(np.concatenate([p[:3], s, al, xi]))
    d = np.array(draws)
    sd = d.std(axis=0)
    return {"bias": sd[:3].tolist(), "scale": sd[3:6].tolist(), "alpha": sd[6:9].tolist(),
            "xi": sd[9:12].tolist()}


def _align(
    segs: list[Segmentation],
    samples: Callable[[Segmentation, Phase], Array],
    M0: Array,
    o: Array,
    min_radius: float,
    report: StepReport,
) -> tuple[Array, float]:
    """T_R from phases (eqs. 25–27): pooled plane normals per axis, then Procrustes. Returns (Q, σ)."""
    acc: dict[int, list[tuple[Array, float]]] = {}
    sig = []
    for seg in segs:
        for ph in seg.phases:
            v = (samples(seg, ph) - o) @ M0.T
            if v.shape[0] < 10:
                continue
            n, radius, share = phase_plane_normal(v, ph.axis)
            if radius < min_radius or share < 0.5:
                continue
            resid = (v - v.mean(0)) @ n
            sig.append(float(np.std(resid) / (radius * np.sqrt(v.shape[0]))))
            acc.setdefault(ph.axis, []).append((n, radius**2 * v.shape[0]))
    normals = {}
    for k, lst in acc.items():
        n = sum(w * n for n, w in lst)
        normals[k] = (n / np.linalg.norm(n), float(sum(w for _, w in lst)))
    report.figures["aligned_axes"] = "".join("xyz"[k] for k in sorted(normals))
    if len(normals) < 2:
        report.warnings.append(
            f"{report.name}: rotation phases usable for alignment about {len(normals)} "
            f"{'axis' if len(normals) == 1 else 'axes'} (need 2): T_R is "
            + ("partly determined" if normals else "taken as identity")
        )
    Q = rotation_to_axes(normals)
    return Q, float(np.sqrt(np.mean(np.square(sig)))) if sig else 0.0


def _mag_samples(seg: Segmentation, ph: Phase) -> Array:
    d = seg.data
    m = (d.t_mag >= ph.t0) & (d.t_mag <= ph.t1)
    return d.mag[m]


def _lpf(x: Array, w: int) -> Array:
    return moving_std(x, w)[0] if x.shape[0] >= w else x


def _acc_samples(seg: Segmentation, ph: Phase) -> Array:
    # Low-pass filtered (paper Sec. III-B): centripetal and hand jitter average out.
    w = max(3, int(round(0.1 * seg.data.imu_rate)))
    return _lpf(seg.data.acc[ph.i0 : ph.i1], w)


def fit_magnetometer(
    segs: list[Segmentation], rng: np.random.Generator
) -> tuple[SensorCalibration, StepReport]:
    """Magnetometer: SVD ellipsoid fit (eqs. 19–24) → LM on eq. 17 → T_R,mag from phases (eqs. 25–27).

    Every mag sample of every log counts for the ellipsoid; the field norm is 1 by definition.
    """
    rep = StepReport("mag")
    x = np.concatenate([s.data.mag for s in segs if s.data.has_mag])
    if x.shape[0] < 50:
        raise FitError(f"magnetometer: only {x.shape[0]} samples")
    # An ellipsoid needs the field seen from directions spanning 3-D: a rest (a point) or a turn
    # about one axis (a circle) leaves it undetermined, and LM would return a degenerate answer.
    ev = np.linalg.eigvalsh(np.cov(x.T))
    spread = float(np.sqrt(max(ev[0], 0.0)) / np.median(np.linalg.norm(x, axis=1)))
    if spread < 0.05:
        raise FitError(f"magnetometer: the field was seen from too few directions (least spread "
                       f"{100 * spread:.1f} % of the reading, need 5 %); turn the unit through all orientations")
    o0, M0 = fit_ellipsoid_svd(x)
    fit = fit_norm_lm(x, 1.0, o0, M0)
    Q, sig_a = _align(segs, _mag_samples, fit.M, fit.o, 0.2, rep)
    M = Q @ fit.M
    norms = np.linalg.norm((x[fit.inliers] - fit.o) @ M.T, axis=1)
    rep.figures.update({
        "samples": int(x.shape[0]),
        "outliers": int((~fit.inliers).sum()),
        "norm_std_percent": float(100 * norms.std()),
        "raw_norm_std_percent": float(100 * np.linalg.norm(x - x.mean(0), axis=1).std()
                                      / np.linalg.norm(x - x.mean(0), axis=1).mean()),
        "svd_vs_lm_bias": float(np.linalg.norm(o0 - fit.o)),
    })
    sig = propagate_sigma(fit.o, fit.M, fit.cov, Q, sig_a, rng)
    return SensorCalibration(fit.o, M, sig), rep


def static_means(segs: list[Segmentation]) -> tuple[Array, Array]:
    """Mean raw accel and gyro of every static interval of every log: (K, 3) each."""
    a, g = [], []
    for s in segs:
        for iv in s.statics:
            a.append(s.data.acc[iv.i0 : iv.i1].mean(axis=0))
            g.append(s.data.gyro[iv.i0 : iv.i1].mean(axis=0))
    return np.array(a).reshape(-1, 3), np.array(g).reshape(-1, 3)


def distinct_directions(v: Array, min_angle_deg: float = 10.0) -> int:
    """How many of the directions of v (K, 3) differ by more than min_angle from all before them."""
    u = v / np.linalg.norm(v, axis=1, keepdims=True)
    kept: list[Array] = []
    for x in u:
        if all(np.degrees(np.arccos(np.clip(x @ k, -1, 1))) > min_angle_deg for k in kept):
            kept.append(x)
    return len(kept)


def fit_accelerometer(
    segs: list[Segmentation], g: float, rng: np.random.Generator
) -> tuple[SensorCalibration, StepReport]:
    """Accelerometer: static-position fit ‖S'(a − o)‖ = g (eq. 32) → T_R,acc from the low-pass-filtered
    accelerometer in the rotation phases (eqs. 25–27), which carries it onto the same axes the
    magnetometer was aligned to.

    The full 9-parameter fit needs static positions in enough distinct attitudes (the paper uses 12);
    with fewer, the fit falls back to bias + per-axis scale (≥ 6 attitudes) or bias + common scale,
    and says so.
    """
    rep = StepReport("accel")
    a, _ = static_means(segs)
    ndir = distinct_directions(a) if a.shape[0] else 0
    rep.figures["static_positions"] = int(a.shape[0])
    rep.figures["distinct_attitudes"] = ndir
    if ndir < 3:
        raise FitError(f"accelerometer: {ndir} distinct static attitude(s), need ≥ 3")
    model = "full" if ndir >= 9 else "diag" if ndir >= 6 else "bias" if ndir >= 4 else "offset"
    if model != "full":
        what = {"diag": "bias + per-axis scale", "bias": "bias + common scale",
                "offset": "bias only (common scale from the mean norm, no misalignment fitted)"}[model]
        rep.warnings.append(f"accel: only {ndir} distinct static attitudes; fitted {what}")
    try:
        o0, M0 = fit_ellipsoid_svd(a) if a.shape[0] >= 10 else (np.zeros(3), np.eye(3))
        M0 = M0 * g
    except FitError:
        o0, M0 = np.zeros(3), np.eye(3) * g / np.linalg.norm(a, axis=1).mean()
    if model != "full" or not np.all(np.isfinite(M0)):
        o0, M0 = np.zeros(3), np.eye(3) * g / np.linalg.norm(a, axis=1).mean()
    fit: NormFit = fit_norm_lm(a, g, o0, M0, model=model)
    Q, sig_a = _align(segs, _acc_samples, fit.M, fit.o, 0.3 * g, rep)
    M = Q @ fit.M
    norms = np.linalg.norm((a - fit.o) @ M.T, axis=1)
    rep.figures.update({
        "model": model,
        "static_norm_rms_error": float(np.sqrt(np.mean((norms - g) ** 2))),
        "raw_static_norm_rms_error": float(np.sqrt(np.mean((np.linalg.norm(a, axis=1) - g) ** 2))),
    })
    sig = propagate_sigma(fit.o, fit.M, fit.cov, Q, sig_a, rng)
    return SensorCalibration(fit.o, M, sig), rep


__all__ = ["fit_magnetometer", "fit_accelerometer", "static_means", "StepReport", "sqrtm_spd", "sqrt_psd"]
