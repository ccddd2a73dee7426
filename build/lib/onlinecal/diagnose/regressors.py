"""Stage 2 of diagnose: residual channels of the baseline model and their linear response to model errors.

Every channel is a relation the paper's model says must hold on calibrated data, evaluated per block:

* ``g_rest`` — at rest the calibrated gyro reads zero: 1-s chunk means of ω (rad/s), per axis;
* ``a_norm`` — a pure rotation keeps |a| = g: block means of |a| − g (m/s²);
* ``m_norm`` — the field has norm 1: block means of |m| − 1;
* ``dip``    — the angle between field and gravity is fixed: block means of â·m̂ (minus a fitted constant);
* ``ka``/``km`` — a world-fixed vector v seen in the body obeys v̇ = v × ω (Poisson's kinematic equation),
  so u = v − ∫ v × ω dt is constant; the channel is the difference of consecutive block means of u,
  per axis (the accelerometer and the magnetometer each checked against the gyro).

A model error is a perturbation δω(t), δa(t), δm(t) of the calibrated signals (N, 3); each channel is
linearised in it (:meth:`Design.response`), so every candidate effect whose raw-signal change is linear in
its parameters becomes a set of regressor columns, and nuisance columns (bias and full 3×3 matrix error of
each sensor) let the baseline re-fit itself so an effect is only credited with what a re-calibration
cannot absorb.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import NDArray

from .motion import Session, integrate_attitude, smooth

Array = NDArray[np.float64]
Mask = NDArray[np.bool_]

SUBCHANNELS = ("g_rest_x", "g_rest_y", "g_rest_z", "a_norm", "ka_x", "ka_y", "ka_z",
               "km_x", "km_y", "km_z", "m_norm", "dip")
CH = {n: i for i, n in enumerate(SUBCHANNELS)}
BLOCK_S = 0.2
CHUNK_S = 1.0


def _cumtrapz(y: Array, t: Array) -> Array:
    """Cumulative trapezoid integral along axis −2 of y (..., N, 3) over t (N,), starting at 0."""
    dt = np.diff(t)[:, None]
    inc = 0.5 * (y[..., 1:, :] + y[..., :-1, :]) * dt
    out = np.zeros_like(y)
    np.cumsum(inc, axis=-2, out=out[..., 1:, :])
    return out


@dataclass
class _Blocks:
    L: int
    K: int
    valid: Mask  # (K,) no gap inside
    t: Array  # (K,) block mid time


def _blocks(s: Session) -> _Blocks:
    L = max(4, int(round(BLOCK_S * s.rate))) if np.isfinite(s.rate) else 4
    K = s.n // L
    dt = np.diff(s.t)
    gap = (cast(Mask, np.concatenate([dt > 3.0 / s.rate, [False]])[: K * L].reshape(K, L).any(axis=1)) if K
           else np.zeros(0, bool))
    tm = s.t[: K * L].reshape(K, L).mean(axis=1) if K else np.zeros(0)
    return _Blocks(L, K, ~gap, tm)


def _bmean(x: Array, b: _Blocks) -> Array:
    """Block means of (..., N, k) → (..., K, k)."""
    n = b.K * b.L
    sh = x.shape[:-2] + (b.K, b.L, x.shape[-1])
    return x[..., :n, :].reshape(sh).mean(axis=-2)


def _rest_chunks(s: Session) -> list[tuple[int, int]]:
    """1-s chunks inside the strict rests (0.1 s trimmed at each end), as row ranges."""
    c = max(5, int(round(CHUNK_S * s.rate)))
    trim = max(1, int(round(0.1 * s.rate)))
    out = []
    for iv in s.rests:
        i0, i1 = iv.i0 + trim, iv.i1 - trim
        for k in range((i1 - i0) // c):
            out.append((i0 + k * c, i0 + (k + 1) * c))
    return out


class Design:
    """The stacked residual rows of one session and the map from model perturbations to them.

    ``y`` (n,) residual, ``ch`` (n,) sub-channel index, ``t`` (n,) time of each row (s, session clock),
    ``sid`` session number (for fold splitting).
    """

    def __init__(self, s: Session, g: float, sid: int = 0, exclude: Array | None = None) -> None:
        # exclude: (N,) bool at run time (censored samples); core's list of them is typed Array
        mask = cast(Mask | None, exclude)
        self.s = s
        self.g = g
        self.sid = sid
        # windows of one long log (diagnose/sample.py) share one drift walk over the log's time span: the group
        # key and that span (s); None: the walk is this session's own
        self.drift_group: object = None
        self.drift_span: tuple[float, float] | None = None
        self.b = _blocks(s)
        self.chunks = _rest_chunks(s)
        b = self.b
        if mask is not None and mask.any():
            # censored samples (clipped at a rail): no block or rest chunk that holds one is a residual row
            ex = cast(Mask, mask[: b.K * b.L].reshape(b.K, b.L).any(axis=1))
            b.valid = b.valid & ~ex
            self.chunks = [c for c in self.chunks if not mask[c[0]:c[1]].any()]
        a, w = s.a, s.w
        an = np.linalg.norm(a, axis=1)
        self.clean = clean_signals(s, g, exclude=mask)
        ac = self.clean["a"]
        self.an = np.linalg.norm(ac, axis=1)
        self.ahat = ac / np.maximum(self.an, 1e-9)[:, None]
        ys, chs, ts = [], [], []
        self._masks: dict[str, Mask] = {}

        def add(name: str, val: Array, tt: Array) -> None:
            ok = np.isfinite(val)
            self._masks[name] = ok
            ys.append(val[ok])
            chs.append(np.full(int(ok.sum()), CH[name]))
            ts.append(tt[ok])

        # g_rest
        if self.chunks:
            cm = np.array([w[i0:i1].mean(axis=0) for i0, i1 in self.chunks])
            ct = np.array([s.t[i0:i1].mean() for i0, i1 in self.chunks])
            for k in range(3):
                add(f"g_rest_{'xyz'[k]}", cm[:, k], ct)
        else:
            for k in range(3):
                add(f"g_rest_{'xyz'[k]}", np.zeros(0), np.zeros(0))
        # a_norm
        v = _bmean((an - g)[:, None], b)[:, 0]
        v[~b.valid] = np.nan
        add("a_norm", v, b.t)
        # ka
        self.pair_ok = b.valid[1:] & b.valid[:-1]
        tp = 0.5 * (b.t[1:] + b.t[:-1])
        u = a - _cumtrapz(np.cross(a, w), s.t)
        du = np.diff(_bmean(u, b), axis=0)
        du[~self.pair_ok] = np.nan
        for k in range(3):
            add(f"ka_{'xyz'[k]}", du[:, k], tp)
        # km, m_norm, dip
        if s.has_mag:
            assert s.m is not None  # has_mag
            m = s.m
            mn = np.linalg.norm(m, axis=1)
            mc = self.clean["m"]
            self.mn = np.linalg.norm(mc, axis=1)
            self.mhat = mc / np.maximum(self.mn, 1e-9)[:, None]
            mh_meas = m / np.maximum(mn, 1e-9)[:, None]
            mz = np.where(np.isfinite(m), m, 0.0)
            um = mz - _cumtrapz(np.cross(mz, w), s.t)
            dum = np.diff(_bmean(um, b), axis=0)
            finite_b = cast(Mask, np.isfinite(_bmean(m, b)).all(axis=1))
            okm = self.pair_ok & finite_b[1:] & finite_b[:-1]
            dum[~okm] = np.nan
            for k in range(3):
                add(f"km_{'xyz'[k]}", dum[:, k], tp)
            v = _bmean((mn - 1.0)[:, None], b)[:, 0]
            v[~b.valid] = np.nan
            add("m_norm", v, b.t)
            ah_meas = a / np.maximum(an, 1e-9)[:, None]
            d = _bmean(np.sum(ah_meas * mh_meas, axis=1)[:, None], b)[:, 0]
            d[~b.valid] = np.nan
            self.dip0 = float(np.nanmedian(d)) if np.isfinite(d).any() else 0.0
            add("dip", d - self.dip0, b.t)
        else:
            self.mhat = None
            for n in ("km_x", "km_y", "km_z", "m_norm", "dip"):
                add(n, np.zeros(0), np.zeros(0))
        self.y = np.concatenate(ys)
        self.ch = np.concatenate(chs).astype(int)
        self.t = np.concatenate(ts)
        self.n_rows = {n: int(self._masks[n].sum()) for n in SUBCHANNELS}

    # -- linear response ------------------------------------------------------------------------
    def local_range(self, i0: int, i1: int) -> tuple[int, int]:
        """Block-aligned sample range covering rows [i0, i1) plus one block each side: a perturbation that is
        zero outside [i0, i1) moves no residual row outside it (see :meth:`response`)."""
        L = self.b.L
        return max(0, (i0 // L - 1) * L), min(self.s.n, (-(-i1 // L) + 1) * L)

    def response(self, dg: Array | None = None, da: Array | None = None, dm: Array | None = None,
                 dip_const: Array | None = None, r0: int = 0, r1: int | None = None) -> Array:
        """Rows (n, p) for p perturbation columns; dg/da/dm (p, r1 − r0, 3) in calibrated units over samples
        [r0, r1) (zero elsewhere; r0 block-aligned, and zero in the first and last block of the range unless
        it reaches the log's ends — :meth:`local_range`), or None.

        ``dip_const`` (p,): a constant added to the dip channel (the unknown field dip).
        """
        s, b = self.s, self.b
        r1 = s.n if r1 is None else r1
        p = next(x.shape[0] for x in (dg, da, dm, dip_const) if x is not None)
        L = b.L
        kb0, kb1 = r0 // L, min(b.K, r1 // L)
        nb = max(kb1 - kb0, 0)
        tt = s.t[r0:r1]
        w, a = self.clean["w"][r0:r1], self.clean["a"][r0:r1]
        out: list[Array] = []

        def bm(x: Array) -> Array:  # (..., r1 − r0, k) → (..., nb, k) block means of the covered blocks
            sh = x.shape[:-2] + (nb, L, x.shape[-1])
            return x[..., : nb * L, :].reshape(sh).mean(axis=-2)

        def place(val: Array, n_all: int, at: int) -> Array:
            full = np.zeros((p, n_all))
            full[:, at : at + val.shape[1]] = val
            return full

        def take(name: str, val: Array) -> None:  # val (p, n_all)
            out.append(val[:, self._masks[name]])

        # g_rest
        if self.chunks:
            cm = np.zeros((p, len(self.chunks), 3))
            if dg is not None:
                cs = np.concatenate([np.zeros((p, 1, 3)), np.cumsum(dg, axis=1)], axis=1)
                for k, (i0, i1) in enumerate(self.chunks):
                    j0, j1 = max(i0, r0), min(i1, r1)  # the perturbation is zero outside [r0, r1)
                    if j1 > j0:
                        cm[:, k] = (cs[:, j1 - r0] - cs[:, j0 - r0]) / (i1 - i0)
            for k in range(3):
                take(f"g_rest_{'xyz'[k]}", cm[:, :, k])
        else:
            for _ in range(3):
                out.append(np.zeros((p, 0)))
        ahat = self.ahat[r0:r1]
        # a_norm
        v = np.zeros((p, nb)) if da is None else bm(np.sum(ahat * da, axis=-1)[..., None])[..., 0]
        take("a_norm", place(v, b.K, kb0))

        def kin(dv: Array | None, v_clean: Array) -> Array:
            if dv is None and dg is None:
                return np.zeros((p, max(nb - 1, 0), 3))
            integrand = np.zeros((p, r1 - r0, 3))
            if dv is not None:
                integrand += np.cross(dv, w)
            if dg is not None:
                integrand += np.cross(v_clean, dg)
            du = -_cumtrapz(integrand, tt)
            if dv is not None:
                du += dv
            return np.diff(bm(du), axis=1)

        ddu = kin(da, a)
        for k in range(3):
            take(f"ka_{'xyz'[k]}", place(ddu[:, :, k], max(b.K - 1, 0), kb0))
        if self.mhat is not None:
            mc = self.clean["m"][r0:r1]
            mz = np.where(np.isfinite(mc), mc, 0.0)
            dmz = None if dm is None else np.where(np.isfinite(dm), dm, 0.0)
            ddu = kin(dmz, mz)
            for k in range(3):
                take(f"km_{'xyz'[k]}", place(ddu[:, :, k], max(b.K - 1, 0), kb0))
            mh = self.mhat[r0:r1]
            mh = np.where(np.isfinite(mh), mh, 0.0)
            v = np.zeros((p, nb)) if dmz is None else bm(np.sum(mh * dmz, axis=-1)[..., None])[..., 0]
            take("m_norm", place(v, b.K, kb0))
            c = np.sum(ahat * mh, axis=1)
            dd = np.zeros((p, r1 - r0))
            if da is not None:
                dd += np.sum((mh - c[:, None] * ahat) / self.an[r0:r1, None] * da, axis=-1)
            if dmz is not None:
                dd += np.sum((ahat - c[:, None] * mh) / np.maximum(self.mn[r0:r1], 1e-9)[:, None] * dmz, axis=-1)
            v = place(bm(dd[..., None])[..., 0], b.K, kb0)
            if dip_const is not None:
                v = v + dip_const[:, None]
            take("dip", v)
        else:
            for _ in range(5):
                out.append(np.zeros((p, 0)))
        return np.concatenate(out, axis=1).T

    # -- signals the candidate effects are built from -----------------------------------------------
    def temp_centered(self) -> Array | None:
        T = self.s.temp
        if not self.s.has_temp:
            return None
        T = np.where(np.isfinite(T), T, np.nanmedian(T))
        return T - T.mean()


ColumnFn = Callable[[Design], Array]


def clean_signals(s: Session, g: float, window_s: float = 10.0, exclude: Mask | None = None) -> dict[str, Array]:
    """Noise-free stand-ins for ω, a, m, ω̇ to build regressors from (a regressor made of the same noisy
    samples as the residual would fit the noise: errors-in-variables).

    ω: moving average over 0.05 s, zero inside rests. a, m: the world-frame vectors R(t)·a(t), R(t)·m(t)
    (R from integrating the calibrated gyro) averaged over ``window_s`` and rotated back, so their noise
    is that of a 10-s mean and the gyro's slow drift is followed; |a| is set to g.
    """
    w = smooth(s.w, max(1, int(round(0.05 * s.rate))))
    for iv in s.rests:
        w[iv.i0:iv.i1] = 0.0
    R = integrate_attitude(w, s.t)
    width = max(3, int(round(window_s * s.rate)))

    def steady(v: Array, fill: bool) -> Array:
        ok = cast(Mask, np.isfinite(v).all(axis=1))
        if exclude is not None:
            ok &= ~exclude
        vz = np.where(ok[:, None], v, 0.0)
        vw = np.einsum("nij,nj->ni", R, vz)
        num = smooth(vw, width)
        den = smooth(ok[:, None].astype(float), width)
        vw_s = num / np.maximum(den, 1e-9)
        bad = den[:, 0] < 0.2
        if fill and bad.any() and (~bad).sum() >= 2:
            # long censored stretches (a rail): carry the world-frame vector across them
            idx = np.flatnonzero(~bad)
            vw_s[bad] = np.column_stack([np.interp(np.flatnonzero(bad), idx, vw_s[idx, k]) for k in range(3)])
            bad = np.zeros_like(bad)
        out = np.einsum("nji,nj->ni", R, vw_s)
        out[bad] = np.nan
        return out

    a = steady(s.a, True)
    a *= g / np.maximum(np.linalg.norm(a, axis=1), 1e-9)[:, None]
    out = {"w": w, "a": a, "wdot": np.gradient(smooth(w, max(3, int(round(0.1 * s.rate)))), s.t, axis=0), "R": R}
    if s.has_mag:
        assert s.m is not None  # has_mag
        m = steady(s.m, False)
        out["m"] = m / np.maximum(np.linalg.norm(m, axis=1), 1e-9)[:, None]
    return out


def nuisance(d: Design) -> Array:
    """Baseline re-fit columns: per sensor a bias (3) and a full matrix error E (9), δc = b + E c, and the
    dip constant. Calibrated-frame perturbations, so they span exactly what a re-calibration with the
    paper's model can change (eqs. 1–6 linearised)."""
    N = d.s.n
    blocks = []
    c = d.clean
    sensors = [("g", c["w"]), ("a", c["a"])] + ([("m", c["m"])] if d.mhat is not None else [])
    for name, cv in sensors:
        cz = np.where(np.isfinite(cv), cv, 0.0)
        cols = np.zeros((12, N, 3))
        for i in range(3):
            cols[i, :, i] = 1.0
            for j in range(3):
                cols[3 + 3 * i + j, :, i] = cz[:, j]
        kw: dict[str, Array | None] = {"dg": None, "da": None, "dm": None}
        kw["d" + name] = cols
        blocks.append(d.response(dg=kw["dg"], da=kw["da"], dm=kw["dm"]))
    if d.mhat is not None:
        blocks.append(d.response(dip_const=np.ones(1)))
    else:
        blocks.append(np.zeros((d.y.size, 13)))  # mag columns and dip: no rows respond
    return np.concatenate(blocks, axis=1)


N_NUISANCE = 37


def earth_rate(d: Design) -> Array:
    """Response to the Earth's rotation (Ω_E = 7.29e-5 rad/s): a gyro senses a rate that is constant in a
    level frame, so in the body R(t)ᵀ Ω_w with R (world ← body) the attitude — a bias while the vehicle
    keeps its heading, but one that moves between the axes when it turns (a fixed-wing's circuit carries
    Ω_E cos φ ≈ 5e-5 rad/s from x to y and back, which a constant-bias baseline leaves to ``bias_drift``).
    Three columns, δω = R(t)ᵀ e_k, R integrated from the calibrated gyro with the session's first body
    frame as the world (each session has its own). Not a free nuisance: Ω_w's norm is known, and where
    the gravity is the only world vector the body sees (rests, a platform turning about a fixed point) an
    isotropic g-sensitivity G = c·I has the same columns — :func:`.analysis.fit_earth_rate` bounds it.
    (rows, 3)."""
    w = np.where(np.isfinite(d.s.w), d.s.w, 0.0)
    R = integrate_attitude(w, d.s.t)
    # R(t)ᵀ e_k is row k of R(t): cols[k, n, :] = R[n, k, :]
    return d.response(dg=np.ascontiguousarray(np.transpose(R, (1, 0, 2))))
