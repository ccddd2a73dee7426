"""Issue 13: the UKF stage of diagnose on the imu_tk Xsens session — the extension (full 3×3 g-sensitivity)
must not make the filter's NIS worse than the baseline's, and the baseline filter must be consistent at all.

The cause of the NIS ≈ 7 that the findings showed: the batch was fitted to the session's local gravity
(9.81744 m/s², imu_tk's value) and the UKF stage ran the filter with the standard 9.80665, so every
accelerometer update carried a 0.011 m/s² norm error (several times the Xsens accelerometer's noise).
"""

from __future__ import annotations

import numpy as np
import pytest

from onlinecal.diagnose import online
from onlinecal.sim import simulate


def test_ukf_stage_runs_the_filter_on_the_diagnosis_gravity(monkeypatch) -> None:
    """run_ukf hands its g to the filter (the accelerometer update's |a| = g)."""
    import onlinecal.ukf as ukf

    seen: list[float] = []
    real = ukf.replay

    def spy(data, cal, cfg=None, *a, **k):  # type: ignore[no-untyped-def]
        seen.append(cfg.gravity)
        return real(data, cal, cfg, *a, **k)

    monkeypatch.setattr(ukf, "replay", spy)
    sim = simulate("paper", 3, duration=40.0)
    r = online.run_ukf([sim.data], sim.truth.calibration, g=9.81744)
    assert "error" not in r, r
    assert seen == [9.81744]


@pytest.mark.slow
def test_xsens_extension_does_not_worsen_the_nis(data_dir) -> None:
    from onlinecal.diagnose import diagnose
    from onlinecal.io import read_log

    x = read_log(data_dir / "imutk-xsens" / "xsens-session.csv")
    d = diagnose([x], g=9.81744, check=False)
    assert d.verdict == "g_sensitivity"
    before, after = d.baseline["ukf"], d.ukf_extended
    assert after is not None and "error" not in after, after
    assert after["corrected"] == ["g_sensitivity"]
    # the filter on the baseline is consistent on average (the health band of a mean NIS), and the
    # extension lowers it rather than only not raising it
    assert 1.5 < before["nis_mean"] < 6.0, before
    assert after["nis_mean"] <= before["nis_mean"], (before["nis_mean"], after["nis_mean"])
    # what an extension removes is model error: windows whose NIS is above the band (innovations larger than
    # R says) must not grow. Windows below it (R larger than the innovations) are the noise model's, not the
    # extension's (session 10: 23 of 44–45 below, none above, with the hand's turns read as noise; before the
    # block-mean noise 17 → 10 above, when the rests' excess noise still read as model error; docs/findings.md)
    assert after["above_band"] <= before["above_band"] + 1e-12, (before["above_band"], after["above_band"])
    assert before["above_band"] <= 0.15, before  # the baseline is consistent from above: 3 of 49 (17 of 44 before)
    # and from below: the noise monitor no longer reads the hand's turns as noise (session 11; docs/flight.md):
    # NIS 2.32 with 20 of 44 windows below the band before, 2.90 with 11 of 49 after. Since session 19 a motion
    # block at a geometry already learned holds the accelerometer's terms and its NIS stays out of the windows
    # (.learning: a held look's innovation repeats the held terms' error, not a white sample): 2.53 with 14 of 45
    # below (learning angle 0, as before: 2.91; 3°: 2.64)
    assert 2.4 < before["nis_mean"] < 3.4, before
    assert before["outside_band"] - before["above_band"] <= 0.33, before
    assert "ukf_guard" not in d.baseline
    assert d.calibration.extensions.get("g_sensitivity") is not None
    top = d.significant[0]
    assert np.isfinite(top.gain["ukf_nis_after"]) and top.gain["ukf_nis_after"] <= top.gain["ukf_nis_before"]


def test_extension_the_filter_cannot_carry_is_reported_and_not_applied(monkeypatch) -> None:
    """Issue 13 item 4: where the extended filter's NIS is worse than the baseline's (beyond 5 %), the
    extensions are left out of the calibration the user gets, the findings are marked ``applied: False`` and
    the guard says why. The filter runs are replaced by two fixed outcomes (the guard's logic is under test,
    not the filter)."""
    from onlinecal.diagnose import diagnose
    from onlinecal.sim.effects import make_effect

    def fake(logs, cal, extensions=None, g=9.80665):  # type: ignore[no-untyped-def]
        m = 3.0 if not extensions else 4.5
        return {"nis_mean": m, "outside_band": 0.1, "band": [2.3, 3.9], "events": 0, "corrected": [],
                "extra_states": [], "sensors": {"accel": {"nis_mean": m, "outside_band": 0.1}}}

    monkeypatch.setattr(online, "run_ukf", fake)
    sm = simulate("paper", 6, effects=[make_effect("g_sensitivity", axis="all", coeff=3e-4)])
    d = diagnose([sm.data], check=False)
    assert d.verdict == "g_sensitivity"
    assert "g_sensitivity" not in d.calibration.extensions
    assert "not applied" in d.baseline["ukf_guard"]
    assert d.significant[0].parameters["applied"] is False
