"""On a thrust-borne vehicle the magnetometer's soft iron is held in motion (session 23).

What was wrong: flights started from their truth but for the magnetometer, whose terms were given the σ its cold
sphere fit gives (UKFConfig.mag_fit_sigma: bias 6 % of the field, scale 15 %, alpha 0.05 rad, xi 0.035 rad — the
start the filter takes where a flight's field sweeps enough directions for the fit), ended with terms confidently
wrong: over 20 seeds the fixed-wing had 6 seeds with a term beyond 3σ that the output called determined
(mag.scale.z −20.0σ on seed 19; gyro scales +3.1…+3.9σ), the multirotor 3 (gyro.scale.y −5.6σ on seed 7), every
health verdict "ok". Widening one sensor's group at a time found the same through the attitude: mag.bias.z −27σ with
the gyro's terms wide, accel.bias.x −4.5σ with the accelerometer's. In flight nothing holds the attitude still
while the field turns (the accelerometer measures thrust; the attitude is the gyro's integral with its own scales),
so a soft-iron error, a tilt error and a gyro scale error explain the same readings. Held there (the bias, the hard
iron, still learned in flight, as the autopilots' own in-flight learning does): worst 2.6σ over the 240 flights of
those probes. The truth: the simulator's calibration, flown through the vehicle dynamics (onlinecal.sim.flight)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from onlinecal.ukf.state import StateLayout

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

SOFT = {f"mag.{p}.{a}" for p in ("scale", "alpha", "xi") for a in "xyz"}


def test_the_mask_holds_the_soft_iron_and_not_the_hard_iron() -> None:
    lay = StateLayout()
    held = {n for n, h in zip(lay.names, lay.consider_mask(True, False, False, False, True), strict=True) if h}
    assert SOFT <= held and not {"mag.bias.x", "mag.bias.y", "mag.bias.z", "dip"} & held
    plain = {n for n, h in zip(lay.names, lay.consider_mask(True, False, False, False), strict=True) if h}
    assert not SOFT & plain


def test_only_a_vibrating_vehicle_holds_them_with_or_without_the_magnetometer_in_the_update() -> None:
    """A hand is a vehicle by the accelerometer gate's drops, not by vibration: its magnetometer keeps learning in
    motion (the paper's and MARG's hand-held sessions calibrate it there)."""
    from onlinecal.ukf import OnlineCalibrator
    from onlinecal.ukf.fastpath import motion_consider
    from onlinecal.ukf.vehicle import VIBRATION_REASON

    cal = OnlineCalibrator(None)
    ix = [cal.lay.names.index(n) for n in sorted(SOFT)]
    ib = cal.lay.names.index("mag.bias.z")
    assert not motion_consider(cal, True)[ix].any()  # no vehicle
    cal._vehicle.active, cal._vehicle.reason = True, "the accelerometer's gate dropped 6 of the last 20 moving blocks"
    assert not motion_consider(cal, True)[ix].any()  # a hand
    cal._vehicle.reason = VIBRATION_REASON + " 0.92 m/s² per sample"
    for mag_in in (True, False):
        m = motion_consider(cal, mag_in)
        assert m[ix].all() and not m[ib]


def test_the_observability_words_say_the_soft_iron_is_held_in_flight() -> None:
    from onlinecal.ukf.vehicle import MotionCoverage, _why

    cov = MotionCoverage()
    why, need = _why("mag.scale.z", cov, True, False, None, True, thrust=True)
    assert "held" in why and "hard iron" in why and "by hand" in need
    why, _ = _why("mag.bias.z", cov, True, False, None, True, thrust=True)
    assert "held" not in why
    why, _ = _why("mag.scale.z", cov, True, False, None, True, thrust=False)
    assert "held" not in why


@pytest.mark.slow
@pytest.mark.parametrize("profile, seed", [("fixedwing", 19), ("multirotor", 7)])
def test_a_flight_from_a_sphere_fit_magnetometer_stays_consistent(profile: str, seed: int, monkeypatch) -> None:
    """The two worst seeds of the probe (before: fixed-wing 19 mag.scale.z −20.0σ, multirotor 7 gyro.scale.y −5.6σ,
    both reported determined): every term not held by the gauge within 3σ of the truth."""
    import flight_stats as fs

    from onlinecal.model import Calibration

    truth_start = fs.truth_start

    def start(truth: Calibration) -> Calibration:
        c = truth_start(truth)
        m = c.sensor("mag")
        r = 1.0 / float(np.mean(np.abs(np.diag(m.matrix))))  # the field's radius in raw units
        return c.replace(mag=m.with_sigma({"bias": [0.06 * r] * 3, "scale": [0.15 / r] * 3, "alpha": [0.05] * 3,
                                           "xi": [0.035] * 3}))

    monkeypatch.setattr(fs, "truth_start", start)
    r = fs.run_flight(profile, seed, "truth", 10.0, gps=True)
    z = np.where(r.held, 0.0, np.abs(r.z))
    assert np.all(z < 3.0), (z.max(), fs.NAMES[int(np.argmax(z))])


def test_a_low_magnetometer_nis_with_its_soft_iron_held_is_a_note_not_a_defect() -> None:
    """Held at the start's σ, the soft iron is in every flight update's S: a start better than its σ reads a mean NIS
    below the band (0.70 on the loiter's truth start), which is a note where most updates held it; otherwise, and
    above the band always, judged as before."""
    from onlinecal.health import HELD_STATUS, nis_checks

    def nis(mean: float, held: int) -> dict:
        return {"band": [0.5, 9.0], "mag": {"updates": 1000, "rejected": 0, "held": held, "windows": 40,
                                            "mean": mean, "in_band": 0.0}}

    out, figs = nis_checks(nis(0.7, 900))
    assert out == [] and figs["mag"]["status"] == HELD_STATUS
    out, figs = nis_checks(nis(0.7, 100))  # mostly rests: the noise is overstated
    assert [v for v, _ in out] == ["degraded"] and "overstated" in out[0][1]
    out, figs = nis_checks(nis(7.5, 900))  # above the band: judged as ever
    assert [v for v, _ in out] == ["degraded"]
    out, figs = nis_checks({"mag": {"updates": 1000, "rejected": 0, "windows": 40, "mean": 0.7}})  # an older result
    assert [v for v, _ in out] == ["degraded"]
