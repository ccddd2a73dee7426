"""Alternated A/B of the online filter's speed in one process: the working tree's ``onlinecal.ukf`` against the
``onlinecal/ukf`` of an earlier commit, both loaded side by side, the 10-min benchmark flight's fast-path replay
alternated between them (order swapped every round), best and median CPU per IMU sample of each.

On a shared machine single replays move by ±40 % with the load; alternating in one process puts both versions
under the same load, round by round. Valid for changes inside ``onlinecal/ukf`` (the rest of the package is the
working tree's for both). Both copies sit in a temporary tree, so both compile their kernels at every run (a minute
or two before the timing starts, after a warm-up replay of each; not timed).

    PYTHONPATH=. python benchmarks/ab_ukf.py REV [--rounds 16] [--minutes 10] [--init none|truth]
"""

from __future__ import annotations

import argparse
import importlib
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

ROOT = Path(__file__).resolve().parent.parent


def build_tree(rev: str, where: Path) -> Path:
    """where/onlinecal: the working tree's package, with ``rev``'s onlinecal/ukf as onlinecal/ukf_a."""
    shutil.copytree(ROOT / "onlinecal", where / "onlinecal", ignore=shutil.ignore_patterns("__pycache__"))
    arch = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "onlinecal/ukf"], check=True,
                          capture_output=True).stdout
    (where / "old").mkdir()
    subprocess.run(["tar", "-x", "-C", str(where / "old")], input=arch, check=True)
    shutil.copytree(where / "old" / "onlinecal" / "ukf", where / "onlinecal" / "ukf_a")
    return where


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("rev", help="the earlier commit (A)")
    ap.add_argument("--rounds", type=int, default=16)
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--init", choices=["none", "truth"], default="none",
                    help="cold start (the benchmark's), or started from the flight's true calibration (the "
                         "magnetometer used from the first block, as in a replay started from a batch or a file)")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="ab_ukf_"))
    try:
        build_tree(args.rev, tmp)
        sys.path.insert(0, str(tmp))
        for m in [m for m in sys.modules if m == "onlinecal" or m.startswith("onlinecal.")]:
            del sys.modules[m]
        sim = importlib.import_module("onlinecal.sim")
        A, B = importlib.import_module("onlinecal.ukf_a"), importlib.import_module("onlinecal.ukf")
        run = sim.simulate("flight", 0, duration=60 * args.minutes, imu_rate=200)
        d, init = run.data, (run.truth.calibration if args.init == "truth" else None)
        for m in (A, B):
            m.replay([d.slice_imu(0, 4000)], init)  # compile or load each copy's kernels
        times: dict[str, list[float]] = {"A": [], "B": []}
        for r in range(args.rounds):
            for k, m in (("A", A), ("B", B)) if r % 2 == 0 else (("B", B), ("A", A)):
                c0 = time.process_time()
                m.replay([d], init)
                times[k].append(1e6 * (time.process_time() - c0) / d.n_imu)
        for k, what in (("A", f"{args.rev} (A)"), ("B", "working tree (B)")):
            t = times[k]
            print(f"{what}: best {min(t):.2f}, median {statistics.median(t):.2f} µs CPU per IMU sample over "
                  f"{len(t)} replays: {', '.join(f'{v:.2f}' for v in t)}")
        print(f"load average {os.getloadavg()[0]:.1f} at the end, on {os.cpu_count()} cores")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
