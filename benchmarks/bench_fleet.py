"""Fleet replay throughput at 1 and 2 workers: process pool and dask LocalCluster, side by side, same logs.

Simulates N paper sessions (100 Hz, 5 min each, written as .tlog), then runs ``onlinecal.fleet.run_fleet``
(read → batch initialisation → UKF replay per log, exactly what ``onlinecal replay --jobs N`` does) with the
process pool at 1 and 2 workers and on a dask LocalCluster of 1 and 2 single-threaded worker processes,
interleaved ``--repeats`` times (the best time of each is kept).
Prints wall time, logs per minute, IMU samples per second and the speed-up 1 → 2 workers of each executor.
The process pool's time includes starting its spawned workers; the dask cluster is started before the clock
(its start-up is printed separately). The machine's load average is printed before and after: on a shared
machine other work takes cores away and the speed-up falls short of 2.

    PYTHONPATH=. python benchmarks/bench_fleet.py [--logs 6] [--repeats 1] [--dir DIR]
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing as mp
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from onlinecal.fleet import run_fleet
from onlinecal.io import write_log
from onlinecal.sim import simulate


def make_logs(d: Path, n: int) -> list[str]:
    paths = []
    for k in range(n):
        p = d / f"unit{k}.tlog"
        if not p.exists():
            write_log(p, simulate("paper", 500 + k).data)
        paths.append(str(p))
    return paths


def _flat(x: object) -> list[float]:
    if isinstance(x, dict):
        return [v for k in sorted(x) for v in _flat(x[k])]
    if isinstance(x, list):
        return [v for u in x for v in _flat(u)]
    return [float(x)] if isinstance(x, float) else []


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--logs", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=1, help="runs per configuration (the best is kept)")
    ap.add_argument("--dir", default=None, help="keep the simulated logs here (default: a temporary folder)")
    args = ap.parse_args()
    from dask.distributed import LocalCluster

    sys.stdout.reconfigure(line_buffering=True)  # progress visible when redirected to a file
    tmp = tempfile.TemporaryDirectory() if args.dir is None else None
    d = Path(args.dir or tmp.name)
    d.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    paths = make_logs(d, args.logs)
    print(f"{args.logs} simulated paper sessions (.tlog, 100 Hz, 309 s each) ready in {time.perf_counter() - t0:.1f} s")
    print(f"cpus: {os.cpu_count()}  load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")

    import onlinecal

    code = Path(onlinecal.__file__).resolve().parent  # the package the workers import too (same PYTHONPATH)

    def code_stamp() -> float:
        return max(p.stat().st_mtime for p in code.rglob("*.py"))

    stamp = code_stamp()
    results: dict[str, list[dict]] = {}
    times: dict[tuple[str, int], list[float]] = {}
    for w in (1, 2):
        # what a process pool pays before its first log: spawning w interpreters that import the pipeline
        t = time.perf_counter()
        with ProcessPoolExecutor(max_workers=w, mp_context=mp.get_context("spawn")) as pool:
            list(pool.map(exec, ["import onlinecal.batch, onlinecal.io, onlinecal.ukf"] * w))
        print(f"process pool of {w}: spawn + import the pipeline in {time.perf_counter() - t:.1f} s "
              "(included in the process times below)")
    with contextlib.ExitStack() as stack:
        clusters = {}
        for w in (1, 2):
            t = time.perf_counter()
            clusters[w] = stack.enter_context(
                LocalCluster(n_workers=w, threads_per_worker=1, processes=True, dashboard_address=None))
            print(f"dask LocalCluster({w} workers) started in {time.perf_counter() - t:.1f} s (not timed below)")
        configs = [("process", 1), ("process", 2), ("dask", 1), ("dask", 2)]
        # interleaved repeats: a burst of load from elsewhere hits every configuration alike; the best is kept
        for _ in range(args.repeats):
            for kind, w in configs:
                t = time.perf_counter()
                if kind == "process":
                    recs = run_fleet(paths, jobs=w)
                else:
                    recs = run_fleet(paths, executor="dask", scheduler=clusters[w].scheduler_address)
                times.setdefault((kind, w), []).append(time.perf_counter() - t)
                assert all(r["ok"] for r in recs), [r["error"] for r in recs if not r["ok"]]
                results[f"{kind} x{w}"] = recs
    n_imu = sum(r["n_imu"] for r in results["process x1"])
    rows = [(f"{k} x{w}", w, min(v), 60 * len(paths) / min(v), n_imu / min(v), v) for (k, w), v in times.items()]

    print()
    print(f"{'executor':<12}{'workers':>8}{'wall [s]':>10}{'logs/min':>10}{'IMU samples/s':>15}{'speed-up':>10}"
          "  all runs [s]")
    base = {}
    for label, w, dt, lpm, sps, allv in rows:
        kind = label.split()[0]
        base.setdefault(kind, dt)
        print(f"{label:<12}{w:>8}{dt:>10.1f}{lpm:>10.1f}{sps:>15.0f}{base[kind] / dt:>9.2f}x  "
              + " ".join(f"{v:.1f}" for v in allv))
    # every configuration computes the same calibrations (up to rounding, see onlinecal.fleet.run_fleet)
    ref = results["process x1"]
    worst = 0.0
    for recs in results.values():
        for a, b in zip(ref, recs, strict=True):
            x, y = (np.array(_flat({s: r["calibration"].get(s) for s in ("gyro", "accel", "mag")})) for r in (a, b))
            worst = max(worst, float(np.max(np.abs(x - y) / np.maximum(np.abs(x), 1e-15))))
    print(f"\nlargest relative difference between configurations, any calibration parameter or σ: {worst:.1e}")
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if code_stamp() != stamp:
        print("WARNING: onlinecal/ source files changed during the run; the configurations may have run different "
              "code, so the comparison above is not valid")
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
