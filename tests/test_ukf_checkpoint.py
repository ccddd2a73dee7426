"""The generic checkpoint (onlinecal.ukf.checkpoint, schema onlinecal.ukf-state/3): every part's dataclass
serialised by its fields; a resume through strict JSON continues bit-identically."""

from __future__ import annotations

import json
import math
from collections import deque

import numpy as np
import pytest

from onlinecal.sim import simulate
from onlinecal.ukf import OnlineCalibrator
from onlinecal.ukf.checkpoint import STATE_ATTRS, STATE_SCHEMA, decode, encode
from onlinecal.ukf.magstart import MagStart


def _roundtrip(v):
    return decode(json.loads(json.dumps(encode(v), allow_nan=False)))


def test_encode_decode_keeps_values_types_shapes():
    a = np.array([[1.0, math.nan], [-math.inf, 1e-300]])
    out = _roundtrip({"a": a, "e": np.zeros((0, 3)), "t": (np.ones(2), None), "f": -math.inf,
                      "q": deque([1, 2], maxlen=5), "i": np.arange(3)})
    assert out["a"].shape == (2, 2) and np.array_equal(out["a"], a, equal_nan=True)
    assert out["e"].shape == (0, 3)
    assert isinstance(out["t"], tuple) and out["t"][1] is None and np.array_equal(out["t"][0], np.ones(2))
    assert out["f"] == -math.inf
    assert isinstance(out["q"], deque) and out["q"].maxlen == 5 and list(out["q"]) == [1, 2]
    assert out["i"].dtype == np.arange(3).dtype
    ms = MagStart(enabled=True, fit_next=-math.inf)
    ms.buf.buf = np.array([[0.1, 0.2, 0.3]])
    back = _roundtrip(ms)
    assert isinstance(back, MagStart) and back.enabled and back.fit_next == -math.inf
    assert np.array_equal(back.buf.buf, ms.buf.buf)


def test_unregistered_part_and_unknown_schema_refused():
    from dataclasses import dataclass

    @dataclass
    class Stranger:
        v: int = 0

    with pytest.raises(TypeError, match="not a registered part"):
        encode(Stranger())
    with pytest.raises(ValueError, match="schema 'onlinecal.ukf-state/9'"):
        OnlineCalibrator.from_state({"schema": "onlinecal.ukf-state/9"})


def _feed(cal, d, cuts):
    for i, j in zip(cuts[:-1], cuts[1:], strict=True):
        cal.feed(d.slice_imu(i, j))


@pytest.mark.slow
@pytest.mark.parametrize("t_cut", [20.0, 55.0])  # inside the opening rest (a running rest), in motion
def test_resume_through_json_is_bit_identical(t_cut):
    d = simulate("paper", 3, duration=70.0).data
    cuts = list(range(0, d.n_imu, 137)) + [d.n_imu]
    k = int(np.searchsorted(cuts, np.searchsorted(d.t_imu, t_cut)))
    ref = OnlineCalibrator(None)
    ref.new_log()
    _feed(ref, d, cuts)
    ref.flush()
    cal = OnlineCalibrator(None)
    cal.new_log()
    _feed(cal, d, cuts[: k + 1])
    if t_cut < 30:
        assert cal._rest_acc is not None  # the checkpoint holds a running rest
    state = json.loads(json.dumps(cal.get_state(), allow_nan=False))
    assert state["schema"] == STATE_SCHEMA == "onlinecal.ukf-state/5"
    assert set(state["state"]) == set(STATE_ATTRS) and len(state["x"]) == cal.n
    res = OnlineCalibrator.from_state(state)
    _feed(res, d, cuts[k:])
    res.flush()
    assert np.array_equal(res.x, ref.x) and np.array_equal(res.P, ref.P)
    assert np.array_equal(res.R_nom, ref.R_nom)
    assert res.trace_rows() and len(res.trace_rows()) == len(ref.trace_rows())
    assert res.events == ref.events
