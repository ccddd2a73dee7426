"""Magnetic disturbances in the online filter (issue 16, item 3): a stretch whose field disagrees with the
field model is excluded from the magnetometer update and reported.

A motor, a steel beam or a passing car adds a field that the paper's model (eq. 17: the calibrated field
has norm 1 and a fixed dip against gravity) has no term for. Before, the mag gate was soft (R inflated to
the gate's size, never dropped): a 30 s disturbance of 0.5 G gave some 300 gate-sized updates, enough to
drag the magnetometer terms, the heading and (through the heading) the gyro terms away; 8 of 20 runs
ended 9–266σ off. :class:`MagDisturbanceGate` judges every filter block's mean field before the update:

* **norm**: | ‖h‖ − 1 | of the calibrated block-mean field h against ``max(NORM_MIN, NORM_K · σ_‖h‖)``,
  σ_‖h‖ the norm's 1σ from the state's magnetometer bias and scale σ (:func:`norm_sigma`: a mag whose
  calibration is still loose is given room, a tight one is judged tightly);
* **direction**: in a quasi-static block (the block-mean specific force within ``STATIC_G`` of g, so it is
  gravity) the dip, the angle of h below the horizontal, against the dip state, beyond
  ``max(DIP_MIN_DEG, DIP_K · σ_dip)`` — a disturbance can leave the norm near 1 at some attitudes (the added
  field at about 120° to the earth's), never the dip as well at every attitude.

Either enters a disturbance; it ends only after ``CLEAR_S`` s of log time in which neither test fired
(hysteresis: inside a disturbance the norm passes through 1 as the body turns, and those blocks are as
wrong as the others). While it lasts the magnetometer is not used (the gyro carries the heading).

A disturbance is a *change* from a field that agreed with a filter in order: the gate is armed only after
``CLEAR_S`` s of agreement and while the latest NIS window of both the accelerometer and the magnetometer
is in order (:func:`nis_in_order`; a window mean within ``NIS_ORDER`` × the band's top). A magnetometer
whose calibration never agreed (a wrong start), or a filter whose state is going wrong (a wrong gyro scale
bends the magnetometer terms before the NIS declares a divergence), is left to the filter's NIS and its
divergence restart (:mod:`.divergence`) instead of being silenced with its wrong terms and small σ.
For the same reason a disagreement that lasts beyond ``MAX_S`` s (a lasting change: the unit moved near
iron, a magnetometer re-mounted) ends the exclusion: the magnetometer is used again, and the gate re-arms
once the field agrees again (after the filter has re-learned it). Each stretch is one ``mag_disturbance``
event at its start and one at its end (with its span and the blocks left out; the events go into the
result's ``meta.events``) and one warning (the command line's stderr line).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .layout import DIP, SENSOR_SLICE, correction

Array = NDArray[np.float64]

NORM_MIN = 0.15  # relative field norm: the least deviation that counts (a drifting calibration is the filter's)
NORM_K = 5.0  # × σ of the norm the calibration's uncertainty allows
DIP_MIN_DEG = 10.0  # deg: the least dip deviation that counts
DIP_K = 4.0  # × σ of the dip state
STATIC_G = 0.02  # a block whose mean specific force is within 2 % of g: quasi-static, the accel is gravity
CLEAR_S = 3.0  # s of agreement that end a disturbance (and that arm the gate)
NIS_ORDER = 2.0  # × the NIS band's top: the latest window of each sensor at most this for the gate to arm
MAX_S = 45.0  # s: a disagreement lasting longer is no passing disturbance; the mag is used (and judged) again


class MagDisturbanceWarning(UserWarning):
    """A stretch of magnetometer data disagreed with the field model and was left out."""


def norm_sigma(x: Array, sig: Array, h: Array) -> float:
    """1σ of the calibrated field's norm ‖h‖ (relative to the unit field) from the magnetometer's bias σ
    (raw unit) and scale σ in the state (x, sig (n,)), at the calibrated field h (3,): to first order
    δ‖h‖ = ĥ·(M δ(m − o)) with M ≈ diag(scale) (eq. 17's dominant terms; alpha and xi turn the field and
    change its norm only to second order)."""
    sl = SENSOR_SLICE["mag"]
    s = x[sl][3:6]
    u = h / max(float(np.linalg.norm(h)), 1e-12)
    var = np.sum((u * s * sig[sl][:3]) ** 2) + np.sum((u * h * sig[sl][3:6] / np.where(s != 0, s, 1.0)) ** 2)
    return float(math.sqrt(var))


def nis_in_order(stats: dict[str, dict[str, Any]], band_hi: float) -> bool:
    """Whether the filter is in order: the latest NIS window ([t, mean] in ``stats[s]["windows"]``, the
    filter's :class:`.health.NisMonitor` bookkeeping) of the accel and of the mag exists and its mean is at
    most ``NIS_ORDER`` × ``band_hi``. (While a disturbance is left out the mag adds no NIS: its last
    window stays the one from before.)"""
    for s in ("accel", "mag"):
        w = stats.get(s, {}).get("windows") or []
        if not w or not float(w[-1][1]) <= NIS_ORDER * band_hi:
            return False
    return True


def calibrated(x: Array, sensor: str, raw_mean: Array) -> Array:
    """The block-mean raw reading (3,) calibrated with the state's estimate (eq. 1: M (raw − o))."""
    o, M = correction(x[None, SENSOR_SLICE[sensor]])
    out: Array = M[0] @ (raw_mean - o[0])
    return out


def calibrated_floats(p: list[float], raw: list[float]) -> tuple[float, float, float]:
    """:func:`calibrated` on Python floats: p the sensor's 12 terms (o, s, alpha, xi), raw (3,) a block
    mean; M (raw − o) with M = S T_R(alpha) T_N(xi) (eqs. 1–6, :func:`onlinecal.model.model_matrices`'s
    closed forms), applied as T_N, then T_R, then S."""
    v0, v1, v2 = raw[0] - p[0], raw[1] - p[1], raw[2] - p[2]
    cf, sf, ct, st = math.cos(p[6]), math.sin(p[6]), math.cos(p[7]), math.sin(p[7])
    cp, sp = math.cos(p[8]), math.sin(p[8])
    sx, sy, sz = math.sin(p[9]), math.sin(p[10]), math.sin(p[11])
    cx, cy, cz = math.cos(p[9]), math.cos(p[10]), math.cos(p[11])
    b, c, d, e, f = sz, cz, -sy, sx * cy, cx * cy
    # T_N = A⁻¹, lower triangular (eq. 6)
    w0 = v0
    w1 = -b / c * v0 + v1 / c
    w2 = (b * e - c * d) / (c * f) * v0 - e / (c * f) * v1 + v2 / f
    # T_R = Rz Ry Rx (eqs. 3–4)
    r0 = cp * ct * w0 + (cp * st * sf - sp * cf) * w1 + (cp * st * cf + sp * sf) * w2
    r1 = sp * ct * w0 + (sp * st * sf + cp * cf) * w1 + (sp * st * cf - cp * sf) * w2
    r2 = -st * w0 + ct * sf * w1 + ct * cf * w2
    return p[3] * r0, p[4] * r1, p[5] * r2


def dip_of(h: Array, f: Array) -> float:
    """Dip (rad) of the field h (3,) below the horizontal, with f (3,) the specific force at rest (up)."""
    c = float(h @ f) / max(float(np.linalg.norm(h) * np.linalg.norm(f)), 1e-12)
    return float(-math.asin(min(1.0, max(-1.0, c))))


@dataclass
class MagDisturbanceGate:
    """Whether the magnetometer's block is used (see the module doc). ``active``: inside a disturbance
    since log time ``since`` s; ``last_bad``: the last block that disagreed; ``excluded``: blocks left out
    in the current stretch; ``stretches``: how many so far; ``armed``: the field has agreed for ``CLEAR_S``
    s (since the start or since a lasting disagreement), from ``agreed_since`` s. ``log_fresh``: no block of
    the current log judged yet; ``whole_log``: the running stretch began with the log's first judged block.

    A log whose field disagrees from its first block on was recorded in another field (another place, another
    mounting) — as the batch leaves such a file out of its magnetometer fit ("field +32 % against the other
    files"), its magnetometer stays out until the field agrees or the log ends, not only for ``MAX_S``: MARG
    set 1's ``unmoved-x-pointing-up.csv`` (70 s at +32 %) was let back in after 45 s, diverged the filter and
    restarted the gyro and mag terms at the cold prior's σ (session 16)."""

    active: bool = False
    since: float = math.nan
    last_bad: float = -math.inf
    excluded: int = 0
    stretches: int = 0
    armed: bool = False
    agreed_since: float = math.nan
    log_fresh: bool = True
    whole_log: bool = False

    def new_log(self) -> None:
        """A new log starts (another recording: another place perhaps): a stretch of the last log ends with it
        (the field of the new one is judged afresh); the gate stays armed."""
        self.active, self.whole_log, self.log_fresh = False, False, True
        self.agreed_since = math.nan

    def disarm(self) -> None:
        """The magnetometer's model was restarted (a divergence): agreement with it must be seen anew before
        a disagreement counts as a disturbance (while the filter re-learns the terms, it is no change)."""
        self.active, self.armed, self.agreed_since = False, False, math.nan

    def judge(self, x: Array, sig: Array, m_raw: Array, a_raw: Array, gravity: float,
              accel_is_gravity: bool = True, means: tuple[Array, Array] | None = None) -> str | None:
        """Why the block's field disagrees with the model, or None. m_raw (N, 3), a_raw (K, 3) raw samples
        of the block; x, sig (n,) the state and its σ; ``gravity`` m/s². ``accel_is_gravity`` False (a
        vehicle in motion, :mod:`.vehicle`): the dip is not judged, since a specific force of norm g can
        still be thrust and acceleration tilted away from gravity (a multirotor accelerating at 2 m/s²
        passes the 2 % norm test with its force 11° off the vertical).

        The arithmetic of :func:`calibrated`, :func:`norm_sigma` and :func:`dip_of` on Python floats
        (:func:`calibrated_floats`; issue 15: numpy's calls on 3-vectors were 18 % of a paper session's replay);
        it agrees with them to rounding (tests/test_speed_detectors.py). ``means``: the block's mean mag and
        accel readings (3,) each where the caller has them (:class:`.blocks.Blocks`' m_mean, a_mean: summed by
        np.add.reduceat, ``mean(axis=0)``'s value to the sums' rounding — only a field within ~1e-15
        of a tolerance could be judged otherwise), instead of forming them again (~6 µs a block)."""
        sl, sa = SENSOR_SLICE["mag"], SENSOR_SLICE["accel"]
        pm = x[sl].tolist()
        m_mean, a_mean = means if means is not None else (m_raw.mean(axis=0), None)
        h = calibrated_floats(pm, m_mean.tolist())
        nh = math.sqrt(h[0] * h[0] + h[1] * h[1] + h[2] * h[2])
        dev = nh - 1.0
        # norm_sigma: δ‖h‖ = ĥ·(M δ(m − o)), M ≈ diag(scale)
        sg = sig[sl].tolist()
        inv = 1.0 / max(nh, 1e-12)
        var = 0.0
        for i in range(3):
            ui, si = h[i] * inv, pm[3 + i]
            var += (ui * si * sg[i]) ** 2 + (ui * h[i] * sg[3 + i] / (si if si != 0 else 1.0)) ** 2
        tol = max(NORM_MIN, NORM_K * math.sqrt(var))
        if abs(dev) > tol:
            return f"field norm {1 + dev:.2f} of the model's 1 (tolerance ±{tol:.2f})"
        if not accel_is_gravity:
            return None
        f = calibrated_floats(x[sa].tolist(), (a_raw.mean(axis=0) if a_mean is None else a_mean).tolist())
        nf = math.sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2])
        if abs(nf / gravity - 1.0) < STATIC_G:
            c = (h[0] * f[0] + h[1] * f[1] + h[2] * f[2]) / max(nh * nf, 1e-12)
            dip = -math.asin(min(1.0, max(-1.0, c)))
            d = math.degrees(dip - float(x[DIP]))
            tol_d = max(DIP_MIN_DEG, DIP_K * math.degrees(float(sig[DIP])))
            if abs(d) > tol_d:
                return f"dip {math.degrees(dip):.1f}° against the model's {math.degrees(x[DIP]):.1f}°"
        return None

    def gate(self, use_mag: bool, x: Array, sig: Array, m_raw: Array, a_raw: Array, t: float, gravity: float,
             event: Callable[[str, str, float], None], in_order: bool = True,
             accel_is_gravity: bool = True, means: tuple[Array, Array] | None = None) -> bool:
        """``use_mag`` unless the block lies in a disturbance; the events through ``event(kind, detail, t)``
        at log time t s. Nothing is judged while the magnetometer is not used (cold, or no sample).
        ``in_order`` (:func:`nis_in_order`): False disarms the gate (and ends a running stretch: the filter's
        own NIS disagree, the disagreement is not the magnetometer's alone). ``means``: as :meth:`judge`'s."""
        if not in_order:
            if self.active:
                event("mag_disturbance", f"magnetometer disturbance left to the filter: t = {self.since:.1f}–"
                                         f"{self.last_bad:.1f} s, {self.excluded} filter blocks of magnetometer data "
                                         "left out; the filter's NIS windows are out of order too", t)
            self.disarm()
            return use_mag
        if not use_mag or m_raw.shape[0] == 0:
            return use_mag and not self.active
        why = self.judge(x, sig, m_raw, a_raw, gravity, accel_is_gravity, means)
        fresh, self.log_fresh = self.log_fresh, False
        if why is None:
            if math.isnan(self.agreed_since):
                self.agreed_since = t
            if t - self.agreed_since >= CLEAR_S:
                self.armed = True
            if self.active and t - self.last_bad >= CLEAR_S:
                self.active = False
                event("mag_disturbance", f"magnetometer disturbance over: t = {self.since:.1f}–{self.last_bad:.1f} "
                                         f"s, {self.excluded} filter blocks of magnetometer data left out", t)
        else:
            self.agreed_since = math.nan
            self.last_bad = t
            if self.active and t - self.since > MAX_S and not self.whole_log:
                self.active, self.armed = False, False
                event("mag_disturbance", f"magnetometer disturbance not passing: the field has disagreed with the "
                                         f"model since t = {self.since:.1f} s ({why}); the magnetometer is used "
                                         "again and its calibration judged by the filter (a lasting change, or "
                                         f"its calibration wrong); {self.excluded} filter blocks were left out", t)
            elif not self.active and self.armed:
                self.active, self.since, self.excluded, self.whole_log = True, t, 0, fresh
                self.stretches += 1
                text = (f"magnetometer disturbance from t = {t:.1f} s ({why}): its updates are left out "
                        f"until the field agrees with the model again for {CLEAR_S:.0f} s"
                        + (" or the log ends (it disagrees from the log's start: another place or a lasting "
                           "disturbance, as a file the batch leaves out of its magnetometer fit)" if fresh else ""))
                event("mag_disturbance", text, t)
                warnings.warn(text, MagDisturbanceWarning, stacklevel=3)
        if self.active:
            self.excluded += 1
            return False
        return True
