"""Where a log was recorded: the vehicle's latitude from the GPS messages the log carries.

The filter takes the Earth's rotation out of the gyro when it knows the latitude (``UKFConfig.latitude_deg``,
:mod:`onlinecal.ukf.earth`). A flight log usually knows it: its GPS messages. :func:`log_position` reads them
before the replay starts (a scan of its own, so that a streamed replay has the latitude from its first block),
and stops after ``max_fixes`` good fixes: the latitude of one flight does not change enough to matter (1° of
latitude moves Ω_E sin φ by at most 1.3e-6 rad/s).

What counts as a fix, per format (the first source in each list that has one is used):

* ``.bin`` (DataFlash) — ``GPS`` instance 0 (field ``I``; old logs: ``GPS``, the second receiver ``GPS2``) with
  ``Status`` ≥ 3 (ArduPilot's GPS_OK_FIX_3D and better), ``Lat``/``Lng`` (format ``L``: 1e-7 deg).
* ``.tlog`` (MAVLink) — ``GPS_RAW_INT`` with ``fix_type`` ≥ 3 (GPS_FIX_TYPE_3D_FIX and better), lat/lon 1e-7
  deg; else ``GLOBAL_POSITION_INT`` (the autopilot's fused position; 0, 0 means none). Packets are found by a
  byte scan for their headers and decoded, CRC-checked, by pymavlink: the log is not parsed message by
  message.
* ``.ulg`` (PX4) — ``vehicle_gps_position`` / ``sensor_gps`` with ``fix_type`` ≥ 3 (``latitude_deg``, or
  ``lat`` in 1e-7 deg before PX4 v1.14); else ``vehicle_global_position`` ``lat`` (deg); else
  ``vehicle_local_position`` ``ref_lat`` where ``xy_global`` (the EKF's origin).
* ``.csv`` — no position (the flat schema has none).

A position of exactly (0, 0) is "no position" in every format, and a latitude beyond ±90° is not a fix.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from onlinecal.io.base import GPS_EPOCH_UNIX_S, LogError, decimal_year
from onlinecal.io.validate import check_file

MAX_FIXES = 50  # fixes read before the scan stops
_FIX_3D = 3  # DataFlash GPS Status, MAVLink GPS_FIX_TYPE, PX4 fix_type: 3 = 3-D fix, higher = better
_CHUNK = 1 << 22  # bytes of a .tlog scanned at a time
_Y2000, _Y2100 = 946_684_800.0, 4_102_444_800.0  # UNIX s: a date outside is no date (a clock never set)


@dataclass(frozen=True)
class LogPosition:
    """The vehicle's position as the log's GPS gives it: median of the fixes read (deg, WGS-84).

    ``source``: the message and what made it a fix, e.g. "GPS_RAW_INT (fix_type ≥ 3)"; ``n_fixes``: how
    many fixes the median is of; ``spread_deg``: max − min of their latitudes; ``year``: the date of the fixes
    as a decimal year (None when the log does not say), ``year_source`` where it came from."""

    latitude_deg: float
    longitude_deg: float
    n_fixes: int
    source: str
    spread_deg: float = 0.0
    year: float | None = None
    year_source: str | None = None

    def describe(self, path: str | None = None) -> str:
        """Where the fix came from, e.g. "f.bin's GPS (GPS instance 0, Status ≥ 3; median of 50 fixes)"."""
        where = f"{Path(path).name}'s" if path else "the log's"
        return f"{where} GPS ({self.source}; median of {self.n_fixes} fix{'es' if self.n_fixes != 1 else ''})"


def position_of(lat: np.ndarray, lon: np.ndarray, ok: np.ndarray, source: str, max_fixes: int,
              unix_s: np.ndarray | None = None, time_source: str | None = None) -> LogPosition | None:
    """The position of fixes (deg): the median of the first ``max_fixes`` good ones, or None; ``unix_s`` their
    UTC times (s; ≤ 0 or outside 2000–2100: not known), whose median dates the position."""
    lat, lon = np.asarray(lat, np.float64), np.asarray(lon, np.float64)
    good = (np.asarray(ok, bool) & np.isfinite(lat) & np.isfinite(lon) & (np.abs(lat) <= 90.0)
            & (np.abs(lon) <= 180.0) & ~((lat == 0.0) & (lon == 0.0)))
    idx = np.flatnonzero(good)[:max_fixes]
    if not idx.size:
        return None
    la, lo = lat[idx], lon[idx]
    year = None
    if unix_s is not None:
        u = np.asarray(unix_s, np.float64)[idx]
        u = u[np.isfinite(u) & (u > _Y2000) & (u < _Y2100)]
        year = decimal_year(float(np.median(u))) if u.size else None
    return LogPosition(float(np.median(la)), float(np.median(lo)), int(idx.size), source,
                       float(la.max() - la.min()), year, time_source if year is not None else None)


def log_position(path: str | Path, max_fixes: int = MAX_FIXES) -> LogPosition | None:
    """The log's GPS position (see the module's list), or None when it has no fix.

    Raises :class:`LogError` only where the file cannot be read at all (missing, empty, a directory); a
    damaged log or GPS record is no fix here (the log's reader reports the damage)."""
    p = str(path)
    ext = Path(p).suffix.lower()
    scan = {".bin": _dataflash, ".tlog": _tlog, ".ulg": _ulog}.get(ext)
    if scan is None:
        return None
    check_file(p)
    try:
        return scan(p, max_fixes)
    except LogError:
        return None
    except Exception:  # noqa: BLE001 - a parser's failure on a damaged file: no position, never a traceback
        return None


# the latitudes of several logs of one replay farther apart than this are not one place (1° moves the Earth
# rate's vertical part by at most 1.3e-6 rad/s: a fiftieth of the allowance it replaces)
SAME_PLACE_DEG = 1.0


def logs_place(paths: list[str]) -> tuple[LogPosition | None, str | None, list[str]]:
    """Where the logs of one replay were recorded, from their GPS: (position, where it came from in words,
    notes). The position's latitude/longitude are the medians over the logs with a fix, its date the first
    dated log's. None when no log has a fix, or when their fixes are more than :data:`SAME_PLACE_DEG` of
    latitude apart (a note says so: give the latitude by hand)."""
    found = [(p, pos) for p in paths if (pos := log_position(p)) is not None]
    if not found:
        return None, None, []
    lats = np.array([pos.latitude_deg for _, pos in found])
    if lats.max() - lats.min() > SAME_PLACE_DEG:
        at = ", ".join(f"{Path(p).name} {pos.latitude_deg:.2f}°" for p, pos in found)
        return None, None, [f"the logs' GPS fixes are at different latitudes ({at}): the Earth's rotation is not "
                            f"taken out (replay each place on its own, or give --latitude)"]
    p0, pos0 = found[0]
    src = pos0.describe(p0) + (f" and {len(found) - 1} more log{'s' if len(found) > 2 else ''}"
                               if len(found) > 1 else "")
    dated = next((pos for _, pos in found if pos.year is not None), None)
    place = LogPosition(float(np.median(lats)), float(np.median([pos.longitude_deg for _, pos in found])),
                        sum(pos.n_fixes for _, pos in found), pos0.source, float(lats.max() - lats.min()),
                        None if dated is None else dated.year, None if dated is None else dated.year_source)
    return place, src, []


# -- DataFlash -------------------------------------------------------------------------------------

def _dataflash(path: str, max_fixes: int) -> LogPosition | None:
    from onlinecal.io.dfparse import DataflashParser

    lat: list[np.ndarray] = []
    lon: list[np.ndarray] = []
    when: list[np.ndarray] = []
    n = 0
    for stretch in DataflashParser(path, {"GPS"}):  # old logs' GPS2 is the second receiver: not read
        for recs in stretch:
            f, rows = recs.fmt, recs.rows
            if f.dtype is None or not all(f.has(c) for c in ("Status", "Lat", "Lng")):
                continue
            keep = f.values(rows, "Status") >= _FIX_3D
            if f.has("I"):
                keep &= f.values(rows, "I") == 0
            if keep.any():
                lat.append(f.values(rows[keep], "Lat"))
                lon.append(f.values(rows[keep], "Lng"))
                wk, ms = (("GWk", "GMS") if f.has("GWk") and f.has("GMS") else ("Week", "TimeMS")
                          if f.has("Week") and f.has("TimeMS") else (None, None))
                when.append(GPS_EPOCH_UNIX_S + f.values(rows[keep], wk) * 604_800.0
                            + f.values(rows[keep], ms) * 1e-3 if wk and ms else np.full(int(keep.sum()), np.nan))
                n += int(keep.sum())
        if n >= max_fixes:
            break
    if not lat:
        return None
    la, lo = np.concatenate(lat), np.concatenate(lon)
    return position_of(la, lo, np.ones(la.size, bool), "GPS instance 0, Status ≥ 3", max_fixes,
                     np.concatenate(when), "GPS week and ms")


# -- MAVLink telemetry log -------------------------------------------------------------------------

def _mavlink() -> Any:
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink.dialects.v20 import ardupilotmega

    return ardupilotmega


def _candidates(buf: np.ndarray, ids: tuple[int, ...]) -> np.ndarray:
    """Byte offsets in ``buf`` where a MAVLink 1 or 2 packet of a message id in ``ids`` may start."""
    n = buf.size
    out = []
    if n > 6:  # v1: 0xFE len seq sys comp id
        s = np.flatnonzero(buf[:n - 6] == 0xFE)
        out.append(s[np.isin(buf[s + 5], ids)])
    if n > 10:  # v2: 0xFD len incompat compat seq sys comp id0 id1 id2
        s = np.flatnonzero(buf[:n - 10] == 0xFD)
        s = s[np.isin(buf[s + 7], ids) & (buf[s + 8] == 0) & (buf[s + 9] == 0)]
        out.append(s)
    return np.sort(np.concatenate(out)) if out else np.zeros(0, np.int64)


def _tlog(path: str, max_fixes: int) -> LogPosition | None:
    ml = _mavlink()
    gps_id, glob_id = ml.MAVLINK_MSG_ID_GPS_RAW_INT, ml.MAVLINK_MSG_ID_GLOBAL_POSITION_INT
    mav = ml.MAVLink(None)
    found: dict[int, list[tuple[float, float, bool, float]]] = {gps_id: [], glob_id: []}
    try:
        fh = open(path, "rb")  # noqa: SIM115 - closed below, read in chunks
    except OSError as e:
        raise LogError(path, f"cannot read it: {e.strerror or e}") from None
    with fh:
        tail = b""
        while len(found[gps_id]) < max_fixes:
            chunk = fh.read(_CHUNK)
            if not chunk:
                break
            data = tail + chunk
            buf = np.frombuffer(data, np.uint8)
            for s in _candidates(buf, (gps_id, glob_id)).tolist():
                v2 = buf[s] == 0xFD
                size = (10 if v2 else 6) + int(buf[s + 1]) + 2 + (13 if v2 and buf[s + 2] & 1 else 0)
                if s + size > buf.size or s + size <= len(tail):
                    continue  # completed in the next chunk (kept in ``tail``), or decoded in the last one
                with contextlib.suppress(Exception):  # not a packet: a CRC or length that does not check out
                    m = mav.decode(bytearray(data[s:s + size]))
                    # the tlog's own 8-byte stamp before the packet: µs of the logger's wall clock
                    stamp = int.from_bytes(data[s - 8:s], "big") * 1e-6 if s >= 8 else float("nan")
                    if m.get_type() == "GPS_RAW_INT":
                        found[gps_id].append((m.lat * 1e-7, m.lon * 1e-7, m.fix_type >= _FIX_3D, stamp))
                    elif m.get_type() == "GLOBAL_POSITION_INT":
                        found[glob_id].append((m.lat * 1e-7, m.lon * 1e-7, True, stamp))
            keep = min(len(data), 300)  # the longest packet (v2, 255 + 12 + 13) straddling the boundary
            tail = data[-keep:]
    return mavlink_position([("GPS_RAW_INT, fix_type ≥ 3", found[gps_id]),
                             ("GLOBAL_POSITION_INT", found[glob_id])], max_fixes, "the tlog's timestamps")


def mavlink_position(sources: list[tuple[str, list[tuple[float, float, bool, float]]]], max_fixes: int,
                     time_source: str) -> LogPosition | None:
    """The position of the first of ``sources`` (label, rows of (lat deg, lon deg, a fix?, UTC s or NaN)) that
    has a fix: GPS_RAW_INT's rows before GLOBAL_POSITION_INT's, in a tlog as on a live link."""
    for label, rows in sources:
        if rows:
            a = np.array(rows, np.float64)
            pos = position_of(a[:, 0], a[:, 1], a[:, 2] > 0, label, max_fixes, a[:, 3], time_source)
            if pos is not None:
                return pos
    return None


# -- PX4 ULog --------------------------------------------------------------------------------------

_ULOG_GPS = ("vehicle_gps_position", "sensor_gps")
_ULOG_TOPICS = [*_ULOG_GPS, "vehicle_global_position", "vehicle_local_position"]


def _ulog(path: str, max_fixes: int) -> LogPosition | None:
    try:
        from pyulog import ULog

        ulog = ULog(path, message_name_filter_list=_ULOG_TOPICS)
    except Exception as e:  # pyulog's own failures on a damaged file
        raise LogError(path, f"pyulog cannot read it: {type(e).__name__}: {e}") from None
    topics: dict[str, Any] = {}
    for d in ulog.data_list:
        topics.setdefault(d.name, d.data)  # the first instance: the primary receiver
    for name in _ULOG_GPS:
        d = topics.get(name)
        if d is None or "fix_type" not in d:
            continue
        if "latitude_deg" in d:
            lat, lon = d["latitude_deg"], d["longitude_deg"]
        elif "lat" in d and "lon" in d:
            lat, lon = np.asarray(d["lat"], np.float64) * 1e-7, np.asarray(d["lon"], np.float64) * 1e-7
        else:
            continue
        utc = np.asarray(d["time_utc_usec"], np.float64) * 1e-6 if "time_utc_usec" in d else None
        pos = position_of(lat, lon, np.asarray(d["fix_type"]) >= _FIX_3D, f"{name}, fix_type ≥ 3", max_fixes, utc,
                        "time_utc_usec")
        if pos is not None:
            return pos
    d = topics.get("vehicle_global_position")
    if d is not None and "lat" in d and "lon" in d:
        pos = position_of(d["lat"], d["lon"], np.ones(len(d["lat"]), bool), "vehicle_global_position", max_fixes)
        if pos is not None:
            return pos
    d = topics.get("vehicle_local_position")
    if d is not None and {"ref_lat", "ref_lon", "xy_global"} <= set(d):
        return position_of(d["ref_lat"], d["ref_lon"], np.asarray(d["xy_global"]) != 0,
                         "vehicle_local_position's origin, xy_global", max_fixes)
    return None
