"""Issue 12.6: PX4 ULog through pyulog, on the real log in shared/data (pyulog's own BSD test log: 69 s,
AUAV-X2.1, sensor_combined at about 248 Hz). Physical checks, not values copied from the reader."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from onlinecal.io import LogError, open_log, read_log
from onlinecal.io.ulog import _combined, _raw_imu

SAMPLE = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "px4-ulog" / "sample.ulg"
needs_data = pytest.mark.skipif(not SAMPLE.is_file(), reason="shared/data/px4-ulog/sample.ulg not present")
G = 9.80665


@needs_data
def test_real_ulog_sample_reads_with_physical_values():
    d = read_log(SAMPLE)
    # The README: 69 s at about 248 Hz.
    assert d.duration == pytest.approx(69.0, abs=1.0)
    assert d.imu_rate == pytest.approx(248.0, rel=0.02)
    assert np.all(np.diff(d.t_imu) > 0) and np.all(np.diff(d.t_mag) > 0)
    # Quiet start (vehicle on the ground): |a| = g within 2 %, |ω| under 0.02 rad/s, steady.
    a0 = np.linalg.norm(d.acc[:500], axis=1)
    assert np.median(a0) == pytest.approx(G, rel=0.02) and np.std(a0) < 0.1
    assert np.median(np.linalg.norm(d.gyro[:500], axis=1)) < 0.02
    # Earth's field in gauss (0.25-0.65 G everywhere on Earth), sampled at its own rate, not the IMU's.
    assert 0.25 < np.median(np.linalg.norm(d.mag, axis=1)) < 0.65
    assert 50.0 < d.n_mag / d.duration < 150.0
    # The log's parameters carried with the data, PX4's own calibration among them; the warning says the
    # sensor_combined values are already corrected by it.
    assert d.params["CAL_ACC0_XSCALE"] > 0.5 and "CAL_GYRO0_XOFF" in d.params
    assert any("sensor_combined" in w and "already corrected" in w for w in d.warnings)


@needs_data
def test_ulog_streams_in_bounded_blocks_and_refuses_a_missing_instance(tmp_path):
    blocks = list(open_log(SAMPLE).blocks(max_samples=1000))
    assert max(b.n_imu for b in blocks) <= 1000 and sum(b.n_imu for b in blocks) == read_log(SAMPLE).n_imu
    with pytest.raises(LogError) as e:
        read_log(SAMPLE, imu=1)
    assert "no sensor_gyro/sensor_accel instance 1" in e.value.message


def test_not_a_ulog_is_refused_with_one_line(tmp_path):
    p = tmp_path / "x.ulg"
    p.write_bytes(b"\0" * 1000)
    with pytest.raises(LogError) as e:
        open_log(p)
    assert "no ULog header" in e.value.message


def test_raw_topics_accel_interpolated_onto_gyro_times():
    tg = np.arange(0, 1_000_000, 1000)  # µs: gyro 1 kHz
    ta = np.arange(500, 1_000_000, 2000)  # accel 500 Hz, its own clock
    g = {"timestamp": tg + 50, "timestamp_sample": tg, "x": np.ones(tg.size), "y": np.zeros(tg.size),
         "z": np.zeros(tg.size), "temperature": np.full(tg.size, 41.0)}
    a = {"timestamp": ta, "x": ta * 1e-6, "y": np.zeros(ta.size), "z": np.full(ta.size, -G)}
    t, gyro, acc, temp = _raw_imu(g, a)
    np.testing.assert_allclose(t, tg * 1e-6)  # timestamp_sample, not the publication time
    inside = (t >= ta[0] * 1e-6) & (t <= ta[-1] * 1e-6)
    np.testing.assert_allclose(acc[inside, 0], t[inside], atol=1e-12)  # a linear signal is exact
    assert np.all(np.isnan(acc[~inside, 0]))  # never extrapolated: dropped by the reader's policy
    assert np.all(temp == 41.0)


def test_sensor_combined_mag_is_one_sample_per_new_stamp():
    t = np.arange(10) * 4000 + 1_000_000
    c = {"timestamp": t, **{f"gyro_rad[{k}]": np.zeros(10) for k in range(3)},
         **{f"accelerometer_m_s2[{k}]": np.full(10, 1.0) for k in range(3)},
         "accelerometer_timestamp_relative": np.zeros(10),
         **{f"magnetometer_ga[{k}]": np.repeat([0.1, 0.2, 0.3, 0.4, 0.5], 2) for k in range(3)},
         "magnetometer_timestamp_relative": np.tile([0, -4000], 5)}
    *_, tm, mag = _combined(c)
    assert tm.size == 5 and np.all(np.diff(tm) > 0)
    np.testing.assert_allclose(mag[:, 0], [0.1, 0.2, 0.3, 0.4, 0.5])
