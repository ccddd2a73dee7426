"""Issue 16, item 3: a stretch whose magnetometer field disagrees with the field model (a motor, a steel
beam) is left out of the filter's magnetometer update and reported (:mod:`onlinecal.ukf.magdisturb`); the
simulator's :class:`onlinecal.sim.effects.MagDisturbance` makes one."""

from __future__ import annotations

import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from onlinecal.sim import simulate
from onlinecal.sim.effects import EffectError, MagDisturbance
from onlinecal.ukf import magdisturb as md
from onlinecal.ukf import replay
from onlinecal.ukf.layout import DIP, N_STATE, SENSOR_SLICE

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from robust_disturbance import disturbance, offset_prior, z_scores  # noqa: E402

G = 9.81
DIP_RAD = math.radians(60.0)


def _state() -> tuple[np.ndarray, np.ndarray]:
    """An identity calibration (bias 0, scale 1) of accel and mag, dip 60°, tight σ."""
    x = np.zeros(N_STATE)
    for s in ("gyro", "accel", "mag"):
        x[SENSOR_SLICE[s].start + 3 : SENSOR_SLICE[s].start + 6] = 1.0
    x[DIP] = DIP_RAD
    return x, np.full(N_STATE, 1e-3)


def _field(norm: float = 1.0, dip: float = DIP_RAD) -> np.ndarray:
    """The body = world field (ENU, north +y, dip below the horizontal), as a block of 5 raw samples."""
    return np.tile(norm * np.array([0.0, math.cos(dip), -math.sin(dip)]), (5, 1))


def _run(gate: md.MagDisturbanceGate, plan: list[tuple[float, float, np.ndarray]]) -> tuple[dict[float, bool], list]:
    """Feed 0.1-s blocks: plan = [(t_from, t_to, mag block)]; returns used per t and the events."""
    x, sig = _state()
    a = np.tile([0.0, 0.0, G], (10, 1))
    used, events = {}, []
    for t0, t1, m in plan:
        for t in np.round(np.arange(t0, t1, 0.1), 1):
            used[float(t)] = gate.gate(True, x, sig, m, a, float(t), G, lambda k, d, tt: events.append((tt, d)))
    return used, events


def test_the_gate_leaves_a_disturbance_out_with_hysteresis_and_reports_it() -> None:
    gate = md.MagDisturbanceGate()
    with pytest.warns(md.MagDisturbanceWarning, match="from t = 5.0 s"):
        used, ev = _run(gate, [(0, 5, _field()), (5, 10, _field(1.5)), (10, 11, _field()), (11, 12, _field(0.6)),
                               (12, 20, _field())])
    assert all(used[t] for t in used if t < 5) and not any(used[t] for t in used if 5 <= t < 14.9)
    assert all(used[t] for t in used if t >= 15.0)  # 3 s (CLEAR_S) after the last disagreeing block, 11.9 s
    assert len(ev) == 2 and ev[0][0] == 5.0 and "norm 1.50" in ev[0][1]
    assert ev[1][0] == 14.9 and "5.0–11.9 s" in ev[1][1] and "99 filter blocks" in ev[1][1]
    assert gate.stretches == 1


def test_a_field_whose_norm_agrees_but_dip_does_not_is_left_out_at_rest() -> None:
    gate = md.MagDisturbanceGate()
    with pytest.warns(md.MagDisturbanceWarning, match="dip"):
        used, ev = _run(gate, [(0, 5, _field()), (5, 7, _field(1.0, math.radians(45.0)))])
    assert not used[5.0] and "dip 45.0°" in ev[0][1]
    # in motion (the specific force is not g) the dip cannot be judged: only the norm is
    x, sig = _state()
    gate2 = md.MagDisturbanceGate()
    for t in np.arange(0, 5, 0.1):
        gate2.gate(True, x, sig, _field(), np.tile([0.0, 0.0, G], (10, 1)), float(t), G, lambda *a: None)
    assert gate2.gate(True, x, sig, _field(1.0, math.radians(45.0)), np.tile([3.0, 0.0, G], (10, 1)), 5.0, G,
                      lambda *a: None)


def test_a_vehicle_in_flight_is_not_judged_on_its_dip() -> None:
    """A multirotor accelerating at 1.9 m/s² (north) has |f| within 2 % of g (√(9.81² + 1.9²) = 9.99) with its
    force 11° off the vertical, so the field's apparent dip is off by 11°. Seen in merged flight replays (bench
    start, seeds 21/22: four false 'dip 49–75°' stretches on a clean flight) before the vehicle's state
    reached the gate."""
    x, sig = _state()
    f_tilted = np.tile([0.0, 1.9, G], (10, 1))
    assert abs(np.linalg.norm(f_tilted[0]) / G - 1.0) < md.STATIC_G  # passes the quasi-static test
    h = _field()  # the undisturbed field
    gate = md.MagDisturbanceGate()
    for t in np.arange(0, 5, 0.1):
        gate.gate(True, x, sig, _field(), np.tile([0.0, 0.0, G], (10, 1)), float(t), G, lambda *a: None)
    assert gate.judge(x, sig, h, f_tilted, G) is not None  # judged as at rest: a false disturbance
    assert gate.judge(x, sig, h, f_tilted, G, accel_is_gravity=False) is None
    assert gate.gate(True, x, sig, h, f_tilted, 5.0, G, lambda *a: None, accel_is_gravity=False)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [21, 22])
def test_a_clean_multirotor_flight_reports_no_disturbance(seed: int) -> None:
    """Bench-started clean multirotor flight (10 min, 200 Hz): no magnetometer disturbance is reported."""
    import flight_stats  # noqa: E402 (benchmarks/ is on the path above)

    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        run = flight_stats.run_flight("multirotor", seed, "bench")
    assert not [x for x in w if issubclass(x.category, md.MagDisturbanceWarning)]
    assert np.abs(run.z).max() < 5


def test_a_field_that_never_agreed_or_keeps_disagreeing_is_left_to_the_filter() -> None:
    """A wrong start never agrees: the gate does not arm (the filter's NIS and divergence restart judge it,
    instead of the wrong terms being kept with their small σ). A disagreement beyond MAX_S is no passing
    disturbance: the magnetometer is used again, and that is said."""
    used, ev = _run(md.MagDisturbanceGate(), [(0, 20, _field(1.5))])
    assert all(used.values()) and not ev
    gate = md.MagDisturbanceGate()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", md.MagDisturbanceWarning)
        used, ev = _run(gate, [(0, 5, _field()), (5, 5 + md.MAX_S + 10, _field(1.5))])
    back = min(t for t in used if t >= 5 and used[t])
    assert 5 + md.MAX_S <= back <= 5 + md.MAX_S + 0.2
    assert "not passing" in ev[-1][1] and not gate.active


def test_the_gate_arms_only_while_the_filter_is_in_order() -> None:
    """A filter whose own NIS windows are out of order (its state going wrong) is not judged by the gate:
    the disagreement is left to its NIS and divergence restart, and a running stretch ends, said so."""
    band_hi = 3.87
    ok = {"accel": {"windows": [[10.0, 3.0]]}, "mag": {"windows": [[10.0, 2.5]]}}
    assert md.nis_in_order(ok, band_hi)
    assert not md.nis_in_order({"accel": {"windows": [[10.0, 9.0]]}, "mag": ok["mag"]}, band_hi)
    assert not md.nis_in_order({"accel": ok["accel"], "mag": {"windows": []}}, band_hi)
    x, sig = _state()
    a = np.tile([0.0, 0.0, G], (10, 1))
    gate, ev = md.MagDisturbanceGate(), []
    for t in np.arange(0, 5, 0.1):
        gate.gate(True, x, sig, _field(), a, float(t), G, lambda k, d, tt: ev.append(d))
    with pytest.warns(md.MagDisturbanceWarning):
        assert not gate.gate(True, x, sig, _field(1.5), a, 5.0, G, lambda k, d, tt: ev.append(d))
    assert gate.gate(True, x, sig, _field(1.5), a, 5.1, G, lambda k, d, tt: ev.append(d), in_order=False)
    assert "left to the filter" in ev[-1] and not gate.active and not gate.armed


def test_the_norm_tolerance_follows_the_calibration_sigma() -> None:
    x, sig = _state()
    u = np.array([0.0, 0.5, -math.sqrt(0.75)])
    # δ‖h‖ = û·δh: a bias error δo gives δh = −δo (σ 1e-3 on every axis: û·δo has σ 1e-3); a scale error
    # δs_i gives δh_i = h_i δs_i, so Σ u_i² δs_i (σ 1e-3 · √Σu_i⁴ = 1e-3 · √0.625)
    assert md.norm_sigma(x, sig, u) == pytest.approx(1e-3 * math.sqrt(1 + 0.625), rel=1e-9)
    sig[SENSOR_SLICE["mag"].start + 3 : SENSOR_SLICE["mag"].start + 6] = 0.05  # a loose mag scale
    gate = md.MagDisturbanceGate()
    assert gate.judge(x, sig, _field(1.2), np.tile([0.0, 0.0, G], (10, 1)), G) is None  # inside 5σ ≈ 0.24
    x2, sig2 = _state()
    assert gate.judge(x2, sig2, _field(1.2), np.tile([0.0, 0.0, G], (10, 1)), G) is not None  # beyond 0.15


def test_the_simulated_disturbance_adds_the_field_in_its_window_only() -> None:
    eff = MagDisturbance(start=5.0, duration=4.0, amplitude=0.5, direction=(2.0, 0.0, 0.0))
    assert eff.direction == (1.0, 0.0, 0.0)
    clean = simulate("paper", 5, duration=20.0)
    dist = simulate("paper", 5, duration=20.0, effects=[eff])
    on = (clean.data.t_mag >= 5.0) & (clean.data.t_mag < 9.0)
    diff = dist.data.mag - clean.data.mag
    assert np.array_equal(diff[~on], np.zeros_like(diff[~on]))  # the same noise draws outside
    want = np.linalg.inv(clean.truth.calibration.mag.matrix) @ np.array([0.5 / 0.48, 0.0, 0.0])
    lsb = float(np.min(np.abs(np.diff(np.unique(clean.data.mag[:, 0])))))
    assert np.all(np.abs(diff[on] - want) <= lsb + 1e-12)
    d = [e for e in dist.truth.effects if e["effect"] == "mag_disturbance"][0]
    assert d["disturbed_samples"] == int(on.sum()) and d["t0"] == 5.0 and d["t1"] == 9.0
    with pytest.raises(EffectError):
        MagDisturbance(direction=(0.0, 0.0, 0.0))
    with pytest.raises(EffectError):
        MagDisturbance(sensor="gyro")


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5])
def test_a_30_s_disturbance_of_half_a_gauss_is_left_out_and_reported(seed: int) -> None:
    """Issue 16: 0.5 G for 30 s (a random body direction, a random start in 60–250 s): before, 20 of 20
    seeds diverged and 13 ended with a term beyond 3σ (up to 46σ). Now: no divergence, the stretch reported
    (one warning, events naming its span), every term within 3σ of the truth — or, where the clean session
    of the same seed already has a term beyond 3σ (seed 3: accel bias 3.2σ), no term worse than the clean
    run's by more than 0.5σ. 20 seeds: benchmarks/robust_disturbance.py, docs/robustness.md."""
    eff = disturbance(seed)
    sim = simulate("paper", seed, effects=[eff])
    truth = sim.truth.calibration
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        res = replay([sim.data], offset_prior(truth, seed))
    assert not [e for e in res.events if e["kind"] == "divergence"]
    assert sum(issubclass(x.category, md.MagDisturbanceWarning) for x in w) == 1
    ev = [e for e in res.events if e["kind"] == "mag_disturbance"]
    assert len(ev) == 2 and eff.start <= ev[0]["t"] <= eff.start + 1.0
    t0, t1 = (float(v) for v in ev[1]["detail"].split("t = ")[1].split(" s,")[0].split("–"))
    assert eff.start <= t0 <= eff.start + 1.0 and eff.start + eff.duration - 2.0 <= t1 <= eff.start + eff.duration + 1.0
    z = z_scores(res.calibration, truth)
    if max(z.values()) > 3.0:
        zc = z_scores(replay([simulate("paper", seed).data], offset_prior(truth, seed)).calibration, truth)
        assert all(z[k] <= max(3.0, zc[k] + 0.5) for k in z), (z, zc)
