"""``onlinecal demo``: simulate a paper session → write it as a .tlog → read it back → batch → UKF →
compare both with the truth. Everything goes through the same code paths a user's log takes."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

from .batch import run_batch
from .files import atomic_write, dumps
from .health import assess, combine
from .io import read_log, write_log
from .model import Calibration
from .progress import stages
from .report import errors_against, truth_table
from .sim import simulate


def _online(logs: list, init: Calibration, on_progress: Any = None) -> tuple[Any, str]:
    try:
        from . import ukf
    except ImportError:
        return None, "online filter not available in this build"
    if not hasattr(ukf, "replay"):
        return None, "online filter not available in this build"
    from .fleet import replay_chunked

    return replay_chunked(logs, init, on_progress=on_progress), ""


def _plots(out: Path, data, batch: Calibration) -> list[str]:
    try:
        from .plots import norms_overview

        norms_overview(out / "norms.png", data, batch)
    except ImportError:
        return []
    return ["norms.png"]


def _save(cal: Calibration, health: dict[str, Any], path: Path) -> None:
    obj = cal.replace(health=health).to_dict()
    atomic_write(path, dumps(obj) + "\n")


def run_demo(out: Path, seed: int = 0) -> int:
    """Exit status: 0, or 4/5 when the batch or online result is degraded/failed (:mod:`onlinecal.health`)."""
    t_start = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    from .ukf import warmup

    # a first run: the filter's kernels compile in worker processes while the session is simulated and calibrated
    warmup.start()
    with stages(["simulate", "write .tlog", "read back", "batch", "online filter", "report"], desc="demo") as st:
        st.next("simulate")
        sim = simulate("paper", seed)
        log = out / "session.tlog"
        st.next("write .tlog")
        write_log(log, sim.data)
        sim.truth.save(str(log) + ".truth.json")
        st.next("read back")
        data = read_log(log)
        st.next("batch")
        t0 = time.perf_counter()
        res = run_batch([data])
        t_batch = time.perf_counter() - t0
        batch = res.calibration
        raw = {"gyro": data.gyro, "accel": data.acc}  # gravity at rest and the rail, as every command judges them
        h_batch = assess(batch, mag_raw=data.mag if data.n_mag else None, raw=raw)
        _save(batch, h_batch, out / "batch.json")
        st.next("online filter")
        t0 = time.perf_counter()
        n = max(1, data.n_imu)
        ores, why = _online([data], batch, lambda i, _n: st.set(4, note=f"online filter {100 * min(i, n) // n}%"))
        t_online = time.perf_counter() - t0
        online: Calibration | None = ores.calibration if ores is not None else None
        h_online = None
        if ores is not None and online is not None:
            h_online = assess(online, nis=ores.nis, events=ores.events, observability=ores.observability,
                              mag_raw=data.mag if data.n_mag else None, raw=raw)
            _save(online, h_online, out / "online.json")
        st.next("report")
    truth = sim.truth.calibration
    table = truth_table(truth, batch, online)
    print(table)
    err = {"batch": errors_against(truth, batch)}
    if online is not None:
        err["online"] = errors_against(truth, online)
    atomic_write(out / "errors.json", dumps(err) + "\n")
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
    lines += ["", f"Health: batch {h_batch['verdict']}" + (f", online {h_online['verdict']}" if h_online else "")]
    lines += [f"- {r}" for h in (h_batch, h_online) if h for r in h["reasons"]]
    if res.warnings:
        lines += ["", "Warnings:", ""] + [f"- {w}" for w in res.warnings]
    atomic_write(out / "report.md", "\n".join(lines) + "\n")
    print(f"\nwrote {out}/ (session.tlog, batch.json{', online.json' if online else ''}, report.md"
          f"{', ' + ', '.join(plots) if plots else ''}) in {time.perf_counter() - t_start:.1f} s",
          file=sys.stderr)
    verdict = combine([h_batch, h_online])
    print(f"health: batch {h_batch['verdict']}" + (f", online {h_online['verdict']}" if h_online else ""),
          file=sys.stderr)
    for h in (h_batch, h_online):
        for r in (h or {}).get("reasons", []):
            print(f"  - {r}", file=sys.stderr)
    return {"ok": 0, "degraded": 4, "failed": 5}[verdict]
