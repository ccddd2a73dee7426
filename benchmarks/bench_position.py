"""Cost of finding where a log was recorded (onlinecal.io.position.log_position) before a replay starts.

A simulated multirotor flight (default 10 min at 200 Hz) is written as .bin, .tlog and .ulg, once with its GPS
position (``simulate(..., gps=True)``: 5 Hz fixes from t = 0) and once without. Each file is scanned in a fresh
call, best of ``--repeat``; the scan stops after 50 fixes, so a log with GPS costs the bytes up to its 50th fix
and one without costs the whole file. The same files' full read (``read_log``) is timed beside it, as the
replay's own cost of reading them. The first scan of a .bin also loads dfparse's compiled record walk from
numba's cache (a warm-up scan is done first and not counted).

    PYTHONPATH=. python benchmarks/bench_position.py [--minutes M] [--rate HZ] [--repeat N]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

from onlinecal.io import read_log, write_log
from onlinecal.io.position import log_position
from onlinecal.sim import simulate


def best(fn: Callable[[], object], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--rate", type=float, default=200.0)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    sims = {gps: simulate("multirotor", 1, duration=60.0 * a.minutes, imu_rate=a.rate, mag_rate=50.0, gps=gps)
            for gps in (True, False)}
    print(f"{a.minutes:g}-min multirotor flight at {a.rate:g} Hz ({sims[True].data.n_imu} IMU samples); "
          f"best of {a.repeat}")
    with tempfile.TemporaryDirectory() as tmp:
        for ext in (".bin", ".tlog", ".ulg"):
            for gps, sim in sims.items():
                p = Path(tmp) / f"f{'_gps' if gps else ''}{ext}"
                write_log(p, sim.data)
                log_position(p)  # warm-up: imports, numba's cached walk
                pos = log_position(p)
                t_scan = best(partial(log_position, p), a.repeat)
                t_read = best(partial(read_log, p), 1)
                found = f"fix at {pos.latitude_deg:.4f}° ({pos.n_fixes} fixes)" if pos else "no fix"
                print(f"  {ext:5s} {'with GPS   ' if gps else 'without GPS'} {p.stat().st_size / 1e6:6.1f} MB: "
                      f"scan {1e3 * t_scan:8.1f} ms ({found}); whole read {t_read:6.2f} s; "
                      f"scan / read {t_scan / t_read:6.3f}")


if __name__ == "__main__":
    main()
