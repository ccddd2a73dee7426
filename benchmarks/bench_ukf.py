"""Speed of the block-vectorised UKF against filterpy's stock per-sample loop on the same model.

A 10-minute 200 Hz flight log (simulated) is replayed in full through ``onlinecal.ukf.replay`` (one core:
OMP/MKL/OPENBLAS_NUM_THREADS=1 are set before numpy loads). The stock ``UnscentedKalmanFilter`` (one
predict + one accel update per IMU sample, filterpy's per-sigma-point Python loop) is timed on a shorter
stretch in the same run and its per-sample cost extrapolated to the whole log — the output says so.

Both are timed by the wall clock and by this process's CPU time (``time.process_time``): on a machine
shared with other jobs the wall clock measures the load as much as the code, the CPU time much less so.
The real-time factor is log duration / time; the speed-up is stock time / block time, per clock.

    PYTHONPATH=. python benchmarks/bench_ukf.py [--stock-samples N] [--minutes M] [--rate HZ]
"""

from __future__ import annotations

import argparse
import os
import time

for _v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402

from onlinecal.sim import simulate  # noqa: E402
from onlinecal.ukf import OnlineCalibrator, replay  # noqa: E402
from onlinecal.ukf.stock import StockUKF  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--rate", type=float, default=200.0)
    ap.add_argument("--stock-samples", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    sim = simulate("flight", args.seed, duration=60 * args.minutes, imu_rate=args.rate)
    d = sim.data
    log_s = d.duration
    c0 = time.process_time()
    res = replay([d], None)
    cpu = time.process_time() - c0
    wall = res.wall_s
    print(f"log: {d.n_imu} IMU samples at {args.rate:g} Hz, {log_s:.0f} s (flight profile, cold start, "
          f"events: {sorted({e['kind'] for e in res.events}) or 'none'})")
    print(f"block UKF (onlinecal.ukf): {wall:.2f} s wall → {log_s / wall:.0f}× real time; "
          f"{cpu:.2f} s CPU → {log_s / cpu:.0f}× real time ({1e6 * cpu / d.n_imu:.1f} µs CPU per IMU sample)")
    cal = OnlineCalibrator(None)
    x0, sig0 = cal._prior()
    sig0[:3] = 0.1
    stock = StockUKF(x0, np.diag(sig0**2), args.rate)
    n = min(args.stock_samples, d.n_imu)
    t0, c0 = time.perf_counter(), time.process_time()
    stock.run(d, n)
    s_wall, s_cpu = time.perf_counter() - t0, time.process_time() - c0
    full_wall, full_cpu = s_wall / (n - 1) * d.n_imu, s_cpu / (n - 1) * d.n_imu
    print(f"stock filterpy UnscentedKalmanFilter, one predict+update per sample, timed on {n - 1} samples: "
          f"{1e6 * s_wall / (n - 1):.0f} µs wall, {1e6 * s_cpu / (n - 1):.0f} µs CPU per sample; "
          f"extrapolated to the whole log: {full_wall:.0f} s wall ({log_s / full_wall:.2f}× real time), "
          f"{full_cpu:.0f} s CPU ({log_s / full_cpu:.2f}× real time)")
    print(f"speed-up of the block UKF over the stock loop: {full_wall / wall:.0f}× (wall), "
          f"{full_cpu / cpu:.0f}× (CPU)")


if __name__ == "__main__":
    main()
