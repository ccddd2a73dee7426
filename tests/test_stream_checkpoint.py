"""Issue 16 (items 2/4 on resume): the divergence history and the magnetic-disturbance gate travel in the
checkpoint (onlinecal.ukf.checkpoint, schema /4). Before, both restarted fresh on ``run --resume``: a second
divergence soon after a resume restarted from a widened prior instead of escalating to the cold prior as the
uninterrupted run does, and a disturbance running at the checkpoint was forgotten."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np
import pytest

from onlinecal.io.base import LogError
from onlinecal.sim import simulate
from onlinecal.ukf import OnlineCalibrator
from onlinecal.ukf import divergence as dv
from onlinecal.ukf.checkpoint import SCHEMA_V3
from onlinecal.ukf.live_files import CHECKPOINT_SCHEMA, load_checkpoint
from onlinecal.ukf.magdisturb import MagDisturbanceGate


def _force(cal: OnlineCalibrator) -> None:
    """Every NIS window declares a divergence (the forcing of test_robust_divergence)."""
    cal._nis.record = lambda s, nis, t, inflated=0.0, held=False: f"{s} NIS window mean forced"  # type: ignore[method-assign]


def _feed_until_divergence(cal: OnlineCalibrator, d, i: int, n_div: int) -> int:
    """Feed one filter block at a time from row i until ``n_div`` divergence events are logged."""
    while sum(e["kind"] == "divergence" for e in cal.events) < n_div and i < d.n_imu:
        cal.feed(d.slice_imu(i, i + 10))
        i += 10
    assert sum(e["kind"] == "divergence" for e in cal.events) == n_div
    return i


def _through_json(cal: OnlineCalibrator) -> dict:
    return json.loads(json.dumps(cal.get_state(), allow_nan=False))


@pytest.mark.filterwarnings("ignore::onlinecal.ukf.divergence.DivergenceWarning")
def test_a_resume_right_after_a_divergence_escalates_as_an_uninterrupted_run() -> None:
    d = simulate("paper", 2, duration=150.0).data
    ref = OnlineCalibrator(None)
    ref.new_log()
    ref.feed(d.slice_imu(0, 4000))
    _force(ref)
    i = _feed_until_divergence(ref, d, 4000, 1)  # the first: a widened prior
    first = [e for e in ref.events if e["kind"] == "divergence"][0]
    assert "widened" in first["detail"] and "second divergence" not in first["detail"]
    state = _through_json(ref)
    assert state["state"]["_div"]["times"] == [pytest.approx(first["t"])]
    resumed = OnlineCalibrator.from_state(state)
    assert resumed._div.times == ref._div.times
    _force(resumed)
    # the second divergence, seconds later: both escalate to the cold prior
    _force(ref)  # the restart built a new NIS monitor
    j_ref = _feed_until_divergence(ref, d, i, 2)
    j_res = _feed_until_divergence(resumed, d, i, 2)
    second_ref = [e for e in ref.events if e["kind"] == "divergence"][1]
    second_res = [e for e in resumed.events if e["kind"] == "divergence"][1]
    assert j_ref == j_res and second_res == second_ref
    assert second_res["t"] - first["t"] < dv.ESCALATE_WINDOW_S
    assert "second divergence within" in second_res["detail"]
    assert "restarted from the cold prior" in second_res["detail"]
    _, sig_cold = dv.cold_prior(resumed.config, resumed.x)
    free = np.arange(3, 27)[~resumed.lay.consider[3:27]]
    assert np.array_equal(resumed.prior_sigma[free], sig_cold[free])
    assert np.array_equal(resumed.x, ref.x) and np.array_equal(resumed.P, ref.P)
    # what a checkpoint without the history (schema /3, as before) gives: a widened restart, not the cold one
    old = copy.deepcopy(state)
    old["schema"] = SCHEMA_V3
    del old["state"]["_div"], old["state"]["_magd"]
    fresh = OnlineCalibrator.from_state(old)
    assert fresh._div.times == []
    _force(fresh)
    _feed_until_divergence(fresh, d, i, 2)
    assert "second divergence" not in [e for e in fresh.events if e["kind"] == "divergence"][1]["detail"]


def test_the_disturbance_gate_is_saved_and_restored() -> None:
    cal = OnlineCalibrator(None)
    cal._magd = MagDisturbanceGate(active=True, since=812.5, last_bad=840.25, excluded=37, stretches=2, armed=True,
                                   agreed_since=math.nan)
    back = OnlineCalibrator.from_state(_through_json(cal))
    g = back._magd
    assert (g.active, g.since, g.last_bad, g.excluded, g.stretches, g.armed) == (True, 812.5, 840.25, 37, 2, True)
    assert math.isnan(g.agreed_since)
    # a fresh gate (never disturbed): last_bad −inf and since NaN survive strict JSON
    fresh = OnlineCalibrator.from_state(_through_json(OnlineCalibrator(None)))._magd
    assert fresh.last_bad == -math.inf and math.isnan(fresh.since) and not fresh.active


@pytest.mark.parametrize("path, value, what", [
    (("_div", "times"), ["soon"], "divergence times"),
    (("_div", "times"), [30.0, 10.0], "backwards"),
    (("_div", "times"), [{"__f__": "nan"}], "divergence times"),
    (("_magd", "active"), 1, "'active'"),
    (("_magd", "excluded"), -3, "'excluded'"),
    (("_magd", "since"), "yesterday", "'since'"),
    (("_magd",), {"__dc__": "DivergenceLog", "times": []}, "not a MagDisturbanceGate"),
    (("_learn", "gates", "mag", "anchor"), [1.0, 2.0], "mag learning gate's anchor"),
    (("_learn", "gates", "accel", "angle"), 0.5, "accel learning gate is not one of the config's angle"),
    (("_learn", "held"), {"__tuple__": [1, 0]}, "'held'"),
    (("_learn",), {"__dc__": "DivergenceLog", "times": []}, "not a Learning"),
])
def test_a_damaged_history_or_gate_is_refused_in_one_line(tmp_path: Path, path: tuple, value: object,
                                                          what: str) -> None:
    state = _through_json(OnlineCalibrator(None))
    node = state["state"]
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    with pytest.raises(ValueError, match=what):
        OnlineCalibrator.from_state(copy.deepcopy(state))
    ck = {"schema": CHECKPOINT_SCHEMA, "filter": state, "source": {"last_us": 0, "offset_us": 0}, "fed": {"imu": 0}}
    p = tmp_path / "ck.json"
    p.write_text(json.dumps(ck))
    with pytest.raises(LogError) as e:
        load_checkpoint(p)
    line = str(e.value)
    assert "\n" not in line and line.startswith(str(p)) and "damaged checkpoint" in line and what.strip("'") in line


def test_the_learning_gates_are_saved_and_restored() -> None:
    """Schema /5 keeps where each sensor last learned its terms (.learning): a resumed run learns at the blocks an
    uninterrupted one would. A /4 checkpoint (without them) resumes with fresh gates: its next block learns."""
    from onlinecal.ukf.checkpoint import SCHEMA_V4

    cal = OnlineCalibrator(None)
    cal._learn.gates["mag"].anchor = np.array([0.1, -0.2, 0.45])
    cal._learn.held = (False, True)
    back = OnlineCalibrator.from_state(_through_json(cal))._learn
    assert np.array_equal(back.gates["mag"].anchor, [0.1, -0.2, 0.45]) and back.gates["accel"].anchor is None
    assert back.held == (False, True)
    assert not back.gates["mag"].learns(np.array([0.1, -0.2, 0.45]), np.zeros(3))
    old = _through_json(cal)
    old["schema"] = SCHEMA_V4
    del old["state"]["_learn"]
    fresh = OnlineCalibrator.from_state(old)._learn
    assert fresh.gates["mag"].anchor is None and fresh.gates["mag"].learns(np.array([0.1, -0.2, 0.45]), np.zeros(3))
