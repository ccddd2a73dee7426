"""Issue 13: two effects at once on the paper session — both found in 4 of 4 pairs (effects drawn at random
per pair by ``random_effect``, the saturation on the gyro: an accelerometer rail at 0.6–0.9 × its peak lies
below 1 g, so most static poses read clipped gravity and no accelerometer baseline can be fitted).

temperature_bias with bias_drift: the simulator's temperature rises steadily with time (rise 15 °C, τ 90 s),
where the two are inseparable; a joint finding (one selected, ``inseparable_from`` naming the other, the
evidence saying "cannot be told apart") names both and counts as finding both — a choice between them
would not.
"""

from __future__ import annotations

import numpy as np
import pytest

from onlinecal.diagnose import diagnose
from onlinecal.sim import simulate
from onlinecal.sim.effects import make_effect, random_effect

PAIRS = [("saturation", "scale_nonlinearity"), ("bias_drift", "temperature_bias"),
         ("g_sensitivity", "time_offset"), ("lever_arm", "temperature_bias")]


def _draw(name: str, rng: np.random.Generator, clean) -> object:  # type: ignore[no-untyped-def]
    if name == "saturation":
        return make_effect(name, sensor="gyro",
                           limit=float(rng.uniform(0.6, 0.9)) * float(np.abs(clean.data.gyro).max()))
    return random_effect(name, rng, clean)


def _named(dg, e: dict) -> bool:  # type: ignore[no-untyped-def]
    for f in dg.significant:
        same_sensor = e["effect"] in ("lever_arm", "g_sensitivity") or f.sensor == e["sensor"]
        if f.effect == e["effect"] and same_sensor:
            return True
        if f.parameters.get("inseparable_from") == e["effect"] and same_sensor:
            assert "cannot be told apart" in f.evidence
            return True
    return False


@pytest.mark.slow
@pytest.mark.parametrize("i", range(4))
def test_two_effects_both_found(i: int) -> None:
    a, b = PAIRS[i]
    seed = 1300 + i
    rng = np.random.default_rng(13000 + i)
    clean = simulate("paper", seed)
    effs = [_draw(a, rng, clean), _draw(b, rng, clean)]
    sm = simulate("paper", seed, effects=effs)
    dg = diagnose([sm.data], check=False, ukf=False, seed=seed)
    got = [(f.effect, f.sensor, f.axis, round(f.score, 1), f.parameters.get("inseparable_from"))
           for f in dg.significant]
    for e in sm.truth.effects:
        assert _named(dg, e), (e, got)


@pytest.mark.slow
def test_steady_temperature_rise_gives_a_joint_finding_not_a_choice() -> None:
    """Only a gyro temperature_bias, temperature rising steadily (τ long against the session): whichever of
    temperature_bias / bias_drift is selected carries the other as inseparable, and the other is not also
    reported as a separate significant effect on the same sensor."""
    e = make_effect("temperature_bias", sensor="gyro", axis="all", coeff=6e-4, rise=20.0, tau=600.0)
    sm = simulate("paper", 1305, effects=[e])
    dg = diagnose([sm.data], check=False, ukf=False, seed=1305)
    sig = [f for f in dg.significant if f.effect in ("temperature_bias", "bias_drift") and f.sensor == "gyro"]
    assert len(sig) == 1, [(f.effect, f.sensor) for f in dg.significant]
    other = "bias_drift" if sig[0].effect == "temperature_bias" else "temperature_bias"
    assert sig[0].parameters.get("inseparable_from") == other
    assert "cannot be told apart" in sig[0].evidence
