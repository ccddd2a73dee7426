"""Stretches without usable samples, cut out before the diagnosis.

The readers drop samples that carry NaN/inf (a burst of them leaves a stretch with no IMU sample) and keep
a logging gap as a gap. The diagnosis integrates the gyro between samples and smooths its channels over
neighbours, and its drift basis puts a knot every 10 s of the time line: across a 30 s hole none of that
means anything (a knot without a sample in its support has no column at all). So each log is cut at every
hole longer than :data:`GAP_MIN_S` (or :data:`GAP_PERIODS` sample periods, whichever is longer) into pieces
that are analysed as separate logs of the same unit, and each hole is named in the result.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..io.base import ImuData

GAP_MIN_S = 1.0
GAP_PERIODS = 20.0
MIN_PIECE = 50  # IMU samples: a shorter piece is left out (and named), as a shorter log is


def gap_threshold(t: np.ndarray) -> float:
    """Seconds between consecutive IMU samples beyond which the time line has a hole: the larger of
    GAP_MIN_S and GAP_PERIODS median sample periods (a 1 Hz telemetry log is not cut every sample)."""
    dt = np.diff(t)
    dt = dt[dt > 0]
    return max(GAP_MIN_S, GAP_PERIODS * float(np.median(dt))) if dt.size else GAP_MIN_S


def _why(d: ImuData) -> str:
    dropped = [w for w in d.warnings if "NaN" in w or "dropped" in w]
    return ("samples the reader dropped (" + "; ".join(dropped) + ")") if dropped else "no samples logged"


def split_at_gaps(logs: list[ImuData]) -> tuple[list[ImuData], list[dict[str, Any]]]:
    """Cut every log at its holes. Returns (pieces in order, excluded) with ``excluded`` one dict per hole
    or dropped short piece: ``source``, ``t0``/``t1`` (s, the log's time line), ``duration_s``, ``reason``.

    A piece holds the IMU samples between two holes and the mag samples of the same span (those inside a
    hole are left out with it). Logs without a hole are returned as they are (the same objects)."""
    pieces: list[ImuData] = []
    excluded: list[dict[str, Any]] = []
    for d in logs:
        t = d.t_imu
        if t.size < 2:
            pieces.append(d)
            continue
        thr = gap_threshold(t)
        cut = np.flatnonzero(np.diff(t) > thr) + 1
        if not cut.size:
            pieces.append(d)
            continue
        why = _why(d)
        for i in cut:
            excluded.append({"source": d.source, "t0": float(t[i - 1]), "t1": float(t[i]),
                             "duration_s": float(t[i] - t[i - 1]),
                             "reason": f"{t[i] - t[i - 1]:.1f} s without IMU samples (more than {thr:.3g} s): "
                                       f"{why}; the log is analysed as separate pieces either side"})
        edges = np.concatenate([[0], cut, [t.size]])
        for i0, i1 in zip(edges[:-1], edges[1:], strict=True):
            lo, hi = t[i0], t[i1 - 1]
            m = (d.t_mag >= lo) & (d.t_mag <= hi)
            if i1 - i0 < MIN_PIECE:
                excluded.append({"source": d.source, "t0": float(lo), "t1": float(hi),
                                 "duration_s": float(hi - lo),
                                 "reason": f"a piece of {i1 - i0} IMU samples between holes (fewer than "
                                           f"{MIN_PIECE}): too short to diagnose"})
                continue
            pieces.append(ImuData(t[i0:i1], d.gyro[i0:i1], d.acc[i0:i1], d.temp[i0:i1], d.t_mag[m], d.mag[m],
                                  d.source, list(d.warnings), params=d.params,
                                  series={k: (ts, v) for k, (ts, v) in d.series.items()}))
    return pieces, excluded


def excluded_text(e: dict[str, Any]) -> str:
    """One line for the terminal: where and why."""
    return f"{e['source']}: t = {e['t0']:.2f}–{e['t1']:.2f} s excluded: {e['reason']}"
