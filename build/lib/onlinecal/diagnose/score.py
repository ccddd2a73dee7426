"""Stage 4 of diagnose: held-out significance and gain of nested linear extensions of the baseline.

Rows are whitened by a per-sub-channel σ (robust spread of the baseline residual, fixed for every model so
likelihoods compare). A model is a set of regressor blocks (optionally with a Gaussian prior: the random-walk
drift); it is fitted by (penalised) least squares on one half of the session (alternate 10-s time blocks)
and scored on the other half, then the halves swap (2-fold cross-validation). Under Gaussian noise the
held-out log-likelihood gain of model 1 over model 0 is ½ Σ_test (r₀² − r₁²)/σ²; the BIC change reported
beside it is −2·gain + Δk·ln n (Schwarz 1978), with Δk the effective number of added parameters.

Everything runs on the Gram matrices of the whitened columns per fold, so comparing dozens of models costs
small p×p solves instead of passes over the rows.

The gain's own spread: the held-out gain is a sum over the 10-s time blocks of their contributions
d_b = ½ Σ_{rows in b} (r₀² − r₁²); across blocks these are close to independent, so the gain's standard
deviation is estimated as √B·sd(d_b) (the paired, block-wise form of Vuong's 1989 test of non-nested
models). A candidate that only fits the session's particular noise (a clean seed) earns a gain of the
order of this spread with either sign; ``Gain.spread`` carries it so that the significance bar covers it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import cho_factor, cho_solve

Array = NDArray[np.float64]
FOLD_S = 10.0


def folds(t: Array, sid: Array) -> Array:
    """Fold 0/1 of each row: alternate FOLD_S-long time blocks (offset per session)."""
    return ((np.floor(t / FOLD_S) + sid) % 2).astype(int)


def robust_sigma(r: Array, ch: Array, n_ch: int) -> Array:
    """Per-channel σ = 1.4826·MAD of the residual (1 for empty channels)."""
    out = np.ones(n_ch)
    for k in range(n_ch):
        v = r[ch == k]
        if v.size >= 5:
            s = 1.4826 * np.median(np.abs(v - np.median(v)))
            out[k] = s if s > 0 else (float(np.std(v)) or 1.0)
    return out


def solve(G: Array, c: Array, want_inv: bool = False) -> tuple[Array, Array]:
    """β = G⁺ c for a symmetric positive semi-definite G (columns scaled to unit diagonal, a 1e-10 ridge for
    the directions no data sees: the gauge of a common rotation of all sensors, an unexcited axis), by
    Cholesky. Returns β and, if asked, the (ridge-regularised) inverse."""
    if G.shape[0] == 0:
        return np.zeros(0), np.zeros((0, 0))
    d = np.sqrt(np.maximum(np.diag(G), 0))
    d[d == 0] = 1.0
    Gs = G / np.outer(d, d)
    Gs[np.diag_indices_from(Gs)] += 1e-10
    cf = cho_factor(Gs, check_finite=False)
    dc = d if c.ndim == 1 else d[:, None]
    beta = cho_solve(cf, c / dc, check_finite=False) / dc
    if not want_inv:
        return beta, np.zeros((0, 0))
    inv = cho_solve(cf, np.eye(G.shape[0]), check_finite=False) / np.outer(d, d)
    return beta, inv


def eff_rank(G: Array) -> int:
    if G.shape[0] == 0:
        return 0
    d = np.sqrt(np.maximum(np.diag(G), 0))
    d[d == 0] = 1.0
    ev = np.linalg.eigvalsh(G / np.outer(d, d))
    return int(np.sum(ev > max(ev.max(), 1e-300) * 1e-9))


@dataclass
class Gain:
    loglik_gain: float
    bic_delta: float
    rms_before: float  # held-out RMS of the whitened residual (1 = the baseline's noise level)
    rms_after: float
    k: float
    n: int
    spread: float = 0.0  # standard deviation of loglik_gain over the session's time blocks (nats, see module doc)

    def to_dict(self) -> dict[str, float]:
        return {"heldout_rms_before": self.rms_before, "heldout_rms_after": self.rms_after,
                "loglik_gain": self.loglik_gain, "bic_delta": self.bic_delta, "gain_spread": self.spread}


@dataclass
class Problem:
    """Whitened rows and the per-fold Gram matrices of every column block.

    ``blocks`` name → column slice into Z; Z = [blocks..., y] whitened; G[f] = Z_fᵀ Z_f for fold f.
    """

    y: Array
    ch: Array
    t: Array
    fold: Array
    sigma: Array
    blocks: dict[str, slice] = field(default_factory=dict)
    Z: Array = field(default_factory=lambda: np.zeros((0, 0)))
    G: list[Array] = field(default_factory=list)
    blk: Array = field(default_factory=lambda: np.zeros(0, int))  # (n,) time-block index of each row (0..B−1)
    _dof: dict[tuple, float] = field(default_factory=dict)
    _r2: dict[tuple, Array] = field(default_factory=dict)

    @classmethod
    def build(cls, y: Array, ch: Array, t: Array, fold: Array, sigma: Array, cols: dict[str, Array],
              blk: Array | None = None) -> Problem:
        w = 1.0 / sigma[ch]
        names = list(cols)
        sl: dict[str, slice] = {}
        i = 0
        for n in names:
            sl[n] = slice(i, i + cols[n].shape[1])
            i += cols[n].shape[1]
        Z = np.concatenate([cols[n] for n in names] + [y[:, None]], axis=1) * w[:, None]
        G = [Z[fold == f].T @ Z[fold == f] for f in (0, 1)]
        if blk is None:
            blk = np.floor(t / FOLD_S).astype(int)
        blk = np.unique(blk, return_inverse=True)[1].astype(int)
        return cls(y, ch, t, fold, sigma, sl, Z, G, blk)

    @property
    def n(self) -> int:
        return int(self.y.size)

    def idx(self, model: list[str]) -> Array:
        return np.concatenate([np.arange(self.blocks[b].start, self.blocks[b].stop) for b in model]) \
            if model else np.zeros(0, int)

    def _fit(self, G: Array, ix: Array, prior: Array | None, want_inv: bool = False) -> tuple[Array, Array]:
        A = G[np.ix_(ix, ix)]
        if prior is not None:
            A = A + prior
        return solve(A, G[ix, -1], want_inv)

    def prior_matrix(self, model: list[str], priors: dict[str, Array]) -> Array | None:
        if not priors:
            return None
        ix = self.idx(model)
        P = np.zeros((ix.size, ix.size))
        off = 0
        for b in model:
            k = self.blocks[b].stop - self.blocks[b].start
            if b in priors:
                P[off : off + k, off : off + k] = priors[b]
            off += k
        return P

    def heldout(self, model: list[str], priors: dict[str, Array] | None = None) -> tuple[float, float, int]:
        """Held-out −½ Σ r² over both folds, the RSS, and the rows counted."""
        ix = self.idx(model)
        P = self.prior_matrix(model, priors or {})
        rss = 0.0
        for f in (0, 1):
            Gtr, Gte = self.G[1 - f], self.G[f]
            beta, _ = self._fit(Gtr, ix, P)
            yy = Gte[-1, -1]
            rss += float(yy - 2 * beta @ Gte[ix, -1] + beta @ Gte[np.ix_(ix, ix)] @ beta)
        return -0.5 * rss, rss, self.n

    def dof(self, model: list[str], priors: dict[str, Array] | None = None) -> float:
        """Effective number of parameters: tr((G + P)⁺ G) (= rank without a prior)."""
        key = tuple(model) + tuple(b for b in model if priors and b in priors)
        if key in self._dof:
            return self._dof[key]
        ix = self.idx(model)
        G = self.G[0] + self.G[1]
        P = self.prior_matrix(model, priors or {})
        if P is None or not P.any():
            out = float(eff_rank(G[np.ix_(ix, ix)]))
        else:
            _, inv = self._fit(G, ix, P, want_inv=True)
            out = float(np.trace(inv @ G[np.ix_(ix, ix)]))
        self._dof[key] = out
        return out

    def fit(self, model: list[str], priors: dict[str, Array] | None = None) -> tuple[Array, Array]:
        """β over all rows and its covariance (G + P)⁺ scaled by the residual variance (≥ 1)."""
        ix = self.idx(model)
        G = self.G[0] + self.G[1]
        P = self.prior_matrix(model, priors or {})
        beta, inv = self._fit(G, ix, P, want_inv=True)
        rss = float(G[-1, -1] - 2 * beta @ G[ix, -1] + beta @ G[np.ix_(ix, ix)] @ beta)
        s2 = max(1.0, rss / max(1, self.n - ix.size))
        return beta, inv * s2

    def residual(self, model: list[str], beta: Array) -> Array:
        """Whitened residual rows of the model with coefficients β."""
        ix = self.idx(model)
        return self.Z[:, -1] - self.Z[:, ix] @ beta

    def heldout_r2(self, model: list[str], priors: dict[str, Array] | None = None) -> Array:
        """(n,) squared held-out residual of every row (each fold predicted by the fit on the other)."""
        key = tuple(model) + tuple(b for b in model if priors and b in priors)
        if key in self._r2:
            return self._r2[key]
        ix = self.idx(model)
        P = self.prior_matrix(model, priors or {})
        r2 = np.empty(self.n)
        for f in (0, 1):
            beta, _ = self._fit(self.G[1 - f], ix, P)
            te = self.fold == f
            Zt = self.Z[te]
            r2[te] = (Zt[:, -1] - Zt[:, ix] @ beta) ** 2
        if len(self._r2) > 64:  # forward selection revisits a few base models; keep the memory bounded
            self._r2.clear()
        self._r2[key] = r2
        return r2

    def spread(self, base: list[str], ext: list[str], priors: dict[str, Array] | None = None) -> float:
        """Standard deviation of the held-out gain of base + ext over base: √B·sd of the per-block gains
        (module doc). 0 with fewer than 4 blocks holding rows."""
        d = 0.5 * (self.heldout_r2(base, priors) - self.heldout_r2(base + ext, priors))
        db = np.bincount(self.blk, weights=d)
        db = db[np.bincount(self.blk) > 0]
        B = db.size
        if B < 4:
            return 0.0
        return float(np.sqrt(B) * np.std(db, ddof=1))

    def gain(self, base: list[str], ext: list[str], priors: dict[str, Array] | None = None) -> Gain:
        if self.n == 0:  # every row left out (no invariant the baseline meets): nothing to score
            return Gain(0.0, 0.0, float("nan"), float("nan"), 0.0, 0, 0.0)
        ll0, rss0, n = self.heldout(base, priors)
        ll1, rss1, _ = self.heldout(base + ext, priors)
        k = self.dof(base + ext, priors) - self.dof(base, priors)
        g = ll1 - ll0
        return Gain(g, -2 * g + k * np.log(max(n, 2)), float(np.sqrt(rss0 / n)), float(np.sqrt(rss1 / n)), k, n,
                    self.spread(base, ext, priors))
