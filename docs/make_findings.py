"""Run ``diagnose`` on every measured session in ../shared/data and write docs/findings.md.

    PYTHONPATH=. python docs/make_findings.py

Sessions: each MARG file on its own, with the unit's campaign calibration as the baseline (a single hand-held
file is too short or too still to calibrate by itself); the MARG campaign as a whole (all 15 files, its own
batch); the Ferraris session (its own batch). The detector is the same as for simulated sessions — nothing
here is tuned to these files.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from onlinecal.batch import run_batch  # noqa: E402
from onlinecal.batch.ellipsoid import FitError  # noqa: E402
from onlinecal.diagnose import diagnose  # noqa: E402
from onlinecal.diagnose.result import Diagnosis  # noqa: E402
from onlinecal.io import read_log  # noqa: E402

UKF_WINDOW = 100  # UKFConfig.nis_window, the updates one NIS window averages
CAVEATS = (
    "Caveats. The gyro's Earth-rate vector is fitted per session within its known norm before effects are "
    "scored; at the bound it has taken Ω_E of something else too (at rests the vertical Earth rate and an "
    "isotropic g-sensitivity are one column, docs/contract-changes.md). "
    "The re-simulation is the fitted paper model driven by the attitude the baseline reconstructs: it "
    "rotates the sensor about a fixed point, so any linear acceleration in the data is absent from it. The MARG "
    "files are hand-held — the hand translates as well as turns — so a lever_arm finding on them most likely "
    "stands for that linear acceleration, not for an accelerometer offset from a centre of rotation, and "
    "accelerometer channel ratios there overstate what the sensor itself gets wrong. The MARG time stamps are "
    "the read times of each burst (gyro, accel and mag read in turn, stamped once), not sampling instants, so a "
    "time_offset there may be the logger's, not the sensor's. Ferraris has neither magnetometer nor temperature, "
    "so time_offset is only relative (accel against gyro) and temperature_bias is untestable. Effects counted "
    "on single MARG files share one campaign calibration, so they are not independent of each other. The "
    "adequacy check compares each invariant with the re-simulation, whose rests are perfectly still: on the "
    "hand-held MARG files a 'rest' is held by hand, so the gyro's rest channel and the field's dip and norm "
    "(campaign calibration applied to each file) exceed it by 10-140x and the verdict is baseline_inadequate. "
    "That statement is true of the data (the invariants do not hold to noise level there), but it does not "
    "tell hand tremor from a wrong calibration; a 'rests not still' classification is not implemented.")

DATA = ROOT.parent / "shared" / "data"
OUT = ROOT / "docs" / "findings.md"
SKIP_PARAMS = ("per_axis_sigma", "sigma", "per_axis_lr", "rate_map_angles_deg")


def fmt(v: object) -> str:
    if isinstance(v, float):
        return f"{v:.3g}"
    if isinstance(v, list):
        return "[" + ", ".join(fmt(x) for x in v) + "]"
    if isinstance(v, dict):
        return ", ".join(f"{k}={fmt(x)}" for k, x in v.items())
    return str(v)


def section(title: str, diag: Diagnosis | None, error: str | None = None) -> list[str]:
    L = [f"### {title}", ""]
    if diag is None:
        return L + [f"Could not be diagnosed: {error}", ""]
    L.append(f"**Verdict: {diag.verdict}** · {diag.timing.get('total', 0):.1f} s")
    L.append("")
    sig = diag.significant
    if sig:
        L += ["| effect | sensor | axis | score (nats) | bar | parameters | held-out RMS before → after | BIC Δ |",
              "|---|---|---|---|---|---|---|---|"]
        for f in sig:
            p = {k: v for k, v in f.parameters.items() if k not in SKIP_PARAMS}
            L.append(f"| {f.effect} | {f.sensor} | {f.axis or 'all'} | {f.score:.1f} | {f.threshold:.1f} | {fmt(p)} | "
                     f"{fmt(f.gain.get('heldout_rms_before'))} → {fmt(f.gain.get('heldout_rms_after'))} | "
                     f"{fmt(f.gain.get('bic_delta'))} |")
        L.append("")
        for f in sig:
            L.append(f"- {f.effect}: {f.evidence}")
        L.append("")
    cm = diag.baseline.get("channels_measured", {})
    cs = diag.baseline.get("channels_simulated", {})
    ratios = {n: cm[n]["rms"] / cs[n]["rms"] for n in cm if n in cs and cs[n]["rms"] > 0}
    if ratios:
        worst = sorted(ratios.items(), key=lambda kv: -kv[1])[:3]
        L.append("Baseline residual, measured / re-simulated RMS (worst channels): "
                 + ", ".join(f"{n} ×{r:.2g}" for n, r in worst) + ".")
    chk = diag.simulation_check.get("channels", {})
    if chk and diag.simulation_check.get("worst_channel") in chk:
        w = diag.simulation_check["worst_channel"]
        c = chk[w]
        L.append(f"Simulator check on {w}: measured {c['measured_rms']:.3g}, paper-model simulation "
                 f"{c['simulated_rms']:.3g}, extended simulation {c['simulated_extended_rms']:.3g} (units of σ).")
    er = diag.baseline.get("earth_rate") or []
    if er:
        L.append("Earth's rotation taken out of the gyro (fitted, |Ω| ≤ Ω_E = 7.29e-5 rad/s): "
                 + ", ".join(f"{e['norm']:.3g} rad/s" + (" (at the bound)" if e["norm"] >= 0.999 * e["bound"] else "")
                             for e in er) + ".")
    if diag.baseline.get("ukf"):
        L.append(f"UKF NIS (window mean per update, expected 3): paper model {_ukf_txt(diag.baseline['ukf'])}"
                 + (f", extended {_ukf_txt(diag.ukf_extended)}" if diag.ukf_extended else "") + ".")
    adq = diag.baseline.get("adequacy") or {}
    if adq.get("inadequate"):
        L.append("Baseline not adequate: " + "; ".join(
            f"{e['sensor']} '{e['invariant']}' {e['ratio']:.3g}× its simulated RMS" for e in adq["inadequate"].values())
            + " (left out of the effect scoring).")
    if diag.baseline.get("ukf_guard"):
        L.append(diag.baseline["ukf_guard"] + ".")
    if diag.untestable:
        L += ["", "Not testable here: " + "; ".join(diag.untestable) + "."]
    notes = diag.baseline.get("notes", [])
    if notes:
        L += ["", "Notes: " + " ".join(notes[:2])]
    return L + [""]


def _ukf_txt(r: dict | None) -> str:
    if not r or "error" in r or r.get("nis_mean") is None:
        return "—"
    return f"{r['nis_mean']:.3g} ({100 * r['outside_band']:.0f} % of windows outside)"


def wrong_summary(runs: dict[str, list[Diagnosis]]) -> list[str]:
    """"What the simulation got wrong", computed from the diagnoses: per data set the significant effects (count
    of sessions), the channels whose measured baseline residual exceeds the re-simulated one most (median
    ratio over sessions), the extended model's held-out RMS gain, and the UKF's NIS before/after."""
    L = ["## What the simulation got wrong", "",
         "Computed from the diagnoses below (no number here is typed by hand). Channel ratios: measured / "
         "re-simulated baseline residual RMS, median over the data set's sessions. Held-out RMS: of each "
         "significant finding on its channels, whitened (1 = noise), median over findings. UKF NIS: window-mean "
         "NIS per update (expected 3), pooled over accel and mag, from the batch start and with the extension.", ""]
    for name, diags in runs.items():
        if not diags:
            continue
        counts: dict[str, int] = {}
        for d in diags:
            for e in {f.effect for f in d.significant}:
                counts[e] = counts.get(e, 0) + 1
        ratios: dict[str, list[float]] = {}
        for d in diags:
            cm, cs = d.baseline.get("channels_measured", {}), d.baseline.get("channels_simulated", {})
            for n in cm:
                if n in cs and cs[n]["rms"] > 0:
                    ratios.setdefault(n, []).append(cm[n]["rms"] / cs[n]["rms"])
        med = sorted(((n, float(np.median(v))) for n, v in ratios.items()), key=lambda kv: -kv[1])[:4]
        gains = [(f.gain["heldout_rms_before"], f.gain["heldout_rms_after"]) for d in diags for f in d.significant
                 if np.isfinite(f.gain.get("heldout_rms_before", np.nan))
                 and np.isfinite(f.gain.get("heldout_rms_after", np.nan))]
        eff = ", ".join(f"{e} ({c} of {len(diags)})" for e, c in sorted(counts.items(), key=lambda kv: -kv[1]))
        L.append(f"- **{name}** ({len(diags)} diagnoses): significant effects {eff or 'none'}.")
        if med:
            L.append("  Channels the paper-model simulation under-predicts most: "
                     + ", ".join(f"{n} ×{r:.3g}" for n, r in med) + ".")
        if gains:
            b, a = np.median([g[0] for g in gains]), np.median([g[1] for g in gains])
            L.append(f"  Extended model, held-out RMS on the affected channels: {b:.3g} → {a:.3g} "
                     f"(median of {len(gains)} findings, {100 * (1 - a / b):.0f} % lower).")
        def fin(r: dict | None) -> bool:
            return bool(r) and "error" not in r and r.get("nis_mean") is not None and np.isfinite(r["nis_mean"])

        pairs = [(d.baseline["ukf"], d.ukf_extended) for d in diags
                 if fin(d.baseline.get("ukf")) and fin(d.ukf_extended)]
        short = sum(1 for d in diags if d.baseline.get("ukf") and not fin(d.baseline.get("ukf")))
        if pairs:
            closer = sum(abs(a_["nis_mean"] - 3) < abs(b_["nis_mean"] - 3) for b_, a_ in pairs)
            L.append("  UKF NIS, paper model → extended (sessions with an extension that changes the data): "
                     + "; ".join(f"{_ukf_txt(b_)} → {_ukf_txt(a_)}" for b_, a_ in pairs[:4])
                     + (f" (first 4 of {len(pairs)})" if len(pairs) > 4 else "")
                     + f"; closer to 3 in {closer} of {len(pairs)}.")
        base_only = [d.baseline["ukf"] for d in diags if not d.ukf_extended and fin(d.baseline.get("ukf"))]
        if base_only:
            L.append(f"  Sessions without a data-changing extension: UKF NIS of the paper model, median "
                     f"{np.median([r['nis_mean'] for r in base_only]):.3g} over {len(base_only)}.")
        if short:
            L.append(f"  {short} session(s) too short for one NIS window ({UKF_WINDOW} updates).")
    return L + ["", CAVEATS, ""]


def main() -> int:
    if not DATA.is_dir():
        print(f"no measured data at {DATA}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    out = ["# Findings on measured data (`onlinecal diagnose`)", "",
           "Generated by `PYTHONPATH=. python docs/make_findings.py` — do not edit by hand. Scores are held-out "
           "log-likelihood gains (nats) of the extended model over the paper's; the bar is max(BIC penalty, the "
           "same score on the session re-simulated through the fitted paper model + 15, 3× that score's spread "
           "over the re-simulation's 10-s blocks). RMS is in units of the baseline's robust residual σ per "
           "channel. Before any effect, the baseline's invariants are checked against the re-simulation "
           "(docs/effects.md, 'What diagnose reports besides effects').", ""]
    summary: list[tuple[str, str, list[str]]] = []
    runs: dict[str, list[Diagnosis]] = {"MARG set 1": [], "Ferraris": [], "imu_tk Xsens": []}
    marg = sorted((DATA / "marg-set1").glob("*.csv"))
    logs = [read_log(p) for p in marg]
    out += ["## MARG set 1 (MPU6050 + HMC5883L, hand-held)", ""]
    try:
        camp = run_batch(logs)
        cal = camp.calibration
    except FitError as e:
        cal = None
        out.append(f"The campaign batch failed ({e}); per-file sessions use their own batch.")
    try:
        dg = diagnose(logs, seed=0)
        out += section("whole campaign (15 files, own batch)", dg)
        runs["MARG set 1"].append(dg)
        summary.append(("MARG campaign", dg.verdict, [f.effect for f in dg.significant[1:]]))
    except FitError as e:
        out += section("whole campaign (15 files, own batch)", None, str(e))
    for p, d in zip(marg, logs, strict=True):
        try:
            dg = diagnose([d], seed=0, calibration=cal)
            out += section(f"{p.name} (campaign calibration)", dg)
            runs["MARG set 1"].append(dg)
            summary.append((p.name, dg.verdict, [f.effect for f in dg.significant[1:]]))
        except FitError as e:
            out += section(p.name, None, str(e))
            summary.append((p.name, "not diagnosable", []))
    out += ["## Ferraris session (imucal example, accel + gyro, no mag, no temperature)", ""]
    fer = DATA / "ferraris" / "imucal-example-session.csv"
    try:
        dg = diagnose([read_log(fer)], seed=0)
        out += section(fer.name, dg)
        runs["Ferraris"].append(dg)
        summary.append((fer.name, dg.verdict, [f.effect for f in dg.significant[1:]]))
    except FitError as e:
        out += section(fer.name, None, str(e))
        summary.append((fer.name, "not diagnosable", []))
    out += ["## imu_tk Xsens session (MTi raw counts, accel + gyro, 38 static poses reached by hand)", ""]
    xs = DATA / "imutk-xsens" / "xsens-session.csv"
    try:
        dg = diagnose([read_log(xs)], g=9.81744, seed=0)
        out += section(xs.name, dg)
        top = dg.significant[0] if dg.significant else None
        if top is not None and "matrix_mrad_s_per_g" in top.parameters:
            G = np.asarray(top.parameters["matrix_mrad_s_per_g"])
            out += ["g-sensitivity G (mrad/s per g; row = gyro axis, column = force axis):", "", "```"]
            out += ["  ".join(f"{v:+6.2f}" for v in row) for row in G] + ["```", ""]
        gb = dg.baseline.get("gyro_bias_rests") or {}
        if gb:
            out += [f"Gyro rest means: spread {fmt(gb['spread'])} rad/s ({fmt(gb['spread_over_noise'])}× noise); "
                    f"batch bias σ {fmt(gb['batch_sigma_bias'])}; after the extension the spread is "
                    f"{fmt(gb.get('spread_after_extension'))}, reported σ {fmt(gb.get('sigma_bias_reported'))}.", ""]
        runs["imu_tk Xsens"].append(dg)
        summary.append((xs.name, dg.verdict, [f.effect for f in dg.significant[1:]]))
    except FitError as e:
        out += section(xs.name, None, str(e))
        summary.append((xs.name, "not diagnosable", []))
    head = ["## Summary", "", "| session | verdict | other significant findings |", "|---|---|---|"]
    head += [f"| {n} | {v} | {', '.join(o) or '—'} |" for n, v, o in summary]
    out = out[:4] + wrong_summary(runs) + head + [""] + out[4:]
    out.append(f"_Total run time {time.perf_counter() - t0:.0f} s._")
    OUT.write_text("\n".join(out) + "\n")
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
