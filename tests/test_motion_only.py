"""Accelerometer terms determined through motion alone are said so, and `export` leaves them out.

Truth from the data, not from the filter: on the real PX4 log (``../shared/data/px4-ulog/sample.ulg``, 69 s,
already corrected by PX4's own six-position calibration) the 60-s rest, replayed alone, leaves the
accelerometer's z scale undetermined — one attitude at rest fixes s·(raw − o), not the split — so the whole
log must not call it determined either (docs/flight.md, *The one real autopilot log*)."""

from __future__ import annotations

import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from onlinecal.io import read_log
from onlinecal.sim import simulate
from onlinecal.ukf import replay
from onlinecal.ukf.vehicle import MotionCoverage, motion_only

SAMPLE = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "px4-ulog" / "sample.ulg"
needs_data = pytest.mark.skipif(not SAMPLE.is_file(), reason="shared/data/px4-ulog/sample.ulg not present")


def test_motion_only_names_the_terms_whose_axis_never_rested_up_and_down() -> None:
    cov = MotionCoverage()
    cov.add_rest(np.array([0.1, 0.0, -1.0]), 10.0)  # one rest, gravity along −z (the z-down face)
    got = motion_only(["accel.bias.z", "accel.scale.z", "accel.scale.x", "gyro.scale.z", "accel.xi.x"], cov)
    assert [c["term"] for c in got] == ["accel.bias.z", "accel.scale.z", "accel.scale.x"]
    assert "never with z up" in got[0]["reason"] and got[0]["motion_needed"] == "hold still for 5 s with z up"
    assert "x up or with x down" in got[2]["reason"]
    cov.add_rest(np.array([0.0, 0.0, 1.0]), 10.0)  # and the z-up face: z is separable by the rests
    assert [c["term"] for c in motion_only(["accel.bias.z", "accel.scale.z"], cov)] == []
    assert motion_only(["accel.scale.z"], MotionCoverage())[0]["reason"].startswith(
        "determined through motion alone: the log rested in 0 attitude(s)")


def test_the_paper_session_rests_on_every_face_so_nothing_is_motion_only() -> None:
    res = replay([simulate("paper", 5).data], None)
    rep = res.calibration.meta["online"]["observability"]
    assert {"accel.bias.z", "accel.scale.z"} <= set(rep["determined"])
    assert rep["caution"] == []


@needs_data
def test_real_px4_log_accel_z_scale_is_not_called_determined_and_not_exported(tmp_path: Path) -> None:
    """Before the block-mean noise (tests/test_block_mean_noise.py) this log's rest split into 50 rests, each a
    fresh measurement of the same pose with the σ of white noise, and the whole log called its z scale
    0.957 ± 0.004 "determined" (the caution then named it). Now neither the rest alone nor the whole log
    determines it, and export leaves the vehicle's value in place."""
    d = read_log(SAMPLE)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        whole = replay([d], None)
        t = d.t_imu - d.t_imu[0]
        rest = replay([d.slice_imu(int(np.searchsorted(t, 8.0)), d.n_imu)], None)
    # one attitude at rest cannot split the z scale from the z bias (σ stays above half its prior) ...
    assert "accel.scale.z" not in rest.calibration.meta["online"]["observability"]["determined"]
    # ... and the 6 s of handling before it do not pretend to
    rep = whole.calibration.meta["online"]["observability"]
    assert "accel.scale.z" not in rep["determined"]
    assert "accel.scale.z" not in {c["term"] for c in rep["caution"]}
    out = tmp_path / "ulg.json"
    r = subprocess.run([sys.executable, "-m", "onlinecal", "replay", str(SAMPLE), "--init", "none", "--json", str(out)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    e = subprocess.run([sys.executable, "-m", "onlinecal", "export", str(out), "--format", "px4", "--out", "-"],
                       capture_output=True, text=True, timeout=300)
    z = [ln for ln in e.stdout.splitlines() if "CAL_ACC0_ZSCALE" in ln]
    assert z and all("NOT WRITTEN" in ln and "not determined" in ln for ln in z), z
    assert not any(ln.startswith("CAL_ACC0_ZSCALE") for ln in e.stdout.splitlines())
