"""Residual statistics set side by side for measured and re-simulated data: RMS per channel, whiteness,
spectra and the Allan deviation of the gyro at rest.

* whiteness: lag-1 autocorrelation and the Ljung–Box statistic Q = n(n+2) Σ_{k≤h} ρ_k²/(n−k) (Ljung & Box
  1978) of each channel's whitened residual in time order (white: Q ~ χ²_h, E = h);
* spectrum: Welch PSD of the calibrated gyro over the rests (unit²/Hz), summarised by its level in three
  bands;
* Allan deviation (IEEE Std 952, overlapping estimator) of the calibrated gyro over the longest rest, per
  axis, at octave-spaced τ.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .regressors import SUBCHANNELS, Design

Array = NDArray[np.float64]


def ljung_box(r: Array, h: int = 10) -> tuple[float, float]:
    """(lag-1 autocorrelation, Ljung–Box Q over h lags) of a series."""
    r = r - r.mean()
    n = r.size
    if n <= h + 2:
        return float("nan"), float("nan")
    d = float(r @ r)
    if d == 0:
        return 0.0, 0.0
    rho = np.array([float(r[k:] @ r[:-k]) / d for k in range(1, h + 1)])
    q = n * (n + 2) * float(np.sum(rho**2 / (n - np.arange(1, h + 1))))
    return float(rho[0]), q


def channel_stats(resid: Array, ch: Array, t: Array) -> dict[str, dict[str, float]]:
    """Per sub-channel: rows, RMS of the whitened residual, lag-1 autocorrelation, Ljung–Box Q (10 lags)."""
    out = {}
    for k, name in enumerate(SUBCHANNELS):
        m = ch == k
        if m.sum() < 12:
            continue
        r = resid[m][np.argsort(t[m], kind="stable")]
        rho1, q = ljung_box(r)
        out[name] = {"n": int(m.sum()), "rms": float(np.sqrt(np.mean(r**2))), "rho1": rho1, "ljung_box_q10": q}
    return out


def allan(x: Array, rate: float, n_tau: int = 8) -> tuple[Array, Array]:
    """Overlapping Allan deviation of x (N, k) sampled at ``rate``; τ = 2^i / rate up to N/4 samples."""
    n = x.shape[0]
    ms = [2**i for i in range(n_tau + 4) if 2**i <= n // 4][:n_tau]
    c = np.concatenate([np.zeros((1, x.shape[1])), np.cumsum(x, axis=0)])
    taus, devs = [], []
    for m in ms:
        avg = (c[m:] - c[:-m]) / m
        d = avg[m:] - avg[:-m]
        taus.append(m / rate)
        devs.append(np.sqrt(0.5 * np.mean(d**2, axis=0)))
    return np.array(taus), np.array(devs)


def rest_stats(d: Design) -> dict[str, Any]:
    """Allan deviation and PSD band levels of the calibrated gyro over the longest rest (≥ 5 s)."""
    s = d.s
    if not s.rests:
        return {}
    iv = max(s.rests, key=lambda v: v.n)
    if iv.n < 5 * s.rate:
        return {}
    x = s.w[iv.i0 : iv.i1]
    taus, devs = allan(x - x.mean(axis=0), s.rate)
    from scipy.signal import welch  # here: scipy.signal takes ~1 s to import

    f, P = welch(x - x.mean(axis=0), fs=s.rate, nperseg=min(256, x.shape[0]), axis=0)
    bands = {}
    for lo, hi in ((0.0, 1.0), (1.0, 10.0), (10.0, s.rate / 2)):
        m = (f > lo) & (f <= hi)
        if m.any():
            bands[f"{lo:g}-{hi:g} Hz"] = np.sqrt(P[m].mean(axis=0)).tolist()
    return {"rest_s": float(iv.n / s.rate), "allan_tau_s": taus.tolist(), "allan_dev": devs.tolist(),
            "psd_sqrt_band": bands, "datasheet": allan_datasheet(taus, devs)}


def allan_datasheet(taus: Array, devs: Array) -> dict[str, Any]:
    """Allan deviation read in a datasheet's units (IEEE Std 952 Annex C), per axis:

    * angle random walk N (°/√h): σ(τ) on the −½ slope read at τ = 1 s, N = σ(1 s)·√(1 s) (interpolated in
      log–log, or extrapolated from the shortest τ along the −½ slope), × 180/π × 60;
    * bias instability B (°/h): the minimum of σ(τ) over the τ measured divided by 0.664 (the flicker floor's
      factor), × 180/π × 3600 — a lower bound on it when the curve is still falling at the longest τ
      (``bias_instability_is_bound``).
    """
    if taus.size < 2:
        return {}
    lt, ld = np.log(taus), np.log(np.maximum(devs, 1e-300))
    at1 = np.array([np.interp(0.0, lt, ld[:, k]) if lt[0] <= 0.0 <= lt[-1] else ld[0, k] + 0.5 * lt[0]
                    for k in range(devs.shape[1])])
    arw = np.exp(at1) * np.degrees(1.0) * 60.0
    i_min = np.argmin(devs, axis=0)
    bi = devs.min(axis=0) / 0.664 * np.degrees(1.0) * 3600.0
    return {"angle_random_walk_deg_sqrt_h": arw.tolist(), "bias_instability_deg_h": bi.tolist(),
            "bias_instability_tau_s": taus[i_min].tolist(),
            "bias_instability_is_bound": (i_min == taus.size - 1).tolist()}
