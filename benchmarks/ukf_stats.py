"""20-seed statistics of the UKF started from the batch result on the paper session.

Per parameter: RMS over seeds of the online error, of the batch error, their ratio; share of parameters
within 3σ (coverage); NEES against its chi-square band, over all 36 terms and over the terms the filter
estimates (the gauge terms — the gyro's alpha and xi when the batch took B from the gyro's rotation
phases — are held at the batch's values as consider states, so their online error is the batch's);
events; wall time.

    PYTHONPATH=. python benchmarks/ukf_stats.py [--seeds 20] [--start 0] [--set KEY=JSON ...]

``--cold S``: instead, the cold start of gyro and accel (prior σ 0.2, 0.2 rad/s; 0.05, 0.5 m/s²; the mag
from the batch) over the first S seconds of each session (90: the 30-s rest and 60 s of turns to static
positions): per seed the largest |error|/σ of the gyro's and the accel's bias and scale and of all their
terms, and how many seeds have every bias and scale within 3σ. ``--mag-cold``: nothing from the batch
(``--init none``), the mag from its own cold sphere fit, and its terms judged too.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter

import numpy as np
from scipy.stats import chi2

from onlinecal.batch.pipeline import run_batch
from onlinecal.model import PARAMS, SENSORS
from onlinecal.sim import simulate
from onlinecal.ukf import replay
from onlinecal.ukf.filter import UKFConfig


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--cold", type=float, default=None, metavar="S")
    ap.add_argument("--mag-cold", action="store_true", help="with --cold: the mag cold too (--init none)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=JSON",
                    help="a UKFConfig field for this run (e.g. update_damping=4), to compare settings")
    args = ap.parse_args()
    args.config = UKFConfig(**{k: json.loads(v) for k, v in (kv.split("=", 1) for kv in args.set)})
    if args.cold is not None:
        cold(args)
        return
    e_on, e_b, z_on, walls, events = [], [], [], [], Counter()
    held: set[str] = set()
    for seed in range(args.start, args.start + args.seeds):
        sim = simulate("paper", seed)
        batch = run_batch([sim.data]).calibration
        res = replay([sim.data], batch, args.config)
        walls.append(res.wall_s)
        events.update(e["kind"] for e in res.events)
        g = res.calibration.meta["online"]["gauge"]
        held |= {f"{g['sensor']}.{p}.{a}" for p in g["terms"] for a in "xyz"}
        tr = sim.truth.calibration
        eo, eb, zo = [], [], []
        for s in SENSORS:
            for p in PARAMS:
                o = res.calibration.sensor(s).params()[p] - tr.sensor(s).params()[p]
                b = batch.sensor(s).params()[p] - tr.sensor(s).params()[p]
                eo += list(o)
                eb += list(b)
                zo += list(o / np.asarray(res.calibration.sensor(s).sigma[p]))
        e_on.append(eo)
        e_b.append(eb)
        z_on.append(zo)
    e_on, e_b, z_on = np.array(e_on), np.array(e_b), np.array(z_on)
    names = [f"{s}.{p}.{a}" for s in SENSORS for p in PARAMS for a in "xyz"]
    rms_on = np.sqrt((e_on**2).mean(0))
    rms_b = np.sqrt((e_b**2).mean(0))
    print(f"{'parameter':18s} {'rms online':>11s} {'rms batch':>11s} {'ratio':>6s} {'in 3σ':>6s}")
    for i, nm in enumerate(names):
        print(f"{nm:18s} {rms_on[i]:11.3e} {rms_b[i]:11.3e} {rms_on[i] / rms_b[i]:6.2f} "
              f"{np.mean(np.abs(z_on[:, i]) < 3):6.2f}{'  held (gauge)' if nm in held else ''}")
    ratio = rms_on / rms_b
    est = np.array([nm not in held for nm in names])
    print(f"ratio online/batch (RMS over {args.seeds} seeds): median {np.median(ratio):.2f}, max {ratio.max():.2f} "
          f"({names[int(np.argmax(ratio))]}); estimated terms only: median {np.median(ratio[est]):.2f}")
    print(f"coverage (|err| < 3σ): {np.mean(np.abs(z_on) < 3):.3f}; estimated terms: "
          f"{np.mean(np.abs(z_on[:, est]) < 3):.3f}")
    for label, cols in (("all 36 terms", np.ones(len(names), bool)), (f"{int(est.sum())} estimated terms", est)):
        nees = np.sum(np.square(z_on[:, cols]), axis=1)
        lo, hi = chi2.ppf([0.025, 0.975], int(cols.sum()))
        inside = np.mean((nees >= lo) & (nees <= hi))
        print(f"NEES ({label}, per-parameter σ, correlations ignored): mean {nees.mean():.1f}, 95% band "
              f"[{lo:.1f}, {hi:.1f}], mean inside the band: {lo <= nees.mean() <= hi}, seeds inside {inside:.2f}")
    print(f"events: {dict(events) or 'none'}; wall per 309-s session: mean {np.mean(walls):.2f} s")


def cold(args: argparse.Namespace) -> None:
    sensors = ("gyro", "accel", "mag") if args.mag_cold else ("gyro", "accel")
    ok = dict.fromkeys(sensors, 0)
    n = 0
    for seed in range(args.start, args.start + args.seeds):
        sim = simulate("paper", seed)
        d = sim.data.slice_imu(0, int(np.searchsorted(sim.data.t_imu, args.cold)))
        if args.mag_cold:
            init = None  # --init none: the mag too, from its own sphere fit
        else:
            init = run_batch([sim.data]).calibration.replace(gyro=None, accel=None)
        res = replay([d], init, args.config)
        line = [f"seed {seed:2d}"]
        for s in sensors:
            c, t = res.calibration.sensor(s), sim.truth.calibration.sensor(s)
            z = np.concatenate([(c.params()[p] - t.params()[p]) / np.asarray(c.sigma[p]) for p in PARAMS])
            bs = float(np.abs(z[:6]).max())
            ok[s] += bs < 3
            rel = float(np.max(np.asarray(c.sigma["scale"]) / np.abs(c.scale)))
            line.append(f"{s}: max |err|/σ bias+scale {bs:5.2f}, all 12 {np.abs(z).max():5.2f}, "
                        f"NEES {z @ z:6.1f}, scale σ ≤ {100 * rel:.2g} %")
        n += 1
        print(" | ".join(line), flush=True)
    print(f"cold start ({'--init none' if args.mag_cold else 'mag from the batch'}) over the first "
          f"{args.cold:g} s: every bias and scale within 3σ on "
          + ", ".join(f"{ok[s]}/{n} seeds ({s})" for s in sensors))


if __name__ == "__main__":
    main()
