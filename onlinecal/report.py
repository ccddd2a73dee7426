"""Tables and comparisons of calibrations: truth · batch · online ± 3σ, and A-vs-B differences."""

from __future__ import annotations

from typing import Any

import numpy as np

from .model import PARAMS, SENSORS, Calibration, SensorCalibration

UNIT = {
    ("gyro", "bias"): "rad/s", ("accel", "bias"): "m/s^2", ("mag", "bias"): "raw",
    "scale": "", "alpha": "rad", "xi": "rad",
}


def _unit(sensor: str, param: str) -> str:
    return UNIT.get((sensor, param), UNIT.get(param, ""))


def param_rows(cals: dict[str, Calibration | None]) -> list[dict[str, Any]]:
    """One row per sensor · parameter · axis with each calibration's value (and σ where known)."""
    rows = []
    for s in SENSORS:
        sc = {k: (c.sensor(s) if c is not None else None) for k, c in cals.items()}
        if all(v is None for v in sc.values()):
            continue
        for p in PARAMS:
            for ax in range(3):
                row: dict[str, Any] = {"sensor": s, "param": p, "axis": "xyz"[ax], "unit": _unit(s, p)}
                for k, c in sc.items():
                    if c is None:
                        row[k] = None
                        continue
                    row[k] = float(c.params()[p][ax])
                    sig = c.sigma.get(p)
                    row[k + "_sigma"] = float(np.asarray(sig)[ax]) if sig is not None else None
                rows.append(row)
    return rows


def _fmt(x: float | None, digits: int = 6) -> str:
    return "—" if x is None else f"{x:+.{digits}f}"


def truth_table(truth: Calibration | None, batch: Calibration | None, online: Calibration | None) -> str:
    """Text table: parameter · truth · batch · online ± 3σ (the demo's and the corpus' table)."""
    rows = param_rows({"truth": truth, "batch": batch, "online": online})
    head = f"{'parameter':<16}{'truth':>12}{'batch':>12}{'online':>12}{'± 3σ':>11}  flag"
    lines = [head, "-" * len(head)]
    for r in rows:
        on = r.get("online")
        sig = r.get("online_sigma")
        flag = ""
        if on is not None and sig and r.get("batch") is not None:
            if abs(on - r["batch"]) > 3 * np.hypot(sig, r.get("batch_sigma") or 0.0):
                flag = "online≠batch"
        name = f"{r['sensor']}.{r['param']}.{r['axis']}"
        lines.append(
            f"{name:<16}{_fmt(r.get('truth')):>12}{_fmt(r.get('batch')):>12}{_fmt(on):>12}"
            f"{(f'{3 * sig:.1e}' if sig else '—'):>11}  {flag}"
        )
    return "\n".join(lines)


def compare(a: Calibration, b: Calibration) -> list[dict[str, Any]]:
    """Parameter-by-parameter difference b − a, and in σ where either side knows its σ."""
    out = []
    for r in param_rows({"a": a, "b": b}):
        if r.get("a") is None or r.get("b") is None:
            continue
        d = r["b"] - r["a"]
        sig = np.hypot(r.get("a_sigma") or 0.0, r.get("b_sigma") or 0.0)
        out.append({**{k: r[k] for k in ("sensor", "param", "axis", "unit", "a", "b")},
                    "diff": d, "sigma": float(sig) if sig > 0 else None,
                    "n_sigma": float(abs(d) / sig) if sig > 0 else None})
    for s in SENSORS:
        ca, cb = a.sensor(s), b.sensor(s)
        if isinstance(ca, SensorCalibration) and isinstance(cb, SensorCalibration):
            out.append({"sensor": s, "param": "matrix", "axis": None, "unit": "",
                        "a": None, "b": None, "diff": cb.matrix_rel_error(ca), "sigma": None,
                        "n_sigma": None})
    return out


def compare_text(a: Calibration, b: Calibration) -> str:
    lines = [f"{'parameter':<16}{'A':>13}{'B':>13}{'B − A':>13}{'σ':>10}{'|Δ|/σ':>8}  unit"]
    for r in compare(a, b):
        if r["param"] == "matrix":
            lines.append(f"{r['sensor'] + '.matrix':<16}{'':>13}{'':>13}{r['diff']:>13.2e}{'':>10}{'':>8}"
                         "  relative (Frobenius)")
            continue
        name = f"{r['sensor']}.{r['param']}.{r['axis']}"
        sig = f"{r['sigma']:.1e}" if r["sigma"] else "—"
        ns = f"{r['n_sigma']:.1f}" if r["n_sigma"] is not None else "—"
        lines.append(f"{name:<16}{r['a']:>+13.6f}{r['b']:>+13.6f}{r['diff']:>+13.2e}{sig:>10}{ns:>8}  {r['unit']}")
    return "\n".join(lines)


def errors_against(truth: Calibration, est: Calibration) -> dict[str, dict[str, list[float]]]:
    """|estimate − truth| per sensor and parameter (3 values each) and the matrix relative error."""
    out: dict[str, dict[str, list[float]]] = {}
    for s in SENSORS:
        t, e = truth.sensor(s), est.sensor(s)
        if t is None or e is None:
            continue
        d = {p: np.abs(e.params()[p] - t.params()[p]).tolist() for p in PARAMS}
        d["matrix_rel"] = [e.matrix_rel_error(t)]
        out[s] = d
    return out


# -- --report DIR: figures and report.md ------------------------------------------------------------

def mag_norm_stats(mag_raw: Any, cal: SensorCalibration | None) -> dict[str, float]:
    """Field-norm figures over M magnetometer samples (M, 3): the raw norm's relative spread
    std(‖m‖)/mean(‖m‖) and, calibrated (``matrix @ (raw − bias)``, eq. 17's unit sphere), mean, std and
    the largest |‖m_cal‖ − 1|."""
    m = np.asarray(mag_raw, float).reshape(-1, 3)
    raw = np.linalg.norm(m, axis=1)
    out = {"n": float(m.shape[0]), "raw_rel_std": float(raw.std() / raw.mean())}
    if cal is not None:
        c = np.linalg.norm(cal.apply(m), axis=1)
        out.update(mean=float(c.mean()), std=float(c.std()), max_dev=float(np.abs(c - 1.0).max()))
    return out


def accel_static_stats(acc_means: Any, cal: SensorCalibration | None, g: float) -> dict[str, float]:
    """Residual of eq. 32 on K statics: ‖ā_k‖ − g raw, or ‖matrix @ (ā_k − bias)‖ − g calibrated
    (ā_k (K, 3) mean raw specific force, m/s²): mean, RMS and largest absolute value, m/s²."""
    a = np.asarray(acc_means, float).reshape(-1, 3)
    n = np.linalg.norm(a if cal is None else cal.apply(a), axis=1) - g
    if n.size == 0:
        return {"k": 0.0, "mean": float("nan"), "rms": float("nan"), "max_abs": float("nan")}
    return {"k": float(n.size), "mean": float(n.mean()), "rms": float(np.sqrt(np.mean(n**2))),
            "max_abs": float(np.abs(n).max())}


def _statics(logs: list[Any], segs: list[Any] | None) -> list[tuple[int, Any]]:
    """(log index, Interval) of every static interval: the batch's own segmentation where there is one."""
    if segs is None:
        from .batch.segment import noise_floors, segment

        floors = noise_floors(logs)
        segs = [segment(d, floors) for d in logs if d.n_imu > 0]
    idx = {id(d): i for i, d in enumerate(logs)}
    return [(idx.get(id(s.data), i), iv) for i, s in enumerate(segs) for iv in s.statics]


def _f(x: float | None, fmt: str) -> str:
    return "—" if x is None or not np.isfinite(x) else format(x, fmt)


def write_report(out_dir: str | Any, logs: list[Any], command: str, batch: Any = None, online: Any = None,
                 init: Calibration | None = None, init_label: str = "init", g: float = 9.80665,
                 progress: Any = None) -> list[str]:
    """Write the PNG figures (:mod:`onlinecal.plots`) and ``report.md`` tying them together into
    ``out_dir``; returns the file names written.

    ``batch``: a BatchResult (its calibration and segmentation), ``online``: an OnlineResult (calibration
    and trace), ``init``: the calibration the filter started from when it was not the batch. ``progress``:
    an object with ``next(name)`` (a :class:`onlinecal.progress.Stages`), advanced once per figure.
    """
    from pathlib import Path

    from . import plots

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)

    def step(name: str) -> None:
        if progress is not None:
            progress.next(name)

    bcal = batch.calibration if batch is not None else None
    ocal = online.calibration if online is not None else None
    cals = {k: c for k, c in (("batch", bcal), (init_label, init), ("online", ocal)) if c is not None}
    files: list[str] = []
    md: list[str] = [f"# onlinecal report — `{command}`", ""]
    md += ["| log | IMU samples | IMU rate [Hz] | mag samples | duration [s] |", "|---|---:|---:|---:|---:|"]
    for d in logs:
        md.append(f"| `{d.source}` | {d.n_imu} | {_f(d.imu_rate, '.1f')} | {d.n_mag} | {d.duration:.1f} |")
    md.append("")
    for k, c in cals.items():
        md.append(f"- {k}: calibration source `{c.source}`")
    md.append("")

    # magnetometer
    mlogs = [d for d in logs if d.n_mag > 0]
    if mlogs:
        mag = np.concatenate([d.mag for d in mlogs])
        mcals = {k: c.mag for k, c in cals.items() if c.mag is not None}
        step("mag sphere")
        files.append(plots.mag_sphere(out / "mag_sphere.png", mag, mcals).name)
        step("field norm")
        t, starts = plots.joined_time([d.t_mag for d in mlogs])
        files.append(plots.field_norm(out / "field_norm.png", t, mag, mcals, starts).name)
        md += ["## Magnetometer", "",
               "Points before and after calibration (calibrated = matrix @ (raw − bias) should lie on the unit "
               "sphere, paper eq. 17), in three projections:", "", "![magnetometer points](mag_sphere.png)", "",
               "Field norm over time (logs joined):", "", "![field norm](field_norm.png)", ""]
        raw = mag_norm_stats(mag, None)
        md += [f"Raw field norm: relative std {100 * raw['raw_rel_std']:.4f} % over {int(raw['n'])} samples.",
               "", "| field norm | samples | mean | std | std [%] | max \\|‖m‖ − 1\\| |",
               "|---|---:|---:|---:|---:|---:|"]
        for k, c in mcals.items():
            s = mag_norm_stats(mag, c)
            md.append(f"| {k} | {int(s['n'])} | {s['mean']:.6f} | {s['std']:.6f} | {100 * s['std']:.4f} | "
                      f"{s['max_dev']:.6f} |")
        md.append("")
    else:
        md += ["## Magnetometer", "", "No magnetometer samples in the logs.", ""]

    # accelerometer on the statics
    sts = _statics(logs, batch.segmentations if batch is not None else None)
    acals = {k: c.accel for k, c in cals.items() if c.accel is not None}
    md += ["## Accelerometer on the statics", ""]
    if sts:
        means = np.array([logs[i].acc[iv.i0:iv.i1].mean(axis=0) for i, iv in sts])
        step("accel statics")
        files.append(plots.accel_statics(out / "accel_statics.png", means, acals, g).name)
        md += [f"{len(sts)} static intervals (mean raw specific force ā_k each); residual of paper eq. 32, "
               f"‖·‖ − g with g = {g} m/s²:", "", "![accelerometer norm on the statics](accel_statics.png)", "",
               "| ‖ā‖ − g [m/s²] | statics | mean | RMS | max \\|·\\| |", "|---|---:|---:|---:|---:|"]
        for k, c in [("raw", None), *acals.items()]:
            s = accel_static_stats(means, c, g)
            md.append(f"| {k} | {int(s['k'])} | {s['mean']:+.5f} | {s['rms']:.5f} | {s['max_abs']:.5f} |")
        md += ["", "<details><summary>static intervals</summary>", "",
               "| k | log | t0 [s] | t1 [s] | samples | ‖ā‖ raw [m/s²] | "
               + " | ".join(f"‖ā‖ {k} [m/s²]" for k in acals) + " |",
               "|---:|---:|---:|---:|---:|---:|" + "---:|" * len(acals)]
        for k, ((i, iv), a) in enumerate(zip(sts, means, strict=True)):
            md.append(f"| {k} | {i} | {iv.t0:.6f} | {iv.t1:.6f} | {iv.n} | {np.linalg.norm(a):.5f} | "
                      + " | ".join(f"{np.linalg.norm(c.apply(a)):.5f}" for c in acals.values()) + " |")
        md += ["", "</details>", ""]
    else:
        md += ["No static interval found in the logs.", ""]

    # online parameters over time
    if online is not None and online.trace:
        refs = {k: c for k, c in cals.items() if k != "online"}
        md += ["## Online filter: parameters over time", "",
               "Each UKF calibration term over the replay: estimate, ±3σ band from the filter's covariance, and "
               + (", ".join(f"the {k} value (dashed)" for k in refs) or "no reference value") + ".", ""]
        for s in SENSORS:
            if ocal is None or ocal.sensor(s) is None:
                continue
            step(f"ukf {s}")
            name = plots.ukf_params(out / f"ukf_{s}.png", online.trace,
                                    s, {k: c.sensor(s) for k, c in refs.items()}).name
            files.append(name)
            md += [f"![{s} parameters]({name})", ""]
        md += [f"Replay: {online.n_imu} IMU samples, {online.log_s:.1f} s of log in {online.wall_s:.2f} s "
               f"({online.realtime_factor:.0f}× real time); {len(online.events)} filter events.", ""]
        if online.missing_motion:
            md += ["Motion still missing to excite every parameter:", ""]
            md += [f"- {m}" for m in online.missing_motion] + [""]

    # batch vs online
    ref_label = "batch" if bcal is not None else (init_label if init is not None else None)
    ref = cals.get(ref_label) if ref_label else None
    if ref is not None and ocal is not None:
        step("batch vs online")
        files.append(plots.batch_vs_online(out / "batch_vs_online.png", ref, ocal).name)
        md += [f"## {ref_label} vs online", "", "![batch vs online](batch_vs_online.png)", "",
               f"| parameter | unit | {ref_label} | σ | online | σ | (online − {ref_label}) / σ |",
               "|---|---|---:|---:|---:|---:|---:|"]
        for r in param_rows({"ref": ref, "online": ocal}):
            if r.get("ref") is None or r.get("online") is None:
                continue
            sig = float(np.hypot(r.get("ref_sigma") or 0.0, r.get("online_sigma") or 0.0))
            z = (r["online"] - r["ref"]) / sig if sig > 0 else None
            md.append(f"| {r['sensor']}.{r['param']}.{r['axis']} | {r['unit']} | {r['ref']:+.8g} | "
                      f"{_f(r.get('ref_sigma'), '.2e')} | {r['online']:+.8g} | {_f(r.get('online_sigma'), '.2e')} | "
                      f"{_f(z, '+.2f')} |")
        md.append("")
    elif ocal is None:
        md += ["## Online filter", "", "Not run by this command (`onlinecal replay LOG --report DIR` adds the "
               "parameters over time and the batch-vs-online comparison).", ""]

    warns = list(dict.fromkeys((batch.warnings if batch is not None else [])
                               + (list(getattr(online, "warnings", [])) if online is not None else [])))
    if warns:
        md += ["## Warnings", ""] + [f"- {w}" for w in warns] + [""]
    step("report.md")
    (out / "report.md").write_text("\n".join(md))
    return [*files, "report.md"]
