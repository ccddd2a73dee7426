"""diagnose: speed on a 5-minute 100 Hz session and detection rates over many seeds.

For each effect, ``--seeds`` sessions with the effect hidden (drawn by ``random_effect`` per seed: sensor,
axis, magnitude in the spec's test range); a session counts as detected when the verdict is the effect with
the right sensor (and axis where it has one) and its main parameter within 20 %. Clean sessions count
``none`` verdicts. Prints the table (copy into docs/benchmarks-diagnose.md).

    PYTHONPATH=. python benchmarks/bench_diagnose.py [--seeds 6] [--clean 40] [--flight] [--cli-flight]

``--cli-flight`` times the user's command ``python -m onlinecal diagnose F.bin`` on a simulated 10-minute
200 Hz multirotor flight twice in one run, in child processes (CPU = the child's user + system time): with
the library's default BLAS threading (``ONLINECAL_DIAGNOSE_THREADED=1``, the path before the one-thread
limit) and with diagnose's small solves on one BLAS thread (the default), and checks that both JSON outputs
agree. Add ``--cli-flight-only`` to skip everything else.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
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


def _floats(x: object, path: str = "") -> list[tuple[str, float]]:
    """Every float of a diagnose JSON with its path, less the timings (wall-clock figures differ by nature)."""
    if isinstance(x, dict):
        return [v for k in sorted(x) if k not in ("timing", "timing_s", "wall_s")
                for v in _floats(x[k], f"{path}/{k}")]
    if isinstance(x, list):
        return [v for i, e in enumerate(x) for v in _floats(e, f"{path}[{i}]")]
    return [(path, float(x))] if isinstance(x, float) else []


def _child(cmd: list[str], env: dict[str, str]) -> tuple[float, float]:
    """(wall s, CPU s of the child: user + system) of one command."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    rc = subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode
    if rc not in (0, 4):  # 4: a degraded result (this flight's magnetometer coverage), still a full diagnosis
        raise SystemExit(f"{' '.join(cmd)}: exit {rc}")
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def cli_flight() -> None:
    """``onlinecal diagnose`` on the paper session and a 10-minute 200 Hz multirotor flight: default BLAS
    threading (before) vs one thread (now), CPU and wall, and how far the two JSON outputs differ."""
    py = [sys.executable, "-m", "onlinecal"]
    env = dict(os.environ)
    with tempfile.TemporaryDirectory() as td:
        logs = {"paper session (simulated, 100 Hz)": ["--profile", "paper"],
                "10-min 200 Hz multirotor flight": ["--profile", "multirotor", "--duration", "600", "--rate", "200"]}
        for i, (label, sim_args) in enumerate(logs.items()):
            f = os.path.join(td, f"log{i}.bin")
            subprocess.run(py + ["simulate", *sim_args, "--out", f], env=env, check=True, stdout=subprocess.DEVNULL)
            _child(py + ["diagnose", f, "--json", os.path.join(td, "warm.json")], env)  # numba and page caches
            out = {}
            for name, thr in (("default BLAS threads (before)", "1"), ("one BLAS thread (now)", "0")):
                js = os.path.join(td, f"{i}-{thr}.json")
                load = os.getloadavg()[0]
                wall, cpu = _child(py + ["diagnose", f, "--json", js], {**env, "ONLINECAL_DIAGNOSE_THREADED": thr})
                out[name] = json.load(open(js))
                print(f"onlinecal diagnose, {label}, {name:30s}: {cpu:6.1f} s CPU, {wall:6.1f} s wall "
                      f"(load average {load:.1f} on {os.cpu_count()} cores)")
            a, b = out.values()
            fa, fb = _floats(a), _floats(b)
            same = a["verdict"] == b["verdict"] and [p for p, _ in fa] == [p for p, _ in fb]
            same &= [(f["effect"], f["sensor"], f["axis"], f["significant"]) for f in a["findings"]] == \
                [(f["effect"], f["sensor"], f["axis"], f["significant"]) for f in b["findings"]]
            rel = [(abs(x - y) / max(abs(x), abs(y)), p) for (p, x), (_, y) in zip(fa, fb, strict=False)
                   if np.isfinite(x) and np.isfinite(y) and max(abs(x), abs(y)) > 1e-4]  # near-zero: see below
            absd = max((abs(x - y) for (_, x), (_, y) in zip(fa, fb, strict=False)
                        if np.isfinite(x) and np.isfinite(y) and max(abs(x), abs(y)) <= 1e-4), default=0.0)
            worst = max(rel, default=(0.0, ""))
            sig = [r for r in rel if any(r[1].startswith(f"/findings[{j}]") for j, f in enumerate(a["findings"])
                                         if f["significant"])]
            print(f"  verdict {a['verdict']} / {b['verdict']}; findings (effect, sensor, axis, significant) "
                  f"{'identical' if same else 'DIFFER'}; {len(fa)} numbers; worst relative difference "
                  f"{worst[0]:.1e} ({worst[1]}); in significant findings {max(sig, default=(0.0, ''))[0]:.1e}; "
                  f"numbers ≤ 1e-4 in size differ by ≤ {absd:.1e} absolute; "
                  f"above 1e-8: {sum(r > 1e-8 for r, _ in rel)}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--clean", type=int, default=40)
    ap.add_argument("--flight", action="store_true", help="also time a 10-minute simulated flight")
    ap.add_argument("--cli-flight", action="store_true",
                    help="also time `onlinecal diagnose` on a 10-minute 200 Hz flight, before/after")
    ap.add_argument("--cli-flight-only", action="store_true", help="only the --cli-flight timing")
    a = ap.parse_args()
    if a.cli_flight or a.cli_flight_only:
        cli_flight()
        if a.cli_flight_only:
            return
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
