"""Issue 13: diagnose on simulated flights (benchmarks/diag_flight_stats.py has the 20-seed rates) — a few
seeds: clean flights give ``none``, the effects a flight can show are named with their sensor, and what a
flight cannot test is reported as untestable (lever_arm, axis_sign: thrust-driven specific force;
g_sensitivity: one gravity direction at rest; a fixed-wing's time_offset and scale_nonlinearity: no rotation
faster than 0.5 rad/s)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.benchload import benchmark

fs = benchmark("diag_flight_stats")


@pytest.mark.slow
@pytest.mark.parametrize("profile,seed", [("multirotor", 7001), ("fixedwing", 7004), ("fixedwing", 7011)])
def test_clean_flight_verdict_none(profile: str, seed: int) -> None:
    # fixed-wing 7004 read as axis_sign + baseline_inadequate (an extrapolated magnetometer fit) and 7011 as
    # an accelerometer bias_drift of 7150 nats (thrust) before the fixes
    dg, _ = fs.run_one(profile, seed, 300.0, [])
    assert dg.verdict == "none", [(f.effect, f.sensor, f.score) for f in dg.significant]
    u = " ".join(dg.untestable)
    for name in fs.UNTESTABLE:
        assert name in u, (name, dg.untestable)


@pytest.mark.slow
@pytest.mark.parametrize("profile,name,i", [("multirotor", "time_offset", 0), ("multirotor", "bias_drift", 1),
                                            ("fixedwing", "saturation", 2), ("fixedwing", "temperature_bias", 1)])
def test_flight_effect_named_with_sensor(profile: str, name: str, i: int) -> None:
    seed = 7100 + i
    rng = np.random.default_rng(9100 + i)
    clean = fs.simulate(profile, seed, duration=300.0) if name == "saturation" else None
    eff = fs.flight_effect(name, rng, clean)
    dg, _ = fs.run_one(profile, seed, 300.0, [eff])
    assert fs.named(dg, eff.describe()), (eff.spec(), [(f.effect, f.sensor, f.score) for f in dg.significant])


@pytest.mark.slow
def test_fixedwing_time_offset_reported_untestable() -> None:
    rng = np.random.default_rng(9100)
    eff = fs.flight_effect("time_offset", rng, None)
    dg, _ = fs.run_one("fixedwing", 7100, 300.0, [eff])
    assert any(u.startswith("time_offset") and "rotation faster than 0.5 rad/s" in u for u in dg.untestable)
    assert not any(f.effect == "time_offset" for f in dg.significant)


def test_gyro_nonlin_limit_is_the_datasheet_figure() -> None:
    """GYRO_NONLIN_MAX against its definition, computed here by a least-squares straight line: raw·(1 + c|raw|)
    over ±250 °/s deviates from its best-fit line by 0.2 % of full scale (MPU-6000's stated nonlinearity)."""
    from onlinecal.diagnose.adequacy import GYRO_NONLIN_MAX

    F = np.radians(250.0)
    x = np.linspace(-F, F, 200001)
    y = x * (1 + GYRO_NONLIN_MAX * np.abs(x))
    fit = np.polyval(np.polyfit(x, y, 1), x)
    assert np.max(np.abs(y - fit)) / F == pytest.approx(0.002, rel=1e-3)


@pytest.mark.slow
def test_multirotor_gyro_nonlinearity_reported_unresolvable() -> None:
    # the multirotor's gentle turns resolve the coefficient to ~2e-2 per rad/s (5 σ): a hidden 5e-3 is
    # reported as beyond what the data can test, not missed in silence or named by chance
    eff = fs.flight_effect("scale_nonlinearity", np.random.default_rng(9103), None)
    dg, _ = fs.run_one("multirotor", 7103, 300.0, [eff])
    why = [u for u in dg.untestable if u.startswith("scale_nonlinearity (gyro)")]
    assert why and "datasheet" in why[0], dg.untestable
    assert not any(f.effect == "scale_nonlinearity" and f.sensor == "gyro" for f in dg.significant)
