"""The command line as a user runs it: a real subprocess, real files, exit codes and one-line errors."""

import json
import subprocess
import sys

import numpy as np
import pytest


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "onlinecal", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=300)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    log = d / "s.tlog"
    r = run("simulate", "--out", str(log), "--seed", "4")
    assert r.returncode == 0, r.stderr
    return d, log


@pytest.mark.slow
def test_simulate_then_batch_through_tlog(session):
    d, log = session
    truth = json.loads((d / "s.tlog.truth.json").read_text())
    out = d / "batch.json"
    r = run("batch", str(log), "--json", str(out))
    assert r.returncode == 0, r.stderr
    cal = json.loads(out.read_text())
    assert cal["schema"] == "onlinecal.calibration/2" and cal["source"] == "batch"
    # through RAW_IMU's 1 mrad/s quantisation the gyro bias is still well inside 1e-3 rad/s
    err = np.abs(np.array(cal["gyro"]["bias"]) - truth["calibration"]["gyro"]["bias"])
    assert err.max() < 1e-3
    assert "gyro.scale.x" in r.stdout


def test_compare_reports_differences_in_sigma(session):
    d, log = session
    a = d / "batch.json"
    if not a.exists():
        assert run("batch", str(log), "--json", str(a)).returncode == 0
    truth = json.loads((d / "s.tlog.truth.json").read_text())["calibration"]
    t = d / "truth.json"
    t.write_text(json.dumps(truth))
    r = run("compare", str(t), str(a))
    assert r.returncode == 0, r.stderr
    assert "gyro.bias.x" in r.stdout and "|Δ|/σ" in r.stdout


@pytest.mark.slow
def test_csv_round_trip_and_bin(tmp_path):
    for ext in (".csv", ".bin"):
        log = tmp_path / f"s{ext}"
        assert run("simulate", "--out", str(log), "--seed", "2").returncode == 0
        r = run("batch", str(log))
        assert r.returncode == 0, r.stderr


@pytest.mark.parametrize("content,needle", [
    (b"", "empty"),
    (b"time_s,gyro_x,gyro_y,gyro_z,acc_x,acc_y,acc_z\n", "no IMU"),
    (b"time_s,gyro_x,gyro_y,gyro_z,acc_x,acc_y,acc_z\n0.0,1,2,3,4,5,6\nabc,1,2\n0.02,1,2,3,4,5,6\n", "line 3"),
])
def test_bad_csv_one_line_exit_2(tmp_path, content, needle):
    p = tmp_path / "bad.csv"
    p.write_bytes(content)
    r = run("batch", str(p))
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    line = r.stderr.strip().splitlines()[-1]
    assert str(p) in line and needle.lower() in line.lower()


@pytest.mark.slow
def test_garbage_tlog_and_missing_file(tmp_path):
    p = tmp_path / "junk.tlog"
    p.write_bytes(np.random.default_rng(0).bytes(5000))
    for path in (p, tmp_path / "missing.csv", tmp_path / "x.txt"):
        r = run("batch", str(path))
        assert r.returncode == 2 and "Traceback" not in r.stderr and str(path) in r.stderr


def test_too_little_data_is_exit_2_not_traceback(tmp_path):
    p = tmp_path / "short.csv"
    rows = ["time_s,gyro_x,gyro_y,gyro_z,acc_x,acc_y,acc_z"] + [f"{i * 0.01},0.01,0,0,0,0,9.8" for i in range(50)]
    p.write_text("\n".join(rows) + "\n")
    r = run("batch", str(p))
    assert r.returncode == 2 and "Traceback" not in r.stderr and "short.csv" in r.stderr


@pytest.mark.slow
def test_demo_writes_its_files(tmp_path):
    r = run("demo", "--out", str(tmp_path / "demo"))
    assert r.returncode == 0, r.stderr
    for f in ("session.tlog", "batch.json", "report.md", "errors.json"):
        assert (tmp_path / "demo" / f).exists()
    err = json.loads((tmp_path / "demo" / "errors.json").read_text())["batch"]
    assert max(err[s]["matrix_rel"][0] for s in err) < 5e-3
