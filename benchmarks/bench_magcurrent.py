"""mag_current on simulated flights: diagnose's fitted coefficients against the simulator's truth, and clean flights.

For each profile (multirotor, fixedwing) and seed: a flight with a random ``mag_current`` (``random_effect``; basis
current or throttle, 5–30 % of the field at full throttle) and a clean flight; ``diagnose`` started from a bench
calibration of the same unit (the batch on a paper session simulated with the flight's truth, as ``diagnose
--init`` would be used). Prints one row per run: basis (truth/fit), per-axis relative error, error in σ, the
held-out gain against its bar, and on the extended calibration the replay's magnetometer NIS without/with the
extension. Figures in docs/effects.md.

    python benchmarks/bench_magcurrent.py [--seeds 1 2 3 4 5] [--duration 300] [--nis]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from onlinecal.apply_ext import prepare
from onlinecal.batch import run_batch
from onlinecal.diagnose import diagnose
from onlinecal.sim import simulate
from onlinecal.sim.effects import random_effect


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--profiles", nargs="+", default=["multirotor", "fixedwing"])
    ap.add_argument("--nis", action="store_true", help="also replay with and without the extension")
    a = ap.parse_args()
    print(f"{'profile':10} {'seed':>4} {'basis':>17} {'rel err x,y,z':>22} {'err/σ':>16} {'gain/bar':>14} "
          f"{'NIS w/o→with':>14} {'clean':>6} {'s':>4}")
    for prof in a.profiles:
        named = within = clean_raised = 0
        for seed in a.seeds:
            t0 = time.perf_counter()
            eff = random_effect("mag_current", np.random.default_rng(500 + seed))
            sim = simulate(prof, seed, duration=a.duration, effects=[eff])
            bench = run_batch([simulate("paper", 7000 + seed, truth=sim.truth.calibration).data]).calibration
            d = diagnose([sim.data], check=False, ukf=False, calibration=bench)
            f = next((f for f in d.significant if f.effect == "mag_current"), None)
            k = np.array(eff.coeff)
            row = f"{prof:10} {seed:>4} "
            if f is None:
                why = [u for u in d.untestable if "mag_current" in u]
                row += f"{eff.basis:>8}/{'-':8} not named ({d.verdict}; {why[0][:60] if why else ''})"
            else:
                fit, sd = np.array(f.parameters["coeff"]), np.array(f.parameters["coeff_sigma"])
                rel = np.abs(fit - k) / np.abs(k)
                ok = f.parameters["basis"] == eff.basis and bool(
                    np.all(np.abs(fit - k) <= np.maximum(0.2 * np.abs(k), 0.05 * np.linalg.norm(k))))
                named += 1
                within += ok
                row += (f"{eff.basis:>8}/{f.parameters['basis']:8} {np.array2string(rel, precision=3):>22} "
                        f"{np.array2string(np.abs(fit - k) / sd, precision=1):>16} "
                        f"{f.score:7.0f}/{f.threshold:<6.1f}")
                if a.nis:
                    from onlinecal.ukf import replay

                    nis = []
                    ext = {"mag_current": d.calibration.extensions["mag_current"]}
                    for cal in (bench, bench.replace(extensions=ext)):
                        logs, _ = prepare([sim.data], cal)
                        nis.append(float(replay(logs, cal.replace(extensions={})).nis["mag"]["mean"]))
                    row += f" {nis[0]:6.2f}→{nis[1]:<6.2f}"
            c = simulate(prof, 100 + seed, duration=a.duration)
            cb = run_batch([simulate("paper", 7000 + seed, truth=c.truth.calibration).data]).calibration
            dc = diagnose([c.data], check=False, ukf=False, calibration=cb)
            raised = any(f.effect == "mag_current" for f in dc.significant)
            clean_raised += raised
            row += f" {'RAISED' if raised else 'none':>6} {time.perf_counter() - t0:4.0f}"
            print(row, flush=True)
        print(f"{prof}: named {named}/{len(a.seeds)}, within 20 % {within}/{len(a.seeds)}, clean flights raising it "
              f"{clean_raised}/{len(a.seeds)}", flush=True)


if __name__ == "__main__":
    main()
