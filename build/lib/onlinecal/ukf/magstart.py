"""The magnetometer's start inside the filter: the flags and buffer the filter keeps about it, and the
steps that turn them (collect raw samples, a cold prior in the raw unit, the cold fit, the yaw turned to
north). Each step takes the filter's values and returns new ones; the filter applies them.

The fit itself is :func:`.attitude_init.fit_mag_cold`; the attitude maths :mod:`.attitude_init`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .attitude_init import MagCollector, MagFit, fit_mag_cold, set_yaw_variance, yaw_to_north
from .config import UKFConfig

Array = NDArray[np.float64]


@dataclass
class MagStart:
    """Where the magnetometer's start stands.

    ``enabled``: the mag is calibrated (from the init or the cold fit) and used; ``dip_known``: the dip
    state was set from a field reading; ``buf``: raw samples buffered for the cold fit; ``fit_next``: log
    time (s) of the next fit try; ``align_next``: the next mag block turns the yaw to north;
    ``yaw_free``: nothing sees the heading (no usable mag), so its σ is kept diffuse."""

    enabled: bool = False
    dip_known: bool = False
    buf: MagCollector = field(default_factory=MagCollector)
    fit_next: float = -math.inf
    align_next: bool = False
    yaw_free: bool = True

    def collect(self, tm: Array, m: Array, cold: bool, max_len: int) -> bool:
        """Buffer the raw samples tm (N,) s, m (N, 3) while the mag is not calibrated. True when these are
        the first samples of a mag without an init (``cold``): the caller sets its prior from them
        (:func:`mag_prior_from_raw`)."""
        if self.enabled:
            return False
        first = bool(not self.buf.buf.shape[0] and m.shape[0] and cold)
        self.buf.add(tm, m, max_len)
        return first

    def try_fit(self, t: float, c: UKFConfig) -> MagFit | None:
        """The cold fit (:func:`.attitude_init.fit_mag_cold`), tried once a second at log time ``t`` (s)
        once ``c.mag_fit_min_samples`` are buffered. On success the mag is enabled, the buffer emptied and
        the yaw is turned at the next mag block; the caller puts the fit into the state."""
        if t < self.fit_next or self.buf.buf.shape[0] < c.mag_fit_min_samples:
            return None
        self.fit_next = t + 1.0
        fit = fit_mag_cold(self.buf.buf, c)
        if fit is None:
            return None
        self.enabled = True
        self.buf.buf = np.zeros((0, 3))
        self.align_next = True
        return fit

    def align(self, R_nom: Array, P: Array, h_cal: Array, var: float, att: slice) -> tuple[float, Array, Array]:
        """First mag block after the cold fit: the dip (rad) from the calibrated field h_cal (3,), the
        nominal attitude R_nom (3, 3) turned so the field points north, and P (n, n) with the heading's
        variance set to ``var`` (slice ``att`` the attitude error). The caller sets the dip state."""
        dip, R_new = yaw_to_north(R_nom, h_cal)
        P_new = set_yaw_variance(P, R_new, var, att)
        self.yaw_free = False
        self.align_next = False
        return dip, R_new, P_new

    def restart(self, enabled: bool) -> None:
        """Forget the mag's start (a divergence of the mag alone): enabled only where an init gives it."""
        self.enabled = enabled
        self.dip_known = False
        self.buf, self.fit_next = MagCollector(), -math.inf
        self.align_next = False


def mag_prior_from_raw(m: Array, cold_sigma: dict[str, float], held: tuple[Array, Array] | None
                       ) -> tuple[Array, Array] | None:
    """Cold mag prior (12,) mean and σ in the raw unit from the first samples m (N, 3): scale 1/|m| (the
    median field magnitude) with σ ``cold_sigma`` relative to it (:func:`.state.prior` assumes a unit
    field). ``held``: (mean, σ) of the alpha and xi (6,) to keep (the mag defines the gauge). None where
    |m| is not a positive number. The mag is not used before its fit, so this only changes what a log
    that never fits it reports: its prior."""
    r = float(np.median(np.linalg.norm(m, axis=1)))
    if not (math.isfinite(r) and r > 0):
        return None
    cs = cold_sigma
    x = np.concatenate([np.zeros(3), np.full(3, 1.0 / r), np.zeros(6)])
    sig = np.concatenate([np.full(3, cs["bias"] * r), np.full(3, cs["scale"] / r),
                          np.full(3, cs["alpha"]), np.full(3, cs["xi"])])
    if held is not None:
        x[6:], sig[6:] = held
    return x, sig
