"""A long log diagnosed on a bounded sample of itself (issue 16.5: memory constant in the log's length).

Every stage of the diagnosis holds arrays in proportion to the samples it is given: the sessions' calibrated
and noise-free signals (~25 arrays of (N, 3) and the attitude (N, 3, 3)), the re-simulated session, and the
residual rows' design matrix Z (rows ∝ duration × a few hundred columns), each twice (measured and null).
Measured on a simulated 200 Hz multirotor flight (docs/robustness.md, "diagnose memory"): 10 minutes peak at
about 1 GB RSS, an hour at several times that. Above :data:`BUDGET` IMU samples (over all logs of the unit)
the diagnosis therefore runs on a sample of each log: :data:`WINDOW_S`-long windows, evenly spaced over the
log, the first at its start and the last at its end (a flight's ground rests before take-off and after
landing are the only rests it has; the gyro bias and the ``g_rest`` rows come from them), as many as the
log's share of the budget holds. Each window is a contiguous stretch of the log, analysed as a separate log
of the same unit (as the pieces between holes are, :mod:`.gaps`), so no integral or smoothing window
bridges a dropped stretch; the slow effects are seen through the windows' spread over the whole log
(temperature), and the windows of one log share one drift walk over its span (``core._share_walks``: the
knots between windows have no rows, the walk's prior ties them).

What is lost, stated with the result: motion that only happens between the windows, and the statistical
power of the dropped samples. The sample is said in ``baseline.bounded_sample`` and in every finding's
evidence.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..io.base import ImuData

BUDGET = 125_000  # IMU samples over all logs: 10.4 minutes at 200 Hz (a 10-minute log, 120,001, is read whole)
WINDOW_S = 120.0  # s: a window holds twelve of the 10-s fold blocks and many 10-s smoothing widths
MIN_WINDOWS = 2


def _window(d: ImuData, i0: int, i1: int) -> ImuData:
    """IMU rows [i0, i1) of d with the mag samples and series of the same time span (the series keep one
    sample either side of it, so interpolation onto the window's clock has both neighbours)."""
    t = d.t_imu
    lo, hi = float(t[i0]), float(t[i1 - 1])
    m = (d.t_mag >= lo) & (d.t_mag <= hi)
    series = {}
    for k, (ts, xs) in d.series.items():
        ts, xs = np.asarray(ts), np.asarray(xs)
        j0 = max(0, int(np.searchsorted(ts, lo, side="left")) - 1)
        j1 = min(ts.size, int(np.searchsorted(ts, hi, side="right")) + 1)
        series[k] = (ts[j0:j1].copy(), xs[j0:j1].copy())
    # copies: a view would keep the whole log's arrays alive for as long as the window lives
    return ImuData(t[i0:i1].copy(), d.gyro[i0:i1].copy(), d.acc[i0:i1].copy(), d.temp[i0:i1].copy(),
                   d.t_mag[m].copy(), d.mag[m].copy(), d.source, list(d.warnings),
                   [b for b in d.boundaries if lo <= b["t"] <= hi], dict(d.params), series)


def windows(n: int, keep: int, width: int) -> list[tuple[int, int]]:
    """Row ranges [i0, i1) of the windows that keep ``keep`` of ``n`` rows: W = max(MIN_WINDOWS, ⌈keep/width⌉)
    windows of ⌊keep/W⌋ rows, evenly spaced, the first at row 0 and the last ending at row n."""
    if keep >= n:
        return [(0, n)]
    w = max(MIN_WINDOWS, -(-keep // max(width, 1)))
    size = max(keep // w, 1)  # a log with a tiny share: windows too short to diagnose are left out there
    starts = np.round(np.linspace(0, n - size, w)).astype(int)
    return [(int(s), int(s) + size) for s in starts]


def bounded_sample(logs: list[ImuData], budget: int = BUDGET,
                   window_s: float = WINDOW_S) -> tuple[list[ImuData], dict[str, Any] | None]:
    """The logs as they are when they hold at most ``budget`` IMU samples together; else each log's windows
    (module doc), the budget shared in proportion to the logs' lengths. Returns (logs, what was kept: None
    when nothing was dropped)."""
    n_all = sum(d.n_imu for d in logs)
    if n_all <= budget:
        return logs, None
    out: list[ImuData] = []
    per_log: list[dict[str, Any]] = []
    for d in logs:
        keep = int(budget * d.n_imu / n_all)
        rate = d.imu_rate if np.isfinite(d.imu_rate) else 100.0
        spans = windows(d.n_imu, keep, int(round(window_s * rate)))
        out += [_window(d, i0, i1) for i0, i1 in spans]
        per_log.append({"source": d.source, "n_imu": d.n_imu, "n_kept": sum(i1 - i0 for i0, i1 in spans),
                        "duration_s": float(d.t_imu[-1] - d.t_imu[0]) if d.n_imu > 1 else 0.0,
                        "windows_s": [[float(d.t_imu[i0]), float(d.t_imu[i1 - 1])] for i0, i1 in spans]})
    info = {"budget": budget, "window_s": window_s, "n_imu": n_all,
            "n_kept": sum(p["n_kept"] for p in per_log), "logs": per_log}
    return out, info


def note(info: dict[str, Any]) -> str:
    """One sentence: the sample the diagnosis ran on."""
    w = sum(len(p["windows_s"]) for p in info["logs"])
    dur = sum(p["duration_s"] for p in info["logs"])
    kept_s = sum(t1 - t0 for p in info["logs"] for t0, t1 in p["windows_s"])
    return (f"diagnosed on a bounded sample: {info['n_kept']} of {info['n_imu']} IMU samples (budget "
            f"{info['budget']}), {w} windows of ~{kept_s / max(w, 1):.0f} s evenly spaced over {dur:.0f} s of log "
            "(memory constant in the log's length; effects seen only between the windows are not tested)")
