"""Stage 2c of diagnose: can the paper's model stand as the baseline, and what can this data test?

Two checks run before any effect is scored:

* **adequacy** — per residual channel (each an invariant of the paper's model, :mod:`.regressors`), the RMS
  of the measured residual against the RMS of the same channel on the re-simulated session (what "the model is
  right" gives for this motion and noise). A channel whose measured RMS stays more than ``ADEQ_MAX`` times the
  simulated one even after *every* candidate effect has been fitted at once, the candidates explaining less
  than ``ADEQ_EXPLAINED`` of its excess variance (or more than ``ADEQ_GROSS`` times, whatever they explain),
  cannot be explained by any effect: the baseline does not meet that invariant. Its rows are left out of the
  effect scoring (effects are scored against the part of the baseline that holds) and the first finding names
  it (sensor, invariant, how far).
  One pattern is told apart: the accelerometer's kinematic channels (|a| = g in motion, gravity fixed in the
  world) failing while |a| = g holds at the rests, with the candidates (a lever arm among them) explaining less
  than ``ADEQ_EXPLAINED`` of |a| − g in motion, is *linear acceleration* of the sensor (thrust in flight, a
  hand carrying the board between poses), not a calibration error: those channels are dropped and the effects
  read from them (lever arm, the accelerometer's time offset and non-linearity, its handedness) are reported
  untestable;
* **data requirements** — each effect needs a minimum rate, duration and excitation (``REQUIRES``); an effect
  whose requirement this data does not meet is not scored, and the untestable list says which figure fell short.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .analysis import Analysis
from .magcurrent import REQUIREMENT as MAG_CURRENT_REQUIREMENT
from .magcurrent import blocked_reason as mag_current_blocked
from .regressors import SUBCHANNELS, Design
from .score import solve

Array = NDArray[np.float64]

ADEQ_MAX = 3.0  # measured/simulated RMS above which an invariant is not met (9× the variance noise gives)
# |a| − g RMS at rest (m/s²) that a 9-parameter accelerometer model may leave on a real part (≈ 5 mg: the
# part's own non-linearity and temperature); beyond it, and beyond ADEQ_MAX× noise, the accel model fails
ACC_REST_TOL = 0.05
# an invariant above ADEQ_MAX after every candidate is still met *by the candidates* when they explain at least
# this share of its excess variance (a large random walk leaves ~5× at the 1-s scale its 10-s knots cannot
# follow, after explaining 98 %); beyond ADEQ_GROSS it is not met whatever they explain
ADEQ_EXPLAINED = 0.9
ADEQ_GROSS = 10.0

INVARIANTS: dict[str, tuple[str, str]] = {
    "g_rest": ("gyro", "the calibrated gyro reads zero at rest"),
    "a_norm": ("accel", "|a| = g"),
    "ka": ("accel", "gravity is fixed in the world (ȧ = a × ω, accelerometer against gyro)"),
    "km": ("mag", "the field is fixed in the world (ṁ = m × ω, magnetometer against gyro)"),
    "m_norm": ("mag", "|m| = 1"),
    "dip": ("mag", "the angle between field and gravity is constant"),
}
ACCEL_KINEMATIC = ("a_norm", "ka_x", "ka_y", "ka_z")
# candidates that read the accelerometer's kinematic channels only (untestable under linear acceleration)
ACCEL_KINEMATIC_EFFECTS = ("lever_arm:accel", "scale_nonlinearity:accel")
# |a| − g RMS in motion (m/s²) beyond which no accelerometer bias term (drift, temperature) can be its
# cause: 50 mg, tens of times the bias instability and temperature drift of MEMS accelerometers (mg-level)
LIN_ACC_BIAS_MAX = 0.5
ACCEL_BIAS_KEYS = ("bias_drift:accel", "temperature_bias:accel")
MIN_RATE_HZ = 10.0  # below it no invariant is checked (0.2-s blocks and 1-s rest chunks need ≥ 2–10 samples)

# minimum data per effect: (rate Hz, duration s, what else), as stated in the evidence and the docs
REQUIRES: dict[str, str] = {
    "temperature_bias": "≥ 10 Hz, ≥ 60 s, a temperature range ≥ 2 °C",
    "bias_drift": "≥ 10 Hz, ≥ 60 s",
    "g_sensitivity": "≥ 10 Hz, rests (≥ 1 s) in ≥ 3 gravity directions ≥ 30° apart",
    "scale_nonlinearity": "≥ 50 Hz, ≥ 10 s of rotation faster than 0.5 rad/s; for the gyro, rates that "
                          "resolve 1.8e-3 per rad/s at 5 σ (the datasheet limit, nonlin_resolution)",
    "lever_arm": "≥ 50 Hz, ≥ 10 s of rotation faster than 0.5 rad/s, gravity-dominated specific force",
    "time_offset": "≥ 50 Hz, ≥ 10 s of rotation faster than 0.5 rad/s",
    "mag_current": "≥ 10 Hz, " + MAG_CURRENT_REQUIREMENT,  # diagnose/magcurrent.py
}


# The largest gyro nonlinearity a MEMS datasheet allows: 0.2 % of full scale, best-fit straight line
# (MPU-6000; ICM-20602 and BMI088 state 0.1 % and 0.05 %), at the smallest common range, ±250 °/s. For the
# model's raw·(1 + c·|raw|) on [−F, F] the best straight line is (3cF/4)·raw and the largest deviation is
# cF²/4 (at ±F), so NL = cF/4 of full scale and c = 4·NL/F = 1.8e-3 per rad/s.
GYRO_NONLIN_MAX = 4.0 * 0.002 / float(np.radians(250.0))
NONLIN_SNR = 5.0  # the coefficient the data must resolve, in σ of its estimate


def nonlin_resolution(an: Analysis, key: str = "scale_nonlinearity:gyro") -> tuple[Array, str | None]:
    """Per-axis σ of the gyro nonlinearity coefficient this data gives (1/(rad/s)), fitted with the baseline's
    nuisance, and why the candidate is untestable (None: testable): the rotation rates it holds must let
    even the largest nonlinearity a datasheet allows (:data:`GYRO_NONLIN_MAX`) stand at :data:`NONLIN_SNR` σ
    on some axis. A turn at one rate makes raw·|raw| a multiple of raw, which the baseline's scale absorbs;
    a multirotor's gentle turns (|ω| mostly under 0.5 rad/s) leave σ ≈ 4e-3, above any real part's value."""
    if key not in an.blocks:
        return np.zeros(0), None
    # the σ the noise alone allows (the Gram inverse of the whitened rows), not scaled by the residual's
    # variance: an effect the baseline lacks (a time offset of 120,000 nats) must not make the data look
    # unable to resolve another
    P = an.problem
    ix = P.idx(["nuisance"] + an.blocks[key])
    _, C = P._fit(P.G[0] + P.G[1], ix, None, want_inv=True)
    sig = np.sqrt(np.maximum(np.diag(C)[-3:], 0.0))
    res = NONLIN_SNR * sig
    if float(res.min()) <= GYRO_NONLIN_MAX:
        return sig, None
    return sig, (f"scale_nonlinearity (gyro): the rotation rates in this data resolve a coefficient of "
                 f"{', '.join(f'{x:.2g}' for x in res)} per rad/s (x, y, z; {NONLIN_SNR:g} σ), more than the "
                 f"largest a MEMS datasheet allows ({GYRO_NONLIN_MAX:.2g}: 0.2 % of ±250 °/s) — turns at "
                 f"several rates, some fast, are needed")


def _group(name: str) -> str:
    return name.rsplit("_", 1)[0] if name[:2] in ("ka", "km") or name.startswith("g_rest") else name


@dataclass
class Coverage:
    """What this data offers, for the per-effect requirements."""

    rate_hz: float
    duration_s: float
    rotation_s: float  # seconds with |ω| > 0.5 rad/s
    rest_directions: int  # distinct gravity directions (≥ 30° apart) over the rests of ≥ 1 s
    temp_range_c: float
    blocked: dict[str, str] = field(default_factory=dict)  # candidate effect → why untestable

    def to_dict(self) -> dict[str, Any]:
        return {"rate_hz": self.rate_hz, "duration_s": self.duration_s, "rotation_s": self.rotation_s,
                "rest_directions": self.rest_directions, "temperature_range_c": self.temp_range_c}


def coverage(designs: list[Design]) -> Coverage:
    """Rate, duration, rotation, rest directions and temperature range over the sessions, and the effects
    they cannot test (``REQUIRES``)."""
    rate = float(max(d.s.rate for d in designs)) if designs else 0.0
    dur = float(sum(d.s.t[-1] - d.s.t[0] for d in designs if d.s.n > 1))
    rot = float(sum(float((np.linalg.norm(d.clean["w"], axis=1) > 0.5).sum()) / d.s.rate for d in designs))
    dirs: list[Array] = []
    for d in designs:
        for iv in d.s.rests:
            if iv.n < d.s.rate:
                continue
            v = d.s.a[iv.i0:iv.i1].mean(axis=0)
            nv = float(np.linalg.norm(v))
            if not np.isfinite(nv) or nv == 0:
                continue
            u = v / nv
            if all(float(u @ w) < np.cos(np.radians(30.0)) for w in dirs):
                dirs.append(u)
    temps = [d.s.temp[np.isfinite(d.s.temp)] for d in designs if d.s.has_temp]
    trange = float(max((np.percentile(T, 99) - np.percentile(T, 1) for T in temps if T.size), default=0.0))
    c = Coverage(rate, dur, rot, len(dirs), trange)
    here = f"this data: {rate:.3g} Hz, {dur:.0f} s"
    b = c.blocked
    for eff in REQUIRES:
        why = []
        fast = eff in ("scale_nonlinearity", "lever_arm", "time_offset")
        if rate < (50.0 if fast else 10.0):
            why.append(f"rate {rate:.3g} Hz")
        if eff in ("temperature_bias", "bias_drift") and dur < 60.0:
            why.append(f"{dur:.0f} s long")
        if eff == "temperature_bias" and temps and trange < 2.0:
            why.append(f"temperature range {trange:.2g} °C")
        if eff == "g_sensitivity" and len(dirs) < 3:
            why.append(f"rests in {len(dirs)} gravity direction{'s' if len(dirs) != 1 else ''}")
        if fast and rot < 10.0:
            why.append(f"{rot:.0f} s of rotation faster than 0.5 rad/s")
        if why:
            b[eff] = f"{eff}: needs {REQUIRES[eff]}; {here}: {', '.join(why)}"
    if "mag_current" not in b and (why_mc := mag_current_blocked(designs)):
        b["mag_current"] = why_mc
    return c


@dataclass
class Adequacy:
    """Per-channel measured/simulated RMS and the verdict on the baseline."""

    channels: dict[str, dict[str, float]]
    inadequate: dict[str, dict[str, Any]]  # invariant group → sensor, invariant, worst ratio, channels
    linear_acceleration: dict[str, Any] | None
    drop: tuple[str, ...]
    extrapolated_mag: str | None = None  # why the magnetometer's invariants are set aside (diagnose core)

    def to_dict(self) -> dict[str, Any]:
        return {"max_ratio": ADEQ_MAX, "channels": self.channels, "inadequate": self.inadequate,
                "linear_acceleration": self.linear_acceleration, "dropped_channels": list(self.drop),
                "adequate": not self.inadequate, "extrapolated_mag": self.extrapolated_mag}


def _rms(x: Array) -> float:
    return float(np.sqrt(np.mean(x**2))) if x.size else float("nan")


def _rest_rows(an: Analysis, margin_s: float = 0.3) -> NDArray[np.bool_]:
    """(n,) True for rows whose time lies inside a rest of their session, ``margin_s`` from its ends (a
    0.2-s block whose centre is near a rest's end still holds motion)."""
    y, ch, t, sid, _ = an.rows
    out = np.zeros(y.size, bool)
    for d in an.designs:
        m = sid == d.sid
        for iv in d.s.rests:
            out |= m & (t >= d.s.t[iv.i0] + margin_s) & (t <= d.s.t[iv.i1 - 1] - margin_s)
    return out


class _FullFit:
    """The baseline with every candidate at once, refitted as rows are taken out (Gram of all rows minus the
    Gram of the rows dropped so far: the cost is that of the dropped rows, not of the kept ones)."""

    def __init__(self, an: Analysis, exclude: tuple[str, ...] = ()) -> None:
        P = an.problem
        self.P = P
        full = ["nuisance"] + [b for k in an.blocks if k not in exclude for b in an.blocks[k]]
        self.ix = P.idx(full)
        G = P.G[0] + P.G[1]
        self.G = G[np.ix_(self.ix, self.ix)].copy()
        self.c = G[self.ix, -1].copy()
        self.d0 = np.diag(self.G).copy()
        self.pri = P.prior_matrix(full, an.priors)
        self.X = P.Z[:, self.ix] if not np.array_equal(self.ix, np.arange(self.ix.size)) else P.Z[:, : self.ix.size]
        self.dropped: NDArray[np.bool_] = np.zeros(P.n, bool)

    def drop(self, rows: NDArray[np.bool_]) -> None:
        new = rows & ~self.dropped
        if new.any():
            Xd, yd = self.X[new], self.P.Z[new, -1]
            self.G -= Xd.T @ Xd
            self.c -= Xd.T @ yd
            self.dropped |= new

    def residual(self) -> Array:
        """Residual (physical units) of the kept rows after the full fit on them (NaN on dropped rows)."""
        # columns whose every row was dropped: their Gram entries are rounding residue; zero them exactly
        G = self.G.copy()
        c = self.c.copy()
        dead = np.diag(G) <= 1e-9 * np.maximum(self.d0, 1e-300)
        G[dead, :] = 0.0
        G[:, dead] = 0.0
        c[dead] = 0.0
        A = G if self.pri is None else G + self.pri
        try:
            beta = solve(A, c)[0]
        except np.linalg.LinAlgError:  # the subtraction lost definiteness: build the kept rows' Gram afresh
            keep = ~self.dropped
            Xk = self.X[keep]
            self.G, self.c = Xk.T @ Xk, Xk.T @ self.P.Z[keep, -1]
            A = self.G if self.pri is None else self.G + self.pri
            beta = solve(A, self.c)[0]
        r = (self.P.Z[:, -1] - self.X @ beta) * self.P.sigma[self.P.ch]
        r[self.dropped] = np.nan
        return r


def assess(an: Analysis, null: Analysis) -> Adequacy:
    """Measured against re-simulated residual RMS per channel (module doc). ``an`` and ``null`` are the full
    (no channel dropped) analyses. The invariants are taken out worst first: the channel group whose RMS,
    with every candidate fitted at once on the channels still in, is furthest above ADEQ_MAX× its simulated
    RMS is named and dropped, and the fit is repeated on the rest (a gross failure in one invariant would
    otherwise distort the fit of the others)."""
    P, Q = an.problem, null.problem
    rb = P.residual(["nuisance"], P.fit(["nuisance"])[0]) * P.sigma[P.ch]
    rs = Q.residual(["nuisance"], Q.fit(["nuisance"])[0]) * Q.sigma[Q.ch]
    rest = _rest_rows(an)
    chans: dict[str, dict[str, float]] = {}
    for i, nm in enumerate(SUBCHANNELS):
        m, ms = P.ch == i, Q.ch == i
        if m.sum() < 12 or ms.sum() < 12:
            continue
        sim = _rms(rs[ms])
        if not sim > 0:
            continue
        chans[nm] = {"rows": int(m.sum()), "rms_measured": _rms(rb[m]), "rms_simulated": sim,
                     "ratio": _rms(rb[m]) / sim}
    drop: set[str] = set()
    inad: dict[str, dict[str, Any]] = {}
    lin = None
    ff = _FullFit(an)
    an_c = chans.get("a_norm")
    if an_c is not None:
        ia = SUBCHANNELS.index("a_norm")
        mr, mm = (P.ch == ia) & rest, (P.ch == ia) & ~rest
        if mr.sum() >= 12 and mm.sum() >= 12:
            # the baseline's own residual (no re-fit: a nuisance re-fit to the motion rows would move the rests),
            # and what every candidate at once (a lever arm's centripetal term among them) leaves of it
            y0 = P.Z[:, -1] * P.sigma[P.ch]
            r_rest, r_move = _rms(y0[mr] - np.median(y0[mr])), _rms(y0[mm] - np.median(y0[mr]))
            # an excess beyond LIN_ACC_BIAS_MAX is no accelerometer bias: the bias-type candidates (a free walk,
            # a temperature curve) would follow a flight's slow manoeuvre accelerations and "explain" them
            # (clean 5-min fixed-wing flight, seed 7011: 2.4 m/s² RMS in motion, 90 % "explained" by a walk)
            r_left = _rms((_FullFit(an, ACCEL_BIAS_KEYS) if r_move > LIN_ACC_BIAS_MAX else ff).residual()[mm])
            sim = an_c["rms_simulated"]
            an_c.update({"rms_at_rest": r_rest, "rms_in_motion": r_move, "rms_in_motion_after_all_candidates": r_left,
                         "ratio_at_rest": r_rest / sim})
            explained = 1.0 - (r_left / max(r_move, 1e-300)) ** 2
            an_c["explained_in_motion"] = explained
            # far above what the re-simulation gives, or (where the measured vibration inflates the
            # re-simulation's noise: a 200-Hz multirotor flight's block means, 0.95 m/s² RMS simulated against
            # 2.3 measured in motion and 0.001 at rest) beyond what any accelerometer bias term could be
            above = r_move > ADEQ_MAX * max(r_rest, sim) or (r_move > LIN_ACC_BIAS_MAX and r_move > ADEQ_MAX * r_rest
                                                             and r_move > sim)
            if above and explained < ADEQ_EXPLAINED:
                # |a| = g holds at rest far better than in motion, and no candidate explains the motion's
                # excess: the sensor is accelerated (thrust, a carrying hand)
                kin = sorted(set(ACCEL_KINEMATIC) & set(chans), key=SUBCHANNELS.index)
                worst = max(kin, key=lambda nm: chans[nm]["ratio"])
                lin = {"channels": kin, "worst": worst, "ratio": chans[worst]["ratio"],
                       "a_norm_rms_m_s2": r_move, "a_norm_rms_at_rest_m_s2": r_rest,
                       "a_norm_noise_m_s2": sim}
                # the dip channel reads gravity's direction from the accelerometer too
                drop |= set(kin) | ({"dip"} & set(chans))
                if r_rest / sim > ADEQ_MAX and r_rest > ACC_REST_TOL:
                    inad["a_norm"] = {"sensor": "accel", "invariant": "|a| = g at rest", "rows": int(mr.sum()),
                                      "channels": {"a_norm (rests)": r_rest / sim}, "ratio": r_rest / sim}
    for _ in range(len(INVARIANTS)):
        keep = ~np.isin(P.ch, [SUBCHANNELS.index(c) for c in drop])
        if keep.sum() < 12:
            break
        ff.drop(~keep)
        ra = ff.residual()
        worst_g, worst_r = None, ADEQ_MAX
        for nm, c in chans.items():
            if nm in drop:
                continue
            r_all = _rms(ra[P.ch == SUBCHANNELS.index(nm)]) / c["rms_simulated"]
            c["ratio_after_all_candidates"] = r_all
            # share of the excess variance over noise that the candidates explain
            c["explained"] = 1.0 - max(r_all**2 - 1.0, 0.0) / max(c["ratio"] ** 2 - 1.0, 1e-12)
            if r_all > worst_r and (r_all > ADEQ_GROSS or c["explained"] < ADEQ_EXPLAINED):
                worst_g, worst_r = _group(nm), r_all
        if worst_g is None:
            break
        sensor, inv = INVARIANTS[worst_g]
        members = [nm for nm in chans if _group(nm) == worst_g and nm not in drop]
        inad[worst_g] = {"sensor": sensor, "invariant": inv, "rows": sum(chans[nm]["rows"] for nm in members),
                         "channels": {nm: chans[nm]["ratio_after_all_candidates"] for nm in members},
                         "ratio": worst_r}
        drop |= set(members)
    if "ka" in inad and "km" in inad:
        # both vector sensors disagree with the gyro's rates: the sensor they share is the gyro
        for gname in ("ka", "km"):
            inad[gname]["sensor"] = "gyro"
            inad[gname]["note"] = "accelerometer and magnetometer both disagree with the gyro's rates"
    return Adequacy(chans, inad, lin, tuple(sorted(drop, key=SUBCHANNELS.index)))
