"""Health verdict of a calibration result: ``ok | degraded | failed``, with the reasons in words.

A result is judged on what can be checked without the truth:

* **physical ranges** (:func:`range_checks`): gyro and accelerometer scale factors within [0.5, 2]; the
  magnetometer's axis scales within a factor 3 of each other (eq. 17 maps the field to the unit sphere, so
  its absolute scale is 1 / field in the raw unit, but a soft-iron ratio beyond 3 is no real magnetometer);
  a hard-iron bias at most 10× the field (‖M (−o)‖ ≤ 10 in the field's unit); |ξ| below 0.5 rad (the
  non-orthogonality of eq. 6 is a fraction of a degree in real sensors; ±π/2 is a degenerate decomposition);
  gyro bias below 1 rad/s and accelerometer bias below 3 m/s². Out of range → **failed**.
* **consistency** of the online filter (:func:`nis_checks`): the mean normalised innovation squared per
  sensor against its expectation, the measurement dimension d = 3 (a chi-square mean). Outside
  [d/2, 2d] → **degraded** (the noise model does not describe the data: the σ are not to be trusted), above
  10 d → **failed** (the estimate does not describe the data at all).
  On a vehicle, the accelerometer updates whose R carries the modelled vehicle acceleration (σ_v² τ_v/Δt,
  :mod:`onlinecal.ukf.vehicle`) are summarised apart (the sensor's ``"vehicle"`` figures,
  :mod:`onlinecal.ukf.health`): their NIS is below d by design whenever the vehicle accelerates less than
  the bound, so only a mean *above* 2 d (the bound did not cover the flight) → **degraded**, above 10 d →
  **failed**; the two-sided band judges the updates whose R is the sensor's noise (rests, the ground).
  A thrust-borne vehicle's magnetometer updates in motion hold its soft iron at the start's σ (Schmidt consider
  states, :attr:`onlinecal.ukf.state.StateLayout.mag_flight_terms`), which is in every one of their S: where those
  are most of its updates (``held`` ≥ :data:`HELD_SHARE` × ``updates``) a mean *below* d/2 says the start is
  better than its σ, not that the noise is overstated — a *note*; above 2 d it is judged as ever.
* **gravity at rest** (:func:`gravity_checks`), when the raw samples are given (whole, or as the
  :class:`RawDigest` a streamed replay or a live run gathers from every sample it fed): where the calibrated
  gyro and accelerometer are still (blocks of :data:`REST_BLOCK` samples), the calibrated specific force is
  gravity, so its norm must be g within what the accelerometer's σ along it allow (5σ) plus the spread of
  local gravity on Earth (:data:`G_LOCAL_TOL`). Beyond → **degraded**. The filter cannot always show this
  in its NIS: its quasi-static weighting reads a norm away from g as a linear acceleration and lowers the
  accelerometer's weight (a bench file 0.3 m/s² off along z, σ 1e-3, replayed on a flight: 9 of 20 runs'
  accel NIS stayed in band).
* **divergences** and **saturation** events of the filter → **degraded**, each counted in words.
* **coverage** of the magnetometer data (:func:`mag_coverage`), when the raw samples are given and the
  magnetometer's bias or scale were fitted on them (:func:`_mag_fitted_here`): the
  share of 32 equal direction cells on the calibrated unit sphere that hold samples. Below 40 % → the
  ellipsoid fit (eq. 17) extrapolates and its bias and scale can be far further off than their σ →
  **degraded** — unless the σ are the batch's prior-regularised fit's
  (:func:`mag_sigma_covers_extrapolation`, :func:`onlinecal.batch.ellipsoid.fit_norm_map`), which keep the
  soft-iron prior's width along the unseen directions: then the terms are judged by those σ, the low
  coverage is a *note*, and the terms the data did not determine are named (on 60 simulated flights every
  determined term within 3.5σ of the truth: docs/json.md).
* **terms the data did not determine** (the filter's posterior σ above ½ its prior σ; a batch term
  without σ) are listed as *notes*: they keep their start value and wide σ, which is honest, not wrong.

The verdict is a plain JSON-serialisable dict (:func:`assess`); the command line prints it, writes it as the
top-level ``"health"`` key of every result JSON, and maps it to the exit status (:data:`EXIT_STATUS`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from .model import PARAMS, SENSORS, Calibration
from .specs import RAIL_SAMPLES, RAIL_TOL

HEALTH_SCHEMA = "onlinecal.health/1"
VERDICTS = ("ok", "degraded", "failed")
# Exit status of a command whose result has this verdict (2: unusable input, 3: missing component).
EXIT_STATUS = {"ok": 0, "degraded": 4, "failed": 5}

SCALE_RANGE = {"gyro": (0.5, 2.0), "accel": (0.5, 2.0)}
MAG_SCALE_RATIO_MAX = 3.0
MAG_BIAS_FIELDS_MAX = 10.0
XI_MAX = 0.5  # rad
BIAS_MAX = {"gyro": 1.0, "accel": 3.0}  # rad/s, m/s²
NIS_DOF = 3
NIS_OK = (0.5, 2.0)  # × dof: the mean NIS of a consistent filter
NIS_FAILED = 10.0  # × dof
NIS_MIN_WINDOWS = 3  # for the degraded band; one window far above 10 d already fails
GATE_DEGRADED = 0.10  # share of a sensor's updates rejected by the filter's gate
GATE_FAILED = 0.40
RAIL_MIN = {"gyro": 1.0, "accel": 19.6}  # rad/s, m/s²: no rail is below (250 °/s gyros, 2 g accels)
UNDETERMINED_RATIO = 0.5  # posterior σ / prior σ above this: the data did not determine the term
COVERAGE_MIN = 0.4
# gravity at rest: blocks of REST_BLOCK samples whose calibrated gyro is below REST_RATE rad/s (mean and
# per-axis σ) and whose calibrated accel per-axis σ is below REST_ACC m/s² (the spec noise of a MEMS part
# is 0.01–0.03 m/s² per sample up to 1 kHz; any running motor is ≥ 0.3); at least REST_MIN_BLOCKS of them
REST_BLOCK = 50
REST_RATE = 0.01
REST_ACC = 0.05
REST_MIN_BLOCKS = 10
# local gravity on the Earth's surface spans 9.764 (high mountains, equator) – 9.834 m/s² (poles): within
# 0.05 m/s² of the standard value the norm check cannot tell a calibration error from the place
G_LOCAL_TOL = 0.05
COVERAGE_CELLS = 32
COVERAGE_MIN_SAMPLES = 3  # per cell


def _worst(a: str, b: str) -> str:
    return a if VERDICTS.index(a) >= VERDICTS.index(b) else b


def range_checks(cal: Calibration) -> list[tuple[str, str]]:
    """(verdict, reason) for every parameter outside its physical range (see the module doc)."""
    out: list[tuple[str, str]] = []
    for s in SENSORS:
        c = cal.sensor(s)
        if c is None:
            continue
        try:
            scale, xi = np.asarray(c.scale), np.asarray(c.xi)
        except (ValueError, np.linalg.LinAlgError):
            out.append(("failed", f"{s}: the matrix has no decomposition into scale, rotation and "
                                  "non-orthogonality (eqs. 2-6)"))
            continue
        if s in SCALE_RANGE:
            lo, hi = SCALE_RANGE[s]
            bad = [f"{a} {v:.4g}" for a, v in zip("xyz", scale, strict=True) if not lo <= abs(v) <= hi]
            if bad:
                out.append(("failed", f"{s}: scale {', '.join(bad)} outside the physical range [{lo}, {hi}]"))
            b = float(np.abs(c.bias).max())
            if b > BIAS_MAX[s]:
                unit = "rad/s" if s == "gyro" else "m/s²"
                out.append(("failed", f"{s}: bias {b:.4g} {unit} larger than any working sensor's "
                                      f"(≤ {BIAS_MAX[s]:g} {unit})"))
        else:
            a = np.abs(scale)
            if a.min() <= 0 or a.max() / a.min() > MAG_SCALE_RATIO_MAX:
                out.append(("failed", f"mag: axis scales {np.array2string(scale, precision=4)} differ by more "
                                      f"than a factor {MAG_SCALE_RATIO_MAX:g}: not a magnetometer's soft iron"))
            hard = float(np.linalg.norm(c.matrix @ c.bias))
            if hard > MAG_BIAS_FIELDS_MAX:
                out.append(("failed", f"mag: hard-iron bias {hard:.3g}× the local field (at most "
                                      f"{MAG_BIAS_FIELDS_MAX:g}× on a vehicle)"))
        big = [f"{a} {v:+.3f}" for a, v in zip("xyz", xi, strict=True) if abs(v) > XI_MAX]
        if big:
            out.append(("failed", f"{s}: non-orthogonality ξ {', '.join(big)} rad beyond {XI_MAX} rad "
                                  "(real sensing axes are orthogonal to a fraction of a degree)"))
    return out


HELD_SHARE = 0.5  # share of a sensor's updates made with its soft iron held above which a low NIS is a note
HELD_STATUS = "below band, soft iron held"


def nis_checks(nis: dict[str, Any] | None) -> tuple[list[tuple[str, str]], dict[str, Any]]:
    """(verdict, reason) per sensor whose mean NIS is out of [d/2, 2d] (degraded) or above 10 d (failed),
    and the per-sensor figures."""
    out: list[tuple[str, str]] = []
    figs: dict[str, Any] = {}
    if not nis:
        return out, figs
    lo, hi = NIS_OK[0] * NIS_DOF, NIS_OK[1] * NIS_DOF
    for s, st in nis.items():
        if not isinstance(st, dict):  # "band", "events_total": figures, not a sensor
            continue
        raw_m, w = st.get("mean"), int(st.get("windows") or 0)
        gate = _gate_check(s, st)
        if gate is not None:
            out.append(gate)
        m = float(raw_m) if isinstance(raw_m, (int, float)) else math.nan
        if not math.isfinite(m) or (w < NIS_MIN_WINDOWS and not (w >= 1 and m > NIS_FAILED * NIS_DOF)):
            figs[s] = {"mean": m if math.isfinite(m) else None, "windows": w, "expected": NIS_DOF,
                       "status": "too few updates"}
            continue
        status = "ok"
        if m > NIS_FAILED * NIS_DOF:
            status = "failed"
            out.append(("failed", f"{s}: mean NIS {m:.4g} against {NIS_DOF} expected: the calibration does not "
                                  "describe the data"))
        elif m < lo and int(st.get("held") or 0) >= HELD_SHARE * max(int(st.get("updates") or 0), 1):
            status = HELD_STATUS  # a note (assess): the held soft iron's σ is in every one of those updates' S
        elif not lo <= m <= hi:
            status = "degraded"
            how = "the data scatter more than the model allows" if m > hi else "the noise is overstated"
            out.append(("degraded", f"{s}: mean NIS {m:.3g} outside [{lo:g}, {hi:g}] ({NIS_DOF} expected): {how}; "
                                    "its σ are not to be trusted"))
        figs[s] = {"mean": m, "windows": w, "expected": NIS_DOF, "band": [lo, hi], "status": status}
    for s, st in nis.items():
        veh = st.get("vehicle") if isinstance(st, dict) else None
        if isinstance(veh, dict):
            vf, figs[s + "_vehicle"] = _vehicle_nis_check(s, veh)
            out += vf
    return out, figs


def _vehicle_nis_check(sensor: str, st: dict[str, Any]) -> tuple[list[tuple[str, str]], dict[str, Any]]:
    """One-sided judgement of the vehicle-disturbed updates' mean NIS (see the module doc): the disturbance
    is a bound, so a mean below d is expected; above 2 d the bound did not cover the vehicle's motion."""
    raw_m, w = st.get("mean"), int(st.get("windows") or 0)
    m = float(raw_m) if isinstance(raw_m, (int, float)) else math.nan
    hi = NIS_OK[1] * NIS_DOF
    fig: dict[str, Any] = {"mean": m if math.isfinite(m) else None, "windows": w, "expected": f"≤ {NIS_DOF}",
                           "band": [0.0, hi]}
    if not math.isfinite(m) or (w < NIS_MIN_WINDOWS and not (w >= 1 and m > NIS_FAILED * NIS_DOF)):
        return [], dict(fig, status="too few updates")
    if m > NIS_FAILED * NIS_DOF:
        return [("failed", f"{sensor} in flight: mean NIS {m:.4g} with the vehicle acceleration modelled "
                           f"({NIS_DOF} at most expected): the calibration does not describe the data")], \
            dict(fig, status="failed")
    if m > hi:
        return [("degraded", f"{sensor} in flight: mean NIS {m:.3g} above {hi:g} with the vehicle acceleration "
                             "modelled: the vehicle accelerated beyond the modelled bound or the calibration is "
                             "off; its σ are not to be trusted")], dict(fig, status="degraded")
    return [], dict(fig, status="ok")


def _gate_check(sensor: str, st: dict[str, Any]) -> tuple[str, str] | None:
    """A sensor whose updates the filter's outlier gate rejected in large numbers: the model and the data
    disagree (a consistent filter rejects about one in a thousand)."""
    up, rej = int(st.get("updates") or 0), int(st.get("rejected") or 0)
    if up + rej < 20 or rej == 0:
        return None
    share = rej / (up + rej)
    if share > GATE_FAILED:
        return ("failed", f"{sensor}: the filter's gate rejected {rej} of {up + rej} updates ({100 * share:.0f} %): "
                          "the calibration does not describe the data")
    if share > GATE_DEGRADED:
        return ("degraded", f"{sensor}: the filter's gate rejected {rej} of {up + rej} updates ({100 * share:.0f} %)")
    return None


class RawDigest:
    """What the health verdict reads of the raw gyro and accelerometer samples, gathered block by block, so that
    a replay that streams its logs (``onlinecal replay`` holds no log whole) is judged as one that held them:
    per :data:`REST_BLOCK` consecutive IMU samples of one log, each sensor's raw mean (3,) and covariance (3, 3)
    (:func:`gravity_checks`: a calibration is linear, so the calibrated block's mean and per-axis σ follow
    exactly), and per sensor and axis the largest magnitude with the samples near it (:func:`rail_checks`,
    :func:`onlinecal.specs.rail_samples`'s rule). Memory: 24 numbers per 50 samples, and the samples within
    :data:`onlinecal.specs.RAIL_TOL` of an axis' top above :data:`RAIL_MIN`.

    ``add(gyro, accel)``: raw samples (N, 3) of the two sensors on one time base, in order; ``new_log()``
    between logs (a block never spans two)."""

    SENSORS = ("gyro", "accel")
    PENDING = 2048  # samples held before they are digested

    def __init__(self) -> None:
        self._pending: list[tuple[np.ndarray, np.ndarray]] = []
        self._n_pending = 0
        self._carry: list[np.ndarray] | None = None
        self._mean: dict[str, list[np.ndarray]] = {s: [] for s in self.SENSORS}
        self._cov: dict[str, list[np.ndarray]] = {s: [] for s in self.SENSORS}
        self._top = {s: np.zeros(3) for s in self.SENSORS}
        self._near: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {s: [(np.zeros(0, np.int64), np.zeros(0))] * 3
                                                                      for s in self.SENSORS}
        self._seen = {s: 0 for s in self.SENSORS}  # samples, the rail candidates' index
        self._blocks_done = 0

    @classmethod
    def of(cls, raw: dict[str, Any] | None) -> RawDigest:
        """The digest of whole arrays (sensor → (N, 3)), as :func:`assess`'s ``raw`` gives them."""
        d = cls()
        w, a = (None if not raw else raw.get(s) for s in cls.SENSORS)
        w = None if w is None else np.asarray(w, float).reshape(-1, 3)
        a = None if a is None else np.asarray(a, float).reshape(-1, 3)
        for s, x in (("gyro", w), ("accel", a)):
            if x is not None:
                d._rails(s, x)
        if w is not None and a is not None:
            n = min(w.shape[0], a.shape[0])
            d._blocks(w[:n], a[:n])
        return d

    def new_log(self) -> None:
        self._flush()
        self._carry = None

    def add(self, gyro: Any, accel: Any) -> None:
        w, a = np.asarray(gyro, float).reshape(-1, 3), np.asarray(accel, float).reshape(-1, 3)
        if w.shape != a.shape:
            raise ValueError(f"gyro {w.shape} and accel {a.shape} samples are not on one time base")
        # a live link's blocks are a few samples each: they wait here and are digested in thousands
        self._pending.append((w.copy(), a.copy()))
        self._n_pending += w.shape[0]
        if self._n_pending >= self.PENDING:
            self._flush()

    def _flush(self) -> None:
        if not self._pending:
            return
        w = np.concatenate([p[0] for p in self._pending])
        a = np.concatenate([p[1] for p in self._pending])
        self._pending, self._n_pending = [], 0
        self._rails("gyro", w)
        self._rails("accel", a)
        if self._carry is not None:
            w, a = np.concatenate([self._carry[0], w]), np.concatenate([self._carry[1], a])
        n = w.shape[0] // REST_BLOCK * REST_BLOCK
        self._blocks(w[:n], a[:n])
        self._carry = [w[n:].copy(), a[n:].copy()]

    def _blocks(self, w: np.ndarray, a: np.ndarray) -> None:
        n = w.shape[0] // REST_BLOCK * REST_BLOCK
        if n == 0:
            return
        for s, x in (("gyro", w[:n]), ("accel", a[:n])):
            X = x.reshape(-1, REST_BLOCK, 3)
            with np.errstate(all="ignore"):
                m = X.mean(1)
                D = X - m[:, None, :]
                self._mean[s].append(m)
                self._cov[s].append(np.matmul(D.transpose(0, 2, 1), D) / REST_BLOCK)
        self._blocks_done += n // REST_BLOCK

    def _rails(self, s: str, x: np.ndarray) -> None:
        ax = np.abs(x)
        ax = np.where(np.isfinite(ax), ax, 0.0)
        i0 = self._seen[s]
        self._seen[s] += ax.shape[0]
        if ax.shape[0] == 0:
            return
        top = np.maximum(self._top[s], ax.max(axis=0))
        self._top[s] = top
        floor = RAIL_MIN[s] * (1 - RAIL_TOL)  # no rail below RAIL_MIN: nothing under it is ever counted
        for k in range(3):
            lo = max(top[k] * (1 - RAIL_TOL), floor)
            idx, val = self._near[s][k]
            keep = val >= lo
            new = np.flatnonzero(ax[:, k] >= lo)
            self._near[s][k] = (np.concatenate([idx[keep], i0 + new]), np.concatenate([val[keep], ax[new, k]]))

    @property
    def blocks(self) -> int:
        """Blocks of :data:`REST_BLOCK` samples digested."""
        self._flush()
        return self._blocks_done

    def block_stats(self, sensor: str) -> tuple[np.ndarray, np.ndarray]:
        """(means (B, 3), covariances (B, 3, 3)) of ``sensor``'s raw blocks."""
        self._flush()
        m, c = self._mean[sensor], self._cov[sensor]
        return (np.concatenate(m) if m else np.zeros((0, 3)), np.concatenate(c) if c else np.zeros((0, 3, 3)))

    def rails(self, sensor: str) -> tuple[np.ndarray, np.ndarray, int]:
        """(top (3,), axes with a rail (3,), samples at any rail axis' top): :func:`onlinecal.specs.rail_samples`."""
        self._flush()
        top = self._top[sensor]
        counts = np.array([self._near[sensor][k][0].size for k in range(3)])
        rail = (counts >= RAIL_SAMPLES) & (top > RAIL_MIN[sensor])
        at = [self._near[sensor][k][0] for k in range(3) if rail[k]]
        n = int(np.unique(np.concatenate(at)).size) if at else 0
        return top, rail, n

    def has(self, sensor: str) -> bool:
        self._flush()
        return self._seen[sensor] > 0

    # A checkpoint of the digest (a live run's, :mod:`onlinecal.ukf.live_files`): the blocks as rows of ROW numbers
    # (each sensor's raw mean (3) and covariance (9), gyro then accel), which only grow and so are appended to a
    # file beside the checkpoint, and the rest (:meth:`state`: the rail's top and candidates, the samples seen, the
    # partial block carried to the next feed), small, in the checkpoint itself.
    ROW = 24

    def rows(self, start: int = 0) -> np.ndarray:
        """The blocks digested from block ``start`` on, (blocks − start, :attr:`ROW`): per block the gyro's raw mean
        (3,) and covariance (9,), then the accelerometer's."""
        self._flush()
        out = np.empty((max(0, self._blocks_done - start), self.ROW))
        for k, s in enumerate(self.SENSORS):
            m, c = self._tail(self._mean[s], start), self._tail(self._cov[s], start)
            out[:, 12 * k: 12 * k + 3] = m
            out[:, 12 * k + 3: 12 * k + 12] = c.reshape(-1, 9)
        return out

    @staticmethod
    def _tail(chunks: list[np.ndarray], start: int) -> np.ndarray:
        """Rows from ``start`` on of a list of chunks, joining only the chunks that hold them."""
        n = sum(c.shape[0] for c in chunks)
        keep, have = [], n
        for c in reversed(chunks):
            if have <= start:
                break
            lo = max(0, start - (have - c.shape[0]))
            keep.append(c[lo:])
            have -= c.shape[0]
        if not keep:
            return np.zeros((0, *chunks[0].shape[1:])) if chunks else np.zeros((0, 3))
        return np.concatenate(keep[::-1])

    def state(self) -> dict[str, Any]:
        """Everything of the digest but its blocks' rows (:meth:`rows`), JSON-serialisable (floats as Python
        floats: exact through JSON)."""
        self._flush()
        return {
            "blocks": self._blocks_done,
            "seen": dict(self._seen),
            "top": {s: self._top[s].tolist() for s in self.SENSORS},
            "near": {s: [[idx.tolist(), val.tolist()] for idx, val in self._near[s]] for s in self.SENSORS},
            "carry": None if self._carry is None else [self._carry[0].tolist(), self._carry[1].tolist()],
        }

    @classmethod
    def from_state(cls, state: dict[str, Any], rows: np.ndarray) -> RawDigest:
        """The digest of :meth:`state` and its ``rows`` (:meth:`rows` from 0). ValueError (one line) when the two
        do not belong together or a part is malformed."""
        d = cls()
        rows = np.asarray(rows, float)
        n = int(state["blocks"])
        if rows.ndim != 2 or rows.shape[1] != cls.ROW or rows.shape[0] != n:
            raise ValueError(f"the digest records {n} blocks, its rows are {rows.shape}")
        for k, s in enumerate(cls.SENSORS):
            d._mean[s] = [rows[:, 12 * k: 12 * k + 3].copy()] if n else []
            d._cov[s] = [rows[:, 12 * k + 3: 12 * k + 12].reshape(-1, 3, 3).copy()] if n else []
            d._seen[s] = int(state["seen"][s])
            top = np.asarray(state["top"][s], float)
            if top.shape != (3,) or d._seen[s] < 0:
                raise ValueError(f"the digest's {s} top is {top.shape}, seen {d._seen[s]}")
            d._top[s] = top
            near = state["near"][s]
            if len(near) != 3:
                raise ValueError(f"the digest's {s} rail candidates hold {len(near)} axes, not 3")
            pairs = [(np.asarray(i, np.int64).reshape(-1), np.asarray(v, float).reshape(-1)) for i, v in near]
            if any(i.size != v.size for i, v in pairs):
                raise ValueError(f"the digest's {s} rail candidates: indices and values differ in length")
            d._near[s] = pairs
        carry = state["carry"]
        if carry is not None:
            w, a = (np.asarray(c, float).reshape(-1, 3) for c in carry)
            if w.shape != a.shape or w.shape[0] >= REST_BLOCK:
                raise ValueError(f"the digest's partial block is {w.shape} and {a.shape}")
            d._carry = [w, a]
        d._blocks_done = n
        return d


def _digest(raw: dict[str, Any] | RawDigest | None) -> RawDigest | None:
    if raw is None or isinstance(raw, RawDigest):
        return raw
    return RawDigest.of(raw) if raw else None


def rail_checks(raw: dict[str, Any] | RawDigest | None) -> tuple[list[tuple[str, str]], dict[str, int]]:
    """Saturation seen in the raw samples (``raw``: sensor → (N, 3), or their :class:`RawDigest`): an axis
    whose largest magnitude, above :data:`RAIL_MIN`, recurs in at least :data:`onlinecal.specs.RAIL_SAMPLES`
    samples is at its rail (a true peak is reached once; :func:`onlinecal.specs.rail_samples`)
    → degraded, whether or not the filter raised an event."""
    out: list[tuple[str, str]] = []
    counts: dict[str, int] = {}
    d = _digest(raw)
    if d is None:
        return out, counts
    for s in RawDigest.SENSORS:
        if not d.has(s):
            continue
        top, rail, n = d.rails(s)
        if n:
            counts[s] = n
            axes = ", ".join(f"{'xyz'[k]} ±{top[k]:.4g}" for k in range(3) if rail[k])
            out.append(("degraded", f"{s}: {n} samples at the sensor's rail ({axes}): clipped readings "
                                    "(saturation) bias every term they enter"))
    return out, counts


def event_checks(events: Iterable[dict[str, Any]] | None) -> tuple[list[tuple[str, str]], dict[str, Any]]:
    """Divergences (the filter re-initialised) and saturation (a sensor at its rail) → degraded."""
    evs = [e for e in (events or []) if isinstance(e, dict)]
    div = [e for e in evs if e.get("kind") == "divergence"]
    sat = [e for e in evs if e.get("kind") == "saturation"]
    out: list[tuple[str, str]] = []
    if div:
        last = div[-1]
        out.append(("degraded", f"the filter diverged {len(div)} time(s) and was re-initialised (last at "
                                f"t = {float(last.get('t', math.nan)):.1f} s: {last.get('detail', '')})"))
    if sat:
        sens = sorted({str(e.get("detail", "")).split(" ")[0] for e in sat})
        out.append(("degraded", f"{len(sat)} stretch(es) of {', '.join(sens)} readings at the sensor's rail "
                                "(saturation): those samples carry no calibration information"))
    return out, {"divergences": len(div), "saturation": len(sat)}


def mag_coverage(mag_cal: Any, cells: int = COVERAGE_CELLS) -> float:
    """Share of ``cells`` equal-area direction cells (Fibonacci centres, nearest-centre assignment) that hold
    at least :data:`COVERAGE_MIN_SAMPLES` of the calibrated magnetometer directions ``mag_cal`` (M, 3)."""
    m = np.asarray(mag_cal, float).reshape(-1, 3)
    n = np.linalg.norm(m, axis=1)
    m = m[np.isfinite(n) & (n > 0)]
    if m.shape[0] == 0:
        return 0.0
    u = m / np.linalg.norm(m, axis=1, keepdims=True)
    i = np.arange(cells) + 0.5
    z = 1.0 - 2.0 * i / cells
    r = np.sqrt(1.0 - z * z)
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    centres = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    k = np.argmax(u @ centres.T, axis=1)
    counts = np.bincount(k, minlength=cells)
    return float(np.mean(counts >= COVERAGE_MIN_SAMPLES))


def gravity_checks(cal: Calibration, raw: dict[str, Any] | RawDigest | None
                   ) -> tuple[list[tuple[str, str]], dict[str, Any]]:
    """At rest the calibrated specific force is gravity: (verdict, reason) when the median of |f| − g over
    the still blocks of ``raw`` (sensor → raw samples (N, 3), gyro and accel on one time base, or their
    :class:`RawDigest`) is beyond 5σ of what the accelerometer's σ allow along f, plus :data:`G_LOCAL_TOL`; and
    the figures. Nothing is judged without both sensors' calibration or with fewer than
    :data:`REST_MIN_BLOCKS` still blocks."""
    from .specs import G0

    fig: dict[str, Any] = {"rest_blocks": 0}
    d = _digest(raw)
    if d is None or cal.accel is None or cal.gyro is None or d.blocks < REST_MIN_BLOCKS:
        return [], fig
    (mw, cw), (ma, ca) = d.block_stats("gyro"), d.block_stats("accel")
    Mg, Ma = np.asarray(cal.gyro.matrix, float), np.asarray(cal.accel.matrix, float)
    with np.errstate(all="ignore"):
        # calibrated = M (raw − o) (eq. 1): block means map through it, per-axis variances are diag(M C Mᵀ)
        wm = (mw - np.asarray(cal.gyro.bias, float)) @ Mg.T
        fm = (ma - np.asarray(cal.accel.bias, float)) @ Ma.T
        ws = np.sqrt(np.maximum(np.einsum("ij,bjk,ik->bi", Mg, cw, Mg), 0.0))
        fs = np.sqrt(np.maximum(np.einsum("ij,bjk,ik->bi", Ma, ca, Ma), 0.0))
        still = (np.abs(wm) < REST_RATE).all(1) & (ws < REST_RATE).all(1) & (fs < REST_ACC).all(1)
    still &= np.isfinite(fm).all(1) & np.isfinite(wm).all(1) & np.isfinite(fs).all(1) & np.isfinite(ws).all(1)
    k = int(still.sum())
    fig["rest_blocks"] = k
    if k < REST_MIN_BLOCKS:
        return [], fig
    f = fm[still]  # (k, 3) m/s²
    dev = float(np.median(np.linalg.norm(f, axis=1) - G0))
    u = np.median(f / np.linalg.norm(f, axis=1, keepdims=True), axis=0)
    sig = cal.accel.sigma or {}
    sb = np.asarray(sig.get("bias", np.zeros(3)), float).reshape(3)
    ss = np.asarray(sig.get("scale", np.zeros(3)), float).reshape(3)
    sb, ss = np.where(np.isfinite(sb), sb, np.inf), np.where(np.isfinite(ss), ss, np.inf)
    # f_i = s_i (raw_i − o_i) along each axis (eqs. 1–2, small angles): δf_i = (f_i/s_i) δs_i − s_i δo_i,
    # independent; |f| moves by Σ u_i δf_i
    sc = np.abs(np.asarray(cal.accel.scale, float))
    s_f = float(np.sqrt(np.sum(u**2 * ((sc * sb) ** 2 + (G0 / sc * ss) ** 2))))
    tol = 5.0 * s_f + G_LOCAL_TOL
    fig.update({"norm_minus_g": dev, "sigma": s_f, "tolerance": tol})
    if abs(dev) > tol:
        return [("degraded", f"accel: at rest ({k} still blocks) the calibrated specific force is {dev:+.3g} m/s² "
                             f"from g (allowed {tol:.2g}: 5σ of the calibration along gravity + local gravity): "
                             "its bias or scale along gravity is off, and its σ are not to be trusted")], fig
    return [], fig


def _mag_fitted_here(cal: Calibration, observability: dict[str, Any] | None, mag_start: str | None = None,
                     events: Sequence[dict[str, Any]] = ()) -> bool:
    """Whether the magnetometer's bias or scale come from these samples, so that their coverage judges
    them: always for a batch result (no observability); for an online one only where the filter used the
    magnetometer and the data determined some mag bias or scale term (posterior σ < ½ prior σ). A cold
    flight whose mag was never calibrated keeps its prior (listed as undetermined), and a flight started
    from a bench file keeps the bench's mag: the flight's coverage says nothing about either (10-min
    multirotor and fixed-wing flights sweep 22–28 % of the directions)."""
    if not observability:
        return True
    if mag_start == "file" and not any(isinstance(e, dict) and e.get("kind") == "mag_cold_start" for e in events):
        # started from a calibration file fitted on other data (a bench session) and never re-fitted here:
        # the filter only refined it, and its σ are judged by the NIS (over 20 bench-started fixed-wing
        # flights the coverage rule called every one degraded, with every term within 3σ)
        return False
    online = cal.meta.get("online", {}) if isinstance(cal.meta, dict) else {}
    if isinstance(online, dict) and online.get("mag_used") is False:
        return False
    return any(isinstance(v, dict) and isinstance(v.get("ratio"), (int, float)) and v["ratio"] <= UNDETERMINED_RATIO
               for k, v in observability.items() if k.startswith(("mag.bias.", "mag.scale.")))


def _raw_coverage(mag: Any, mag_raw: Any) -> float | None:
    """:func:`mag_coverage` of the raw samples ``mag_raw`` (M, 3) calibrated by ``mag``; None when they
    cannot be (not a numeric (M, 3) array)."""
    try:
        return mag_coverage(mag.apply(np.asarray(mag_raw, float).reshape(-1, 3)))
    except (ValueError, TypeError):
        return None


def filter_start(cal: Calibration, mag_raw: Any = None) -> tuple[Calibration, list[str]]:
    """A batch result as the online filter's start (``replay --init batch``, the fleet): a magnetometer whose
    ellipsoid fit (eq. 17) saw under :data:`COVERAGE_MIN` of the field directions in ``mag_raw`` (M, 3) is
    left out, so that the filter starts the magnetometer cold (which waits for a 3-D sweep and otherwise
    keeps it undetermined, at its prior). Its σ understate the extrapolation error, and the filter would
    take them as a promise: on 10-min multirotor and fixed-wing flights (seeds 0–8), replays started from
    such a batch ended 8–332σ off on 17 of 18 (degraded by this module, but wrong); started without its
    mag, seeds 0–3 end ok with every determined term within 1σ (docs/json.md). This holds for the batch's
    prior-regularised fit too (:func:`mag_sigma_covers_extrapolation`): its σ are honest as marginal σ, but
    the filter takes a start's σ as a diagonal covariance, and the band's valley is a correlation (the
    centre along the unseen direction against the scale along it); handed over, the replays of
    multirotor/fixed-wing seeds 0–1 ended degraded with terms 4.5–16σ off (accel gate rejections 12–20 %),
    against ok and ≤ 0.6σ from the cold start (docs/json.md). Returns (start, warnings)."""
    if cal.mag is None or mag_raw is None or np.size(mag_raw) == 0:
        return cal, []
    cov = _raw_coverage(cal.mag, mag_raw)
    if cov is None or cov >= COVERAGE_MIN:
        return cal, []
    return cal.replace(mag=None), [
        f"mag: the batch's magnetometer fit saw only {100 * cov:.0f} % of the field directions (need "
        f"{100 * COVERAGE_MIN:.0f} %): the online filter starts the magnetometer cold instead of from it"]


def mag_sigma_covers_extrapolation(cal: Calibration, observability: dict[str, Any] | None = None) -> bool:
    """Whether the magnetometer's σ are those of the batch's prior-regularised ellipsoid fit
    (:func:`onlinecal.batch.ellipsoid.fit_norm_map`, ``meta.batch.steps.mag.figures.sigma_source`` =
    ``"soft-iron prior"``): σ that keep the prior's width along the directions a partial sweep did not see,
    so that a low coverage is not a fault of those σ. Only a batch result (no ``observability``) whose mag is
    that fit's."""
    if observability:
        return False
    meta = cal.meta if isinstance(cal.meta, dict) else {}
    try:
        figs = meta["batch"]["steps"]["mag"]["figures"]
    except (KeyError, TypeError):
        return False
    return isinstance(figs, dict) and figs.get("sigma_source") == "soft-iron prior" and bool(
        cal.mag is not None and cal.mag.sigma)


def motion_only_terms(online: Any) -> list[str]:
    """The terms an online result calls determined through motion alone (``meta.online.observability.caution``,
    :func:`onlinecal.ukf.vehicle.motion_only`): accelerometer biases and scales whose axis never rested up
    and down."""
    obs = online.get("observability") if isinstance(online, dict) else None
    rows = obs.get("caution") if isinstance(obs, dict) else None
    return sorted(str(r["term"]) for r in rows or [] if isinstance(r, dict) and "term" in r)


def undetermined_terms(cal: Calibration, observability: dict[str, Any] | None) -> list[str]:
    """Terms the data did not determine: posterior σ / prior σ > ½ (the filter's observability), or, with
    no observability, a term without σ of a sensor that has σ for others (the batch left it at its start
    value) and the batch's own list (``meta.batch.undetermined``: also axis terms such as
    ``mag.scale.z`` whose σ is the prior's, :func:`mag_sigma_covers_extrapolation`)."""
    if observability:
        return sorted(k for k, v in observability.items()
                      if isinstance(v, dict) and isinstance(v.get("ratio"), (int, float))
                      and math.isfinite(v["ratio"]) and v["ratio"] > UNDETERMINED_RATIO
                      and k.split(".")[0] in SENSORS and cal.sensor(k.split(".")[0]) is not None)
    out = []
    for s in SENSORS:
        c = cal.sensor(s)
        if c is None or not c.sigma:  # no σ at all (a truth or hand-written file): unknown, not undetermined
            continue
        for p in ("bias", "scale", "alpha", "xi"):
            sig = c.sigma.get(p)
            if sig is None or not np.all(np.isfinite(np.asarray(sig, float))):
                out.append(f"{s}.{p}")
    meta = cal.meta if isinstance(cal.meta, dict) else {}
    listed = meta.get("batch", {}).get("undetermined") if isinstance(meta.get("batch"), dict) else None
    for k in listed if isinstance(listed, list) else []:
        # an axis term (mag.scale.z) whose σ is kept (the prior's width) but not determined by the data
        if isinstance(k, str) and k.count(".") == 2 and k.split(".")[0] in SENSORS and k not in out \
                and k.rsplit(".", 1)[0] not in out and cal.sensor(k.split(".")[0]) is not None:
            out.append(k)
    return out


START_AGREEMENT_SIGMA = 5.0  # |online − start| / hypot(σ_online, σ_start) beyond this: the two disagree


def start_checks(cal: Calibration, start: Calibration | None, observability: dict[str, Any] | None,
                 same_data: bool) -> tuple[list[tuple[str, str]], list[dict[str, Any]]]:
    """The cross-check of an online result against the calibration it started from (the mission: the filter is
    initialised *and cross-checked* by the batch). A term that both give with σ, that the filter determined
    (observability ratio ≤ :data:`UNDETERMINED_RATIO`; an undetermined one is the start's value), and whose two
    values differ by more than :data:`START_AGREEMENT_SIGMA` combined σ is a contradiction: one of the two σ is a
    false promise. It degrades the result, and the words say which case: on the same logs (``same_data``: the batch
    of these logs) two fits of one data set disagree — MARG set 1, session 16: the batch's magnetometer bias σ
    (3e-4, from 6 744 samples as if independent) against a field that differs by place by 2 %; from a calibration
    of other data the sensor may have changed since, or either may be wrong. Returns (findings, the terms:
    ``term``, ``online``, ``start``, ``sigmas``)."""
    if start is None:
        return [], []
    out: list[dict[str, Any]] = []
    for s in SENSORS:
        a, b = cal.sensor(s), start.sensor(s)
        if a is None or b is None:
            continue
        pa, pb = a.params(), b.params()
        for p in PARAMS:
            sa, sb = a.sigma.get(p), b.sigma.get(p)
            if sa is None or sb is None:
                continue
            for i, ax in enumerate("xyz"):
                key = f"{s}.{p}.{ax}"
                ob = (observability or {}).get(key)
                if isinstance(ob, dict) and isinstance(ob.get("ratio"), (int, float)) \
                        and not ob["ratio"] <= UNDETERMINED_RATIO:
                    continue
                d = float(pa[p][i] - pb[p][i])
                sig = math.hypot(float(np.asarray(sa)[i]), float(np.asarray(sb)[i]))
                if sig > 0 and math.isfinite(d) and abs(d) > START_AGREEMENT_SIGMA * sig:
                    out.append({"term": key, "online": float(pa[p][i]), "start": float(pb[p][i]),
                                "sigmas": abs(d) / sig})
    if not out:
        return [], []
    out.sort(key=lambda r: -r["sigmas"])
    words = ", ".join(f"{r['term']} {r['online']:+.4g} against {r['start']:+.4g} ({r['sigmas']:.0f}σ)" for r in out[:6])
    words += f" and {len(out) - 6} more" if len(out) > 6 else ""
    if same_data:
        return [("degraded", f"the online result contradicts the batch it started from, on the same logs, beyond "
                             f"both σ: {words}: at least one of the two σ is a false promise; check both out of fit "
                             "(turn angles, attitude closure) before using either")], out
    return [("degraded", f"the online result moved from its start calibration beyond both σ: {words}: the sensor "
                         "changed since, or one of the two is wrong")], out


def assess(cal: Calibration, *, nis: dict[str, Any] | None = None, events: Sequence[dict[str, Any]] | None = None,
           observability: dict[str, Any] | None = None, mag_raw: Any = None,
           raw: dict[str, Any] | RawDigest | None = None, warnings: Sequence[str] = (),
           mag_start: str | None = None, start: Calibration | None = None) -> dict[str, Any]:
    """The health verdict of ``cal`` (see the module doc).

    ``nis`` and ``events`` default to ``cal.meta["online"]`` (an online result); ``observability``: the filter's
    per-term posterior/prior σ ratio; ``mag_raw`` (M, 3): the raw magnetometer samples the result was fitted on, for
    the coverage check; ``raw``: sensor → raw samples (N, 3), or their :class:`RawDigest`, for the rail and gravity
    checks (:func:`rail_checks`, :func:`gravity_checks`); ``warnings``: the fit's own warnings (kept as notes);
    ``mag_start``: where an online result's magnetometer started, ``"file"`` (a calibration fitted on other data:
    the coverage of these samples does not judge it unless the filter re-fitted it cold), ``"batch"`` (fitted on
    these samples) or None (unknown: judged as fitted here); ``start``: the calibration an online result started
    from, for the cross-check (:func:`start_checks`; its data the same logs where ``mag_start`` is "batch").
    Returns ``{"schema", "verdict", "reasons", "notes", "checks"}``.
    """
    online = cal.meta.get("online", {}) if isinstance(cal.meta, dict) else {}
    if nis is None and isinstance(online, dict):
        nis = online.get("nis")
    if events is None and isinstance(online, dict):
        events = online.get("events")
    found: list[tuple[str, str]] = []
    checks: dict[str, Any] = {}
    notes: list[str] = []
    ranges = range_checks(cal)
    found += ranges
    checks["ranges"] = [r for _, r in ranges]
    nf, checks["nis"] = nis_checks(nis)
    found += nf
    for s, f in checks["nis"].items():
        if f.get("status") == HELD_STATUS:
            notes.append(f"{s}: mean NIS {f['mean']:.3g} below [{f['band'][0]:g}, {f['band'][1]:g}] with its soft "
                         "iron (scales, axis angles) held at the start's σ in most of its updates (in flight: "
                         "docs/flight.md): the start is better than its σ says, which the NIS cannot tell from "
                         "overstated noise; not counted against the verdict")
    ef, ev = event_checks(events)
    found += ef
    checks.update(ev)
    raw = _digest(raw)  # once, for both checks
    gf, checks["gravity_at_rest"] = gravity_checks(cal, raw)
    found += gf
    rf, rails = rail_checks(raw)
    if not ev.get("saturation"):  # the filter's own saturation event already says it
        found += rf
    checks["rail_samples"] = rails
    if mag_raw is not None and cal.mag is not None and _mag_fitted_here(cal, observability, mag_start, events or ()):
        cov = _raw_coverage(cal.mag, mag_raw)
        checks["mag_coverage"] = cov
        if cov is not None and cov < COVERAGE_MIN:
            if mag_sigma_covers_extrapolation(cal, observability):
                notes.append(f"mag: the samples point in only {100 * cov:.0f} % of directions: the ellipsoid (eq. 17) "
                             "is extrapolated with a prior on the soft iron, and its σ keep the prior's width along "
                             "the unseen directions (terms the data did not determine are listed)")
            else:
                found.append(("degraded", f"mag: the samples point in only {100 * cov:.0f} % of directions (need "
                                          f"{100 * COVERAGE_MIN:.0f} %): the ellipsoid fit (eq. 17) extrapolates and "
                                          "its bias and scales can be off by far more than their σ"))
    sf, agreement = start_checks(cal, start, observability, mag_start == "batch")
    found += sf
    if start is not None:
        checks["start_agreement"] = agreement
    und = undetermined_terms(cal, observability)
    checks["undetermined"] = und
    if und:
        notes.append("not determined by the data (start value kept, σ wide): " + ", ".join(und))
    caution = motion_only_terms(online)
    checks["motion_only"] = caution
    if caution:
        notes.append("determined through motion alone, on the assumption that the motion carried no linear "
                     "acceleration (no rest with the axis up and with it down; a hand or a vehicle breaks it, "
                     "and `export` leaves these out): " + ", ".join(caution))
    notes += [w for w in warnings if w not in notes]
    verdict = "ok"
    for v, _ in found:
        verdict = _worst(verdict, v)
    return {"schema": HEALTH_SCHEMA, "verdict": verdict, "reasons": [r for _, r in found], "notes": notes,
            "checks": checks}


def combine(verdicts: Iterable[dict[str, Any] | None]) -> str:
    """The worst verdict of several (a missing one counts as ok)."""
    out = "ok"
    for h in verdicts:
        if h:
            out = _worst(out, str(h.get("verdict", "ok")))
    return out


def exit_status(health: dict[str, Any] | None) -> int:
    """0 ok, 4 degraded, 5 failed (:data:`EXIT_STATUS`)."""
    return EXIT_STATUS.get(str((health or {}).get("verdict", "ok")), 0)


def summary_lines(health: dict[str, Any], what: str = "result") -> list[str]:
    """Lines for the terminal: ``health: degraded`` then one line per reason (and per note, indented)."""
    lines = [f"health of the {what}: {health['verdict']}"]
    lines += [f"  - {r}" for r in health.get("reasons", [])]
    return lines
