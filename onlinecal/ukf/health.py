"""The filter's health: the innovation (NIS) statistics per sensor against their chi-square band, the
divergence they signal, and the event log.

A window of ``nis_window`` updates has a mean NIS whose band, for a consistent filter, is
χ²(W·3)/W at the two-sided probability ``nis_band_p``; ``divergence_windows`` windows in a row above
``divergence_factor`` × its upper end are a divergence (:meth:`NisMonitor.record` says so; the filter
re-initialises).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.stats import chi2


def new_nis_stats() -> dict[str, Any]:
    """Empty NIS bookkeeping of one sensor (JSON-able: it goes into the checkpoint as it is)."""
    return {"sum": 0.0, "n": 0, "windows": [], "bad_run": 0, "rejected": 0, "updates": 0}


@dataclass
class NisMonitor:
    """Windowed mean NIS per sensor (``accel``, ``mag``) against its chi-square band: ``window`` updates
    per window, band of probability 1 − ``band_p``; a divergence after ``windows`` windows in a row above
    ``factor`` × the band's top. ``stats``: per sensor the running bookkeeping (:func:`new_nis_stats`)."""

    window: int
    band_p: float
    factor: float
    windows: int
    stats: dict[str, dict[str, Any]] = field(default_factory=lambda: {s: new_nis_stats() for s in ("accel", "mag")})

    def band(self, dof: int = 3) -> tuple[float, float]:
        """Band (lo, hi) of a window's mean NIS (``dof`` per update)."""
        W = self.window
        p = self.band_p / 2
        return (float(chi2.ppf(p, W * dof) / W), float(chi2.ppf(1 - p, W * dof) / W))

    def reject(self, sensor: str) -> None:
        """Count an update of ``sensor`` gated out (dropped or R inflated)."""
        self.stats[sensor]["rejected"] += 1

    def record(self, sensor: str, nis: float, t: float) -> str | None:
        """Add one NIS of ``sensor`` at log time t s; returns why it diverged, or None."""
        st = self.stats[sensor]
        st["sum"] += min(nis, 1e6)
        st["n"] += 1
        st["updates"] += 1
        st["last"] = nis
        if st["n"] < self.window:
            return None
        mean = st["sum"] / st["n"]
        st["sum"], st["n"] = 0.0, 0
        lo, hi = self.band()
        st["windows"].append([t, mean])
        if len(st["windows"]) > 1000:
            st["windows"] = st["windows"][-1000:]
        if mean > self.factor * hi:
            st["bad_run"] += 1
        else:
            st["bad_run"] = 0
        if st["bad_run"] >= self.windows:
            return (f"{sensor} NIS window mean {mean:.3g} far above its band [{lo:.3g}, {hi:.3g}] "
                    f"for {st['bad_run']} windows")
        return None

    def restart(self, sensor: str) -> None:
        """The running window of ``sensor`` restarts (its model was re-initialised)."""
        self.stats[sensor].update({"sum": 0.0, "n": 0, "bad_run": 0})

    def last(self, sensor: str) -> float:
        return float(self.stats[sensor].get("last", float("nan")))

    def summary(self, events_total: int) -> dict[str, Any]:
        """Per sensor: updates, rejected by the gate, windows, share of window means inside the band."""
        lo, hi = self.band()
        out: dict[str, Any] = {"band": [lo, hi]}
        for s, st in self.stats.items():
            ws = np.array([w[1] for w in st["windows"]]) if st["windows"] else np.zeros(0)
            out[s] = {
                "updates": st["updates"], "rejected": st["rejected"], "windows": int(ws.size),
                "mean": float(ws.mean()) if ws.size else float("nan"),
                "in_band": float(np.mean((ws >= lo) & (ws <= hi))) if ws.size else float("nan"),
            }
        out["events_total"] = events_total
        return out


@dataclass
class EventLog:
    """Events (gaps, saturation, noise, divergence, the mag cold start): the last ``max_events`` kept,
    the count of all in ``total``."""

    max_events: int
    events: list[dict[str, Any]] = field(default_factory=list)
    total: int = 0

    def add(self, kind: str, detail: str, t: float) -> None:
        self.total += 1
        self.events.append({"t": float(t), "kind": kind, "detail": detail})
        if len(self.events) > self.max_events:
            del self.events[: len(self.events) - self.max_events]


def finite_or_none(v: float) -> float | None:
    """JSON has no infinity: None for a non-finite value (:func:`none_to_inf` reverses it)."""
    return None if not math.isfinite(v) else float(v)


def none_to_inf(v: float | None) -> float:
    return -math.inf if v is None else float(v)
