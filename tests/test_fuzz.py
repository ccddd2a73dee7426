"""The readers under random damage (issue 5): byte flips, insertions, deletions, truncations, zeroed blocks and
swapped chunks of a real ``.tlog``, ``.bin`` and ``.csv`` written by onlinecal's own writers from a short
simulated session, and of one measured CSV read from ``../shared/data``.

Property, for every damaged file: ``read_log`` either returns an :class:`ImuData` that keeps the readers'
promises (shapes, float64, finite values, strictly increasing times per sensor, no all-zero readings — see
``onlinecal.io.validate``) or raises :class:`LogError` whose text is one line naming the file; no other
exception, no output on the terminal, and no hang: every read runs under a SIGALRM watchdog and a read
that takes longer than ``CASE_LIMIT_S`` fails the test instead of hanging CI.

Reproducible: hypothesis runs derandomized (examples follow from the test's source) without a database.
Longer fuzzing locally, e.g. 20000 cases per format::

    ONLINECAL_FUZZ_EXAMPLES=20000 python -m pytest tests/test_fuzz.py -s -q

(``-s`` shows the per-format counts; ``ONLINECAL_FUZZ_SEED=N`` switches the derandomized sequence to
hypothesis' random one under seed N, for a different set of cases.)
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, seed, settings
from hypothesis import strategies as st

from onlinecal.io import ImuData, LogError, read_log, write_log
from onlinecal.io.dataflash import IMU_FORMAT, MAG_FORMAT, _record_dtype

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
REAL_CSV = DATA / "marg-set1" / "rotate-360ccw-around-y-pointing-left.csv"  # the smallest measured session

# Cases per format. The defaults keep the whole file near 60 s on 2 busy cores (the .bin reader is the
# slowest, ~15 ms per read of pymavlink's per-message Python).
EXAMPLES = {"tlog": 1200, "bin": 1000, "csv": 1500, "real-csv": 1200}
if os.environ.get("ONLINECAL_FUZZ_EXAMPLES"):
    EXAMPLES = dict.fromkeys(EXAMPLES, int(os.environ["ONLINECAL_FUZZ_EXAMPLES"]))
FUZZ_SEED = os.environ.get("ONLINECAL_FUZZ_SEED")
CASE_LIMIT_S = 5.0  # a healthy read of these files takes < 0.1 s: 5 s is a hang, not a slow machine

EXT = {"tlog": ".tlog", "bin": ".bin", "csv": ".csv", "real-csv": ".csv"}


# --- the damage --------------------------------------------------------------------------------------

_POS = st.integers(0, 2**32 - 1)  # taken modulo the file length: small values hit the header, large anywhere
_OPS = st.one_of(
    st.tuples(st.just("flip"), _POS, st.integers(1, 255)),  # XOR one byte with a mask
    st.tuples(st.just("insert"), _POS, st.binary(min_size=1, max_size=16)),
    st.tuples(st.just("delete"), _POS, st.integers(1, 64)),
    st.tuples(st.just("truncate"), _POS, st.just(0)),
    st.tuples(st.just("zero"), _POS, st.integers(1, 512)),
    st.tuples(st.just("swap"), _POS, st.tuples(_POS, st.integers(1, 256))),  # exchange two chunks
)
MUTATIONS = st.lists(_OPS, min_size=1, max_size=4)


def mutate(data: bytes, ops: list[tuple]) -> bytes:
    b = bytearray(data)
    for kind, pos, arg in ops:
        if not b:
            break
        i = pos % len(b)
        if kind == "flip":
            b[i] ^= arg
        elif kind == "insert":
            b[i:i] = arg
        elif kind == "delete":
            del b[i:i + arg]
        elif kind == "truncate":
            del b[i:]
        elif kind == "zero":
            n = min(arg, len(b) - i)
            b[i:i + n] = bytes(n)
        elif kind == "swap":
            j, n = arg[0] % len(b), arg[1]
            i, j = min(i, j), max(i, j)
            n = min(n, j - i, len(b) - j)
            if n > 0:
                b[i:i + n], b[j:j + n] = b[j:j + n], b[i:i + n]
    return bytes(b)


# --- the property ------------------------------------------------------------------------------------

class _Hang(BaseException):
    """Raised by the watchdog; a BaseException so no reader's ``except Exception`` can swallow it."""


def _on_alarm(signum, frame):
    raise _Hang


def read_guarded(path: Path) -> tuple[ImuData | None, LogError | None, float]:
    """read_log under the watchdog → (data, None, seconds) or (None, error, seconds)."""
    old = signal.signal(signal.SIGALRM, _on_alarm)
    signal.setitimer(signal.ITIMER_REAL, CASE_LIMIT_S)
    t0 = time.perf_counter()
    try:
        return read_log(path), None, time.perf_counter() - t0
    except LogError as e:
        return None, e, time.perf_counter() - t0
    except _Hang:
        raise AssertionError(f"read_log did not return within {CASE_LIMIT_S} s (a hang)") from None
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def assert_valid(d: ImuData, path: Path) -> None:
    """What every reader promises about the data it returns (onlinecal.io.base / validate)."""
    n, m = d.n_imu, d.n_mag
    assert n >= 1  # no IMU sample at all is a LogError
    assert d.source == str(path)
    shapes = {"t_imu": (n,), "gyro": (n, 3), "acc": (n, 3), "temp": (n,), "t_mag": (m,), "mag": (m, 3)}
    for name, shape in shapes.items():
        a = getattr(d, name)
        assert a.shape == shape and a.dtype == np.float64, (name, a.shape, a.dtype)
    for name in ("t_imu", "gyro", "acc", "t_mag", "mag"):
        assert np.isfinite(getattr(d, name)).all(), name
    assert not np.isinf(d.temp).any()  # a temperature is a number or NaN ("not given")
    assert np.all(np.diff(d.t_imu) > 0) and np.all(np.diff(d.t_mag) > 0)
    assert not np.any(np.all(np.hstack([d.gyro, d.acc]) == 0, axis=1))  # all-zero reads are dropouts
    assert not np.any(np.all(d.mag == 0, axis=1))
    for w in d.warnings:
        assert isinstance(w, str) and w and w.splitlines() == [w], w


def assert_one_line_error(e: LogError, path: Path) -> None:
    msg = str(e)
    assert msg.splitlines() == [msg], msg
    assert e.path == str(path) and msg.startswith(f"{path}: ") and e.message
    assert len(msg) <= len(str(path)) + 400, msg


# --- the files ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def bases(tmp_path_factory) -> dict[str, bytes]:
    """The undamaged files: a 2-s simulated paper session (201 IMU, 100 mag samples) in each format."""
    from onlinecal.sim import simulate

    d = simulate("paper", seed=5, duration=2.0).data
    folder = tmp_path_factory.mktemp("fuzz-bases")
    out = {}
    for kind in ("tlog", "bin", "csv"):
        p = folder / f"base{EXT[kind]}"
        write_log(p, d)
        back = read_log(p)  # the base is a good file: every sample comes back
        assert back.n_imu == d.n_imu == 201
        out[kind] = p.read_bytes()
    if REAL_CSV.is_file():
        out["real-csv"] = REAL_CSV.read_bytes()
    return out


@pytest.mark.slow
@pytest.mark.parametrize("kind", list(EXAMPLES))
def test_damaged_files_give_data_or_one_line_error(kind, bases, tmp_path, capfd):
    if kind not in bases:
        pytest.skip(f"measured data not present at {REAL_CSV}")
    base = bases[kind]
    path = tmp_path / f"case{EXT[kind]}"
    outcome: Counter[str] = Counter()
    times: list[float] = []
    slowest: list = []

    @settings(max_examples=EXAMPLES[kind], derandomize=FUZZ_SEED is None, database=None, deadline=None,
              phases=[Phase.explicit, Phase.generate], suppress_health_check=list(HealthCheck))
    @given(ops=MUTATIONS)
    def one_case(ops):
        path.write_bytes(mutate(base, ops))
        data, err, dt = read_guarded(path)
        times.append(dt)
        if dt >= max(times):
            slowest[:] = [ops]
        if err is None:
            assert_valid(data, path)
            outcome["data"] += 1
        else:
            assert_one_line_error(err, path)
            outcome["error"] += 1

    if FUZZ_SEED is not None:
        one_case = seed(int(FUZZ_SEED))(one_case)
    one_case()
    out, err = capfd.readouterr()
    assert out == "" and err == "", (out[:300], err[:300])  # pymavlink's complaints stay off the terminal
    n = len(times)
    with capfd.disabled():
        print(f"\n[fuzz {kind}] {n} damaged files: {outcome['data']} read as data, {outcome['error']} LogError; "
              f"per read mean {1e3 * np.mean(times):.1f} ms, max {1e3 * max(times):.1f} ms "
              f"(damage {slowest[0]!r:.200})")
    assert n == EXAMPLES[kind] == outcome["data"] + outcome["error"]
    # Both outcomes occur: the damage neither always breaks the files nor never touches the data.
    assert outcome["data"] >= 0.05 * n and outcome["error"] >= 0.01 * n, outcome


# --- what fuzzing found, kept as regressions -----------------------------------------------------------

def _bin_records(raw: bytes) -> list[tuple[int, int]]:
    """(offset, message id) of each record after the three FMT records of onlinecal's .bin writer."""
    size = {100: _record_dtype(*IMU_FORMAT[1:]).itemsize, 101: _record_dtype(*MAG_FORMAT[1:]).itemsize}
    out, o = [], 3 * 89
    while o < len(raw):
        out.append((o, raw[o + 2]))
        o += size[raw[o + 2]]
    return out


@pytest.mark.parametrize("fmt_at", [89, 178], ids=["IMU-FMT", "MAG-FMT"])
def test_bin_fmt_declaring_length_zero_is_an_error_not_a_hang(bases, tmp_path, fmt_at):
    # A FMT record with Length 0 made pymavlink return the same message for ever (found by the fuzzer); its
    # indexer also stops there, so nothing after it can be read: a LogError at that byte.
    raw = bytearray(bases["bin"])
    assert raw[fmt_at:fmt_at + 3] == b"\xa3\x95\x80"
    raw[fmt_at + 4] = 0  # Length
    p = tmp_path / "len0.bin"
    p.write_bytes(bytes(raw))
    data, err, _ = read_guarded(p)
    assert data is None
    assert_one_line_error(err, p)
    assert err.where == f"byte {fmt_at}" and "index of the log stops here" in err.message


def test_bin_fmt_with_more_columns_than_formats_is_an_error(bases, tmp_path):
    # pymavlink's field access raised IndexError (not AttributeError) for such a FMT: a traceback before.
    raw = bytearray(bases["bin"])
    cols_at = 89 + 3 + 1 + 1 + 4 + 16  # IMU FMT: header, Type, Length, Name[4], Format[16], Columns[64]
    raw[cols_at:cols_at + 64] = b"TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AS,I".ljust(64, b"\0")
    p = tmp_path / "cols.bin"
    p.write_bytes(bytes(raw))
    data, err, _ = read_guarded(p)
    assert data is None
    assert_one_line_error(err, p)
    assert err.where == "byte 321, message 1"  # the end of the first IMU message: 3 FMT records + 54 bytes
    assert err.message.startswith("IMU message without a usable field (IndexError")


def test_bin_lone_timestamp_corrupted_into_the_future_drops_one_sample(bases, tmp_path):
    # A flipped high byte of one TimeUS used to make every later sample "go backwards" (> half: error).
    raw = bytearray(bases["bin"])
    imu = [o for o, k in _bin_records(bytes(raw)) if k == 100]
    raw[imu[50] + 3 + 5] ^= 0x01  # TimeUS byte 5: + 2**40 µs ≈ 12.7 days
    p = tmp_path / "ahead.bin"
    p.write_bytes(bytes(raw))
    d = read_log(p)
    assert d.n_imu == 200
    assert d.warnings == ["dropped 1 IMU messages stamped ahead of the samples after them (a lone jump forward "
                          "in time)"]


def test_tlog_swapped_chunk_loses_only_the_moved_packets(bases, tmp_path):
    # Two 300-byte chunks exchanged: the later chunk's packets now sit early, stamped ahead of the samples
    # after them. They are dropped (with the early chunk's packets, now behind), not the 100 in between.
    raw = bases["tlog"]
    i, j, n = 2000, 9000, 300
    swapped = raw[:i] + raw[j:j + n] + raw[i + n:j] + raw[i:i + n] + raw[j + n:]
    p = tmp_path / "swap.tlog"
    p.write_bytes(swapped)
    d = read_log(p)
    whole = 201
    packets_per_chunk = n / (len(raw) / (whole + 3))  # RAW_IMU and 3 HEARTBEATs, ~same size
    assert whole - 4 * packets_per_chunk - 2 <= d.n_imu < whole
    assert any("stamped ahead" in w for w in d.warnings)
    assert any("going backwards" in w for w in d.warnings)


# --- the command line ---------------------------------------------------------------------------------

@pytest.mark.slow
def test_cli_batch_on_damaged_files_exits_2_with_one_line(bases, tmp_path):
    raw_bin = bytearray(bases["bin"])
    raw_bin[89 + 9] = ord("\\")  # the IMU FMT's first format character: one pymavlink does not know
    csv_lines = bases["csv"].decode().splitlines(keepends=True)
    csv_lines[40] = "0.39,0.1,oops,0.3,0.1,0.2,9.8,,,,25\n"
    cases = {
        "cut.tlog": bases["tlog"][:20],  # inside the first packet (a HEARTBEAT)
        "noise.tlog": np.random.default_rng(3).bytes(20_000),
        "badfmt.bin": bytes(raw_bin),
        "len0.bin": bases["bin"][:89 + 4] + b"\x00" + bases["bin"][89 + 5:],
        "binary.csv": bases["tlog"],
    }
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    procs = {}
    for name, content in cases.items():
        p = tmp_path / name
        p.write_bytes(content)
        procs[name] = (p, subprocess.Popen([sys.executable, "-m", "onlinecal", "batch", str(p)], env=env,
                                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    said = {}
    for name, (p, proc) in procs.items():
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 2, (name, out, err)
        assert "Traceback" not in err and out == "", (name, err)
        lines = err.splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"onlinecal batch: {p}: "), (name, err)
        said[name] = lines[0]
    assert "no MAVLink message in its 20 bytes" in said["cut.tlog"]
    assert "not a MAVLink telemetry log" in said["noise.tlog"]
    assert "Unsupported format char" in said["badfmt.bin"]
    assert ": byte 93: " not in said["len0.bin"] and ": byte 89: no IMU messages read" in said["len0.bin"]
    assert ": line 1: first line is not a CSV header (binary data" in said["binary.csv"]
