"""The health verdict against the truth, on simulated paper and flight sessions (issue 12, Numbers).

For each profile and seed: the batch result and the UKF replay started from it, each judged by
:func:`onlinecal.health.assess` exactly as the command line does (NIS, events, observability, mag coverage),
and compared with the truth: the largest |estimate − truth| / σ over every term that has a σ and that the
data determined. A result is *bad* when that exceeds 5 or its NIS is out of band; the table counts both
directions: bad results the verdict called ok (missed) and good results it did not call ok (false alarms).

A batch magnetometer fitted on part of the sphere (a flight's band) carries σ from the prior-regularised fit
(:func:`onlinecal.batch.ellipsoid.fit_norm_map`); the terms it names as not determined are listed per row
(``undetermined``) and left out of the worst z, as every undetermined term is.

``--stages batch`` leaves out the UKF replay (the costly part; the online stage's start does not depend on
the batch's magnetometer where its coverage is under 40 %: :func:`onlinecal.health.filter_start` leaves it out).

    python benchmarks/bench_health.py [--seeds 4] [--profiles paper,multirotor,fixedwing,flight] [--stages batch,online]
"""

from __future__ import annotations

import argparse
import signal
import time
from typing import Any

import numpy as np

from onlinecal.batch import run_batch
from onlinecal.batch.ellipsoid import FitError
from onlinecal.health import assess, filter_start
from onlinecal.model import PARAMS, SENSORS, Calibration
from onlinecal.sim import simulate
from onlinecal.ukf import replay


def worst_z(est: Calibration, truth: Calibration, undetermined: list[str]) -> tuple[float, str]:
    """Largest |est − truth| / σ over terms with a σ that the data determined; and its name."""
    best, name = 0.0, ""
    for s in SENSORS:
        e, t = est.sensor(s), truth.sensor(s)
        if e is None or t is None:
            continue
        for p in PARAMS:
            sig = e.sigma.get(p)
            if sig is None or f"{s}.{p}" in undetermined:
                continue
            for i, a in enumerate("xyz"):
                if f"{s}.{p}.{a}" in undetermined:
                    continue
                sg = float(np.asarray(sig)[i])
                if sg > 0 and np.isfinite(sg):
                    z = abs(float(e.params()[p][i] - t.params()[p][i])) / sg
                    if z > best:
                        best, name = z, f"{s}.{p}.{a}"
    return best, name


def nis_out(h: dict[str, Any]) -> bool:
    """Some NIS stream's mean outside its band: [d/2, 2d] for the updates whose R is the sensor noise,
    [0, 2d] for the vehicle-disturbed accel updates (a bound: below d by design); streams with too few
    windows to judge are left out."""
    return any(v.get("mean") is not None and "band" in v and not v["band"][0] <= v["mean"] <= v["band"][1]
               for v in h["checks"].get("nis", {}).values())


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--profiles", default="paper,multirotor,fixedwing,flight")
    ap.add_argument("--stages", default="batch,online")
    a = ap.parse_args()
    tally: dict[tuple[str, str], dict[str, int]] = {}
    print(f"{'profile':<7} {'seed':>4} {'stage':<6} {'verdict':<9} {'worst z':>8} {'term':<16} {'NIS out':>7}  reasons")
    signal.signal(signal.SIGTERM, _stop)  # kill PID: the tally of what finished is still printed
    try:
        _runs(a, tally)
    except KeyboardInterrupt:
        print("\nstopped before the last seed finished: the tally holds the results printed above")
    print("\nprofile stage   good→ok good→not-ok (false alarm)  bad→not-ok bad→ok (missed)")
    for (prof, stage), t in tally.items():
        print(f"{prof:<7} {stage:<7} {t['good_ok']:>7} {t['good_not_ok']:>25} {t['bad_not_ok']:>11} {t['bad_ok']:>15}")


def _stop(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def _runs(a: argparse.Namespace, tally: dict[tuple[str, str], dict[str, int]]) -> None:
    # seeds outermost: a run stopped early holds the same count for every profile
    for seed in range(a.seeds):
        for prof in a.profiles.split(","):
            sim = simulate(prof, seed)
            truth = sim.truth.calibration
            mag = sim.data.mag if sim.data.n_mag else None
            t0 = time.perf_counter()
            try:
                b = run_batch([sim.data])
            except FitError as e:
                print(f"{prof:<7} {seed:>4} batch  FitError {e}")
                continue
            raw = {"gyro": sim.data.gyro, "accel": sim.data.acc}  # as the command line passes them (cli._raw)
            results = [("batch", b.calibration, assess(b.calibration, mag_raw=mag, raw=raw))]
            if "online" in a.stages.split(","):
                start, _ = filter_start(b.calibration, mag)  # as `replay --init batch` starts the filter
                r = replay([sim.data], start)
                results.append(("online", r.calibration, assess(r.calibration, nis=r.nis, events=r.events,
                                                               observability=r.observability, mag_raw=mag, raw=raw)))
            for stage, cal, h in results:
                z, term = worst_z(cal, truth, h["checks"].get("undetermined", []))
                bad = z > 5 or nis_out(h)
                t = tally.setdefault((prof, stage), {"good_ok": 0, "good_not_ok": 0, "bad_ok": 0, "bad_not_ok": 0})
                t[f"{'bad' if bad else 'good'}_{'ok' if h['verdict'] == 'ok' else 'not_ok'}"] += 1
                und = [u for u in h["checks"].get("undetermined", []) if u.startswith("mag.")]
                print(f"{prof:<7} {seed:>4} {stage:<6} {h['verdict']:<9} {z:>8.1f} {term:<16} {str(nis_out(h)):>7}  "
                      + " | ".join(r_[:70] for r_ in h["reasons"])
                      + (f"  [undetermined: {', '.join(und)}]" if und else ""), flush=True)
            print(f"        ({time.perf_counter() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
