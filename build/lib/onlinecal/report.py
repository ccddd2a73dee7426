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
    return "—" if x is None or not np.isfinite(x) else f"{x:+.{digits}f}"


def _fmt_sig(x: float | None) -> str:
    return "—" if x is None or not np.isfinite(x) or x <= 0 else f"{x:.1e}"


def truth_table(truth: Calibration | None, batch: Calibration | None, online: Calibration | None,
                labels: tuple[str, str] = ("batch", "online")) -> str:
    """Text table: parameter · unit · truth · batch ± 3σ · online ± 3σ (the demo's, batch's, replay's table).

    Only the columns that carry data are drawn: a calibration that is None has no column, and a σ column
    appears only where that calibration has a σ for some parameter. ``labels`` names the two estimate
    columns (e.g. ``("init", "online")`` for a replay from a calibration file). The flag marks an online
    value more than 3 combined σ from the other estimate."""
    la, lb = labels
    rows = param_rows({"truth": truth, la: batch, lb: online})
    have = {k: c is not None for k, c in (("truth", truth), (la, batch), (lb, online))}
    sig = {k: have[k] and any(r.get(k + "_sigma") for r in rows) for k in (la, lb)}
    cols: list[tuple[str, str, int]] = []  # (key, header, width)
    if have["truth"]:
        cols.append(("truth", "truth", 12))
    for k in (la, lb):
        if have[k]:
            cols.append((k, k, 12))
            if sig[k]:
                cols.append((k + "_sigma", "± 3σ", 9))
    both = have[la] and have[lb]
    head = f"{'parameter':<16}{'unit':<7}" + "".join(f"{h:>{w}}" for _, h, w in cols) + ("  flag" if both else "")
    lines = [head, "-" * len(head)]
    for r in rows:
        on, ref = r.get(lb), r.get(la)
        s_on, s_ref = r.get(lb + "_sigma"), r.get(la + "_sigma")
        flag = ""
        if both and on is not None and ref is not None and s_on:
            if abs(on - ref) > 3 * np.hypot(s_on, s_ref or 0.0):
                flag = f"{lb}≠{la}"
        cells = []
        for k, _, w in cols:
            v = r.get(k)
            cells.append(f"{_fmt_sig(3 * v if v else None):>{w}}" if k.endswith("_sigma") else f"{_fmt(v):>{w}}")
        name = f"{r['sensor']}.{r['param']}.{r['axis']}"
        lines.append(f"{name:<16}{r['unit'] or '-':<7}" + "".join(cells) + (f"  {flag}" if flag else ""))
    return "\n".join(lines)


def compare(a: Calibration, b: Calibration, tol: float | None = None,
            abs_tol: float | None = None) -> list[dict[str, Any]]:
    """Parameter-by-parameter difference b − a, and in σ where either side knows its σ.

    ``beyond`` marks a row outside the tolerance: ``|Δ| > tol·σ`` where σ (A and B combined) is known,
    ``|Δ| > abs_tol`` (in the parameter's unit) where it is not."""
    out = []
    for r in param_rows({"a": a, "b": b}):
        if r.get("a") is None or r.get("b") is None:
            continue
        d = r["b"] - r["a"]
        sa, sb = r.get("a_sigma"), r.get("b_sigma")
        sig = float(np.hypot(sa if sa is not None and np.isfinite(sa) else 0.0,
                             sb if sb is not None and np.isfinite(sb) else 0.0))
        row = {**{k: r[k] for k in ("sensor", "param", "axis", "unit", "a", "b")},
               "diff": d, "sigma": sig if sig > 0 else None, "n_sigma": float(abs(d) / sig) if sig > 0 else None}
        row["beyond"] = bool((tol is not None and sig > 0 and abs(d) > tol * sig)
                             or (abs_tol is not None and sig == 0 and abs(d) > abs_tol))
        out.append(row)
    for s in SENSORS:
        ca, cb = a.sensor(s), b.sensor(s)
        if isinstance(ca, SensorCalibration) and isinstance(cb, SensorCalibration):
            out.append({"sensor": s, "param": "matrix", "axis": None, "unit": "",
                        "a": None, "b": None, "diff": cb.matrix_rel_error(ca), "sigma": None,
                        "n_sigma": None, "beyond": False})
    return out


def compare_text(a: Calibration, b: Calibration, rows: list[dict[str, Any]] | None = None,
                 tol: float | None = None, abs_tol: float | None = None) -> str:
    """The comparison as a table with a space between every column; rows beyond the tolerance flagged."""
    if rows is None:
        rows = compare(a, b, tol, abs_tol)
    head = f"{'parameter':<16} {'unit':<6} {'A':>13} {'B':>13} {'B − A':>11} {'σ':>9} {'|Δ|/σ':>8}"
    lines = [head, "-" * (len(head) + 8)]
    for r in rows:
        if r["param"] == "matrix":
            lines.append(f"{r['sensor'] + '.matrix':<16} {'rel.':<6} {'':>13} {'':>13} {r['diff']:>11.2e} "
                         f"{'':>9} {'':>8}  (relative Frobenius difference)")
            continue
        name = f"{r['sensor']}.{r['param']}.{r['axis']}"
        sig = f"{r['sigma']:.1e}" if r["sigma"] else "—"
        ns = f"{r['n_sigma']:.1f}" if r["n_sigma"] is not None else "—"
        flag = "  BEYOND" if r.get("beyond") else ""
        lines.append(f"{name:<16} {r['unit'] or '-':<6} {r['a']:>+13.6f} {r['b']:>+13.6f} {r['diff']:>+11.2e} "
                     f"{sig:>9} {ns:>8}{flag}")
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
        for j, ((i, iv), a) in enumerate(zip(sts, means, strict=True)):
            md.append(f"| {j} | {i} | {iv.t0:.6f} | {iv.t1:.6f} | {iv.n} | {np.linalg.norm(a):.5f} | "
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
        for sn in SENSORS:
            if ocal is None or ocal.sensor(sn) is None:
                continue
            step(f"ukf {sn}")
            name = plots.ukf_params(out / f"ukf_{sn}.png", online.trace,
                                    sn, {k: c.sensor(sn) for k, c in refs.items()}).name
            files.append(name)
            md += [f"![{sn} parameters]({name})", ""]
        md += [f"Replay: {online.n_imu} IMU samples, {online.log_s:.1f} s of log in {online.wall_s:.2f} s "
               f"({online.realtime_factor:.0f}× real time); {len(online.events)} filter events.", ""]
        if online.missing_motion:
            md += ["Motion still missing to excite every parameter:", ""]
            md += [f"- {m}" for m in online.missing_motion] + [""]
        obs = (ocal.meta or {}).get("online", {}).get("observability") if ocal is not None else None
        if obs:
            from .ukf.vehicle import observability_text

            md += ["What the data determined, what it did not, and the Earth's rotation:", ""]
            md += [f"- {line}" for line in observability_text(obs)] + [""]

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
    from .files import atomic_write

    atomic_write(out / "report.md", "\n".join(md))
    return [*files, "report.md"]
