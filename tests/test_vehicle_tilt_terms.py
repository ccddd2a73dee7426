"""In vehicle motion without a magnetometer in the update, the gyro's x/y scales are held (session 20).

What was wrong: on a cold fixed-wing flight the gyro's x and y scales ended 0.68–0.92 for a truth of 1.14 — pulled
*away* from the truth, starting from the prior's 1.0 — with σ 0.13–0.15 (0.7 of the prior: reported
"undetermined", so `export` refused them, but the JSON carried 0.73 ± 0.15 where the truth is 1.14). Over 12 seeds
the mean z was −2.1 (x) and −2.2 (y); a multirotor's −1.1. The cause: in a coordinated turn the specific force
stays along body z (a multirotor's thrust too, tilted to accelerate), so the accelerometer reads "level" while the
gyro integrates the bank; a lower roll scale integrates less bank and agrees better. The vehicle model's σ_v bounds
how far, not the direction. With the accelerometer uninformative in flight (σ_v 30 m/s²) the same flight ended at
1.03/1.01, which located it in that update. The truth here: the simulator's calibration, flown through the
coordinated-turn dynamics (onlinecal.sim.flight), not the filter's model."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from closure import MARG, closure

from onlinecal.ukf.layout import NAMES
from onlinecal.ukf.state import StateLayout

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


def _held(lay: StateLayout, vehicle: bool, gyro_tilt: bool) -> set[str]:
    return {n for n, h in zip(lay.names, lay.consider_mask(vehicle, False, False, gyro_tilt), strict=True) if h}


def test_the_mask_holds_the_three_scales_only_where_asked() -> None:
    lay = StateLayout()
    held = _held(lay, True, True)
    scales = {"gyro.scale.x", "gyro.scale.y", "gyro.scale.z"}
    assert scales <= held and "gyro.bias.x" not in held and "gyro.alpha.z" not in held
    assert not scales & _held(lay, True, False)
    assert not scales & _held(lay, False, False)
    assert len(NAMES) <= lay.n


def test_only_a_vibrating_vehicle_without_the_magnetometer_holds_them() -> None:
    """A hand is a vehicle by the gate's drops, not by vibration: its x/y scales stay learned in motion (held, MARG's
    cold replay ended at gyro.scale.y 0.75 ± 0.16 against 0.985 ± 0.057, its y-turn closure 34.6° → 171°)."""
    from onlinecal.ukf import OnlineCalibrator
    from onlinecal.ukf.fastpath import motion_consider
    from onlinecal.ukf.vehicle import VIBRATION_REASON

    cal = OnlineCalibrator(None)
    ix = cal.lay.names.index("gyro.scale.x")
    assert not motion_consider(cal, False)[ix]  # no vehicle
    cal._vehicle.active, cal._vehicle.reason = True, "the accelerometer's gate dropped 6 of the last 20 moving blocks"
    assert not motion_consider(cal, False)[ix]  # a hand
    cal._vehicle.reason = VIBRATION_REASON + " 0.92 m/s² per sample"
    assert motion_consider(cal, False)[ix] and not motion_consider(cal, True)[ix]


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_a_cold_fixed_wing_leaves_its_roll_and_pitch_scales_where_the_prior_put_them(seed: int) -> None:
    """Seed 0 ended at z −2.25 (x) and −2.73 (y) before; held, −0.69 and −0.78: the prior mean 1.0's own offset
    from the truth 1.14 at σ ≈ 0.19. No term beyond 3σ."""
    from flight_stats import NAMES as TERMS
    from flight_stats import run_flight

    r = run_flight("fixedwing", seed, "cold", 10.0, gps=True)
    z = dict(zip(TERMS, r.z, strict=True))
    assert abs(z["gyro.scale.x"]) < 1.5 and abs(z["gyro.scale.y"]) < 1.5, (z["gyro.scale.x"], z["gyro.scale.y"])
    assert np.all(np.abs(r.z) < 3.0), (np.abs(r.z).max(), TERMS[int(np.argmax(np.abs(r.z)))])
    assert r.verdict == "ok", r.reasons


@pytest.mark.slow
def test_a_hand_held_cold_replay_still_closes_its_turns(tmp_path: Path) -> None:
    """Out of fit, on measured data (MARG set 1, all 15 files replayed cold; ../shared/tools/gyro_closure.py on the
    three 360° rotations): the hand is a vehicle by the gate's drops, not by vibration, so its x/y scales are learned
    in motion as before — 18.3°, 34.6°, 17.8° over ~810° each. Held there (this change's first form), the y turn
    closed at 171° (gyro.scale.y 0.75)."""
    import subprocess

    logs = sorted(MARG.glob("*.csv"))
    out = tmp_path / "cold.json"
    p = subprocess.run([sys.executable, "-m", "onlinecal", "-q", "replay", *map(str, logs), "--init", "none", "--json",
                        str(out)], capture_output=True, text=True, timeout=600)
    assert p.returncode in (0, 4), p.stderr[-2000:]
    errs = closure(out, [f for f in logs if f.name.startswith("rotate-360")])
    assert len(errs) == 3 and max(errs) < 60.0, errs


@pytest.mark.slow
@pytest.mark.parametrize("seed", [5, 7])
def test_a_fixed_wing_without_magnetometer_does_not_learn_its_yaw_scale_from_the_turns(seed: int, monkeypatch) -> None:
    """Session 22: the yaw scale is pulled too. A fixed-wing flight started from its truth for everything but the
    gyro's z scale (σ 0.2 about the truth's own value) and the magnetometer (cold: no heading is held, the
    accelerometer is the only attitude reference in the air). Learned in that motion, the z scale ended 3.09, 3.35
    and 7.38σ off on seeds 4, 5 and 7 of 20 (σ 0.02–0.04, "determined"; mean z +1.3 over the 20: pulled high, as the
    x/y scales were pulled low), a multirotor's 1 of 20 at −3.02σ. A yaw-scale error turns the heading in proportion
    to the turn; with no heading reference the only thing it moves is the tilt a coordinated turn's specific force
    hides — the x/y scales' case. Held there too: within 3σ on all 20 of each profile, undetermined (its σ stays
    near the prior: the flight has no reference for the heading). The truth: the simulator's calibration, flown
    through the coordinated-turn dynamics (onlinecal.sim.flight)."""
    import flight_stats as fs

    from onlinecal.model import Calibration

    truth_start = fs.truth_start

    def start(truth: Calibration) -> Calibration:
        c = truth_start(truth).replace(mag=None)
        g = c.sensor("gyro")
        return c.replace(gyro=g.with_sigma({"bias": [0.2] * 3, "scale": [0.005, 0.005, 0.2], "alpha": [0.005] * 3,
                                            "xi": [0.005] * 3}))

    monkeypatch.setattr(fs, "truth_start", start)
    r = fs.run_flight("fixedwing", seed, "truth", 10.0, gps=True)
    z = dict(zip(fs.NAMES, r.z, strict=True))
    assert abs(z["gyro.scale.z"]) < 3.0, z["gyro.scale.z"]
    assert np.all(np.abs(r.z) < 3.0), (np.abs(r.z).max(), fs.NAMES[int(np.argmax(np.abs(r.z)))])
    assert not r.determined[fs.NAMES.index("gyro.scale.z")]  # σ above half its prior: reported undetermined
