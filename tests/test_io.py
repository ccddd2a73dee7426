"""Log readers and writers on real files: round trips, the shared data set, streaming, bad input."""

from __future__ import annotations

import struct
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from onlinecal.io import ImuData, LogError, open_log, read_log, write_log
from onlinecal.io.csv import COLUMNS, write_csv
from onlinecal.io.dataflash import write_dataflash
from onlinecal.io.mavlink import G0
from onlinecal.io.tlog import write_tlog

DATA = Path(__file__).parents[1].parent / "shared" / "data"
MARG = DATA / "marg-set1"
FERRARIS = DATA / "ferraris" / "imucal-example-session.csv"
needs_data = pytest.mark.skipif(not MARG.is_dir(), reason=f"shared data set not found at {DATA}")


def synth(n: int = 2000, rate: float = 100.0, mag_every: int = 3, seed: int = 0) -> ImuData:
    """A plausible IMU+mag stream: gyro ~0.5 rad/s noise, acc ≈ gravity, mag ≈ 0.5 gauss, 25-30 °C."""
    rng = np.random.default_rng(seed)
    t = 0.5 + np.arange(n) / rate
    t_mag = t[::mag_every] + 0.3 / rate
    return ImuData(
        t_imu=t,
        gyro=rng.normal(0.0, 0.5, (n, 3)),
        acc=rng.normal(0.0, 1.0, (n, 3)) + [0.0, 0.0, 9.81],
        temp=25.0 + 5.0 * np.arange(n) / n,
        t_mag=t_mag,
        mag=rng.normal(0.0, 0.2, (t_mag.size, 3)) + [0.2, 0.0, 0.4],
        source="synth",
    )


def assert_same(a: ImuData, b: ImuData) -> None:
    for name in ("t_imu", "gyro", "acc", "temp", "t_mag", "mag"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def csv_text(rows: list[str], header: str = ",".join(COLUMNS)) -> str:
    return header + "\n" + "\n".join(rows) + "\n"


def imu_row(t: float, g: float = 0.01, a: float = 9.8, temp: str = "25.0") -> str:
    return f"{t},{g},{-g},{2 * g},0.1,-0.2,{a},,,,{temp}"


def mag_row(t: float, m: float = 0.3) -> str:
    return f"{t},,,,,,,{m},{-m},{2 * m},"


# --- round trips -----------------------------------------------------------------------------------

def test_csv_round_trip_is_exact(tmp_path):
    d = synth()
    p = tmp_path / "s.csv"
    write_log(p, d)
    back = read_log(p)
    assert_same(back, d)
    assert back.warnings == []
    text = p.read_text().splitlines()
    assert text[0] == ",".join(COLUMNS)
    assert len(text) == 1 + d.n_imu + d.n_mag  # IMU and mag rows kept apart, none lost


def test_csv_columns_by_name_optional_mag_and_temp(tmp_path):
    p = tmp_path / "reordered.csv"
    p.write_text("acc_z,acc_y,acc_x,time_s,gyro_z,gyro_y,gyro_x,extra\n"
                 "9.8,0.2,0.1,0.01,3,2,1,x\n"
                 "9.7,0.3,0.2,0.02,6,5,4,y\n")
    d = read_log(p)
    np.testing.assert_array_equal(d.t_imu, [0.01, 0.02])
    np.testing.assert_array_equal(d.gyro, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(d.acc, [[0.1, 0.2, 9.8], [0.2, 0.3, 9.7]])
    assert np.all(np.isnan(d.temp)) and d.n_mag == 0


def test_csv_row_with_both_sensors_and_scale(tmp_path):
    p = tmp_path / "both.csv"
    p.write_text(csv_text(["0.1,1,2,3,4,5,6,0.5,0.6,0.7,20", imu_row(0.2), mag_row(0.25)]))
    d = read_log(p, gyro_scale=2.0, mag_scale=1000.0)
    np.testing.assert_array_equal(d.t_imu, [0.1, 0.2])
    np.testing.assert_array_equal(d.t_mag, [0.1, 0.25])
    np.testing.assert_allclose(d.gyro[0], [2, 4, 6])
    np.testing.assert_allclose(d.mag[0], [500, 600, 700])
    np.testing.assert_array_equal(d.acc[0], [4, 5, 6])


def test_tlog_round_trip_within_unit_quantisation(tmp_path):
    d = synth(n=1500)
    p = tmp_path / "s.tlog"
    write_log(p, d)
    back = read_log(p)
    assert back.n_imu == d.n_imu
    np.testing.assert_allclose(back.t_imu, d.t_imu, atol=0.6e-6, rtol=0)
    np.testing.assert_allclose(back.acc, d.acc, atol=0.5 * G0 * 1e-3 + 1e-12, rtol=0)  # 1 mG
    np.testing.assert_allclose(back.gyro, d.gyro, atol=0.5e-3 + 1e-12, rtol=0)  # 1 mrad/s
    np.testing.assert_allclose(back.temp, d.temp, atol=0.005 + 1e-9, rtol=0)  # 1 c°C
    # RAW_IMU carries the mag sample-and-hold at the IMU rate; the reader keeps the changes.
    j = np.searchsorted(d.t_mag, d.t_imu, side="right") - 1
    held = np.where((j >= 0)[:, None], np.rint(d.mag[np.maximum(j, 0)] * 1e3), 0)
    change = np.any(held != np.vstack([[np.nan] * 3, held[:-1]]), axis=1) & np.any(held != 0, axis=1)
    assert back.n_mag == change.sum() > 0
    np.testing.assert_allclose(back.t_mag, d.t_imu[change], atol=0.6e-6, rtol=0)
    np.testing.assert_allclose(back.mag, held[change] * 1e-3, atol=1e-12, rtol=0)  # 1 mgauss
    assert np.max(np.abs(back.mag - d.mag[j[change]])) <= 0.5e-3 + 1e-12


def test_tlog_clips_to_int16_and_encodes_temperature(tmp_path):
    d = synth(n=50)
    d.acc[10] = [40 * G0, -40 * G0, 9.81]  # beyond ±32.767 g
    d.temp[:] = np.nan
    d.temp[20] = 0.0
    p = tmp_path / "clip.tlog"
    write_tlog(p, d)
    back = read_log(p)
    np.testing.assert_allclose(back.acc[10, :2], [32767 * G0 * 1e-3, -32768 * G0 * 1e-3])
    # NaN is sent as 0 ("no temperature") and comes back NaN; 0 °C is sent as 0.01 °C.
    assert np.isnan(back.temp[0]) and back.temp[20] == pytest.approx(0.01)


def test_tlog_written_file_is_what_pymavlink_sees(tmp_path):
    from pymavlink import mavutil

    d = synth(n=250)  # 2.5 s of data → heartbeats at 0, 1 and 2 s
    p = tmp_path / "s.tlog"
    write_tlog(p, d, system_id=7)
    conn = mavutil.mavlogfile(str(p))
    kinds: dict[str, int] = {}
    first = None
    while (m := conn.recv_match(blocking=False)) is not None:
        kinds[m.get_type()] = kinds.get(m.get_type(), 0) + 1
        if first is None:
            first = m
    conn.close()
    assert kinds == {"HEARTBEAT": 3, "RAW_IMU": 250}
    assert first.get_type() == "HEARTBEAT" and first.get_srcSystem() == 7
    raw = p.read_bytes()
    assert raw[8] == 0xFD  # MAVLink 2 magic after the 8-byte timestamp


def _mav2():
    from pymavlink.dialects.v20 import ardupilotmega

    return ardupilotmega.MAVLink(None, srcSystem=1, srcComponent=1)


def _tlog_write(path: Path, msgs: list[tuple[int, object]], mav) -> None:
    out = bytearray()
    for us, msg in msgs:
        out += struct.pack(">Q", 1_700_000_000_000_000 + us) + msg.pack(mav)
        mav.seq = (mav.seq + 1) % 256
    path.write_bytes(bytes(out))


def test_tlog_prefers_raw_imu_id0_and_names_the_others(tmp_path):
    mav = _mav2()
    msgs = []
    for i in range(300):
        ms = 1000 + 10 * i
        msgs.append((ms * 1000, mav.scaled_imu2_encode(ms, 0, 0, 2000, 1, 1, 1, 100, 0, 0, 3000)))
        msgs.append((ms * 1000, mav.raw_imu_encode(ms * 1000, 10, 20, 1000, 1, 2, 3, 0, 0, 0, 0, 2500)))
    p = tmp_path / "two.tlog"
    _tlog_write(p, msgs, mav)
    r = open_log(p)
    d = ImuData.concat(r.blocks(100))
    assert d.n_imu == 300
    np.testing.assert_allclose(d.acc[0], np.array([10, 20, 1000]) * G0 * 1e-3)
    np.testing.assert_allclose(d.t_imu[:2], [1.0, 1.01])
    assert d.n_mag == 0  # all-zero mag means no compass: no samples, and no error
    assert any("SCALED_IMU2" in w and "ignored" in w for w in r.warnings)
    assert any(w.startswith("300 of 300 RAW_IMU messages carried a mag of exact zeros")
               for w in r.warnings)


def test_tlog_mavlink1_raw_imu_without_extensions(tmp_path):
    from pymavlink.dialects.v20 import ardupilotmega as m2

    out = bytearray()
    for i in range(50):
        # A MAVLink 1 RAW_IMU as old firmware sends it: the 26-byte base payload, no id/temperature.
        payload = struct.pack("<Q9h", 20_000 * i, -5, 7, 1001, 10, -20, 30, 200, -100 - (i // 5), 400)
        frame = bytes([len(payload), i % 256, 1, 1, m2.MAVLINK_MSG_ID_RAW_IMU]) + payload
        crc = m2.x25crc(frame)
        crc.accumulate(bytes([m2.MAVLink_raw_imu_message.crc_extra]))
        out += struct.pack(">Q", 1_700_000_000_000_000 + 20_000 * i) + b"\xfe" + frame
        out += struct.pack("<H", crc.crc)
    p = tmp_path / "v1.tlog"
    p.write_bytes(bytes(out))
    assert p.read_bytes()[8] == 0xFE  # MAVLink 1: no id/temperature extensions on the wire
    d = read_log(p)
    assert d.n_imu == 50 and np.all(np.isnan(d.temp))
    np.testing.assert_allclose(d.gyro[0], [0.010, -0.020, 0.030])
    assert d.n_mag == 10  # the mag changed every 5th message
    np.testing.assert_allclose(d.mag[-1], [0.2, -0.109, 0.4])


def test_tlog_highres_imu_honours_fields_updated(tmp_path):
    mav = _mav2()
    msgs = []
    for i in range(400):
        us = 2_000_000 + 5000 * i
        bits = 0x3F | (0x1C0 if i % 4 == 0 else 0) | (0x1000 if i == 0 else 0)
        msgs.append((us, mav.highres_imu_encode(us, 0.1, 0.2, 9.8, 0.01, 0.02, 0.03, 0.2 + i * 1e-4, 0.0, 0.4,
                                                1013.0, 0.0, 0.0, 31.5 if i == 0 else 99.0, bits, 0)))
    p = tmp_path / "hr.tlog"
    _tlog_write(p, msgs, mav)
    d = read_log(p, acc_scale=2.0)
    assert d.n_imu == 400 and d.n_mag == 100
    np.testing.assert_allclose(d.acc[5], [0.2, 0.4, 19.6], rtol=1e-6)  # SI, times the override
    np.testing.assert_allclose(d.gyro[5], [0.01, 0.02, 0.03], rtol=1e-6)
    np.testing.assert_allclose(d.t_mag[:2], [2.0, 2.02])
    assert np.all(d.temp == np.float32(31.5))  # held from the one update, later values not flagged


def test_tlog_scale_override_replaces_default(tmp_path):
    d = synth(n=100)
    p = tmp_path / "s.tlog"
    write_tlog(p, d)
    default, scaled = read_log(p), read_log(p, acc_scale=1.0, gyro_scale=1.0, mag_scale=1.0)
    np.testing.assert_allclose(scaled.acc, default.acc / (G0 * 1e-3))  # raw mG counts
    np.testing.assert_allclose(scaled.gyro, default.gyro * 1e3)
    np.testing.assert_allclose(scaled.mag, default.mag * 1e3)


def test_dataflash_round_trip(tmp_path):
    d = synth(n=3000)
    p = tmp_path / "s.bin"
    write_log(p, d)
    assert p.read_bytes()[:3] == b"\xa3\x95\x80"
    back = read_log(p)
    assert back.warnings == []
    np.testing.assert_allclose(back.t_imu, d.t_imu, atol=0.6e-6, rtol=0)
    np.testing.assert_allclose(back.gyro, d.gyro, rtol=1e-6, atol=1e-7)  # float32
    np.testing.assert_allclose(back.acc, d.acc, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(back.temp, d.temp, rtol=1e-6)
    np.testing.assert_allclose(back.t_mag, d.t_mag, atol=0.6e-6, rtol=0)
    np.testing.assert_allclose(back.mag, d.mag, atol=0.5e-3 + 1e-12, rtol=0)  # int16 mgauss


def _df_fmt(msg_id: int, name: str, fmt: str, cols: str, length: int) -> bytes:
    return b"\xa3\x95\x80" + struct.pack("<BB4s16s64s", msg_id, length, name.encode(), fmt.encode(),
                                         cols.encode())


def test_dataflash_reads_instance_zero_of_a_hand_made_log(tmp_path):
    # Built with struct rather than the package's writer, so the reader is checked against the format.
    imu = struct.Struct("<QBffffffIIfBBHH")
    mag = struct.Struct("<QBhhhhhhhhhBI")
    out = bytearray(_df_fmt(0x80, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns", 89))
    out += _df_fmt(17, "IMU", "QBffffffIIfBBHH",
                   "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz", 3 + imu.size)
    out += _df_fmt(29, "MAG", "QBhhhhhhhhhBI",
                   "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S", 3 + mag.size)
    for i in range(200):
        us = 10_000_000 + 2500 * i
        for inst in (0, 1):
            out += b"\xa3\x95\x11" + imu.pack(us, inst, 0.5 + inst, 0, 0, 0, 0, -9.75, 0, 0, 40.0 + inst,
                                              1, 1, 400, 400)
        if i % 8 == 0:
            out += b"\xa3\x95\x1d" + mag.pack(us + 100, 0, 150 + i, -20, 410, 0, 0, 0, 0, 0, 0, 1, 0)
    p = tmp_path / "hand.bin"
    p.write_bytes(bytes(out))
    r = open_log(p)
    d = ImuData.concat(r.blocks(64))
    assert d.n_imu == 200 and d.n_mag == 25
    np.testing.assert_allclose(d.gyro[:, 0], 0.5)
    np.testing.assert_allclose(d.acc[:, 2], -9.75)
    np.testing.assert_allclose(d.temp, 40.0)
    np.testing.assert_allclose(d.t_imu[:2], [10.0, 10.0025])
    np.testing.assert_allclose(d.mag[1], [0.158, -0.020, 0.410])  # milligauss → gauss
    assert any("IMU instance 1" in w for w in r.warnings)


# --- the shared real data set ---------------------------------------------------------------------

def _direct_counts(path: Path) -> tuple[np.ndarray, int, int, int, int]:
    """Independent of the reader: numpy's own CSV parser, cells counted by hand."""
    a = np.genfromtxt(path, delimiter=",", names=True)
    imu = np.column_stack([a[c] for c in ("gyro_x", "gyro_y", "gyro_z", "acc_x", "acc_y", "acc_z")])
    mag = np.column_stack([a[c] for c in ("mag_x", "mag_y", "mag_z")])
    imu_rows = ~np.all(np.isnan(imu), axis=1)
    mag_rows = ~np.all(np.isnan(mag), axis=1)
    imu_zero = imu_rows & np.all(imu == 0, axis=1)
    mag_zero = mag_rows & np.all(mag == 0, axis=1)
    return a, int(imu_rows.sum()), int(imu_zero.sum()), int(mag_rows.sum()), int(mag_zero.sum())


@needs_data
@pytest.mark.parametrize("path", sorted(MARG.glob("*.csv")) + [FERRARIS], ids=lambda p: p.name)
def test_real_csv_counts_and_values(path):
    a, n_imu, n_imu_zero, n_mag, n_mag_zero = _direct_counts(path)
    d = read_log(path)
    assert d.n_imu == n_imu - n_imu_zero
    assert d.n_mag == n_mag - n_mag_zero
    # The kept samples are exactly numpy's parse of the non-zero rows.
    keep = ~np.isnan(a["gyro_x"]) & ~((a["gyro_x"] == 0) & (a["gyro_y"] == 0) & (a["gyro_z"] == 0)
                                      & (a["acc_x"] == 0) & (a["acc_y"] == 0) & (a["acc_z"] == 0))
    np.testing.assert_array_equal(d.t_imu, a["time_s"][keep])
    np.testing.assert_array_equal(d.acc[:, 2], a["acc_z"][keep])
    assert np.all(np.diff(d.t_imu) > 0) and np.all(np.diff(d.t_mag) > 0)
    if n_imu_zero == 0 and n_mag_zero == 0:
        assert d.warnings == []


@needs_data
def test_real_csv_zero_rows_are_dropped_with_a_warning_on_every_block():
    path = MARG / "unmoved-z-pointing-left.csv"
    r = open_log(path)
    blocks = []
    for b in r.blocks(1000):
        # The 720 zero rows open the file, so the count is final by the first block.
        assert "dropped 720 IMU rows of all zeros (sensor dropout)" in b.warnings
        assert b.n_imu <= 1000
        blocks.append(b)
    assert len(blocks) == 7
    d = ImuData.concat(blocks)
    assert d.n_imu == 7000 - 720 and d.t_imu[0] > 0
    assert "dropped 168 mag rows of all zeros (sensor dropout)" in r.warnings


@needs_data
def test_real_ferraris_session_has_no_mag_no_temperature():
    d = read_log(FERRARIS)
    assert d.n_imu == 10376 and d.n_mag == 0 and np.all(np.isnan(d.temp))
    assert d.imu_rate == pytest.approx(102.4, rel=1e-3)


# --- streaming -------------------------------------------------------------------------------------

@pytest.mark.parametrize("ext,n", [(".csv", 30000), (".tlog", 3000), (".bin", 6000)])
def test_blocks_are_bounded_and_concat_to_read_log(tmp_path, ext, n):
    d = synth(n=n, mag_every=2, seed=3)
    p = tmp_path / f"long{ext}"
    write_log(p, d)
    blocks = list(open_log(p).blocks(max_samples=700))
    sizes = [b.n_imu for b in blocks]
    assert max(sizes) <= 700 and sum(sizes) == n
    assert len(blocks) == -(-n // 700)
    for b in blocks[:-1]:  # a block's mag samples lie in its IMU time span (up to its last IMU time)
        assert b.n_mag == 0 or b.t_mag[-1] <= b.t_imu[-1]
    whole = read_log(p)
    assert_same(ImuData.concat(blocks), whole)


@pytest.mark.slow
def test_csv_streaming_memory_does_not_grow_with_the_log(tmp_path):
    peaks = []
    for n in (20000, 80000):
        p = tmp_path / f"m{n}.csv"
        write_csv(p, synth(n=n, mag_every=2))
        reader = open_log(p)
        tracemalloc.start()
        total = 0
        for b in reader.blocks(1000):
            total += b.n_imu
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
        assert total == n
    # 4x the rows must not mean 4x the memory: the reader holds a chunk, not the log.
    assert peaks[1] < 1.5 * peaks[0], peaks


# --- bad input -------------------------------------------------------------------------------------

def _error(path, **kw) -> str:
    with pytest.raises(LogError) as exc:
        read_log(path, **kw)
    msg = str(exc.value)
    assert "\n" not in msg and str(path) in msg
    return msg


@pytest.mark.parametrize("ext", [".csv", ".tlog", ".bin"])
def test_missing_and_empty_files(tmp_path, ext):
    assert "cannot open" in _error(tmp_path / f"nope{ext}")
    p = tmp_path / f"empty{ext}"
    p.write_bytes(b"")
    assert "empty file" in _error(p)


def test_unknown_extension(tmp_path):
    p = tmp_path / "x.log"
    p.write_text("whatever")
    assert "unknown log format '.log'" in _error(p)


def test_csv_header_only_and_bad_headers(tmp_path):
    p = tmp_path / "h.csv"
    p.write_text(",".join(COLUMNS) + "\n")
    assert "no IMU samples" in _error(p)
    p.write_text("time_s,gyro_x,gyro_y,acc_x,acc_y,acc_z\n0,1,2,3,4,5\n")
    assert "line 1" in (m := _error(p)) and "gyro_z" in m
    p.write_text(imu_row(0.0) + "\n" + imu_row(0.01) + "\n")
    assert "no header line" in _error(p)
    p.write_text(csv_text([mag_row(0.1), mag_row(0.2)]))
    assert "no IMU samples" in _error(p)


def test_csv_garbage_row_in_the_middle_is_skipped_and_named(tmp_path):
    """Issue 12/16.5: one malformed row no longer aborts the file; it is skipped with a counted warning that
    names it. A file that is mostly malformed is still refused."""
    rows = [imu_row(0.01 * i) for i in range(1, 50)]
    rows[20] = "0.21,0.1,oops,0.3,0.1,0.2,9.8,,,,25"  # line 22 of the file (header is line 1)
    rows[30] = "0.31,0.1,0.2"  # line 32: too few cells
    rows[35] = imu_row(0.36) + ",1.0"  # line 37: an extra field
    p = tmp_path / "g.csv"
    p.write_text(csv_text(rows))
    d = read_log(p)
    assert d.n_imu == 46 and 0.21 not in d.t_imu and 0.31 not in d.t_imu and 0.36 not in d.t_imu
    said = [w for w in d.warnings if "malformed" in w]
    assert len(said) == 1 and said[0].startswith("skipped 3 malformed rows (the first, line 22: column 'gyro_y'")
    rows = [imu_row(0.01 * i) if i % 3 == 0 else "0.1,0.2" for i in range(1, 50)]
    p.write_text(csv_text(rows))
    msg = _error(p)
    assert "33 of 49 rows malformed" in msg and "line 2" in msg and "found 2" in msg


def test_csv_binary_tail_stops_reading_without_loading_it_as_a_line(tmp_path):
    """A valid CSV followed by binary data (a pre-allocated logger file): the rows before are read, the tail
    is not held as one line (before: 4.3 GB of memory for a 2 GB tail)."""
    import tracemalloc

    rows = [imu_row(0.001 * i) for i in range(1, 10001)]
    p = tmp_path / "late.csv"
    p.write_text(csv_text(rows))
    with open(p, "ab") as f:
        f.write(b"\x00" * (64 << 20))  # 64 MiB of zeros, no newline
    tracemalloc.start()
    d = read_log(p)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert d.n_imu == 10000
    assert any("stopped reading at line 10002: binary data" in w for w in d.warnings)
    assert peak < 32 << 20, peak  # far less than the 64 MiB tail
    rows[9000] = "\x00\x01binary junk"  # binary in the middle: the rows before it are kept
    p.write_text(csv_text(rows))
    d = read_log(p)
    assert d.n_imu == 9000 and any("line 9002" in w for w in d.warnings)


def test_csv_truncated_last_line_is_dropped_with_a_warning(tmp_path):
    rows = [imu_row(0.01 * i) for i in range(1, 11)]
    p = tmp_path / "t.csv"
    p.write_text(csv_text(rows) + "0.11,0.01,-0.0")  # a write cut short: no newline, too few cells
    d = read_log(p)
    assert d.n_imu == 10
    assert any("line 12" in w and "cut short" in w for w in d.warnings)
    p.write_text(csv_text(rows) + "0.11,0.01,-0.01,0.0x")  # cut inside a number
    assert read_log(p).n_imu == 10
    p.write_text(csv_text(rows) + imu_row(0.11))  # complete, merely no final newline: kept
    d = read_log(p)
    assert d.n_imu == 11 and d.warnings == []
    p.write_text(csv_text(rows) + "0.11,0.01,-0.0\n")  # same short line WITH a newline: a malformed row
    d = read_log(p)
    assert d.n_imu == 10 and any("skipped 1 malformed rows (the first, line 12" in w for w in d.warnings)


def test_csv_nan_inf_and_missing_cells_drop_that_sensor_sample(tmp_path):
    rows = [imu_row(0.01 * i) for i in range(1, 21)] + [mag_row(0.01 * i + 0.005) for i in range(1, 21)]
    rows[3] = "0.04,nan,0.1,0.1,0.1,0.1,9.8,,,,25"
    rows[5] = "0.06,0.1,0.1,0.1,0.1,inf,9.8,,,,25"
    rows[7] = "0.08,0.1,0.1,0.1,,0.1,9.8,,,,25"  # a partial IMU sample
    rows[9] = "0.1,0.1,0.1,0.1,0.1,0.1,9.8,,,,NaN"  # no temperature: kept, temp NaN
    rows[25] = "0.065,,,,,,,0.3,-inf,0.6,"
    rows.sort(key=lambda r: float(r.split(",")[0]))
    p = tmp_path / "nan.csv"
    p.write_text(csv_text(rows))
    d = read_log(p)
    assert d.n_imu == 17 and d.n_mag == 19
    assert np.all(np.isfinite(d.gyro)) and np.all(np.isfinite(d.acc)) and np.all(np.isfinite(d.mag))
    assert np.isnan(d.temp[d.t_imu == 0.1]).all()
    assert "dropped 3 IMU rows with NaN, inf or missing values" in d.warnings
    assert "dropped 1 mag rows with NaN, inf or missing values" in d.warnings


def test_csv_repeated_and_backward_timestamps(tmp_path):
    times = [0.01 * i for i in range(1, 31)]
    times[10] = times[9]  # repeat
    times[20] = times[19]  # repeat
    times[25] = 0.05  # back in time
    times[26] = 0.0  # back in time
    rows = [imu_row(t) for t in times]
    p = tmp_path / "ts.csv"
    p.write_text(csv_text(rows))
    d = read_log(p)
    assert d.n_imu == 26 and np.all(np.diff(d.t_imu) > 0)
    assert "dropped 4 IMU rows whose time did not increase (2 repeated, 2 going backwards)" in d.warnings
    # A gap is not an error.
    p.write_text(csv_text([imu_row(0.01), imu_row(0.02), imu_row(100.0), imu_row(100.01)]))
    assert read_log(p).n_imu == 4
    # Mostly backwards: unusable.
    p.write_text(csv_text([imu_row(t) for t in [5.0, 6.0] + [0.1 * i for i in range(1, 10)]]))
    assert "timestamps not increasing" in _error(p)


def test_csv_mostly_zero_rows_is_an_error(tmp_path):
    rows = [imu_row(0.01), imu_row(0.02)] + ["0,0,0,0,0,0,0,,,,0"] * 5
    p = tmp_path / "z.csv"
    p.write_text(csv_text(rows))
    assert "sensor dropout" in _error(p)


@pytest.mark.parametrize("ext", [".csv", ".tlog", ".bin"])
def test_random_bytes_are_a_log_error(tmp_path, ext, capfd):
    p = tmp_path / f"random{ext}"
    p.write_bytes(np.random.default_rng(11).bytes(50_000))
    _error(p)
    # pymavlink's complaints about bad bytes (thousands of lines) are kept off the terminal.
    out, err = capfd.readouterr()
    assert len(err.splitlines()) + len(out.splitlines()) < 3, err[:500]


def test_tlog_truncated_mid_message_reads_what_is_there(tmp_path):
    d = synth(n=400)
    p = tmp_path / "t.tlog"
    write_tlog(p, d)
    raw = p.read_bytes()
    # Packets: 8-byte timestamp + RAW_IMU; cut in the middle of the 300th RAW_IMU.
    pos, n_raw = 0, 0
    while n_raw < 300:
        plen = raw[pos + 9]
        msgid = int.from_bytes(raw[pos + 15:pos + 18], "little")
        n_raw += msgid == 27  # RAW_IMU
        pos += 8 + 12 + plen
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(raw[:pos - 7])
    back = read_log(cut)
    assert back.n_imu == 299
    np.testing.assert_allclose(back.t_imu, d.t_imu[:299], atol=1e-6)


def test_tlog_corrupt_packets_are_skipped(tmp_path):
    d = synth(n=300)
    p = tmp_path / "c.tlog"
    write_tlog(p, d)
    raw = bytearray(p.read_bytes())
    raw[len(raw) // 2] ^= 0xFF  # one flipped byte: that packet fails its CRC
    p.write_bytes(bytes(raw))
    back = read_log(p)
    assert 295 <= back.n_imu < 300
    assert any("could not decode" in w for w in back.warnings)


def test_dataflash_truncated_mid_message_reads_what_is_there(tmp_path):
    d = synth(n=500)
    d.t_mag, d.mag = d.t_mag[:0], d.mag[:0]
    p = tmp_path / "t.bin"
    write_dataflash(p, d)
    raw = p.read_bytes()
    header = 3 * 89
    rec = (len(raw) - header) // 500
    cut = tmp_path / "cut.bin"
    cut.write_bytes(raw[:header + 321 * rec + rec // 2])
    back = read_log(cut)
    assert back.n_imu == 321
    np.testing.assert_allclose(back.acc, d.acc[:321], rtol=1e-6)


def test_slice_imu_chunks_partition_the_mag_samples() -> None:
    # A mag clock that does not divide the IMU clock puts mag samples between two chunks' IMU stamps;
    # chunked feeding (replay --chunk, live blocks) must neither lose nor double them.
    from onlinecal.sim import simulate

    d = simulate("paper", 1, duration=20, imu_rate=100, mag_rate=37).data
    for size in (1, 7, 173, d.n_imu):
        parts = [d.slice_imu(i, i + size) for i in range(0, d.n_imu, size)]
        joined = ImuData.concat(parts)
        assert joined.n_imu == d.n_imu
        np.testing.assert_array_equal(joined.t_mag, d.t_mag)
        np.testing.assert_array_equal(joined.mag, d.mag)
