"""Automatic segmentation: static intervals, motion segments between them, and rotation phases.

Nobody marks sections by hand. Thresholds come from the data itself: the noise floor is the low
percentile of the windowed standard deviation, so the same code serves a quiet platform and a
hand-held recording.

A *static interval* is a stretch where gyro and accel vary no more than their noise and the gyro
stays near its bias (this excludes constant-rate turns about the vertical, which are quiet too).
A *motion segment* is what lies between two static intervals. A *rotation phase* (paper Sec. III) is a
motion segment whose body rate keeps one direction close to a sensor axis and turns by at least half
a revolution.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..io.base import ImuData

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class Interval:
    """IMU sample rows [i0, i1) and their times."""

    i0: int
    i1: int
    t0: float
    t1: float

    @property
    def n(self) -> int:
        return self.i1 - self.i0

    @property
    def duration(self) -> float:
        return self.t1 - self.t0


@dataclass(frozen=True)
class Phase(Interval):
    """A rotation phase about sensor axis ``axis`` (0, 1, 2); ``sign`` +1/−1 is the turn direction
    in the raw gyro; ``direction`` (3,) the unit raw-rate direction; ``linearity`` the share of the
    rate energy along it; ``angle`` the raw integrated angle along it (rad, uncalibrated)."""

    axis: int = 0
    sign: int = 1
    direction: Array = field(default_factory=lambda: np.zeros(3))
    linearity: float = 0.0
    angle: float = 0.0


@dataclass
class Segmentation:
    """Result for one log: statics, motions (between consecutive statics), phases (a subset of motions)."""

    data: ImuData
    statics: list[Interval]
    motions: list[Interval]
    phases: list[Phase]
    gyro_noise: float
    acc_noise: float
    bias_guess: Array
    max_gap: float
    warnings: list[str] = field(default_factory=list)
    bias_rests: list[Interval] | None = None  # strict rests for the gyro bias when statics are relaxed
    bursts: list[tuple[int, int]] = field(default_factory=list)  # gyro noise bursts, IMU rows [i0, i1)

    @property
    def rests(self) -> list[Interval]:
        """True rests (for the gyro bias): the strict statics even when ``statics`` are quasi-static."""
        return self.statics if self.bias_rests is None else self.bias_rests

    def noisy(self, iv: Interval) -> bool:
        """True where a gyro noise burst (:func:`~onlinecal.batch.clean.noise_bursts`) overlaps ``iv``."""
        return any(a < iv.i1 and b > iv.i0 for a, b in self.bursts)

    def gapped(self, iv: Interval, factor: float = 5.0) -> bool:
        """True where the logger dropped samples inside ``iv`` (a gap > factor × median period)."""
        t = self.data.t_imu[iv.i0 : iv.i1]
        if t.size < 2:
            return True
        return bool(np.diff(t).max() > factor * self.max_gap)


def _moving_std_rows(x: Array, w: int, b0: int, b1: int) -> tuple[Array, Array]:
    """Rows b0:b1 of :func:`moving_std` (w already within [2, N]), from cumsums over only the samples
    those rows' windows reach."""
    n, k = x.shape
    lo = np.clip(np.arange(b0, b1) - w // 2, 0, n - w)
    s0, s1 = int(lo[0]), int(lo[-1]) + w
    # Shifted by the stretch's mean: the variance E[x²] − E[x]² then cancels no large offset (gravity,
    # a hard-iron field) and the cumsums stay small.
    ref = np.mean(x[s0:s1], axis=0)
    xs = np.asarray(x[s0:s1], np.float64) - ref
    c1 = np.zeros((s1 - s0 + 1, k))
    c2 = np.zeros((s1 - s0 + 1, k))
    np.cumsum(xs, axis=0, out=c1[1:])
    np.cumsum(xs * xs, axis=0, out=c2[1:])
    j = lo - s0
    m = (c1[j + w] - c1[j]) / w
    return m + ref, np.sqrt(np.maximum((c2[j + w] - c2[j]) / w - m**2, 0.0))


def moving_std(x: Array, w: int, block: int = 1 << 15) -> tuple[Array, Array]:
    """Centered moving mean and std over windows of w samples, (N, k) → (N, k) each, via cumsums.

    Worked in blocks of ``block`` output rows, each with its own cumsums over the samples its windows
    need: the temporaries stay bounded for any log length (before: seven (N, k) arrays at once), and the
    sums never run over the whole log (no loss of precision in ``c2[b] - c2[a]`` on an hour-long log)."""
    n, k = x.shape
    w = max(2, min(w, n))
    mean = np.empty((n, k))
    sd = np.empty((n, k))
    for b0 in range(0, n, block):
        b1 = min(n, b0 + block)
        mean[b0:b1], sd[b0:b1] = _moving_std_rows(x, w, b0, b1)
    return mean, sd


def _runs(mask: Array) -> list[tuple[int, int]]:
    """[start, stop) of each run of True."""
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    d = np.diff(m)
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True))


WINDOW_S = 0.5


def _window_std(data: ImuData, window_s: float, block: int = 1 << 15) -> tuple[Array, Array, Array]:
    """Moving gyro mean (N, 3) rad/s and the moving std summed over axes (norm) of the gyro (N,) rad/s and
    the accel (N,) m/s², over ``window_s``; ``block`` rows at a time, so that only these outputs grow with
    the log (issue 16.5)."""
    n = data.n_imu
    w = max(2, min(max(5, int(round(window_s * data.imu_rate))), n))
    gm = np.empty((n, 3))
    gs = np.empty(n)
    as_ = np.empty(n)
    for b0 in range(0, n, block):
        b1 = min(n, b0 + block)
        gm[b0:b1], sd = _moving_std_rows(data.gyro, w, b0, b1)
        gs[b0:b1] = np.linalg.norm(sd, axis=1)
        as_[b0:b1] = np.linalg.norm(_moving_std_rows(data.acc, w, b0, b1)[1], axis=1)
    return gm, gs, as_


def noise_floors(logs: list[ImuData], window_s: float = WINDOW_S) -> tuple[float, float]:
    """Windowed-std noise floors (gyro rad/s, accel m/s², summed over axes) of one sensor unit.

    The 5th percentile of the windowed std of every log, and the smallest over logs: a log that
    hardly rests (a hand-held turn) would otherwise take its motion for noise. Absolute floors keep a
    quantised, noiseless signal usable.
    """
    g, a = [], []
    for d in logs:
        if d.n_imu >= 10:
            _, gs, as_ = _window_std(d, window_s)
            g.append(np.percentile(gs, 5))
            a.append(np.percentile(as_, 5))
    return max(min(g, default=0.0), 2e-4), max(min(a, default=0.0), 2e-3)


STILL_GYRO_CAP = 0.03  # rad/s, windowed std summed over axes
STILL_ACC_CAP = 0.3  # m/s²


def _powered(data: ImuData) -> BoolArray:
    """(N,) True at IMU samples where the log says the vehicle is armed or its throttle is above 5 %.

    Uses optional series on the log data when a reader provides them (``t_armed``/``armed``,
    ``t_throttle``/``throttle`` in 0–1 or 0–100 %), each held from one record to the next; all False
    without them. A powered vehicle is not at rest, however still its IMU looks."""
    out = np.zeros(data.n_imu, bool)
    for tn, vn, lim in (("t_armed", "armed", 0.5), ("t_throttle", "throttle", None)):
        t, v = getattr(data, tn, None), getattr(data, vn, None)
        if t is None or v is None or len(t) == 0 or data.n_imu == 0:
            continue
        t, v = np.asarray(t, float), np.asarray(v, float)
        if lim is None:
            lim = 5.0 if np.nanmax(v) > 1.5 else 0.05  # percent or fraction
        j = np.clip(np.searchsorted(t, data.t_imu, side="right") - 1, 0, t.size - 1)
        out |= (v[j] > lim) & (data.t_imu >= t[0])
    return out


def find_statics(
    data: ImuData,
    floors: tuple[float, float] | None = None,
    window_s: float = WINDOW_S,
    min_duration_s: float = 1.0,
    margin_s: float = 0.15,
    relaxed: bool = False,
) -> tuple[list[Interval], float, float, Array]:
    """Static intervals of one log. Returns (intervals, gyro noise σ, accel noise σ, bias guess).

    ``floors``: the unit's (gyro, accel) windowed-std floors from :func:`noise_floors`; by default
    this log's own. ``relaxed``: quasi-static instead — a hand that holds still: accel std below
    0.25 m/s² (gravity direction good to ~1.5°) and mean rate within 0.1 rad/s of the bias, for 0.5 s.
    """
    n = data.n_imu
    if n < 10:
        return [], float("nan"), float("nan"), np.zeros(3)
    rate = data.imu_rate
    gm, g_std, a_std = _window_std(data, window_s)
    g_floor, a_floor = floors if floors is not None else noise_floors([data], window_s)
    # Absolute caps as well as the floors: a log that never rests (a flight) has its vibration as its
    # own floor, and a hover would pass a floor-relative test. No calibration rest shakes more than
    # 0.3 m/s² or 0.03 rad/s (summed windowed std); rotor vibration on a healthy frame is several m/s².
    quiet = ((g_std < 4 * g_floor + 2e-3) & (a_std < 4 * a_floor + 0.02)
             & (g_std < STILL_GYRO_CAP) & (a_std < STILL_ACC_CAP) & ~_powered(data))
    if not quiet.any():
        return [], g_floor, a_floor, np.zeros(3)
    bias = np.median(data.gyro[quiet], axis=0)
    # A constant-rate turn is quiet but not at rest: require the mean rate near the bias too.
    rate_dev = np.linalg.norm(gm - bias, axis=1)
    still = quiet & (rate_dev < max(0.02, 8 * g_floor))
    if relaxed:
        still = (a_std < max(0.25, 4 * a_floor + 0.02)) & (rate_dev < 0.1) & (a_std < STILL_ACC_CAP) & ~_powered(data)
        min_duration_s = min(min_duration_s, 0.5)
    margin = int(round(margin_s * rate))
    out: list[Interval] = []
    t = data.t_imu
    for i0, i1 in _runs(still):
        i0, i1 = i0 + margin, i1 - margin
        if i1 - i0 < 3:
            continue
        # A logger gap inside a rest does not break it, but a rest must span real time.
        if t[i1 - 1] - t[i0] < min_duration_s:
            continue
        out.append(Interval(int(i0), int(i1), float(t[i0]), float(t[i1 - 1])))
    if out:
        sel = np.concatenate([np.arange(s.i0, s.i1) for s in out])
        bias = np.median(data.gyro[sel], axis=0)
    return out, float(g_floor / np.sqrt(3)), float(a_floor / np.sqrt(3)), bias


def classify_phase(
    data: ImuData,
    iv: Interval,
    bias: Array,
    min_linearity: float = 0.95,
    max_axis_angle_deg: float = 25.0,
    min_turn_rad: float = np.pi,
) -> Phase | None:
    """A motion segment is a rotation phase if its rate keeps one direction near a sensor axis."""
    w = data.gyro[iv.i0 : iv.i1] - bias
    t = data.t_imu[iv.i0 : iv.i1]
    if w.shape[0] < 10:
        return None
    dt = np.diff(t)
    wm = 0.5 * (w[1:] + w[:-1]) * dt[:, None]  # per-step angle increments
    _, s, Vt = np.linalg.svd(wm, full_matrices=False)
    u = Vt[0]
    energy = s**2
    lin = float(energy[0] / energy.sum()) if energy.sum() > 0 else 0.0
    k = int(np.argmax(np.abs(u)))
    if u[k] < 0:
        u = -u
    ang = float((wm @ u).sum())
    if lin < min_linearity or abs(u[k]) < np.cos(np.radians(max_axis_angle_deg)) or abs(ang) < min_turn_rad:
        return None
    return Phase(iv.i0, iv.i1, iv.t0, iv.t1, axis=k, sign=1 if ang > 0 else -1, direction=u,
                 linearity=lin, angle=ang)


def consensus_phases(phases: list[Phase], max_deg: float = 3.0) -> list[Phase]:
    """Keep, per axis, the phases whose raw rate direction agrees with the majority.

    A transition between two attitudes can be nearly a one-axis turn; taken for a phase it would tilt
    the alignment of eqs. 25–27. True phases about one axis agree to the noise; the medoid direction
    (most turn angle within ``max_deg``) wins, the rest are dropped.
    """
    out: list[Phase] = []
    cos_lim = np.cos(np.radians(max_deg))
    for k in range(3):
        ph = [p for p in phases if p.axis == k]
        if len(ph) <= 1:
            out += ph
            continue
        U = np.array([p.direction for p in ph])
        w = np.array([abs(p.angle) for p in ph])
        close = (U @ U.T) >= cos_lim
        best = int(np.argmax(close @ w))
        out += [p for p, c in zip(ph, close[best], strict=True) if c]
    return sorted(out, key=lambda p: p.i0)


def segment(data: ImuData, floors: tuple[float, float] | None = None, relaxed: bool = False,
            bias: Array | None = None) -> Segmentation:
    """Segment one log into statics, motions and rotation phases (no hand marking).

    ``relaxed`` segments at quasi-static rests (see :func:`find_statics`); ``bias`` overrides the
    log's own rest-based gyro bias guess (a log that never rests has none).
    """
    statics, g_noise, a_noise, own_bias = find_statics(data, floors, relaxed=relaxed)
    bias = own_bias if bias is None else bias
    warnings: list[str] = []
    motions: list[Interval] = []
    t = data.t_imu
    for a, b in zip(statics[:-1], statics[1:], strict=True):
        # The motion runs from the last rest sample to the first of the next rest, so that its
        # integral covers the whole turn.
        i0, i1 = a.i1 - 1, b.i0 + 1
        motions.append(Interval(i0, i1, float(t[i0]), float(t[i1 - 1])))
    candidates = list(motions)
    if not statics and data.n_imu > 10:
        # A log that never rests may still be one turn (a hand-held "rotate 360°" recording): its
        # samples serve the alignment of eqs. 25–27, though without rests it cannot give an angle.
        candidates.append(Interval(0, data.n_imu, float(t[0]), float(t[-1])))
    phases = consensus_phases([p for p in (classify_phase(data, m, bias) for m in candidates) if p is not None])
    med = 1.0 / data.imu_rate if data.n_imu > 1 else float("nan")
    if not statics:
        warnings.append(f"{data.source}: no static interval found")
    seg = Segmentation(data, statics, motions, phases, g_noise, a_noise, bias, med, warnings)
    return seg
