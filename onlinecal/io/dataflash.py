"""ArduPilot DataFlash binary logs (``.bin``): read IMU and MAG in bounded blocks, and write minimal logs.

Read through pymavlink's DFReader:

* ``IMU`` — TimeUS µs, GyrX/Y/Z rad/s, AccX/Y/Z m/s², T °C; the instance ``imu`` (field ``I``; logs from
  before the ``I`` field name the second and third IMU ``IMU2``/``IMU3``, read as instances 1 and 2).
* ``MAG`` — TimeUS µs, MagX/Y/Z milligauss (× 1e-3 → gauss); instance 0, the primary compass, whatever
  the IMU instance (a compass is its own chip; old logs name the others ``MAG2``/``MAG3``).
* ``PARM`` — Name, Value: ``ImuData.params`` (the firmware's parameters at the time, e.g. its own
  calibration INS_ACCOFFS_X, COMPASS_OFS_X, ...). When they hold a non-default calibration a warning says
  that the logged values are already corrected by it.
* Optional series (``ImuData.series``, on the last block): ``current`` A (BAT/CURR ``Curr``), ``throttle``
  0..1 (CTUN ``ThO``, else RCOU ``C3`` PWM 1000-2000 µs), ``armed`` 0/1 (ARM ``ArmState``, else EV ids 10
  ARMED / 11 DISARMED).

``acc_scale``/``gyro_scale``/``mag_scale`` replace the default multipliers (1, 1, 1e-3).

Note that ArduPilot logs IMU and MAG values *after* its own calibration (accel offsets/scales, compass
offsets and matrices): a calibration fitted on them is relative to the autopilot's.

DFReader maps the file and indexes every message up front (a few bytes per message); the blocks this
reader builds are bounded as for the other formats. pymavlink reports corrupt stretches by printing;
that output is kept off the terminal and summed into a warning.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from onlinecal.io.base import ImuData, LogError
from onlinecal.io.validate import LOOKAHEAD, BlockAssembler, SampleFilter, check_file, probe_head

HEAD = b"\xa3\x95"
FMT_ID = 0x80
IMU_ID = 100  # ArduPilot assigns ids per build; DFReader only needs them to match the FMT records
MAG_ID = 101
# (name, format, columns) as ArduPilot 4.x logs them.
FMT_FORMAT = ("FMT", "BBnNZ", "Type,Length,Name,Format,Columns")
IMU_FORMAT = ("IMU", "QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz")
MAG_FORMAT = ("MAG", "QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S")
_NP = {"Q": "<u8", "q": "<i8", "B": "u1", "b": "i1", "M": "u1", "f": "<f4", "d": "<f8", "I": "<u4", "i": "<i4",
       "H": "<u2", "h": "<i2", "n": "S4", "N": "S16", "Z": "S64"}  # DataFlash format characters
_SKIPPED = re.compile(r"Skipped (\d+) bad bytes")
_IMU_FIELDS = ("GyrX", "GyrY", "GyrZ", "AccX", "AccY", "AccZ")
_OLD_NAMES = {"IMU2": ("IMU", 1), "IMU3": ("IMU", 2), "MAG2": ("MAG", 1), "MAG3": ("MAG", 2)}
_READ = ["IMU", "IMU2", "IMU3", "MAG", "MAG2", "MAG3", "PARM", "BAT", "CURR", "CTUN", "RCOU", "ARM", "EV"]
_EV_ARMED, _EV_DISARMED = 10, 11  # ArduPilot LogEvent ids
# The firmware's own calibration: (parameter prefix, its default); a value off the default means the logged
# IMU/MAG values were corrected with it.
_CAL_DEFAULTS = (("INS_ACCOFFS", 0.0), ("INS_ACC2OFFS", 0.0), ("INS_ACC3OFFS", 0.0), ("INS_ACCSCAL", 1.0),
                 ("INS_ACC2SCAL", 1.0), ("INS_ACC3SCAL", 1.0), ("INS_GYROFFS", 0.0), ("INS_GYR2OFFS", 0.0),
                 ("INS_GYR3OFFS", 0.0), ("COMPASS_OFS", 0.0), ("COMPASS_DIA", 1.0), ("COMPASS_ODI", 0.0),
                 ("COMPASS_OFS2", 0.0), ("COMPASS_OFS3", 0.0), ("COMPASS_MOT", 0.0))


def calibration_params(params: dict[str, float]) -> dict[str, float]:
    """The firmware-calibration parameters among ``params`` that are off their default (INS_ACCOFFS_*,
    INS_ACCSCAL_*, INS_GYROFFS_*, COMPASS_OFS_*, COMPASS_DIA_*, COMPASS_ODI_*, ... as ArduPilot names them)."""
    out = {}
    for name, v in params.items():
        for prefix, default in _CAL_DEFAULTS:
            if name.startswith(prefix + "_") and abs(float(v) - default) > 1e-9:
                out[name] = float(v)
    return out
_MAG_FIELDS = ("MagX", "MagY", "MagZ")


@contextlib.contextmanager
def _captured_output(fd_level: bool = False) -> Iterator[io.StringIO]:
    """Capture what pymavlink prints. ``fd_level`` also silences file descriptor 2, where the compiled
    DataFlash indexer writes one line per bad byte; only used around the (non-yielding) constructor."""
    buf = io.StringIO()
    saved = None
    if fd_level:
        try:
            sys.stderr.flush()
            devnull = os.open(os.devnull, os.O_WRONLY)
        except (OSError, ValueError):
            devnull = None
        if devnull is not None:
            try:
                saved = os.dup(2)
                os.dup2(devnull, 2)
            except OSError:  # no fd 2 to silence: nothing to restore either
                if saved is not None:
                    os.close(saved)
                saved = None
            finally:
                os.close(devnull)
    try:
        with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
            yield buf
    finally:
        if saved is not None:
            os.dup2(saved, 2)
            os.close(saved)


_GUARDED: type | None = None


def _guarded_reader_class() -> type:
    """pymavlink's ``DFReader_binary`` with a parser that always moves forward.

    A FMT record declaring a message length of 0 bytes (only a corrupt one does: the header alone is 3)
    makes pymavlink's ``_parse_next`` return a message without advancing, so its readers loop for ever
    on it. Here such a message is dropped and parsing resumes one byte later, as pymavlink itself does
    for bytes it cannot parse; ``stalls`` counts them.
    """
    global _GUARDED
    if _GUARDED is None:
        from pymavlink import DFReader

        class GuardedDFReader(DFReader.DFReader_binary):
            stalls = 0
            offset: int  # set by DFReader_binary.__init__ (pymavlink is untyped: mypy cannot infer it)

            def _parse_next(self) -> Any:
                while True:
                    start = int(getattr(self, "offset"))  # noqa: B009 - pymavlink's untyped attribute
                    m = super()._parse_next()
                    if m is None or int(getattr(self, "offset")) > start:  # noqa: B009
                        return m
                    self.stalls += 1
                    self.offset = start + 1
                    self.remaining = self.data_len - self.offset

        _GUARDED = GuardedDFReader
    return _GUARDED


class DataflashReader:
    """Streaming reader of one IMU instance (``imu``, default 0) and its MAG of one DataFlash ``.bin`` log."""

    def __init__(self, path: str | Path, acc_scale: float | None = None, gyro_scale: float | None = None,
                 mag_scale: float | None = None, imu: int = 0) -> None:
        self.path = str(path)
        self.imu = int(imu)
        self.warnings: list[str] = []
        self.scale = {
            "acc": 1.0 if acc_scale is None else float(acc_scale),
            "gyro": 1.0 if gyro_scale is None else float(gyro_scale),
            "mag": 1e-3 if mag_scale is None else float(mag_scale),
        }
        self._si_units = acc_scale is None and gyro_scale is None
        check_file(self.path)
        # A DataFlash log starts with its FMT records: one must be in the first megabytes.
        probe_head(self.path, lambda head: HEAD + bytes([FMT_ID]) in head,
                   "no DataFlash record in {span} (FMT or other); not an ArduPilot .bin log?")

    def blocks(self, max_samples: int = 4096) -> Iterator[ImuData]:
        """Yield ImuData blocks of at most ``max_samples`` IMU samples, in log order."""
        filt = SampleFilter(self.path, unit="messages", lookahead=LOOKAHEAD, gaps=True,
                            limits=self._si_units)
        self.warnings = filt.warnings
        asm = BlockAssembler(self.path, filt.warnings, max_samples, filt)
        skipped = 0
        try:
            with _captured_output(fd_level=True):
                dfr = _guarded_reader_class()(self.path, zero_time_base=True)
        except Exception as e:
            raise LogError(self.path, f"not a readable DataFlash log: {type(e).__name__}: {e}") from None
        stalls0 = dfr.stalls  # those of the constructor's own passes over the log are counted again below
        unindexed = _unindexed_from(dfr)
        batch = _Batch(self.path, self.imu)
        asm.params = batch.params  # filled as PARM records are read (they come first in a log)
        flush_every = max(1, min(max_samples, 1 << 14))
        try:
            done = False
            while not done:
                # Read a batch with pymavlink's prints captured, then hand it on outside the capture
                # (never yield while stdout/stderr are redirected).
                with _captured_output() as out:
                    done = batch.read(dfr, flush_every)
                skipped += sum(int(k) for k in _SKIPPED.findall(out.getvalue()))
                self._flush(batch, filt, asm)
                yield from asm.pop()
        finally:
            with contextlib.suppress(Exception):
                dfr.data_map.close()
                dfr.filehandle.close()
        if unindexed is not None:
            rest = dfr.data_len - unindexed
            if batch.n_imu_msg == 0:
                raise LogError(self.path, f"no IMU messages read: pymavlink's index of the log stops here, {rest} "
                               f"bytes before the end (a corrupt FMT record?)", f"byte {unindexed}")
            filt.note(f"pymavlink's index of the log stops at byte {unindexed} (a corrupt FMT record?); the "
                      f"remaining {rest} bytes were not read")
        if batch.n_imu_msg == 0:
            if not _n_records(dfr):
                raise LogError(self.path, "no DataFlash record in it (FMT or other); not an ArduPilot .bin log?")
            raise LogError(self.path, "no IMU messages in the log")
        if batch.n_imu_read == 0:
            have = sorted({int(x.split()[-1]) for x in batch.other if x.startswith("IMU")})
            raise LogError(self.path, f"no IMU instance {self.imu} in the log (instances: "
                           f"{', '.join(map(str, have)) or 'none'}); pick one with --imu N")
        if batch.other:
            filt.note(f"read IMU instance {self.imu} and MAG instance 0; ignored {', '.join(sorted(batch.other))}")
        onboard = calibration_params(batch.params)
        if onboard:
            shown = ", ".join(f"{k}={v:g}" for k, v in list(onboard.items())[:6])
            filt.note(f"the log's parameters hold the firmware's own calibration ({shown}"
                      f"{', ...' if len(onboard) > 6 else ''}): the logged IMU/MAG values are already corrected "
                      f"by it, so a calibration fitted here is a residual on top of it")
        asm.series = batch.series()
        if skipped:
            filt.note(f"skipped {skipped} corrupt bytes that pymavlink could not parse")
        if dfr.stalls > stalls0:
            filt.note(f"skipped {dfr.stalls - stalls0} messages whose FMT record declares a length of 0 bytes "
                      f"(corrupt)")
        if batch.mag_unusable:
            filt.note(f"magnetometer not read: {batch.mag_unusable}")
        asm.add(*filt.flush())
        filt.finish()
        yield from asm.pop(final=True)

    def _flush(self, batch: _Batch, filt: SampleFilter, asm: BlockAssembler) -> None:
        a = np.asarray(batch.imu, np.float64).reshape(-1, 8)
        b = np.asarray(batch.mag, np.float64).reshape(-1, 4)
        batch.imu, batch.mag = [], []
        s = self.scale
        asm.add(filt.imu(a[:, 0], a[:, 1:4] * s["gyro"], a[:, 4:7] * s["acc"], a[:, 7]),
                filt.mag(b[:, 0], b[:, 1:4] * s["mag"]))


class _Batch:
    """Rows of the chosen IMU/MAG instance read from a DFReader since the last flush, and running counts."""

    def __init__(self, path: str, imu: int = 0) -> None:
        self.path = path
        self.want = imu
        self.imu: list[tuple] = []  # (t s, gyro xyz, acc xyz, T)
        self.mag: list[tuple] = []  # (t s, mag xyz in file units)
        self.other: set[str] = set()  # instances seen and not read
        self.n_msg = 0
        self.n_imu_msg = 0
        self.n_imu_read = 0
        self.mag_unusable = ""  # why MAG messages are not read, once one proved unreadable
        self.params: dict[str, float] = {}
        self._series: dict[str, list[tuple[float, float]]] = {}
        self._throttle_from: str | None = None
        self._armed_from: str | None = None

    def series(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        out = {}
        for k, rows in self._series.items():
            a = np.asarray(rows, np.float64).reshape(-1, 2)
            out[k] = (a[:, 0], a[:, 1])
        return out

    def _aux(self, typ: str, m: Any) -> None:
        """PARM and the optional series; a record lacking the fields is skipped (other firmware versions)."""
        if typ == "PARM":
            name, value = getattr(m, "Name", None), getattr(m, "Value", None)
            if isinstance(name, str) and value is not None and np.isfinite(float(value)):
                self.params[name] = float(value)
            return
        t = _time_s(m)
        if typ in ("BAT", "CURR") and getattr(m, "Curr", None) is not None:
            if typ == "BAT" and int(getattr(m, "Inst", getattr(m, "Instance", 0)) or 0) != 0:
                return
            self._series.setdefault("current", []).append((t, float(m.Curr)))
        elif typ == "CTUN" and getattr(m, "ThO", None) is not None and self._throttle_from in (None, "CTUN"):
            self._throttle_from = "CTUN"
            self._series.setdefault("throttle", []).append((t, float(m.ThO)))
        elif typ == "RCOU" and getattr(m, "C3", None) is not None and self._throttle_from in (None, "RCOU"):
            self._throttle_from = "RCOU"
            self._series.setdefault("throttle", []).append((t, min(max((float(m.C3) - 1000.0) / 1000.0, 0.0),
                                                                   1.0)))
        elif typ == "ARM" and getattr(m, "ArmState", None) is not None:
            if self._armed_from != "ARM":  # ARM is the direct record: it replaces what EV said
                self._armed_from = "ARM"
                self._series["armed"] = []
            self._series["armed"].append((t, float(bool(m.ArmState))))
        elif typ == "EV" and self._armed_from in (None, "EV") and getattr(m, "Id", None) in (_EV_ARMED,
                                                                                               _EV_DISARMED):
            self._armed_from = "EV"
            self._series.setdefault("armed", []).append((t, float(m.Id == _EV_ARMED)))

    def read(self, dfr: Any, limit: int) -> bool:
        """Read until ``limit`` rows are held; True when the log has ended."""
        while len(self.imu) + len(self.mag) < limit:
            where = f"byte {getattr(dfr, 'offset', '?')}, message {self.n_msg + 1}"
            try:
                m = dfr.recv_match(type=_READ)
            except Exception as e:
                raise LogError(self.path, f"pymavlink failed: {type(e).__name__}: {e}", where) from None
            if m is None:
                return True
            self.n_msg += 1
            typ = m.get_type()
            if typ not in ("IMU", "IMU2", "IMU3", "MAG", "MAG2", "MAG3"):
                with contextlib.suppress(Exception):  # a damaged optional record never stops the log
                    self._aux(typ, m)
                continue
            base, old_inst = _OLD_NAMES.get(typ, (typ, None))
            if base == "MAG" and self.mag_unusable:
                continue
            try:
                inst = _instance(m) if old_inst is None else old_inst
                t = _time_s(m)
                if base == "IMU":
                    self.n_imu_msg += 1
                    if inst == self.want:
                        self.n_imu_read += 1
                        temp = float(getattr(m, "T", getattr(m, "Temp", float("nan"))))
                        self.imu.append((t, *(float(getattr(m, f)) for f in _IMU_FIELDS), temp))
                    else:
                        self.other.add(f"IMU instance {inst}")
                else:
                    if inst == 0:
                        self.mag.append((t, *(float(getattr(m, f)) for f in _MAG_FIELDS)))
                    else:
                        self.other.add(f"MAG instance {inst}")
            except Exception as e:  # pymavlink's field access on a corrupt FMT: AttributeError, IndexError, ...
                # Fields come from the FMT record, so every message of this type is alike: a broken
                # schema, not one bad message. IMU is required; MAG is optional and is then not read.
                where = f"byte {getattr(dfr, 'offset', '?')}, message {self.n_msg}"  # the message's end
                problem = (f"{typ} message without a usable field ({type(e).__name__}: {e}); its FMT record "
                           f"is corrupt or not ArduPilot's")
                if base == "IMU":
                    raise LogError(self.path, problem, where) from None
                self.mag_unusable = f"{problem}, first at {where}"
        return False


def _unindexed_from(dfr: Any) -> int | None:
    """The byte where pymavlink's index of the log ends, if message headers follow it (None if not).

    pymavlink's indexer stops at the first FMT record it cannot use (a declared length under 3): what
    follows is never read, and would otherwise be lost without a word."""
    try:
        ends = [int(o[-1]) + int(dfr.formats[t].len) for t, o in enumerate(dfr.offsets)
                if len(o) and t in dfr.formats]
        end = max(ends, default=0)
        if end < dfr.data_len and dfr.data_map.find(HEAD, end) >= 0:
            return end
    except Exception:  # an index pymavlink laid out differently: no claim either way
        return None
    return None


def _n_records(dfr: Any) -> int:
    """Records pymavlink indexed (any type); -1 if its index is laid out differently."""
    try:
        return int(sum(dfr.counts))
    except Exception:
        return -1


def _time_s(m: Any) -> float:
    t = getattr(m, "TimeUS", None)
    if t is not None:
        return float(t) * 1e-6
    t = getattr(m, "TimeMS", None)  # logs before TimeUS (ArduPilot < 3.3)
    if t is None:
        raise AttributeError("neither TimeUS nor TimeMS")
    return float(t) * 1e-3


def _instance(m: Any) -> int:
    i = getattr(m, "I", 0)
    if isinstance(i, float) and not i.is_integer():
        raise ValueError(f"instance I = {i!r} is not an integer")
    return int(i)


def _record_dtype(fmt: str, columns: str) -> np.dtype:
    names = columns.split(",")
    fields = [("h1", "u1"), ("h2", "u1"), ("id", "u1")]
    fields += [(n, _NP[c]) for n, c in zip(names, fmt, strict=True)]
    return np.dtype(fields)  # packed: numpy adds no padding unless align=True


def _fmt_record(msg_id: int, name: str, fmt: str, columns: str) -> bytes:
    length = _record_dtype(fmt, columns).itemsize if name != "FMT" else 89
    rec = np.zeros(1, np.dtype([("h", "u1", 3), ("Type", "u1"), ("Length", "u1"), ("Name", "S4"),
                                ("Format", "S16"), ("Columns", "S64")]))
    rec["h"] = [HEAD[0], HEAD[1], FMT_ID]
    rec["Type"], rec["Length"] = msg_id, length
    rec["Name"], rec["Format"], rec["Columns"] = name.encode(), fmt.encode(), columns.encode()
    return rec.tobytes()


def write_dataflash(path: str | Path, data: ImuData) -> None:
    """Write ``data`` as a minimal ArduPilot DataFlash log: FMT records for FMT, IMU and MAG, then IMU
    (instance 0; gyro rad/s, acc m/s², T °C as float32) and MAG (instance 0; int16 milligauss, rounded
    and clipped) records merged in time order. TimeUS = round(t µs); times must be ≥ 0."""
    for t in (data.t_imu, data.t_mag):
        if t.size and (not np.all(np.isfinite(t)) or t.min() < 0):
            raise ValueError("write_dataflash needs finite, non-negative times")
    di = _record_dtype(IMU_FORMAT[1], IMU_FORMAT[2])
    dm = _record_dtype(MAG_FORMAT[1], MAG_FORMAT[2])
    imu = np.zeros(data.n_imu, di)
    imu["h1"], imu["h2"], imu["id"] = HEAD[0], HEAD[1], IMU_ID
    imu["TimeUS"] = np.rint(data.t_imu * 1e6).astype(np.uint64)
    for k, c in enumerate("XYZ"):
        imu[f"Gyr{c}"] = data.gyro[:, k]
        imu[f"Acc{c}"] = data.acc[:, k]
    imu["T"] = data.temp
    imu["GH"] = imu["AH"] = 1
    rate = data.imu_rate
    imu["GHz"] = imu["AHz"] = int(np.clip(round(rate), 0, 65535)) if np.isfinite(rate) else 0
    mag = np.zeros(data.n_mag, dm)
    mag["h1"], mag["h2"], mag["id"] = HEAD[0], HEAD[1], MAG_ID
    mag["TimeUS"] = np.rint(data.t_mag * 1e6).astype(np.uint64)
    mq = np.clip(np.rint(data.mag * 1e3), -32768, 32767).astype(np.int16) if data.n_mag else None
    for k, c in enumerate("XYZ"):
        if mq is not None:
            mag[f"Mag{c}"] = mq[:, k]
    mag["Health"] = 1
    # Merge by time (IMU first on ties): scatter both record arrays into one byte buffer.
    t = np.concatenate([imu["TimeUS"], mag["TimeUS"]])
    order = np.argsort(t, kind="stable")
    size = np.where(order < data.n_imu, di.itemsize, dm.itemsize)
    start = np.concatenate([[0], np.cumsum(size)[:-1]]).astype(np.int64)
    pos = np.empty_like(start)
    pos[order] = start
    body = np.zeros(int(size.sum()), np.uint8)
    for recs, p in ((imu, pos[: data.n_imu]), (mag, pos[data.n_imu:])):
        if recs.size:
            raw = recs.view(np.uint8).reshape(recs.size, recs.dtype.itemsize)
            body[p[:, None] + np.arange(recs.dtype.itemsize)] = raw
    with open(path, "wb") as f:
        f.write(_fmt_record(FMT_ID, *FMT_FORMAT))
        f.write(_fmt_record(IMU_ID, *IMU_FORMAT))
        f.write(_fmt_record(MAG_ID, *MAG_FORMAT))
        f.write(body.tobytes())
