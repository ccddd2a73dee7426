"""diagnose on data that cannot carry an effect, or on a baseline that is wrong: the adequacy check names the
invariant the paper model does not meet before any effect; a 1 Hz log gets no verdict; linear acceleration
(a flight's thrust) is not read as a lever arm or an axis flip; temperature rising with time and a drifting
bias are reported as inseparable; the significance bar covers the null's spread.

The truths here come from outside the code under test: the simulator's hidden settings and a baseline
broken on purpose (a gyro scale of 0.2, as the flight issue's cold start gave 0.17).
"""

from __future__ import annotations

import numpy as np
import pytest

from onlinecal.diagnose import diagnose
from onlinecal.diagnose.core import Z_SPREAD, _threshold
from onlinecal.model import SensorCalibration
from onlinecal.sim import simulate
from onlinecal.sim.effects import TemperatureBias


def test_threshold_covers_the_null_spread() -> None:
    # BIC ½·3·ln(1e4) = 13.8, null + margin = 15: a null spread of 10 nats must lift the bar to 3σ = 30
    assert _threshold(3, 10_000, 0.0, 10.0) == pytest.approx(Z_SPREAD * 10.0)
    assert _threshold(3, 10_000, 0.0, 0.0) == pytest.approx(15.0)


def test_one_hertz_log_gets_no_findings() -> None:
    """140 samples at 1 Hz (a telemetry log): no effect and no adequacy verdict; the untestable list states
    the rate each check needs and the rate this log has."""
    s = simulate("paper", 3, imu_rate=1.0, mag_rate=1.0, duration=140.0)
    assert s.data.n_imu <= 141
    d = diagnose([s.data], check=False, ukf=False)
    assert d.verdict == "none" and not d.significant
    text = " ".join(d.untestable)
    for eff in ("g_sensitivity", "bias_drift", "scale_nonlinearity", "lever_arm", "baseline adequacy"):
        assert eff in text
    assert "1 Hz" in text


@pytest.mark.slow
def test_wrong_gyro_scale_is_the_first_finding_not_an_effect() -> None:
    """A baseline whose gyro matrix is 0.2× the truth: the accelerometer's and the magnetometer's kinematic
    invariants both fail against the gyro, so the first finding names the gyro; no effect is significant."""
    s = simulate("paper", 5)
    tr = s.truth.calibration
    assert tr.gyro is not None
    bad = tr.replace(gyro=SensorCalibration(tr.gyro.bias, tr.gyro.matrix * 0.2, {}))
    d = diagnose([s.data], calibration=bad, check=False, ukf=False)
    assert d.verdict == "baseline_inadequate"
    first = d.significant[0]
    assert first.sensor == "gyro" and first.parameters["rms_ratio"] > 10
    assert all(f.effect == "baseline_inadequate" for f in d.significant), [f.effect for f in d.significant]
    assert d.baseline["adequacy"]["adequate"] is False
    assert set(d.baseline["adequacy"]["dropped_channels"]) >= {"ka_x", "km_x"}


@pytest.mark.slow
def test_clean_paper_session_baseline_is_adequate() -> None:
    s = simulate("paper", 7)
    d = diagnose([s.data], check=False, ukf=False)
    adq = d.baseline["adequacy"]
    assert adq["adequate"] and not adq["dropped_channels"] and adq["linear_acceleration"] is None
    ratios = [c["ratio"] for c in adq["channels"].values()]
    assert max(ratios) < 2.0, adq["channels"]


@pytest.mark.slow
def test_flight_thrust_is_not_a_lever_arm_or_axis_flip() -> None:
    """A simulated flight (thrust: |a| − g of ~1.6 m/s² RMS in motion) from the bench calibration: the
    accelerometer's kinematic channels are set aside as linear acceleration and nothing is significant."""
    s = simulate("flight", 3, duration=300.0)
    d = diagnose([s.data], calibration=s.truth.calibration, check=False, ukf=False)
    assert d.verdict == "none", [(f.effect, f.sensor, f.score, f.threshold) for f in d.significant]
    la = d.baseline["adequacy"]["linear_acceleration"]
    assert la is not None and la["a_norm_rms_m_s2"] > 0.5
    assert any("linear acceleration" in u and "lever_arm" in u for u in d.untestable)


@pytest.mark.slow
def test_temperature_rising_with_time_and_drift_are_reported_inseparable() -> None:
    """A gyro temperature coefficient while the temperature rises almost linearly (τ = 3000 s on a 309-s
    session): the data cannot tell it from a drifting bias, and the finding says so."""
    s = simulate("paper", 6, effects=[TemperatureBias(sensor="gyro", axis="y", coeff=5e-4, rise=100.0,
                                                      tau=3000.0)])
    d = diagnose([s.data], check=False, ukf=False)
    top = d.significant[0]
    assert top.effect in ("temperature_bias", "bias_drift") and top.sensor == "gyro"
    other = {"temperature_bias": "bias_drift", "bias_drift": "temperature_bias"}[top.effect]
    assert top.parameters.get("inseparable_from") == other
    assert "cannot be told apart" in top.evidence


@pytest.mark.slow
def test_clean_sessions_false_alarm_rate_with_the_spread_bar() -> None:
    """The documented false-alarm rate: ≤ 1 of 10 clean paper sessions has a significant finding (the bar
    is at least 3 standard deviations of the null's block-wise gain)."""
    hits = []
    for s in range(10):
        d = diagnose([simulate("paper", 300 + s).data], check=False, seed=s, ukf=False)
        hits.append(d.verdict)
        for f in d.findings:
            assert np.isfinite(f.threshold)
    assert sum(v != "none" for v in hits) <= 1, hits
