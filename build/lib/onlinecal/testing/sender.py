"""A stand-in vehicle: stream a session as MAVLink 2 RAW_IMU over a real pymavlink link.

For testing ``onlinecal run --connect`` (and :class:`onlinecal.io.live.LiveSource`) without hardware. The
sender behaves like an ArduPilot vehicle as far as the calibration link needs: a HEARTBEAT (quadrotor,
ArduPilot) about once a second, one RAW_IMU per IMU sample, a COMMAND_ACK for every COMMAND_LONG
(ACCEPTED for MAV_CMD_SET_MESSAGE_INTERVAL, whose interval it then ignores: the session's own rate is sent),
and the MAVLink parameter protocol on a parameter table: PARAM_SET stores the value as float32 and is
answered by PARAM_VALUE (param_id up to 16 characters, MAV_PARAM_TYPE_REAL32), as are PARAM_REQUEST_READ
and PARAM_REQUEST_LIST. Like ArduPilot, a strict table ignores PARAM_SET of names it does not have.

RAW_IMU fields, ArduPilot's units: ``time_usec`` µs (= t_imu), acc milli-g, gyro milli-rad/s, mag
milli-gauss, temperature centi-°C (0 means "not provided", so a real 0 °C is sent as 1), each rounded and
clipped to int16. The magnetometer is sample-and-hold: every RAW_IMU carries the latest mag sample at or
before its time, zeros before the first (ArduPilot's "no compass yet").

Link faults can be injected: a fraction of packets dropped, reordered (sent 1-3 packets later) or sent
twice (same bytes, same MAVLink sequence number, as a duplicating radio or router would).

Command line: ``python -m onlinecal.testing.sender LOG URL [--rate-scale R] [--drop F] [--reorder F]
[--duplicate F] [--seed N] [--linger S]`` where LOG is a ``.csv``/``.tlog`` log or ``sim:PROFILE:SEED`` (a simulated
session) and URL a pymavlink connection string, for example ``udpout:127.0.0.1:14550``.
"""

from __future__ import annotations

import struct
import threading
import time
from typing import Any

import numpy as np

from onlinecal.io.base import WRITE_EPOCH_US, ImuData, LogError, gps_fixes
from onlinecal.io.mavlink import (
    ACC_UNIT,
    GYRO_UNIT,
    MAG_UNIT,
    MAV_CMD_SET_MESSAGE_INTERVAL,
    TEMP_UNIT,
    mavutil_v2,
)

__all__ = ["ACC_UNIT", "GYRO_UNIT", "MAG_UNIT", "TEMP_UNIT", "fault_schedule", "raw_imu_rows", "send_session"]
_INT16 = (-32768, 32767)
_SERVER_SCHEMES = ("udpin:", "tcpin:")  # links whose peer is only known once it has sent something


def _q16(x: Any, unit: float) -> np.ndarray:
    """Values → int16 counts of ``unit`` (rounded, clipped to the int16 range as a real link does)."""
    return np.clip(np.rint(np.asarray(x, np.float64) / unit), *_INT16).astype(np.int64)


def raw_imu_rows(data: ImuData) -> np.ndarray:
    """The RAW_IMU integer fields of every IMU sample, (N, 11) int64.

    Columns: time_usec µs, xacc..zacc milli-g, xgyro..zgyro mrad/s, xmag..zmag mgauss (latest mag sample
    at or before the IMU time, zeros before the first), temperature c°C (NaN → 0, a real 0 °C → 1).
    """
    t = np.asarray(data.t_imu, np.float64)
    if t.size and (not np.all(np.isfinite(t)) or t.min() < 0):
        raise ValueError("RAW_IMU needs finite, non-negative IMU times")
    usec = np.rint(t * 1e6).astype(np.int64)
    temp = np.asarray(data.temp, np.float64)
    temp_c = np.clip(np.rint(np.nan_to_num(temp, nan=0.0) / TEMP_UNIT), *_INT16).astype(np.int64)
    temp_c[(temp_c == 0) & np.isfinite(temp)] = 1
    mag = np.zeros((t.size, 3), np.int64)
    if data.n_mag:
        j = np.searchsorted(data.t_mag, t, side="right") - 1
        mag[j >= 0] = _q16(data.mag, MAG_UNIT)[j[j >= 0]]
    return np.concatenate([usec[:, None], _q16(data.acc, ACC_UNIT), _q16(data.gyro, GYRO_UNIT), mag,
                           temp_c[:, None]], axis=1)


def fault_schedule(n: int, drop: float, reorder: float, duplicate: float,
                   rng: np.random.Generator) -> tuple[list[tuple[int, int]], dict[str, int]]:
    """The order in which packets 0..n-1 go out, as (packet, copies): some dropped (absent), some sent
    1-3 places late, some twice (copies 2). Also returns how many of each fault were drawn."""
    for name, p in (("drop", drop), ("reorder", reorder), ("duplicate", duplicate)):
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"{name} must be a fraction in [0, 1], got {p}")
    keep = rng.random(n) >= drop
    late = (rng.random(n) < reorder) & keep
    twice = (rng.random(n) < duplicate) & keep
    # A reordered packet is sorted in after the next 1-3 packets (a fractional key keeps it between them).
    key = np.arange(n, dtype=np.float64) + np.where(late, rng.integers(1, 4, n) + 0.5, 0.0)
    kept = np.flatnonzero(keep)
    order = [(int(k), 2 if twice[k] else 1) for k in kept[np.argsort(key[kept], kind="stable")]]
    counts = {"dropped": int(n - keep.sum()), "reordered": int(late.sum()), "duplicated": int(twice.sum())}
    return order, counts


def send_session(data: ImuData, url: str, rate_scale: float = 0.0, drop: float = 0.0, reorder: float = 0.0,
                 duplicate: float = 0.0, seed: int = 0, heartbeat: bool = True,
                 stop_event: threading.Event | None = None, system_id: int = 1,
                 wait_peer_s: float = 10.0, params: dict[str, float] | None = None, strict_params: bool = False,
                 param_bytewise: bool = False, linger_s: float = 0.0,
                 hold: threading.Event | None = None) -> dict[str, Any]:
    """Stream ``data`` as RAW_IMU over the pymavlink link ``url``; return what was done.

    ``rate_scale``: wall seconds per second of data (0 as fast as possible, 1 real time, 0.1 ten times
    faster). ``drop``/``reorder``/``duplicate``: fractions of packets lost, sent 1-3 packets late, sent
    twice (drawn with ``seed``). ``heartbeat``: send the vehicle HEARTBEAT (at the start, then every
    second of wall time or of data, whichever comes first). ``stop_event`` ends the stream early.
    ``udpin:``/``tcpin:`` links first wait up to ``wait_peer_s`` s for the peer to send something (the
    sender cannot address it before); nothing is sent if it does not.

    ``params``: the vehicle's parameter table (name → value), changed in place by PARAM_SET (a new dict
    if None); ``strict_params``: PARAM_SET of a name not in the table is ignored (no echo), as ArduPilot
    does. ``param_bytewise``: INT32 parameters travel as the int's bytes in the float (PX4's
    PARAM_ENCODE_BYTEWISE; the table holds the int), otherwise as a float (ArduPilot's cast).
    ``linger_s``: after the stream, stay on the link that long (heartbeats, commands, parameters)
    or until ``stop_event``. ``hold``: while set, nothing is sent and the pacing clock stops (a link
    outage: the stream goes on where it stopped, not with a burst to catch up).

    A ``latitude``/``longitude`` series in ``data`` (``simulate(..., gps=True)``) is sent as GPS_RAW_INT with a
    3-D fix at its own times (time_usec: ``io.base.WRITE_EPOCH_US`` + t, a UNIX time), counted in ``gps``.

    Returns counts: ``sent`` (RAW_IMU packets written, duplicates included), ``samples``, ``dropped``,
    ``reordered``, ``duplicated``, ``commands`` (COMMAND_LONGs answered), ``intervals`` (message id → the
    interval asked for it, µs), ``interval_us`` (the last
    interval asked for with SET_MESSAGE_INTERVAL, or None), ``peer`` (False if no peer turned up),
    ``param_sets`` (PARAM_SETs received) and ``params`` (the table).
    Raises LogError if the link cannot be opened.
    """
    mavutil = mavutil_v2()
    mavlink = mavutil.mavlink
    rows = raw_imu_rows(data)
    order, counts = fault_schedule(rows.shape[0], drop, reorder, duplicate, np.random.default_rng(seed))
    stats: dict[str, Any] = dict(counts)
    table: dict[str, float] = {} if params is None else params
    stats.update(sent=0, samples=int(rows.shape[0]), commands=0, interval_us=None, peer=True, param_sets=0,
                 params=table, gps=0, intervals={})
    fixes = gps_fixes(data)
    gps_rows = [] if fixes is None else list(zip(*(x.tolist() for x in fixes), strict=True))
    gi = 0
    stop = stop_event or threading.Event()
    try:
        conn = mavutil.mavlink_connection(url, source_system=system_id, source_component=1, retries=0)
    except Exception as e:  # pymavlink raises OSError, ValueError, OverflowError... for bad strings
        raise LogError(url, f"cannot open connection: {e}") from None
    got_any = False

    int_params: set[str] = set()

    def param_value(name: str) -> None:
        names = list(table)
        value, typ = table[name], mavlink.MAV_PARAM_TYPE_REAL32
        if name in int_params:
            typ = mavlink.MAV_PARAM_TYPE_INT32
            if param_bytewise:
                value = float(struct.unpack("<f", struct.pack("<i", int(value)))[0])
        conn.mav.param_value_send(name.encode("ascii", "replace"), value, typ, len(names), names.index(name))

    def on_param(msg: Any) -> None:
        """The parameter protocol: PARAM_SET → store float32, echo PARAM_VALUE; reads → PARAM_VALUE."""
        typ = msg.get_type()
        if typ == "PARAM_SET":
            stats["param_sets"] += 1
            name = msg.param_id
            if strict_params and name not in table:
                return
            value = float(np.float32(msg.param_value))  # what a float32 parameter can hold
            if msg.param_type == mavlink.MAV_PARAM_TYPE_INT32:
                int_params.add(name)
                value = float(struct.unpack("<i", struct.pack("<f", value))[0] if param_bytewise else int(value))
            table[name] = value
            param_value(name)
        elif typ == "PARAM_REQUEST_READ":
            names = list(table)
            name = msg.param_id if msg.param_index < 0 else (
                names[msg.param_index] if msg.param_index < len(names) else "")
            if name in table:
                param_value(name)
        else:
            for name in list(table):
                param_value(name)

    def poll() -> None:
        """Answer what the ground station sent (COMMAND_LONG → COMMAND_ACK, parameter messages)."""
        nonlocal got_any
        while True:
            try:
                msg = conn.recv_msg()
            except OSError:
                return
            if msg is None:
                return
            got_any = True
            typ = msg.get_type()
            if typ in ("PARAM_SET", "PARAM_REQUEST_READ", "PARAM_REQUEST_LIST"):
                if msg.target_system in (0, system_id):
                    on_param(msg)
                continue
            if typ != "COMMAND_LONG" or msg.target_system not in (0, system_id):
                continue
            ok = msg.command == MAV_CMD_SET_MESSAGE_INTERVAL
            if ok:
                stats["interval_us"] = float(msg.param2)
                stats["intervals"][int(msg.param1)] = float(msg.param2)
            stats["commands"] += 1
            conn.mav.command_ack_send(
                msg.command, mavlink.MAV_RESULT_ACCEPTED if ok else mavlink.MAV_RESULT_UNSUPPORTED,
                0, 0, msg.get_srcSystem(), msg.get_srcComponent())

    def send_heartbeat() -> None:
        conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0,
                                mavlink.MAV_STATE_ACTIVE)

    try:
        if url.startswith(_SERVER_SCHEMES):
            give_up = time.monotonic() + wait_peer_s
            while not got_any and not stop.is_set() and time.monotonic() < give_up:
                conn.select(0.05)
                poll()
            if not got_any:
                stats["peer"] = False
                return stats
        mav = conn.mav
        t0_wall = time.monotonic()
        t0_data = int(rows[0, 0]) if rows.shape[0] else 0
        next_hb_wall = next_hb_data = -np.inf
        t_data = t0_data  # latest data time sent (µs): paces the stream, reordered packets included
        for k, copies in order:
            if stop.is_set():
                break
            if hold is not None and hold.is_set():
                held_from = time.monotonic()
                while hold.is_set() and not stop.is_set():
                    stop.wait(0.01)
                t0_wall += time.monotonic() - held_from
            t_data = max(t_data, int(rows[k, 0]))
            now = time.monotonic()
            if rate_scale > 0:
                ahead = t0_wall + rate_scale * (t_data - t0_data) * 1e-6 - now
                while ahead > 0.002 and not stop.is_set():
                    # Sleep in short slices so commands are still answered promptly.
                    stop.wait(min(ahead, 0.05))
                    poll()
                    now = time.monotonic()
                    ahead = t0_wall + rate_scale * (t_data - t0_data) * 1e-6 - now
            if heartbeat and (now >= next_hb_wall or t_data >= next_hb_data):
                send_heartbeat()
                next_hb_wall, next_hb_data = now + 1.0, t_data + 1_000_000
            while gi < len(gps_rows) and gps_rows[gi][0] <= t_data:
                g_us, g_lat, g_lon = gps_rows[gi]
                conn.mav.gps_raw_int_send(WRITE_EPOCH_US + g_us, 3, g_lat, g_lon, 0, 80, 120, 0, 0, 12)
                stats["gps"] += 1
                gi += 1
            us, ax, ay, az, gx, gy, gz, mx, my, mz, tc = (int(v) for v in rows[k])
            # Packed once and the sequence number advanced by hand so a duplicate is byte-identical (same
            # seq), as a duplicating radio or router would deliver it.
            buf = mav.raw_imu_encode(us, ax, ay, az, gx, gy, gz, mx, my, mz, 0, tc).pack(mav)
            mav.seq = (mav.seq + 1) % 256
            for _ in range(copies):
                conn.write(buf)
            stats["sent"] += copies
            if stats["sent"] % 16 < copies:
                poll()
        linger_end = time.monotonic() + linger_s
        while not stop.is_set() and time.monotonic() < linger_end:
            if heartbeat and time.monotonic() >= next_hb_wall:
                send_heartbeat()
                next_hb_wall = time.monotonic() + 1.0
            conn.select(0.05)
            poll()
        poll()  # read what is pending: closing a TCP socket with unread input resets the connection
    finally:
        conn.close()
    return stats


def _load(spec: str) -> ImuData:
    """A log (.csv, .tlog) or ``sim:PROFILE:SEED`` → ImuData (imports only what the source needs)."""
    if spec.startswith("sim:"):
        from onlinecal.sim.sensors import simulate

        _, profile, *rest = spec.split(":")
        return simulate(profile or "paper", int(rest[0]) if rest else 0).data
    if spec.lower().endswith(".csv"):
        from onlinecal.io.csv import CsvReader

        return ImuData.concat(CsvReader(spec).blocks(), spec)
    if spec.lower().endswith(".tlog"):
        from onlinecal.io.tlog import TlogReader

        return ImuData.concat(TlogReader(spec).blocks(), spec)
    raise LogError(spec, "not a .csv or .tlog log, nor sim:PROFILE:SEED")


def main(argv: list[str] | None = None) -> int:
    import argparse
    import sys

    p = argparse.ArgumentParser(prog="python -m onlinecal.testing.sender", description=__doc__.split("\n")[0])
    p.add_argument("log", help=".csv or .tlog log, or sim:PROFILE:SEED")
    p.add_argument("url", help="pymavlink connection string, e.g. udpout:127.0.0.1:14550")
    p.add_argument("--rate-scale", type=float, default=1.0,
                   help="wall seconds per second of data (0 = as fast as possible; default 1, real time)")
    p.add_argument("--drop", type=float, default=0.0, help="fraction of packets dropped")
    p.add_argument("--reorder", type=float, default=0.0, help="fraction of packets sent 1-3 packets late")
    p.add_argument("--duplicate", type=float, default=0.0, help="fraction of packets sent twice")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--linger", type=float, default=0.0,
                   help="s to stay on the link after the stream (heartbeats, commands, PARAM_SET)")
    a = p.parse_args(argv)
    try:
        data = _load(a.log)
        stats = send_session(data, a.url, a.rate_scale, a.drop, a.reorder, a.duplicate, a.seed, linger_s=a.linger)
    except LogError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    stats.pop("params")
    print(" ".join(f"{k}={v}" for k, v in stats.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
