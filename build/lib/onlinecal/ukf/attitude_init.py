"""Starting the attitude and the magnetometer: what the filter does before (or instead of) a UKF step.

* :func:`initial_attitude` — roll and pitch from the block's mean accel, yaw from its field (TRIAD), and
  the σ of that start in the body-frame error;
* :func:`set_yaw_variance` — forget the heading (nothing sees it without a mag) and give it a σ;
* :func:`yaw_to_north` — once the mag is calibrated, turn the world so that the field points north;
* :class:`MagCollector`, :func:`fit_mag_cold` — the magnetometer's cold start: a sphere fit on buffered
  raw samples, refined to the full ellipsoid (eq. 17) where the samples carry it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..batch.ellipsoid import fit_norm_lm
from ..model import decompose
from . import kernels
from .config import UKFConfig
from .geometry import rodrigues1, triad, yaw_rotation
from .kernels_magfit import fit_refused
from .layout import field_world

Array = NDArray[np.float64]
E_Z = np.array([0.0, 0.0, 1.0])


def initial_attitude(f: Array, h: Array | None, h_world: Array | None, s_rp: float, s_y: float) -> tuple[Array, Array]:
    """Attitude R (world ← body) (3, 3) from the unit specific force f (3,) and the unit field h (3,) in
    the body frame (TRIAD against e_z and ``h_world``), and the covariance (3, 3) of the body-frame
    attitude error for σ ``s_rp`` (roll, pitch) and ``s_y`` (heading) about the world axes.

    ``h`` None (no calibrated mag): the yaw is arbitrary (the body x axis is put east) and ``s_y`` should
    be diffuse.
    """
    if h is None or h_world is None:
        h = np.array([1.0, 0.0, 0.0]) if abs(f[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        h_world = np.array([1.0, 0.0, 0.0])
    R = triad(f, h, E_Z, h_world)
    # σ given about the world axes (tilt, heading), turned into the body-frame error
    P_att: Array = R.T @ np.diag([s_rp, s_rp, s_y]) ** 2 @ R
    return R, P_att


def attitude_start(f: Array, h: Array | None, dip: float, dip_known: bool, s_rp: float, s_y_free: float
                   ) -> tuple[Array, Array, float | None]:
    """The attitude start of a block: R (3, 3) and the attitude error's covariance (3, 3)
    (:func:`initial_attitude`) from the calibrated mean specific force f (3,) and, where the mag is
    usable, the calibrated mean field h (3,) (else the heading gets the diffuse σ ``s_y_free``). The
    field's world direction uses the dip state ``dip`` (rad) once ``dip_known``; before, the dip from
    these readings, returned as the third value for the caller's dip state (None: leave it)."""
    fu = f / np.linalg.norm(f)
    if h is None:
        R, P_att = initial_attitude(fu, None, None, s_rp, s_y_free)
        return R, P_att, None
    hu = h / np.linalg.norm(h)
    new_dip = None if dip_known else dip_of(fu, hu)
    hw = field_world(np.array([dip if new_dip is None else new_dip]))[0]
    R, P_att = initial_attitude(fu, hu, hw, s_rp, s_rp)
    return R, P_att, new_dip


def fold_attitude(R_nom: Array, x: Array, P: Array, yaw_var: float | None, att: slice) -> tuple[Array, Array, Array]:
    """After an update (USQUE reset): the attitude error of x (n,) folded into the nominal R_nom (3, 3) and
    set to 0 (x is changed in place), P (n, n) symmetrised; ``yaw_var``: nothing sees the heading, so its
    knowledge is marginalised out and given this variance (:func:`set_yaw_variance`). Returns (R, x, P)."""
    P = 0.5 * (P + P.T)
    R = R_nom @ rodrigues1(x[att])
    x[att] = 0.0
    if yaw_var is not None:
        P = set_yaw_variance(P, R, yaw_var, att)
    return R, x, P


def dip_of(f: Array, h: Array) -> float:
    """Dip δ (rad) of the field from the unit specific force f and unit field h (body frame): sin δ = −f·h."""
    return math.asin(float(np.clip(-f @ h, -1, 1)))


def set_yaw_variance(P: Array, R_nom: Array, var: float, att: slice) -> Array:
    """P (n, n) with everything it knows about the heading (rotation about world z) removed and ``var``
    given to it instead.

    The error is in the body frame, so the heading is the direction u = R_nomᵀ e_z of the attitude error
    (``att`` its slice): P ← J P Jᵀ with J = I − u uᵀ on the attitude block, then var · u uᵀ added. J differs
    from the identity only in the attitude block, so only the attitude rows and columns change.
    """
    u = R_nom[2, :]  # R_nomᵀ e_z
    J = np.eye(3) - np.outer(u, u)
    P = P.copy()
    P[att, :] = J @ P[att, :]
    P[:, att] = P[:, att] @ J.T
    P[att, att] += var * np.outer(u, u)
    return P


def yaw_to_north(R_nom: Array, h_cal: Array) -> tuple[float, Array]:
    """First calibrated mag block: the field h_cal (3,) (body frame) gives the dip (rad) and the turn of
    the world about z that puts its horizontal part on north (+y). Returns (dip, R_nom turned)."""
    hw = R_nom @ (h_cal / np.linalg.norm(h_cal))
    dip = math.asin(float(np.clip(-hw[2], -1, 1)))
    psi = math.atan2(hw[0], hw[1])  # turning the world by +psi about z moves hw onto +y
    return dip, yaw_rotation(psi) @ R_nom


@dataclass
class MagCollector:
    """A bounded, time-decimated (one per 0.1 s) buffer (N, 3) of raw mag samples for the cold-start fit
    (a numpy array: a flight whose field never sweeps 3-D keeps it full for the whole log).

    ``buf`` is a view of a larger store that :meth:`add` fills in place (issue 15: a concatenation of the
    whole buffer per filter block was most of the collection's cost, ~1 µs per IMU sample); the store is
    no field (a checkpoint saves ``buf``), and a ``buf`` set from outside is copied into a new store at the
    next add. The values, their order and the halving are those of a concatenation."""

    buf: Array = field(default_factory=lambda: np.zeros((0, 3)))
    next_t: float = -math.inf

    def add(self, tm: Array, m: Array, max_len: int) -> None:
        """Take in the samples of tm (N,) s, m (N, 3) at least 0.1 s after the last one taken; keep every
        second sample when the buffer exceeds ``max_len``. The decimation is a loop over the block's few
        samples (about 5 a block at 50 Hz: cheaper than numpy's calls; no Python step per buffered sample)."""
        sel = []
        nt = self.next_t
        for k, ti in enumerate(tm.tolist()):  # Python floats: the same comparisons, a third of the cost
            if ti >= nt:
                sel.append(k)
                nt = ti + 0.1
        self.next_t = nt
        if sel:
            n, k = self.buf.shape[0], len(sel)
            store: Array | None = getattr(self, "_store", None)
            if (store is None or getattr(self, "_view", None) is not self.buf or not self.buf.flags.c_contiguous
                    or store.shape[0] < n + k):
                store = np.empty((max(2 * (n + k), max_len + 64), 3))
                store[:n] = self.buf
                setattr(self, "_store", store)  # noqa: B010 (no field: not in a checkpoint)
            store[n : n + k] = np.asarray(m, float)[sel[0]] if k == 1 else np.asarray(m, float)[sel]
            self.buf = store[: n + k]
            setattr(self, "_view", self.buf)  # noqa: B010
        if self.buf.shape[0] > max_len:
            self.buf = self.buf[::2]  # a strided view: copied into a new store at the next add
            setattr(self, "_view", self.buf)  # noqa: B010


@dataclass
class MagFit:
    """A usable cold-start fit: the 12 mag terms x (bias, scale, alpha, xi), their σ, the cold prior σ in
    the fit's raw unit (for the observability ratios) and what to say about it."""

    x: Array
    sigma: Array
    prior_sigma: Array
    detail: str


def fit_mag_cold(x: Array, c: UKFConfig) -> MagFit | None:
    """Sphere fit ‖x − o‖ = r (linear least squares) of raw samples x (N, 3), refined to the ellipsoid
    (eq. 17) where the samples carry it; None unless they span enough directions and pin the centre.

    Sphere: o_mag = centre, s_mag = 1/r (all axes), angles 0, σ ``c.mag_fit_sigma``. Ellipsoid (geometric
    fit, :func:`ellipsoid_gn`): the soft iron starts near its value, σ ``c.mag_ellipsoid_sigma``, so the
    first mag updates stay in the UKF's near-linear range.

    On the numba backend a compiled screen (:func:`.kernels_magfit.fit_refused`) first returns None where
    one of the three tests below is certain to fail (by over 1 %): the same decisions, ~20× cheaper on a
    flight that tries the fit every second of its log (issue 15).
    """
    if kernels.backend() == "numba" and fit_refused(x, c.mag_fit_max_centre_sigma, c.mag_fit_min_spread,
                                                    c.mag_fit_min_cover):
        return None
    m0 = x.mean(axis=0)
    xc = x - m0  # centred for conditioning
    A = np.column_stack([2 * xc, np.ones(x.shape[0])])
    b = (xc**2).sum(axis=1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    oc = sol[:3]
    r2 = sol[3] + oc @ oc
    if r2 <= 0:
        return None
    r = math.sqrt(r2)
    o = m0 + oc
    # usable only when the samples pin the centre down: LS covariance of the centre (the residual
    # includes the soft iron the sphere lacks, so this also rejects a cloud of noise or a flat circle)
    e = b - A @ sol
    s2 = float(e @ e) / max(1, x.shape[0] - 4)
    try:
        cov = s2 * np.linalg.inv(A.T @ A)
    except np.linalg.LinAlgError:
        return None
    sig_o = float(np.sqrt(np.max(np.diag(cov)[:3])))
    # the three tests in order of cost, each a return (the same decision as testing all three at once):
    # a flight's band of field directions fails one of them every second of its log (issue 15)
    if not sig_o < c.mag_fit_max_centre_sigma * r:
        return None
    u = (x - o) / np.linalg.norm(x - o, axis=1)[:, None]
    spread = float(np.linalg.eigvalsh(u.T @ u / u.shape[0])[0])
    if spread < c.mag_fit_min_spread:
        return None
    cover = float(np.linalg.eigvalsh(np.cov(u.T))[0])  # a band of directions (a flight) is not enough
    if cover < c.mag_fit_min_cover:
        return None
    fs = c.mag_fit_sigma
    x_m = np.concatenate([o, np.full(3, 1.0 / r), np.zeros(6)])
    sig = np.concatenate([np.full(3, fs["bias"] * r), np.full(3, fs["scale"] / r),
                          np.full(3, fs["alpha"]), np.full(3, fs["xi"])])
    kind = "sphere"
    ell = _ellipsoid_refine(x, o, r, c)
    if ell is not None:
        x_m, sig = ell
        kind = "ellipsoid"
    cs = c.cold_sigma["mag"]
    prior_sig = np.concatenate([np.full(3, cs["bias"] * r), np.full(3, cs["scale"] / r),
                                np.full(3, cs["alpha"]), np.full(3, cs["xi"])])
    detail = (f"{kind} fit on {x.shape[0]} samples: |field| {r:.4g} raw, "
              f"hard iron {np.round(o, 4).tolist()} ± {sig_o:.2g}, direction spread {spread:.3f}")
    return MagFit(x_m, sig, prior_sig, detail)


def _ellipsoid_refine(x: Array, o: Array, r: float, c: UKFConfig) -> tuple[Array, Array] | None:
    """The 12 mag terms and σ from the geometric ellipsoid fit started at the sphere (o, r), or None when
    its covariance says the samples do not carry an ellipsoid."""
    try:
        o_e, M_e, cov_e, _ = ellipsoid_gn(x, o, np.eye(3) / r)
        sd = np.sqrt(np.clip(np.diag(cov_e), 0, None))
        if (np.all(np.isfinite(sd)) and sd[:3].max() < c.mag_fit_max_centre_sigma * r
                and sd[3:].max() < 0.01 / r and np.linalg.det(M_e) > 0):
            s_e, a_e, xi_e = decompose(M_e)
            fe = c.mag_ellipsoid_sigma
            return (np.concatenate([o_e, s_e, a_e, xi_e]),
                    np.concatenate([np.maximum(3 * sd[:3], fe["bias"] * r), np.full(3, fe["scale"] / r),
                                    np.full(3, fe["alpha"]), np.full(3, fe["xi"])]))
    except (ValueError, np.linalg.LinAlgError):
        pass
    return None


def ellipsoid_gn(x: Array, o0: Array, M0: Array, max_iter: int = 40,
                 reject_sigma: float = 5.0) -> tuple[Array, Array, Array, float]:
    """Geometric ellipsoid fit ‖M (x − o)‖ = 1 (Zhang et al. eq. 17): the batch's fit
    (:func:`onlinecal.batch.ellipsoid.fit_norm_lm`, Levenberg–Marquardt with the analytic Jacobian; o (3,)
    and a symmetric M) with unit weights and one outlier rejection at ``reject_sigma`` × MAD, then a refit.

    x (N, 3) raw samples; o0, M0 the start (a sphere fit). Returns (o, M, cov (9, 9) of (o, upper triangle
    of M) from the Gauss–Newton normal matrix and the residual variance, residual rms). A fixed iteration
    budget (``max_iter``) keeps the cost bounded (a few ms) where the data do not carry an ellipsoid; the
    caller rejects such fits by their covariance. FitError (a ValueError) under 9 samples.
    """
    f = fit_norm_lm(x, 1.0, o0, M0, reject_sigma=reject_sigma, max_iter=max_iter, rounds=1)
    return f.o, f.M, f.cov, f.rms
