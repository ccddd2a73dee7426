"""Stage 3 of diagnose: one candidate model per effect of the contract's vocabulary.

Linear-in-parameter effects are regressor columns on the residual channels (:mod:`.regressors`); each is a
raw-signal change φ(t) on one sensor axis (effects_spec.md), mapped to the calibrated frame by the
baseline's matrix (δc = M δraw, eq. 1). Saturation and axis_sign are discrete and have their own tests
here (flat runs at the rail; handedness of each sensor against the others).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from ..model import Calibration
from .regressors import Design

Array = NDArray[np.float64]
AXES = "xyz"
DRIFT_KNOT_S = 10.0
# at most this many knots per log for the drift walk (61: a 10-minute log at DRIFT_KNOT_S): longer logs get
# wider knot spacing, so the drift block has a duration-independent column count and the dense design stays
# (rows × bounded columns), i.e. memory linear in the duration (it grew as T² with a fixed spacing: 4.9 GB
# for a 30-minute flight). A rate random walk's power is ∝ 1/f², so the coarser knots lose only its fast
# part; drift_prior takes the actual spacing, so the walk's density keeps its meaning.
DRIFT_MAX_KNOTS = 61
PILE_UP = 3.0  # samples at a rail against the median count of the three values just below it (find_saturation)


@dataclass
class Candidate:
    """A nested extension of the baseline: ``columns(design) → (n_rows, k)`` and the map from the fitted
    coefficients to the effect's spec parameters."""

    effect: str
    sensor: str
    k_per_session: bool  # columns differ per session (drift knots) rather than shared parameters
    columns: Callable[[Design, Calibration], Array]
    params: Callable[[Array, Array, list[Design], Calibration], dict[str, Any]] = field(repr=False)
    needs: tuple[str, ...] = ()

    @property
    def key(self) -> str:
        return f"{self.effect}:{self.sensor}"


def _raw_cols(d: Design, cal: Calibration, sensor: str, phi: Array, r0: int = 0, r1: int | None = None) -> Array:
    """phi (r1 − r0, 3): per-axis raw change on axis j (one column per axis) → response rows (n, 3)."""
    sc = cal.sensor(sensor)
    M = sc.matrix if sc is not None else np.eye(3)
    cols = phi.T[:, :, None] * M.T[:, None, :]  # (3 axes, samples, 3 calibrated components)
    key = {"gyro": "dg", "accel": "da", "mag": "dm"}[sensor]
    return d.response(**{key: cols}, r0=r0, r1=r1)


def _raw_clean(d: Design, cal: Calibration, sensor: str) -> Array:
    """Model-predicted raw signal (noise-free): M⁻¹ c_clean + o (eq. 1 inverted)."""
    sc = cal.sensor(sensor)
    c = d.clean["w" if sensor == "gyro" else "a"]
    return sc.inv().apply(c) if sc is not None else c


# -- column builders -------------------------------------------------------------------------------

def temp_cols(sensor: str) -> Callable[[Design, Calibration], Array]:
    def f(d: Design, cal: Calibration) -> Array:
        T = d.temp_centered()
        if T is None:
            return np.zeros((d.y.size, 3))
        return _raw_cols(d, cal, sensor, np.repeat(T[:, None], 3, axis=1))
    return f


def drift_knots(d: Design, spacing: float = DRIFT_KNOT_S, max_knots: int = DRIFT_MAX_KNOTS) -> Array:
    """Knot times (K,) of the drift walk over the log: ``spacing`` s apart, at most ``max_knots``. A window of a
    sampled log (``d.drift_span`` set) has the knots of the whole log's span: one walk through all its windows."""
    t0, t1 = d.drift_span if d.drift_span is not None else (float(d.s.t[0]), float(d.s.t[-1]))
    nk = min(max_knots, max(2, int(np.ceil((t1 - t0) / spacing)) + 1))
    return np.linspace(t0, t1, nk)


def hats(t: Array, knots: Array) -> Array:
    """Piecewise-linear interpolation basis (N, K) over ``knots`` (the first one dropped: the constant is the
    bias nuisance's)."""
    K = knots.size
    H = np.zeros((t.size, K))
    j = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, K - 2)
    u = (t - knots[j]) / (knots[j + 1] - knots[j])
    H[np.arange(t.size), j] = 1 - u
    H[np.arange(t.size), j + 1] = u
    return H[:, 1:]


def _hat(t: Array, knots: Array, k: int) -> Array:
    """The piecewise-linear hat of knot k (1 at knots[k], 0 at its neighbours and beyond) at times t."""
    y = np.zeros(t.size)
    if k > 0:
        m = (t >= knots[k - 1]) & (t <= knots[k])
        y[m] = (t[m] - knots[k - 1]) / (knots[k] - knots[k - 1])
    if k < knots.size - 1:
        m = (t > knots[k]) & (t <= knots[k + 1])
        y[m] = (knots[k + 1] - t[m]) / (knots[k + 1] - knots[k])
    elif k == knots.size - 1:
        y[t >= knots[k]] = 1.0
    return y


def drift_cols(sensor: str) -> Callable[[Design, Calibration], Array]:
    """The drift walk's columns: one hat per knot (the first dropped: the constant is the bias nuisance's)
    and axis, each built over its own support only (two knot intervals), so no samples × knots matrix is
    held (the same values as :func:`hats`)."""
    def f(d: Design, cal: Calibration) -> Array:
        kn = drift_knots(d)
        t = d.s.t
        out = []
        for k in range(1, kn.size):
            i0 = int(np.searchsorted(t, kn[k - 1], side="left"))
            i1 = int(np.searchsorted(t, kn[k + 1], side="right")) if k + 1 < kn.size else t.size
            r0, r1 = d.local_range(i0, max(i1, i0 + 1))
            if r1 >= d.s.n - d.b.L:  # the last knot's hat reaches the log's end: no zero margin needed
                r1 = d.s.n
            phi = np.repeat(_hat(t[r0:r1], kn, k)[:, None], 3, axis=1)
            out.append(_raw_cols(d, cal, sensor, phi, r0, r1))
        return np.concatenate(out, axis=1)  # column order: knot-major, axis-minor
    return f


def gsens_cols(d: Design, cal: Calibration) -> Array:
    """The full 3×3 g-sensitivity (raw gyro ← G·f, f the body specific force): for each force component j a
    raw change f_j on every gyro axis i, i.e. the column of G[i, j] at 3·j + i."""
    f = d.clean["a"]
    return np.concatenate([_raw_cols(d, cal, "gyro", np.repeat(f[:, j : j + 1], 3, axis=1)) for j in range(3)],
                          axis=1)


def gsens_params(beta: Array, cov: Array, ds: list[Design], cal: Calibration) -> dict[str, Any]:
    """G (3×3, rad/s per m/s²) from the 9 coefficients (order 3·j + i); a cross-axis term counts when it is
    ≥ 5 σ and ≥ 30 % of the largest element: then the finding is the full matrix (axis all, ``matrix``), else
    the same-axis terms alone as before (``coeff`` on one axis or per axis)."""
    G = beta.reshape(3, 3).T
    sd = np.sqrt(np.maximum(np.diag(cov), 0)).reshape(3, 3).T
    off = ~np.eye(3, dtype=bool)
    z = np.abs(G) / np.maximum(sd, 1e-300)
    big = (z >= 5.0) & (np.abs(G) >= 0.3 * np.abs(G).max())
    out: dict[str, Any] = {"matrix": G.tolist(), "matrix_sigma": sd.tolist(),
                           "matrix_mrad_s_per_g": (G * 9.80665e3).tolist()}
    if (big & off).any():
        out.update({"axis": None, "coeff": np.diag(G).tolist(), "per_axis": np.diag(G).tolist(),
                    "per_axis_sigma": np.diag(sd).tolist(), "full": True})
        return out
    axis, c = _axis_choice(np.diag(G), np.diag(sd))
    out.update({"axis": axis, "coeff": c, "per_axis": np.diag(G).tolist(), "per_axis_sigma": np.diag(sd).tolist(),
                "full": False})
    return out


def nonlin_cols(sensor: str) -> Callable[[Design, Calibration], Array]:
    def f(d: Design, cal: Calibration) -> Array:
        r = _raw_clean(d, cal, sensor)
        return _raw_cols(d, cal, sensor, r * np.abs(r))
    return f


def lever_cols(d: Design, cal: Calibration) -> Array:
    w, wd = d.clean["w"], d.clean["wdot"]
    cols = np.zeros((3, d.s.n, 3))
    for j in range(3):
        e = np.zeros(3)
        e[j] = 1.0
        cols[j] = np.cross(wd, e) + np.cross(w, np.cross(w, e))
    return d.response(da=cols)


def offset_cols(d: Design, cal: Calibration) -> Array:
    """Late stamps: v_meas(t) = v(t − δ) ≈ v − δ v̇ with v̇ = v × ω (Poisson). Two columns, the accel's and
    the mag's offset relative to the gyro's (a common offset of all three is invisible)."""
    w, a = d.clean["w"], d.clean["a"]
    ca = d.response(da=-np.cross(a, w)[None])
    if d.mhat is None:
        return np.concatenate([ca, np.zeros_like(ca)], axis=1)
    m = np.where(np.isfinite(d.clean["m"]), d.clean["m"], 0.0)
    cm = d.response(dm=-np.cross(m, w)[None])
    return np.concatenate([ca, cm], axis=1)


# -- parameters from coefficients ------------------------------------------------------------------

def _axis_choice(beta: Array, sd: Array, z_min: float = 5.0) -> tuple[str | None, float]:
    """One axis or all: an axis counts when its coefficient is ≥ z_min σ and ≥ 30 % of the largest;
    exactly one such axis → that axis and its coefficient, else all axes and their σ-weighted mean."""
    z = np.abs(beta) / np.maximum(sd, 1e-300)
    big = (z >= z_min) & (np.abs(beta) >= 0.3 * np.max(np.abs(beta)))
    if big.sum() == 1:
        j = int(np.argmax(big))
        return AXES[j], float(beta[j])
    w = 1.0 / np.maximum(sd, 1e-300) ** 2
    return None, float(np.sum(w * beta) / np.sum(w))


def per_axis_params(name: str) -> Callable[[Array, Array, list[Design], Calibration], dict[str, Any]]:
    def f(beta: Array, cov: Array, ds: list[Design], cal: Calibration) -> dict[str, Any]:
        sd = np.sqrt(np.maximum(np.diag(cov), 0))
        axis, c = _axis_choice(beta, sd)
        return {"axis": axis, name: c, "per_axis": beta.tolist(), "per_axis_sigma": sd.tolist()}
    return f


def lever_params(beta: Array, cov: Array, ds: list[Design], cal: Calibration) -> dict[str, Any]:
    sd = np.sqrt(np.maximum(np.diag(cov), 0))
    return {"axis": None, "x": float(beta[0]), "y": float(beta[1]), "z": float(beta[2]),
            "sigma": sd.tolist()}


def offset_params(beta: Array, cov: Array, ds: list[Design], cal: Calibration) -> dict[str, Any]:
    """Which sensor is off: (δ_a − δ_g, δ_m − δ_g) is (s, 0) for the accel, (0, s) for the mag and
    (−s, −s) for the gyro; the pattern closest in the coefficients' own metric wins."""
    da, dm = float(beta[0]), float(beta[1])
    sd = np.sqrt(np.maximum(np.diag(cov), 1e-30))
    has_mag = any(d.mhat is not None for d in ds)
    if not has_mag:
        return {"sensor": "accel", "axis": None, "seconds": da, "relative_to": "gyro",
                "note": "no magnetometer: an accel stamped late cannot be told from a gyro stamped early"}
    cands = {"accel": (np.array([da, 0.0]), da), "mag": (np.array([0.0, dm]), dm),
             "gyro": (np.array([(da + dm) / 2] * 2), -(da + dm) / 2)}
    best = min(cands, key=lambda k: float(np.sum(((np.array([da, dm]) - cands[k][0]) / sd) ** 2)))
    return {"sensor": best, "axis": None, "seconds": float(cands[best][1]),
            "relative": {"accel_minus_gyro": da, "mag_minus_gyro": dm}}


def drift_prior(K: int, q: Array, dt: float) -> Array:
    """Prior precision of the knot values of a rate random walk (density q per axis, knots dt apart, the
    first knot pinned at 0 by the bias nuisance): increments ~ N(0, q²·dt) independent (Wiener process).
    Column order knot-major, axis-minor. (3K, 3K)."""
    D = np.eye(K) - np.eye(K, k=-1)
    DD = D.T @ D
    return cast(Array, np.kron(DD, np.diag(1.0 / (np.maximum(q, 1e-12) ** 2 * dt))))  # stub: floating[Any]


def drift_params(beta: Array, cov: Array, ds: list[Design], cal: Calibration, q: Array | None = None,
                 lr: Array | None = None) -> dict[str, Any]:
    """The density is the maximum-marginal-likelihood q per axis (set by the caller); an axis counts when
    dropping its walk costs ≥ 5 in log marginal likelihood; one such axis → that axis."""
    assert q is not None and lr is not None
    big = lr >= 5.0
    if big.sum() == 1:
        j = int(np.argmax(big))
        return {"axis": AXES[j], "density": float(q[j]), "per_axis": q.tolist(), "per_axis_lr": lr.tolist()}
    sel = big if big.any() else np.ones(3, bool)
    return {"axis": None, "density": float(np.sqrt(np.mean(q[sel] ** 2))), "per_axis": q.tolist(),
            "per_axis_lr": lr.tolist()}


def candidates(has_mag: bool, has_temp: bool) -> list[Candidate]:
    """Every linear candidate the data can test (temperature needs a temperature channel)."""
    out = [
        Candidate("bias_drift", "gyro", True, drift_cols("gyro"), drift_params),
        Candidate("bias_drift", "accel", True, drift_cols("accel"), drift_params),
        Candidate("g_sensitivity", "gyro", False, gsens_cols, gsens_params),
        Candidate("scale_nonlinearity", "gyro", False, nonlin_cols("gyro"), per_axis_params("coeff")),
        Candidate("scale_nonlinearity", "accel", False, nonlin_cols("accel"), per_axis_params("coeff")),
        Candidate("lever_arm", "accel", False, lever_cols, lever_params),
        Candidate("time_offset", "all", False, offset_cols, offset_params),
    ]
    if has_mag:  # mag_current (diagnose/magcurrent.py); coverage blocks it without a varying current/throttle
        from .magcurrent import candidates as mag_current_candidates
        out += mag_current_candidates()
    if has_temp:
        out = [Candidate("temperature_bias", "gyro", False, temp_cols("gyro"), per_axis_params("coeff")),
               Candidate("temperature_bias", "accel", False, temp_cols("accel"), per_axis_params("coeff"))] + out
    return out


# -- discrete effects ------------------------------------------------------------------------------

@dataclass
class Saturated:
    sensor: str
    limit: float
    mask: NDArray[np.bool_]  # (N,) any axis at the rail
    n_rail: int
    longest_run: int
    per_axis: list[int]


def find_saturation(raw: Array, sensor: str, min_samples: int = 10, min_run: int = 3) -> Saturated | None:
    """Flat runs at the extreme value: an ADC rail reads exactly ±limit on every axis, so the largest |raw|
    repeats in runs of consecutive samples. A clean signal with noise reaches its largest value once or
    a few times (quantisation), never in a run of min_run samples on several occasions."""
    a = np.abs(raw)
    if a.size == 0 or not np.isfinite(a).any():
        return None
    top = float(np.nanmax(a))
    at = a >= top * (1 - 1e-9)
    anyax = cast(NDArray[np.bool_], at.any(axis=1))  # 2-D → an array (stub: bool | array)
    n = int(anyax.sum())
    if n < min_samples:
        return None
    m = np.concatenate([[0], anyax.astype(np.int8), [0]])
    d = np.diff(m)
    runs = np.flatnonzero(d == -1) - np.flatnonzero(d == 1)
    if (runs >= min_run).sum() < 2:
        return None
    # a rail piles the samples up: every sample whose input is beyond it reads exactly the limit, so the top
    # value holds many times more samples than the values just below it. A flat-topped motion (a fixed-wing's
    # roll-rate limit, a plateau of the rate setpoint) reaches its top as often as its neighbours on the
    # quantisation lattice (clean 5-min fixed-wing flight, seed 7012: 17 samples at the top against 8–12 at
    # each of the three values below; a simulated gyro rail: 53 against 1–2, an accelerometer rail 3262
    # against 2–5)
    below = np.unique(a[np.isfinite(a) & (a < top * (1 - 1e-9))])[-3:]
    if below.size:
        near = float(np.median([np.count_nonzero(a == v) for v in below]))
        if n < PILE_UP * max(near, 1.0):
            return None
    return Saturated(sensor, top, anyax, n, int(runs.max()), at.sum(axis=0).tolist())


@dataclass
class Handedness:
    sensor: str | None
    axis: str | None
    det_gyro: float  # sign of det of the gyro→vector-sensor rate map (−1: gyro left-handed)
    angles_deg: dict[str, float]  # rotation angle of each vector sensor's rate map (≈180°: reflected)
    evidence: str


def _rate_map(v: Array, t: Array, w_raw: Array, rate: float) -> Array | None:
    """G (3×3) with v̇ ≈ v × (G ω) (Poisson's equation with an unknown linear gyro map), least squares over
    the samples in motion. v: a world-fixed vector in the sensor's frame, ω: bias-removed raw gyro."""
    k = max(3, int(round(0.1 * rate)))
    from .motion import smooth

    ok = cast(NDArray[np.bool_], np.isfinite(v).all(axis=1))  # 2-D → an array (stub: bool | array)
    if ok.sum() < 100:
        return None
    vs = smooth(np.where(ok[:, None], v, 0.0), k)
    ws = smooth(w_raw, k)
    vd = np.gradient(vs, t, axis=0)
    good = ok & (np.linalg.norm(ws, axis=1) > 0.3)
    good[: 2 * k] = False
    good[-2 * k:] = False
    if good.sum() < 50:
        return None
    vs, ws, vd = vs[good], ws[good], vd[good]
    vn = np.linalg.norm(vs, axis=1, keepdims=True)
    vs, vd = vs / vn, vd / vn
    # v × (G ω) = [v]ₓ G ω; coefficient of G_ij in row r is ([v]ₓ)_ri ω_j
    S = np.zeros((vs.shape[0], 3, 3))
    S[:, 0, 1], S[:, 0, 2], S[:, 1, 0] = -vs[:, 2], vs[:, 1], vs[:, 2]
    S[:, 1, 2], S[:, 2, 0], S[:, 2, 1] = -vs[:, 0], -vs[:, 1], vs[:, 0]
    A = np.einsum("nri,nj->nrij", S, ws).reshape(-1, 9)
    g = np.linalg.lstsq(A, vd.reshape(-1), rcond=None)[0]
    return g.reshape(3, 3)


def find_axis_sign(t: Array, raw_g: Array, gyro_bias: Array, a: Array | None, m: Array | None,
                   rate: float) -> Handedness | None:
    """Handedness of each sensor against the others (Poisson's equation v̇ = v × ω holds in right-handed
    frames only; Q(a×b) = det Q · (Qa × Qb) for orthogonal Q).

    For a vector sensor v and the gyro, fit G with v̇ = v × (G ω_raw). A gyro with an inverted axis gives
    det G < 0 against every vector sensor; a vector sensor with an inverted axis j gives G = −F_j·(…), a
    proper rotation by 180° about j — sensors of one board are nominally aligned, so a 180° rate map names
    the inverted vector sensor and its axis. ``a``, ``m``: bias-removed vectors in their own raw frames (None:
    not usable — an accelerometer that sees linear acceleration is no world-fixed vector).
    """
    w = raw_g - gyro_bias
    fitted = {"accel": _rate_map(a, t, w, rate)} if a is not None else {}
    if m is not None:
        fitted["mag"] = _rate_map(m, t, w, rate)
    maps: dict[str, Array] = {k: v for k, v in fitted.items() if v is not None}
    if not maps:
        return None
    dets = {k: float(np.sign(np.linalg.det(G))) for k, G in maps.items()}
    angles = {}
    axes = {}
    for k, G in maps.items():
        U, _, Vt = np.linalg.svd(G)
        Rm = U @ Vt
        if np.linalg.det(Rm) < 0:
            # gyro reflected: remove the reflection along the axis that leaves the smallest rotation
            best = None
            for j in range(3):
                F = np.eye(3)
                F[j, j] = -1
                R2 = Rm @ F
                ang = np.degrees(np.arccos(np.clip((np.trace(R2) - 1) / 2, -1, 1)))
                if best is None or ang < best[0]:
                    best = (ang, j)
            assert best is not None
            angles[k] = float(best[0])
            axes[k] = AXES[best[1]]
            continue
        ang = float(np.degrees(np.arccos(np.clip((np.trace(Rm) - 1) / 2, -1, 1))))
        angles[k] = ang
        ev, V = np.linalg.eig(Rm)
        axes[k] = AXES[int(np.argmax(np.abs(V[:, int(np.argmin(np.abs(ev - 1)))])))]
    if all(d < 0 for d in dets.values()):
        ax = next(iter(axes.values()))
        return Handedness("gyro", ax, -1.0, angles,
                          f"the gyro's rate map to {' and '.join(maps)} has det < 0 (a left-handed triad); "
                          f"flipping gyro {ax} makes it a rotation of {min(angles.values()):.1f}°")
    flipped = [k for k in maps if dets[k] > 0 and angles[k] > 150.0]
    if len(flipped) == 1:
        k = flipped[0]
        return Handedness(k, axes[k], 1.0, angles,
                          f"the {k}'s rates against the gyro need a {angles[k]:.0f}° turn about {axes[k]} "
                          f"(= one inverted axis: −F_{axes[k]} is that turn); the other sensors agree within "
                          f"{max([angles[j] for j in maps if j != k] or [0.0]):.1f}°")
    return Handedness(None, None, 1.0, angles, "every sensor's rate map is a proper rotation")
