"""Where a cold flight's gyro-bias error comes from: the two ground rests' readings of the Earth's rotation.

A cold flight (``--init none``) never fits its magnetometer, so the filter never knows its heading. Told the
latitude (the log's GPS), it takes the Earth rate's vertical part out of the gyro; the horizontal part,
Ω_E cos φ = 4.94e-5 rad/s at 47.4°, points to a north the filter cannot find, so the zero-rate update reads it
as bias at each rest, and the bias σ carries a floor for it (:func:`onlinecal.ukf.earth.allowance`: h²/2 per
level axis, the variance of one rest's projection at a heading nobody knows, plus the declination's s_D²).

This script measures what the x/y bias error is made of. Per flight (simulated with the Earth's rotation and a
GPS fix, replayed cold as ``flight_stats.py --gps`` does): the final bias error e (rad/s, through the true
scale), its σ, and what the gyro read at each rest besides its bias — the mean of the start rest (5–34 s,
disarmed) and of the last 12 s (landed), through the true calibration, its vertical part removed (the accel's
direction): the horizontal Earth rate at that rest's heading plus the mean's noise (~1e-5 per axis). Then the
least-squares weights of e on the two rests' readings, and the residual.

    PYTHONPATH=. python benchmarks/cold_bias_rests.py [--seeds N]

Output in docs/flight.md (session 21).
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from flight_stats import DEFAULT_LATITUDE_DEG, config_from_gps  # noqa: E402

from onlinecal.sim import simulate  # noqa: E402
from onlinecal.ukf import replay  # noqa: E402


def rest_reading(d, cal, t0: float, t1: float) -> np.ndarray:
    """The gyro's mean over [t0, t1) s less its true bias, through the true scale (rad/s), without its component
    along the accel's mean direction (the vertical, which the filter takes out): (3,)."""
    m = (d.t_imu >= t0) & (d.t_imu < t1)
    w = (d.gyro[m].mean(axis=0) - np.asarray(cal.gyro.bias)) * np.asarray(cal.gyro.scale)
    a = (d.acc[m].mean(axis=0) - np.asarray(cal.accel.bias)) * np.asarray(cal.accel.scale)
    u = a / np.linalg.norm(a)
    out: np.ndarray = w - (w @ u) * u
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=5, help="seeds per profile (default 5)")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    E, S, F, SIG = [], [], [], []
    print("profile    seed  error e (x, y) 1e-5 rad/s   σ (x, y)       start rest (x, y)   end rest (x, y)")
    for prof in ("multirotor", "fixedwing"):
        for seed in range(args.seeds):
            sim = simulate(prof, seed, duration=600.0, imu_rate=200.0, mag_rate=50.0, latitude=DEFAULT_LATITUDE_DEG,
                           earth_rate=True, gps=True)
            res = replay([sim.data], None, config_from_gps(sim.data, None))
            truth, g = sim.truth.calibration, res.calibration.gyro
            e = (np.asarray(g.bias) - np.asarray(truth.gyro.bias)) * np.asarray(truth.gyro.scale)
            s = np.asarray(g.sigma["bias"]) * np.asarray(truth.gyro.scale)
            t_end = float(sim.data.t_imu[-1])
            r0, r1 = rest_reading(sim.data, truth, 5.0, 34.0), rest_reading(sim.data, truth, t_end - 12.0, t_end)
            E.append(e[:2])
            SIG.append(s[:2])
            S.append(r0[:2])
            F.append(r1[:2])
            print(f"{prof:10s} {seed:4d}  ({1e5 * e[0]:+6.2f}, {1e5 * e[1]:+6.2f})         "
                  f"({1e5 * s[0]:4.2f}, {1e5 * s[1]:4.2f})   ({1e5 * r0[0]:+6.2f}, {1e5 * r0[1]:+6.2f})    "
                  f"({1e5 * r1[0]:+6.2f}, {1e5 * r1[1]:+6.2f})", flush=True)
    e_all, s_all = np.array(E).ravel(), np.array(SIG).ravel()
    A = np.column_stack([np.array(S).ravel(), np.array(F).ravel()])
    c, *_ = np.linalg.lstsq(A, e_all, rcond=None)
    resid = e_all - A @ c
    print(f"x/y bias error rms {1e5 * np.sqrt(np.mean(e_all**2)):.2f}e-5 rad/s, its σ (mean) "
          f"{1e5 * np.mean(s_all):.2f}e-5, mean z² {np.mean((e_all / s_all) ** 2):.2f} over {e_all.size} terms")
    explained = 100 * (1 - np.sum(resid**2) / np.sum(e_all**2))
    print(f"least squares e ≈ {c[0]:.2f} × start rest + {c[1]:.2f} × end rest: residual rms "
          f"{1e5 * np.sqrt(np.mean(resid**2)):.2f}e-5 rad/s ({explained:.0f} % of the error's square explained)")
    h2 = float(np.mean(A**2))  # the rests' readings' mean square per axis (h²/2 + the means' noise)
    print(f"the rests' readings, mean square per axis {h2:.3e} (rad/s)² (h²/2 = {0.5 * 4.936e-5**2:.3e}); the "
          f"weighted sum's variance at independent headings ({c[0]:.2f}² + {c[1]:.2f}²) × that = "
          f"{(c[0] ** 2 + c[1] ** 2) * h2:.3e}, the floor's σ² {np.mean(s_all**2):.3e}")


if __name__ == "__main__":
    main()
