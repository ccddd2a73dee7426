"""``diagnose``: where the paper's sensor model disagrees with the data, the named cause, the extended model
and its measured gain (the stages are the sibling modules; this one runs them in order).

1. baseline: the batch pipeline (paper Sec. III) — after undoing an inverted axis, if the handedness test
   finds one, and with clipped samples censored, if a rail is found;
2. residual channels of the baseline (:mod:`.regressors`) and the re-simulated session (:mod:`.resim`);
   the data requirements of each effect (:func:`.adequacy.coverage`: rate, duration, excitation — an effect the
   data cannot carry is not scored) and the adequacy of the baseline (:func:`.adequacy.assess`: an invariant
   it does not meet is the first finding, ``baseline_inadequate``, and its rows are left out; linear
   acceleration sets the accelerometer's kinematic channels aside);
3. every candidate scored by its held-out log-likelihood gain (:mod:`.score`); the same score on the
   re-simulation is the null; forward selection keeps a candidate while its gain clears
   max(BIC penalty, null + margin, 3 × the null gain's spread over time blocks);
4. the selected effects' parameters (the spec's keys) and the extended calibration (``extensions``);
5. the simulator with the fitted extension, checked against the measured residual statistics;
6. the UKF (:mod:`.online`) from the baseline, and again with the extension (as extra states where the UKF
   has them, else by correcting the data): its NIS before/after in ``baseline.ukf``, ``ukf_extended`` and
   each significant finding's gain.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..batch import run_batch
from ..batch.ellipsoid import FitError
from ..batch.segment import noise_floors, segment
from ..io.base import ImuData
from ..model import Calibration
from ..specs import G0, OMEGA_EARTH
from . import magcurrent
from .adequacy import (
    ACCEL_KINEMATIC_EFFECTS,
    ADEQ_MAX,
    MIN_RATE_HZ,
    REQUIRES,
    Adequacy,
    assess,
    coverage,
    nonlin_resolution,
)
from .analysis import Analysis, analyse, channel_mask, one_blas_thread, restrict
from .detectors import Handedness, Saturated, candidates, find_axis_sign, find_saturation
from .gaps import excluded_text, split_at_gaps
from .motion import prepare
from .regressors import SUBCHANNELS, Design
from .resim import resimulate
from .result import Diagnosis, Finding
from .sample import bounded_sample
from .sample import note as sample_note
from .stats import channel_stats, rest_stats

Array = NDArray[np.float64]
MAX_EFFECTS = 4
NULL_MARGIN = 15.0  # nats above the re-simulation's own score
INSEPARABLE_RHO = 0.95  # |Spearman ρ(T, t)| above which temperature and drift are one regressor in practice
Z_SPREAD = 3.0  # the bar is at least this many standard deviations of the null's held-out gain
LIN_ACC_RMS = 0.5  # m/s²: |a| − g RMS in rotation beyond which the accelerometer is not used for handedness
NIS_TOL = 0.05  # the extended UKF's mean NIS may exceed the baseline's by this share before it is refused


def _designs(logs: list[ImuData], cal: Calibration, segs: list[Any], g: float,
             exclude: list[Array | None] | None = None) -> list[Design]:
    out = []
    for i, (d, sg) in enumerate(zip(logs, segs, strict=True)):
        s = prepare(d, cal, sg.rests)
        if s.n < 50:
            continue
        out.append(Design(s, g, i, None if exclude is None else exclude[i]))
    return out


def _share_walks(designs: list[Design], logs: list[ImuData], sampled: dict[str, Any] | None) -> None:
    """The windows of one sampled log (:mod:`.sample`) share one drift walk over the log's whole span: a bias
    that wandered between two windows is the same walk's value there, not an offset the model lacks (with a
    walk per window, 1-hour flight with a gyro walk of 1e-4 rad/s/√s: density 5.9e-4 and a spurious
    temperature_bias, the windows' offsets following the rising temperature)."""
    if sampled is None:
        return
    for d in designs:
        t0, t1 = float(d.s.t[0]), float(d.s.t[-1])
        src = logs[d.sid].source
        for j, p in enumerate(sampled["logs"]):
            w = p["windows_s"]
            # a window of that log (a re-stamped clock may differ from the stamps by a fraction of a second)
            if p["source"] == src and w[0][0] - 1.0 <= t0 and t1 <= w[-1][1] + 1.0:
                d.drift_group, d.drift_span = ("sample", j), (float(w[0][0]), float(w[-1][1]))
                break


def _threshold(k: float, n: int, null: float, spread: float = 0.0) -> float:
    """Significance bar (nats): the largest of the BIC penalty ½·k·ln n, the re-simulation's score plus a
    margin, and Z_SPREAD standard deviations of the candidate's held-out gain over the time blocks of the
    re-simulated session (:meth:`.score.Problem.spread`; the null: this motion and noise, no effect) — a
    candidate that only fits the noise scores within that spread of zero with either sign, so the bar is
    calibrated to it (one-sided 3σ: ≈ 0.1 % per candidate, ≈ 1 % per session over the ~9 candidates). The
    measured session's own spread is not used: a real effect concentrated in a few blocks inflates it."""
    return max(0.5 * k * np.log(max(n, 2)), null + NULL_MARGIN, Z_SPREAD * spread)


def _k(an: Analysis, key: str, gain: Any) -> float:
    """Parameters a candidate adds, for the BIC bar: a random walk (bias_drift) is a hierarchical model whose
    knot values are integrated out in the marginal likelihood; its parameters are the 3 densities."""
    return 3.0 if key in an.q else float(gain.k)


EVIDENCE = {
    "temperature_bias": "the {sensor} residual follows the temperature column (coefficient per °C) better on held-out "
                        "time blocks than a bias that wanders freely",
    "bias_drift": "the {sensor} bias wanders between rests (random walk of density {density:.3g}/√s by maximum "
                  "marginal likelihood), more than temperature explains",
    "g_sensitivity": "the gyro's rest readings change with the direction of gravity across the static positions "
                     "(full 3×3 G, raw gyro ← G·f)",
    "scale_nonlinearity": "the {sensor} error grows with the square of the rate (fast turns vs slow ones), beyond "
                          "what a linear scale absorbs",
    "lever_arm": "accelerometer residuals follow ω̇×r + ω×(ω×r) during turns (|f| ≠ g while rotating)",
    "time_offset": "the {sensor} lags the other sensors: the kinematic residual follows −δ·v̇ during turns",
    "mag_current": magcurrent.EVIDENCE,
}


def _finding(an: Analysis, model: list[str], key: str, gain: Any, thr: float, null: float,
             significant: bool, null_spread: float = 0.0) -> Finding:
    cand = next(c for c in an.cands if c.key == key)
    params = an.params(model, key)
    sensor = params.pop("sensor", cand.sensor)
    axis = params.pop("axis", None)
    txt = EVIDENCE.get(cand.effect, "").format(sensor=sensor, **{k: v for k, v in params.items()
                                                                   if isinstance(v, float)})
    req = f" Data needed: {REQUIRES[cand.effect]}." if cand.effect in REQUIRES else ""
    ev = (f"{txt}; held-out log-likelihood gain {gain.loglik_gain:.1f} nats against a bar of {thr:.1f} "
          f"(re-simulation without effects: {null:.1f} ± {null_spread:.1f})."
          f"{req}")
    return Finding(cand.effect, sensor, axis, float(gain.loglik_gain), significant, params, gain.to_dict(), ev,
                   thr, null)


def _extension(f: Finding, T0: float | None) -> dict[str, Any]:
    """The calibration JSON's ``extensions`` entry (onlinecal.extensions format) for a finding."""
    p = f.parameters
    e: dict[str, Any] = {}
    if f.effect in ("temperature_bias", "g_sensitivity", "scale_nonlinearity"):
        e = {"sensor": f.sensor, "axis": f.axis,
             "coeff": p["coeff"] if f.axis is not None else p.get("per_axis", p["coeff"])}
        if f.effect == "temperature_bias":
            e["T0"] = T0 if T0 is not None else 25.0
        if f.effect == "g_sensitivity":
            e.pop("sensor")
            if p.get("full"):  # cross-axis terms: the full matrix (its diagonal included), no separate coeff
                e = {"axis": None, "matrix": p["matrix"]}
    elif f.effect == "bias_drift":
        e = {"sensor": f.sensor, "axis": f.axis, "density": p["density"]}
    elif f.effect == "lever_arm":
        e = {"x": p["x"], "y": p["y"], "z": p["z"]}
    elif f.effect == "time_offset":
        e = {"sensor": f.sensor, "seconds": p["seconds"]}
    elif f.effect == "saturation":
        e = {"sensor": f.sensor, "limit": p["limit"]}
    elif f.effect == "axis_sign":
        e = {"sensor": f.sensor, "axis": f.axis}
    elif f.effect == "mag_current":
        e = magcurrent.extension(p)
    return e


def _mag_extrapolated(logs: list[ImuData], cal: Calibration) -> str | None:
    """Why the batch's own magnetometer fit is an extrapolation (its calibrated samples cover fewer than
    health.COVERAGE_MIN of the field directions: a flight's yaw turns sweep a band, on which the ellipsoid's
    scale across the band is not determined), or None. Measured: 5-minute simulated multirotor and fixed-wing
    flights (seeds 7000–7019) cover 19–28 % with mag matrix errors 4–20 %; on such a fit the field's
    invariants fail by the calibration's error, not the sensor's, and the handedness test cannot use the
    magnetometer (clean fixed-wing flights read as axis_sign and baseline_inadequate in 5 of 20)."""
    from ..health import COVERAGE_MIN, _raw_coverage

    if cal.mag is None:
        return None
    raw = [d.mag for d in logs if d.n_mag > 0]
    if not raw:
        return None
    cov = _raw_coverage(cal.mag, np.concatenate(raw))
    if cov is None or cov >= COVERAGE_MIN:
        return None
    return (f"the batch's magnetometer fit saw {100 * cov:.0f} % of the field directions (needs "
            f"{100 * COVERAGE_MIN:.0f} %), so its calibration is extrapolated (give a bench calibration with "
            "--init to test the magnetometer)")


def _accelerated(s: Any, g: float) -> bool:
    """The calibrated |a| departs from g by more than LIN_ACC_RMS (m/s², RMS) while rotating (|ω| > 0.3 rad/s):
    specific force other than gravity, so the accelerometer cannot serve as a world-fixed vector."""
    moving = np.linalg.norm(s.w, axis=1) > 0.3
    if moving.sum() < 50:
        return False
    dev = np.linalg.norm(s.a[moving], axis=1) - g
    return bool(np.sqrt(np.mean(dev**2)) > LIN_ACC_RMS)


def _handedness(logs: list[ImuData], cal: Calibration, segs: list[Any], g: float = G0) -> Handedness | None:
    """Run the handedness test on the longest log with motion (raw frames, biases from the batch)."""
    best = None
    for d, sg in zip(logs, segs, strict=True):
        if d.n_imu < 200:
            continue
        rests = [d.gyro[iv.i0:iv.i1] for iv in sg.rests]
        bias = np.median(np.concatenate(rests), axis=0) if rests else (
            cal.gyro.bias if cal.gyro is not None else np.median(d.gyro, axis=0))
        a: Array | None = d.acc - (cal.accel.bias if cal.accel is not None else 0.0)
        m = None
        if d.n_mag > 100 and cal.mag is not None:
            mm = d.mag - cal.mag.bias
            m = np.column_stack([np.interp(d.t_imu, d.t_mag, mm[:, k]) for k in range(3)])
        s = prepare(d, cal, sg.rests)
        if _accelerated(s, g):
            a = None  # thrust or a carrying hand: the accelerometer is no world-fixed vector in motion
        h = find_axis_sign(s.t, d.gyro, bias, a, m, s.rate)
        if h is not None and (best is None or d.n_imu > best[0]):
            best = (d.n_imu, h)
    return best[1] if best else None


@dataclass
class _Given:
    """A baseline given from outside (the unit's campaign calibration) with this session's segmentation."""

    calibration: Calibration
    segmentations: list[Any]
    warnings: list[str]


def _baseline(logs: list[ImuData], g: float, calibration: Calibration | None) -> Any:
    if calibration is None:
        return run_batch(logs, g=g)
    floors = noise_floors(logs)
    return _Given(calibration, [segment(d, floors) for d in logs], ["baseline calibration given (not fitted here)"])


@one_blas_thread()  # small solves throughout: BLAS threads only spin (analysis.one_blas_thread)
def diagnose(logs: list[ImuData], g: float = G0, seed: int = 0, check: bool = True,
             calibration: Calibration | None = None, ukf: bool = True,
             sampled: dict[str, Any] | None = None) -> Diagnosis:
    """Model-discrepancy discovery over the logs of one sensor unit (module docstring).

    ``seed`` seeds the re-simulation's noise; ``check`` runs stage 5 (the extended simulator against the
    measured statistics); ``calibration``: use this baseline (e.g. the unit's campaign calibration, for a
    session too short or too still to calibrate on its own) instead of running the batch on ``logs``;
    ``ukf``: run stage 6 (the UKF from the baseline, and with the extension; NIS before/after). Logs over
    :data:`.sample.BUDGET` IMU samples are diagnosed on a bounded sample of themselves (:mod:`.sample`);
    ``sampled``: the description of such a sample the caller already took (the CLI, so that it need not hold
    the whole log), stated in the result as if taken here.
    Raises FitError when the batch cannot calibrate anything.
    """
    t_start = time.perf_counter()
    timing: dict[str, float] = {}
    logs = [d for d in logs if d.n_imu > 0]
    if not logs:
        raise FitError("no IMU samples in the logs")
    sources = list(dict.fromkeys(d.source for d in logs))
    # a log over the budget is diagnosed on evenly spaced windows of itself (memory constant in its length)
    logs, taken = bounded_sample(logs)
    sampled = taken or sampled
    # holes in the time line (a NaN burst the reader dropped, a logging gap) cut a log into pieces
    logs, excluded = split_at_gaps(logs)
    if not logs:
        raise FitError("no stretch between the holes in the logs is long enough to diagnose: "
                       + "; ".join(excluded_text(e) for e in excluded))
    untestable: list[str] = []
    rng = np.random.default_rng(seed)
    findings: list[Finding] = []
    # -- 1. baseline, handedness, rails ---------------------------------------------------------------
    res = _baseline(logs, g, calibration)
    timing["batch"] = time.perf_counter() - t_start
    mag_extrap = _mag_extrapolated(logs, res.calibration) if calibration is None else None
    hand = _handedness(logs, res.calibration if mag_extrap is None else res.calibration.replace(mag=None),
                       res.segmentations, g)
    flip: Finding | None = None
    if hand is not None and hand.sensor is not None:
        from ..extensions import correct

        ext = {"axis_sign": {"sensor": hand.sensor, "axis": hand.axis}}
        before = res
        logs = [correct(d, ext) for d in logs]
        res = run_batch(logs, g=g) if calibration is None else _baseline(logs, g, calibration)
        flip = Finding("axis_sign", hand.sensor, hand.axis, 0.0, True, {}, {}, hand.evidence)
        flip.parameters = {"rate_map_angles_deg": hand.angles_deg}
        flip._before = before  # type: ignore[attr-defined]
    elif hand is None and any(_accelerated(prepare(d, res.calibration, sg.rests), g)
                              for d, sg in zip(logs, res.segmentations, strict=True) if d.n_imu >= 200):
        untestable.append("axis_sign: the accelerometer is accelerated in motion (|a| − g RMS > "
                          f"{LIN_ACC_RMS:g} m/s²) and no magnetometer is calibrated: no world-fixed vector to "
                          "compare the gyro's handedness with")
    elif hand is None:
        untestable.append("axis_sign: too little rotation (|ω| > 0.3 rad/s) to compare the sensors' handedness")
    cal = res.calibration
    sats: list[Saturated] = []
    exclude: list[Array | None] = [None] * len(logs)
    for sensor, key in (("gyro", "gyro"), ("accel", "acc")):
        allraw = np.concatenate([getattr(d, key) for d in logs])
        st = find_saturation(allraw, sensor)
        if st is not None:
            sats.append(st)
    if sats:
        for i, d in enumerate(logs):
            m = np.zeros(d.n_imu, bool)
            for st in sats:
                raw = d.gyro if st.sensor == "gyro" else d.acc
                m |= (np.abs(raw) >= st.limit * (1 - 1e-9)).any(axis=1)
            # a clipped rate or force spoils the kinematic rows around it (smoothing, integration)
            half = 5
            exclude[i] = np.convolve(m.astype(float), np.ones(2 * half + 1), mode="same") > 0  # type: ignore[assignment]
    # -- 2. residual channels, measured and re-simulated -------------------------------------------
    t0 = time.perf_counter()
    designs = _designs(logs, cal, res.segmentations, g, exclude)
    _share_walks(designs, logs, sampled)
    if not designs:
        raise FitError("no log long enough to diagnose (≥ 50 IMU samples)")
    cov = coverage(designs)
    untestable += list(cov.blocked.values())
    an = analyse(designs, cal, only=[c.key for c in candidates(True, True) if c.effect not in cov.blocked])
    timing["analyse"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    sim_logs = [resimulate(dz.s, dz.clean, cal, logs[dz.sid], rng) for dz in designs]
    null_designs = []
    for dz, sl in zip(designs, sim_logs, strict=True):
        ss = prepare(sl, cal, dz.s.rests)
        ss.restamped = dz.s.restamped
        nd = Design(ss, g, dz.sid)
        nd.drift_group, nd.drift_span = dz.drift_group, dz.drift_span
        null_designs.append(nd)
    null = analyse(null_designs, cal, only=[c.key for c in an.cands])
    timing["null"] = time.perf_counter() - t0
    # -- 2c. is the baseline adequate? (invariants it does not meet are named and left out) ---------------
    t0 = time.perf_counter()
    if cov.rate_hz >= MIN_RATE_HZ:
        adq = assess(an, null)
    else:
        adq = Adequacy({}, {}, None, ())
        untestable.append(f"baseline adequacy: needs ≥ {MIN_RATE_HZ:g} Hz to check the model's invariants "
                          f"against noise; this data: {cov.rate_hz:.3g} Hz, {cov.duration_s:.0f} s")
    if mag_extrap is not None:
        # an extrapolated magnetometer fit does not meet the field's invariants whatever the sensor does: those
        # rows are left out, as for an inadequate baseline, but the finding is the data's, not the model's
        for grp in [k for k, e in adq.inadequate.items() if e["sensor"] == "mag"]:
            e = adq.inadequate.pop(grp)
            untestable.append(f"the magnetometer's invariant '{e['invariant']}' ({e['ratio']:.1f}× its simulated "
                              f"RMS): {mag_extrap}; its rows are left out, not read as an effect or a baseline "
                              "failure")
        adq.extrapolated_mag = mag_extrap
    full_an, full_null = an, null
    if adq.drop:
        an, null = restrict(an, adq.drop), restrict(null, adq.drop)
    blocked_keys: set[str] = set()
    if adq.linear_acceleration is not None:
        la = adq.linear_acceleration
        blocked_keys |= set(ACCEL_KINEMATIC_EFFECTS)
        untestable.append(
            f"lever_arm, scale_nonlinearity (accel), time_offset (accel), axis_sign (accel): the accelerometer "
            f"sees specific force other than gravity in motion (|a| − g RMS {la['a_norm_rms_m_s2']:.3g} m/s² "
            f"against {la['a_norm_noise_m_s2']:.2g} from noise; {la['worst']} {la['ratio']:.0f}× its simulated "
            f"RMS) while |a| = g holds at rest: linear acceleration (thrust, a carrying hand), not a model error")
    if (why_nl := nonlin_resolution(an)[1]) is not None:
        blocked_keys.add("scale_nonlinearity:gyro")
        untestable.append(why_nl)
    if (why_mc := magcurrent.untestable_after(adq.drop, an.first)) is not None:  # diagnose/magcurrent.py
        blocked_keys |= set(magcurrent.KEYS)
        untestable.append(why_mc)
    timing["adequacy"] = time.perf_counter() - t0
    # -- 3. forward selection ------------------------------------------------------------------------
    n = an.problem.n
    model = ["nuisance"]
    chosen: list[str] = []
    cond: dict[str, Any] = {k: v for k, v in an.first.items() if k not in blocked_keys} if n else {}
    thr = {k: _threshold(_k(an, k, g_), n, null.first[k].loglik_gain, null.first[k].spread) for k, g_ in cond.items()}
    an.first_bar = dict(thr)  # type: ignore[attr-defined]
    while len(chosen) < MAX_EFFECTS:
        ok = [k for k in cond if k not in chosen and cond[k].loglik_gain > thr[k]]
        if not ok:
            break
        best = max(ok, key=lambda k: cond[k].loglik_gain)
        chosen.append(best)
        model = model + an.blocks[best]
        for k in cond:
            if k not in chosen:
                cond[k] = an.score(model, k)
                thr[k] = _threshold(_k(an, k, cond[k]), n, null.first[k].loglik_gain, null.first[k].spread)
    # -- 4. findings ------------------------------------------------------------------------------------
    for k in chosen:
        rest_model = ["nuisance"] + [b for c in chosen if c != k for b in an.blocks[c]]
        gk = an.score(rest_model, k)
        f = _finding(an, rest_model, k, gk, thr[k], null.first[k].loglik_gain, True, null.first[k].spread)
        f.gain.update(_rms_physical(an, rest_model, k))
        findings.append(f)
    others = sorted((k for k in cond if k not in chosen), key=lambda k: -cond[k].loglik_gain)
    for k in others:
        findings.append(_finding(an, model, k, cond[k], thr[k], null.first[k].loglik_gain, False,
                                 null.first[k].spread))
    _inseparable(findings, an, designs, thr)
    for st in sats:
        findings.insert(0, _saturation_finding(st, an))
    for grp, e in adq.inadequate.items():
        findings.insert(0, _inadequate_finding(grp, e))
    if flip is not None:
        _flip_gain(flip, logs, g)
        findings.insert(0, flip)
    # structural findings lead: an inverted axis or a rail is undone/censored before the baseline is fitted,
    # so every other finding is conditional on them; then the linear effects by held-out gain
    structural = ("baseline_inadequate", "axis_sign", "saturation")
    # (an axis flip and a rail lead even a failed invariant: they are undone or censored before the baseline)
    findings.sort(key=lambda f: (not f.significant, f.effect not in structural,
                                 f.effect not in ("axis_sign", "saturation"), -f.score if f.significant else 0.0))
    # -- 5. extended calibration, statistics, simulator check -------------------------------------------
    T0 = _rest_temperature(designs)
    exts: dict[str, Any] = {}
    for f in findings:
        if f.significant and f.effect != "baseline_inadequate":
            exts.setdefault(f.effect, []).append(_extension(f, T0))
    exts = {k: v[0] if len(v) == 1 or k == "mag_current" else v for k, v in exts.items()}  # one basis: the best
    gbr = gyro_bias_rests(designs, cal, exts.get("g_sensitivity"))
    ext_cal = _honest_gyro_sigma(cal.replace(extensions=exts), gbr)
    if "mag_current" in exts and calibration is None:  # a batch on these logs: its hard iron holds k·x̄
        ext_cal = magcurrent.interference_free_bias(ext_cal, logs, exts["mag_current"])
    base_beta, _ = an.problem.fit(["nuisance"])
    r_meas = an.problem.residual(["nuisance"], base_beta)
    nb, _ = null.problem.fit(["nuisance"])
    r_sim = null.problem.residual(["nuisance"], nb) * null.problem.sigma[null.problem.ch] / \
        an.problem.sigma[null.problem.ch]
    baseline = {
        "model": "paper",
        "calibration": cal.to_dict(),
        "batch_warnings": res.warnings,
        "rows": {nm: int((an.problem.ch == i).sum()) for i, nm in enumerate(SUBCHANNELS)},
        "sigma": {nm: float(an.problem.sigma[i]) for i, nm in enumerate(SUBCHANNELS)
                  if (an.problem.ch == i).any()},
        "channels_measured": channel_stats(r_meas, an.problem.ch, an.problem.t),
        "channels_simulated": channel_stats(r_sim, null.problem.ch, null.problem.t),
        "rest_measured": rest_stats(designs[0]),
        "rest_simulated": rest_stats(null_designs[0]),
        "notes": [nt for d in designs for nt in d.s.notes],
        "adequacy": adq.to_dict(),
        "coverage": cov.to_dict(),
        "gyro_bias_rests": gbr,
        # the Earth's rotation the gyro senses, fitted within |Ω| ≤ Ω_E and taken out before scoring
        "earth_rate": [{"rad_s": [float(x) for x in v], "norm": float(np.linalg.norm(v)), "bound": OMEGA_EARTH,
                        "frame": "the session's first body frame"} for v in an.earth_rate],
        "excluded": excluded,
        "bounded_sample": sampled,
    }
    if sampled is not None:
        baseline["notes"].insert(0, sample_note(sampled))
        for f in findings:
            f.evidence += (f" (On a bounded sample of the log: {sampled['n_kept']} of {sampled['n_imu']} IMU "
                           "samples in evenly spaced windows, baseline.bounded_sample.)")
    untestable += _untestable(designs, an)
    diag = Diagnosis(baseline, findings, ext_cal, untestable, {}, timing, sources)
    diag._parts = (an, null, chosen, model, full_an, full_null)  # type: ignore[attr-defined]
    if check and chosen:
        t0 = time.perf_counter()
        diag.simulation_check = _simulation_check(an, chosen, r_meas, r_sim, null.problem.ch)
        timing["check"] = time.perf_counter() - t0
    if ukf:
        t0 = time.perf_counter()
        _ukf_stage(diag, logs, cal, exts, g)
        timing["ukf"] = time.perf_counter() - t0
    timing["total"] = time.perf_counter() - t_start
    return diag


def _ukf_stage(diag: Diagnosis, logs: list[ImuData], cal: Calibration, exts: dict[str, Any],
               g: float = G0) -> None:
    """Stage 6: NIS of the UKF from the baseline, and with the extensions; the figures of the sensor a finding
    acts on (accel, mag; pooled over both for the gyro and "all") go into its gain."""
    from .online import NOT_CORRECTED, run_ukf

    before = run_ukf(logs, cal, g=g)
    diag.baseline["ukf"] = before
    if "error" in before or not any(k not in NOT_CORRECTED for k in exts):
        return
    after = run_ukf(logs, cal.replace(mag=diag.calibration.mag) if "mag_current" in exts else cal, exts, g=g)
    diag.ukf_extended = after
    if "error" in after:
        return

    def pick(r: dict[str, Any], sensor: str) -> tuple[float, float]:
        s = r["sensors"].get(sensor)
        return (s["nis_mean"], s["outside_band"]) if s else (r["nis_mean"], r["outside_band"])

    for f in diag.significant:
        if f.effect in NOT_CORRECTED or f.effect == "baseline_inadequate":
            continue
        (nb, ob), (na, oa) = pick(before, f.sensor), pick(after, f.sensor)
        f.gain.update({"ukf_nis_before": nb, "ukf_nis_after": na, "ukf_outside_before": ob, "ukf_outside_after": oa})
    # the extensions must keep the filter consistent: where the NIS with them is worse than the baseline's
    # (beyond the window-mean's own scatter), they are not carried into the calibration the user gets
    nb, na = float(before["nis_mean"]), float(after["nis_mean"])
    if np.isfinite(nb) and np.isfinite(na) and na > nb * (1.0 + NIS_TOL):
        kept = {k: v for k, v in exts.items() if k in NOT_CORRECTED}
        diag.calibration = diag.calibration.replace(extensions=kept)
        diag.baseline["ukf_guard"] = (
            f"extensions {', '.join(k for k in exts if k not in NOT_CORRECTED)} not applied: the UKF's mean NIS "
            f"with them ({na:.3g}) exceeds the baseline's ({nb:.3g}) by more than {NIS_TOL:.0%}; the findings "
            f"stand as diagnosis, the filter cannot carry them on this data")
        for f in diag.significant:
            if f.effect not in NOT_CORRECTED and f.effect != "baseline_inadequate":
                f.parameters["applied"] = False


def _rest_temperature(designs: list[Design]) -> float | None:
    """The temperature the baseline's gyro bias belongs to: the batch fits one common slope to the cumulative
    rate over all rests (eqs. 34–35), each rest weighted by Σ(t − t̄)² (∝ length³), so its bias is that
    weighted mean over the rests' mean temperatures (an unweighted mean put T0 ~5 °C off on a warming session)."""
    num = den = 0.0
    for d in designs:
        for iv in d.s.rests:
            T = d.s.temp[iv.i0:iv.i1]
            t = d.s.t[iv.i0:iv.i1]
            ok = np.isfinite(T)
            if ok.sum() < 3:
                continue
            w = float(np.sum((t[ok] - t[ok].mean()) ** 2))
            num += w * float(T[ok].mean())
            den += w
    return num / den if den > 0 else None


def _rms_physical(an: Analysis, model: list[str], key: str) -> dict[str, float]:
    """Held-out RMS before/after on the channels the effect acts on, in the whitened unit (1 = noise)."""
    P = an.problem
    cand = next(c for c in an.cands if c.key == key)
    mask = channel_mask(P, cand.sensor)
    out = {}
    for name, mdl in (("heldout_rms_before", model), ("heldout_rms_after", model + an.blocks[key])):
        ix = P.idx(mdl)
        pri = P.prior_matrix(mdl, an.priors)
        r = np.empty(P.n)
        for f in (0, 1):
            beta, _ = P._fit(P.G[1 - f], ix, pri)
            te = P.fold == f
            r[te] = P.Z[te, -1] - P.Z[te][:, ix] @ beta
        out[name] = float(np.sqrt(np.mean(r[mask] ** 2))) if mask.any() else float("nan")
    return out


def _saturation_finding(st: Saturated, an: Analysis) -> Finding:
    """Clipping-aware model: the rows holding a clipped sample are censored instead of fitted. The gain is
    what those rows cost the baseline's likelihood beyond their expected noise."""
    n_rail = st.n_rail
    ev = (f"{n_rail} samples sit exactly at ±{st.limit:.4g} (per axis {st.per_axis}), in flat runs up to "
          f"{st.longest_run} samples long: readings clipped at the {st.sensor}'s rail.")
    gain = {"heldout_rms_before": float("nan"), "heldout_rms_after": float("nan"),
            "loglik_gain": float("nan"), "bic_delta": float("nan")}
    score = float(n_rail)
    return Finding("saturation", st.sensor, None, score, True, {"limit": st.limit, "n_clipped": n_rail}, gain, ev,
                   10.0, 0.0)


def _flip_gain(flip: Finding, logs: list[ImuData], g: float) -> None:
    """Held-out gain of the corrected sign: the baseline's residual with and without the flip undone."""
    before = flip._before  # type: ignore[attr-defined]
    try:
        from ..io.base import ImuData as _I  # noqa: F401

        d0 = _designs([_undo(d, flip) for d in logs], before.calibration, before.segmentations, g)
        d1 = _designs(logs, before.calibration, before.segmentations, g)
    except Exception:  # noqa: BLE001 - the comparison is informative only
        return
    del d1
    a0 = analyse(d0, before.calibration, only=[])
    ll0, rss0, n0 = a0.problem.heldout(["nuisance"])
    flip.gain = {"heldout_rms_before": float(np.sqrt(rss0 / n0)), "heldout_rms_after": 1.0,
                 "loglik_gain": float(0.5 * (rss0 - n0)), "bic_delta": float(-(rss0 - n0) + np.log(n0))}
    flip.score = flip.gain["loglik_gain"]


def _undo(d: ImuData, flip: Finding) -> ImuData:
    from ..extensions import correct

    return correct(d, {"axis_sign": {"sensor": flip.sensor, "axis": flip.axis}})


def _untestable(designs: list[Design], an: Analysis) -> list[str]:
    out = []
    if not any(d.s.has_temp for d in designs):
        out.append("temperature_bias: the logs have no temperature column (or it never changes)")
    if not any(d.chunks for d in designs):
        out.append("g_sensitivity, bias_drift: no rests, so the gyro bias is seen only through the kinematic rows")
    if not any(d.mhat is not None for d in designs):
        out.append("time_offset: no magnetometer, so only the accelerometer's lag against the gyro is measured "
                   "(a late accel and an early gyro look the same)")
    return out


def _inadequate_finding(group: str, e: dict[str, Any]) -> Finding:
    """The baseline does not meet an invariant: the first finding, before any effect (adequacy module)."""
    chans = ", ".join(f"{k} {v:.1f}×" for k, v in e["channels"].items())
    ev = (f"the paper-model baseline does not meet '{e['invariant']}' ({e['sensor']}): the measured residual's "
          f"RMS is {e['ratio']:.1f}× that of the same session re-simulated through the fitted model ({chans}), "
          f"even with every candidate effect fitted at once (bar {ADEQ_MAX:g}×); these rows are left out of the "
          f"effect scoring and no effect is fitted to them.")
    # excess log-likelihood of the failing rows against noise: ½·n·(ratio² − 1), as a scale of "how far"
    score = 0.5 * e["rows"] * (e["ratio"] ** 2 - 1.0)
    return Finding("baseline_inadequate", e["sensor"], None, float(score), True,
                   {"invariant": e["invariant"], "channels": e["channels"], "rms_ratio": e["ratio"]},
                   {"heldout_rms_before": e["ratio"], "heldout_rms_after": float("nan"),
                    "loglik_gain": float("nan"), "bic_delta": float("nan")}, ev, ADEQ_MAX, 1.0)


def _monotonic_temperature(designs: list[Design]) -> float:
    """Largest |Spearman ρ| between temperature and time over the sessions with a temperature column."""
    from scipy.stats import spearmanr

    best = 0.0
    for d in designs:
        if not d.s.has_temp:
            continue
        T = d.s.temp
        ok = np.isfinite(T)
        if ok.sum() < 10:
            continue
        rho = float(spearmanr(d.s.t[ok], T[ok])[0])
        if np.isfinite(rho):
            best = max(best, abs(rho))
    return best


def _inseparable(findings: list[Finding], an: Analysis, designs: list[Design], thr: dict[str, float]) -> None:
    """temperature_bias and bias_drift of one sensor that this data cannot tell apart: the significant one is
    kept but marked (``inseparable_from``), and the other named — a joint finding, not a choice.

    Two cases: the temperature is a monotonic function of time (|Spearman ρ| ≥ INSEPARABLE_RHO) and the other
    also clears its bar on its own; or, whatever the temperature does, the other clears its bar on its own
    (first step) yet adds nothing significant once this one is fitted, while not itself selected — both explain
    the same residual (a free walk follows any smooth temperature curve; clean-rate 5-min multirotor flight,
    seed 7100, gyro temperature_bias: alone 142 nats, drift alone 154, each nothing once the other is in)."""
    rho = _monotonic_temperature(designs)
    sig = {f"{f.effect}:{f.sensor}" for f in findings if f.significant}
    for f in findings:
        if not f.significant or f.effect not in ("temperature_bias", "bias_drift"):
            continue
        other = "bias_drift" if f.effect == "temperature_bias" else "temperature_bias"
        ok = f"{other}:{f.sensor}"
        g0 = an.first.get(ok)
        if g0 is None:
            continue
        if rho >= INSEPARABLE_RHO and g0.loglik_gain > thr.get(ok, np.inf):
            why = f"the temperature rises with time (|Spearman ρ| = {rho:.3f})"
        elif ok not in sig and g0.loglik_gain > _first_bar(an, ok, thr):
            why = (f"{other} alone explains the same residual and adds nothing significant once {f.effect} is "
                   f"fitted (temperature against time: |Spearman ρ| = {rho:.2f})")
        else:
            continue
        f.parameters["inseparable_from"] = other
        f.evidence = (f"cannot be told apart from {other} on this data: {why}, and {other} alone also clears "
                      f"its bar ({g0.loglik_gain:.1f} nats); read as '{f.effect} or {other}'. " + f.evidence)


def _first_bar(an: Analysis, key: str, thr: dict[str, float]) -> float:
    """The bar ``key`` had to clear in the first selection step (stored by diagnose), else its final bar."""
    return float(getattr(an, "first_bar", {}).get(key, thr.get(key, np.inf)))


def _honest_gyro_sigma(cal: Calibration, gbr: dict[str, Any]) -> Calibration:
    """The gyro bias σ widened to cover the rest-to-rest spread (after the g_sensitivity extension where one
    was found): until an extension explains the spread, the bias is known no better than it."""
    if not gbr or cal.gyro is None:
        return cal
    key = "spread_after_extension" if "spread_after_extension" in gbr else "spread"
    spread, noise = np.asarray(gbr[key]), np.asarray(gbr["noise"])
    sig = np.asarray(gbr["batch_sigma_bias"], float)
    k = int(gbr["rests"])
    # rests that agree within noise: the bias is their mean, known to spread/√k; rests that disagree beyond
    # twice the noise (nothing explains it): the bias at an arbitrary moment is known only to the spread itself
    new = np.where(spread > 2.0 * noise, np.maximum(sig, spread), np.maximum(sig, spread / np.sqrt(k)))
    gbr["sigma_bias_reported"] = new.tolist()
    if np.array_equal(new, sig):
        return cal
    return cal.replace(gyro=cal.gyro.with_sigma({**cal.gyro.sigma, "bias": new}))


def gyro_bias_rests(designs: list[Design], cal: Calibration, gsens: Any = None) -> dict[str, Any]:
    """Rest-to-rest spread of the calibrated gyro's rest means against what noise allows, and the gyro bias
    σ that covers it (issue: a batch σ of 3e-5 rad/s beside a rest-to-rest spread ten times larger).

    Per rest of ≥ 1 s: the mean calibrated rate (rad/s) and its noise σ (within-rest sd/√n). ``spread`` is the
    sd of the rest means per axis; ``noise`` the RMS of their noise σ; while the spread exceeds noise the bias
    is not one constant, and ``sigma_bias`` = max(batch σ, spread) is the honest 1σ of the bias at an
    arbitrary moment. With a g_sensitivity extension (``gsens``, the calibration JSON entry) the rest means
    are corrected by it first (``spread_after_extension``, ``sigma_bias_after_extension``)."""
    means, accs, noise = [], [], []
    for d in designs:
        for iv in d.s.rests:
            if iv.n < max(5, d.s.rate):
                continue
            w = d.s.w[iv.i0:iv.i1]
            means.append(w.mean(axis=0))
            accs.append(d.s.a[iv.i0:iv.i1].mean(axis=0))
            noise.append(w.std(axis=0, ddof=1) / np.sqrt(w.shape[0]))
    if len(means) < 3 or cal.gyro is None:
        return {}
    W, A, E = np.array(means), np.array(accs), np.array(noise)
    batch = np.asarray(cal.gyro.sigma.get("bias", np.zeros(3)), float).reshape(-1)[:3]
    if batch.size < 3:
        batch = np.zeros(3)
    spread = W.std(axis=0, ddof=1)
    nz = np.sqrt(np.mean(E**2, axis=0))
    out: dict[str, Any] = {"rests": len(means), "spread": spread.tolist(), "noise": nz.tolist(),
                           "spread_over_noise": (spread / np.maximum(nz, 1e-300)).tolist(),
                           "batch_sigma_bias": batch.tolist(), "sigma_bias": np.maximum(batch, spread).tolist()}
    if gsens is not None:
        from ..extensions import gsens_matrix

        G = sum((gsens_matrix(e) for e in (gsens if isinstance(gsens, list) else [gsens])), np.zeros((3, 3)))
        Wc = W - A @ (cal.gyro.matrix @ G).T  # δω_cal = M·G·f: the extension's share of each rest mean
        sp2 = Wc.std(axis=0, ddof=1)
        out["spread_after_extension"] = sp2.tolist()
        out["sigma_bias_after_extension"] = np.maximum(batch, sp2).tolist()
    return out


def _simulation_check(an: Analysis, chosen: list[str], r_meas: Array, r_sim: Array,
                      sim_ch: Array) -> dict[str, Any]:
    """The simulator with the fitted effects added (their residual rows from the fitted columns, on the same
    motion) against the per-channel RMS of the baseline residual: measured vs simulated without and with the
    extension (whitened units)."""
    P = an.problem
    model = ["nuisance"] + [b for k in chosen for b in an.blocks[k]]
    beta, _ = P.fit(model, an.priors)
    # the fitted effects' share of the measured residual rows, per channel
    ix_eff = np.concatenate([np.arange(P.blocks[b].start, P.blocks[b].stop) for k in chosen for b in an.blocks[k]])
    nx = P.idx(["nuisance"]).size
    effect_rows = P.Z[:, ix_eff] @ beta[nx:]
    out: dict[str, Any] = {"effects": chosen, "channels": {}}
    for i, nm in enumerate(SUBCHANNELS):
        m = P.ch == i
        ms = sim_ch == i
        if m.sum() < 12 or ms.sum() < 12:
            continue
        rm = float(np.sqrt(np.mean(r_meas[m] ** 2)))
        rs = float(np.sqrt(np.mean(r_sim[ms] ** 2)))
        # the extended simulator: the re-simulated noise plus the fitted effect's rows (linear model, same
        # motion); noise and effect are independent, so their mean squares add
        rext = float(np.sqrt(rs**2 + np.mean(effect_rows[m] ** 2)))
        out["channels"][nm] = {"measured_rms": rm, "simulated_rms": rs, "simulated_extended_rms": rext}
    worst = max(out["channels"].items(), key=lambda kv: kv[1]["measured_rms"] / max(kv[1]["simulated_rms"], 1e-12),
                default=None)
    if worst is not None:
        out["worst_channel"] = worst[0]
    return out
