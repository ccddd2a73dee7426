"""A first run's cost: ``onlinecal demo`` from an empty numba cache, with the kernels compiled side by side in
worker processes (onlinecal.ukf.warmup, the default) and without (``ONLINECAL_WARMUP=0``: the demo's own process
compiles them one after another, as before), alternated, in one run.

Each run is a fresh ``python -m onlinecal demo`` with its own empty ``NUMBA_CACHE_DIR`` (everything numba
compiles is compiled again: the simulator's, the batch's and the filter's kernels), wall clock from the start
of the process to its end; the warm demo (the same cache again) for comparison. The two cold runs' online
results are compared bit for bit (online.json without its timing fields). Issue 15 asks for the demo under a
minute including any compilation.

    PYTHONPATH=. python benchmarks/bench_firstrun.py [--rounds N] [--seed S]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def demo(out: Path, cache: Path, warm: bool, seed: int) -> tuple[float, int, dict]:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), ONLINECAL_WARMUP="1" if warm else "0",
               PYTHONPATH=str(ROOT) + (os.pathsep + os.environ["PYTHONPATH"] if os.environ.get("PYTHONPATH") else ""))
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "onlinecal", "demo", "--out", str(out), "--seed", str(seed)], env=env,
                       capture_output=True, text=True)
    wall = time.perf_counter() - t0
    online = json.loads((out / "online.json").read_text()) if (out / "online.json").exists() else {}
    return wall, p.returncode, online


def _strip(d: dict) -> dict:
    """online.json without what depends on the clock (speed, wall time)."""
    d = json.loads(json.dumps(d))
    d.get("meta", {}).get("online", {}).pop("speed", None)
    for k in ("wall_s", "realtime_factor", "created"):
        d.get("meta", {}).get("online", {}).pop(k, None)
        d.get("meta", {}).pop(k, None)
    return d


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    print(f"onlinecal demo from an empty numba cache, {a.rounds} round(s) alternated; {cpus} CPUs, "
          f"load average {os.getloadavg()[0]:.1f}")
    times: dict[bool, list[float]] = {True: [], False: []}
    results: dict[bool, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        for r in range(a.rounds):
            for warm in ((True, False) if r % 2 == 0 else (False, True)):
                d = t / f"{r}-{int(warm)}"
                wall, rc, online = demo(d / "out", d / "numba", warm, a.seed)
                if rc != 0:
                    sys.exit(f"demo exited {rc} (warm-up {'on' if warm else 'off'})")
                times[warm].append(wall)
                results[warm] = _strip(online)
                print(f"  round {r + 1}: warm-up {'on ' if warm else 'off'} {wall:6.1f} s "
                      f"(load {os.getloadavg()[0]:.1f})")
        d = t / "0-1"
        wall_warm, rc, _ = demo(d / "again", d / "numba", True, a.seed)
    on, off = min(times[True]), min(times[False])
    print(f"cold demo, kernels compiled in worker processes (default): best {on:.1f} s, all "
          + ", ".join(f"{x:.1f}" for x in times[True]))
    print(f"cold demo, compiled in the demo's process (ONLINECAL_WARMUP=0): best {off:.1f} s, all "
          + ", ".join(f"{x:.1f}" for x in times[False]))
    print(f"ratio (best off / best on): {off / on:.2f}×; warm cache: {wall_warm:.1f} s")
    same = results[True] == results[False]
    print(f"online.json of the two cold runs {'identical' if same else 'DIFFERENT'} (timing fields aside)")
    print(f"issue 15: demo under a minute including compilation — {on:.1f} s "
          f"({'reached' if on < 60 else 'not reached'})")


if __name__ == "__main__":
    main()
