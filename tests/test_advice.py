"""Issue 12: the "still needed" motion advice derives from the faces the data holds (gravity direction at
each static segment), never asking for a face the session already has.

Truth for the faces comes from the simulator's trajectory (its specific force in the body frame at the
holds), not from the advice code."""

from __future__ import annotations

import numpy as np
import pytest

import onlinecal.sim.sensors as simsens
from onlinecal.advice import FACES, accel_face_advice, face_words, faces_at_rest, missing_faces
from onlinecal.batch.segment import segment
from onlinecal.sim import simulate
from onlinecal.sim.motion import Trajectory
from onlinecal.ukf.filter import OnlineCalibrator
from onlinecal.ukf.layout import AXES
from onlinecal.ukf.outputs import missing_motion
from onlinecal.ukf.state import StateLayout
from onlinecal.ukf.vehicle import MotionCoverage, VehicleDetector, observability_report

ACCEL_TERMS = [f"accel.{p}.{a}" for p in ("bias", "scale") for a in AXES]


def _four_faces() -> Trajectory:
    """A session resting on four faces only: z up, z down, and one face each of x and y (by roll/pitch
    of 90°), with turns between; the opposite x and y faces are never held."""
    tr = Trajectory()
    tr.hold(20.0, label="rest")
    for target in ((0, 0, 40), (180, 0, -30), (90, 0, 100), (0, 90, 10), (0, 0, 0)):
        tr.move(target, 3.0).hold(6.0, label="static position")
    tr.tumble(40.0, (3.0, 0.0, 2.0), 60.0, 5)
    tr.move((0, 0, 0), 3.0).hold(6.0, label="final rest")
    return tr


def _truth_faces(sim) -> set[str]:
    """Faces from the trajectory's own specific force at its holds (|ω| = 0)."""
    m = sim.trajectory.evaluate(sim.data.t_imu)
    rest = np.linalg.norm(m.omega, axis=1) < 1e-9
    return set(faces_at_rest(m.f[rest][:: 50]))


def _static_dirs(data) -> np.ndarray:
    seg = segment(data)
    return np.array([data.acc[s.i0:s.i1].mean(axis=0) for s in seg.statics])


def _not_excited(names):
    return {n: {"ratio": 0.9, "excited": False} for n in names}


@pytest.fixture(scope="module")
def paper():
    return simulate("paper", 4)


@pytest.fixture(scope="module")
def four(request):
    mp = pytest.MonkeyPatch()
    mp.setattr(simsens, "make_trajectory", lambda profile, rng, duration: _four_faces())
    try:
        return simulate("paper", 5)
    finally:
        mp.undo()


def test_face_helpers():
    assert faces_at_rest([[0, 0, 9.8], [0.3, 0, -9.7], [0, 6.9, 6.9]]) == ["+z", "-z"]  # 45° is no face
    assert faces_at_rest(np.zeros((0, 3))) == [] and faces_at_rest([[np.nan, 0, 0]]) == []
    assert missing_faces(["+x", "-y"], ["x", "y"]) == ["-x", "+y"]
    assert face_words("-z") == "z down" and face_words("+y") == "y up"
    assert accel_face_advice(FACES, ACCEL_TERMS) is None
    assert accel_face_advice(["+y"], ["accel.bias.y", "accel.xi.x"]) == "hold still for 5 s with y down"


def test_paper_session_holds_all_faces_and_no_face_is_asked(paper):
    assert _truth_faces(paper) == set(FACES)
    dirs = _static_dirs(paper.data)
    assert sorted(faces_at_rest(dirs)) == sorted(FACES)
    # The case of the issue: a filter started from the batch, whose accel σ cannot halve, reports the
    # accel bias/scale as not excited. The advice must not ask for any face.
    cov = MotionCoverage()
    for u in dirs:
        cov.add_rest(u, 6.0)
    lay = StateLayout()
    need = missing_motion(_not_excited(ACCEL_TERMS), lay, cov)
    assert not any(" up" in m or " down" in m for m in need), need
    rep = observability_report(["att.x", "att.y", "att.z"] + ACCEL_TERMS, np.full(9, 0.9), np.ones(9), cov,
                               VehicleDetector(), set(), None)
    for u in rep["undetermined"]:
        assert u["motion_needed"].startswith("none"), u
    # Without the data's coverage (the old behaviour) all six faces were asked: the contradiction.
    old = missing_motion(_not_excited(ACCEL_TERMS), lay)
    assert sum(("up" in m and "down" in m) for m in old) == 3


def test_session_missing_two_faces_asks_exactly_those(four):
    truth = _truth_faces(four)
    absent = sorted(set(FACES) - truth)
    assert len(absent) == 2 and {f[1] for f in absent} == {"x", "y"}  # the trajectory's design
    dirs = _static_dirs(four.data)
    assert set(faces_at_rest(dirs)) == truth  # the data's rests give the trajectory's faces
    cov = MotionCoverage()
    for u in dirs:
        cov.add_rest(u, 6.0)
    need = missing_motion(_not_excited(ACCEL_TERMS), StateLayout(), cov)
    asked = [w for m in need for w in (face_words(f) for f in FACES) if w in m]
    assert sorted(asked) == sorted(face_words(f) for f in absent), need
    rep = observability_report(["att.x", "att.y", "att.z"] + ACCEL_TERMS, np.full(9, 0.9), np.ones(9), cov,
                               VehicleDetector(), set(), None)
    per_axis = {u["term"]: u["motion_needed"] for u in rep["undetermined"]}
    for f in absent:
        assert face_words(f) in per_axis[f"accel.bias.{f[1]}"]
    assert per_axis["accel.bias.z"].startswith("none")


def _tight_start(sim):
    """The truth as the start, with accelerometer σ so small that no data halves it (the batch-started
    filter of the issue, exaggerated): the accel bias and scale are reported not excited."""
    tc = sim.truth.calibration
    return tc.replace(accel=tc.accel.with_sigma({"bias": [1e-5] * 3, "scale": [1e-6] * 3, "alpha": [1e-3] * 3,
                                                 "xi": [1e-3] * 3}))


@pytest.mark.slow
@pytest.mark.parametrize("which", ["paper", "four"])
def test_filter_asks_exactly_the_faces_the_session_lacks(which, paper, four):
    """End to end: the UKF's own coverage (its calibrated rests) on the paper session (no face asked) and
    on the four-face session (exactly the two absent faces asked)."""
    sim = paper if which == "paper" else four
    cal = OnlineCalibrator(init=_tight_start(sim))
    cal.feed(sim.data)
    cal.flush()
    obs = cal.observability()
    assert all(not obs[t]["excited"] for t in ACCEL_TERMS)  # the case where the old advice asked all six
    absent = sorted(set(FACES) - _truth_faces(sim))
    need = cal.missing_motion()
    asked = sorted(w for m in need for w in (face_words(f) for f in FACES) if w in m)
    assert asked == sorted(face_words(f) for f in absent), need
