"""``diagnose --report DIR``: a readable markdown report with plots (matplotlib, Agg backend).

Plots: per-channel residual RMS of the baseline, measured against re-simulated (and, where an extension
was fitted, the extended simulator); the Allan deviation of the gyro at rest, measured against simulated;
the held-out RMS before/after each significant finding.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .result import Diagnosis


def _plots(diag: Diagnosis, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    cm = diag.baseline.get("channels_measured", {})
    cs = diag.baseline.get("channels_simulated", {})
    names = [n for n in cm if n in cs]
    if names:
        fig, ax = plt.subplots(figsize=(9, 3.5))
        x = np.arange(len(names))
        ax.bar(x - 0.27, [cm[n]["rms"] for n in names], 0.27, label="measured")
        ax.bar(x, [cs[n]["rms"] for n in names], 0.27, label="simulated (paper model)")
        chk = diag.simulation_check.get("channels", {})
        if chk:
            ax.bar(x + 0.27, [chk.get(n, {}).get("simulated_extended_rms", np.nan) for n in names], 0.27,
                   label="simulated (extended)")
        ax.set_xticks(x, names, rotation=30)
        ax.set_yscale("log")
        ax.set_ylabel("residual RMS / baseline σ")
        ax.legend(fontsize=8)
        ax.set_title("baseline residual per channel: measured vs simulated")
        fig.tight_layout()
        fig.savefig(out / "channels.png", dpi=110)
        plt.close(fig)
        files.append("channels.png")
    rm, rs = diag.baseline.get("rest_measured", {}), diag.baseline.get("rest_simulated", {})
    if rm.get("allan_tau_s") and rs.get("allan_tau_s"):
        fig, ax = plt.subplots(figsize=(6, 4))
        for lab, r, ls in (("measured", rm, "-"), ("simulated", rs, "--")):
            d = np.asarray(r["allan_dev"])
            for k in range(3):
                ax.loglog(r["allan_tau_s"], d[:, k], ls, color=f"C{k}", label=f"{lab} {'xyz'[k]}")
        ax.set_xlabel("τ [s]")
        ax.set_ylabel("Allan deviation [rad/s]")
        ax.set_title("gyro at rest")
        ax.legend(fontsize=7, ncol=2)
        fig.tight_layout()
        fig.savefig(out / "allan.png", dpi=110)
        plt.close(fig)
        files.append("allan.png")
    sig = [f for f in diag.findings if f.significant and np.isfinite(f.gain.get("heldout_rms_after", np.nan))]
    if sig:
        fig, ax = plt.subplots(figsize=(6, 3))
        x = np.arange(len(sig))
        ax.bar(x - 0.2, [f.gain["heldout_rms_before"] for f in sig], 0.4, label="before")
        ax.bar(x + 0.2, [f.gain["heldout_rms_after"] for f in sig], 0.4, label="after")
        ax.set_xticks(x, [f"{f.effect}\n{f.sensor}" for f in sig], fontsize=8)
        ax.set_ylabel("held-out RMS / σ")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / "gain.png", dpi=110)
        plt.close(fig)
        files.append("gain.png")
    return files


def _fmt(v: object) -> str:
    if isinstance(v, float):
        return f"{v:.4g}" if np.isfinite(v) else "n/a"  # not measured for this finding (never a bare nan)
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_fmt(x)}" for k, x in v.items()) + "}"
    return str(v)


def _ukf_lines(diag: Diagnosis) -> list[str]:
    """The UKF stage: window-mean NIS per sensor (per update, 3 dof: expected 3) and the share of windows
    outside its chi-square band, from the baseline and with the extension."""
    runs = [("paper model (batch start)", diag.baseline.get("ukf") or {}), ("extended", diag.ukf_extended or {})]
    runs = [(n, r) for n, r in runs if r]
    if not runs:
        return []
    L = ["", "## UKF innovation consistency (window-mean NIS per update; expected 3)", ""]
    for n, r in runs:
        if "error" in r:
            L.append(f"- {n}: the UKF could not run ({r['error']})")
    ok = [(n, r) for n, r in runs if "error" not in r]
    if ok:
        band = ok[0][1]["band"]
        L += [f"Band of a window mean: [{band[0]:.3g}, {band[1]:.3g}].", "",
              "| run | sensor | NIS mean | windows outside band | gate rejections |", "|---|---|---|---|---|"]
        for n, r in ok:
            for s, v in r["sensors"].items():
                L.append(f"| {n} | {s} | {v['nis_mean']:.3g} | {100 * v['outside_band']:.0f} % | {v['rejected']} |")
        ext = [r for n, r in ok if n == "extended"]
        if ext and ext[0].get("extra_states"):
            L += ["", f"Extended run: UKF extra states {', '.join(ext[0]['extra_states'])} "
                  f"(online estimate {_fmt(ext[0].get('online_extensions', {}))}); data corrected for "
                  f"{', '.join(ext[0].get('corrected', [])) or 'nothing else'}."]
        elif ext:
            L += ["", f"Extended run: data corrected for {', '.join(ext[0].get('corrected', []))}."]
    return L


def write_report(diag: Diagnosis, out: Path) -> Path:
    """Write ``out/report.md`` and its plots; returns the markdown's path."""
    out.mkdir(parents=True, exist_ok=True)
    files = _plots(diag, out)
    L = [f"# Diagnosis: {', '.join(diag.sources)}", "", f"**Verdict: {diag.verdict}**", ""]
    L += ["## Findings (held-out log-likelihood gain, nats; bar = max(BIC penalty, re-simulation + margin))", "",
          "| effect | sensor | axis | score | bar | significant | parameters "
          "| held-out residual RMS before → after (1 = noise) |",
          "|---|---|---|---|---|---|---|---|"]
    for f in diag.findings:
        p = {k: v for k, v in f.parameters.items() if k not in ("per_axis_sigma", "sigma", "per_axis_lr")}
        L.append(f"| {f.effect} | {f.sensor} | {f.axis or 'all'} | {f.score:.1f} | {f.threshold:.1f} | "
                 f"{'yes' if f.significant else 'no'} | {_fmt(p)} | "
                 f"{_fmt(f.gain.get('heldout_rms_before'))} → {_fmt(f.gain.get('heldout_rms_after'))} |")
    L += [""]
    for f in diag.significant:
        L += [f"- **{f.effect}** ({f.sensor}): {f.evidence}"]
    if diag.untestable:
        L += ["", "## Not testable on these logs", ""] + [f"- {u}" for u in diag.untestable]
    L += _ukf_lines(diag)
    cm = diag.baseline.get("channels_measured", {})
    cs = diag.baseline.get("channels_simulated", {})
    L += ["", "## Baseline residual, measured vs re-simulated through the fitted paper model", "",
          "| channel | rows | RMS measured | RMS simulated | lag-1 ρ measured | lag-1 ρ simulated | Q10 measured |",
          "|---|---|---|---|---|---|---|"]
    for n, v in cm.items():
        w = cs.get(n, {})
        L.append(f"| {n} | {v['n']} | {v['rms']:.3g} | {w.get('rms', float('nan')):.3g} | {v['rho1']:.3f} | "
                 f"{w.get('rho1', float('nan')):.3f} | {v['ljung_box_q10']:.1f} |")
    chk = diag.simulation_check.get("channels", {})
    if chk:
        L += ["", "## The simulator with the extension", "",
              "| channel | measured | simulated (paper) | simulated (extended) |", "|---|---|---|---|"]
        for n, v in chk.items():
            L.append(f"| {n} | {v['measured_rms']:.3g} | {v['simulated_rms']:.3g} | "
                     f"{v['simulated_extended_rms']:.3g} |")
    L += [""] + [f"![{f}]({f})" for f in files] + [""]
    notes = diag.baseline.get("notes", []) + diag.baseline.get("batch_warnings", [])
    if notes:
        L += ["## Notes", ""] + [f"- {n}" for n in notes] + [""]
    path = out / "report.md"
    path.write_text("\n".join(L))
    return path
