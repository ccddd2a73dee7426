"""Gyroscope calibration without tools (eqs. 28–31, 34–36) and with a rate table (eq. 33).

* bias: least-squares line fit of the cumulative sum (integrated angle) over the rests (eqs. 34–35);
* axes: raw rate direction between the 1/3 and 2/3 points of each rotation phase (eqs. 28–31);
* scale: the turn angle seen by the calibrated accelerometer/magnetometer against the integrated raw
  rate over each phase (eq. 36);
* then eq. 36 generalised: all nine entries of the gyro matrix refined so that, over every motion
  between two rests, the integrated attitude change carries gravity (and the field) from the rest
  before to the rest after. This uses every transition, not only the phases, and is what makes the
  tool-free result work on sessions whose turns are about the vertical (the Ferraris procedure).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..io.base import ImuData
from ..model import Calibration, SensorCalibration
from ..specs import OMEGA_EARTH, RAIL_TOL, rail_samples
from .decomp import decompose_many
from .ellipsoid import FitError
from .segment import Interval, Phase, Segmentation, moving_std
from .sensors import StepReport, sqrt_psd

Array = NDArray[np.float64]


def gyro_bias_cumsum(segs: list[Segmentation], notes: list[str] | None = None,
                     latitude_deg: float | None = None, figures: dict[str, Any] | None = None) -> tuple[Array, Array]:
    """Bias o_gyr by an LS line fit to the cumulative sum of the raw rate over rests (eqs. 34–35).

    In a rest the integrated raw rate grows as θ(t) = o·t + c; one common slope over all rests (each
    with its own intercept). Returns (o (3,), 1σ (3,)) in rad/s; σ is that of this estimator for white rate
    noise of each rest's own variance, and at least the standard error of the rest means; where the rests
    disagree beyond their own noise (:func:`rest_disagreement`) σ covers their spread, with a sentence
    appended to ``notes``; and σ includes the Earth's rotation where the rests' attitudes do not cancel it
    (end of the function). With ``latitude_deg`` (deg, a log's GPS or ``--latitude``) its vertical part is
    taken out of o (recorded in ``figures["earth_rate_removed"]``) and only the horizontal part, whose
    direction needs the heading, stays in σ.

    The estimator is linear in the rates, o = Σ_j β_j w_j / Σ tc², and weights a rest by about its length
    cubed (the slope's leverage): a 30 s rest outweighs a 5 s one 200 times. Its variance is therefore
    Σ_rests var(w) Σ_j β_j² / (Σ tc²)², not the pooled mean's var(w)/N — on the paper session 2–3 times
    larger (the pooled formula put the truth at up to 5 σ on clean simulated sessions).
    """
    num = np.zeros(3)
    den = 0.0
    var_num = np.zeros(3)
    up_w: list[tuple[float, Array]] = []  # per rest: its weight in o (Σ β_j) and the gravity direction
    for s in segs:
        for iv in s.rests:
            t = s.data.t_imu[iv.i0 : iv.i1]
            w = s.data.gyro[iv.i0 : iv.i1]
            if t.size < 3:
                continue
            th = np.concatenate([[np.zeros(3)], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t)[:, None], 0)])
            tc = t - t.mean()
            num += tc @ (th - th.mean(0))
            den += float(tc @ tc)
            # the weight β_j of rate sample j in tc·θ (θ's trapezoid puts w_j in the steps on both sides of t_j):
            # β_j = (dt_j S_j + dt_{j+1} S_{j+1}) / 2 with S_i = Σ_{k≥i} tc_k, dt_i = t_i − t_{i−1}
            S = np.cumsum(tc[::-1])[::-1]
            half = 0.5 * np.diff(t) * S[1:]
            beta = np.zeros(t.size)
            beta[:-1] += half
            beta[1:] += half
            var_num += w.var(axis=0) * float(beta @ beta)
            a = s.data.acc[iv.i0 : iv.i1].mean(axis=0)
            up_w.append((float(beta.sum()), a / max(float(np.linalg.norm(a)), 1e-12)))
    if den <= 0:
        raise FitError("gyro bias: no static interval (need a rest to fit eqs. 34–35)")
    o = num / den
    sigma = np.sqrt(var_num) / den
    # Rests far apart in time see a bias that moved (temperature, instability): the white-noise σ is
    # then optimistic. With several rests, σ is at least the standard error of their means' scatter.
    # Rests that disagree beyond their own noise (g-sensitivity, bias instability, temperature) leave the
    # bias at any one moment known only to their spread: a σ is a promise, it must cover that spread.
    rests = [s.data.gyro[iv.i0:iv.i1] for s in segs for iv in s.rests if iv.n >= 3]
    if len(rests) >= 2:
        means = np.array([w.mean(0) for w in rests])
        se = np.array([w.std(0) / np.sqrt(w.shape[0]) for w in rests])
        spread = means.std(axis=0, ddof=1)
        chi2, bar, disagree = rest_disagreement(means, se)
        sigma = np.where(disagree, np.maximum(sigma, spread), np.maximum(sigma, spread / np.sqrt(len(rests))))
        if disagree.any() and notes is not None:
            ax = [a for a, d in zip("xyz", disagree, strict=True) if d]
            notes.append(f"gyro bias: the {len(rests)} rests disagree beyond their noise on {', '.join(ax)} "
                         f"(χ² {', '.join(f'{c:.0f}' for c in chi2[disagree])} against {bar:.0f} on "
                         f"{len(rests) - 1} dof; spread {', '.join(f'{x:.2g}' for x in spread[disagree])} rad/s): "
                         "σ widened to the spread (g-sensitivity, instability or temperature; `diagnose` names it)")
    # Values on a lattice coarser than the noise (RAW_IMU: 1 mrad/s) do not average out: the mean of
    # held readings can be off by up to half a step. σ is floored at q/√12 where the noise is below q.
    w_all = np.concatenate([s.data.gyro[iv.i0:iv.i1] for s in segs for iv in s.rests])
    w_log = np.concatenate([s.data.gyro[:: max(1, s.data.n_imu // 20000)] for s in segs])  # the lattice
    for k in range(3):
        d = np.diff(np.unique(w_log[:, k]))
        q = float(d.min()) if d.size else 0.0
        # noise well below a step (no dithering), or whole mrad/s (MAVLink RAW_IMU): the stored values were
        # rounded by the log format, whose error against the sensor's own reading need not average out
        if q > 0 and (np.std(w_all[:, k]) < 0.6 * q or abs(q - 1e-3) < 1e-9):
            sigma[k] = max(sigma[k], q / np.sqrt(12))
    # At rest a gyro reads its bias plus the Earth's rotation on its axes (Ω_E sin φ up, Ω_E cos φ north),
    # which the paper's model lacks and eqs. 34–35 take for bias: o is off by the weighted mean of the rests'
    # Earth rates. Rests in opposite attitudes cancel it (the paper's faces); rests in one attitude (a
    # vehicle on the ground) leave all of it — 20 simulated flights had gyro.bias.z 4–7σ off. Heading and
    # latitude unknown, its rms per axis is Ω_E/√3 (the UKF's zero-rate allowance) times the length of the
    # weighted mean gravity direction: 1 for one attitude, ~0 for balanced faces. Added in quadrature.
    wsum = sum(b for b, _ in up_w)
    u_bar = sum(b * u for b, u in up_w) / wsum if wsum > 0 else np.array([0.0, 0.0, 1.0])
    m_up = min(float(np.linalg.norm(u_bar)), 1.0)
    if latitude_deg is None:
        return o, np.hypot(sigma, OMEGA_EARTH / np.sqrt(3.0) * m_up)
    # Told the latitude φ: each rest's vertical part, Ω_E sin φ along its own up (the accelerometer's mean
    # specific force), enters o with the rest's weight — the same weighted mean u_bar. What is left is the
    # horizontal part, Ω_E cos φ along north at a heading the rests do not give: per axis rms
    # Ω_E cos φ · √((1 − û_k²)/2) of the mean up direction û (nothing on a level body's z), times m_up as above.
    phi = np.radians(latitude_deg)
    removed = OMEGA_EARTH * np.sin(phi) * u_bar
    o = o - removed
    if figures is not None:
        figures["earth_rate_removed"] = {"latitude_deg": float(latitude_deg), "rad_s": removed.tolist()}
    u_hat = u_bar / max(float(np.linalg.norm(u_bar)), 1e-12)
    horizontal = OMEGA_EARTH * np.cos(phi) * np.sqrt(np.clip(1.0 - u_hat**2, 0.0, 1.0) / 2.0) * m_up
    return o, np.hypot(sigma, horizontal)


def rest_disagreement(means: Array, se: Array) -> tuple[Array, float, NDArray[np.bool_]]:
    """Whether K rest means (K, 3) rad/s disagree beyond their standard errors ``se`` (K, 3): per axis
    χ² = Σ ((m_i − m̄)/se_i)² on K − 1 degrees of freedom against the bar K − 1 + 5·√(2(K − 1)) (5 σ of
    the χ² above its mean). A rest with se = 0 (readings held on a lattice) counts only where its mean
    differs. Returns (χ² (3,), bar, disagree (3,) bool)."""
    k = means.shape[0]
    d = means - means.mean(axis=0)
    z = np.divide(d, se, out=np.where(np.abs(d) > 0, np.inf, 0.0), where=se > 0)
    chi2 = np.sum(z**2, axis=0)
    bar = (k - 1) + 5.0 * np.sqrt(2.0 * (k - 1))
    return chi2, float(bar), chi2 > bar


def gyro_axes_from_phases(segs: list[Segmentation], o: Array) -> dict[int, tuple[Array, float, float]]:
    """Raw direction of each body axis from the phases about it (eqs. 28–31).

    The paper takes the bias-corrected rate at the 1/3 and 2/3 points of a phase; we average it over
    that middle third (same direction, less noise). Forward and backward phases are pooled so that a
    bias error cancels. Returns axis → (unit direction, summed weight, σ of the direction in rad per
    perpendicular component): the scatter of the samples across the direction over √N and over the
    mean rate — what the sensor's noise (and any wobble of the turn) leaves in the mean.
    """
    acc: dict[int, Array] = {}
    wts: dict[int, float] = {}
    rows: dict[int, list[Array]] = {}
    for s in segs:
        for ph in s.phases:
            if s.noisy(ph) and any(q.axis == ph.axis and not s2.noisy(q) for s2 in segs for q in s2.phases):
                continue  # a noise burst in the middle third would tilt the mean direction
            n = ph.i1 - ph.i0
            a, b = ph.i0 + n // 3, ph.i0 + (2 * n) // 3
            if b - a < 2:
                continue
            w = (s.data.gyro[a:b] - o) * ph.sign
            v = w.mean(axis=0)
            if v @ ph.direction <= 0:
                continue  # the middle third is not turning the phase's way (a hand-held wobble)
            acc[ph.axis] = acc.get(ph.axis, np.zeros(3)) + v * (b - a)
            wts[ph.axis] = wts.get(ph.axis, 0.0) + float(b - a)
            rows.setdefault(ph.axis, []).append(w - v)  # about each phase's own mean
    out: dict[int, tuple[Array, float, float]] = {}
    for k, v in acc.items():
        u = v / np.linalg.norm(v)
        r = np.concatenate(rows[k])
        perp = r - np.outer(r @ u, u)
        # two perpendicular components share the scatter; the mean of N samples, over |ω|
        sd = float(np.sqrt(np.mean(np.einsum("ij,ij->i", perp, perp)) / 2.0 / r.shape[0]))
        out[k] = (u, wts[k], sd / float(np.linalg.norm(v / wts[k])))
    return out


def phase_matrix_sigma(axes: dict[int, tuple[Array, float, float]], scales: dict[int, float],
                       scale_sd: Array, rng: np.random.Generator, draws: int = 200) -> Array:
    """σ of (scale, alpha, xi) (9,) of the phase method's matrix G = [c_k u_k]⁻¹ (eqs. 28–31, 36), by
    drawing each axis direction u_k within its σ (:func:`gyro_axes_from_phases`) and each c_k = 1/scale
    within ``scale_sd`` (3,), and decomposing (eqs. 2–6). Needs all three axes."""
    mats = np.empty((draws, 3, 3))
    for k in range(3):
        u, _, sd = axes[k]
        e = rng.standard_normal((draws, 3)) * sd
        u2 = u + e - np.outer(e @ u, u)
        s_k = scales[k] ** -1 + rng.standard_normal(draws) * scale_sd[k]  # scales holds c = 1/scale
        mats[:, :, k] = u2 / np.linalg.norm(u2, axis=1, keepdims=True) / s_k[:, None]
    par, ok = decompose_many(np.asarray(np.linalg.inv(mats), float))
    return np.std(par[ok], axis=0)


def _static_before_after(seg: Segmentation, iv: Interval) -> tuple[Interval, Interval] | None:
    before = [s for s in seg.statics if s.i1 - 1 == iv.i0]
    after = [s for s in seg.statics if s.i0 == iv.i1 - 1]
    return (before[0], after[0]) if before and after else None


def _vectors(seg: Segmentation, acc: SensorCalibration | None, mag: SensorCalibration | None,
             iv: Interval) -> list[tuple[Array, Array, float]]:
    """Calibrated unit gravity (and field) at the rests around ``iv``: (before, after, 1σ direction)."""
    ba = _static_before_after(seg, iv)
    if ba is None:
        return []
    out = []
    d = seg.data
    for cal, t, x in (
        (acc, d.t_imu, d.acc),
        (mag, d.t_mag, d.mag),
    ):
        if cal is None or x.shape[0] == 0:
            continue
        vs = []
        for st in ba:
            m = (t >= st.t0) & (t <= st.t1)
            if m.sum() < 3:
                break
            v = cal.apply(x[m])
            vs.append((v.mean(axis=0), v.std(axis=0).mean() / np.sqrt(m.sum()), np.linalg.norm(v.mean(0))))
        if len(vs) == 2:
            (v0, s0, n0), (v1, s1, n1) = vs
            # A floor on σ: the calibrations themselves are good to ~1e-3.
            sig = float(np.hypot(np.hypot(s0 / n0, s1 / n1), 1e-3))
            out.append((v0 / n0, v1 / n1, sig))
    return out


def phase_angle(seg: Segmentation, ph: Phase, acc: SensorCalibration | None,
                mag: SensorCalibration | None) -> tuple[float, float] | None:
    """Turn angle of a phase seen by the calibrated accelerometer and magnetometer (eq. 36, left side).

    The angle of the vector's projection onto the plane normal to the phase axis, unwrapped from the
    rest before to the rest after; a body turning by +θ about e_k sees a world-fixed vector turn by −θ.
    Accel and mag estimates are averaged with weights from their projected radius. Returns
    (angle rad, 1σ rad) or None when neither sensor sweeps a usable circle.
    """
    ba = _static_before_after(seg, ph)
    if ba is None:
        return None
    k = ph.axis
    i, j = (k + 1) % 3, (k + 2) % 3
    d = seg.data
    ests = []
    for cal, t, x, lim in ((acc, d.t_imu, d.acc, 0.3), (mag, d.t_mag, d.mag, 0.2)):
        if cal is None or x.shape[0] == 0:
            continue
        m = (t >= ba[0].t0) & (t <= ba[1].t1)
        if m.sum() < 10:
            continue
        v = cal.apply(x[m])
        scale = np.median(np.linalg.norm(v, axis=1))
        v = v / scale
        radius = np.hypot(v[:, i], v[:, j])
        tt = t[m]
        inb = tt <= ba[0].t1
        ina = tt >= ba[1].t0
        if inb.sum() < 3 or ina.sum() < 3 or np.median(radius) < lim:
            continue
        ang = np.unwrap(np.arctan2(v[:, j], v[:, i]))
        a0 = ang[inb].mean()
        a1 = ang[ina].mean()
        sig = float(np.hypot(ang[inb].std() / np.sqrt(inb.sum()), ang[ina].std() / np.sqrt(ina.sum())))
        sig = max(sig, 1e-4)
        ests.append((-(a1 - a0), sig))
    if not ests:
        return None
    w = np.array([1 / s**2 for _, s in ests])
    ang = float(np.sum([a for a, _ in ests] * w) / w.sum())
    return ang, float(1 / np.sqrt(w.sum()))


def gyro_scale_from_phases(segs: list[Segmentation], o: Array, axes: dict[int, tuple[Array, float, float]],
                           acc: SensorCalibration | None, mag: SensorCalibration | None) -> dict[int, float]:
    """c_k = ∫ u_kᵀ(ω_raw − o) dt / φ_k over the phases about axis k (eq. 36). Raw-per-true gain."""
    num: dict[int, float] = {}
    den: dict[int, float] = {}
    for s in segs:
        for ph in s.phases:
            if ph.axis not in axes or s.gapped(ph) or s.noisy(ph):
                continue
            pa = phase_angle(s, ph, acc, mag)
            if pa is None:
                continue
            t = s.data.t_imu[ph.i0 : ph.i1]
            w = s.data.gyro[ph.i0 : ph.i1] - o
            integ = float((0.5 * (w[1:] + w[:-1]) * np.diff(t)[:, None]).sum(0) @ axes[ph.axis][0])
            num[ph.axis] = num.get(ph.axis, 0.0) + integ * np.sign(pa[0])
            den[ph.axis] = den.get(ph.axis, 0.0) + abs(pa[0])
    return {k: num[k] / den[k] for k in num if den[k] > 0}


# -- eq. 36 generalised: attitude change between rests -----------------------------------------------

def rodrigues(theta: Array) -> Array:
    """exp([θ]_x) for θ (N, 3) → (N, 3, 3), exact for any angle (sinc forms avoid a branch at 0)."""
    a = np.linalg.norm(theta, axis=1)
    s = np.sinc(a / np.pi)[:, None, None]  # sin(a)/a
    c = (0.5 * np.sinc(a / (2 * np.pi)) ** 2)[:, None, None]  # (1 − cos a)/a²
    K = np.zeros((theta.shape[0], 3, 3))
    K[:, 0, 1], K[:, 0, 2] = -theta[:, 2], theta[:, 1]
    K[:, 1, 0], K[:, 1, 2] = theta[:, 2], -theta[:, 0]
    K[:, 2, 0], K[:, 2, 1] = -theta[:, 1], theta[:, 0]
    return np.eye(3) + s * K + c * (K @ K)


def ordered_product(R: Array) -> Array:
    """R[0] @ R[1] @ … @ R[L-1] along axis 1 for R (S, L, 3, 3) by pairwise tree reduction.

    The product of many small rotations is the attitude change; the tree keeps it vectorised
    (log₂ L batched matmuls instead of L sequential ones).
    """
    while R.shape[1] > 1:
        if R.shape[1] % 2:
            R = np.concatenate([R, np.broadcast_to(np.eye(3), (R.shape[0], 1, 3, 3))], axis=1)
        R = R[:, 0::2] @ R[:, 1::2]
    return R[:, 0]


MAX_TRANSITION_S = 60.0


@dataclass
class _Transitions:
    increments: list[Array]  # per motion (n_i, 3): raw-rate·dt minus bias·dt
    pairs: list[tuple[int, Array, Array, float]]  # (motion index, before, after, σ)

    def buckets(self) -> list[tuple[NDArray[np.intp], Array]]:
        """Motions grouped by power-of-two padded length: (motion indices, increments (S, L, 3)).

        Grouping keeps the zero padding (identity steps) small when one motion is much longer."""
        lens = np.array([x.shape[0] for x in self.increments])
        L = 1 << np.ceil(np.log2(np.maximum(lens, 2))).astype(int)
        out = []
        for Lb in np.unique(L):
            ids = np.flatnonzero(L == Lb)
            arr = np.zeros((ids.size, int(Lb), 3))
            for j, i in enumerate(ids):
                arr[j, : lens[i]] = self.increments[i]
            out.append((ids, arr))
        return out


def _collect_transitions(segs: list[Segmentation], o: Array, acc: SensorCalibration | None,
                         mag: SensorCalibration | None) -> _Transitions:
    incs = []
    pairs = []
    for s in segs:
        for iv in s.motions:
            # A motion of minutes (a whole flight between two ground rests) integrates the bias error
            # into the attitude (σ_o · T) and costs the fit its time: eq. 36 takes turns, not journeys.
            if s.gapped(iv) or s.noisy(iv) or iv.duration > MAX_TRANSITION_S:
                continue
            vecs = _vectors(s, acc, mag, iv)
            if not vecs:
                continue
            t = s.data.t_imu[iv.i0 : iv.i1]
            w = s.data.gyro[iv.i0 : iv.i1] - o
            incs.append(0.5 * (w[1:] + w[:-1]) * np.diff(t)[:, None])
            for v0, v1, sig in vecs:
                pairs.append((len(incs) - 1, v0, v1, sig))
    return _Transitions(incs, pairs)


def refine_gyro_matrix(segs: list[Segmentation], o: Array, G0: Array, acc: SensorCalibration | None,
                       mag: SensorCalibration | None) -> tuple[Array, Array, float, int]:
    """Gyro matrix G (calibrated = G (raw − o)) from every motion between two rests (eq. 36 generalised).

    Residual per transition and reference vector v (gravity, field; unit, body frame):
    ``v_after − Cᵀ v_before`` with ``C = Π exp([G Δθ_raw]_x)`` the integrated attitude change.
    Returns (G, covariance of vec(G) (9, 9), residual RMS, number of transitions).
    """
    tr = _collect_transitions(segs, o, acc, mag)
    n_seg = len({p[0] for p in tr.pairs})
    if len(tr.pairs) * 3 < 12 or n_seg < 4:
        raise FitError(f"gyro: {n_seg} motion(s) between rests with reference vectors, need ≥ 4")
    buckets = tr.buckets()
    n_mot = len(tr.increments)
    idx = np.array([p[0] for p in tr.pairs])
    v0 = np.array([p[1] for p in tr.pairs])
    v1 = np.array([p[2] for p in tr.pairs])
    sig = np.array([p[3] for p in tr.pairs])

    def resid(g: Array) -> Array:
        G = g.reshape(3, 3)
        C = np.empty((n_mot, 3, 3))
        for ids, arr in buckets:
            S, L, _ = arr.shape
            C[ids] = ordered_product(rodrigues(arr.reshape(-1, 3) @ G.T).reshape(S, L, 3, 3))
        pred = np.einsum("sji,sj->si", C[idx], v0)
        return ((v1 - pred) / sig[:, None]).ravel()

    from scipy.optimize import least_squares  # lazily: ~0.3 s of every CLI start-up otherwise

    sol = least_squares(resid, G0.ravel(), method="lm", x_scale="jac")
    r = sol.fun
    dof = max(1, r.size - 9)
    s2 = float(r @ r / dof)
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * max(s2, 1.0)
    except np.linalg.LinAlgError:
        cov = np.full((9, 9), np.inf)
    rms = float(np.sqrt(np.mean(((r.reshape(-1, 3)) * sig[:, None]) ** 2)))
    return sol.x.reshape(3, 3), cov, rms, n_seg


def fit_gyro_rate_table(raw_means: Array, rates_body: Array) -> SensorCalibration:
    """Rotation-table variant (eq. 33): known body rates ω_k (K, 3) and mean raw readings (K, 3).

    raw = G⁻¹ ω + o is linear in (G⁻¹, o): one least-squares solve. Needs K ≥ 4 non-coplanar rates.
    """
    raw_means = np.asarray(raw_means, float)
    rates_body = np.asarray(rates_body, float)
    if raw_means.shape[0] < 4:
        raise FitError("rate table: need ≥ 4 rate steps")
    X = np.column_stack([rates_body, np.ones(rates_body.shape[0])])
    coef, *_ = np.linalg.lstsq(X, raw_means, rcond=None)
    Ginv = coef[:3].T
    o = coef[3]
    return SensorCalibration(o, np.linalg.inv(Ginv))


MIN_INTEGRATION_RATE = 20.0  # Hz: below it no step integrates the gyro (hand and vehicle turns reach 5–10 Hz)


def fit_gyroscope(segs: list[Segmentation], acc: SensorCalibration | None, mag: SensorCalibration | None,
                  rng: np.random.Generator, g: float = 9.80665,
                  latitude_deg: float | None = None) -> tuple[SensorCalibration, StepReport]:
    """The tool-free gyro pipeline: bias (34–35) → axes (28–31) → scale (36) → eq. 36 over all motions;
    where neither phases about all three axes nor four rest-to-rest motions exist (a hand-held session),
    eq. 36 generalised to any rotation (:func:`fit_gyro_kinematic`): with the rests' bias where there are
    rests (the matrix fitted given it; the joint fit's bias kept in the figures), spans with clipped readings
    left out, each clipped file named in a warning with its clipped times and the rotation they lost
    (``figures["clipped"]``), and each resting recording's own bias in ``figures["bias_per_file"]``.
    Where none of these can run, the scale and axes are *undetermined*: the matrix stays the identity, its σ
    is absent, and ``figures["undetermined"]`` lists the terms with a warning naming the missing motion.
    ``latitude_deg``: the rests' bias without the Earth rotation's vertical part (:func:`gyro_bias_cumsum`).
    """
    rep = StepReport("gyro")
    try:
        o, sig_o = gyro_bias_cumsum(segs, rep.warnings, latitude_deg, rep.figures)
        bias_from = "rests (eqs. 34-35)"
    except FitError:
        o, sig_o, bias_from = None, None, None
    rates = [s.data.imu_rate for s in segs if s.data.n_imu >= 2 and np.isfinite(s.data.imu_rate)]
    rate = max(rates, default=float("nan"))
    if not rate >= MIN_INTEGRATION_RATE:
        # Integrating a hand's or a vehicle's turns (eq. 36) needs samples well inside their bandwidth;
        # a 1 Hz telemetry stream gives a number like a gyro scale of 0.000017, not a calibration.
        rep.warnings.append(f"gyro: the IMU is logged at {rate:.2g} Hz, too slow to integrate turns (need ≥ "
                            f"{MIN_INTEGRATION_RATE:.0f} Hz): gyro scale and axes undetermined (matrix left at "
                            "identity, NOT a calibration)" + ("" if o is not None else "; no rest for the bias"))
        rep.figures.update({"undetermined": ["scale", "alpha", "xi"], "method": "none (bias only)",
                            "imu_rate_hz": rate})
        if o is None or sig_o is None:
            raise FitError(f"gyro: IMU at {rate:.2g} Hz is too slow to integrate and no rest gives the bias")
        return SensorCalibration(o, np.eye(3), {"bias": sig_o.tolist()}), rep
    o_axes = o if o is not None else np.median(np.concatenate([s.data.gyro for s in segs]), axis=0)
    axes = gyro_axes_from_phases(segs, o_axes) if o is not None else {}
    scales = gyro_scale_from_phases(segs, o, axes, acc, mag) if o is not None else {}
    rep.figures["phase_axes"] = "".join("xyz"[k] for k in sorted(axes))
    rep.figures["phase_scales"] = {"xyz"[k]: 1.0 / c for k, c in sorted(scales.items())}
    cols = []
    for k in range(3):
        u = axes[k][0] if k in axes else np.eye(3)[k]
        c = scales.get(k, np.mean(list(scales.values())) if scales else 1.0)
        cols.append(c * u)
    G_paper = np.linalg.inv(np.column_stack(cols))
    rep.figures["paper_matrix"] = G_paper.tolist()
    missing = [k for k in range(3) if k not in scales or k not in axes]
    G_ref, cov = None, np.full((9, 9), np.nan)
    ref_err = ""
    if o is not None:
        try:
            G_ref, cov, rms, n = refine_gyro_matrix(segs, o, G_paper, acc, mag)
            rep.figures.update({"refined_transitions": n, "refined_residual_rms": rms,
                                "refined_vs_paper": float(np.linalg.norm(G_ref - G_paper) / np.linalg.norm(G_paper))})
        except FitError as e:
            rep.figures["refined_transitions"] = 0
            ref_err = str(e)
    sigma: dict[str, Any] = {}
    if missing and G_ref is None:
        # Any rotation: the field (and gravity while quasi-static) seen from the turning body. Clipped
        # readings (at the rail) hold a rate that is not the body's: their windows stay out of the fit.
        rails = gyro_rails(segs)
        clips = [clipped_stretches(s.data, rails) for s in segs]
        excl = [np.convolve(m, np.ones(3), "same") > 0 for m, _ in clips]  # and one sample either side
        try:
            G_k, o_k, cov12, figs = fit_gyro_kinematic(segs, mag, acc, g, exclude=excl)
            if o is not None and sig_o is not None:
                # Rests measure the bias directly (eqs. 34-35); the joint fit's bias absorbs whatever
                # else the spans disagree on (MARG set: 2.6 mrad/s on y, ~3σ, and the unmoved files
                # close at 8.7-9.7° with it against 1.6-3.0° with the rests'). G is refitted given o.
                o_joint, cov_joint = o_k, cov12
                G_k, o_k, cov12, figs = fit_gyro_kinematic(segs, mag, acc, g, bias=o, exclude=excl)
                figs["bias_joint_fit"] = o_joint.tolist()
                # σ of G: the joint fit's, marginal over the bias (given the bias it would be optimistic by
                # what a per-recording bias offset does to G, which the rests cannot rule out)
                cov12 = cov_joint
        except FitError as e:
            what = "".join("xyz"[k] for k in missing)
            rep.warnings.append(
                f"gyro: scale and axes undetermined (no rotation phase about {what}; {ref_err or 'no rests'}; {e}): "
                "the matrix is left at identity and is NOT a calibration; record turns about all three axes "
                "(a rest before and after each, or with the magnetometer logging)")
            rep.figures["undetermined"] = ["scale", "alpha", "xi"]
            rep.figures["method"] = "none (bias only)"
            if o is None or sig_o is None:
                raise FitError(f"gyro: no rest for the bias and {e}") from e
            sigma["bias"] = sig_o.tolist()
            return SensorCalibration(o, np.eye(3), sigma), rep
        rep.figures["any_rotation"] = figs
        rep.figures["method"] = "any rotation (eq. 36 generalised: v' = v x w, v the field or gravity)"
        if o is not None and sig_o is not None:
            rep.figures["bias_rests_minus_any_rotation"] = (o - np.asarray(figs["bias_joint_fit"])).tolist()
            bias_from = "rests (eqs. 34-35); the matrix fitted given it"
        else:
            Gi = np.linalg.inv(G_k)
            o, sig_o = o_k, np.sqrt(np.abs(np.diag(Gi @ cov12[9:, 9:] @ Gi.T)))
            bias_from = "any rotation, fitted with the matrix"
        G, cov = G_k, cov12[:9, :9]
        use_phase_sigma = False
        rep.figures["clipped"] = _clip_report(segs, clips, rails, G, o, mag, rep.warnings)
        rep.figures["bias_per_file"] = bias_per_file(segs)
    else:
        if o is None:
            raise FitError("gyro bias: no static interval (need a rest to fit eqs. 34–35)")
        # The paper's phase-based estimate wherever phases cover all three axes (it is the more precise:
        # it does not inherit the accel/mag alignment); the all-transitions fit otherwise.
        G = G_paper if (not missing or G_ref is None) else G_ref
        rep.figures["method"] = ("phases (eqs. 28-31, 36)" if G is G_paper
                                 else "all transitions (eq. 36 generalised)")
        use_phase_sigma = G is G_paper and not missing
    rep.figures["bias_from"] = bias_from
    # σ: the fit's covariance, drawn through the decomposition. For the phase method that is an upper
    # bound: it serves for the scale (eq. 36 compares the same reference angles), but the axis
    # directions of eqs. 28–31 are known from the phases' own sample scatter — 10–20× tighter on the
    # simulated paper session, where the bound was 10–20× the actual error of alpha and xi (a batch-started
    # filter holds those as consider states: an inflated σ there costs the other terms information).
    sigma["bias"] = np.asarray(sig_o).tolist()
    if np.all(np.isfinite(cov)):
        L = sqrt_psd(cov)
        par, ok = decompose_many((G.ravel() + rng.standard_normal((48, 9)) @ L.T).reshape(-1, 3, 3))
        if ok.mean() < 0.9:
            # the fit's uncertainty reaches a singular matrix: scale and axes are not determined
            cov = np.full((9, 9), np.nan)
            ref_err = ref_err or "the fit's σ reaches a singular gyro matrix"
    if np.all(np.isfinite(cov)):
        sd = np.std(par[ok], axis=0)
        if use_phase_sigma:
            sd[3:] = phase_matrix_sigma(axes, scales, sd[:3], rng)[3:]
            rep.figures["sigma_angles"] = "phase scatter (eqs. 28-31)"
        sigma.update({"scale": sd[:3].tolist(), "alpha": sd[3:6].tolist(), "xi": sd[6:].tolist(),
                      "matrix": np.sqrt(np.diag(cov)).reshape(3, 3).tolist()})
    else:
        rep.figures["undetermined"] = ["scale", "alpha", "xi"]
        what = "".join("xyz"[k] for k in missing)
        why = (f": no usable phase about {what}" if what else "") + (f"; {ref_err}" if ref_err else "")
        rep.warnings.append(f"gyro: scale and axes undetermined (σ absent){why}; the matrix is NOT a calibration")
    return SensorCalibration(o, G, sigma), rep


# -- any rotation: a world-fixed vector seen from the turning body (ṁ = −ω × m) ----------------------------

_EPS = np.zeros((3, 3, 3))
_EPS[0, 1, 2] = _EPS[1, 2, 0] = _EPS[2, 0, 1] = 1.0
_EPS[0, 2, 1] = _EPS[2, 1, 0] = _EPS[1, 0, 2] = -1.0


def _kinematic_rows(t: Array, w: Array, v: Array, ok: NDArray[np.bool_], win: int,
                    chunk: int = 40000) -> tuple[Array, Array, Array]:
    """Equations of one log for :func:`fit_gyro_kinematic`: over each window of ``win`` samples,
    ``v(t_b) − v(t_a) = ∫ v × ω dt`` with ``ω = G w − b`` (the body frame sees a world-fixed unit vector v
    turn as v̇ = −ω × v = v × ω; exact for any rotation, integrated by the trapezoid rule).

    t (N,), w (N, 3) raw rate, v (N, 3) unit vector at the IMU times, ok (N,) usable samples.
    Returns (A (3K, 12) for the unknowns vec(G) row-major and b, y (3K,), window start index (K,)).
    Worked in chunks of about ``chunk`` samples: memory stays bounded for any log length.
    """
    n = t.size
    bad = np.concatenate([[0], np.cumsum(~ok)])
    starts = np.arange(0, n - win, win)
    good = (bad[starts + win + 1] - bad[starts]) == 0
    starts = starts[good]
    if starts.size == 0:
        return np.zeros((0, 12)), np.zeros(0), starts
    # Gather each window's own win+1 samples (windows need not be adjacent: where the reference is
    # unusable they are sparse, and a chunk of windows must not span the samples between them).
    per = max(1, chunk // (win + 1))
    A = np.empty((starts.size, 3, 12))
    steps = np.arange(win + 1)
    for c0 in range(0, starts.size, per):
        idx = starts[c0:c0 + per, None] + steps  # (k, win+1)
        vv, ww = v[idx], w[idx]
        # v × (G w) = [v]× G w: entry i is Σ_jk ε_ijk v_j Σ_l G_kl w_l → coefficient of G_kl is [v]×_ik w_l
        vx = np.einsum("ijk,mnj->mnik", _EPS, vv)  # [v]× per sample (k, win+1, 3, 3)
        k = idx.shape[0]
        blk = np.concatenate([(vx[..., None] * ww[:, :, None, None, :]).reshape(k, win + 1, 3, 9), -vx], axis=3)
        dt = np.diff(t[idx], axis=1)[:, :, None, None]
        A[c0:c0 + per] = (0.5 * (blk[:, 1:] + blk[:, :-1]) * dt).sum(axis=1)  # trapezoid over the window
    y = (v[starts + win] - v[starts]).ravel()
    return A.reshape(-1, 12), y, starts


def fit_gyro_kinematic(segs: list[Segmentation], mag: SensorCalibration | None, acc: SensorCalibration | None,
                       g: float, window_s: float = 0.5, quasi_static: float = 0.3,
                       bias: Array | None = None, exclude: list[NDArray[np.bool_]] | None = None
                       ) -> tuple[Array, Array, Array, dict]:
    """Gyro matrix G and bias o from any rotation (eq. 36 generalised to a continuum of short spans).

    A world-fixed vector v seen in the body frame obeys v̇ = v × ω (ω = G (w_raw − o)): the calibrated,
    normalised magnetometer always (its field is world-fixed), and the calibrated accelerometer where
    the unit is quasi-static (moving std over 0.5 s below ``quasi_static`` m/s² and ‖a‖ within
    ``quasi_static`` of g: gravity). Integrated over windows of ``window_s``,
    ``v(t_b) − v(t_a) = Σ v × (G w − b) dt`` is linear in the 12 unknowns (G, b = G o): one least-squares
    solve, windows beyond 5 MAD (a disturbance, a knock) dropped and the solve repeated. Bias, scale,
    misalignment, non-orthogonality, a wrong axis sign and a mounting rotation of any angle are all
    inside G. G comes out in the frame of the reference vectors (the magnetometer's when it is given).

    ``bias`` (3,) raw rad/s: known (the rests' eqs. 34–35) — the rows then hold G alone (9 unknowns), the
    returned o is ``bias`` and the covariance's bias block is zero. ``exclude``: per log, an (N,) mask of IMU
    samples no window may contain (clipped readings: their rate is not the body's).

    Returns (G (3, 3), o (3,), covariance of (vec G, b) (12, 12), figures). Raises FitError when the
    rotation seen does not determine all 12 unknowns (the smallest singular value of the design names
    the unexcited direction).
    """
    As, ys, src = [], [], []
    for i_s, s in enumerate(segs):
        d = s.data
        if d.n_imu < 50:
            continue
        gyr = d.gyro if bias is None else d.gyro - bias
        usable = np.ones(d.n_imu, bool) if exclude is None else ~exclude[i_s]
        win = max(2, int(round(window_s * d.imu_rate)))
        t = d.t_imu
        refs = []
        if mag is not None and d.n_mag >= 20:
            m = mag.apply(d.mag)
            m /= np.linalg.norm(m, axis=1, keepdims=True)
            v = np.column_stack([np.interp(t, d.t_mag, m[:, k]) for k in range(3)])
            v /= np.linalg.norm(v, axis=1, keepdims=True)
            # usable where a mag sample lies within 2 mag periods (no bridging of mag gaps)
            per = (d.t_mag[-1] - d.t_mag[0]) / max(1, d.n_mag - 1)
            j = np.clip(np.searchsorted(d.t_mag, t), 1, d.n_mag - 1)
            near = np.minimum(np.abs(t - d.t_mag[j - 1]), np.abs(d.t_mag[j] - t)) <= 2 * per
            ok = near & (t >= d.t_mag[0]) & (t <= d.t_mag[-1])
            refs.append(("mag", v, ok))
        if acc is not None and mag is None:
            a = acc.apply(d.acc)
            _, sd = moving_std(a, max(5, int(round(0.5 * d.imu_rate))))
            nrm = np.linalg.norm(a, axis=1)
            ok = (np.linalg.norm(sd, axis=1) < quasi_static) & (np.abs(nrm - g) < quasi_static)
            refs.append(("accel", a / nrm[:, None], ok))
        for name, v, ok in refs:
            A, y, _ = _kinematic_rows(t, gyr, v, ok & usable, win)
            if bias is not None:
                A = A[:, :9]  # the bias is known (rests, eqs. 34-35): G alone
            if A.shape[0]:
                As.append(A)
                ys.append(y)
                src.append((d.source, name, A.shape[0] // 3))
    if not As:
        raise FitError("gyro (any rotation): no span with a reference vector (magnetometer, or accelerometer "
                       "while quasi-static)")
    A = np.concatenate(As)
    y = np.concatenate(ys)
    keep = np.ones(A.shape[0] // 3, bool)
    for _ in range(3):
        rows = np.repeat(keep, 3)
        x, *_ = np.linalg.lstsq(A[rows], y[rows], rcond=None)
        r = (y - A @ x).reshape(-1, 3)
        rn = np.linalg.norm(r, axis=1)
        lim = 5 * 1.4826 * np.median(rn[keep]) + 1e-12
        new = rn <= lim
        if np.array_equal(new, keep):
            break
        keep = new
    rows = np.repeat(keep, 3)
    sv = np.linalg.svd(A[rows], compute_uv=False)
    nx = A.shape[1]
    if sv[-1] < 1e-6 * sv[0]:
        raise FitError("gyro (any rotation): the rotations seen do not determine every gyro term (turn the unit "
                       "about all three axes)")
    r = y[rows] - A[rows] @ x
    dof = max(1, r.size - nx)
    s2 = float(r @ r / dof)
    # Adjacent windows share an end point (its noise enters both with opposite sign): σ is inflated by
    # √2 to stay on the safe side of that correlation.
    cov = np.zeros((12, 12))
    cov[:nx, :nx] = np.linalg.inv(A[rows].T @ A[rows]) * s2 * 2.0
    G = x[:9].reshape(3, 3)
    o = np.linalg.solve(G, x[9:]) if bias is None else np.asarray(bias, float)
    figs = {"spans": int(keep.sum()), "spans_dropped": int((~keep).sum()), "window_s": window_s,
            "residual_rms": float(np.sqrt(s2)), "references": sorted({n for _, n, _ in src}),
            "condition": float(sv[0] / sv[-1])}
    return G, o, cov, figs


# -- saturation: readings at the gyro's rail (issue 11: tilt-sphere) ------------------------------------------

RAIL_MIN = 1.0  # rad/s: no gyro rail lies below (the smallest MEMS range, ±250 °/s, is 4.36 rad/s)


@dataclass
class ClippedStretch:
    """One run of consecutive IMU samples with a gyro axis at its rail: samples [i0, i1) of its log,
    times t0–t1 (s, on the batch's clock), clipped raw axes, and — where bridged — the rotation the
    clipped readings missed (deg, |∫ G e dt| of the excess e the field kinematics give)."""

    i0: int
    i1: int
    t0: float
    t1: float
    axes: str
    lost_deg: float | None = None


def gyro_rails(segs: list[Segmentation]) -> Array:
    """The raw gyro rail per axis (3,) rad/s, NaN where an axis has none: an axis whose largest magnitude
    over all logs exceeds :data:`RAIL_MIN` and recurs in at least :data:`onlinecal.specs.RAIL_SAMPLES` samples (a true
    peak is reached once; a clipped reading repeats the sensor's full-scale value)."""
    g = np.concatenate([np.abs(s.data.gyro) for s in segs if s.data.n_imu]) if segs else np.zeros((0, 3))
    out = np.full(3, np.nan)
    if g.shape[0] == 0:
        return out
    top, _, ok = rail_samples(g, RAIL_MIN)
    out[ok] = top[ok]
    return out


def clipped_stretches(data: ImuData, rails: Array) -> tuple[NDArray[np.bool_], list[ClippedStretch]]:
    """Samples of ``data`` with a gyro axis at its rail (``rails`` (3,), from :func:`gyro_rails`):
    (mask (N,), runs of consecutive clipped samples)."""
    lim = np.where(np.isfinite(rails), rails * (1 - RAIL_TOL), np.inf)
    at = np.abs(data.gyro) >= lim
    m: NDArray[np.bool_] = np.asarray(at.any(axis=1), dtype=bool)
    edge = np.diff(np.concatenate([[0], m.astype(np.int8), [0]]))
    runs = []
    for a, b in zip(np.flatnonzero(edge == 1), np.flatnonzero(edge == -1), strict=True):
        ax = "".join("xyz"[k] for k in range(3) if at[a:b, k].any())
        runs.append(ClippedStretch(int(a), int(b), float(data.t_imu[a]), float(data.t_imu[b - 1]), ax))
    return m, runs


def bridge_clipped(data: ImuData, G: Array, o: Array, mag: SensorCalibration, rails: Array,
                   runs: list[ClippedStretch]) -> Array:
    """Raw gyro (N, 3) with each clipped run's lost excess restored from the field kinematics (eq. 36
    generalised, v̇ = v × ω): over the run and one sample either side, the measured change of the
    calibrated unit field v is ``Δv = Σ v × G (w − o) dt``; with the clipped axis k reading its rail, the
    true raw rate is ``w_k = rail_k·sign + c_k·p(t)`` with p a parabolic cap (zero one sample outside the
    run, 1 at its middle). The c_k of the run's clipped axes solve the three equations by least squares
    (where the field is nearly along a clipped axis, that axis is not observable and is left clipped).
    Sets ``lost_deg`` of each run. Evidence only: the batch's fits leave clipped samples out instead.
    """
    w = data.gyro.copy()
    if data.n_mag < 2 or not runs:
        return w
    m = mag.apply(data.mag)
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    t = data.t_imu
    v = np.column_stack([np.interp(t, data.t_mag, m[:, k]) for k in range(3)])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for r in runs:
        a, b = max(0, r.i0 - 1), min(data.n_imu, r.i1 + 1)  # one unclipped sample either side
        if b - a < 3:
            continue
        tt, vv = t[a:b], v[a:b]
        dt = np.diff(tt)[:, None]
        wc = (w[a:b] - o) @ G.T
        f = np.cross(vv, wc)
        y = vv[-1] - vv[0] - (0.5 * (f[1:] + f[:-1]) * dt).sum(axis=0)
        mid, half = 0.5 * (tt[0] + tt[-1]), 0.5 * (tt[-1] - tt[0])
        p = np.clip(1.0 - ((tt - mid) / half) ** 2, 0.0, None)
        cols, axes = [], []
        for k in range(3):
            if "xyz"[k] not in r.axes:
                continue
            fk = np.cross(vv, np.outer(p, G[:, k]))  # v × G e_k p(t)
            cols.append((0.5 * (fk[1:] + fk[:-1]) * dt).sum(axis=0))
            axes.append(k)
        X = np.column_stack(cols)
        sv = np.linalg.svd(X, compute_uv=False)
        if sv[-1] < 0.2 * (4.0 / 3.0) * half:  # ∫p dt = 4/3·half: the field within ~12° of a clipped axis
            continue
        c, *_ = np.linalg.lstsq(X, y, rcond=None)
        exc = np.zeros((b - a, 3))
        for ck, k in zip(c, axes, strict=True):
            sgn = np.sign(np.median(w[r.i0:r.i1, k]))
            # only an excess beyond the rail is physical: the true rate lies outside the clipped value
            exc[:, k] = sgn * max(0.0, float(ck * sgn)) * p
        w[a:b] += exc
        ex = exc @ G.T
        r.lost_deg = float(np.degrees(np.linalg.norm((0.5 * (ex[1:] + ex[:-1]) * dt).sum(axis=0))))
    return w


def _clip_report(segs: list[Segmentation], clips: list[tuple[NDArray[np.bool_], list[ClippedStretch]]],
                 rails: Array, G: Array, o: Array, mag: SensorCalibration | None, warnings: list[str]) -> dict:
    """Per file with gyro readings at the rail: a warning naming the file, the clipped samples and times and
    the rotation they lost (bridged by the field kinematics, :func:`bridge_clipped`), and its figures."""
    out: dict[str, Any] = {}
    for s, (m, runs) in zip(segs, clips, strict=True):
        if not runs:
            continue
        if mag is not None:
            bridge_clipped(s.data, G, o, mag, rails, runs)
        lost = [r.lost_deg for r in runs if r.lost_deg is not None]
        t0 = s.data.t_imu[0]
        where = ", ".join(f"{r.t0 - t0:.2f}–{r.t1 - t0:.2f} s ({r.axes})" for r in runs[:6])
        more = f" and {len(runs) - 6} more" if len(runs) > 6 else ""
        hit = set("".join(r.axes for r in runs))
        rail = ", ".join(f"{'xyz'[k]} ±{rails[k]:.4g}" for k in range(3) if "xyz"[k] in hit)
        lost_txt = (f"; the field kinematics put the rotation the clipped readings missed at ≈ {sum(lost):.0f}° "
                    f"in all ({max(lost):.0f}° in the worst stretch)" if lost else "")
        warnings.append(f"gyro: {s.data.source}: {int(m.sum())} samples at the gyro's rail ({rail} rad/s) in "
                        f"{len(runs)} stretch(es) at {where}{more} after its start{lost_txt}: a clipped gyro loses "
                        "rotation that no calibration restores (those spans are left out of the gyro fit, and "
                        "integrating this file's gyro cannot close its attitude)")
        out[s.data.source] = {"samples": int(m.sum()), "stretches": [
            {"t0_s": r.t0 - t0, "t1_s": r.t1 - t0, "axes": r.axes, "lost_deg": r.lost_deg} for r in runs],
            "lost_deg_total": float(sum(lost)) if lost else None}
    return out


PER_FILE_EDGE_S = 1.0  # s: a per-file bias keeps off each file's first and last second (the closure check's ends)


def bias_per_file(segs: list[Segmentation]) -> dict[str, dict[str, Any]]:
    """Each recording's own gyro bias (a per-power-up nuisance: an MPU6050's turn-on bias differs by
    mrad/s between power-ups) from its own strict rests (eqs. 34–35 for one file: the mean raw rate, the
    least-squares slope of the cumulative sum), using only samples more than :data:`PER_FILE_EDGE_S` from
    the file's ends. Returns file → {"bias" (3,) rad/s, "sigma" (3,), "samples", "temp_c", "from"}, or
    {"bias": None, "why": ...} where the file never rests. σ: the larger of the white-noise standard
    error and the scatter of 5-s block means over √blocks (the bias wanders within a file)."""
    out: dict[str, dict[str, Any]] = {}
    for s in segs:
        d = s.data
        if d.n_imu == 0:
            continue
        lo, hi = d.t_imu[0] + PER_FILE_EDGE_S, d.t_imu[-1] - PER_FILE_EDGE_S
        idx = np.concatenate([np.arange(iv.i0, iv.i1) for iv in s.rests] or [np.zeros(0, np.intp)])
        idx = idx[(d.t_imu[idx] >= lo) & (d.t_imu[idx] <= hi)] if idx.size else idx
        if idx.size < 100:
            out[d.source] = {"bias": None, "why": "no rest in this file away from its first and last second "
                             "(a hand never holds still long enough: the pooled bias applies)"}
            continue
        w = d.gyro[idx]
        se = w.std(axis=0) / np.sqrt(idx.size)
        blk = max(1, int(round(5.0 * d.imu_rate)))
        nb = idx.size // blk
        if nb >= 2:
            bm = w[: nb * blk].reshape(nb, blk, 3).mean(axis=1)
            se = np.maximum(se, bm.std(axis=0, ddof=1) / np.sqrt(nb))
        temp = d.temp[idx]
        out[d.source] = {"bias": w.mean(axis=0).tolist(), "sigma": se.tolist(), "samples": int(idx.size),
                         "temp_c": float(np.nanmean(temp)) if np.isfinite(temp).any() else None,
                         "from": f"this file's rests, {PER_FILE_EDGE_S:.0f} s or more from its ends"}
    return out


def axis_gain_from_transitions(segs: list[Segmentation], G: Array, o: Array, acc: SensorCalibration | None,
                               mag: SensorCalibration | None, axis: int, skip: set[tuple[int, int]] | None = None
                               ) -> tuple[float, float, int]:
    """How much the rest-to-rest motions want row ``axis`` of G scaled (eq. 36 generalised, one factor f):
    the residuals ``v_after − Cᵀ v_before`` of :func:`refine_gyro_matrix` with ``G[axis] *= f``, linearised
    about f = 1 and solved by least squares; σ from the residual scatter (each residual component an
    independent draw). ``skip``: (log index, motion index) pairs left out — e.g. the turns whose angle is
    being checked, so the factor is not fitted to them. Returns (f, 1σ, motions used).

    A turn about the vertical leaves gravity unchanged: its own angle is not in its residual, and the
    factor comes from the other motions (the faces of a Ferraris session)."""
    skip = skip or set()
    incs: list[Array] = []
    pairs: list[tuple[int, Array, Array]] = []
    for j, s in enumerate(segs):
        for i, iv in enumerate(s.motions):
            # the motions refine_gyro_matrix uses (_collect_transitions), less the skipped ones
            if (j, i) in skip or s.gapped(iv) or s.noisy(iv) or iv.duration > MAX_TRANSITION_S:
                continue
            vecs = _vectors(s, acc, mag, iv)
            if not vecs:
                continue
            t = s.data.t_imu[iv.i0:iv.i1]
            w = s.data.gyro[iv.i0:iv.i1] - o
            incs.append(0.5 * (w[1:] + w[:-1]) * np.diff(t)[:, None])
            pairs += [(len(incs) - 1, v0, v1) for v0, v1, _ in vecs]
    if len(pairs) < 2:
        raise FitError("too few rest-to-rest motions to test a gyro axis scale")

    def r(f: float) -> Array:
        G2 = G.copy()
        G2[axis] *= f
        out = []
        for i, v0, v1 in pairs:
            C = ordered_product(rodrigues(incs[i] @ G2.T)[None])[0]
            out.append(v1 - C.T @ v0)
        return np.concatenate(out)

    h = 1e-4
    r0 = r(1.0)
    J = (r(1.0 + h) - r0) / h
    f = 1.0 - float(J @ r0) / float(J @ J)
    r1 = r(f)
    s2 = float(r1 @ r1) / max(1, r1.size - 1)
    return f, float(np.sqrt(s2 / float(J @ J))), len({p[0] for p in pairs})


def per_file_calibrations(cal: Calibration) -> dict[str, Calibration]:
    """One calibration per recording that rests, for an out-of-fit check that applies only matrix and bias
    (``../shared/tools/gyro_closure.py``): the batch's calibration with the gyro bias (and its σ) replaced by
    that file's own (:func:`bias_per_file`, in ``meta.batch.steps.gyro.figures.bias_per_file``); everything
    else pooled. Files without their own bias are absent. Returns file → calibration."""
    meta = cal.meta.get("batch", {}) if cal.meta else {}
    per = meta.get("steps", {}).get("gyro", {}).get("figures", {}).get("bias_per_file", {})
    g = cal.gyro
    out: dict[str, Calibration] = {}
    if g is None:
        return out
    for src, r in per.items():
        if r.get("bias") is None:
            continue
        sig = {k: v for k, v in g.sigma.items()}
        sig["bias"] = list(r["sigma"])
        gf = SensorCalibration(np.asarray(r["bias"], float), g.matrix, sig)
        out[src] = cal.replace(gyro=gf, meta={"per_file_bias_of": src, **dict(cal.meta or {})})
    return out
