"""Damaged logs as real files (issue 5): the measured session with a dropout, and synthetic damage — no data,
broken clocks, sensor dropouts, wrong formats, bad paths. Each is either read with warnings that name the
damage and how much was dropped, or refused with one line naming the file (exit status 2 from the CLI).

The expected counts are worked out here from the damage that was put in, not read back from the reader.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from onlinecal.io import ImuData, LogError, read_log, write_log
from onlinecal.io.csv import COLUMNS

REPO = Path(__file__).resolve().parents[1]
UNMOVED = REPO.parent / "shared" / "data" / "marg-set1" / "unmoved-z-pointing-left.csv"
needs_data = pytest.mark.skipif(not UNMOVED.is_file(), reason=f"measured data not found at {UNMOVED}")


# --- writing damaged CSV files ------------------------------------------------------------------------

@pytest.fixture(scope="module")
def sess() -> ImuData:
    """20 s of the simulated paper session: IMU 100 Hz (t = 0, 0.01, ...), mag 50 Hz (t = 0.01, 0.03, ...)."""
    from onlinecal.sim import simulate

    d = simulate("paper", seed=3, duration=20.0).data
    assert d.n_imu == 2001 and d.n_mag == 1000
    return d


def _fmt(x: np.ndarray) -> list[str]:
    return [repr(v) for v in np.asarray(x, np.float64).tolist()]


def cells(d: ImuData) -> tuple[np.ndarray, np.ndarray]:
    """The CSV cells (as strings) of the IMU rows (n, 11) and the mag rows (m, 11), to be damaged."""
    imu = np.full((d.n_imu, len(COLUMNS)), "", object)
    mag = np.full((d.n_mag, len(COLUMNS)), "", object)
    imu[:, 0], mag[:, 0] = _fmt(d.t_imu), _fmt(d.t_mag)
    for k in range(3):
        imu[:, 1 + k], imu[:, 4 + k], mag[:, 7 + k] = _fmt(d.gyro[:, k]), _fmt(d.acc[:, k]), _fmt(d.mag[:, k])
    imu[:, 10] = _fmt(d.temp)
    return imu, mag


def write_rows(path: Path, d: ImuData, imu: np.ndarray, mag: np.ndarray) -> Path:
    """Rows in the order a logger writes them — by the TRUE sample time — whatever their stamps say."""
    order = np.argsort(np.concatenate([d.t_imu, d.t_mag]), kind="stable")
    rows = np.concatenate([imu, mag])[order]
    path.write_text(",".join(COLUMNS) + "\n" + "".join(",".join(r) + "\n" for r in rows.tolist()))
    return path


def error_of(path: Path) -> LogError:
    with pytest.raises(LogError) as exc:
        read_log(path)
    msg = str(exc.value)
    assert msg.splitlines() == [msg] and msg.startswith(f"{path}: ")
    return exc.value


def gap_sentence(sensor: str, t_before: float, t_after: float) -> str:
    return (f"{sensor} time has 1 gap without samples ({t_after - t_before:.3f} s from t={t_before:.3f} s); "
            f"kept as a gap")


# --- the measured session -----------------------------------------------------------------------------

@needs_data
def test_measured_unmoved_session_zero_rows_from_an_unfilled_buffer():
    # What is damaged: the file holds exactly 7000 IMU and 5000 mag rows (the logger's buffer sizes), of
    # which the first 720 IMU and 168 mag rows were never filled: all values 0, time 0, temperature 0.
    a = np.genfromtxt(UNMOVED, delimiter=",", names=True)
    imu_rows = ~np.isnan(a["gyro_x"])
    mag_rows = ~np.isnan(a["mag_x"])
    assert imu_rows.sum() == 7000 and mag_rows.sum() == 5000 and not np.any(imu_rows & mag_rows)
    imu = np.column_stack([a[c][imu_rows] for c in COLUMNS[1:7]])
    mag = np.column_stack([a[c][mag_rows] for c in COLUMNS[7:10]])
    zi, zm = np.all(imu == 0, axis=1), np.all(mag == 0, axis=1)
    n_zi, n_zm = int(zi.sum()), int(zm.sum())
    assert (n_zi, n_zm) == (720, 168)
    assert zi[:n_zi].all() and zm[:n_zm].all()  # a block at the start, nothing later
    assert np.all(a["time_s"][imu_rows][:n_zi] == 0) and np.all(a["temp_c"][imu_rows][:n_zi] == 0)
    t_ok, tm_ok = a["time_s"][imu_rows][n_zi:], a["time_s"][mag_rows][n_zm:]
    assert np.all(np.diff(t_ok) > 0) and np.all(np.diff(tm_ok) > 0) and t_ok[0] > 0  # the rest is sound
    assert not np.isnan(imu).any() and not np.isnan(mag).any()

    d = read_log(UNMOVED)
    assert d.warnings == [f"dropped {n_zi} IMU rows of all zeros (sensor dropout)",
                          f"dropped {n_zm} mag rows of all zeros (sensor dropout)"]
    assert d.n_imu == 7000 - n_zi and d.n_mag == 5000 - n_zm
    np.testing.assert_array_equal(d.t_imu, t_ok)
    np.testing.assert_array_equal(d.t_mag, tm_ok)


# --- no data ------------------------------------------------------------------------------------------

def test_header_only_and_blank_lines_are_no_data(tmp_path):
    p = tmp_path / "header.csv"
    p.write_text(",".join(COLUMNS) + "\n")
    assert error_of(p).message == "no IMU samples (gyro and accelerometer) in the log"
    p.write_text(",".join(COLUMNS) + "\n\n  \n\n")
    assert error_of(p).message == "no IMU samples (gyro and accelerometer) in the log"


def test_rows_of_zeros_only_are_a_dropout_error(tmp_path, sess):
    imu, mag = cells(sess)
    imu[:, 1:7] = "0"
    mag[:, 7:10] = "0"
    e = error_of(write_rows(tmp_path / "zeros.csv", sess, imu, mag))
    assert e.message == (f"all-zero readings (sensor dropout): {sess.n_imu} of {sess.n_imu} IMU rows unusable "
                         f"(dropped {sess.n_imu} IMU rows of all zeros (sensor dropout))")


# --- broken clocks ------------------------------------------------------------------------------------

def test_clock_stepping_back_drops_the_overlap(tmp_path, sess):
    imu, mag = cells(sess)
    k, km = np.searchsorted(sess.t_imu, 10.0), np.searchsorted(sess.t_mag, 10.0)
    s_imu, s_mag = sess.t_imu.copy(), sess.t_mag.copy()
    s_imu[k:] -= 5.0  # the clock is set back by 5 s at t = 10 s
    s_mag[km:] -= 5.0
    imu[:, 0], mag[:, 0] = _fmt(s_imu), _fmt(s_mag)
    d = read_log(write_rows(tmp_path / "back.csv", sess, imu, mag))
    # Every sample stamped at or before the last one before the step is dropped; the others are kept.
    rep, back = (int(np.sum(s_imu[k:] == s_imu[k - 1])), int(np.sum(s_imu[k:] < s_imu[k - 1])))
    rep_m, back_m = (int(np.sum(s_mag[km:] == s_mag[km - 1])), int(np.sum(s_mag[km:] < s_mag[km - 1])))
    assert back > 400 and back_m > 200
    assert d.warnings == [
        f"dropped {rep + back} IMU rows whose time did not increase ({rep} repeated, {back} going backwards)",
        f"dropped {rep_m + back_m} mag rows whose time did not increase ({rep_m} repeated, {back_m} going "
        f"backwards)",
    ]
    np.testing.assert_array_equal(d.t_imu, s_imu[s_imu > np.maximum.accumulate(np.r_[-1, s_imu[:-1]])])
    assert d.n_imu == sess.n_imu - rep - back and d.n_mag == sess.n_mag - rep_m - back_m


def test_repeated_stamps_are_dropped_and_counted(tmp_path, sess):
    imu, mag = cells(sess)
    imu[7::7, 0] = imu[6:-1:7, 0]  # every 7th IMU row repeats the stamp of the row before
    n_rep = len(range(7, sess.n_imu, 7))
    d = read_log(write_rows(tmp_path / "rep.csv", sess, imu, mag))
    assert d.warnings == [f"dropped {n_rep} IMU rows whose time did not increase ({n_rep} repeated)"]
    assert d.n_imu == sess.n_imu - n_rep and d.n_mag == sess.n_mag


def test_clock_jumping_hours_ahead_is_kept_as_a_gap(tmp_path, sess):
    imu, mag = cells(sess)
    k, km = np.searchsorted(sess.t_imu, 10.0), np.searchsorted(sess.t_mag, 10.0)
    s_imu, s_mag = sess.t_imu.copy(), sess.t_mag.copy()
    s_imu[k:] += 3 * 3600.0
    s_mag[km:] += 3 * 3600.0
    imu[:, 0], mag[:, 0] = _fmt(s_imu), _fmt(s_mag)
    d = read_log(write_rows(tmp_path / "hours.csv", sess, imu, mag))
    # No IMU sample dropped: the clock carries on. A jump far beyond any gap seen is a clock segment
    # (issue 16.2), and the mag samples stamped inside the IMU's silence are not used across it.
    inside = (s_mag > s_imu[k - 1]) & (s_mag < s_imu[k])
    assert d.n_imu == sess.n_imu and d.n_mag == sess.n_mag - inside.sum()
    assert [b["cause"] for b in d.boundaries] == ["clock jump"]
    assert s_imu[k - 1] < d.boundaries[0]["t"] < s_imu[k]
    assert d.warnings[:2] == [gap_sentence("IMU", s_imu[k - 1], s_imu[k]),
                              gap_sentence("mag", s_mag[km - 1], s_mag[km])]
    assert d.warnings[2].startswith(f"the log's clock jumped forward from t={s_imu[k - 1]:.3f} s")
    assert len(d.warnings) == 3 + bool(inside.sum())
    np.testing.assert_array_equal(d.t_imu, s_imu)


def test_one_stamp_far_ahead_drops_that_sample_only(tmp_path, sess):
    imu, mag = cells(sess)
    imu[500, 0] = repr(float(sess.t_imu[500]) + 1000.0)
    d = read_log(write_rows(tmp_path / "ahead.csv", sess, imu, mag))
    assert d.warnings == ["dropped 1 IMU rows stamped ahead of the samples after them (a lone jump forward in time)"]
    np.testing.assert_array_equal(d.t_imu, np.delete(sess.t_imu, 500))


def test_nan_and_empty_time_cells_drop_those_samples(tmp_path, sess):
    imu, mag = cells(sess)
    imu[100:105, 0] = "nan"
    imu[200:206, 0] = ""
    mag[50:53, 0] = ""
    d = read_log(write_rows(tmp_path / "nantime.csv", sess, imu, mag))
    assert d.warnings == ["dropped 11 IMU rows with NaN, inf or missing values",
                          "dropped 3 mag rows with NaN, inf or missing values"]
    assert d.n_imu == sess.n_imu - 11 and d.n_mag == sess.n_mag - 3


# --- sensor dropouts ----------------------------------------------------------------------------------

def test_mag_cells_empty_for_a_stretch(tmp_path, sess):
    imu, mag = cells(sess)
    gone = (sess.t_mag >= 8.0) & (sess.t_mag < 13.0)
    mag[gone, 7:10] = ""  # those rows are left with a time and nothing else
    d = read_log(write_rows(tmp_path / "magout.csv", sess, imu, mag))
    i0, i1 = np.flatnonzero(gone)[[0, -1]]
    assert d.warnings == [gap_sentence("mag", sess.t_mag[i0 - 1], sess.t_mag[i1 + 1]),
                          f"skipped {gone.sum()} rows with no sensor values"]
    assert d.n_mag == sess.n_mag - gone.sum() and d.n_imu == sess.n_imu


def test_gyro_cells_empty_for_a_stretch(tmp_path, sess):
    imu, mag = cells(sess)
    gone = (sess.t_imu >= 5.0) & (sess.t_imu < 7.0)
    imu[gone, 1:4] = ""  # acc and temperature still there: a partial IMU sample
    d = read_log(write_rows(tmp_path / "gyroout.csv", sess, imu, mag))
    i0, i1 = np.flatnonzero(gone)[[0, -1]]
    # The compass kept logging through the IMU's 2 s gap: those mag samples are not used across it (16.2).
    inside = (sess.t_mag > sess.t_imu[i0 - 1]) & (sess.t_mag < sess.t_imu[i1 + 1])
    assert d.warnings == [f"dropped {gone.sum()} IMU rows with NaN, inf or missing values",
                          gap_sentence("IMU", sess.t_imu[i0 - 1], sess.t_imu[i1 + 1]),
                          f"dropped {inside.sum()} mag samples inside IMU gaps longer than 0.5 s (not used to "
                          "update across the gap)"]
    assert d.n_imu == sess.n_imu - gone.sum() and d.n_mag == sess.n_mag - inside.sum()
    assert not np.any((d.t_mag > sess.t_imu[i0 - 1]) & (d.t_mag < sess.t_imu[i1 + 1]))


def test_imu_reading_zeros_for_half_a_second(tmp_path, sess):
    imu, mag = cells(sess)
    gone = (sess.t_imu >= 12.0) & (sess.t_imu < 12.5)
    imu[gone, 1:7] = "0"
    d = read_log(write_rows(tmp_path / "zeros.csv", sess, imu, mag))
    i0, i1 = np.flatnonzero(gone)[[0, -1]]
    inside = (sess.t_mag > sess.t_imu[i0 - 1]) & (sess.t_mag < sess.t_imu[i1 + 1])  # a 0.51 s IMU silence
    assert d.warnings == [f"dropped {gone.sum()} IMU rows of all zeros (sensor dropout)",  # 0.5 s: not a gap
                          f"dropped {inside.sum()} mag samples inside IMU gaps longer than 0.5 s (not used to "
                          "update across the gap)"]
    assert d.n_imu == sess.n_imu - gone.sum() == sess.n_imu - 50


def test_one_sensor_entirely_absent(tmp_path, sess):
    imu, mag = cells(sess)
    mag[:, 7:10] = ""
    d = read_log(write_rows(tmp_path / "nomag.csv", sess, imu, mag))
    assert d.n_mag == 0 and d.n_imu == sess.n_imu  # a log without a magnetometer is still a log
    assert d.warnings == [f"skipped {sess.n_mag} rows with no sensor values"]
    imu, mag = cells(sess)
    imu[:, 1:4] = ""
    e = error_of(write_rows(tmp_path / "nogyro.csv", sess, imu, mag))
    n = sess.n_imu
    assert e.message == (f"NaN, inf or missing values: {n} of {n} IMU rows unusable (dropped {n} IMU rows with "
                         f"NaN, inf or missing values)")


def test_tlog_with_broken_clock_same_policy(tmp_path, sess):
    # The drop policy is shared: a RAW_IMU log with repeated stamps and one stamp far ahead.
    d = ImuData(sess.t_imu.copy(), sess.gyro, sess.acc, sess.temp, sess.t_mag, sess.mag)
    d.t_imu[301::50] = d.t_imu[300:-1:50]
    d.t_imu[777] += 500.0
    p = tmp_path / "clock.tlog"
    write_log(p, d)
    back = read_log(p)
    n_rep = len(range(301, sess.n_imu, 50))
    assert "dropped 1 IMU messages stamped ahead of the samples after them (a lone jump forward in time)" \
        in back.warnings
    assert f"dropped {n_rep} IMU messages whose time did not increase ({n_rep} repeated)" in back.warnings
    assert back.n_imu == sess.n_imu - n_rep - 1


# --- not a log at all ---------------------------------------------------------------------------------

def test_wrong_format_behind_an_extension(tmp_path, sess):
    good = {}
    for ext in (".csv", ".tlog", ".bin"):
        good[ext] = tmp_path / f"good{ext}"
        write_log(good[ext], sess)
    expect = {
        (".csv", ".tlog"): "not a MAVLink telemetry log?",
        (".csv", ".bin"): "(FMT or other); not an ArduPilot .bin log?",
        (".tlog", ".csv"): "first line is not a CSV header (binary data; not a .csv file?)",
        (".tlog", ".bin"): "(FMT or other); not an ArduPilot .bin log?",
        (".bin", ".csv"): "first line is not a CSV header (binary data; not a .csv file?)",
        (".bin", ".tlog"): "not a MAVLink telemetry log?",
    }
    for (real, named), words in expect.items():
        p = tmp_path / f"{real[1:]}-as{named}"
        p.write_bytes(good[real].read_bytes())
        assert error_of(p).message.endswith(words), (real, named)


@pytest.mark.parametrize("ext", [".csv", ".tlog", ".bin"])
def test_empty_file_directory_and_missing_path(tmp_path, ext):
    empty = tmp_path / f"empty{ext}"
    empty.write_bytes(b"")
    assert error_of(empty).message == "empty file"
    folder = tmp_path / f"folder{ext}"
    folder.mkdir()
    assert error_of(folder).message == "cannot open: is a directory"
    assert error_of(tmp_path / f"missing{ext}").message == "cannot open: No such file or directory"


# --- the command line ---------------------------------------------------------------------------------

def _batch(*paths: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.Popen([sys.executable, "-m", "onlinecal", "batch", *map(str, paths)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
def test_cli_batch_on_damaged_logs(tmp_path, sess):
    from onlinecal.sim import simulate

    # A whole paper session (the batch needs one) with a dropout, NaN stamps, repeats and one stamp ahead.
    full = simulate("paper", seed=3).data
    imu, mag = cells(full)
    drop = (full.t_imu >= 12.0) & (full.t_imu < 12.5)
    imu[drop, 1:7] = "0"
    imu[100:105, 0] = "nan"
    imu[7001::97, 0] = imu[7000:-1:97, 0]
    imu[500, 0] = repr(float(full.t_imu[500]) + 1000.0)
    damaged = write_rows(tmp_path / "damaged.csv", full, imu, mag)
    n_rep = len(range(7001, full.n_imu, 97))

    header = tmp_path / "header.csv"
    header.write_text(",".join(COLUMNS) + "\n")
    empty = tmp_path / "empty.bin"
    empty.write_bytes(b"")
    text = tmp_path / "text.tlog"
    text.write_text(",".join(COLUMNS) + "\n0.1,1,2,3,4,5,6,,,,25\n")
    folder = tmp_path / "folder.csv"
    folder.mkdir()
    refused = [header, empty, text, folder, tmp_path / "missing.tlog"]
    runs = {p: _batch(p) for p in refused}
    runs[damaged] = _batch(damaged)
    if UNMOVED.is_file():
        runs[UNMOVED] = _batch(UNMOVED)
    res = {p: (proc.wait(timeout=120), *proc.communicate()) for p, proc in runs.items()}

    for p in refused:
        code, out, err = res[p]
        assert code == 2 and out == "" and "Traceback" not in err, (p, err)
        assert len(err.splitlines()) == 1 and err.startswith(f"onlinecal batch: {p}: "), (p, err)

    code, out, err = res[damaged]
    assert code == 0 and "Traceback" not in err, err
    # Each reader warning names its file (several logs of one unit are merged into one report).
    mine = f"warning: {damaged}: dropped"
    warned = [w.replace(f"{damaged}: ", "", 1) for w in err.splitlines() if w.startswith(mine)]
    assert warned == [
        f"warning: dropped {drop.sum()} IMU rows of all zeros (sensor dropout)",
        "warning: dropped 5 IMU rows with NaN, inf or missing values",
        f"warning: dropped {n_rep} IMU rows whose time did not increase ({n_rep} repeated)",
        "warning: dropped 1 IMU rows stamped ahead of the samples after them (a lone jump forward in time)",
        "warning: dropped 25 mag samples inside IMU gaps longer than 0.5 s (not used to update across the gap)",
    ]
    kept = full.n_imu - drop.sum() - 5 - n_rep - 1
    assert f"batch pipeline: {kept} IMU samples" in out

    if UNMOVED.is_file():
        code, out, err = res[UNMOVED]
        assert code == 0 and "Traceback" not in err, err
        lines = err.splitlines()
        assert lines[:2] == [f"warning: {UNMOVED}: dropped 720 IMU rows of all zeros (sensor dropout)",
                             f"warning: {UNMOVED}: dropped 168 mag rows of all zeros (sensor dropout)"]
        assert "batch pipeline: 6280 IMU samples" in out
