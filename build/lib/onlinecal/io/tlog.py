"""MAVLink telemetry logs (``.tlog``): read IMU messages in bounded blocks, and write RAW_IMU logs.

A tlog is a sequence of ``[8-byte big-endian µs wall-clock timestamp][MAVLink packet]``. The reader
takes ONE IMU source (message type, instance, system, component): of IMU instance ``imu`` (default 0:
RAW_IMU/HIGHRES_IMU ``id``, SCALED_IMU = 0, SCALED_IMU2 = 1, SCALED_IMU3 = 2), RAW_IMU if the log has it,
else HIGHRES_IMU (what PX4 streams), else SCALED_IMU*; with ``imu`` = 0 and none of instance 0, the first
source seen. The choice is made from the first ``_DECIDE_AFTER`` IMU messages (kept
in memory until then) so the log is read once; other sources are named in a warning.

Units (defaults; ``acc_scale``/``gyro_scale``/``mag_scale`` replace the multiplier):

* RAW_IMU, SCALED_IMU, SCALED_IMU2/3 — acc mG (× 9.80665e-3 → m/s²), gyro mrad/s (× 1e-3 → rad/s),
  mag mgauss (× 1e-3 → gauss), temperature c°C (× 0.01; 0 means "not provided" → NaN).
  Time: RAW_IMU ``time_usec`` µs, SCALED_IMU* ``time_boot_ms`` ms.
* HIGHRES_IMU — SI already (m/s², rad/s, gauss, °C), time ``time_usec``; ``fields_updated`` bits 0-2
  acc, 3-5 gyro, 6-8 mag, 12 temperature say which fields are new (0 = all). The temperature is
  held from its last update.

Magnetometer in RAW_IMU/SCALED_IMU*: the autopilot sends the latest compass reading at the IMU rate
(sample-and-hold), so a mag sample is emitted only when the mag triple differs from the previous
message's; its time is that message's time (up to one IMU period after the compass sampled it). An
identical consecutive reading is merged with the one before. A triple of exact zeros means "no compass
(yet)" in ArduPilot: it is not a sample (counted in a warning), so a vehicle without a compass gives a
log with no mag rather than an error.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from onlinecal.io.base import WRITE_EPOCH_US, ImuData, LogError, gps_fixes
from onlinecal.io.mavlink import ACC_UNIT, GYRO_UNIT, IMU_MESSAGES, MAG_UNIT, SCALED_INSTANCE, mavutil_v2
from onlinecal.io.validate import LOOKAHEAD, BlockAssembler, SampleFilter, check_file, probe_head

__all__ = ["IMU_MESSAGES", "TlogReader", "mavutil_v2", "write_tlog"]
_INT_UNITS = {"acc": ACC_UNIT, "gyro": GYRO_UNIT, "mag": MAG_UNIT}  # RAW_IMU / SCALED_IMU*
_SI_UNITS = {"acc": 1.0, "gyro": 1.0, "mag": 1.0}  # HIGHRES_IMU
_DECIDE_AFTER = 1000  # IMU messages looked at before settling for a source other than RAW_IMU id 0
_TLOG_EPOCH_US = WRITE_EPOCH_US  # wall-clock base of written tlog timestamps (2023-11-14)
_INT16 = (-32768, 32767)
_NOT_MESSAGES = ("MAV", "HOME", "BAD_DATA")  # entries of pymavlink's ``messages`` that are not a message read
# ImuData.series from the vehicle's status messages: SYS_STATUS current_battery (cA, −1 = not measured) → current A,
# VFR_HUD throttle (%) → throttle 0..1. They carry no boot time: their tlog (receive) stamp is put on the IMU's
# boot clock by the median offset between the chosen IMU source's tlog stamps and its own times.
_SERIES_MESSAGES = ("SYS_STATUS", "VFR_HUD")
_OFFSET_EVERY = 64  # IMU messages between two samples of the tlog-stamp − boot-time offset


class TlogReader:
    """Streaming reader of the IMU (and the magnetometer it carries) in one MAVLink ``.tlog``."""

    def __init__(self, path: str | Path, acc_scale: float | None = None, gyro_scale: float | None = None,
                 mag_scale: float | None = None, imu: int = 0) -> None:
        self.path = str(path)
        self.imu = int(imu)
        self.warnings: list[str] = []
        self.scale_override = {"acc": acc_scale, "gyro": gyro_scale, "mag": mag_scale}
        self.source: str | None = None  # the IMU source read, e.g. "RAW_IMU id 0 (system 1)"
        check_file(self.path)
        probe_head(self.path, _has_mavlink, "no MAVLink message in {span}; not a MAVLink telemetry log?")

    def blocks(self, max_samples: int = 4096) -> Iterator[ImuData]:
        """Yield ImuData blocks of at most ``max_samples`` IMU samples, in log order."""
        filt = SampleFilter(self.path, unit="messages", lookahead=LOOKAHEAD, gaps=True,
                            limits=self.scale_override["acc"] is None and self.scale_override["gyro"] is None)
        self.warnings = filt.warnings
        asm = BlockAssembler(self.path, filt.warnings, max_samples, filt)
        mavutil = mavutil_v2()
        try:
            conn = mavutil.mavlogfile(self.path, robust_parsing=True)
        except Exception as e:  # pymavlink's own failures on odd files: report, never a traceback
            raise LogError(self.path, f"pymavlink cannot open it: {type(e).__name__}: {e}") from None
        st = _State(self.scale_override)
        seen: dict[tuple, str] = {}  # source key → description, in order of first appearance
        pending: list[tuple[tuple, Any]] = []  # IMU messages before the source is chosen
        chosen: tuple | None = None
        n_msg = n_bad = 0
        series_raw: list[tuple[int, str, float, float]] = []  # (system, message, tlog stamp s, value)
        offsets: dict[tuple, list[float]] = {}  # IMU source key → tlog stamp − boot time samples (s)
        flush_every = max(1, min(max_samples, 1 << 14))
        try:
            while True:
                try:
                    msg = conn.recv_match(type=[*IMU_MESSAGES, *_SERIES_MESSAGES, "BAD_DATA"], blocking=False)
                except Exception as e:
                    raise LogError(self.path, f"pymavlink failed: {type(e).__name__}: {e}",
                                   f"byte {_tell(conn)}, message {n_msg + 1}") from None
                if msg is None:
                    break
                n_msg += 1
                typ = msg.get_type()
                if typ == "BAD_DATA":
                    n_bad += 1
                    continue
                if typ in _SERIES_MESSAGES:
                    v = (msg.current_battery / 100.0 if msg.current_battery >= 0 else float("nan")) \
                        if typ == "SYS_STATUS" else msg.throttle / 100.0
                    series_raw.append((msg.get_srcSystem(), typ, float(getattr(msg, "_timestamp", 0.0)), v))
                    continue
                key = _source_key(msg, typ)
                if n_msg % _OFFSET_EVERY == 1 and hasattr(msg, "_timestamp"):
                    boot = msg.time_boot_ms * 1e-3 if typ.startswith("SCALED") else msg.time_usec * 1e-6
                    offsets.setdefault(key, []).append(float(msg._timestamp) - boot)
                if key not in seen:
                    seen[key] = _describe(key)
                if chosen is None:
                    pending.append((key, msg))
                    if (typ == "RAW_IMU" and key[3] == self.imu) or len(pending) >= _DECIDE_AFTER:
                        chosen = self._choose(seen)
                        for k, m in pending:
                            if k == chosen:
                                st.add(m, k[2])
                        pending = []
                elif key == chosen:
                    st.add(msg, typ)
                if st.n >= flush_every:
                    self._flush(st, filt, asm)
                    yield from asm.pop()
            if chosen is None and seen:
                chosen = self._choose(seen)
                for k, m in pending:
                    if k == chosen:
                        st.add(m, k[2])
                pending = []
        finally:
            conn.close()
        if not seen:
            # UNKNOWN_<id>: an id this dialect lacks, so no CRC check either; random bytes give some.
            kinds = sorted(k for k in getattr(conn, "messages", {})
                           if k not in _NOT_MESSAGES and "[" not in k and not k.startswith("UNKNOWN_"))
            if not kinds:
                size = os.path.getsize(self.path)
                raise LogError(self.path, f"no MAVLink message in its {size} bytes ({n_bad} undecodable stretches); "
                               f"not a MAVLink telemetry log?")
            shown = ", ".join(kinds[:8]) + (", ..." if len(kinds) > 8 else "")
            raise LogError(self.path, f"no IMU messages ({', '.join(IMU_MESSAGES)}) in the log; it holds {shown}")
        assert chosen is not None  # seen is not empty, and the first IMU message chose a source
        self._flush(st, filt, asm)
        assert chosen is not None  # seen is not empty, so a source was chosen
        self.source = seen[chosen]
        others = [d for k, d in seen.items() if k != chosen]
        if others:
            filt.note(f"read {seen[chosen]}; ignored the other IMU source(s) {', '.join(others)}")
        if st.zero_mag:
            filt.note(f"{st.zero_mag} of {st.n_msgs} {chosen[2]} messages carried a mag of exact zeros "
                      f"(no compass reading); not used as mag samples")
        if n_bad:
            filt.note(f"skipped {n_bad} stretches of bytes pymavlink could not decode (bad CRC or garbage)")
        asm.series = _series(series_raw, offsets.get(chosen, []), chosen[0])
        asm.add(*filt.flush())
        filt.finish()
        yield from asm.pop(final=True)

    def _choose(self, seen: dict[tuple, str]) -> tuple:
        """The source of instance ``imu``: RAW_IMU, else HIGHRES_IMU, else SCALED_IMU*; LogError if the log has
        no IMU of that instance (``imu`` = 0: the first source seen)."""
        rank = {"RAW_IMU": 0, "HIGHRES_IMU": 1}
        mine = sorted((k for k in seen if k[3] == self.imu), key=lambda k: rank.get(k[2], 2))
        if mine:
            return mine[0]
        if self.imu == 0:
            return next(iter(seen))
        raise LogError(self.path, f"no IMU instance {self.imu} in the log (it holds {', '.join(seen.values())}); "
                       f"pick one with --imu N")

    @staticmethod
    def _flush(st: _State, filt: SampleFilter, asm: BlockAssembler) -> None:
        imu, mag = st.take()
        asm.add(filt.imu(*imu), filt.mag(*mag))


class _State:
    """Per-message conversion of the chosen source into row lists, turned into arrays per flush."""

    def __init__(self, override: dict[str, float | None]) -> None:
        self.override = override
        self.imu: list[tuple] = []
        self.mag: list[tuple] = []
        self.prev_mag: tuple | None = None
        self.zero_mag = 0
        self.hr_temp = float("nan")
        self.kind: str | None = None
        self.n_msgs = 0

    @property
    def n(self) -> int:
        return len(self.imu) + len(self.mag)

    def add(self, msg: Any, typ: str) -> None:
        self.kind = typ
        self.n_msgs += 1
        if typ == "HIGHRES_IMU":
            fu = int(msg.fields_updated) or 0xFFFF
            t = msg.time_usec * 1e-6
            if fu & 0x1000:
                self.hr_temp = float(msg.temperature)
            if fu & 0x3F:
                self.imu.append((t, msg.xgyro, msg.ygyro, msg.zgyro, msg.xacc, msg.yacc, msg.zacc,
                                 self.hr_temp))
            if fu & 0x1C0:
                self.mag.append((t, msg.xmag, msg.ymag, msg.zmag))
            return
        t = msg.time_usec * 1e-6 if typ == "RAW_IMU" else msg.time_boot_ms * 1e-3
        temp_c = getattr(msg, "temperature", 0)
        self.imu.append((t, msg.xgyro, msg.ygyro, msg.zgyro, msg.xacc, msg.yacc, msg.zacc,
                         temp_c * 0.01 if temp_c else float("nan")))
        m = (msg.xmag, msg.ymag, msg.zmag)
        if m == (0, 0, 0):
            self.zero_mag += 1
        elif m != self.prev_mag:
            self.mag.append((t, *m))
        self.prev_mag = m

    def take(self) -> tuple[tuple, tuple]:
        units = dict(_SI_UNITS if self.kind == "HIGHRES_IMU" else _INT_UNITS)
        units.update({k: v for k, v in self.override.items() if v is not None})
        a = np.asarray(self.imu, np.float64).reshape(-1, 8)
        b = np.asarray(self.mag, np.float64).reshape(-1, 4)
        self.imu, self.mag = [], []
        imu = (a[:, 0], a[:, 1:4] * units["gyro"], a[:, 4:7] * units["acc"], a[:, 7])
        return imu, (b[:, 0], b[:, 1:4] * units["mag"])


def _has_mavlink(head: bytes) -> bool:
    """Does ``head`` hold one MAVLink packet with a valid checksum (of a message this dialect knows)? Tried
    at the first 2000 start-of-frame bytes (0xFD v2, 0xFE v1), each with a fresh parser."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    arr = np.frombuffer(head, np.uint8)
    for p in np.flatnonzero((arr == 0xFD) | (arr == 0xFE))[:2000].tolist():
        mav = mavlink2.MAVLink(None)
        mav.robust_parsing = True
        try:
            msgs = mav.parse_buffer(head[p:p + 280]) or []
        except Exception:  # pymavlink's own failures on a bad frame: try the next start byte
            continue
        if any(m.get_type() != "BAD_DATA" and not m.get_type().startswith("UNKNOWN_") for m in msgs):
            return True
    return False


def _series(raw: list[tuple[int, str, float, float]], offsets: list[float], system: int
            ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``current``/``throttle`` series of the IMU's system from SYS_STATUS/VFR_HUD, on the IMU's boot clock."""
    if not raw or not offsets:
        return {}
    off = float(np.median(offsets))
    out = {}
    for typ, name in (("SYS_STATUS", "current"), ("VFR_HUD", "throttle")):
        rows = np.array([(t, v) for s, k, t, v in raw if s == system and k == typ and np.isfinite(v)]).reshape(-1, 2)
        if rows.shape[0]:
            out[name] = (rows[:, 0] - off, rows[:, 1])
    return out


def _source_key(msg: Any, typ: str) -> tuple:
    if typ in ("RAW_IMU", "HIGHRES_IMU"):
        inst = int(getattr(msg, "id", 0) or 0)
    else:
        inst = SCALED_INSTANCE[typ]
    return (msg.get_srcSystem(), msg.get_srcComponent(), typ, inst)


def _describe(key: tuple) -> str:
    sysid, compid, typ, inst = key
    return f"{typ} id {inst} (system {sysid}, component {compid})"


def _tell(conn: Any) -> int | str:
    try:
        return int(conn.f.tell())
    except Exception:
        return "?"


def _q16(x: np.ndarray, scale: float) -> np.ndarray:
    """Values → int16 counts of ``scale`` (rounded, clipped to the int16 range as a real link does)."""
    return np.clip(np.rint(np.asarray(x, np.float64) / scale), *_INT16).astype(np.int64)


def write_tlog(path: str | Path, data: ImuData, system_id: int = 1) -> None:
    """Write ``data`` as a MAVLink 2 tlog of RAW_IMU messages (id 0), a HEARTBEAT every second.

    One RAW_IMU per IMU sample: time_usec = t_imu µs (t_imu must be ≥ 0), acc mG, gyro mrad/s,
    temperature c°C (NaN → 0 "not provided", 0 °C → 1 as the spec asks), mag mgauss = the latest mag
    sample at or before that time (sample-and-hold; zeros before the first). Values are rounded and
    clipped to int16. ``data.series`` ``current`` (A) and ``throttle`` (0..1), where present, are written as
    SYS_STATUS current_battery (cA) and VFR_HUD throttle (%) at their own times, ``latitude``/``longitude``
    (deg) as GPS_RAW_INT with a 3-D fix. Each packet is prefixed by
    the 8-byte big-endian µs timestamp of tlogs (``_TLOG_EPOCH_US`` + time_usec, so files are reproducible).
    """
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    t = np.asarray(data.t_imu, np.float64)
    if t.size and (not np.all(np.isfinite(t)) or t.min() < 0):
        raise ValueError("write_tlog needs finite, non-negative IMU times")
    usec = np.rint(t * 1e6).astype(np.int64)
    acc = _q16(data.acc, ACC_UNIT)
    gyro = _q16(data.gyro, GYRO_UNIT)
    temp = np.nan_to_num(np.asarray(data.temp, np.float64), nan=0.0)
    temp_c = np.clip(np.rint(temp * 100.0), *_INT16).astype(np.int64)
    temp_c[(temp_c == 0) & np.isfinite(data.temp)] = 1
    mag = np.zeros((t.size, 3), np.int64)
    if data.n_mag:
        j = np.searchsorted(data.t_mag, t, side="right") - 1
        mag[j >= 0] = _q16(data.mag, 1e-3)[j[j >= 0]]

    mav = mavlink2.MAVLink(None, srcSystem=int(system_id), srcComponent=1)
    hb = mav.heartbeat_encode(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0,
                              mavlink2.MAV_STATE_ACTIVE, 3)
    out = bytearray()

    def put(msg: Any, us: int) -> None:
        out.extend(struct.pack(">Q", _TLOG_EPOCH_US + us))
        out.extend(msg.pack(mav))
        mav.seq = (mav.seq + 1) % 256

    # the vehicle's series (ImuData.series): SYS_STATUS current_battery cA, VFR_HUD throttle %, at their own times
    status: list[tuple[int, Any]] = []
    for key in ("current", "throttle"):
        if key in data.series and data.series[key][0].size:
            ts, xs = (np.asarray(v, np.float64) for v in data.series[key])
            for us_s, x in zip(np.rint(ts * 1e6).astype(np.int64).tolist(), xs.tolist(), strict=True):
                if us_s < 0 or not np.isfinite(x):
                    continue
                status.append((us_s, mav.sys_status_encode(0, 0, 0, 0, 0, int(np.clip(round(x * 100), -1, 32767)),
                                                           -1, 0, 0, 0, 0, 0, 0) if key == "current"
                               else mav.vfr_hud_encode(0, 0, 0, int(np.clip(round(x * 100), 0, 65535)), 0, 0)))
    gps = gps_fixes(data)
    if gps is not None:  # GPS_RAW_INT with a 3-D fix (read back by onlinecal.io.position)
        for us_s, la, lo in zip(*(x.tolist() for x in gps), strict=True):
            status.append((us_s, mav.gps_raw_int_encode(us_s, 3, la, lo, 0, 80, 120, 0, 0, 12)))
    status.sort(key=lambda e: e[0])
    js = 0
    next_hb = None
    rows = np.concatenate([usec[:, None], acc, gyro, mag, temp_c[:, None]], axis=1).tolist()
    with open(path, "wb") as f:
        for us, ax, ay, az, gx, gy, gz, mx, my, mz, tc in rows:
            if next_hb is None or us >= next_hb:
                put(hb, us)
                next_hb = us + 1_000_000
            while js < len(status) and status[js][0] <= us:
                put(status[js][1], status[js][0])
                js += 1
            put(mav.raw_imu_encode(us, ax, ay, az, gx, gy, gz, mx, my, mz, 0, tc), us)
            if len(out) > 1 << 20:
                f.write(out)
                out.clear()
        f.write(out)
