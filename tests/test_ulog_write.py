"""Issue 12.6: simulated sessions written as PX4 ULog (onlinecal.io.ulog_write), checked by an independent
reader (pyulog, PX4's own parser) and by onlinecal's ULog reader and batch pipeline."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from onlinecal.batch.pipeline import run_batch
from onlinecal.io import read_log, write_log
from onlinecal.io.ulog_write import DEVICE_ID
from onlinecal.report import compare
from onlinecal.sim import simulate


@pytest.fixture(scope="module")
def paper():
    return simulate("paper", 3)


def test_pyulog_reads_the_written_file(tmp_path, paper):
    from pyulog import ULog

    p = tmp_path / "s.ulg"
    write_log(p, paper.data)
    u = ULog(str(p))
    assert not u.file_corruption
    topics = {d.name: d.data for d in u.data_list}
    assert sorted(topics) == ["sensor_accel", "sensor_gyro", "sensor_mag"]
    d = paper.data
    # PX4's field names and units: timestamp µs, x/y/z in rad/s, m/s², gauss; float32 values.
    for name, t, v in (("sensor_gyro", d.t_imu, d.gyro), ("sensor_accel", d.t_imu, d.acc),
                       ("sensor_mag", d.t_mag, d.mag)):
        got = topics[name]
        np.testing.assert_array_equal(got["timestamp"], np.rint(t * 1e6).astype(np.uint64))
        np.testing.assert_array_equal(got["timestamp_sample"], got["timestamp"])
        np.testing.assert_array_equal(np.column_stack([got[c] for c in "xyz"]), v.astype(np.float32))
        assert np.all(got["device_id"] == DEVICE_ID[name])
    # Specific force in m/s² (|a| ≈ g on a hand-turned session), not in g or mG.
    assert 8.0 < np.median(np.linalg.norm(np.column_stack([topics["sensor_accel"][c] for c in "xyz"]), axis=1)) < 12.0
    # The calibration parameters: identity onboard calibration for the written device ids.
    prm = u.initial_parameters
    assert prm["CAL_ACC0_ID"] == DEVICE_ID["sensor_accel"] and prm["CAL_MAG0_ID"] == DEVICE_ID["sensor_mag"]
    assert prm["CAL_ACC0_XSCALE"] == 1.0 and prm["CAL_GYRO0_ZOFF"] == 0.0 and prm["CAL_MAG0_ROT"] == 0
    assert u.msg_info_dict["sys_name"] == "onlinecal simulate"


def test_reader_gives_back_the_samples_to_float32(tmp_path, paper):
    p = tmp_path / "s.ulg"
    write_log(p, paper.data)
    d, r = paper.data, read_log(p)
    assert r.n_imu == d.n_imu and r.n_mag == d.n_mag and not r.warnings
    np.testing.assert_allclose(r.t_imu, d.t_imu, atol=0.5e-6)  # µs stamps
    np.testing.assert_allclose(r.t_mag, d.t_mag, atol=0.5e-6)
    for got, want in ((r.gyro, d.gyro), (r.acc, d.acc), (r.mag, d.mag)):
        np.testing.assert_array_equal(got, want.astype(np.float32).astype(np.float64))
        # float32 precision: relative error within half an ulp (2⁻²⁴)
        assert np.max(np.abs(got - want) / np.maximum(np.abs(want), 1e-30)) <= 2.0 ** -24
    np.testing.assert_array_equal(r.temp, d.temp.astype(np.float32).astype(np.float64))
    assert r.params["CAL_GYRO0_ID"] == DEVICE_ID["sensor_gyro"]


def test_params_carried_into_the_log_override_the_identity(tmp_path, paper):
    from dataclasses import replace

    p = tmp_path / "s.ulg"
    write_log(p, replace(paper.data, params={"CAL_ACC0_XOFF": 0.25, "CAL_MAG0_ROT": 2.0}))
    r = read_log(p)
    assert r.params["CAL_ACC0_XOFF"] == pytest.approx(0.25) and r.params["CAL_MAG0_ROT"] == 2.0
    assert r.params["CAL_ACC0_YOFF"] == 0.0


def test_negative_or_nan_times_are_refused(tmp_path, paper):
    from dataclasses import replace

    bad = replace(paper.data, t_imu=paper.data.t_imu - 1.0)
    with pytest.raises(ValueError, match="non-negative IMU times"):
        write_log(tmp_path / "x.ulg", bad)


@pytest.mark.slow
def test_batch_on_ulg_matches_exact_csv_and_tlog(tmp_path, paper):
    """The same session through three files: CSV (float64, exact), ULog (float32) and tlog (int16: 1 mG,
    1 mrad/s, 1 mgauss counts). ULog vs the exact CSV within σ/10 on every term (float32 rounding, 6e-8
    relative, is far below the noise); the tlog's int16 quantisation is itself a noise of 0.3 LSB rms
    (2.8 mm/s², 0.3 mrad/s), so against the tlog the bound is a few σ, not σ/10."""
    cals = {}
    for ext in ("csv", "ulg", "tlog"):
        p = tmp_path / f"s.{ext}"
        write_log(p, paper.data)
        cals[ext] = run_batch([read_log(p)]).calibration
    rows = [r for r in compare(cals["csv"], cals["ulg"]) if r["param"] != "matrix"]
    assert len(rows) == 36 and all(r["sigma"] for r in rows)
    worst = max(r["n_sigma"] for r in rows)
    assert worst < 0.1, worst
    tl = [r for r in compare(cals["ulg"], cals["tlog"]) if r["param"] != "matrix"]
    assert max(r["n_sigma"] for r in tl) < 5.0


@pytest.mark.slow
def test_simulate_cli_writes_ulg(tmp_path):
    out = tmp_path / "s.ulg"
    r = subprocess.run([sys.executable, "-m", "onlinecal", "simulate", "--out", str(out), "--duration", "20",
                        "--seed", "2"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert out.read_bytes()[:7] == b"ULog\x01\x12\x35" and (tmp_path / "s.ulg.truth.json").is_file()
    d = read_log(out)
    assert d.n_imu == 2001 and d.duration == pytest.approx(20.0, abs=0.05)
    r = subprocess.run([sys.executable, "-m", "onlinecal", "simulate", "--out", str(tmp_path / "s.ulog")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and ".ulg" in r.stderr and "Traceback" not in r.stderr
