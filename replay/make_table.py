"""The replay corpus against its truth: parameter · truth · batch · online ± 3σ, per session.

    PYTHONPATH=. python replay/make_table.py          # writes replay/corpus.md

Each session of ``replay/corpus`` (beside its ``.truth.json``) is read through its real file format, run
through the batch pipeline and then through the UKF started from the batch result (or cold, where the
batch cannot run — a flight log has no rests in twelve attitudes). A row is flagged where online and
batch differ by more than 3σ (both σ combined); every flag gets a cause in words, found from the
figures: the batch's own error against the truth, the format's re-quantisation, the gauge, excitation.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from onlinecal.batch import run_batch
from onlinecal.batch.ellipsoid import FitError
from onlinecal.io import read_log
from onlinecal.model import Calibration
from onlinecal.report import param_rows
from onlinecal.sim import Truth
from onlinecal.ukf import replay
from onlinecal.ukf.gauge import align_gauge

HERE = Path(__file__).resolve().parent
CORPUS = HERE / "corpus"


@dataclass
class SessionTable:
    name: str
    rows: list[dict[str, Any]]
    notes: list[str] = field(default_factory=list)

    def flagged(self) -> list[dict[str, Any]]:
        return [r for r in self.rows if r["flag"]]


def sessions() -> list[Path]:
    return sorted(p for p in CORPUS.iterdir() if not p.name.endswith(".json") and Path(str(p) + ".truth.json").exists())


def _explain(r: dict[str, Any], meta: dict[str, Any], obs: dict[str, Any]) -> str:
    """Cause of an online≠batch flag, from the figures of the row."""
    name = f"{r['sensor']}.{r['param']}.{r['axis']}"
    b_err, o_err = r["batch"] - r["truth"], r["online"] - r["truth"]
    b_z = abs(b_err) / r["batch_sigma"] if r.get("batch_sigma") else float("inf")
    o_z = abs(o_err) / r["online_sigma"]
    if r["sensor"] == meta["gauge"]["sensor"] and r["param"] in meta["gauge"]["terms"]:
        return "gauge term held at the batch value (cannot differ)"
    parts = []
    if b_z > 3 and o_z <= 3:
        q = meta.get("quantisation", {})
        if r["param"] == "bias" and q.get(f"{r['sensor']}_requant"):
            parts.append(f"batch off the truth by {b_z:.0f} of its σ: its bias from the rests carries the "
                         f"format's re-quantisation error (lattice {q[r['sensor']]:.3g}, mean of a held reading "
                         "does not average it out); the online filter models it (hold offset) and is within "
                         f"{o_z:.1f}σ of the truth")
        else:
            parts.append(f"batch off the truth by {b_z:.0f} of its σ (its σ too small); online within {o_z:.1f}σ")
    elif o_z > 3:
        parts.append(f"online off the truth by {o_z:.1f}σ")
        if not obs.get(name, {}).get("excited", True):
            parts.append("the parameter is not excited by this session")
    else:
        parts.append(f"both within reach of the truth (batch {b_z:.1f}σ_batch, online {o_z:.1f}σ)")
    return "; ".join(parts)


def build(path: Path) -> SessionTable:
    truth = Truth.load(str(path) + ".truth.json").calibration
    data = read_log(path)
    notes = []
    init: Calibration | None
    try:
        batch: Calibration | None = run_batch([data]).calibration
    except FitError as e:
        batch = None
        notes.append(f"batch pipeline cannot run on this session ({e})")
    init = batch
    if batch is not None and any(batch.sensor(s) is None for s in ("gyro", "accel", "mag")):
        # a batch that left a sensor out also fell back elsewhere (flight: no static attitudes, no phases);
        # its σ are no prior to start from
        init = None
        notes.append("the batch left a sensor out (no static attitudes / rotation phases in this session): "
                     "the online filter starts cold (--init none)")
    res = replay([data], init)
    online = res.calibration
    meta = online.meta["online"]
    ev = [e["kind"] for e in res.events]
    if ev:
        notes.append("online events: " + ", ".join(sorted(set(ev))))
    g = (meta.get("gauge") or {}).get("sensor")
    if init is None and g and online.sensor(g) is not None:
        # cold: B is the gauge sensor's own frame (its alpha held at 0 by definition), so the truth is
        # compared in that frame (one common rotation of all sensors, which no data can see)
        truth = align_gauge(truth, g, online.sensor(g).alpha)
        notes.append(f"cold start: truth expressed in the filter's body frame (the {g}'s frame, its alpha "
                     "held at 0 by definition)")
    rows = []
    for r in param_rows({"truth": truth, "batch": batch, "online": online}):
        on, sig = r["online"], r["online_sigma"]
        r["flag"] = False
        r["why"] = ""
        if batch is not None and r.get("batch") is not None and sig:
            comb = float(np.hypot(sig, r.get("batch_sigma") or 0.0))
            if abs(on - r["batch"]) > 3 * comb:
                r["flag"] = True
                r["why"] = _explain(r, meta, res.observability)
        r["online_in_3sigma"] = bool(abs(on - r["truth"]) <= 3 * sig)
        rows.append(r)
    return SessionTable(path.name, rows, notes)


def markdown(tables: list[SessionTable]) -> str:
    out = ["# Replay corpus: truth · batch · online", "",
           "Generated by `PYTHONPATH=. python replay/make_table.py` (do not edit). Online: the UKF started from "
           "the batch result; ± 3σ is the online σ. `⚑` marks online and batch more than 3σ apart "
           "(both σ combined); the cause is given below each table.", ""]
    for t in tables:
        inside = np.mean([r["online_in_3sigma"] for r in t.rows])
        out += [f"## {t.name}", "",
                f"Online within 3σ of the truth: {100 * inside:.0f} % of {len(t.rows)} parameters.", ""]
        out += [f"- {n}" for n in t.notes] + ([""] if t.notes else [])
        out += ["| parameter | truth | batch | online | ± 3σ | |", "|---|---:|---:|---:|---:|---|"]
        for r in t.rows:
            b = "—" if r.get("batch") is None else f"{r['batch']:+.6f}"
            out.append(f"| {r['sensor']}.{r['param']}.{r['axis']} | {r['truth']:+.6f} | {b} | {r['online']:+.6f} "
                       f"| {3 * r['online_sigma']:.1e} | {'⚑' if r['flag'] else ''} |")
        fl = t.flagged()
        out += [""] + ([f"- ⚑ {r['sensor']}.{r['param']}.{r['axis']}: {r['why']}" for r in fl] or ["No flags."]) + [""]
    return "\n".join(out)


def main() -> int:
    tables = [build(p) for p in sessions()]
    (HERE / "corpus.md").write_text(markdown(tables))
    for t in tables:
        print(f"{t.name}: {len(t.flagged())} flagged, online within 3σ of truth "
              f"{100 * np.mean([r['online_in_3sigma'] for r in t.rows]):.0f} %", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
