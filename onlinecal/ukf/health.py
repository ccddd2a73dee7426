"""The filter's health: the innovation (NIS) statistics per sensor against their chi-square band, the
divergence they signal, and the event log.

A window of ``nis_window`` updates has a mean NIS whose band, for a consistent filter, is
χ²(W·3)/W at the two-sided probability ``nis_band_p``; ``divergence_windows`` windows in a row above
``divergence_factor`` × its upper end are a divergence (:meth:`NisMonitor.record` says so; the filter
re-initialises).

**Vehicle-disturbed updates apart.** On a vehicle the filter adds the unknown vehicle acceleration to the
accelerometer's R outside a rest (:func:`.vehicle.vehicle_accel_var`: σ_v²·k, k = max(1, τ_v/Δt): one
σ_v-measurement per correlation time, spread over the k blocks it covers). Such an update's NIS is ≈ d/k
times (actual acceleration / σ_v)²: about 0.003 on a clean multirotor flight (k = 300), and mixed with the
rest updates it dragged a clean flight's accel mean NIS to 0.7–0.9, below the band — the design, not an
overstated sensor noise, and it hid the sensor's own consistency. So an accel update whose R carries the
disturbance (``inflated`` = k, passed with that update) goes to the sensor's ``vehicle``
sub-stream as NIS·k, which judges the innovation against σ_v² itself: ≤ d while the vehicle stays within
the modelled bound, whatever the block length. That stream is judged one-sided over the whole run
(:func:`onlinecal.health.nis_checks`: only *above* 2d is a fault, the bound did not cover the flight) and
takes no part in the divergence test (the disturbance is correlated over τ_v, a 10-s window is one draw of
it). The sensor's main stream keeps the updates whose R is the sensor's noise (rests, the ground, a
platform), judged two-sided and for divergence as before.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.special import gammaincinv


def chi2_ppf(p: float, dof: float) -> float:
    """The p quantile of χ²(dof): 2·P⁻¹(dof/2, p), P the regularised lower incomplete gamma function —
    scipy.stats.chi2.ppf's own formula, the same bits, without importing scipy.stats (~0.5 s of every
    start-up; ``tests/test_ukf_parts.py`` compares the two)."""
    return float(2.0 * gammaincinv(dof / 2.0, p))


def new_nis_stats() -> dict[str, Any]:
    """Empty NIS bookkeeping of one sensor (JSON-able: it goes into the checkpoint as it is)."""
    return {"sum": 0.0, "n": 0, "windows": [], "bad_run": 0, "rejected": 0, "updates": 0}


def _add(st: dict[str, Any], nis: float, t: float, window: int) -> float | None:
    """Add one NIS at log time t s to the stream ``st``; the window's mean when ``window`` updates
    completed it (the last 1000 window means are kept), else None."""
    st["sum"] += min(nis, 1e6)
    st["n"] += 1
    st["updates"] += 1
    if st["n"] < window:
        return None
    mean = float(st["sum"] / st["n"])
    st["sum"], st["n"] = 0.0, 0
    st["windows"].append([t, mean])
    if len(st["windows"]) > 1000:
        st["windows"] = st["windows"][-1000:]
    return mean


def _window_summary(st: dict[str, Any], lo: float, hi: float) -> dict[str, Any]:
    """Updates, rejected, windows, mean of the window means and the share inside [lo, hi] of one stream, and
    the shares above and below it (an innovation larger than R says — model error — against a smaller one)."""
    ws = np.array([w[1] for w in st["windows"]]) if st["windows"] else np.zeros(0)
    return {"updates": st["updates"], "rejected": st["rejected"], "held": int(st.get("held", 0)),
            "windows": int(ws.size),
            "mean": float(ws.mean()) if ws.size else float("nan"),
            "in_band": float(np.mean((ws >= lo) & (ws <= hi))) if ws.size else float("nan"),
            "above_band": float(np.mean(ws > hi)) if ws.size else float("nan"),
            "below_band": float(np.mean(ws < lo)) if ws.size else float("nan")}


@functools.lru_cache(maxsize=64)
def _window_band(W: int, band_p: float, dof: int) -> tuple[float, float]:
    """The two-sided ``band_p`` band of the mean of W χ²(dof) NIS: chi2.ppf(·, W·dof)/W. Cached: the
    filter asks for it every block (the disturbance gate), and scipy's ppf costs ~150 µs a call."""
    p = band_p / 2
    return (float(chi2_ppf(p, W * dof) / W), float(chi2_ppf(1 - p, W * dof) / W))


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

    def _stream(self, sensor: str, inflated: float) -> dict[str, Any]:
        """The bookkeeping an update of ``sensor`` goes to: the ``vehicle`` sub-stream for an accel update
        whose R carries the vehicle disturbance (``inflated`` = k > 0, see the module doc)."""
        st = self.stats[sensor]
        if inflated > 0 and sensor == "accel":
            return st.setdefault("vehicle", new_nis_stats())  # a checkpoint from before has none
        return st

    def band(self, dof: int = 3) -> tuple[float, float]:
        """Band (lo, hi) of a window's mean NIS (``dof`` per update)."""
        return _window_band(self.window, self.band_p, dof)

    def reject(self, sensor: str, inflated: float = 0.0) -> None:
        """Count an update of ``sensor`` gated out (dropped or R inflated); ``inflated`` as in :meth:`record`."""
        self._stream(sensor, inflated)["rejected"] += 1

    def record(self, sensor: str, nis: float, t: float, inflated: float = 0.0, held: bool = False) -> str | None:
        """Add one NIS of ``sensor`` at log time t s; returns why it diverged, or None. ``inflated`` = k > 0:
        the update's accel R carried the vehicle disturbance σ_v²·k (its NIS goes to the vehicle stream).
        ``held``: the update held the sensor's soft iron at its σ (:attr:`.state.StateLayout.mag_flight_terms`),
        counted as ``held`` beside ``updates`` (:func:`onlinecal.health.nis_checks` reads the share)."""
        self.stats[sensor]["last"] = nis  # the trace's nis.<sensor>: whichever stream
        st = self._stream(sensor, inflated)
        if held:
            st["held"] = st.get("held", 0) + 1  # (a key of its own only where it happens: older checkpoints lack it)
        if st is not self.stats[sensor]:
            # vehicle-disturbed: R carries σ_v²·k (k = max(1, τ_v/Δt), one σ_v-measurement per correlation
            # time spread over k blocks); ν's disturbance part has the vehicle's own per-block variance, so
            # NIS·k judges it against σ_v² itself (≤ d while the vehicle stays within the bound). Kept out
            # of the divergence test: a correlated disturbance makes 10-s windows one draw each, and the
            # health verdict judges this stream over the whole run (onlinecal.health)
            _add(st, nis * inflated, t, self.window)
            return None
        mean = _add(st, nis, t, self.window)
        if mean is None:
            return None
        lo, hi = self.band()
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
        if "vehicle" in self.stats[sensor]:
            self.stats[sensor]["vehicle"].update({"sum": 0.0, "n": 0, "bad_run": 0})

    def last(self, sensor: str) -> float:
        return float(self.stats[sensor].get("last", float("nan")))

    def summary(self, events_total: int) -> dict[str, Any]:
        """Per sensor: updates, rejected by the gate, windows, share of window means inside the band — of
        the updates whose R is the sensor's noise; the vehicle-disturbed accel updates, where there were
        any, under the sensor's ``"vehicle"`` key with the same figures."""
        lo, hi = self.band()
        out: dict[str, Any] = {"band": [lo, hi]}
        for s, st in self.stats.items():
            out[s] = _window_summary(st, lo, hi)
            if st.get("vehicle", {}).get("updates"):
                out[s]["vehicle"] = _window_summary(st["vehicle"], lo, hi)
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
