"""Issue 16.5: our own DataFlash parser (onlinecal.io.dfparse) decodes what pymavlink's DFReader decodes, field
by field, on simulated logs, on measured sessions written as .bin, on a hand-made ArduPilot flight log (IMU
instances, PARM, BAT, CTUN, ARM) and on damaged copies; and it reads a long log in bounded memory."""

from __future__ import annotations

import contextlib
import io
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from onlinecal.io import dfparse, read_log, write_dataflash
from onlinecal.io.dfparse import DataflashParser
from onlinecal.sim import simulate

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / ".." / "shared" / "data"
TYPES = {"IMU", "IMU2", "MAG", "PARM", "BAT", "CTUN", "ARM"}


def pymavlink_rows(path: Path, types: set[str]) -> dict[str, list[dict]]:
    """Every message of ``types`` as pymavlink's DFReader returns it, in log order (its prints silenced)."""
    from pymavlink import DFReader

    out: dict[str, list[dict]] = {}
    sink = io.StringIO()
    devnull = os.open(os.devnull, os.O_WRONLY)
    saved = os.dup(2)
    os.dup2(devnull, 2)
    try:
        with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
            dfr = DFReader.DFReader_binary(str(path), zero_time_base=True)
            while True:
                m = dfr.recv_match(type=sorted(types))
                if m is None:
                    break
                d = m.to_dict()
                out.setdefault(m.get_type(), []).append(d)
            dfr.data_map.close()
            dfr.filehandle.close()
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)
    return out


def our_rows(path: Path, types: set[str]) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = {}
    for stretch in DataflashParser(str(path), types):
        for r in stretch:
            names = [n for n in r.fmt.columns if r.fmt.has(n)]
            cols = {n: r.fmt.values(r.rows, n) if r.rows[n].dtype.kind in "iuf" else r.rows[n] for n in names}
            for k in range(r.rows.size):
                out.setdefault(r.fmt.name, []).append({n: cols[n][k] for n in names})
    # pymavlink's order within a type is the log's; ours too (stretches in order, records in order)
    return out


def assert_same(path: Path, types: set[str] = TYPES) -> int:
    """Field-by-field equality of the two decodes; returns the number of messages compared."""
    ref, ours = pymavlink_rows(path, types), our_rows(path, types)
    assert set(ref) == set(ours), (set(ref), set(ours))
    n = 0
    for typ, rows in ref.items():
        assert len(rows) == len(ours[typ]), (typ, len(rows), len(ours[typ]))
        for a, b in zip(rows, ours[typ], strict=True):
            for col, v in b.items():
                r = a[col]
                if isinstance(r, str):
                    assert r == v.split(b"\0", 1)[0].decode("ascii", "replace"), (typ, col)
                elif isinstance(r, float) and np.isnan(r):
                    assert np.isnan(v), (typ, col)
                else:
                    assert float(r) == pytest.approx(float(v), rel=1e-12, abs=1e-12), (typ, col, r, v)
            n += 1
    return n


@pytest.mark.slow
def test_simulated_flight_decodes_as_pymavlink(tmp_path):
    sim = simulate("flight", 2, duration=30, imu_rate=200.0, mag_rate=50.0)
    p = tmp_path / "f.bin"
    write_dataflash(p, sim.data)
    assert assert_same(p) == sim.data.n_imu + sim.data.n_mag


@pytest.mark.slow
@pytest.mark.parametrize("name", ["tilt-sphere.csv", "rotate-360ccw-around-z-pointing-up.csv"])
def test_measured_session_written_as_bin_decodes_as_pymavlink(tmp_path, name):
    src = DATA / "marg-set1" / name
    if not src.exists():
        pytest.skip(f"measured data not present: {src}")
    d = read_log(src)
    p = tmp_path / "m.bin"
    write_dataflash(p, d)
    assert assert_same(p) == d.n_imu + d.n_mag
    back = read_log(p)
    np.testing.assert_array_equal(back.gyro, d.gyro.astype(np.float32).astype(np.float64))
    np.testing.assert_allclose(back.t_imu, d.t_imu, atol=5e-7)


def test_handmade_ardupilot_flight_decodes_as_pymavlink(tmp_path):
    from tests.test_dataflash_flight import flight

    p = flight(tmp_path, params={"INS_ACCOFFS_X": 0.1, "COMPASS_OFS_Y": 12.0})
    assert assert_same(p) > 2000
    old = flight(tmp_path, old_names=True)
    assert assert_same(old) > 2000


@pytest.mark.parametrize("seed", range(6))
def test_damaged_log_decodes_as_pymavlink(tmp_path, seed):
    # Random bytes inserted, flipped and zeroed inside the records: both readers resynchronise on the next
    # record header and must keep the same messages.
    rng = np.random.default_rng(seed)
    sim = simulate("paper", seed, duration=20, imu_rate=100.0, mag_rate=50.0)
    p = tmp_path / "d.bin"
    write_dataflash(p, sim.data)
    raw = bytearray(p.read_bytes())
    for _ in range(5):
        i = int(rng.integers(300, len(raw) - 10))
        kind = rng.integers(3)
        if kind == 0:
            raw[i:i] = rng.bytes(int(rng.integers(1, 40)))
        elif kind == 1:
            raw[i] ^= int(rng.integers(1, 256))
        else:
            raw[i:i + 30] = bytes(30)
    p.write_bytes(bytes(raw))
    assert assert_same(p, {"IMU", "MAG"}) > 0.9 * (sim.data.n_imu + sim.data.n_mag)


@pytest.mark.slow
@pytest.mark.parametrize("chunk", [97, 1000, 4099])
def test_records_across_chunk_boundaries_are_all_read(tmp_path, monkeypatch, chunk):
    # A log many chunks long: no record is lost or doubled where a chunk ends inside it (a chunk even
    # shorter than a FMT record).
    sim = simulate("flight", 3, duration=20, imu_rate=200.0, mag_rate=50.0)
    p = tmp_path / "long.bin"
    write_dataflash(p, sim.data)
    whole = read_log(p)
    monkeypatch.setattr(dfparse, "CHUNK", chunk)
    assert p.stat().st_size > 50 * chunk
    back = read_log(p)
    assert back.n_imu == sim.data.n_imu and back.n_mag == sim.data.n_mag
    for name in ("t_imu", "gyro", "acc", "temp", "t_mag", "mag"):
        np.testing.assert_array_equal(getattr(back, name), getattr(whole, name))
    np.testing.assert_allclose(back.acc, sim.data.acc, rtol=1e-6)
    assert back.warnings == whole.warnings == []


# VmHWM: this process's own peak (ru_maxrss would carry the parent's peak, the simulated hour, across fork + exec)
_RSS = """
import sys
import time
from onlinecal.io import open_log
n = 0
for b in open_log(sys.argv[1]).blocks(4096):
    n += b.n_imu
print(n, [int(x.split()[1]) for x in open("/proc/self/status") if x.startswith("VmHWM:")][0])
"""


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads the peak memory from /proc (Linux)")
def test_reading_a_six_times_longer_log_takes_no_more_memory(tmp_path):
    # Streaming a one-hour 200 Hz log costs what a 10-minute one does (within 1.2x, issue 16.5): the
    # parser holds one chunk of the file and the blocks being built, never the whole log.
    peaks = {}
    for minutes in (10, 60):
        sim = simulate("flight", 1, duration=60.0 * minutes, imu_rate=200.0, mag_rate=50.0)
        p = tmp_path / f"{minutes}.bin"
        write_dataflash(p, sim.data)
        del sim
        env = {**os.environ, "PYTHONPATH": str(REPO)}
        r = subprocess.run([sys.executable, "-c", _RSS, str(p)], capture_output=True, text=True, env=env,
                           check=True)
        n, kb = map(int, r.stdout.split())
        assert n == int(round(minutes * 60 * 200)) + 1
        peaks[minutes] = kb
    assert peaks[60] <= 1.2 * peaks[10], peaks


def test_zero_tail_of_a_preallocated_logger_file_is_skipped_and_told(tmp_path):
    # A logger that pre-allocates its file leaves megabytes of zeros after the last record: they are walked
    # over in compiled code (pymavlink took 23 minutes on 2 GB of them) and told as zero bytes.
    sim = simulate("flight", 5, duration=10, imu_rate=200.0, mag_rate=50.0)
    p = tmp_path / "prealloc.bin"
    write_dataflash(p, sim.data)
    tail = 24 << 20
    with open(p, "ab") as f:
        f.write(bytes(tail))
    t0 = time.perf_counter()
    d = read_log(p)
    assert time.perf_counter() - t0 < 30.0  # ~1 s alone; generous for a shared machine
    assert d.n_imu == sim.data.n_imu and d.n_mag == sim.data.n_mag
    # every zero byte but the last two (too short to hold a record header) is counted
    assert d.warnings == [f"skipped {tail - 2} corrupt bytes that begin no DataFlash record ({tail - 2} of them "
                          "zero: an erased or pre-allocated stretch)"]
