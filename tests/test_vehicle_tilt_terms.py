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

from onlinecal.ukf.layout import NAMES
from onlinecal.ukf.state import StateLayout

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


def test_the_mask_holds_the_roll_and_pitch_scales_only_without_a_magnetometer() -> None:
    lay = StateLayout()
    held = {n for n, h in zip(lay.names, lay.consider_mask(True, False, False, mag_in=False), strict=True) if h}
    assert {"gyro.scale.x", "gyro.scale.y"} <= held and "gyro.scale.z" not in held and "gyro.bias.x" not in held
    with_mag = {n for n, h in zip(lay.names, lay.consider_mask(True, False, False, mag_in=True), strict=True) if h}
    assert not {"gyro.scale.x", "gyro.scale.y"} & with_mag
    not_vehicle = {n for n, h in zip(lay.names, lay.consider_mask(False, False, False, mag_in=False), strict=True) if h}
    assert not {"gyro.scale.x", "gyro.scale.y"} & not_vehicle  # a platform's or a hand's accelerometer is gravity
    assert len(NAMES) <= lay.n


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_a_cold_fixed_wing_leaves_its_roll_and_pitch_scales_where_the_prior_put_them(seed: int) -> None:
    """Seed 0 ended at z −2.25 (x) and −2.73 (y) before; held, −0.69 and −0.78: the prior mean 1.0's own offset
    from the truth 1.14 at σ ≈ 0.19. No term beyond 3σ, the z scale still learned."""
    from flight_stats import NAMES as TERMS
    from flight_stats import run_flight

    r = run_flight("fixedwing", seed, "cold", 10.0, gps=True)
    z = dict(zip(TERMS, r.z, strict=True))
    assert abs(z["gyro.scale.x"]) < 1.5 and abs(z["gyro.scale.y"]) < 1.5, (z["gyro.scale.x"], z["gyro.scale.y"])
    assert np.all(np.abs(r.z) < 3.0), (np.abs(r.z).max(), TERMS[int(np.argmax(np.abs(r.z)))])
    assert r.verdict == "ok", r.reasons
