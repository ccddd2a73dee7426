"""ArduPilot DataFlash binary logs (``.bin``): read IMU and MAG in bounded blocks, and write minimal logs.

Read with :mod:`onlinecal.io.dfparse` (our own parser of the DataFlash layout: FMT records, then numpy views
of the records, one chunk at a time):

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

Memory is bounded whatever the log's length (one chunk of the file and the blocks being built; pymavlink's
DFReader, used before, indexed every message up front). It decodes what pymavlink's DFReader decodes
(tests/test_scale_dataflash.py compares them field by field). Bytes that begin no record are skipped up
to the next record header, as pymavlink does, and summed into one warning.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from onlinecal.io.base import GPS_EPOCH_UNIX_S, WRITE_EPOCH_US, ImuData, LogError, gps_fixes
from onlinecal.io.dfparse import FORMAT_CHARS, DataflashParser, Records
from onlinecal.io.validate import LOOKAHEAD, BlockAssembler, SampleFilter, check_file, probe_head

HEAD = b"\xa3\x95"
FMT_ID = 0x80
IMU_ID = 100  # ArduPilot assigns ids per build; DFReader only needs them to match the FMT records
MAG_ID = 101
# (name, format, columns) as ArduPilot 4.x logs them.
FMT_FORMAT = ("FMT", "BBnNZ", "Type,Length,Name,Format,Columns")
IMU_FORMAT = ("IMU", "QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz")
MAG_FORMAT = ("MAG", "QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S")
# the series a vehicle's log carries (ImuData.series "current" A, "throttle" 0..1), fields as ArduPilot names them
BAT_ID, CTUN_ID, GPS_ID = 102, 103, 104
BAT_FORMAT = ("BAT", "QBfffff", "TimeUS,Inst,Volt,VoltR,Curr,CurrTot,EnrgTot")
CTUN_FORMAT = ("CTUN", "Qfff", "TimeUS,ThI,ThO,ThH")
# the position (ImuData.series "latitude"/"longitude", deg; read back by onlinecal.io.position), ArduPilot 4.x's GPS
GPS_FORMAT = ("GPS", "QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U")
_NP = {c: t for c, (t, _) in FORMAT_CHARS.items()}  # DataFlash format character → numpy type, as dfparse reads it
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
        parser = DataflashParser(self.path, set(_READ))
        acc = _Collect(self.path, self.imu)
        asm.params = acc.params  # filled as PARM records are read (they come first in a log)
        s = self.scale
        try:
            for stretch in parser:
                got = False
                for recs in stretch:
                    imu, mag = acc.take(recs)
                    if imu is not None:
                        t, a = imu
                        asm.add(filt.imu(t, a[:, 0:3] * s["gyro"], a[:, 3:6] * s["acc"], a[:, 6]), None)
                    if mag is not None:
                        asm.add(None, filt.mag(mag[0], mag[1] * s["mag"]))
                    got = got or imu is not None or mag is not None
                if got:  # IMU and MAG of one stretch are added before a block is cut
                    yield from asm.pop()
        except OSError as e:
            raise LogError(self.path, f"cannot read: {e.strerror or e}") from None
        if parser.stopped_at is not None:
            rest = parser.data_len - parser.stopped_at
            if acc.n_imu_msg == 0:
                raise LogError(self.path, f"no IMU messages read: the index of the log stops here, at a FMT record "
                               f"declaring a length under 3 bytes (corrupt), {rest} bytes before the end",
                               f"byte {parser.stopped_at}")
            filt.note(f"the index of the log stops at byte {parser.stopped_at}, a FMT record declaring a length "
                      f"under 3 bytes (corrupt); the remaining {rest} bytes were not read")
        if acc.n_imu_msg == 0:
            if not parser.n_records:
                raise LogError(self.path, "no DataFlash record in it (FMT or other); not an ArduPilot .bin log?")
            raise LogError(self.path, "no IMU messages in the log" + (f" ({acc.imu_unusable})"
                                                                       if acc.imu_unusable else ""))
        if acc.n_imu_read == 0:
            have = sorted({int(x.split()[-1]) for x in acc.other if x.startswith("IMU")})
            raise LogError(self.path, f"no IMU instance {self.imu} in the log (instances: "
                           f"{', '.join(map(str, have)) or 'none'}); pick one with --imu N")
        if acc.other:
            filt.note(f"read IMU instance {self.imu} and MAG instance 0; ignored {', '.join(sorted(acc.other))}")
        onboard = calibration_params(acc.params)
        if onboard:
            shown = ", ".join(f"{k}={v:g}" for k, v in list(onboard.items())[:6])
            filt.note(f"the log's parameters hold the firmware's own calibration ({shown}"
                      f"{', ...' if len(onboard) > 6 else ''}): the logged IMU/MAG values are already corrected "
                      f"by it, so a calibration fitted here is a residual on top of it")
        asm.series = acc.series()
        if parser.skipped:
            zero = (f" ({parser.skipped_zero} of them zero: an erased or pre-allocated stretch)"
                    if parser.skipped_zero else "")
            filt.note(f"skipped {parser.skipped} corrupt bytes that begin no DataFlash record{zero}")
        if acc.mag_unusable:
            filt.note(f"magnetometer not read: {acc.mag_unusable}")
        asm.add(*filt.flush())
        filt.finish()
        yield from asm.pop(final=True)


class _Collect:
    """The chosen IMU/MAG instance's rows from decoded records, PARM, the optional series, running counts."""

    def __init__(self, path: str, imu: int = 0) -> None:
        self.path = path
        self.want = imu
        self.other: set[str] = set()  # instances seen and not read
        self.n_imu_msg = 0
        self.n_imu_read = 0
        self.imu_unusable = ""
        self.mag_unusable = ""  # why MAG messages are not read, once one proved unreadable
        self.params: dict[str, float] = {}
        # source -> list of (record offsets, t, value); decided on at the end (see series())
        self._series: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}

    def series(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """current (BAT instance 0 and CURR, in log order), throttle (CTUN ThO, else RCOU C3 as 0..1: whichever
        the log holds first), armed (ARM ArmState, else EV ARMED/DISARMED)."""
        def joined(*names: str) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
            parts = [p for n in names for p in self._series.get(n, [])]
            if not parts:
                return None
            o, t, v = (np.concatenate([p[k] for p in parts]) for k in range(3))
            order = np.argsort(o, kind="stable")
            return o[order], t[order], v[order]

        out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        cur = joined("BAT", "CURR")
        if cur is not None:
            out["current"] = (cur[1], cur[2])
        ctun, rcou = joined("CTUN"), joined("RCOU")
        first = [s for s in (ctun, rcou) if s is not None and s[0].size]
        if first:
            thr = min(first, key=lambda s: int(s[0][0]))
            out["throttle"] = (thr[1], thr[2])
        arm = joined("ARM")
        ev = joined("EV")
        if arm is not None and arm[0].size:
            out["armed"] = (arm[1], arm[2])
        elif ev is not None and ev[0].size:
            out["armed"] = (ev[1], ev[2])
        return out

    def _fail(self, recs: Records, k: int, why: str, base: str) -> None:
        """A broken schema (fields come from the FMT record, so every message of this type is alike): IMU is
        required (LogError), MAG is optional (then not read); ``k`` the first record concerned."""
        where = f"byte {int(recs.offsets[k]) + recs.fmt.length}, message {int(recs.ordinal[k])}"  # its end
        problem = (f"{recs.fmt.name} message without a usable field ({why}); its FMT record is corrupt or not "
                   "ArduPilot's")
        if base == "IMU":
            raise LogError(self.path, problem, where)
        self.mag_unusable = f"{problem}, first at {where}"

    def take(self, recs: Records) -> tuple[tuple[np.ndarray, np.ndarray] | None, tuple[np.ndarray, np.ndarray] | None]:
        """Rows of ``recs`` for the IMU ((t s, (n, 7) gyro xyz, acc xyz, T)) or the MAG ((t s, (n, 3) file
        units)) read; None for either when the records are of another type or instance."""
        f, rows = recs.fmt, recs.rows
        typ = f.name
        if typ not in ("IMU", "IMU2", "IMU3", "MAG", "MAG2", "MAG3"):
            with contextlib.suppress(Exception):  # a damaged optional record never stops the log
                self._aux(recs)
            return None, None
        base, old_inst = _OLD_NAMES.get(typ, (typ, None))
        if base == "MAG" and self.mag_unusable:
            return None, None
        if f.dtype is None:  # not decodable: pymavlink skipped such records as unparseable
            if base == "IMU":
                self.imu_unusable = f"{typ} records cannot be decoded: {f.problem}"
                if "Unsupported format char" in f.problem:
                    raise LogError(self.path, f"not a readable DataFlash log: {f.problem}", f"byte {f.at}")
            else:
                self.mag_unusable = f"{typ} records cannot be decoded: {f.problem}"
            return None, None
        if base == "IMU":
            self.n_imu_msg += rows.size
        fields = _IMU_FIELDS if base == "IMU" else _MAG_FIELDS
        names = set(rows.dtype.names or ())
        tcol = "TimeUS" if "TimeUS" in names else "TimeMS" if "TimeMS" in names else None
        missing = [c for c in ("I",) if old_inst is None and c in f.extra_columns]
        missing += [c for c in (*fields,) if c not in names]
        if tcol is None:
            missing.insert(0, "TimeUS")
        if missing or tcol is None:
            err = "IndexError" if any(c in f.extra_columns for c in missing) else "AttributeError"
            self._fail(recs, 0, f"{err}: no value for column {missing[0]!r}", base)
            return None, None
        t = f.values(rows, tcol) * (1e-6 if tcol == "TimeUS" else 1e-3)
        if old_inst is not None:
            inst = np.full(rows.size, old_inst, np.int64)
        elif "I" in names:
            iv = f.values(rows, "I")
            bad = np.flatnonzero(iv != np.round(iv))
            if bad.size:
                self._fail(recs, int(bad[0]), f"ValueError: instance I = {iv[bad[0]]!r} is not an integer", base)
                return None, None
            inst = iv.astype(np.int64)
        else:
            inst = np.zeros(rows.size, np.int64)
        want = self.want if base == "IMU" else 0
        mine = inst == want
        for i in np.unique(inst[~mine]):
            self.other.add(f"{base} instance {int(i)}")
        if not mine.any():
            return None, None
        vals = np.column_stack([f.values(rows[mine], c) for c in fields])
        if base == "IMU":
            self.n_imu_read += int(mine.sum())
            tc = "T" if "T" in names else "Temp" if "Temp" in names else None
            temp = f.values(rows[mine], tc) if tc else np.full(int(mine.sum()), np.nan)
            return (t[mine], np.column_stack([vals, temp])), None
        return None, (t[mine], vals)

    def _aux(self, recs: Records) -> None:
        """PARM and the optional series; records lacking the fields are skipped (other firmware versions)."""
        f, rows = recs.fmt, recs.rows
        typ = f.name
        names = set(rows.dtype.names or ()) if f.dtype is not None else set()
        if typ == "PARM":
            if {"Name", "Value"} <= names:
                for name, value in zip(rows["Name"], f.values(rows, "Value"), strict=True):
                    if np.isfinite(value):
                        self.params[name.split(b"\0", 1)[0].decode("ascii", errors="replace")] = float(value)
            return
        tcol = "TimeUS" if "TimeUS" in names else "TimeMS" if "TimeMS" in names else None
        if tcol is None:
            return
        t = f.values(rows, tcol) * (1e-6 if tcol == "TimeUS" else 1e-3)
        keep = np.ones(rows.size, bool)
        if typ in ("BAT", "CURR") and "Curr" in names:
            if typ == "BAT":
                ic = "Inst" if "Inst" in names else "Instance" if "Instance" in names else None
                if ic is not None:
                    keep = f.values(rows, ic) == 0
            col, v = typ, f.values(rows, "Curr")
        elif typ == "CTUN" and "ThO" in names:
            col, v = typ, f.values(rows, "ThO")
        elif typ == "RCOU" and "C3" in names:
            col, v = typ, np.clip((f.values(rows, "C3") - 1000.0) / 1000.0, 0.0, 1.0)
        elif typ == "ARM" and "ArmState" in names:
            col, v = typ, (f.values(rows, "ArmState") != 0).astype(float)
        elif typ == "EV" and "Id" in names:
            ids = f.values(rows, "Id")
            keep = (ids == _EV_ARMED) | (ids == _EV_DISARMED)
            col, v = typ, (ids == _EV_ARMED).astype(float)
        else:
            return
        self._series.setdefault(col, []).append((recs.offsets[keep], t[keep], v[keep]))


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
    and clipped) records merged in time order. TimeUS = round(t µs); times must be ≥ 0. ``data.series``
    ``current`` (A) and ``throttle`` (0..1), where present, are written as BAT (Inst 0, Curr) and CTUN (ThO);
    ``latitude``/``longitude`` (deg, one time line) as GPS instance 0 with a 3-D fix (Status 3), its GPS week
    and ms from ``base.WRITE_EPOCH_US`` + t."""
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
    kinds = [(IMU_ID, IMU_FORMAT, imu), (MAG_ID, MAG_FORMAT, mag)]
    # the series a flight log carries: BAT Curr (A, instance 0), CTUN ThO (0..1)
    for key, mid, fmt, col in (("current", BAT_ID, BAT_FORMAT, "Curr"), ("throttle", CTUN_ID, CTUN_FORMAT, "ThO")):
        if key in data.series and data.series[key][0].size:
            ts, xs = (np.asarray(v, float) for v in data.series[key])
            if not np.all(np.isfinite(ts)) or ts.min() < 0:
                raise ValueError(f"write_dataflash needs finite, non-negative {key} times")
            rec = np.zeros(ts.size, _record_dtype(fmt[1], fmt[2]))
            rec["h1"], rec["h2"], rec["id"] = HEAD[0], HEAD[1], mid
            rec["TimeUS"] = np.rint(ts * 1e6).astype(np.uint64)
            rec[col] = xs
            kinds.append((mid, fmt, rec))
    gps = gps_fixes(data)
    if gps is not None:
        us, lat, lon = gps
        rec = np.zeros(us.size, _record_dtype(GPS_FORMAT[1], GPS_FORMAT[2]))
        rec["h1"], rec["h2"], rec["id"] = HEAD[0], HEAD[1], GPS_ID
        rec["TimeUS"] = us
        rec["Status"], rec["NSats"], rec["HDop"], rec["U"] = 3, 12, 80, 1  # a 3-D fix (HDop c: 0.8)
        gps_ms = np.rint((WRITE_EPOCH_US * 1e-6 - GPS_EPOCH_UNIX_S + us * 1e-6) * 1e3).astype(np.int64)  # GPS time
        rec["GWk"], rec["GMS"] = gps_ms // 604_800_000, gps_ms % 604_800_000
        rec["Lat"], rec["Lng"] = lat, lon  # format L: 1e-7 deg
        kinds.append((GPS_ID, GPS_FORMAT, rec))
    # Merge by time (IMU first on ties, then MAG, then the series): scatter the record arrays into one buffer.
    t = np.concatenate([r["TimeUS"] for _, _, r in kinds])
    sizes = np.concatenate([np.full(r.size, r.dtype.itemsize) for _, _, r in kinds])
    order = np.argsort(t, kind="stable")
    start = np.concatenate([[0], np.cumsum(sizes[order])[:-1]]).astype(np.int64)
    pos = np.empty_like(start)
    pos[order] = start
    body = np.zeros(int(sizes.sum()), np.uint8)
    at = 0
    for _, _, recs in kinds:
        p = pos[at:at + recs.size]
        at += recs.size
        if recs.size:
            raw = recs.view(np.uint8).reshape(recs.size, recs.dtype.itemsize)
            body[p[:, None] + np.arange(recs.dtype.itemsize)] = raw
    with open(path, "wb") as f:
        f.write(_fmt_record(FMT_ID, *FMT_FORMAT))
        for mid, fmt, _ in kinds:
            f.write(_fmt_record(mid, *fmt))
        f.write(body.tobytes())
