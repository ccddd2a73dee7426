"""Figures a person wants to look at, headless (matplotlib Agg). Every function writes one PNG and returns
its path; none keeps a figure open. Used by ``batch/replay --report``, the demo, and open to ``diagnose``.

Conventions: calibrated = matrix @ (raw − bias) (paper eq. 1); magnetometer calibrated to unit field norm,
accelerometer in m/s²; parameters in the calibration JSON's units (bias in the sensor unit, scale, alpha
and xi in rad). Point clouds are thinned to at most ``max_points`` by an even stride (no randomness, so a
report is reproducible).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .model import PARAMS, SENSORS, SensorCalibration

Array = NDArray[np.float64]
DPI = 90
AXES = "xyz"
_COLORS = {"raw": "0.55", "batch": "tab:blue", "online": "tab:orange", "init": "tab:green", "truth": "k"}


def pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend (no display needed). Raises ImportError without matplotlib."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _color(label: str, i: int) -> str:
    return _COLORS.get(label.split()[0], f"C{(i + 2) % 10}")


def _save(fig: Any, path: str | Path) -> Path:
    import io
    import warnings

    from .files import atomic_write

    p = Path(path)
    with warnings.catch_warnings():
        # tight_layout's "not compatible" notice says nothing about the data; the figure is still right
        warnings.simplefilter("ignore", UserWarning)
        fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, dpi=DPI, format=p.suffix.lstrip(".") or "png")
    pyplot().close(fig)
    atomic_write(p, buf.getvalue())  # one writer for every output: never half a PNG
    return p


def _thin(n: int, max_points: int) -> slice:
    return slice(None, None, max(1, int(np.ceil(n / max_points))))


def joined_time(ts: Sequence[Array]) -> tuple[Array, list[float]]:
    """Concatenate per-log time axes (s) into one increasing axis: each log starts 1 s after the end of the
    one before. Returns the axis and the times where a new log starts (for boundary lines)."""
    out, starts, off = [], [], 0.0
    for t in ts:
        t = np.asarray(t, float)
        if t.size == 0:
            continue
        shifted = t - t[0] + off
        starts.append(off)
        out.append(shifted)
        off = float(shifted[-1]) + 1.0
    return (np.concatenate(out) if out else np.zeros(0)), starts


def monotone_time(t: Array) -> Array:
    """A trace's time column (each log restarts its clock) made increasing: a step back starts a new log,
    placed 1 s after the previous row."""
    t = np.asarray(t, float)
    if t.size < 2:
        return t.copy()
    d = np.diff(t)
    d = np.where(d > 0, d, 1.0)
    return np.concatenate([[0.0], np.cumsum(d)]) + t[0]


def mag_sphere(path: str | Path, mag_raw: Array, cals: Mapping[str, SensorCalibration],
               max_points: int = 4000) -> Path:
    """Magnetometer points before and after calibration, in three projections (xy, yz, zx).

    mag_raw (M, 3) in the sensor unit. Row "raw": raw / median ‖raw‖ (the hard-iron offset shows as a
    shifted, the soft iron as a squashed circle); one row per calibration: matrix @ (raw − bias), which should
    lie on the unit sphere (eq. 17), drawn against the unit circle.
    """
    plt = pyplot()
    m = np.asarray(mag_raw, float)[_thin(len(mag_raw), max_points)]
    rows = [("raw", m / np.median(np.linalg.norm(m, axis=1)))]
    rows += [(k, c.apply(m)) for k, c in cals.items()]
    fig, axs = plt.subplots(len(rows), 3, figsize=(10, 3.3 * len(rows)), squeeze=False)
    ang = np.linspace(0, 2 * np.pi, 200)
    for r, (label, p) in enumerate(rows):
        for c, (i, j) in enumerate(((0, 1), (1, 2), (2, 0))):
            ax = axs[r][c]
            ax.plot(np.cos(ang), np.sin(ang), "k-", lw=0.6)
            ax.scatter(p[:, i], p[:, j], s=1.5, alpha=0.5, color=_color(label, r), rasterized=True)
            ax.set_aspect("equal", adjustable="datalim")
            ax.set(xlabel=f"{AXES[i]}", ylabel=f"{AXES[j]}",
                   title=f"{label}: {AXES[i]}{AXES[j]} projection" + (" (÷ median norm)" if r == 0 else ""))
    return _save(fig, path)


def field_norm(path: str | Path, t: Array, mag_raw: Array, cals: Mapping[str, SensorCalibration],
               log_starts: Sequence[float] = ()) -> Path:
    """Field norm over time: ‖raw‖ / mean ‖raw‖ and ‖matrix @ (raw − bias)‖ per calibration (target 1) on top;
    below, zoomed, the calibrated norms' deviation from 1 in %."""
    plt = pyplot()
    m = np.asarray(mag_raw, float)
    fig, axs = plt.subplots(2, 1, figsize=(10, 5.6), sharex=True, height_ratios=(1, 1))
    raw = np.linalg.norm(m, axis=1)
    axs[0].plot(t, raw / raw.mean(), lw=0.5, color=_color("raw", 0), label="raw / mean")
    for i, (k, c) in enumerate(cals.items()):
        n = np.linalg.norm(c.apply(m), axis=1)
        axs[0].plot(t, n, lw=0.6, color=_color(k, i), label=k)
        axs[1].plot(t, 100 * (n - 1.0), lw=0.4, color=_color(k, i), label=k, alpha=0.8)
    axs[0].axhline(1.0, color="k", lw=0.5)
    axs[1].axhline(0.0, color="k", lw=0.5)
    for ax in axs:
        for s in log_starts[1:]:
            ax.axvline(s, color="0.3", lw=0.5, ls=":")
    axs[0].set(ylabel="field norm", title="magnetometer field norm")
    axs[1].set(xlabel="time [s] (logs joined)", ylabel="‖m_cal‖ − 1 [%]", title="calibrated, zoomed")
    axs[0].legend(loc="upper right", fontsize=8)
    if cals:
        axs[1].legend(loc="upper right", fontsize=8)
    return _save(fig, path)


def accel_statics(path: str | Path, acc_means: Array, cals: Mapping[str, SensorCalibration],
                  g: float) -> Path:
    """Accelerometer norm on the static intervals: ‖ā_k‖ before and ‖matrix @ (ā_k − bias)‖ after, per
    static k (ā_k (K, 3) the mean raw specific force of static k, m/s²), against g (eq. 32's target);
    right panel the residual ‖·‖ − g in mm/s²."""
    plt = pyplot()
    a = np.asarray(acc_means, float).reshape(-1, 3)
    k = np.arange(a.shape[0])
    fig, axs = plt.subplots(1, 2, figsize=(10, 3.6))
    axs[0].plot(k, np.linalg.norm(a, axis=1), "o", ms=4, color=_color("raw", 0), label="raw")
    for i, (lab, c) in enumerate(cals.items()):
        n = np.linalg.norm(c.apply(a), axis=1)
        axs[0].plot(k, n, "s", ms=3, color=_color(lab, i), label=lab)
        axs[1].plot(k, 1e3 * (n - g), "s-", ms=3, lw=0.6, color=_color(lab, i), label=lab)
    axs[0].axhline(g, color="k", lw=0.5)
    axs[1].axhline(0.0, color="k", lw=0.5)
    axs[0].set(xlabel="static interval", ylabel="|a| [m/s²]", title="accelerometer norm on the statics")
    axs[1].set(xlabel="static interval", ylabel="|a| − g [mm/s²]", title="after calibration")
    axs[0].legend(fontsize=8)
    axs[1].legend(fontsize=8)
    return _save(fig, path)


def ukf_params(path: str | Path, trace: Sequence[Mapping[str, float]], sensor: str,
               refs: Mapping[str, SensorCalibration | None] | None = None) -> Path:
    """One sensor's 12 UKF parameters over time (rows bias, scale, alpha, xi; columns x, y, z): the
    estimate, its ±3σ band (σ from the filter's covariance, trace columns ``name.sigma``) and each reference
    calibration's value (batch, init) as a horizontal line. The y range follows the band over the second half
    of the trace, so the wide prior at the start does not flatten the converged part."""
    plt = pyplot()
    t = monotone_time(np.array([r["t"] for r in trace], float))
    fig, axs = plt.subplots(len(PARAMS), 3, figsize=(11, 2.3 * len(PARAMS)), squeeze=False, sharex=True)
    half = t.size // 2
    for i, p in enumerate(PARAMS):
        for j, a in enumerate(AXES):
            ax = axs[i][j]
            name = f"{sensor}.{p}.{a}"
            x = np.array([r[name] for r in trace], float)
            s = np.array([r[name + ".sigma"] for r in trace], float)
            ax.fill_between(t, x - 3 * s, x + 3 * s, color=_color("online", 0), alpha=0.25, lw=0)
            ax.plot(t, x, color=_color("online", 0), lw=0.8, label="online ±3σ")
            lo, hi = np.nanmin((x - 3 * s)[half:]), np.nanmax((x + 3 * s)[half:])
            for k, (lab, c) in enumerate((refs or {}).items()):
                if c is None:
                    continue
                v = float(c.params()[p][j])
                ax.axhline(v, color=_color(lab, k), lw=0.9, ls="--", label=lab)
                lo, hi = min(lo, v), max(hi, v)
            if np.isfinite(lo) and np.isfinite(hi):
                pad = 0.15 * (hi - lo) if hi > lo else 1e-9 + 1e-3 * abs(hi)
                ax.set_ylim(lo - pad, hi + pad)
            ax.set_title(name, fontsize=9)
            ax.tick_params(labelsize=7)
            if i == len(PARAMS) - 1:
                ax.set_xlabel("time [s]", fontsize=8)
    axs[0][0].legend(fontsize=7, loc="best")
    fig.suptitle(f"{sensor}: online estimate ±3σ and reference values")
    return _save(fig, path)


def batch_vs_online(path: str | Path, batch: Any, online: Any) -> Path:
    """Online − batch for every parameter (3 sensors × bias, scale, alpha, xi × 3 axes), in units of the
    combined σ = hypot(σ_online, σ_batch) where known (bars), with the ±3 lines."""
    plt = pyplot()
    names, z = [], []
    for s in SENSORS:
        b, o = batch.sensor(s), online.sensor(s)
        if b is None or o is None:
            continue
        for p in PARAMS:
            sb = b.sigma.get(p)
            so = o.sigma.get(p)
            for j, a in enumerate(AXES):
                sig = np.hypot(0.0 if sb is None else float(np.asarray(sb)[j]),
                               0.0 if so is None else float(np.asarray(so)[j]))
                d = float(o.params()[p][j] - b.params()[p][j])
                names.append(f"{s}.{p}.{a}")
                z.append(d / sig if sig > 0 else np.nan)
    fig, ax = plt.subplots(1, 1, figsize=(12, 3.8))
    zz = np.asarray(z, float)
    col = ["tab:red" if abs(v) > 3 else "tab:blue" for v in np.nan_to_num(zz)]
    ax.bar(np.arange(zz.size), np.nan_to_num(zz), color=col)
    for v in (-3, 3):
        ax.axhline(v, color="k", lw=0.6, ls="--")
    ax.set_xticks(np.arange(zz.size), names, rotation=90, fontsize=6)
    ax.set(ylabel="(online − batch) / σ", title="batch vs online, per parameter (σ combined)")
    return _save(fig, path)


def norms_overview(path: str | Path, data: Any, cal: Any, g: float = 9.80665) -> Path:
    """The demo's two-panel figure: magnetometer norm (raw / mean, calibrated) and accelerometer norm (raw,
    calibrated) over the whole log."""
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    raw = np.linalg.norm(data.mag, axis=1)
    calm = np.linalg.norm(cal.mag.apply(data.mag), axis=1) if cal.mag is not None else None
    ax[0].plot(data.t_mag, raw / raw.mean(), lw=0.5, label="raw / mean")
    if calm is not None:
        ax[0].plot(data.t_mag, calm, lw=0.5, label="calibrated")
    ax[0].set(xlabel="time [s]", ylabel="field norm", title="magnetometer norm")
    ax[0].legend()
    ax[1].plot(data.t_imu, np.linalg.norm(data.acc, axis=1), lw=0.5, label="raw")
    if cal.accel is not None:
        ax[1].plot(data.t_imu, np.linalg.norm(cal.accel.apply(data.acc), axis=1), lw=0.5, label="calibrated")
    ax[1].axhline(g, color="k", lw=0.5)
    ax[1].set(xlabel="time [s]", ylabel="|a| [m/s²]", title="accelerometer norm", ylim=(8.5, 11))
    ax[1].legend()
    return _save(fig, path)
