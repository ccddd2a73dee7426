"""diagnose on simulated flights (issue 13): false alarms on clean flights and detection of the effects a
flight can show, per vehicle profile.

For each profile (``multirotor``, ``fixedwing``): ``--clean`` clean seeds (a session counts when the verdict is
``none``), and for each flight-testable effect ``--seeds`` seeds with it hidden (a session counts when a
significant finding names the effect with the right sensor; for temperature_bias and bias_drift, a finding of
the other one marked ``inseparable_from`` this one also counts: the flight's temperature rises with time, so
the two are one joint finding, reported as such).

Which effects a flight can show, from the physics (the same list is in docs/benchmarks-diagnose.md):

* bias_drift (gyro): the gyro is compared with the magnetometer's rotation in flight and with the rests;
* temperature_bias (gyro): the board warms in flight (the simulator's temperature rises with time), so it is
  testable but joint with bias_drift;
* saturation (gyro or accel): a rail is seen in the raw samples whatever the motion;
* scale_nonlinearity (gyro): turns at several rates, gyro against the magnetometer's rotation — where the
  rates resolve the largest coefficient a datasheet allows (1.8e-3 per rad/s) at 5σ; a multirotor's gentle
  turns do not (σ ≈ 4e-3), so there it is checked to be reported as untestable, not counted;
* time_offset (mag): the magnetometer's field turns with the gyro's rate; a gyro offset is the same lag with
  the opposite sign (the accelerometer, the only third reference, carries thrust), so the mag is the one;
* not testable in flight: lever_arm and axis_sign (accel) — the accelerometer measures thrust-driven specific
  force, not gravity, in motion; g_sensitivity — the specific force is nearly constant along body z (thrust ≈
  weight), so a G column along z is a bias and the x/y columns see ~1 m/s² of drag; rests on the ground are
  in one gravity direction. These are checked to be reported as untestable, not counted.

    PYTHONPATH=. nice python benchmarks/diag_flight_stats.py [--clean 20] [--seeds 5] [--duration 300]

Prints one line per session as it goes, then the table.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import numpy as np

from onlinecal.diagnose import diagnose
from onlinecal.sim import simulate
from onlinecal.sim.effects import make_effect

FLIGHT_EFFECTS = ("bias_drift", "temperature_bias", "saturation", "scale_nonlinearity", "time_offset")
UNTESTABLE = ("lever_arm", "axis_sign", "g_sensitivity")


def flight_effect(name: str, rng: np.random.Generator, clean: Any) -> Any:
    """An effect of the spec's test size on the sensor a flight can show it on (module docstring)."""
    sign = float(rng.choice([-1.0, 1.0]))
    axis = str(rng.choice(["x", "y", "z", "all"]))
    if name == "bias_drift":
        return make_effect(name, sensor="gyro", axis=axis, density=float(rng.uniform(5e-5, 3e-4)))
    if name == "temperature_bias":
        return make_effect(name, sensor="gyro", axis=axis, coeff=sign * float(rng.uniform(2e-4, 1e-3)))
    if name == "saturation":
        sensor = str(rng.choice(["gyro", "accel"]))
        raw = clean.data.gyro if sensor == "gyro" else clean.data.acc
        return make_effect(name, sensor=sensor, limit=float(rng.uniform(0.6, 0.9)) * float(np.abs(raw).max()))
    if name == "scale_nonlinearity":
        return make_effect(name, sensor="gyro", axis=axis, coeff=float(rng.uniform(1e-3, 5e-3)))
    if name == "time_offset":
        return make_effect(name, sensor="mag", seconds=sign * float(rng.uniform(0.01, 0.08)))
    raise ValueError(name)


def named(dg: Any, eff: dict[str, Any]) -> bool:
    """A significant finding names the effect with its sensor (or the joint temperature/drift finding)."""
    for f in dg.significant:
        if f.sensor != eff["sensor"]:
            continue
        if f.effect == eff["effect"]:
            return True
        if f.parameters.get("inseparable_from") == eff["effect"]:
            return True
    return False


def run_one(profile: str, seed: int, duration: float, effects: list[Any]) -> tuple[Any, float]:
    sm = simulate(profile, seed, duration=duration, effects=effects)
    t0 = time.process_time()
    dg = diagnose([sm.data], check=False, ukf=False, seed=seed)
    return dg, time.process_time() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--profiles", default="multirotor,fixedwing")
    ap.add_argument("--clean", type=int, default=20)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--effects", default=",".join(FLIGHT_EFFECTS))
    a = ap.parse_args()
    rows: list[tuple[str, str, int, int, int, float]] = []
    for prof in a.profiles.split(","):
        nones, cpu, untest_ok = 0, [], 0
        for s in range(a.clean):
            seed = 7000 + s
            dg, c = run_one(prof, seed, a.duration, [])
            cpu.append(c)
            nones += dg.verdict == "none"
            u = " ".join(dg.untestable)
            untest_ok += all(k in u for k in UNTESTABLE)
            sig = [(f.effect, f.sensor, f.axis, round(f.score, 1), round(f.threshold, 1)) for f in dg.significant]
            print(f"{prof} clean seed {seed}: verdict {dg.verdict} {sig} cpu {c:.1f} s", flush=True)
        rows.append((prof, "none (clean)", a.clean, nones, 0, float(np.mean(cpu))))
        print(f"{prof}: untestable list names {', '.join(UNTESTABLE)} in {untest_ok}/{a.clean}", flush=True)
        for name in a.effects.split(","):
            hits, unt, cpu = 0, 0, []
            for s in range(a.seeds):
                seed = 7100 + s
                rng = np.random.default_rng(9100 + s)
                clean = simulate(prof, seed, duration=a.duration) if name == "saturation" else None
                eff = flight_effect(name, rng, clean)
                dg, c = run_one(prof, seed, a.duration, [eff])
                cpu.append(c)
                ok = named(dg, eff.describe())
                hits += ok
                blocked = any(u.startswith(name) for u in dg.untestable)
                unt += blocked
                found = [(f.effect, f.sensor, f.axis, round(f.score, 1)) for f in dg.significant]
                what = "named" if ok else "untestable (reported)" if blocked else "MISSED"
                print(f"{prof} {eff.spec()} seed {seed}: {what}; verdict {dg.verdict} {found} cpu {c:.1f} s",
                      flush=True)
            rows.append((prof, name, a.seeds, hits, unt, float(np.mean(cpu))))
    print()
    print(f"flights of {a.duration:.0f} s at 100 Hz (simulate defaults), diagnose without the UKF stage")
    print("ok: verdict none (clean) or the effect named with its sensor; untestable: the effect is in the "
          "diagnosis' untestable list (its data requirement not met)")
    print(f"{'profile':11s} {'effect':20s} {'sessions':>8} {'ok':>4} {'untestable':>10} {'mean CPU s':>10}")
    for prof, name, n, k, nu, c in rows:
        print(f"{prof:11s} {name:20s} {n:8d} {k:4d} {nu:10d} {c:10.1f}")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
