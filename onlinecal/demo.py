"""``onlinecal demo``: simulate a paper session → write it as a .tlog → read it back → batch → UKF →
compare both with the truth. Everything goes through the same code paths a user's log takes."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from .batch import run_batch
from .io import read_log, write_log
from .model import Calibration
from .report import errors_against, truth_table
from .sim import simulate


def _online(logs: list, init: Calibration) -> tuple[Calibration | None, str]:
    try:
        from . import ukf
    except ImportError:
        ukf = None
    if ukf is None or not hasattr(ukf, "replay"):
        return None, "online filter not available in this build"
    res = ukf.replay(logs, init)
    return res.calibration, ""


def _plots(out: Path, data, batch: Calibration) -> list[str]:
    try:
        from .plots import norms_overview

        norms_overview(out / "norms.png", data, batch)
    except ImportError:
        return []
    return ["norms.png"]


def run_demo(out: Path, seed: int = 0) -> int:
    t_start = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    sim = simulate("paper", seed)
    log = out / "session.tlog"
    write_log(log, sim.data)
    sim.truth.save(str(log) + ".truth.json")
    data = read_log(log)
    t0 = time.perf_counter()
    res = run_batch([data])
    t_batch = time.perf_counter() - t0
    batch = res.calibration
    batch.save(out / "batch.json")
    t0 = time.perf_counter()
    online, why = _online([data], batch)
    t_online = time.perf_counter() - t0
    if online is not None:
        online.save(out / "online.json")
    truth = sim.truth.calibration
    table = truth_table(truth, batch, online)
    print(table)
    err = {"batch": errors_against(truth, batch)}
    if online is not None:
        err["online"] = errors_against(truth, online)
    (out / "errors.json").write_text(json.dumps(err, indent=2) + "\n")
    plots = _plots(out, data, batch)
    lines = [
        "# onlinecal demo",
        "",
        f"Simulated paper session (seed {seed}): {data.n_imu} IMU samples at {data.imu_rate:.0f} Hz, "
        f"{data.n_mag} magnetometer samples, {data.duration:.0f} s, written as `session.tlog` (RAW_IMU) "
        "and read back.",
        "",
        f"Batch pipeline: {t_batch:.2f} s." + (f" Online filter: {t_online:.2f} s." if online else f" {why}."),
        "",
        "```",
        table,
        "```",
        "",
        "Matrix relative error (Frobenius): "
        + ", ".join(f"{s} {100 * err['batch'][s]['matrix_rel'][0]:.3f} %" for s in err["batch"]),
        "",
    ] + [f"![{p}]({p})" for p in plots]
    if res.warnings:
        lines += ["", "Warnings:", ""] + [f"- {w}" for w in res.warnings]
    (out / "report.md").write_text("\n".join(lines) + "\n")
    print(f"\nwrote {out}/ (session.tlog, batch.json{', online.json' if online else ''}, report.md"
          f"{', ' + ', '.join(plots) if plots else ''}) in {time.perf_counter() - t_start:.1f} s",
          file=sys.stderr)
    return 0
