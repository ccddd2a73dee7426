"""Speed of the block-vectorised UKF against filterpy's stock per-sample loop on the same model.

A 10-minute 200 Hz flight log (simulated) is replayed in full through ``onlinecal.ukf.replay`` (one core;
set OMP/MKL/OPENBLAS_NUM_THREADS=1 to be strict). The stock ``UnscentedKalmanFilter`` (one predict + one
accel update per IMU sample, filterpy's per-sigma-point Python loop) is timed on a shorter stretch and its
per-sample cost extrapolated to the whole log — the output says so.

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
    res = replay([d], None)
    log_s = d.duration
    print(f"log: {d.n_imu} IMU samples at {args.rate:g} Hz, {log_s:.0f} s")
    print(f"block UKF (onlinecal.ukf): {res.wall_s:.2f} s wall  → {log_s / res.wall_s:.0f}× real time "
          f"({1e6 * res.wall_s / d.n_imu:.1f} µs per IMU sample)")
    cal = OnlineCalibrator(None)
    x0, sig0 = cal._prior()
    sig0[:3] = 0.1
    stock = StockUKF(x0, np.diag(sig0**2), args.rate)
    n = min(args.stock_samples, d.n_imu)
    t0 = time.perf_counter()
    stock.run(d, n)
    dt = time.perf_counter() - t0
    per = dt / (n - 1)
    full = per * d.n_imu
    print(f"stock filterpy UnscentedKalmanFilter, one predict+update per sample: {dt:.2f} s for {n - 1} "
          f"samples = {1e6 * per:.0f} µs per sample; extrapolated to the whole log: {full:.0f} s "
          f"({log_s / full:.2f}× real time)")
    print(f"speed-up of the block UKF over the stock loop: {full / res.wall_s:.0f}×")


if __name__ == "__main__":
    main()
