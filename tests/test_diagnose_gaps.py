"""Issue 12 row: `diagnose` on a .bin with a 30 s burst of NaN and on a log with a 30 s gap ended in exit 70
(IndexError in the drift basis: a knot with no sample). Now the hole is cut out, named, and the rest
diagnosed. Real files written by the project's writers; truth from the simulator."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from onlinecal.diagnose.gaps import MIN_PIECE, split_at_gaps
from onlinecal.io import read_log, write_log
from onlinecal.io.base import ImuData
from onlinecal.model import Calibration
from onlinecal.sim import simulate


def _log(t: np.ndarray, tm: np.ndarray) -> ImuData:
    n, m = t.size, tm.size
    return ImuData(t, np.zeros((n, 3)), np.tile([0, 0, 9.8], (n, 1)), np.full(n, np.nan), tm,
                   np.tile([0.2, 0, 0.4], (m, 1)), "x.tlog")


def test_split_cuts_at_the_hole_and_names_it():
    t = np.concatenate([np.arange(0, 10, 0.01), np.arange(40, 50, 0.01)])
    tm = np.concatenate([np.arange(0, 10, 0.02), np.arange(20, 25, 0.02), np.arange(40, 50, 0.02)])
    pieces, exc = split_at_gaps([_log(t, tm)])
    assert [p.n_imu for p in pieces] == [1000, 1000]
    assert pieces[0].t_imu[-1] < 10 <= 40 <= pieces[1].t_imu[0]
    # mag samples inside the hole (20–25 s) go with it; the others stay with their piece
    assert pieces[0].n_mag == 500 and pieces[1].n_mag == 500
    assert len(exc) == 1 and exc[0]["t0"] == pytest.approx(9.99) and exc[0]["t1"] == pytest.approx(40.0)
    assert exc[0]["duration_s"] == pytest.approx(30.01) and "without IMU samples" in exc[0]["reason"]


def test_no_hole_no_cut_and_a_slow_log_is_not_cut_per_sample():
    d = _log(np.arange(0, 100, 0.01), np.arange(0, 100, 0.02))
    pieces, exc = split_at_gaps([d])
    assert pieces[0] is d and not exc
    slow = _log(np.arange(0, 140, 1.0), np.zeros(0))  # 1 Hz telemetry: 1 s steps are its rate, not holes
    assert split_at_gaps([slow])[0][0] is slow


def test_a_piece_too_short_between_holes_is_left_out_and_named():
    t = np.concatenate([np.arange(0, 10, 0.01), 30 + np.arange(MIN_PIECE - 10) * 0.01, np.arange(60, 70, 0.01)])
    pieces, exc = split_at_gaps([_log(t, np.zeros(0))])
    assert [p.n_imu for p in pieces] == [1000, 1000]
    assert len(exc) == 3 and any("too short" in e["reason"] for e in exc)


@pytest.fixture(scope="module")
def session():
    return simulate("paper", 7)


def _hole(d: ImuData, lo: float, hi: float, nan: bool) -> ImuData:
    m, mm = (d.t_imu >= lo) & (d.t_imu < hi), (d.t_mag >= lo) & (d.t_mag < hi)
    if nan:  # the samples stay in the file, as NaN (the reader drops them)
        g, a = d.gyro.copy(), d.acc.copy()
        g[m], a[m] = np.nan, np.nan
        return replace(d, gyro=g, acc=a)
    return replace(d, t_imu=d.t_imu[~m], gyro=d.gyro[~m], acc=d.acc[~m], temp=d.temp[~m], t_mag=d.t_mag[~mm],
                   mag=d.mag[~mm])


def _diagnose(path, tmp_path):
    js = tmp_path / "d.json"
    r = subprocess.run([sys.executable, "-m", "onlinecal", "--quiet", "diagnose", str(path), "--json", str(js)],
                       capture_output=True, text=True, timeout=600)
    assert "Traceback" not in r.stderr and r.returncode != 70, r.stderr
    return r, json.loads(js.read_text())


@pytest.mark.slow
@pytest.mark.parametrize("ext, lo, nan", [(".bin", 40.0, True), (".tlog", 245.0, False)])
def test_diagnose_gives_a_result_with_the_hole_named(tmp_path, session, ext, lo, nan):
    """30 s NaN burst in the static positions of a .bin; 30 s logging gap in the tumble of a .tlog."""
    p = tmp_path / f"s{ext}"
    write_log(p, _hole(session.data, lo, lo + 30.0, nan))
    assert read_log(p).n_imu == session.data.n_imu - 3000  # the hole is there: 30 s at 100 Hz
    r, js = _diagnose(p, tmp_path)
    assert r.returncode == 0, r.stderr
    (e,) = js["baseline"]["excluded"]
    assert e["t0"] == pytest.approx(lo - 0.01, abs=0.011) and e["t1"] == pytest.approx(lo + 30.0, abs=0.011)
    assert f"t = {e['t0']:.2f}–{e['t1']:.2f} s excluded" in r.stdout + r.stderr
    assert ("NaN" in e["reason"]) == nan
    # the rest of the session is diagnosed as the clean session would be: nothing found, and the baseline
    # (fitted on the two pieces) within 0.1 % of the simulator's truth
    assert js["verdict"] == "none"
    cal, truth = Calibration.from_dict(js["baseline"]["calibration"]), session.truth.calibration
    for s in ("gyro", "accel", "mag"):
        assert cal.sensor(s).matrix_rel_error(truth.sensor(s)) < 1e-3


@pytest.mark.slow
def test_diagnose_hole_across_rotation_phases_gives_a_result(tmp_path, session):
    """A hole that cuts the rotation phases (150–180 s): the batch has half phases only, so the baseline is
    poor; the result must still come, name the hole and say the calibration is not to be trusted."""
    p = tmp_path / "s.bin"
    write_log(p, _hole(session.data, 150.0, 180.0, True))
    r, js = _diagnose(p, tmp_path)
    assert r.returncode in (0, 4, 5) and js["baseline"]["excluded"]
    assert r.returncode == 0 or js["health"]["verdict"] != "ok"
