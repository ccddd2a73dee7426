"""Noise of the online filter: measurement σ from the sensor specs, the log's lattice and the measured
level; process noise (Q) of a block; the allowance for what the sigma points cannot see.

* :meth:`NoiseModel.spec_noise` — per-sample σ of each raw reading from its spec (white + own ADC);
* :meth:`NoiseModel.noise` — that, with a format's re-quantisation q²/12 and the measured level where it
  is far above the spec (:meth:`NoiseModel.monitor`, third differences of the raw data);
* :meth:`NoiseModel.process_noise`, :meth:`NoiseModel.cal_rw` — the diagonal of Q: angle random walk of
  the gyro, random walk of the calibration terms;
* :func:`bilinear_var` — the gyro rate error δM·δo the unscented transform leaves out;
* :func:`hold_sigma`, :func:`lattice_plan` — the mean error of held readings on a coarse lattice;
* :meth:`NoiseModel.rest_pair`, :meth:`NoiseModel.for_means` — the noise of a block *mean*: white noise
  averages down as σ²/L, correlated noise (a log low-pass filtered before it was written, as PX4's
  ``sensor_combined``) does not; measured from consecutive block means at rest and applied to every
  block mean the filter uses (issue 10);
* :meth:`NoiseModel.walk_from_rest` — the gyro bias's random walk measured at rest from the trend of its
  rest means, used in place of the spec's allowance where the data show more (issue 10: a freshly powered
  unit's bias drifts while it warms up).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..model import SENSORS
from ..specs import FIELD_GAUSS, SensorSpec
from .layout import ATT, DIP, SENSOR_SLICE

Array = NDArray[np.float64]

MEDIAN_CHI2_3 = 2.365974  # median of χ²(3)
# relative σ of κ̂ from m pairs: the sample median of χ²(3)/median has σ ≈ 1/(2 f(med) med √m) = 1.12/√m
# (f(med) = 0.188, the density at the median); consecutive pairs share a block (differences correlated
# −½), widened to 1.35/√m
KAPPA_REL_SIGMA = 1.35
KAPPA_MIN_PAIRS = 50  # 5 s of 0.1-s blocks at rest before any κ is claimed (from 20, white paper
# sessions switched it on at their first rests in ~1 of 6 seeds: a 3σ test repeated at every pair)
KAPPA_ON_SIGMA = 3.0  # κ̂ − 1 beyond this many of its σ switches it on; within one σ switches it off
KAPPA_EVERY_FROM = 100  # from here on κ̂ is taken every 10th pair (a rest-heavy log spent a third of its
# replay on the median at every pair: the paper session 1.20 → 1.81 s CPU)
KAPPA_KEEP = 3000  # pairs kept (5 minutes of rest at 0.1-s blocks): the median of the most recent
WALK_CHI2_3 = 30.664  # χ²(3) at 1 − 1e-6: the test of a rest's gyro trend, re-taken at every rest block (at
# 1 − 1e-4 one of 60 white paper sessions switched on, 2.2 s into a rest: a turn's settling read as a drift)
WALK_MIN_BLOCKS = 50  # blocks of a rest before its trend is tested (5 s: past a turn's settling)
WALK_CLEAR_S = 30.0  # a rest this long without a trend returns the bias's walk to the spec's


def hold_sigma(q: float, sigma_n: float) -> float:
    """σ of the error of the mean of a held reading re-quantised to q (no averaging removes it).

    A value already quantised by the sensor's ADC and then rounded to a coarser format lattice q is off
    on average by a function of where it sits on the two lattices; white noise σ_n dithers it only
    partly. Bound used: q/√12 · exp(−σ_n/q) (q/√12: no dither). Simulated for sensor lattices of
    0.24–0.53 q and σ_n = 0.3–1.5 q, the rms error stays below this bound (e.g. 0.13 q at σ_n = q/2
    against 0.18 q; ``tests/test_ukf.py::test_hold_sigma_bounds_double_quantisation``).
    """
    if q <= 0:
        return 0.0
    return q / math.sqrt(12.0) * math.exp(-sigma_n / q)



def bilinear_var(P: Array) -> Array:
    """Variance (rad²/s², per body axis) of the rate error the unscented transform leaves out: the
    product δM·δo of the gyro's matrix and bias errors in ω = M (w − o) (eq. 1). Its sigma points move
    M or o, never both, so the product — second order, but 0.04 rad/s for a cold start's 20 % × 0.2
    rad/s — is invisible to them; unmodelled, the attitude drift it causes reads as information on the
    scale (a bilinear term linearised at a wrong bias). Σ_j σ²(M_ij) σ²(o_j), with σ(M_ii) the scale's
    σ and σ(M_ij) that of the axis angles; vanishes once the bias is known (a rest). P (n, n) the state
    covariance."""
    sig = np.sqrt(np.diag(P)[SENSOR_SLICE["gyro"]])
    s_o, s_s = sig[0:3], sig[3:6]
    s_ang = np.maximum(sig[6:9], sig[9:12]).max()
    v_o = s_o * s_o
    out: Array = s_s * s_s * v_o + s_ang**2 * (v_o.sum() - v_o)
    return out


def lattice_plan(q: dict[str, Any], sensors: tuple[str, ...], rate: float, mag_unit: float,
                 specs: dict[str, SensorSpec]) -> list[tuple[str, bool, float]]:
    """Per sensor in ``sensors``: whether its value lattice q[s] is a re-quantisation by the format (coarser
    than 1.5 × the sensor's own ADC step) and the σ of a held reading's mean error (:func:`hold_sigma`)
    on it. ``mag_unit`` the raw magnitude of the unit field (the mag spec is in gauss)."""
    own = {"gyro": specs["gyro"].lsb, "accel": specs["accel"].lsb,
           "mag": specs["mag"].lsb / FIELD_GAUSS * mag_unit}
    white = {"gyro": specs["gyro"].sigma(rate), "accel": specs["accel"].sigma(rate),
             "mag": specs["mag"].sigma(50.0) / FIELD_GAUSS * mag_unit}
    return [(s, bool(q[s] > 1.5 * own[s]), hold_sigma(q[s], white[s])) for s in sensors]


_S0 = SENSOR_SLICE["mag"].start + 3  # the mag's scale in the state


@functools.lru_cache(maxsize=64)
def _density_of(spec: SensorSpec) -> float:
    """:meth:`NoiseModel._density`, kept per spec (a frozen value: the same float every time). The mag's
    spec has no density, and its σ at 50 Hz (numpy scalars, ~4 µs) was recomputed every block (issue 15)."""
    return spec.density if spec.density > 0 else spec.sigma(50.0) / math.sqrt(25.0)


def mag_unit_of(x: Array) -> float:
    """Raw magnitude of the unit field: 1 / mean mag scale of the state x (n,). The mean as numpy forms it
    for three numbers, ((s_x + s_y) + s_z) / 3, in Python floats: the same bits, a tenth of the cost."""
    sx, sy, sz = x[_S0 : _S0 + 3].tolist()
    return 1.0 / ((sx + sy + sz) / 3.0)


def raw_field_unit(x: Array, mag_enabled: bool, first_raw: list[list[float]]) -> float:
    """Raw field magnitude: from the mag scale of the state x once the mag is calibrated, else the median
    norm of the first raw samples ``first_raw`` (M, 3); 1 without either."""
    if mag_enabled:
        return mag_unit_of(x)
    if first_raw:
        return float(np.median(np.linalg.norm(np.asarray(first_raw), axis=1)))
    return 1.0


@dataclass
class NoiseModel:
    """The filter's noise levels. ``specs`` the sensor specs (from the config); ``ratio``, ``high`` the
    measured noise against the spec (smoothed) and whether the sensor's noise is raised now."""

    specs: dict[str, SensorSpec]
    ratio: dict[str, float] = field(default_factory=lambda: {s: 1.0 for s in SENSORS})
    high: dict[str, bool] = field(default_factory=lambda: {s: False for s in SENSORS})
    _spec_key: tuple[float, float] | None = None
    _spec_cache: dict[str, float] = field(default_factory=dict)
    _rw_key: tuple[int, float] | None = None
    _rw_cache: Array = field(default_factory=lambda: np.zeros(0))
    _walk_set: bool = False
    pair_r: dict[str, list[float]] = field(default_factory=lambda: {s: [] for s in SENSORS})
    kappa: dict[str, float] = field(default_factory=lambda: {s: 1.0 for s in SENSORS})
    q_walk: float = 0.0  # the gyro bias's random walk measured at rest (:meth:`walk_from_rest`), rad²/s³; 0: spec

    def spec_noise(self, rate: float | None, x: Array) -> dict[str, float]:
        """Per-sample σ of the raw readings from the specs (white noise + the sensor's own quantisation);
        the mag's relative to the field, in the raw unit of the state x (gauss or milli-gauss).

        Cached on what the values depend on (issue 15): the rate (key ``(rate, 0.0)``); the mag's σ per
        unit field is cached and multiplied by the state's unit (:func:`mag_unit_of`) at every call — the
        same product as the uncached formula, so the same bits. (Keyed on the mag scale, the cache missed
        nearly every block: every update moves the scale.)"""
        r = rate or 100.0
        if self._spec_key is None or self._spec_key[0] != r or self._spec_key[1] != 0.0:
            g, a, m = self.specs["gyro"], self.specs["accel"], self.specs["mag"]
            self._spec_key = (r, 0.0)
            self._spec_cache = {
                "gyro": math.hypot(g.sigma(r), g.lsb / math.sqrt(12)),
                "accel": math.hypot(a.sigma(r), a.lsb / math.sqrt(12)),
                "mag": math.hypot(m.sigma(50.0), m.lsb / math.sqrt(12)) / FIELD_GAUSS,  # per unit field
            }
        sc = self._spec_cache
        return {"gyro": sc["gyro"], "accel": sc["accel"], "mag": sc["mag"] * mag_unit_of(x)}

    def noise(self, spec: dict[str, float], q: dict[str, Any]) -> dict[str, float]:
        """Per-sample σ used by the filter: the spec's, the format's re-quantisation (q²/12, white part)
        and, where the measured noise is far above the spec, scaled to the measured level."""
        n = dict(spec)
        for s in SENSORS:
            if q.get(s + "_requant"):
                n[s] = math.hypot(n[s], q[s] / math.sqrt(12.0))
            if self.high[s]:
                n[s] *= math.sqrt(self.ratio[s])
        return n

    def rest_pair(self, sensor: str, mean: Array, prev: Array, inv_counts: float, sigma: float
                  ) -> tuple[str, str] | None:
        """Record one pair of consecutive block means at rest, ``mean`` and ``prev`` (3,), of L₁ and L₂ samples
        (``inv_counts`` = 1/L₁ + 1/L₂), against the filter's per-sample σ ``sigma`` now; update the sensor's
        block-mean factor κ and return the event of a change (kind, detail), or None.

        Kept per pair: |Δ|²/(1/L₁ + 1/L₂), the per-sample variance the pair implies (raw unit²), so that κ
        follows the σ the filter uses now (the magnetometer's raw unit is only known after its cold start,
        and the noise monitor may raise a σ). κ̂ = median / (median χ²(3) σ²): 1 for white noise,
        (1 + ρ)/(1 − ρ) for AR(1) samples of correlation ρ at long blocks — the factor by which a block
        mean's variance exceeds σ²/L. The median keeps one pair that caught the start of a motion from
        deciding it. Applied (``kappa``) only where the data say so: κ̂ − 1 beyond 3 of its own σ
        (:data:`KAPPA_REL_SIGMA`/√m) after :data:`KAPPA_MIN_PAIRS` pairs, and kept until κ̂ − 1 falls within
        one σ; never below 1 (the spec's white noise is the floor the filter keeps)."""
        var_white = sigma**2 * inv_counts
        if not (var_white > 0.0 and math.isfinite(var_white)):
            return None
        (ax, ay, az), (bx, by, bz) = mean.tolist(), prev.tolist()  # Python floats: ~1 µs against numpy's ~5
        r = ((ax - bx) ** 2 + (ay - by) ** 2 + (az - bz) ** 2) / inv_counts
        if not math.isfinite(r):
            return None
        buf = self.pair_r[sensor]
        buf.append(r)
        if len(buf) > KAPPA_KEEP:
            del buf[: len(buf) - KAPPA_KEEP]
        m = len(buf)
        if m < KAPPA_MIN_PAIRS or (m >= KAPPA_EVERY_FROM and m % 10):
            return None  # past KAPPA_EVERY_FROM pairs, κ̂ is taken every 10th pair: one median of up to 3000
        k_hat = float(np.median(buf)) / (MEDIAN_CHI2_3 * sigma**2)
        old = self.kappa[sensor]
        # on beyond 3σ of κ̂, off only once within 1σ of white: a κ̂ near the threshold does not toggle
        on = k_hat - 1.0 > (1.0 if old > 1.0 else KAPPA_ON_SIGMA) * KAPPA_REL_SIGMA / math.sqrt(m)
        new = k_hat if on else 1.0
        self.kappa[sensor] = new
        if old == 1.0 and new > 1.0:
            return ("noise_means",
                    f"{sensor} block means at rest vary {new:.2g}× (in variance) what white noise of the filter's "
                    f"σ gives ({m} pairs): its noise is correlated (a log low-pass filtered before it was "
                    f"written) or above that σ; every block mean's σ raised by {math.sqrt(new):.2g}×")
        if old > 1.0 and new == 1.0:
            return "noise_means", f"{sensor} block means at rest back within white noise of its σ ({m} pairs)"
        return None

    def for_means(self, n: dict[str, float]) -> dict[str, float]:
        """The per-sample σ ``n`` scaled so that σ²/L is the variance of an L-sample block mean (or sum):
        × √κ per sensor (:meth:`rest_pair`). The same dict when every κ is 1."""
        k = self.kappa
        if k["gyro"] == 1.0 and k["accel"] == 1.0 and k["mag"] == 1.0:
            return n
        return {s: v * math.sqrt(k[s]) for s, v in n.items()}

    def walk_from_rest(self, slope: Array, var_slope: float, T: float, k: int) -> tuple[str, str] | None:
        """The gyro bias's random walk from a rest of ``T`` s and ``k`` blocks whose gyro means trend by
        ``slope`` (3,) rad/s per s, each axis of variance ``var_slope`` under the block means' noise
        (:meth:`.rest.RestAccumulator.trend`). Returns the event of a change, or None.

        At rest the gyro reads its bias (and the Earth's rate, constant at rest): a trend is a bias that
        moves — a freshly powered unit warming up (the real PX4 log's: 5–11 µrad/s per s over its 60-s rest).
        Tested as χ² = Σ slope²/var_slope against χ²(3) at 1 − 10⁻⁶ (:data:`WALK_CHI2_3`; re-taken at every block of
        a rest, so a strict level), from the rest's :data:`WALK_MIN_BLOCKS`-th block, once the noise of a block mean
        is decided (:data:`KAPPA_MIN_PAIRS` pairs at rest in the log). Where it passes, the walk is the drift's
        excess power per axis times the rest's length, q² = T · Σ(slope² − var_slope)/3 (rad²/s³): the random walk
        whose spread over the next T s, q²T, is the drift's (rT)², and whose end-against-mean over the rest, q²T/3,
        covers the drift's (rT/2)². It is kept (a warm-up does not stop when a rest ends) until a rest of at least
        :data:`WALK_CLEAR_S` s shows no trend; a drift that slows is then seen as none. A drift is not a random
        walk: the allowance holds over horizons like the rest's, not far beyond."""
        if k < WALK_MIN_BLOCKS or len(self.pair_r["gyro"]) < KAPPA_MIN_PAIRS or not var_slope > 0.0:
            return None  # nor before the noise of a block mean (κ, :meth:`rest_pair`) is decided: on a low-pass
            # filtered log the slope's variance would be κ times too small
        sx, sy, sz = slope.tolist()
        chi = (sx * sx + sy * sy + sz * sz) / var_slope
        old = self.q_walk
        if chi > WALK_CHI2_3:
            self.q_walk = max(0.0, (sx * sx + sy * sy + sz * sz - 3.0 * var_slope) / 3.0) * T
        elif T >= WALK_CLEAR_S:
            self.q_walk = 0.0
        new = self.q_walk
        if old == 0.0 and new > 0.0:
            return ("bias_walk", f"gyro bias drifts at rest by {math.sqrt(sx * sx + sy * sy + sz * sz):.2g} rad/s "
                    f"per s over {T:.3g} s (χ² {chi:.3g}, 3 dof): its random walk raised from the spec's to "
                    f"{math.sqrt(new):.2g} rad/s/√s")
        if old > 0.0 and new == 0.0:
            return "bias_walk", f"gyro bias steady over a {T:.3g}-s rest: its random walk back to the spec's"
        return None

    def cal_rw(self, n: int, x: Array, ext_sigma: list[tuple[slice, float]], rw_factor: float) -> Array:
        """Random-walk variance per second of every state (n,) (attitude entries 0): density × ``rw_factor``
        per √s (bias), density/full-scale × ``rw_factor`` (dimensionless terms) — a slow drift allowance set
        from the specs, not tuned per log; extensions (``ext_sigma``: (slice, prior σ)) their prior σ ×
        ``rw_factor``; hold offsets none (a held value's error is constant).

        Only the mag bias's entries depend on the state (through the raw unit of the field, x's mag scale):
        the rest is cached on (n, ``rw_factor``) and those three are set at every call from the current x
        (issue 15: before, the whole vector was keyed on the unit rounded to 1e-6 — a ``round`` of a numpy
        scalar, ~5 µs, and a miss nearly every block; the entries lagged the unit by up to that rounding).
        The gyro bias's entries are the measured walk (:meth:`walk_from_rest`) where it is above the spec's.
        Returns the cached array, as before (read it, do not change it: the next call rewrites it)."""
        key = (n, float(rw_factor))
        if self._rw_key != key or self._rw_cache.shape[0] != n:
            q = np.zeros(n)
            for s, spec in self.specs.items():
                sl = SENSOR_SLICE[s]
                dens = self._density(spec)
                q[sl.start : sl.start + 3] = (dens * rw_factor) ** 2  # the mag's replaced below
                q[sl.start + 3 : sl.stop] = (dens / spec.full_scale * rw_factor) ** 2
            q[DIP] = (1e-6) ** 2
            for sl, sig in ext_sigma:
                q[sl] = (sig * rw_factor) ** 2
            self._rw_key, self._rw_cache = key, q
        q = self._rw_cache
        if self.q_walk > 0.0 or self._walk_set:
            self.apply_walk(rw_factor)
        if "mag" in self.specs:
            unit = mag_unit_of(x) / FIELD_GAUSS
            sm = SENSOR_SLICE["mag"].start
            q[sm : sm + 3] = (self._density(self.specs["mag"]) * unit * rw_factor) ** 2
        return q

    def apply_walk(self, rw_factor: float) -> None:
        """Set the gyro bias's entries of the cached random-walk vector (:meth:`cal_rw`) in place: the walk
        measured at rest (:meth:`walk_from_rest`) where it is above the spec's, the spec's otherwise. The fast
        path keeps that array between blocks (:func:`.fastpath._block_consts`) and calls this where a walk is
        or was in use."""
        gb = SENSOR_SLICE["gyro"].start
        q_spec = (self._density(self.specs["gyro"]) * rw_factor) ** 2
        self._rw_cache[gb : gb + 3] = max(q_spec, self.q_walk)
        self._walk_set = self.q_walk > 0.0

    @staticmethod
    def _density(spec: SensorSpec) -> float:
        """Noise density of ``spec`` (its white σ at 50 Hz over √25 where none is given)."""
        return _density_of(spec)

    @staticmethod
    def process_noise(cal_rw: Array, dt: float, rate: float | None, sigma_gyr: float) -> Array:
        """Diagonal of Q for one block lasting ``dt`` s; ``sigma_gyr`` the gyro's per-sample σ (rad/s).

        Attitude: angle random walk of the gyro, σ_gyr/r per sample for the r·dt samples the block spans
        (rad², every axis; by its duration, so that dropped samples do not shrink it); calibration: the
        random walk ``cal_rw`` (:meth:`cal_rw`) over dt.
        """
        r = rate or 100.0
        q = cal_rw * dt
        q[ATT] = dt * r * (sigma_gyr / r) ** 2
        return q

    def monitor_all(self, var3: dict[str, float], spec: dict[str, float], q: dict[str, Any], tau_blocks: float,
                    high: float, low: float) -> list[tuple[str, str]]:
        """:meth:`monitor` for every sensor (``var3``, ``spec`` per sensor); the events, in sensor order."""
        evs = [self.monitor(s, var3[s], spec[s], q, tau_blocks, high, low) for s in SENSORS]
        return [e for e in evs if e is not None]

    def monitor(self, sensor: str, var: float, spec: float, q: dict[str, Any], tau_blocks: float,
                high: float, low: float) -> tuple[str, str] | None:
        """Measured per-sample noise ``var`` (third differences of the block, :func:`.blocks.third_diff_var`)
        against the spec σ ``spec``, smoothed over ``tau_blocks``; raises the sensor's noise when it is
        above ``high`` × the spec variance and returns to the spec below ``low``. Returns the event
        (kind, detail) of a change, or None. NaN (too few regular samples): no change."""
        if not math.isfinite(var):
            return None
        if q.get(sensor + "_requant"):
            spec = math.hypot(spec, q[sensor] / math.sqrt(12.0))
        a = 1.0 / tau_blocks
        r = (1 - a) * self.ratio[sensor] + a * var / spec**2
        self.ratio[sensor] = r
        if not self.high[sensor] and r > high:
            self.high[sensor] = True
            return "noise_high", f"{sensor} noise {math.sqrt(r):.2g}× its spec: its weight lowered"
        if self.high[sensor] and r < low:
            self.high[sensor] = False
            return "noise_normal", f"{sensor} noise back to {math.sqrt(r):.2g}× its spec"
        return None
