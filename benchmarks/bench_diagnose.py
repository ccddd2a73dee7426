"""diagnose: speed on a 5-minute 100 Hz session and detection rates over many seeds.

For each effect, ``--seeds`` sessions with the effect hidden (drawn by ``random_effect`` per seed: sensor,
axis, magnitude in the spec's test range); a session counts as detected when the verdict is the effect with
the right sensor (and axis where it has one) and its main parameter within 20 %. Clean sessions count
``none`` verdicts. Prints the table (copy into docs/benchmarks-diagnose.md).

    PYTHONPATH=. python benchmarks/bench_diagnose.py [--seeds 6] [--clean 40] [--flight]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from onlinecal.diagnose import diagnose
from onlinecal.sim import simulate
from onlinecal.sim.effects import EFFECTS, random_effect

PRIMARY = {"temperature_bias": "coeff", "bias_drift": "density", "g_sensitivity": "coeff",
           "time_offset": "seconds", "saturation": "limit", "scale_nonlinearity": "coeff"}


def correct(f, truth: dict) -> tuple[bool, float]:
    """(sensor/axis right and parameter within 20 %, relative parameter error)."""
    if f.effect != truth["effect"] or f.sensor != truth["sensor"]:
        return False, float("nan")
    if truth["effect"] not in ("time_offset", "saturation", "lever_arm") and f.axis != truth["axis"]:
        return False, float("nan")
    if truth["effect"] == "lever_arm":
        r = np.array([truth[k] for k in "xyz"])
        e = np.array([f.parameters[k] for k in "xyz"])
        err = float(np.linalg.norm(e - r) / np.linalg.norm(r))
    elif truth["effect"] in PRIMARY:
        k = PRIMARY[truth["effect"]]
        err = abs(f.parameters[k] - truth[k]) / abs(truth[k])
    else:
        err = 0.0
    return err <= 0.2, err


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--clean", type=int, default=40)
    ap.add_argument("--flight", action="store_true", help="also time a 10-minute simulated flight")
    a = ap.parse_args()
    sim = simulate("paper", 0)
    t0 = time.perf_counter()
    d = diagnose([sim.data])
    wall = time.perf_counter() - t0
    print(f"speed: {sim.data.duration:.0f}-s session at {sim.data.imu_rate:.0f} Hz: diagnose {wall:.1f} s "
          f"(stages {', '.join(f'{k} {v:.2f}' for k, v in d.timing.items())}); target ≤ 60 s")
    if a.flight:
        fl = simulate("flight", 1, duration=600.0)
        t0 = time.perf_counter()
        d = diagnose([fl.data], calibration=fl.truth.calibration, check=False, ukf=False)
        wall = time.perf_counter() - t0
        print(f"speed: 600-s simulated flight at 100 Hz from the bench calibration (--init; the batch is not timed): "
              f"diagnose {wall:.1f} s (stages {', '.join(f'{k} {v:.2f}' for k, v in d.timing.items())}); "
              f"verdict {d.verdict}; target ≤ 60 s")
    print()
    print(f"{'effect':20s} {'sessions':>8} {'verdict ok':>10} {'all ok':>7} {'median |err|':>12} {'max |err|':>10} "
          f"{'mean s':>7}")
    for name in EFFECTS:
        ok_v = ok_all = 0
        errs, times = [], []
        for s in range(a.seeds):
            seed = 500 + s
            rng = np.random.default_rng(9000 + s)
            clean = simulate("paper", seed) if name == "saturation" else None
            eff = random_effect(name, rng, clean)
            sm = simulate("paper", seed, effects=[eff])
            t = time.perf_counter()
            dg = diagnose([sm.data], check=False)
            times.append(time.perf_counter() - t)
            if dg.verdict == name:
                ok_v += 1
                good, err = correct(dg.significant[0], sm.truth.effects[0])
                ok_all += good
                if np.isfinite(err):
                    errs.append(err)
        e = np.array(errs) if errs else np.array([np.nan])
        print(f"{name:20s} {a.seeds:8d} {ok_v:10d} {ok_all:7d} {np.median(e):12.3f} {np.max(e):10.3f} "
              f"{np.mean(times):7.1f}")
    nones = 0
    for s in range(a.clean):
        dg = diagnose([simulate("paper", 3000 + s).data], check=False, seed=s)
        nones += dg.verdict == "none"
    print(f"{'none (clean)':20s} {a.clean:8d} {nones:10d}")


if __name__ == "__main__":
    main()
