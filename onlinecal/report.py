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
