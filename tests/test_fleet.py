"""Fleet replay (`replay --jobs N`, `--executor dask`): every log an independent unit, the same result whatever
runs it, a bad log reported on its own line, and the drift summary against the simulator's truth."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from onlinecal.fleet import FLEET_SCHEMA, fleet_summary, log_start_time, run_fleet, weighted_trend
from onlinecal.io import write_log
from onlinecal.model import SensorCalibration
from onlinecal.sim import paper_truth, simulate

DAY = 86400.0
TLOG_EPOCH_S = 1_700_000_000.0  # write_tlog stamps records with this wall-clock base + the IMU time
DRIFT = 1e-3  # rad/s per day, gyro bias x of the drifting unit
RECORD_KEYS = {"schema", "log", "ok", "error", "calibration", "init", "n_imu", "log_s", "wall_s", "t_start",
               "t_start_source", "warnings", "health"}


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "onlinecal", *args], capture_output=True, text=True, timeout=600)


def _same(x, y, path: str = "") -> None:
    """Equal structure and strings; numbers equal up to rounding (1e-9 relative). Bit-for-bit equality is not
    promised across processes: SIMD/BLAS rounding depends on the arrays' alignment in memory (observed
    differences ~1e-13 relative, every parameter's σ is > 1e-7 relative)."""
    if isinstance(x, dict):
        assert isinstance(y, dict) and x.keys() == y.keys(), path
        for k in x:
            _same(x[k], y[k], f"{path}.{k}")
    elif isinstance(x, list):
        assert isinstance(y, list) and len(x) == len(y), path
        for i, (u, v) in enumerate(zip(x, y, strict=True)):
            _same(u, v, f"{path}[{i}]")
    elif isinstance(x, float) and not isinstance(y, bool):
        assert y == pytest.approx(x, rel=1e-9, abs=1e-15), path
    else:
        assert x == y, path


@pytest.fixture(scope="module")
def short_fleet(tmp_path_factory):
    """Three 60 s flight logs (50 Hz, CSV) of one unit, a corrupt log, and the unit's calibration as --init."""
    d = tmp_path_factory.mktemp("fleet")
    truth = paper_truth(np.random.default_rng(3))
    paths, n_imu = [], []
    for k in range(3):
        sim = simulate("flight", 30 + k, duration=60.0, imu_rate=50.0, mag_rate=25.0, truth=truth)
        p = d / f"f{k}.csv"
        write_log(p, sim.data)
        paths.append(str(p))
        n_imu.append(sim.data.n_imu)
    bad = d / "corrupt.tlog"
    bad.write_bytes(b"\x00not a tlog" * 200)
    paths.insert(1, str(bad))
    return paths, truth.replace(source="batch").to_dict(), n_imu


@pytest.mark.slow
def test_jobs_and_dask_agree_exactly_and_a_corrupt_log_is_isolated(short_fleet):
    from dask.distributed import LocalCluster

    paths, init, n_imu = short_fleet
    r1 = run_fleet(paths, init=init, jobs=1)
    r2 = run_fleet(paths, init=init, jobs=2)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as c:
        r3 = run_fleet(paths, init=init, executor="dask", scheduler=c.scheduler_address)
    for a, b, c in zip(r1, r2, r3, strict=True):
        assert a["log"] == b["log"] == c["log"]
        assert set(a) == RECORD_KEYS and a["schema"] == FLEET_SCHEMA
        assert a["ok"] == b["ok"] == c["ok"]
        _same(a["calibration"], b["calibration"])
        _same(a["calibration"], c["calibration"])
    bad = r1[1]
    assert bad["ok"] is False and bad["calibration"] is None
    assert "corrupt.tlog" in bad["error"] and "MAVLink" in bad["error"]
    for r, n in zip((r1[0], r1[2], r1[3]), n_imu, strict=True):
        assert r["ok"] and r["error"] is None and r["init"] == "file" and r["n_imu"] == n
        cal = r["calibration"]
        assert cal["schema"] == "onlinecal.calibration/2" and cal["source"] == "online"
        json.dumps(r, allow_nan=False)  # strict JSON: no NaN/Infinity anywhere
        assert r["t_start"] is None  # a CSV with a boot-relative clock carries no date
    s = fleet_summary(r1)
    assert s["ordered_by"] == "input" and s["failed"] == [paths[1]] and len(s["logs"]) == 3
    assert all(p["trend_per_day"] is None for p in s["params"])


@pytest.fixture(scope="module")
def drifting_fleet(tmp_path_factory):
    """One unit recorded on days 0, 2 and 5 (paper sessions, 50 Hz, .tlog) whose gyro x bias drifts by DRIFT a
    day, and a garbage .tlog among them."""
    d = tmp_path_factory.mktemp("drift")
    base = paper_truth(np.random.default_rng(0))
    p = base.gyro.params()
    days = (0, 2, 5)
    paths, truths = [], []
    for k, day in enumerate(days):
        gyro = SensorCalibration.from_params(p["bias"] + np.array([DRIFT * day, 0, 0]), p["scale"], p["alpha"],
                                             p["xi"])
        truth = base.replace(gyro=gyro)
        sim = simulate("paper", 100 + k, imu_rate=50.0, mag_rate=25.0, truth=truth)
        sim.data.t_imu = sim.data.t_imu + day * DAY  # the tlog's wall-clock stamps follow the IMU clock
        sim.data.t_mag = sim.data.t_mag + day * DAY
        path = d / f"unit-day{day}.tlog"
        write_log(path, sim.data)
        paths.append(str(path))
        truths.append(truth)
    bad = d / "bad.tlog"
    bad.write_bytes(b"\x00garbage" * 100)
    # given out of time order on purpose: the summary orders by the logs' start times
    return [paths[2], str(bad), paths[0], paths[1]], paths, days, truths, d


@pytest.mark.slow
def test_cli_jobs_jsonl_and_drift_summary(drifting_fleet):
    given, paths, days, truths, d = drifting_fleet
    out = d / "fleet.jsonl"
    r = cli("replay", *given, "--jobs", "2", "--json", str(out))
    assert r.returncode == 2  # one log unusable: its line says so, the others are done
    assert "bad.tlog" in r.stderr and "Traceback" not in r.stderr
    assert "\r" not in r.stderr  # stderr is a pipe: no progress bar
    recs = {x["log"]: x for x in map(json.loads, out.read_text().splitlines())}
    assert set(recs) == set(given)
    assert recs[given[1]]["ok"] is False and "bad.tlog" in recs[given[1]]["error"]
    for p, day in zip(paths, days, strict=True):
        x = recs[p]
        assert x["ok"] and x["init"] == "batch" and x["t_start_source"] == "tlog"
        assert x["t_start"] == pytest.approx(TLOG_EPOCH_S + day * DAY, abs=1e-3)
        assert log_start_time(p) == (x["t_start"], "tlog")
    s = fleet_summary(list(recs.values()))
    assert s["ordered_by"] == "t_start" and [x["log"] for x in s["logs"]] == paths
    assert s["days"] == pytest.approx(list(days), abs=1e-6)
    rows = {x["param"]: x for x in s["params"]}
    assert len(rows) == 36
    # the summary's trend is a weighted least-squares line over the JSON values (checked against numpy)
    for name in ("gyro.bias.x", "accel.scale.y", "mag.xi.z"):
        sensor, param, ax = name.split(".")
        j = "xyz".index(ax)
        v = np.array([recs[p]["calibration"][sensor][param][j] for p in paths])
        sg = np.array([recs[p]["calibration"][sensor]["sigma"][param][j] for p in paths])
        slope = np.polyfit(np.array(days, float), v, 1, w=1 / sg)[0]
        assert rows[name]["trend_per_day"] == pytest.approx(slope, rel=1e-9, abs=1e-15)
        assert rows[name]["first"] == v[0] and rows[name]["last"] == v[-1]
        assert rows[name]["span"] == pytest.approx(v.max() - v.min(), rel=1e-12)
    # the drift itself: the batch that starts the filter has the gyro bias of a quantised 50 Hz tlog within
    # ~1.8e-4 rad/s of the truth (measured on these logs), so even without the filter's help the slope over 5 days
    # is good to 2·1.8e-4/5 ≈ 7e-5 rad/s/day; 1e-4 is the bound
    assert abs(rows["gyro.bias.x"]["trend_per_day"] - DRIFT) < 1e-4
    assert abs(rows["gyro.bias.y"]["trend_per_day"]) < 1e-4 and abs(rows["gyro.bias.z"]["trend_per_day"]) < 1e-4
    assert rows["gyro.bias.x"]["trend_n_sigma"] > 3
    # the table on stdout shows the same trend
    line = next(ln for ln in r.stdout.splitlines() if ln.startswith("gyro.bias.x"))
    assert f"{rows['gyro.bias.x']['trend_per_day']:+.3e}" in line and line.endswith("*")


def test_weighted_trend_and_birge_ratio():
    x = np.array([0.0, 1.0, 2.0, 4.0])
    y = 0.5 + 0.25 * x
    slope, sig = weighted_trend(x, y, np.full(4, 0.1))
    assert slope == pytest.approx(0.25) and sig == pytest.approx(0.1 / np.sqrt(np.sum((x - x.mean()) ** 2)))
    # scatter 10× what the σ claim: σ_slope widened by sqrt(chi²/dof), the slope unchanged from numpy's
    y2 = y + np.array([1.0, -1.0, -1.0, 1.0])
    slope2, sig2 = weighted_trend(x, y2, np.full(4, 0.1))
    r = y2 - np.polyval(np.polyfit(x, y2, 1), x)
    assert slope2 == pytest.approx(np.polyfit(x, y2, 1)[0])
    assert sig2 == pytest.approx(sig * np.sqrt(np.sum((r / 0.1) ** 2) / 2))


def test_dask_missing_is_exit_3_with_the_install_hint(tmp_path):
    code = ("import sys; sys.modules['dask'] = None; sys.modules['dask.distributed'] = None; "
            "from onlinecal.cli import main; sys.exit(main(sys.argv[1:]))")
    out = tmp_path / "x.jsonl"
    r = subprocess.run([sys.executable, "-c", code, "replay", "a.tlog", "--executor", "dask", "--json", str(out)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 3 and "pip install onlinecal[dask]" in r.stderr and "Traceback" not in r.stderr
    assert not out.exists()


@pytest.mark.slow
def test_fleet_options_that_belong_to_one_replay_are_refused(tmp_path):
    r = cli("replay", "a.tlog", "--jobs", "2", "--report", str(tmp_path / "r"))
    assert r.returncode == 2 and "--report" in r.stderr
    r = cli("replay", "a.tlog", "--jobs", "0")
    assert r.returncode == 2 and "positive integer" in r.stderr


def test_a_result_that_failed_its_health_is_not_ok(tmp_path, monkeypatch):
    """`replay --jobs` marked a log whose result was a wreck (mag bias 60× the field, mag scale z 1e-6)
    `ok: true`. The record now carries the health verdict and `ok` is false; the drift summary skips it."""
    from types import SimpleNamespace

    import onlinecal.fleet as fleet
    from onlinecal.fleet import process_log
    from onlinecal.model import Calibration

    sim = simulate("paper", 5, duration=20.0)
    log = tmp_path / "s.csv"
    write_log(log, sim.data)
    wreck = Calibration(gyro=SensorCalibration.from_params(bias=(0.01, 0, 0)),
                        mag=SensorCalibration.from_params(bias=(-27.4, 15.6, 56.5), scale=(2.0, 2.1, 1e-6)),
                        source="online")
    fake = SimpleNamespace(calibration=wreck, nis={}, events=[], observability={}, warnings=[])
    monkeypatch.setattr(fleet, "replay_chunked", lambda logs, init, config=None: fake)
    rec = process_log(str(log), init="none")
    assert rec["ok"] is False and rec["error"] is None and rec["health"]["verdict"] == "failed"
    assert rec["calibration"]["health"]["verdict"] == "failed"
    assert any("hard-iron" in r for r in rec["health"]["reasons"])
    assert fleet_summary([rec])["failed"] == [str(log)]
