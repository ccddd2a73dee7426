"""The statistical core of diagnose: stack the sessions' residual rows, fit the baseline's nuisance, score every
candidate extension on held-out data, and select effects forward (most held-out likelihood first).

The same function runs on the measured sessions and on their re-simulation through the fitted baseline
(the parametric-bootstrap null of :mod:`.resim`), so "significant" means: better than what this session's
own motion and noise produce without any effect.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import cho_factor, cho_solve

from ..model import Calibration
from ..specs import OMEGA_EARTH
from .detectors import Candidate, candidates, drift_knots, drift_prior
from .regressors import SUBCHANNELS, Design, earth_rate, nuisance
from .score import FOLD_S, Gain, Problem, folds, robust_sigma, solve

Array = NDArray[np.float64]
EARTH = "earth_rate"  # the rows' key for the Earth-rate response (not a column block of the Problem)
Q_GRID = {"gyro": np.logspace(-6.5, -2.0, 10), "accel": np.logspace(-5.5, -1.0, 10)}
# channels each candidate acts on (for the before/after RMS)
# Set to 1 to let the BLAS library pick its own thread count in the small solves below (the previous
# behaviour; benchmarks/bench_diagnose.py --flight times both paths in one run).
THREADED_ENV = "ONLINECAL_DIAGNOSE_THREADED"
_controller: Any = None


@contextlib.contextmanager
def one_blas_thread() -> Iterator[None]:
    """Run the enclosed linear algebra on one BLAS thread.

    Every factorisation here is small (p ≤ a few hundred columns: nuisance + one candidate + the drift knots);
    at that size OpenBLAS's threads only synchronise. Measured on a 10-minute 200 Hz flight (docs/
    benchmarks-diagnose.md): 1211 Cholesky factorisations of 37–414 columns cost 0.12 s CPU on one thread
    and 13.2 s with OpenBLAS's default two threads on a loaded two-core machine (each 180×180 factorisation
    0.2 ms → 10–150 ms, the threads spin waiting for a core). Same arithmetic: a one-thread run is bit-for-bit
    the same whichever path a caller came from; it differs from a threaded run only by rounding (see
    tests/test_diagnose_speed.py). A no-op where threadpoolctl is missing or ``ONLINECAL_DIAGNOSE_THREADED=1``.
    """
    global _controller
    if os.environ.get(THREADED_ENV, "") == "1":
        yield
        return
    try:
        if _controller is None:
            from threadpoolctl import ThreadpoolController

            _controller = ThreadpoolController()
        ctx: Any = _controller.limit(limits=1, user_api="blas")
    except ImportError:  # optional speed-up; the arithmetic is the same without it
        ctx = contextlib.nullcontext()
    with ctx:
        yield


CHANNELS = {
    "gyro": ("g_rest_x", "g_rest_y", "g_rest_z", "ka_x", "ka_y", "ka_z", "km_x", "km_y", "km_z"),
    "accel": ("a_norm", "ka_x", "ka_y", "ka_z", "dip"),
    "all": ("ka_x", "ka_y", "ka_z", "km_x", "km_y", "km_z", "dip"),
}


@dataclass
class Scored:
    cand: Candidate
    blocks: list[str]
    gain: Gain
    params: dict[str, Any] = field(default_factory=dict)
    priors: dict[str, Array] = field(default_factory=dict)


@dataclass
class Analysis:
    problem: Problem
    designs: list[Design]
    cal: Calibration
    cands: list[Candidate]
    blocks: dict[str, list[str]]  # candidate key → its column blocks
    priors: dict[str, Array]  # drift blocks → prior precision at the ML density
    q: dict[str, Array]  # drift candidate key → ML density per axis
    q_lr: dict[str, Array]  # drift candidate key → 2·Δ log ML for dropping each axis
    first: dict[str, Gain] = field(default_factory=dict)  # each candidate against the baseline alone
    rows: Any = None  # (y, ch, t, sid, cols) before any channel is dropped (for :func:`restrict`)
    dropped: tuple[str, ...] = ()  # sub-channels left out (the baseline does not meet them)
    # (S, 3) rad/s: the Earth's rotation fitted per session (its first body frame) and taken out of the rows
    earth_rate: Array = field(default_factory=lambda: np.zeros((0, 3)))

    def score(self, base: list[str], key: str) -> Gain:
        with one_blas_thread():
            return self.problem.gain(base, self.blocks[key], self.priors)

    def params(self, model: list[str], key: str) -> dict[str, Any]:
        cand = next(c for c in self.cands if c.key == key)
        with one_blas_thread():
            beta, cov = self.problem.fit(model + self.blocks[key], self.priors)
        k = sum(self.problem.blocks[b].stop - self.problem.blocks[b].start for b in self.blocks[key])
        b, C = beta[-k:], cov[-k:, -k:]
        if cand.effect == "bias_drift":
            drift = cast(Callable[..., dict[str, Any]], cand.params)  # drift_params: also takes q= and lr=
            return drift(b, C, self.designs, self.cal, q=self.q[key], lr=self.q_lr[key])
        return cand.params(b, C, self.designs, self.cal)


class _Marginal:
    """Restricted log marginal likelihood of a Gaussian-prior block over a flat-prior base (whitened rows,
    MacKay 1992): with the base profiled out (Schur complement S, reduced c̃, ỹ'ỹ),
    log ML(Π) = −½ (ỹ'ỹ − c̃'(S + Π)⁻¹c̃) − ½ log det(S + Π) + ½ log det Π."""

    def __init__(self, P: Problem, base: list[str], ext: list[str]) -> None:
        G = P.G[0] + P.G[1]
        bi, ei = P.idx(base), P.idx(ext)
        G00 = G[np.ix_(bi, bi)]
        G01 = G[np.ix_(bi, ei)]
        # G00⁺ [G01 c0] through the same ridge-regularised Cholesky as every fit
        X = np.column_stack([G01, G[bi, -1]])
        sol = np.column_stack([solve(G00, X[:, k])[0] for k in range(X.shape[1])])
        self.S = G[np.ix_(ei, ei)] - G01.T @ sol[:, :-1]
        self.c = G[ei, -1] - G01.T @ sol[:, -1]
        self.yy = float(G[-1, -1] - G[bi, -1] @ sol[:, -1])

    def __call__(self, prior: Array, logdet_prior: float) -> float:
        A = self.S + prior
        cf = cho_factor(A, check_finite=False)
        fit = float(self.c @ cho_solve(cf, self.c, check_finite=False))
        ld = 2 * float(np.sum(np.log(np.diag(cf[0]))))
        return -0.5 * (self.yy - fit) - 0.5 * ld + 0.5 * logdet_prior


def _fit_density(P: Problem, base: list[str], blocks: list[str], Ks: list[int], dts: list[float],
                 grid: Array) -> tuple[Array, Array, dict[str, Array]]:
    """Per-axis random-walk density by maximum marginal likelihood (coordinate search on a log grid)."""
    mar = _Marginal(P, base, blocks)

    def ml(q: Array) -> float:
        pri = _blockdiag([drift_prior(K, q, dt) for K, dt in zip(Ks, dts, strict=True)])
        # det(DᵀD) = 1 (unit lower-bidiagonal D): log det Π = −Σ_blocks K Σ_axes log(q²·dt)
        ld = -sum(K * float(np.sum(np.log(np.maximum(q, 1e-12) ** 2 * dt))) for K, dt in zip(Ks, dts, strict=True))
        return mar(pri, ld)

    # coordinate search on the coarse grid, then a parabola through the best point and its neighbours in
    # log q (the grid steps are 0.5 decade; the density must come out within a few per cent)
    q = np.full(3, grid[len(grid) // 2])
    for _ in range(2):
        for j in range(3):
            vals = []
            for g in grid:
                qq = q.copy()
                qq[j] = g
                vals.append(ml(qq))
            i = int(np.argmax(vals))
            q[j] = grid[i]
            if 0 < i < len(grid) - 1:
                y0, y1, y2 = vals[i - 1], vals[i], vals[i + 1]
                den = y0 - 2 * y1 + y2
                if den < 0:
                    h = float(np.log(grid[i + 1] / grid[i]))
                    q[j] = grid[i] * float(np.exp(np.clip(0.5 * h * (y0 - y2) / den, -h, h)))
    best = ml(q)
    lr = np.zeros(3)
    for j in range(3):
        qq = q.copy()
        qq[j] = grid[0] * 1e-3
        lr[j] = 2 * (best - ml(qq))
    pri = {}
    for b, K, dt in zip(blocks, Ks, dts, strict=True):
        pri[b] = drift_prior(K, q, dt)
    return q, lr, pri


def _blockdiag(ms: list[Array]) -> Array:
    n = sum(m.shape[0] for m in ms)
    out = np.zeros((n, n))
    i = 0
    for m in ms:
        k = m.shape[0]
        out[i : i + k, i : i + k] = m
        i += k
    return out


def analyse(designs: list[Design], cal: Calibration, only: list[str] | None = None,
            drop: tuple[str, ...] = ()) -> Analysis:
    """Rows, nuisance, candidate columns, whitening, drift densities and every candidate's first-step gain.

    ``only``: the candidate keys to build (None: all the data can test); ``drop``: sub-channels whose rows
    are left out (an invariant the baseline does not meet, :func:`restrict`)."""
    y = np.concatenate([d.y for d in designs])
    ch = np.concatenate([d.ch for d in designs])
    t = np.concatenate([d.t for d in designs])
    sid = np.concatenate([np.full(d.y.size, d.sid) for d in designs])
    has_mag = any(d.mhat is not None for d in designs)
    has_temp = any(d.s.has_temp for d in designs)
    cands = [c for c in candidates(has_mag, has_temp) if only is None or c.key in only]
    cols: dict[str, Array] = {"nuisance": np.concatenate([nuisance(d) for d in designs], axis=0)}
    # the Earth's rotation is part of what a gyro measures, not a model error: its response (block-diagonal
    # over sessions) is fitted within its known norm in _finish, on the rows kept, and taken out of them
    E = [earth_rate(d) for d in designs]
    Ef = np.zeros((y.size, 3 * len(E)))
    r = 0
    for i, e in enumerate(E):
        Ef[r : r + e.shape[0], 3 * i : 3 * i + 3] = e
        r += e.shape[0]
    cols[EARTH] = Ef
    blocks: dict[str, list[str]] = {}
    offs = np.cumsum([0] + [d.y.size for d in designs])
    for c in cands:
        if c.k_per_session:
            names = []
            # one block per session, or per group of sessions that share a walk (the windows of one sampled log,
            # Design.drift_group), named after the group's first session
            groups: dict[object, list[int]] = {}
            for i, d in enumerate(designs):
                groups.setdefault(("own", i) if d.drift_group is None else d.drift_group, []).append(i)
            for idx in groups.values():
                full = np.zeros(0)
                for i in idx:
                    X = c.columns(designs[i], cal)
                    if not full.size:
                        full = np.zeros((y.size, X.shape[1]))
                    full[offs[i] : offs[i + 1]] = X
                nm = f"{c.key}#{idx[0]}"
                cols[nm] = full
                names.append(nm)
            blocks[c.key] = names
        else:
            cols[c.key] = np.concatenate([c.columns(d, cal) for d in designs], axis=0)
            blocks[c.key] = [c.key]
    for k in cols:  # a column undefined somewhere (no clean signal there) carries no information there
        cols[k] = np.nan_to_num(cols[k], nan=0.0, posinf=0.0, neginf=0.0)
    return _finish(designs, cal, cands, blocks, (y, ch, t, sid, cols), drop)


def _trust_region(H: Array, g: Array, r: float) -> Array:
    """argmin ½ vᵀHv − gᵀv subject to |v| ≤ r, H symmetric positive semi-definite (the trust-region
    subproblem: v(λ) = (H + λI)⁻¹ g with the λ ≥ 0 that puts v on the bound when the free minimum is
    outside it; |v(λ)| falls with λ, found by bisection on a log scale)."""
    if not np.any(g):  # no row responds (all dropped, or no rotation seen): nothing pulls it off zero
        return np.zeros_like(g)
    e, Q = np.linalg.eigh(H)
    e = np.maximum(e, 0.0)
    gq = Q.T @ g

    def v(lam: float) -> Array:
        return cast(Array, Q @ (gq / np.maximum(e + lam, 1e-300)))

    if e.min() > 1e-12 * max(e.max(), 1e-300) and np.linalg.norm(v(0.0)) <= r:
        return v(0.0)
    hi = float(np.linalg.norm(g)) / r * 2.0  # |v(hi)| ≤ |g|/hi < r
    lo = max(hi * 1e-30, float(np.finfo(float).tiny))
    for _ in range(200):  # |v(hi)| ≤ r throughout: the answer never leaves the bound
        mid = float(np.sqrt(lo * hi))
        if np.linalg.norm(v(mid)) > r:
            lo = mid
        else:
            hi = mid
        if hi / lo < 1.0 + 1e-9:
            break
    return v(hi)


def fit_earth_rate(y: Array, ch: Array, N: Array, Ef: Array, sweeps: int = 30) -> Array:
    """The Earth-rate vector Ω_w of each session (its first body frame; (S, 3) rad/s), fitted with the
    baseline's nuisance N and bounded by its known norm, |Ω_w| ≤ Ω_E: least squares on the rows whitened by
    the baseline's residual σ, N projected out, then the trust-region subproblem per session (block
    coordinate descent when sessions share the nuisance — a convex problem, so the sweeps converge).

    Without the bound a free Ω_w would take an isotropic g-sensitivity whole wherever the gravity is the
    only world vector the body sees (:func:`.regressors.earth_rate`); with it, at most Ω_E of one."""
    N = np.nan_to_num(N, nan=0.0, posinf=0.0, neginf=0.0)  # undefined somewhere: no information there
    beta = solve(N.T @ N, N.T @ y)[0]
    w = 1.0 / robust_sigma(y - N @ beta, ch, len(SUBCHANNELS))[ch]
    Ef = np.nan_to_num(Ef, nan=0.0, posinf=0.0, neginf=0.0)
    Nw, Ew, yw = N * w[:, None], Ef * w[:, None], y * w
    GN = Nw.T @ Nw
    proj = solve(GN, Nw.T @ np.column_stack([Ew, yw]))[0]  # (solve takes a matrix right-hand side too)
    R = np.column_stack([Ew, yw]) - Nw @ proj
    H, g = R[:, :-1].T @ R[:, :-1], R[:, :-1].T @ R[:, -1]
    S = Ef.shape[1] // 3
    v = np.zeros(3 * S)
    for _ in range(sweeps if S > 1 else 1):
        for i in range(S):
            ix = slice(3 * i, 3 * i + 3)
            gi = g[ix] - H[ix] @ v + H[ix, ix] @ v[ix]
            v[ix] = _trust_region(H[ix, ix], gi, OMEGA_EARTH)
    return v.reshape(S, 3)


def restrict(an: Analysis, drop: tuple[str, ...]) -> Analysis:
    """The same analysis with the rows of the sub-channels ``drop`` left out (columns are not rebuilt; the
    whitening and the drift densities are refitted on the rows kept)."""
    return _finish(an.designs, an.cal, an.cands, an.blocks, an.rows, tuple(drop))


def _finish(designs: list[Design], cal: Calibration, cands: list[Candidate], blocks: dict[str, list[str]],
            rows: tuple[Array, Array, Array, Array, dict[str, Array]], drop: tuple[str, ...]) -> Analysis:
    y, ch, t, sid, cols = rows
    keep = ~np.isin(ch, [SUBCHANNELS.index(c) for c in drop])
    if not keep.all():
        y, ch, t, sid = y[keep], ch[keep], t[keep], sid[keep]
        cols = {k: v[keep] for k, v in cols.items()}
    cols = dict(cols)
    # fitted on the rows kept: where the accelerometer's kinematic rows carry thrust they are dropped first
    Ek = cols.pop(EARTH)
    v_earth = fit_earth_rate(y, ch, cols["nuisance"], Ek)
    y = y - Ek @ v_earth.ravel()
    fold = folds(t, sid)
    # whitening σ from the baseline's residual over all rows
    X0 = cols["nuisance"]
    beta = solve(X0.T @ X0, X0.T @ y)[0]
    sigma = robust_sigma(y - X0 @ beta, ch, len(SUBCHANNELS))
    P = Problem.build(y, ch, t, fold, sigma, cols, np.floor(t / FOLD_S).astype(int) * 1000 + sid)
    priors: dict[str, Array] = {}
    q: dict[str, Array] = {}
    q_lr: dict[str, Array] = {}
    for c in cands:
        if c.effect == "bias_drift":
            first = [designs[int(b.rsplit("#", 1)[1])] for b in blocks[c.key]]  # each block's first session
            Ks = [drift_knots(d).size - 1 for d in first]
            dts = [float(np.diff(drift_knots(d))[0]) for d in first]
            with one_blas_thread():
                q[c.key], q_lr[c.key], pri = _fit_density(P, ["nuisance"], blocks[c.key], Ks, dts,
                                                          Q_GRID[c.sensor])
            priors.update(pri)
    an = Analysis(P, designs, cal, cands, blocks, priors, q, q_lr, rows=rows, dropped=drop, earth_rate=v_earth)
    for c in cands:
        an.first[c.key] = an.score(["nuisance"], c.key)
    return an


def channel_mask(P: Problem, sensor: str) -> NDArray[np.bool_]:
    names = CHANNELS.get(sensor, CHANNELS["all"])
    ids = [SUBCHANNELS.index(n) for n in names]
    return np.isin(P.ch, ids)
