"""Magnetometer (eqs. 17–27) and accelerometer (eq. 32 + eqs. 25–27) calibration from segmented logs."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..model import SensorCalibration
from .align import phase_plane_normal, rotation_to_axes
from .decomp import decompose_many
from .ellipsoid import (
    SOFT_DIAG_SIGMA,
    SOFT_OFF_SIGMA,
    FitError,
    NormFit,
    fit_ellipsoid_svd,
    fit_norm_lm,
    fit_norm_map,
    psd_excess,
    soft_iron_prior_sigma,
    sphere_bin_weights,
    sqrtm_spd,
)
from .segment import Phase, Segmentation, moving_std

Array = NDArray[np.float64]

_IU = np.triu_indices(3)
# Generators of so(3): a @ _SKEW = [a]×.
_SKEW = np.array([[[0, 0, 0], [0, 0, -1], [0, 1, 0]], [[0, 0, 1], [0, 0, 0], [-1, 0, 0]],
                  [[0, -1, 0], [1, 0, 0], [0, 0, 0]]], float)


@dataclass
class StepReport:
    """What one step did, for the batch report: figures and warnings."""

    name: str
    figures: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"figures": self.figures, "warnings": list(self.warnings)}


def sqrt_psd(cov: Array) -> Array:
    """L with L Lᵀ = cov for a symmetric positive semi-definite cov (reduced fits are singular)."""
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    return V * np.sqrt(np.clip(w, 0.0, None))


def propagate_sigma(
    o: Array, M: Array, cov9: Array, Q: Array, sig_align: float, rng: np.random.Generator, n: int = 64
) -> dict[str, list[float]]:
    """1σ of bias, scale, alpha, xi for ``Q · M`` by Monte Carlo over the fit covariance (o, upper
    triangle of symmetric M) and an isotropic alignment error of ``sig_align`` rad."""
    if not np.all(np.isfinite(cov9)):
        return {"bias": np.sqrt(np.abs(np.diag(cov9))[:3]).tolist()}
    L = sqrt_psd(cov9)
    p0 = np.concatenate([o, M[np.triu_indices(3)]])
    p = p0 + rng.standard_normal((n, 9)) @ L.T
    a = rng.normal(0, sig_align, (n, 3))
    Ra = np.eye(3) + np.einsum("nk,kij->nij", a, _SKEW)
    Ms = np.zeros((n, 3, 3))
    Ms[:, _IU[0], _IU[1]] = p[:, 3:]
    Ms = Ms + np.triu(Ms, 1).transpose(0, 2, 1)
    par, ok = decompose_many(Ra @ Q @ Ms)  # closed form, all draws at once
    if ok.mean() < 0.9:  # the draws reach across a singular matrix: no σ of the split is meaningful
        return {"bias": np.sqrt(np.abs(np.diag(cov9))[:3]).tolist()}
    d = np.concatenate([p[ok, :3], par[ok]], axis=1)
    sd = d.std(axis=0)
    return {"bias": sd[:3].tolist(), "scale": sd[3:6].tolist(), "alpha": sd[6:9].tolist(),
            "xi": sd[9:12].tolist()}


def _align(
    segs: list[Segmentation],
    samples: Callable[[Segmentation, Phase], Array],
    M0: Array,
    o: Array,
    min_radius: float,
    report: StepReport,
) -> tuple[Array, float]:
    """T_R from phases (eqs. 25–27): pooled plane normals per axis, then Procrustes. Returns (Q, σ)."""
    acc: dict[int, list[tuple[Array, float]]] = {}
    sig = []
    for seg in segs:
        for ph in seg.phases:
            v = (samples(seg, ph) - o) @ M0.T
            if v.shape[0] < 10:
                continue
            n, radius, share = phase_plane_normal(v, ph.axis)
            if radius < min_radius or share < 0.5:
                continue
            resid = (v - v.mean(0)) @ n
            sig.append(float(np.std(resid) / (radius * np.sqrt(v.shape[0]))))
            acc.setdefault(ph.axis, []).append((n, radius**2 * v.shape[0]))
    normals = {}
    for k, lst in acc.items():
        n = np.sum([w * n for n, w in lst], axis=0)
        normals[k] = (n / np.linalg.norm(n), float(sum(w for _, w in lst)))
    report.figures["aligned_axes"] = "".join("xyz"[k] for k in sorted(normals))
    if len(normals) < 2:
        report.figures["undetermined"] = ["alpha"]
        report.warnings.append(
            f"{report.name}: rotation phases usable for alignment about {len(normals)} "
            f"{'axis' if len(normals) == 1 else 'axes'} (need 2): T_R is "
            + ("partly determined" if normals else "taken as identity")
        )
    Q = rotation_to_axes(normals)
    return Q, float(np.sqrt(np.mean(np.square(sig)))) if sig else 0.0


def _mag_samples(seg: Segmentation, ph: Phase) -> Array:
    d = seg.data
    m = (d.t_mag >= ph.t0) & (d.t_mag <= ph.t1)
    return d.mag[m]


def _lpf(x: Array, w: int) -> Array:
    return moving_std(x, w)[0] if x.shape[0] >= w else x


def _acc_samples(seg: Segmentation, ph: Phase) -> Array:
    # Low-pass filtered (paper Sec. III-B): centripetal and hand jitter average out.
    w = max(3, int(round(0.1 * seg.data.imu_rate)))
    return _lpf(seg.data.acc[ph.i0 : ph.i1], w)


def _runs_text(t: Array, bad: NDArray[np.bool_], gap: float = 1.0) -> tuple[int, str]:
    """Stretches of ``bad`` samples (times t) merged across gaps < ``gap`` s: (count, "t0–t1 s, …")."""
    tb = t[bad]
    if tb.size == 0:
        return 0, ""
    cut = np.flatnonzero(np.diff(tb) > gap)
    starts = np.concatenate([[tb[0]], tb[cut + 1]])
    ends = np.concatenate([tb[cut], [tb[-1]]])
    txt = ", ".join(f"{a:.1f}–{b:.1f} s" for a, b in list(zip(starts, ends, strict=True))[:5])
    return int(starts.size), txt + (" …" if starts.size > 5 else "")


MIN_COVERAGE = 0.2  # smallest eigenvalue of the binned E[u uᵀ] of calibrated field directions


def _lm_diverged(fit: NormFit, o0: Array, M0: Array) -> bool:
    """True when LM moved the centre by more than 0.3 field radii or a singular value of M by more than
    30 % from the algebraic start: a degenerate valley, not a refinement (eq. 17 refines; it does not
    re-decide the ellipsoid)."""
    step = float(np.linalg.norm(M0 @ (fit.o - o0)))
    s0, s1 = np.linalg.svd(M0, compute_uv=False), np.linalg.svd(fit.M, compute_uv=False)
    return step > 0.3 or bool(np.any(np.abs(s1 / s0 - 1) > 0.3))


def _close_stretches(t: Array, fid: Array, bad: NDArray[np.bool_], gap: float) -> NDArray[np.bool_]:
    """``bad`` with the samples between two bad ones of the same file less than ``gap`` s apart set too:
    inside a disturbance the norm can pass through its undisturbed value (an added field at the right
    angle), and those samples are just as wrong."""
    out = bad.copy()
    i = np.flatnonzero(bad)
    if i.size < 2:
        return out
    close = (np.diff(t[i]) < gap) & (fid[i[1:]] == fid[i[:-1]]) & (np.diff(i) > 1)
    for a, b in zip(i[:-1][close], i[1:][close], strict=True):
        out[a:b] = True
    return out


def dip_outliers(segs: list[Segmentation], acc: SensorCalibration, mag: SensorCalibration,
                 tol_deg: float = 3.0) -> tuple[int, list[str]]:
    """Rests whose field direction disagrees with the others: the angle between calibrated gravity and the
    calibrated field (the dip) is the same at every attitude; a rest whose dip differs by more than
    ``tol_deg`` from the median (a disturbance whose norm happens to look right) loses its mag samples
    (``seg.data`` is replaced). Returns (samples removed, one line per rest)."""
    rows = []
    for sg in segs:
        d = sg.data
        for iv in sg.statics:
            m = (d.t_mag >= iv.t0) & (d.t_mag <= iv.t1)
            if m.sum() < 3:
                continue
            a = acc.apply(d.acc[iv.i0:iv.i1].mean(0))
            f = mag.apply(d.mag[m]).mean(0)
            dip = float(np.degrees(np.arccos(np.clip(a @ f / np.linalg.norm(a) / np.linalg.norm(f), -1, 1))))
            rows.append((sg, iv, m, dip))
    if len(rows) < 4:
        return 0, []
    med = float(np.median([r[3] for r in rows]))
    n, lines = 0, []
    drop: dict[int, tuple[Segmentation, NDArray[np.bool_]]] = {}
    for sg, iv, m, dip in rows:
        if abs(dip - med) > tol_deg:
            n += int(m.sum())
            prev = drop.get(id(sg), (sg, np.zeros_like(m)))[1]
            drop[id(sg)] = (sg, prev | m)
            lines.append(f"{sg.data.source} {iv.t0:.1f}–{iv.t1:.1f} s (dip {dip:.1f}° against {med:.1f}°)")
    for sg, m in drop.values():
        sg.data = replace(sg.data, t_mag=sg.data.t_mag[~m], mag=sg.data.mag[~m])
    return n, lines


TRIM_KEEP = 80.0  # percent of the samples (by residual) the trimmed refit keeps each round
TRIM_BENT = 3.0  # the full fit is bent by a minority when its residual MAD is this many times the trimmed fit's


def _trimmed_fit(x: Array, use: NDArray[np.bool_], fit: NormFit, floor: float = 0.02) -> NormFit | None:
    """A fit of eq. 17 on the majority of the samples, when a minority bent the full one; else None.

    A passing disturbance (0.5 G for 30 s: a tenth of a paper session) puts samples far off the sphere,
    where the coverage bins (:func:`sphere_bin_weights`) are empty and give them a high weight: the full
    fit bends towards them until their residuals no longer stand out against the (now large) MAD, and
    nothing is excluded. Refitted 4 times on the ``TRIM_KEEP`` % best-fitting samples, the fit returns to
    the majority's sphere; it is taken when the full fit's residual MAD is ``TRIM_BENT`` × the trimmed
    one's (a clean log: about 1.3×). Skipped when the full fit's MAD is already below ``floor`` (the least
    residual ever called an outlier). x (N, 3) raw, ``use`` (N,) the samples of the shape fit."""
    def resid(f: NormFit) -> Array:
        out: Array = np.linalg.norm((x - f.o) @ f.M.T, axis=1) - 1.0
        return out

    def mad(r: Array) -> float:
        return 1.4826 * float(np.median(np.abs(r - np.median(r))))

    mad_all = mad(resid(fit)[use])
    if mad_all < floor or use.sum() < 100:
        return None
    f, keep = fit, use.copy()
    for _ in range(4):
        r = np.abs(resid(f))
        keep = use & (r <= float(np.percentile(r[keep], TRIM_KEEP)))
        w = sphere_bin_weights((x[keep] - f.o) @ f.M.T, per_bin=30)
        f = fit_norm_lm(x[keep], 1.0, f.o, f.M, weights=w)
    return f if mad_all > TRIM_BENT * mad(resid(f)[keep]) else None


def fit_magnetometer(
    segs: list[Segmentation], rng: np.random.Generator, field_tol: float = 0.05,
) -> tuple[SensorCalibration, StepReport]:
    """Magnetometer: SVD ellipsoid fit (eqs. 19–24) → LM on eq. 17 → T_R,mag from phases (eqs. 25–27).

    The field norm is 1 by definition. Samples are weighted by attitude coverage
    (:func:`~onlinecal.batch.ellipsoid.sphere_bin_weights`, 10° cells, at most 30 samples per cell): a
    10-minute rest counts as one attitude, and the fit's work is bounded whatever the log's length.
    A file whose median calibrated norm differs from 1 by more than ``field_tol`` (another place, a
    disturbance that lasts the whole file) is named in a warning and kept out of the shape fit; samples
    beyond 5 MAD of the norm residual (a passing disturbance, a corrupt reading) are excluded and counted,
    and removed from the segmentations' logs (``seg.data``) so that no later step uses them.
    """
    rep = StepReport("mag")
    with_mag = [s for s in segs if s.data.has_mag]
    xs = [s.data.mag for s in with_mag]
    x = np.concatenate(xs) if xs else np.zeros((0, 3))
    fid = np.concatenate([np.full(len(v), i) for i, v in enumerate(xs)]) if xs else np.zeros(0, int)
    tt = np.concatenate([s.data.t_mag for s in with_mag]) if xs else np.zeros(0)
    if x.shape[0] < 50:
        raise FitError(f"magnetometer: only {x.shape[0]} samples")
    lo, hi = np.percentile(x, [1, 99], axis=0)
    w0 = sphere_bin_weights(x - 0.5 * (lo + hi), per_bin=30)
    # An ellipsoid needs the field seen from directions spanning 3-D: a rest (a point) or a turn
    # about one axis (a circle) leaves it undetermined, and LM would return a degenerate answer.
    sel = w0 > 0
    ev = np.linalg.eigvalsh(np.cov(x[sel].T, aweights=w0[sel]))
    spread = float(np.sqrt(max(ev[0], 0.0)) / np.median(np.linalg.norm(x, axis=1)))
    if spread < 0.05:
        raise FitError(f"magnetometer: the field was seen from too few directions (least spread "
                       f"{100 * spread:.1f} % of the reading, need 5 %); turn the unit through all orientations")
    use = np.ones(x.shape[0], bool)
    excluded: list[str] = []
    for _ in range(3):
        xu = x[use]
        lo, hi = np.percentile(xu, [1, 99], axis=0)
        w = sphere_bin_weights(xu - 0.5 * (lo + hi), per_bin=30)
        o0, M0 = fit_ellipsoid_svd(xu, w)
        w = sphere_bin_weights((xu - o0) @ M0.T, per_bin=30)
        fit = fit_norm_lm(xu, 1.0, o0, M0, weights=w)
        diverged = _lm_diverged(fit, o0, M0)
        if diverged:
            # The field seen over a band of directions (a flight's yaw turns with small tilts): many
            # ellipsoids fit it, and LM slides along the valley to a huge one with a residual below the
            # sensor's noise. The algebraic fit's answer is kept, with the covariance at that point.
            fit = fit_norm_lm(xu, 1.0, o0, M0, weights=w, refine=False)
        nrm_all = np.linalg.norm((x - fit.o) @ fit.M.T, axis=1)
        # Per-file field strength: a file whose field differs is named and left out of the shape fit.
        off = []
        for i in range(len(with_mag)):
            m = fid == i
            med = float(np.median(nrm_all[m])) if m.any() else 1.0
            if use[m].any() and abs(med - 1.0) > field_tol:
                off.append((i, med))
        if not off or use.sum() - sum((fid == i).sum() for i, _ in off) < 50:
            break
        worst = max(off, key=lambda v: abs(v[1] - 1))  # one at a time: a bad file distorts the others
        use &= fid != worst[0]
        excluded.append(f"{with_mag[worst[0]].data.source}: field {100 * (worst[1] - 1):+.0f} % against the other "
                        "files (another place or a lasting disturbance); left out of the magnetometer fit")
    rep.warnings += [f"mag: {e}" for e in excluded]
    trimmed = None if diverged else _trimmed_fit(x, use, fit)
    if trimmed is not None:
        # a minority (a passing disturbance) bent the fit: the majority's fit finds it, below
        fit = trimmed
    if diverged:
        rep.figures["degenerate"] = True
        rep.warnings.append("mag: the field was seen from a band of directions only (no full tumble): the geometric "
                            "fit (eq. 17) is not determined and left the algebraic fit's answer by a field-sized "
                            "step; the algebraic fit (eqs. 19-24) starts a fit with a prior on the soft iron "
                            "instead, and no later step uses the magnetometer as a direction reference")
    Q, sig_a = _align(segs, _mag_samples, fit.M, fit.o, 0.2, rep)
    M = Q @ fit.M
    res = np.linalg.norm((x - fit.o) @ M.T, axis=1) - 1.0
    r_in = res[use]
    mad = 1.4826 * float(np.median(np.abs(r_in - np.median(r_in))))
    bad = use & (np.abs(res) > max(5 * mad, 0.02))
    bad = _close_stretches(tt, fid, bad, 3.0) & use
    if bad.any():
        n_str, txt = _runs_text(tt, bad)
        rep.warnings.append(f"mag: {int(bad.sum())} samples whose field norm is off by more than "
                            f"{100 * max(5 * mad, 0.02):.1f} % (disturbance or corrupt readings) excluded, "
                            f"in {n_str} stretch{'es' if n_str > 1 else ''}: {txt}")
        # The excluded samples leave the logs for every later step too (the gyro's reference vectors).
        for i, sg in enumerate(with_mag):
            g_i = ~bad[fid == i]
            if not g_i.all():
                sg.data = replace(sg.data, t_mag=sg.data.t_mag[g_i], mag=sg.data.mag[g_i])
        if bad[use].mean() > 0.01:
            # Refit without them (the binned fit saw them at a low weight; a long disturbance
            # should not bend the shape).
            keep = use & ~bad
            w = sphere_bin_weights((x[keep] - fit.o) @ fit.M.T, per_bin=30)
            fit = fit_norm_lm(x[keep], 1.0, fit.o, fit.M, weights=w)
            Q, sig_a = _align(segs, _mag_samples, fit.M, fit.o, 0.2, rep)
            M = Q @ fit.M
            res = np.linalg.norm((x - fit.o) @ M.T, axis=1) - 1.0
    good = use & ~bad
    norms = res[good] + 1.0
    # Coverage of the calibrated field directions (attitude-binned): a full tumble gives a smallest
    # eigenvalue of E[u uᵀ] near 1/3 (the paper session 0.30, the MARG set 0.30); a flight's yaw turns with
    # ±20° tilts trace a band (0.10), over which the shape (scale, non-orthogonality) is not determined.
    u = (x[good] - fit.o) @ M.T
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    wu = sphere_bin_weights(u, per_bin=5)
    cover = float(np.linalg.eigvalsh((u * wu[:, None]).T @ u / wu.sum())[0])
    rep.figures["coverage_min_eig"] = cover
    prior_fit = cover < MIN_COVERAGE or diverged
    if prior_fit:
        # Part of the sphere only: eq. 17 extrapolates, and the least-squares covariance does not cover
        # the extrapolation (a valley along the unseen directions). The MAP fit with the soft-iron prior
        # gives the answer and σ that keep the prior's width where the data say nothing (fit_norm_map).
        # from the algebraic start and (unless it slid off) from eq. 17's answer: the valley can hold a
        # second, worse minimum; the one with the smaller raw-unit residual is kept
        cands = []
        for o_s, M_s in [(o0, M0)] + ([] if diverged else [(fit.o, fit.M)]):
            try:
                cands.append(fit_norm_map(x[good], o_s, M_s,
                                          weights=sphere_bin_weights((x[good] - o_s) @ M_s.T, per_bin=30)))
            except FitError:
                continue
        if not cands:
            raise FitError("magnetometer: the prior-regularised ellipsoid fit found no answer")
        fit = min(cands, key=lambda f: f.rms)
        Q, sig_a = _align(segs, _mag_samples, fit.M, fit.o, 0.2, rep)
        M = Q @ fit.M
        res = np.linalg.norm((x - fit.o) @ M.T, axis=1) - 1.0
        norms = res[good] + 1.0
        rep.figures["partial_coverage"] = cover < MIN_COVERAGE
        rep.figures["sigma_source"] = "soft-iron prior"
        rep.figures["soft_iron_prior"] = {"diag_rel": SOFT_DIAG_SIGMA, "offdiag_rel": SOFT_OFF_SIGMA}
    rep.figures.update({
        "samples": int(x.shape[0]),
        "fit_samples": int((w > 0).sum()),
        "outliers": int(bad.sum()),
        "files_excluded": len(excluded),
        "weighting": "attitude bins (10° cells, ≤ 30 samples each)",
        "norm_std_percent": float(100 * norms.std()),
        "raw_norm_std_percent": float(100 * np.linalg.norm(x - x.mean(0), axis=1).std()
                                      / np.linalg.norm(x - x.mean(0), axis=1).mean()),
        "svd_vs_lm_bias": float(np.linalg.norm(o0 - fit.o)),
    })
    file_means = None if prior_fit else _files_disagree(res, fid, good)
    if file_means is not None:
        # one field per file, not one for the session: the σ must cover an error common to a file's samples
        fit = replace(fit, cov=fit.cov + psd_excess(_file_jackknife_cov(x[good], fid[good], fit), fit.cov))
        rep.figures["files_field_spread_percent"] = [round(100 * float(v), 3) for v in file_means]
        rep.warnings.append(
            f"mag: the {len(file_means)} files' fields differ beyond their noise (mean calibrated norm per file "
            f"{100 * min(file_means):+.2f} … {100 * max(file_means):+.2f} % of the field): the hand carried the sensor "
            "through places or gradients; σ cover an error common to each file's samples (jackknife over the "
            "files)")
    sig = propagate_sigma(fit.o, fit.M, fit.cov, Q, sig_a, rng, n=256 if prior_fit else 64)
    if prior_fit:
        und = _prior_undetermined(sig, fit.M, Q, rng)
        if "alpha" in rep.figures.get("undetermined", []):
            # ξ (eq. 6: x the reference axis, y in the xy plane) depends on the frame the matrix is expressed
            # in: without T_R the symmetric fit's ξ is that of another frame (flights: 6–42σ from the truth's)
            und = [u for u in und if not u.startswith("xi")] + ["xi"]
        rep.figures["undetermined"] = sorted(set(rep.figures.get("undetermined", [])) | set(und))
        rep.warnings.append(
            f"mag: the field was seen over part of the sphere only (coverage {cover:.2f}, a full tumble gives 0.3; "
            f"need {MIN_COVERAGE}): the ellipsoid (eq. 17) is extrapolated with a prior on the soft iron (axis gains "
            f"within {100 * SOFT_DIAG_SIGMA:.0f} %, cross terms {100 * SOFT_OFF_SIGMA:.1f} %), whose width its σ "
            "keep along the unseen directions"
            + (f"; not determined by the data (σ above half the prior's): {', '.join('mag.' + u for u in und)}"
               if und else "")
            + "; no later step uses it as a direction reference; turn the unit through all orientations")
    return SensorCalibration(fit.o, M, sig), rep


def _file_jackknife_cov(x: Array, fid: NDArray[np.int_], fit: NormFit) -> Array:
    """Delete-one-file jackknife covariance (9, 9) of the eq. 17 fit (o, upper triangle of M: :class:`NormFit`'s
    layout): the fit refitted without each file in turn (from ``fit``, attitude-binned weights as the batch's),
    (G − 1)/G Σ_g (θ_g − θ̄)(θ_g − θ̄)ᵀ over the G files. Where each file carries its own error (its own field),
    the per-sample σ take a file's thousands of samples for independent draws; the jackknife sees the files as
    the draws. Drawn hand-held files in fields 2 % apart (tests/test_mag_cluster_sigma.py): the centre's z RMS
    11.7 with the per-sample σ, 1.2 with these (a cluster-robust sandwich gave 1.4–1.5)."""
    thetas = []
    for g in np.unique(fid):
        m = fid != g
        w = sphere_bin_weights((x[m] - fit.o) @ fit.M.T, per_bin=30)
        f = fit_norm_lm(x[m], 1.0, fit.o, fit.M, weights=w)
        thetas.append(np.concatenate([f.o, f.M[np.triu_indices(3)]]))
    th = np.array(thetas)
    G = th.shape[0]
    d = th - th.mean(0)
    out: Array = (G - 1) / G * d.T @ d
    return out


def _files_disagree(res: Array, fid: NDArray[np.int_], good: NDArray[np.bool_], p: float = 1e-3) -> list[float] | None:
    """The per-file mean norm residuals (relative to the field) where two or more files' means differ beyond
    what their samples' scatter allows (χ² of the between-file spread against each mean's standard error,
    probability below ``p`` under one field), else None. ``res`` (N,) the norm residuals, ``fid`` (N,) the
    file of each sample, ``good`` (N,) the samples of the fit."""
    from scipy.stats import chi2

    means, var = [], []
    for i in np.unique(fid[good]):
        r = res[good & (fid == i)]
        if r.size < 10:
            continue
        means.append(float(r.mean()))
        var.append(float(r.var(ddof=1)) / r.size)
    if len(means) < 2:
        return None
    m, v = np.array(means), np.maximum(np.array(var), 1e-300)
    w = 1.0 / v
    stat = float(np.sum(w * (m - np.sum(w * m) / w.sum()) ** 2))
    return means if chi2.sf(stat, len(means) - 1) < p else None


def _prior_undetermined(sig: dict[str, list[float]], Ms: Array, Q: Array, rng: np.random.Generator) -> list[str]:
    """Axis terms of a prior-regularised magnetometer fit (:func:`fit_norm_map`) that the data did not
    determine: posterior σ above :data:`~onlinecal.health.UNDETERMINED_RATIO` (½) of the prior's own σ
    (:func:`soft_iron_prior_sigma` for scale and ξ; for the bias the online filter's cold prior, 0.6 field)."""
    prior = soft_iron_prior_sigma(Ms, Q, rng)
    mbar = float(np.trace(Ms) / 3.0)
    prior["bias"] = np.full(3, 0.6 / mbar)
    return _above_half_prior(sig, prior, whole_terms=False)


def _above_half_prior(sig: dict[str, list[float]], prior: dict[str, Any], whole_terms: bool) -> list[str]:
    """Terms of bias, scale and ξ whose σ (``sig``) stayed above half their prior σ (``prior``: per axis (3,) or one
    number): a term without σ by its name alone ("scale"), else its axes ("bias.z"); with ``whole_terms`` a term
    whose three axes are all above also by its name alone (its σ are then dropped: :func:`.pipeline._drop_sigma`)."""
    out = []
    for p in ("bias", "scale", "xi"):
        s = sig.get(p)
        if s is None:
            out.append(p)
            continue
        lim = np.broadcast_to(np.asarray(prior[p], float), (3,))
        axes = [a for i, a in enumerate("xyz") if not float(s[i]) <= 0.5 * float(lim[i])]
        out += [p] if whole_terms and len(axes) == 3 else [f"{p}.{a}" for a in axes]
    return out


def static_means(segs: list[Segmentation]) -> tuple[Array, Array]:
    """Mean raw accel and gyro of every static interval of every log: (K, 3) each."""
    a, g = [], []
    for s in segs:
        for iv in s.statics:
            a.append(s.data.acc[iv.i0 : iv.i1].mean(axis=0))
            g.append(s.data.gyro[iv.i0 : iv.i1].mean(axis=0))
    return np.array(a).reshape(-1, 3), np.array(g).reshape(-1, 3)


def distinct_directions(v: Array, min_angle_deg: float = 10.0) -> int:
    """How many of the directions of v (K, 3) differ by more than min_angle from all before them."""
    u = v / np.linalg.norm(v, axis=1, keepdims=True)
    kept: list[Array] = []
    for x in u:
        if all(np.degrees(np.arccos(np.clip(x @ k, -1, 1))) > min_angle_deg for k in kept):
            kept.append(x)
    return len(kept)


def fit_accelerometer(
    segs: list[Segmentation], g: float, rng: np.random.Generator
) -> tuple[SensorCalibration, StepReport]:
    """Accelerometer: static-position fit ‖S'(a − o)‖ = g (eq. 32) → T_R,acc from the low-pass-filtered
    accelerometer in the rotation phases (eqs. 25–27), which carries it onto the same axes the
    magnetometer was aligned to.

    The full 9-parameter fit needs static positions in enough distinct attitudes (the paper uses 12);
    with fewer, the fit falls back to bias + per-axis scale (≥ 6 attitudes) or bias + common scale,
    and says so.
    """
    rep = StepReport("accel")
    a, _ = static_means(segs)
    ndir = distinct_directions(a) if a.shape[0] else 0
    rep.figures["static_positions"] = int(a.shape[0])
    rep.figures["distinct_attitudes"] = ndir
    if ndir < 3:
        raise FitError(f"accelerometer: {ndir} distinct static attitude(s), need ≥ 3")
    model = "full" if ndir >= 9 else "diag" if ndir >= 6 else "bias" if ndir >= 4 else "offset"
    if model != "full":
        what = {"diag": "bias + per-axis scale", "bias": "bias + common scale",
                "offset": "bias only (common scale from the mean norm, no misalignment fitted)"}[model]
        rep.warnings.append(f"accel: only {ndir} distinct static attitudes; fitted {what}")
    try:
        o0, M0 = fit_ellipsoid_svd(a) if a.shape[0] >= 10 else (np.zeros(3), np.eye(3))
        M0 = M0 * g
    except FitError:
        o0, M0 = np.zeros(3), np.eye(3) * g / np.linalg.norm(a, axis=1).mean()
    if model != "full" or not np.all(np.isfinite(M0)):
        o0, M0 = np.zeros(3), np.eye(3) * g / np.linalg.norm(a, axis=1).mean()
    fit: NormFit = fit_norm_lm(a, g, o0, M0, model=model)
    Q, sig_a = _align(segs, _acc_samples, fit.M, fit.o, 0.3 * g, rep)
    M = Q @ fit.M
    cov9 = fit.cov if model == "full" else reduced_model_cov(a, g, fit, model, _static_noise_var(segs))
    norms = np.linalg.norm((a - fit.o) @ M.T, axis=1)
    rep.figures.update({
        "model": model,
        "static_norm_rms_error": float(np.sqrt(np.mean((norms - g) ** 2))),
        "raw_static_norm_rms_error": float(np.sqrt(np.mean((np.linalg.norm(a, axis=1) - g) ** 2))),
    })
    sig = propagate_sigma(fit.o, fit.M, cov9, Q, sig_a, rng)
    if model != "full":
        und = _above_half_prior(sig, ACC_PRIOR_SIGMA, whole_terms=True)
        if und:
            rep.figures["undetermined"] = sorted(set(rep.figures.get("undetermined", [])) | set(und))
            rep.warnings.append(
                f"accel: with the terms the {model!r} fit holds fixed at their prior "
                f"({100 * ACC_PRIOR_SIGMA['scale']:.0f} % scale, "
                f"{ACC_PRIOR_SIGMA['xi']} rad non-orthogonality) not determined by the data (σ above half the "
                f"prior's): {', '.join('accel.' + u for u in und)} — start values, not a calibration; hold the unit "
                "still in more attitudes (the paper's 12 positions)")
    return SensorCalibration(fit.o, M, sig), rep


# The prior of the accelerometer terms a reduced static fit holds fixed, and the width against which a term counts
# as undetermined (σ above half of it): the online filter's cold prior (UKFConfig.cold_sigma["accel"], the same
# numbers, checked by tests/test_accel_reduced_sigma.py) — 0.5 m/s² bias, 5 % scale, 0.02 rad non-orthogonality.
ACC_PRIOR_SIGMA = {"bias": 0.5, "scale": 0.05, "xi": 0.02}


def _static_noise_var(segs: list[Segmentation]) -> Array:
    """Variance (K,) (m/s²)² of the norm of each static mean (:func:`static_means`' order): the mean per-axis
    sample variance over the samples in it — the floor of the fit's residual where it has no degree of freedom
    to estimate one (three attitudes, three unknowns: an exact solve leaves a residual of zero)."""
    v = []
    for s in segs:
        for iv in s.statics:
            x = s.data.acc[iv.i0 : iv.i1]
            v.append(float(np.mean(x.var(axis=0))) / max(1, x.shape[0]))
    return np.array(v)


def reduced_model_cov(a: Array, g: float, fit: NormFit, model: str, noise_var: Array) -> Array:
    """Covariance (9, 9) of (o, upper triangle of M) for a reduced static fit (eq. 32 with ``model`` "offset",
    "bias" or "diag", :func:`.ellipsoid.fit_norm_lm`) that states what the fit assumed: the matrix directions it
    holds fixed carry the prior :data:`ACC_PRIOR_SIGMA` (× the mean scale m̄: σ m̄·0.05 on the diagonal, m̄·0.01
    off it, which turns two axes by 0.02 rad), and the fitted parameters move with them as the solve would
    (δp_F = −(AᵀA)⁻¹AᵀB δu, A and B the residual Jacobian along the fitted and the fixed directions). Without a
    degree of freedom the residual's variance is the static means' noise (``noise_var`` (K,)) instead of the zero
    the exact solve leaves.
    Before (session 16), the fixed directions had no variance: MARG set 1's three rests gave an accelerometer
    bias of ±1e-16 m/s² and a scale of ±4e-7 — σ of an assumption, not of the data."""
    from .ellipsoid import _resid_jac_full

    p9 = np.concatenate([fit.o, fit.M[_IU]])
    _, J = _resid_jac_full(p9, a, g)
    diag6 = np.array([1.0, 0.0, 0.0, 1.0, 0.0, 1.0])  # the diagonal of M in the upper-triangle order
    fitted = [np.eye(9)[k] for k in range(3)]
    if model == "bias":
        fitted.append(np.concatenate([np.zeros(3), diag6]) / math.sqrt(3.0))
    elif model == "diag":
        fitted += [np.eye(9)[3 + k] for k in (0, 3, 5)]
    F = np.array(fitted).T  # (9, P), orthonormal
    w, V = np.linalg.eigh(np.eye(9) - F @ F.T)
    U = V[:, w > 0.5]  # (9, 9 − P): the directions the fit holds fixed (all within M)
    mbar = float(np.trace(fit.M) / 3.0)
    # an off-diagonal E_jk of a symmetric M = m̄(I + E) turns axes j and k towards each other by 2E_jk: σ ξ / 2
    prior = np.concatenate([np.zeros(3), np.where(diag6 > 0, (mbar * ACC_PRIOR_SIGMA["scale"]) ** 2,
                                                  (mbar * ACC_PRIOR_SIGMA["xi"] / 2.0) ** 2)])
    Su = U.T @ np.diag(prior) @ U
    A, B = J @ F, J @ U
    AtA_inv = np.linalg.pinv(A.T @ A)
    G = F @ (-AtA_inv @ A.T @ B) + U
    if a.shape[0] > F.shape[1]:
        cov_fit = fit.cov
    else:  # an exact solve: the noise of the means, not the zero residual
        s2 = float(np.mean(noise_var)) if noise_var.size else 0.0
        cov_fit = s2 * (F @ AtA_inv @ F.T)
    out: Array = cov_fit + G @ Su @ G.T
    # the fixed directions move the norms at second order too (~g·E², which the linear map above leaves out): with
    # six rests along ±axes and 1 % off-diagonals, 2e-4 m/s² of bias, 1.5× the noise of 6 long rests. Sized on that
    # case (tests/test_accel_reduced_sigma.py: an eighth of g·tr(Σu)/m̄² per bias axis), negligible beside the
    # first-order term wherever that one is not zero
    out[:3, :3] += np.eye(3) * (0.125 * g * float(np.trace(Su)) / mbar**2) ** 2
    return 0.5 * (out + out.T)


__all__ = ["fit_magnetometer", "fit_accelerometer", "static_means", "StepReport", "sqrtm_spd", "sqrt_psd"]


def quasi_static_pairs(segs: list[Segmentation], acc: SensorCalibration, mag: SensorCalibration, g: float,
                       tol: float = 0.3) -> tuple[Array, Array]:
    """Calibrated (accel, mag) pairs at the IMU times where the unit is quasi-static (moving std over 0.5 s
    below ``tol`` m/s² and ‖a‖ within ``tol`` of g), the mag interpolated onto those times (only where a
    mag sample lies within two mag periods). Returns (a (K, 3), m (K, 3))."""
    A, M = [], []
    for sg in segs:
        d = sg.data
        if d.n_imu < 50 or d.n_mag < 20:
            continue
        a = acc.apply(d.acc)
        _, sd = moving_std(a, max(5, int(round(0.5 * d.imu_rate))))
        nrm = np.linalg.norm(a, axis=1)
        t = d.t_imu
        per = (d.t_mag[-1] - d.t_mag[0]) / max(1, d.n_mag - 1)
        j = np.clip(np.searchsorted(d.t_mag, t), 1, d.n_mag - 1)
        near = np.minimum(np.abs(t - d.t_mag[j - 1]), np.abs(d.t_mag[j] - t)) <= 2 * per
        ok = (np.linalg.norm(sd, axis=1) < tol) & (np.abs(nrm - g) < tol) & near
        if not ok.any():
            continue
        m = mag.apply(d.mag)
        A.append(a[ok])
        M.append(np.column_stack([np.interp(t[ok], d.t_mag, m[:, k]) for k in range(3)]))
    return (np.concatenate(A), np.concatenate(M)) if A else (np.zeros((0, 3)), np.zeros((0, 3)))


def mag_to_accel_rotation(segs: list[Segmentation], acc: SensorCalibration, mag: SensorCalibration,
                          g: float) -> tuple[Array, dict]:
    """Rotation P (any angle) that carries the magnetometer's frame onto the accelerometer's, from the
    constant angle between gravity and the field at quasi-static attitudes (:func:`align.align_by_dip`),
    the samples weighted by attitude coverage. Used where rotation phases could not align the two
    (eqs. 25–27 need phases about two axes). Returns (P (3, 3), figures: angle °, σ °, dip °, samples).
    Raises FitError when gravity was not seen tilted about two axes (P is then not determined)."""
    from .align import align_by_dip

    a, m = quasi_static_pairs(segs, acc, mag, g)
    w = sphere_bin_weights(a, per_bin=20)
    k = w > 0
    n_dir = distinct_directions(a[sphere_bin_weights(a, per_bin=1) > 0]) if a.shape[0] else 0  # one per cell
    if a.shape[0] < 20 or n_dir < 4:
        raise FitError(f"mag-to-accel rotation: {n_dir} distinct quasi-static attitudes (need 4, tilted about "
                       "two axes)")
    P, c, rms, cov = align_by_dip(a[k], m[k], w[k])
    sig = float(np.degrees(np.sqrt(np.trace(cov[:3, :3]) / 3))) if np.all(np.isfinite(cov)) else float("inf")
    ang = float(np.degrees(np.arccos(np.clip((np.trace(P) - 1) / 2, -1, 1))))
    return P, {"angle_deg": ang, "sigma_deg": sig, "dip_deg": float(np.degrees(np.arcsin(np.clip(c, -1, 1)))),
               "residual_rms": rms, "samples": int(a.shape[0]), "attitude_cells": int(k.sum())}


def within_direction_spread(m: Array, cell_deg: float = 3.0, min_count: int = 5) -> tuple[float, float]:
    """How much of a calibrated field's norm spread sits *at one direction*: the RMS deviation of ‖m‖ from
    the mean of its direction cell (cells of ``cell_deg``, :func:`sphere_bin_weights`' grid; cells with at
    least ``min_count`` samples), in % of the mean norm, and the share of samples in such cells.

    The ellipsoid of eq. 17 changes the norm smoothly with the direction: an error ε of one axis' scale
    moves ‖m‖ by ε cos²θ, at most ε per radian, so within a 3° cell by at most 0.015 ε RMS (0.15 % for a
    10 % error). Two samples in one cell whose norms differ by more than the noise saw different
    fields: a disturbance near the sensor or a field that changed while the file was recorded — no
    calibration of the sensor removes that part. m (N, 3) calibrated samples. Returns (%, share)."""
    m = np.asarray(m, float).reshape(-1, 3)
    n = np.linalg.norm(m, axis=1)
    ok = np.isfinite(n) & (n > 0)
    m, n = m[ok], n[ok]
    if n.size == 0:
        return float("nan"), 0.0
    u = m / n[:, None]
    lat = np.arcsin(np.clip(u[:, 2], -1.0, 1.0))
    lon = np.arctan2(u[:, 1], u[:, 0])
    step = np.radians(cell_deg)
    ring = np.minimum(((lat + np.pi / 2) / step).astype(int), int(np.ceil(np.pi / step)) - 1)
    n_lon = np.maximum(1, np.round(2 * np.pi * np.cos(-np.pi / 2 + (ring + 0.5) * step) / step)).astype(int)
    col = np.minimum(((lon + np.pi) / (2 * np.pi) * n_lon).astype(int), n_lon - 1)
    _, inv, cnt = np.unique(ring * 100000 + col, return_inverse=True, return_counts=True)
    mean = np.bincount(inv, weights=n) / cnt
    big = cnt[inv] >= min_count
    if not big.any():
        return float("nan"), 0.0
    dev = (n - mean[inv])[big]
    return float(100 * np.sqrt(np.mean(dev * dev)) / n.mean()), float(big.mean())


def quasi_static_holds(acc: Array, gyro: Array, rate_hz: float, window_s: float = 1.0, acc_std_max: float = 0.5,
                       rate_max: float = 0.5, stride: int = 10) -> Array:
    """Mean specific force (K, 3) over the quasi-static holds of a hand-held log: windows of ``window_s``
    whose accelerometer std (norm over the axes) is below ``acc_std_max`` m/s² and whose mean rate differs
    from the log's median by less than ``rate_max`` rad/s (centripetal ω²r < 0.03 m/s² at a hand's 0.1 m);
    every ``stride``-th window centre. acc, gyro (N, 3) raw, one time base at ``rate_hz``."""
    w = max(5, int(round(window_s * rate_hz)))
    if acc.shape[0] < w:
        return np.zeros((0, 3))
    am, sd = moving_std(np.asarray(acc, float), w)
    gm, _ = moving_std(np.asarray(gyro, float), w)
    q = (np.linalg.norm(sd, axis=1) < acc_std_max) & (np.linalg.norm(gm - np.median(gm, axis=0), axis=1) < rate_max)
    out: Array = am[q][::stride]
    return out
