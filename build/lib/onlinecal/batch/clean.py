"""Impossible samples and noise bursts, found before the batch fits (issue 16).

A log can hold a corrupt sample (a bit flip gives 1e6 rad/s), a handful of wild readings, or a few
seconds of a sensor gone noisy. One such sample moves a least-squares fit by far more than its σ; a
rate spike integrated over a rotation phase moves the gyro scale (eq. 36) by ``spike · dt / angle``.

* **Impossible**: beyond any sensor's range (|ω| > 70 rad/s = 4000°/s; ‖a‖ > 50 g) or far from its
  neighbours — a sample that differs from the median of its ±2 neighbours by more than 12 × the log's
  robust scale of that same difference *and* by more than a physical floor (2 rad/s, 20 m/s²; the mag
  0.3 × its median norm), while its neighbours agree with each other, is a spike, not motion: motion
  (and an impact) moves the neighbours too.
  Such IMU samples are replaced by the mean of their good neighbours (so the time grid and the
  integral of eq. 36 stay continuous); such mag samples are dropped.
* **Noise burst**: a stretch where the gyro's third difference (which removes any smooth motion) has an
  RMS over 0.5 s more than 6 × the log's median and 2.5 × the first difference's (white noise: 3.2,
  not a hand's jerk) for at least 0.5 s (an impact rings for less); eq. 36 skips motions and phases
  that overlap one.

Each is counted in a warning naming the file.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from ..io.base import ImuData

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

GYRO_LIMIT = 70.0  # rad/s: 4000 °/s, beyond the widest MEMS gyro range
ACC_LIMIT = 50 * 9.80665  # m/s²


@dataclass
class Cleaned:
    """The cleaned log, the rows changed, and the noisy IMU stretches [i0, i1)."""

    data: ImuData
    imu_replaced: int = 0
    mag_dropped: int = 0
    bursts: list[tuple[int, int]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def _median5(x: Array, block: int = 1 << 15) -> Array:
    """Median of each sample's ±2 neighbours, itself excluded: (N, 3) → (N, 3). In blocks of ``block`` rows
    (the same values; the (N, 4, 3) gather and its sorted copy no longer grow with the log: issue 16.5)."""
    n = x.shape[0]
    out = np.empty(x.shape)
    for b0 in range(0, n, block):
        idx = np.clip(np.arange(b0, min(n, b0 + block))[:, None] + np.array([-2, -1, 1, 2]), 0, n - 1)
        s = np.sort(x[idx], axis=1)
        out[b0:b0 + block] = 0.5 * (s[:, 1] + s[:, 2])  # the median of four
    return out


def _spikes(x: Array, floor: float) -> BoolArray:
    """Rows of x (N, 3) that stand alone: far from their neighbours' median beyond noise and floor, while
    the neighbours either side agree with each other five times better (an impact or a jerk moves the
    neighbours too; a corrupt sample does not)."""
    n = x.shape[0]
    if n < 8:
        return np.zeros(n, bool)
    d = np.linalg.norm(x - _median5(x), axis=1)
    scale = 1.4826 * np.median(d) + 1e-12
    i = np.arange(n)
    nb = np.linalg.norm(x[np.clip(i - 1, 0, n - 1)] - x[np.clip(i + 1, 0, n - 1)], axis=1)
    return (d > 12 * scale) & (d > floor) & (d > 5 * nb)


def _fill(x: Array, bad: BoolArray) -> Array:
    """x with the bad rows replaced by linear interpolation over the good ones (per column)."""
    if not bad.any() or bad.all():
        return x
    i = np.arange(x.shape[0])
    out = x.copy()
    for k in range(x.shape[1]):
        out[bad, k] = np.interp(i[bad], i[~bad], x[~bad, k])
    return out


def noise_bursts(gyro: Array, rate: float, window_s: float = 0.5, factor: float = 6.0) -> list[tuple[int, int]]:
    """IMU rows [i0, i1) where the gyro is noisy: its third-difference RMS over ``window_s`` exceeds
    ``factor`` × the log's median, *and* is more than 2.5 × its first-difference RMS there.

    White noise of σ has third differences of RMS √20 σ and first differences √2 σ (ratio 3.2); motion,
    even a hand's jerk, lives below ~10 Hz, where at 100 Hz the ratio is below 0.4. The ratio keeps
    fast hand-held turns from counting as noise; the factor keeps the sensor's own noise from it.
    """
    n = gyro.shape[0]
    if n < 40 or not np.isfinite(rate):
        return []
    w = max(5, int(round(window_s * rate)))
    lo = np.clip(np.arange(n) - w // 2, 0, n - w)

    def wrms(k: int) -> Array:
        dk = np.zeros(n)
        dk[k:] = np.sum(np.diff(gyro, k, axis=0) ** 2, axis=1)
        c = np.cumsum(np.concatenate([[0.0], dk]))
        return np.sqrt((c[lo + w] - c[lo]) / w)

    r3, r1 = wrms(3), wrms(1)
    ref = float(np.median(r3))
    if ref <= 0:
        return []
    mask = (r3 > factor * ref) & (r3 > 2.5 * r1)
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    dm = np.diff(m)
    # at least a window long: an impact (a unit put down on a table) rings for less
    return [(int(a), int(b)) for a, b in zip(np.flatnonzero(dm == 1), np.flatnonzero(dm == -1), strict=True)
            if b - a >= w]


def clean_log(d: ImuData) -> Cleaned:
    """Replace impossible IMU samples, drop impossible mag samples, find gyro noise bursts (see module)."""
    warnings: list[str] = []
    gyro, acc, mag, t_mag = d.gyro, d.acc, d.mag, d.t_mag
    bad_g = ~np.all(np.isfinite(gyro), axis=1) | (np.abs(gyro).max(axis=1, initial=0) > GYRO_LIMIT)
    bad_a = ~np.all(np.isfinite(acc), axis=1) | (np.linalg.norm(acc, axis=1) > ACC_LIMIT)
    # Spikes are judged against neighbours that are themselves possible.
    g_ok = _fill(np.nan_to_num(gyro, posinf=0, neginf=0), bad_g)
    a_ok = _fill(np.nan_to_num(acc, posinf=0, neginf=0), bad_a)
    bursts = noise_bursts(g_ok, d.imu_rate) if d.imu_rate >= 20 else []
    in_burst = np.zeros(d.n_imu, bool)
    for a, b in bursts:
        in_burst[max(0, a - 3):b + 3] = True
    if d.imu_rate >= 20:  # below, neighbours are too far apart in time to vouch for each other
        # (inside a noise burst every sample stands alone: that is the burst, handled below)
        # floors above any hand's or impact's sample-to-sample change (the Ferraris session's table
        # knocks reach 0.6 rad/s and 6 m/s² in one sample)
        bad_g |= _spikes(g_ok, 2.0) & ~in_burst
        bad_a |= _spikes(a_ok, 20.0) & ~in_burst
    n_imu = int((bad_g | bad_a).sum())
    if n_imu:
        gyro = _fill(g_ok, bad_g)
        acc = _fill(a_ok, bad_a)
        warnings.append(f"{d.source}: {int(bad_g.sum())} gyro and {int(bad_a.sum())} accel samples beyond the "
                        "sensor's range or standing alone far from their neighbours (corrupt readings) "
                        "replaced by their neighbours' mean")
    n_mag = 0
    if d.n_mag >= 8:
        finite = np.all(np.isfinite(mag), axis=1)
        med = float(np.median(np.linalg.norm(mag[finite], axis=1))) if finite.any() else 0.0
        nrm = np.linalg.norm(np.nan_to_num(mag), axis=1)
        bad_m = ~finite | (nrm > 10 * med) | (nrm < 0.1 * med)
        mag_rate = (d.n_mag - 1) / max(float(t_mag[-1] - t_mag[0]), 1e-9)
        if mag_rate >= 20:
            bad_m |= _spikes(_fill(np.nan_to_num(mag), bad_m), 0.3 * med)
        n_mag = int(bad_m.sum())
        if n_mag:
            mag, t_mag = mag[~bad_m], t_mag[~bad_m]
            warnings.append(f"{d.source}: {n_mag} magnetometer samples far from any plausible field or from "
                            "their neighbours (corrupt readings) dropped")
    if bursts:
        t = d.t_imu
        tot = sum(t[min(b, d.n_imu - 1)] - t[a] for a, b in bursts)
        warnings.append(f"{d.source}: gyro noise bursts (white noise > 6× the log's median) in "
                        f"{len(bursts)} stretch{'es' if len(bursts) > 1 else ''}, {tot:.1f} s in all; "
                        "motions that overlap them are not used for the gyro scale")
    data = replace(d, gyro=gyro, acc=acc, t_mag=t_mag, mag=mag) if (n_imu or n_mag) else d
    return Cleaned(data, n_imu, n_mag, bursts, warnings)
