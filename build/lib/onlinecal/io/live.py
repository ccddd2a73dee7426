"""A live MAVLink link (serial, UDP, TCP) as a stream of ImuData blocks: the input of ``onlinecal run``.

:class:`LiveSource` opens any pymavlink connection string, asks the vehicle for RAW_IMU at ``rate_hz``
(COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL, once a vehicle HEARTBEAT names its system and component) and
turns the IMU messages of one source into blocks in time order. The source: the vehicle (system, component)
given (``source_system``/``source_component``) or else the first vehicle HEARTBEAT's (others named in a
warning); its IMU instance ``imu`` (RAW_IMU/HIGHRES_IMU ``id``, SCALED_IMU = 0, SCALED_IMU2 = 1,
SCALED_IMU3 = 2), as RAW_IMU (ArduPilot) or, when the vehicle sends none, HIGHRES_IMU (PX4 has no RAW_IMU
stream) or SCALED_IMU*: the first type seen, replaced by a better one (RAW_IMU, then HIGHRES_IMU) that
arrives before any sample was handed on.

Units, as in ``onlinecal.io.tlog`` (ArduPilot's RAW_IMU): ``time_usec`` µs → t s (vehicle boot time),
acc milli-g → m/s², gyro mrad/s → rad/s, mag mgauss → gauss, temperature c°C → °C (0 = "not provided"
→ NaN). ``acc_scale``/``gyro_scale``/``mag_scale`` replace the multiplier (SI unit per count).
Magnetometer: RAW_IMU repeats the latest compass reading at the IMU rate (sample-and-hold), so a mag
sample is emitted, at that message's time, only when the triple changes; all-zero triples mean "no
compass (yet)" and are not samples.

What the link does to packets and what is done about it:

* reordering: a buffer of ``reorder_window`` packets, sorted by ``time_usec``, puts late packets back
  in place (counted in ``stats['reordered']``); a packet older than the last emitted sample is dropped
  (``dropped_late``);
* duplicates (same ``time_usec``) are dropped (``duplicates``); loss is just a gap in time (``lost``
  counts the missing sample periods), except that a mag change first seen right after a gap is not used:
  it happened somewhere in the gap (``mag_uncertain``);
* silence for ``reconnect_s`` (or a socket error, or TCP EOF): the connection is closed and opened
  again, and the rate request is sent again (``reconnects``);
* a vehicle clock that restarts (reboot: ``time_usec`` back near 0 for many packets in a row) is a new
  clock segment: later times are shifted to continue :data:`onlinecal.io.validate.SEGMENT_GAP_S` after the last
  emitted sample and the block holding the boundary carries it in ``ImuData.boundaries`` (the consumer
  restarts the attitude there), with a warning;
* the end: ``timeout_s`` s without an IMU message of the source (``onlinecal run --idle-timeout``);
  ``duration_s`` counts the data's own time, where a jump of the stamps forward (a burst of corrupt stamps)
  counts as at most 10 sample periods, so it cannot end a run early.

The IMU samples then go through the shared input policy (``onlinecal.io.validate.SampleFilter``:
all-zero or non-finite readings dropped, with warnings), as for a log file.
"""

from __future__ import annotations

import binascii
import contextlib
import heapq
import os
import re
import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

from onlinecal.io.base import ImuData, LogError
from onlinecal.io.mavlink import (
    ACC_UNIT,
    GPS_RAW_INT_ID,
    GYRO_UNIT,
    HR_ACC,
    HR_GYRO,
    HR_MAG,
    HR_TEMP,
    MAG_UNIT,
    MAV_CMD_SET_MESSAGE_INTERVAL,
    MAV_COMP_ID_MISSIONPLANNER,
    MSG_ID,
    mavutil_v2,
)
from onlinecal.io.position import MAX_FIXES, LogPosition, mavlink_position
from onlinecal.io.validate import SEGMENT_GAP_S, SampleFilter

RAW_IMU_ID = MSG_ID["RAW_IMU"]
_GCS_COMPONENT = MAV_COMP_ID_MISSIONPLANNER  # what a ground station calls itself
_SCHEMES = ("udpin:", "udpout:", "udpbcast:", "udp:", "tcpin:", "tcp:", "uds:", "unix:", "mcast:",
            "ws:", "wss:", "wsserver:")
_LOG_SUFFIXES = (".tlog", ".bin", ".log", ".csv", ".px4log", ".mavlink", ".raw")
_REQUEST_TRIES = 3  # SET_MESSAGE_INTERVAL attempts per connection, one second apart
_RESET_BEHIND_S = 1.0  # a packet this far behind the last emitted one may be a restarted vehicle clock
_COALESCE_S = 0.02  # s waited after the link turns readable, before reading (fewer wake-ups)
_RECV_BATCH = 1000  # messages handled before the block/stop checks run again
_JUMP_CAP_S = 1.0  # the data time a jump forward adds before a sample period is known (then 10 periods)
_RCVBUF = 1 << 24  # bytes asked for the UDP receive buffer (the kernel caps it at net.core.rmem_max)
_TYPE_RANK = {"RAW_IMU": 0, "HIGHRES_IMU": 1, "SCALED_IMU": 2, "SCALED_IMU2": 2, "SCALED_IMU3": 2}
# the vehicle's position on the link (LiveSource.gps_position): the raw fix first, the fused position else
_GPS_TYPES = ("GPS_RAW_INT", "GLOBAL_POSITION_INT")


_BAD = object()  # recv_msg raised MAVError


class _LinkLost(Exception):
    """The transport reported the peer gone (TCP EOF or reset)."""


class _Link:
    """Per-connection state: reset by every (re)connect."""

    def __init__(self, conn: Any, now: float) -> None:
        self.conn = conn
        self.opened = now
        self.last_msg = now  # wall time of the last message of any kind
        self.got_any = False
        self.vehicle: tuple[int, int] | None = None  # (system, component) of the vehicle HEARTBEAT
        self.next_hb = now  # our GCS heartbeat
        self.requests = 0
        self.next_request = now
        self.acked = False
        self.gps_asked = False  # GPS_RAW_INT's interval asked (after RAW_IMU's ack: an ack names no message)


def _int_bits(i: int) -> float:
    """An int32 carried bytewise in a MAVLink float field (PX4's PARAM_ENCODE_BYTEWISE)."""
    return float(struct.unpack("<f", struct.pack("<i", i))[0])


def _bits_int(f: float) -> int:
    return int(struct.unpack("<i", struct.pack("<f", f))[0])


def _reason(e: BaseException) -> str:
    if isinstance(e, ModuleNotFoundError):
        return f"{e.name} is not installed (serial links need pyserial)"
    if isinstance(e, OSError) and e.strerror:
        return e.strerror
    return str(e) or type(e).__name__


_REV8 = bytes(int(f"{i:08b}"[::-1], 2) for i in range(256))  # each byte's bits reversed


class RawImuMessage:
    """One RAW_IMU message decoded by :class:`RawImuFrames`: the fields of pymavlink's
    ``MAVLink_raw_imu_message`` (same names, same values) and the accessors :class:`LiveSource` reads."""

    __slots__ = ("_src", "time_usec", "xacc", "yacc", "zacc", "xgyro", "ygyro", "zgyro", "xmag", "ymag", "zmag",
                 "id", "temperature")
    FIELDS = ("time_usec", "xacc", "yacc", "zacc", "xgyro", "ygyro", "zgyro", "xmag", "ymag", "zmag", "id",
              "temperature")

    def __init__(self, src: tuple[int, int], values: tuple[int, ...]) -> None:
        self._src = src
        (self.time_usec, self.xacc, self.yacc, self.zacc, self.xgyro, self.ygyro, self.zgyro, self.xmag,
         self.ymag, self.zmag, self.id, self.temperature) = values

    def get_type(self) -> str:
        return "RAW_IMU"

    def get_srcSystem(self) -> int:  # noqa: N802 - pymavlink's name
        return self._src[0]

    def get_srcComponent(self) -> int:  # noqa: N802 - pymavlink's name
        return self._src[1]

    def to_dict(self) -> dict[str, Any]:
        """As pymavlink's ``to_dict``: the fields and ``mavpackettype``."""
        return {"mavpackettype": "RAW_IMU", **{f: getattr(self, f) for f in self.FIELDS}}


class RawImuFrames:
    """Bulk decoding of the RAW_IMU frames of a UDP datagram, without pymavlink's per-byte parser.

    :meth:`split` walks the datagram's frames from its start: while the frame there is a complete MAVLink 1
    or 2 RAW_IMU frame (message id, length and CRC-16/MCRF4XX over header, payload and the message's
    CRC_EXTRA from pymavlink's dialect, as pymavlink's ``decode``; MAVLink 2 flags 0 or signed, a signature
    only where the parser verifies none) it is unpacked with the dialect's own ``struct`` (a truncated
    MAVLink 2 payload zero-padded, as pymavlink does); the rest of the datagram, from the first frame that is
    anything else (another message, a bad CRC, junk), goes to pymavlink's parser unchanged, so every other
    message, and every error, is pymavlink's. The frames taken come first in the datagram: handling them
    before the parser's messages keeps the datagram's order. The CRC is ``binascii.crc_hqx`` (CRC-CCITT, in
    C) on the bit-reversed bytes, which is the reflected MCRF4XX CRC bit-reversed.

    Why: pymavlink parses and builds a message object byte by byte in Python; at 400 Hz that was 4.6 % of
    a core of the 6.2 % ``onlinecal run`` used (benchmarks/bench_live.py).
    """

    def __init__(self, mavlink: Any) -> None:
        cls = mavlink.MAVLink_raw_imu_message
        self.msgid = int(mavlink.MAVLINK_MSG_ID_RAW_IMU)
        self.crc_extra = bytes([int(cls.crc_extra)])
        self.unpacker: struct.Struct = cls.unpacker
        # the wire order must be the field order (no re-sorting, no arrays) for one unpack to give the fields
        self.usable = (list(cls.orders) == list(range(len(RawImuMessage.FIELDS)))
                       and tuple(cls.fieldnames) == RawImuMessage.FIELDS and sum(cls.lengths) == len(cls.lengths))
        self._size = self.unpacker.size

    def _frame(self, data: bytes, pos: int, signed_ok: bool) -> tuple[RawImuMessage, int] | None:
        """The RAW_IMU frame at data[pos:] and the position after it, or None if there is none."""
        n = len(data)
        if n - pos < 8:
            return None
        magic = data[pos]
        if magic == 0xFE:
            hl, sig = 6, 0
            if data[pos + 5] != self.msgid:
                return None
        elif magic == 0xFD and n - pos >= 12:
            hl, flags = 10, data[pos + 2]
            if flags not in (0, 1) or (flags and not signed_ok):
                return None
            sig = 13 if flags else 0
            if data[pos + 7] | (data[pos + 8] << 8) | (data[pos + 9] << 16) != self.msgid:
                return None
        else:
            return None
        plen = data[pos + 1]
        end = pos + hl + plen + 2
        if end + sig > n:
            return None
        crc = binascii.crc_hqx(data[pos + 1 : pos + hl + plen].translate(_REV8), 0xFFFF)
        crc = binascii.crc_hqx(self.crc_extra.translate(_REV8), crc)
        lo, hi = data[end - 2], data[end - 1]  # the frame's CRC, little-endian, bit-reversed below
        if crc != (_REV8[lo] << 8) | _REV8[hi]:
            return None
        payload = data[pos + hl : pos + hl + plen]
        if plen < self._size:
            payload = payload + bytes(self._size - plen)
        values = self.unpacker.unpack(payload[: self._size])
        src = (data[pos + 3], data[pos + 4]) if hl == 6 else (data[pos + 5], data[pos + 6])
        return RawImuMessage(src, values), end + sig

    def split(self, data: bytes, signed_ok: bool = True) -> tuple[list[RawImuMessage], bytes]:
        """(the datagram's leading RAW_IMU messages, the bytes after them for pymavlink's parser)."""
        out: list[RawImuMessage] = []
        pos = 0
        if not self.usable:
            return out, data
        while True:
            got = self._frame(data, pos, signed_ok)
            if got is None:
                return out, data[pos:] if pos else data
            out.append(got[0])
            pos = got[1]


class LiveSource:
    """RAW_IMU from a live MAVLink link, as ImuData blocks of about ``block_s`` s of samples.

    ``url``: pymavlink connection string — ``udpin:HOST:PORT`` (listen; replies go to every address
    heard from on this connection), ``udpout:HOST:PORT`` (send to; the vehicle learns our address from
    our heartbeats), ``tcp:HOST:PORT`` (connect), ``tcpin:HOST:PORT`` (accept), or a serial device
    ``/dev/ttyACM0`` with an optional ``,BAUD`` (needs pyserial). The link is opened by the constructor
    (LogError if it cannot be: ``url: cannot open connection: ...``).

    ``rate_hz``: RAW_IMU rate asked for (0: ask for nothing). ``block_s``: s of data per block.
    ``reorder_window``: packets held back to repair reordering (adds that many samples of latency).
    ``reconnect_s``: s of silence before the connection is re-opened. ``timeout_s``: s without RAW_IMU
    after which the stream ends (None: never); LogError if no sample arrived at all. ``duration_s``:
    s of data after which the stream ends (None: never). ``acc_scale``/``gyro_scale``/``mag_scale``:
    m/s², rad/s, gauss per RAW_IMU count (defaults milli-g, mrad/s, mgauss).

    ``imu``: IMU instance to read. ``source_system``/``source_component``: the vehicle to read (None: the
    first vehicle HEARTBEAT's, or the first IMU source's; other sources are named in a warning).

    ``stats`` (live dict): received (RAW_IMU packets of the source), emitted, lost (IMU samples missing
    from the time line: gaps of k sample periods count k − 1), mag (samples emitted), mag_uncertain (mag
    changes first seen right after lost packets, so of unknown time: not used),
    duplicates, reordered, dropped_late, reconnects, ack (COMMAND_ACKs for the rate request),
    ack_result (last MAV_RESULT or None), interval_requests, heartbeats (vehicle HEARTBEATs),
    ignored (RAW_IMU of other sources), bad_data, clock_resets, stop_reason
    ('duration' | 'timeout' | 'closed' | None). ``warnings``: one sentence per problem, shared with
    every block.
    """

    def __init__(self, url: str, rate_hz: float = 200.0, block_s: float = 0.25, reorder_window: int = 32,
                 reconnect_s: float = 2.0, timeout_s: float | None = None, duration_s: float | None = None,
                 acc_scale: float | None = None, gyro_scale: float | None = None,
                 mag_scale: float | None = None, imu: int = 0, source_system: int | None = None,
                 source_component: int | None = None, ask_gps: bool = False) -> None:
        if not rate_hz >= 0 or not block_s > 0 or not reconnect_s > 0 or reorder_window < 0:
            raise ValueError("need rate_hz >= 0, block_s > 0, reconnect_s > 0, reorder_window >= 0")
        self.url = self.path = str(url)
        self.rate_hz = float(rate_hz)
        self.ask_gps = bool(ask_gps) and self.rate_hz > 0  # GPS_RAW_INT at 1 Hz, once RAW_IMU's rate is acked
        self.block_s = float(block_s)
        self.reorder_window = int(reorder_window)
        self.reconnect_s = float(reconnect_s)
        self.timeout_s = timeout_s
        self.duration_s = duration_s
        self.mag_scale = mag_scale
        self._user_units = acc_scale is not None or gyro_scale is not None
        self.units = {"acc": ACC_UNIT if acc_scale is None else float(acc_scale),
                      "gyro": GYRO_UNIT if gyro_scale is None else float(gyro_scale),
                      "mag": MAG_UNIT if mag_scale is None else float(mag_scale)}
        self.imu = int(imu)
        self.want_system = source_system
        self.want_component = source_component
        self._imu_type: str | None = None  # the message type read (RAW_IMU, HIGHRES_IMU, SCALED_IMU*)
        self._others: set[tuple[int, int]] = set()  # IMU sources seen and not read
        self._hr_temp = float("nan")
        self._hr_mag: tuple = (0.0, 0.0, 0.0)
        self.boundaries: list[dict[str, Any]] = []  # clock segments met (all of them, for the result)
        self._pending_bounds: list[dict[str, Any]] = []  # not yet handed on with a block
        self._data_us = 0.0  # the data's own time, what duration_s counts (forward jumps capped)
        self._segment_start = False  # the next emitted sample starts a clock segment
        self.warnings: list[str] = []
        self.stats: dict[str, Any] = dict(
            received=0, emitted=0, lost=0, mag=0, mag_uncertain=0, duplicates=0, reordered=0, dropped_late=0,
            reconnects=0, ack=0, ack_result=None, interval_requests=0, gps_requests=0, gps_ack_result=None,
            heartbeats=0, ignored=0, bad_data=0, clock_resets=0, resyncs=0, stop_reason=None)
        self._mavutil = mavutil_v2()
        self._mavlink = self._mavutil.mavlink
        self._frames = RawImuFrames(self._mavlink)
        self._fast: list[RawImuMessage] = []  # decoded by RawImuFrames, not yet handled
        self._lock = threading.Lock()  # the connection is used by blocks() and closed by close()
        self._closing = threading.Event()
        self._started = False
        self._notes: list[str] = []
        self._filter = SampleFilter(self.url, unit="messages")
        now = time.monotonic()
        self._link: _Link | None = _Link(self._open(), now)
        self._next_open = now
        self._retry_s = max(0.05, min(self.reconnect_s / 2, 1.0))
        self._last_error = ""
        # Sample state (times as integer µs on the emitted, possibly shifted, clock).
        self._source: tuple[int, int] | None = None
        self._offset_us = 0  # added to time_usec; changes only when the vehicle clock restarts
        self._heap: list[tuple[int, tuple]] = []
        self._in_heap: set[int] = set()
        self._max_us = -1  # latest time received (for counting reordered packets)
        self._last_us = -1  # last emitted
        self._last_dt_us = 0
        self._first_us: int | None = None
        self._recent: deque[int] = deque()
        self._recent_set: set[int] = set()
        self._recent_max = 4 * self.reorder_window + 16
        self._behind: list[tuple[int, tuple]] = []  # consecutive far-late packets: clock restart?
        self._prev_mag: tuple | None = None
        self._zero_mag = 0
        self._imu_rows: list[tuple] = []
        self._mag_rows: list[tuple] = []
        self._block_wall: float | None = None  # wall time the pending block got its first sample
        self._last_data = now  # wall time of the last RAW_IMU of the source
        # (lat deg, lon deg, a fix?, UTC s or NaN) per position message type, the first MAX_FIXES of each
        self._gps: dict[str, list[tuple[float, float, bool, float]]] = {t: [] for t in _GPS_TYPES}
        self._done: str | None = None  # why the stream ends: 'duration' | 'timeout' | 'closed'
        self._full = False  # duration_s of data emitted: later samples are not wanted
        # Loss estimate and the position of the last sample handed on (for checkpoints).
        self._period_us: float | None = None
        self._taken_us: float | None = None
        self._pos: dict[str, Any] | None = None

    # -- opening and closing ----------------------------------------------------------------------
    def _open(self) -> Any:
        url = self.url
        device, baud = url, 115200
        if not url.startswith(_SCHEMES):
            m = re.fullmatch(r"(.+),(\d+)", url)
            if m:  # MAVProxy's "DEVICE,BAUD"; pymavlink itself takes the baud rate separately
                device, baud = m.group(1), int(m.group(2))
            if os.path.isfile(device) or device.lower().endswith(_LOG_SUFFIXES):
                raise LogError(url, "cannot open connection: a log file, not a live link (use replay)")
            if device.startswith("/") and not os.path.exists(device):
                raise LogError(url, "cannot open connection: no such device")
        try:
            # retries=0: one attempt, no "sleeping" prints; re-opening is done here, on our schedule.
            conn = self._mavutil.mavlink_connection(device, baud=baud, source_system=255,
                                                    source_component=_GCS_COMPONENT, retries=0)
        except Exception as e:  # OSError, ValueError, OverflowError, ImportError: all "cannot open"
            raise LogError(url, f"cannot open connection: {_reason(e)}") from None
        port = getattr(conn, "port", None)
        if isinstance(port, socket.socket) and port.type == socket.SOCK_DGRAM:
            # Bursts (Wi-Fi telemetry, a fast replay) overflow the default UDP buffer; best effort.
            # Junk datagrams take buffer space too: a large buffer keeps them from crowding out valid ones
            # while the parser works through them.
            with contextlib.suppress(OSError):
                port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _RCVBUF)
            self._datagram_framing(conn)
        if hasattr(conn, "handle_eof"):
            # pymavlink's TCP client prints and carries on reading an EOF socket (busy loop); make the
            # loss visible so the link is re-opened at once.
            def lost() -> None:
                raise _LinkLost()

            conn.handle_eof = lost
            conn.handle_disconnect = lost
        return conn

    def _datagram_framing(self, conn: Any) -> None:
        """A UDP datagram holds whole MAVLink packets, but pymavlink parses a link as one byte stream: a junk
        datagram holding a start-of-frame byte makes the parser wait for the rest of that "frame" and eat the
        next, valid, datagram with it (measured: 4000 junk datagrams cost 56 % of 2000 valid packets). So an
        unfinished frame left over from an earlier datagram is dropped before the next datagram is read,
        once the packets still complete in the buffer were taken (counted in ``stats['resyncs']``).
        The datagram's leading RAW_IMU frames are decoded here in bulk (:class:`RawImuFrames`) into
        ``self._fast``; the parser gets the rest."""
        orig = conn.recv
        mav = conn.mav
        seen: list[int | None] = [None]  # the buffer length last handed back to the parser unchanged
        frames = self._frames

        def recv(n: int | None = None) -> Any:
            pending = mav.buf_len()
            if pending and pending != seen[0]:
                seen[0] = pending
                return b""  # let the parser take what is complete in its buffer first
            if pending:  # nothing more came of it: the remains of a junk datagram
                mav.buf = bytearray()
                mav.buf_index = 0
                mav.expected_length = 8  # HEADER_LEN_V1 + 2: the parser's own reset value
                mav.have_prefix_error = False
                self.stats["resyncs"] += 1
            seen[0] = None
            data = orig(n)
            if not data:
                return data
            # RAW_IMU frames decoded in bulk (handed on by _step before what the parser returns); the
            # rest of the datagram goes to the parser
            fast, rest = frames.split(bytes(data), mav.signing.secret_key is None)
            if fast:
                self._fast.extend(fast)
            return rest

        conn.recv = recv

    def _drop_link(self) -> None:
        if self._link is not None:
            with contextlib.suppress(Exception):
                self._link.conn.close()
            self._link = None

    def close(self) -> None:
        """End the stream (from any thread) and close the link: blocks() yields what it holds and returns."""
        self._closing.set()
        with self._lock:
            self._drop_link()

    def stop(self) -> None:
        """Ask the stream to end (within ~50 ms) without touching the link: safe in a signal handler, where
        :meth:`close` could wait for the lock held by the very code the signal interrupted."""
        self._closing.set()

    # -- checkpoints ------------------------------------------------------------------------------
    def position(self) -> dict[str, Any] | None:
        """Where the stream stands after the last block handed on (None before the first), JSON-able:
        ``last_us`` (its last IMU time, µs on the emitted clock), ``offset_us`` (the clock-restart shift in
        force), ``first_us`` (time of the first sample: ``duration_s`` counts from it), ``mag`` (the RAW_IMU
        mag triple held at ``last_us``) and ``period_us`` (the sample period estimate)."""
        return dict(self._pos) if self._pos is not None else None

    def resume_from(self, pos: dict[str, Any]) -> None:
        """Continue after :meth:`position` ``pos`` of an earlier source (call before :meth:`blocks`): samples
        at or before ``last_us`` are not emitted again, the clock shift and the duration's start carry
        over, and a vehicle clock restarted meanwhile (reboot) is joined on as in a running stream."""
        if self._started:
            raise RuntimeError("resume_from() must come before blocks()")
        try:
            last_us, offset_us = int(pos["last_us"]), int(pos["offset_us"])
            first_us = None if pos.get("first_us") is None else int(pos["first_us"])
            mag = pos.get("mag")
            mag_t = None if mag is None else tuple(float(v) for v in mag)
            period = pos.get("period_us")
            period_us = None if period is None else float(period)
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"not a live-source position ({e})") from None
        if mag_t is not None and len(mag_t) != 3:
            raise ValueError("not a live-source position (mag is not a triple)")
        self._last_us = self._max_us = last_us
        self._offset_us = offset_us
        self._first_us = first_us
        self._prev_mag = mag_t
        self._period_us = period_us
        self._taken_us = float(last_us)
        data = pos.get("data_us")
        self._data_us = float(data) if data is not None else float(last_us - first_us) if first_us is not None \
            else 0.0
        self._pos = {"last_us": last_us, "offset_us": offset_us, "first_us": first_us, "data_us": self._data_us,
                     "mag": None if mag_t is None else list(mag_t), "period_us": period_us}

    def __enter__(self) -> LiveSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the stream -------------------------------------------------------------------------------
    def blocks(self, max_samples: int = 4096, idle_s: float | None = None) -> Iterator[ImuData]:
        """Yield ImuData blocks in time order, each about ``block_s`` s (at most ``max_samples`` IMU
        samples), until ``duration_s`` of data, ``timeout_s`` without data, or :meth:`close`/:meth:`stop`.

        ``idle_s``: while no data flows, yield an empty block every ``idle_s`` wall seconds (so the consumer
        can report on the link). Raises LogError when ``timeout_s`` passes and no sample arrived at all.
        Iterate once. The link stays open after the stream ends by duration or timeout (for
        :meth:`set_params`) until :meth:`close`.
        """
        if self._started:
            raise RuntimeError("LiveSource.blocks() can be iterated only once")
        self._started = True
        completed = False
        last_yield = time.monotonic()
        try:
            while True:
                with self._lock:
                    if self._closing.is_set():
                        self._done = "closed"
                    else:
                        self._step()
                if self._full:
                    self._done = "duration"
                if self._done:
                    break
                block = self._ready_block(max_samples)
                if block is not None:
                    yield block
                    last_yield = time.monotonic()
                elif idle_s is not None and time.monotonic() - last_yield >= idle_s:
                    yield ImuData.empty(self.url)
                    last_yield = time.monotonic()
            self.stats["stop_reason"] = self._done
            self._flush_heap()
            while self._imu_rows or self._mag_rows:
                block = self._take_block(max_samples)
                if block is not None:
                    yield block
            if self._done == "timeout" and self.stats["emitted"] == 0:
                raise LogError(self.url, self._nothing_received())
            completed = True
        finally:
            if not completed or self._closing.is_set():
                with self._lock:
                    self._drop_link()

    def _step(self) -> None:
        """One round of I/O: (re)open if needed, send what is due, read what is there (or wait ≤ 50 ms)."""
        now = time.monotonic()
        if self.timeout_s is not None and now - self._last_data >= self.timeout_s:
            self._done = "timeout"
            return
        link = self._link
        if link is None:
            if now < self._next_open:
                self._closing.wait(min(0.05, self._next_open - now))
                return
            try:
                link = self._link = _Link(self._open(), now)
            except LogError as e:
                self._last_error = e.message
                self._next_open = now + self._retry_s
                return
            self.stats["reconnects"] += 1
        try:
            self._send_due(link, now)
            n = 0
            while n < _RECV_BATCH and not self._full and not self._span_done():
                n += 1
                try:
                    msg = link.conn.recv_msg()
                except self._mavlink.MAVError:
                    msg = _BAD
                fast = self._fast
                if fast:  # decoded in bulk from the datagram, earlier in it than msg
                    self._fast = []
                    for m in fast:
                        self._handle(link, m)
                if msg is _BAD:
                    self.stats["bad_data"] += 1
                    continue
                if msg is None:
                    if fast:  # the datagram was all RAW_IMU: read on
                        continue
                    n -= 1
                    break
                self._handle(link, msg)
            if n == 0 and not self._span_done() and link.conn.select(0.05):
                # Data came: let a few more datagrams arrive before reading them, so that one wake-up takes
                # ~8 messages at 400 Hz instead of one (the wake-ups were most of the link's CPU). 20 ms is
                # small beside what a sample waits anyway (the reorder window, the block of block_s).
                self._closing.wait(_COALESCE_S)
        except (OSError, _LinkLost):
            self._reopen(link)
            return
        if time.monotonic() - link.last_msg >= self.reconnect_s:
            self._reopen(link)

    def _reopen(self, link: _Link) -> None:
        self._drop_link()
        # At once, but not more often than every _retry_s when the peer keeps closing on us.
        self._next_open = link.opened + self._retry_s

    def _send_due(self, link: _Link, now: float) -> None:
        mav, ml = link.conn.mav, self._mavlink
        if now >= link.next_hb:
            # A ground-station heartbeat: over udpout it is how the vehicle learns where to send; sent
            # faster until the vehicle answers, so the stream starts soon after the link opens.
            mav.heartbeat_send(ml.MAV_TYPE_GCS, ml.MAV_AUTOPILOT_INVALID, 0, 0, ml.MAV_STATE_ACTIVE)
            link.next_hb = now + (1.0 if link.got_any else 0.25)
        if (self.rate_hz > 0 and link.vehicle is not None and not link.acked and now >= link.next_request
                and link.requests < _REQUEST_TRIES):
            sysid, compid = link.vehicle
            mav.command_long_send(sysid, compid, MAV_CMD_SET_MESSAGE_INTERVAL, link.requests,
                                  float(RAW_IMU_ID), round(1e6 / self.rate_hz), 0, 0, 0, 0, 0)
            link.requests += 1
            link.next_request = now + 1.0
            self.stats["interval_requests"] += 1
        elif link.requests >= _REQUEST_TRIES and not link.acked and now >= link.next_request:
            self._note("no COMMAND_ACK for SET_MESSAGE_INTERVAL: the RAW_IMU rate is the vehicle's own")
        if self.ask_gps and link.acked and not link.gps_asked and link.vehicle is not None:
            # the vehicle's position for the filter's Earth-rate settings (onlinecal run without --latitude);
            # asked once per link, after RAW_IMU's answer so the two COMMAND_ACKs are not confused
            sysid, compid = link.vehicle
            mav.command_long_send(sysid, compid, MAV_CMD_SET_MESSAGE_INTERVAL, 0, float(GPS_RAW_INT_ID),
                                  1_000_000, 0, 0, 0, 0, 0)
            link.gps_asked = True
            self.stats["gps_requests"] += 1

    def _handle(self, link: _Link, msg: Any) -> None:
        link.last_msg = time.monotonic()
        link.got_any = True
        typ = msg.get_type()
        if typ in _TYPE_RANK:
            key = (msg.get_srcSystem(), msg.get_srcComponent())
            if not self._is_source(link, key):
                self.stats["ignored"] += 1
                if key not in self._others:
                    self._others.add(key)
                    shown = ", ".join(f"system {a} component {b}" for a, b in sorted(self._others))
                    self._note(f"IMU messages of other vehicles or components ignored ({shown}); reading system "
                               f"{self._source[0] if self._source else '?'} component "
                               f"{self._source[1] if self._source else '?'} (pick one with --sysid/--compid)")
                return
            inst = int(getattr(msg, "id", 0) or 0) if typ in ("RAW_IMU", "HIGHRES_IMU") else \
                {"SCALED_IMU": 0, "SCALED_IMU2": 1, "SCALED_IMU3": 2}[typ]
            if inst != self.imu:
                self.stats["ignored"] += 1
                self._note(f"IMU messages of other instances ignored (instance {self.imu} is read)")
                return
            if self._imu_type != typ:
                better = self._imu_type is None or (_TYPE_RANK[typ] < _TYPE_RANK[self._imu_type]
                                                    and self.stats["emitted"] == 0)
                if not better:
                    self.stats["ignored"] += 1
                    return
                if self._imu_type is not None:  # nothing handed on yet: start over with the better type
                    self._heap.clear()
                    self._in_heap.clear()
                    self._max_us = -1
                self._imu_type = typ
            self._last_data = link.last_msg
            self._accept(msg)
        elif typ == "HEARTBEAT":
            if link.vehicle is None and link.conn.probably_vehicle_heartbeat(msg) and (
                    self._source is None or self._source[0] == msg.get_srcSystem()):
                link.vehicle = (msg.get_srcSystem(), msg.get_srcComponent())
            if link.vehicle == (msg.get_srcSystem(), msg.get_srcComponent()):
                self.stats["heartbeats"] += 1
        elif typ == "COMMAND_ACK":
            if (msg.command == MAV_CMD_SET_MESSAGE_INTERVAL and link.gps_asked
                    and getattr(msg, "target_system", 0) in (0, 255)):
                self.stats["gps_ack_result"] = int(msg.result)  # the answer to the GPS_RAW_INT request
            elif msg.command == MAV_CMD_SET_MESSAGE_INTERVAL and getattr(msg, "target_system", 0) in (0, 255):
                link.acked = True
                self.stats["ack"] += 1
                self.stats["ack_result"] = int(msg.result)
                if msg.result != self._mavlink.MAV_RESULT_ACCEPTED:
                    self._note(f"the vehicle refused the RAW_IMU rate request (MAV_RESULT {msg.result})")
        elif typ in _GPS_TYPES:
            self._take_gps(link, msg, typ)
        elif typ == "BAD_DATA":
            self.stats["bad_data"] += 1

    def _take_gps(self, link: _Link, msg: Any, typ: str) -> None:
        """Keep a position message of the vehicle read (GPS_RAW_INT: a fix when fix_type ≥ 3)."""
        system = self._source[0] if self._source else (link.vehicle[0] if link.vehicle else self.want_system)
        rows = self._gps[typ]
        if (system is not None and msg.get_srcSystem() != system) or len(rows) >= MAX_FIXES:
            return
        if typ == "GPS_RAW_INT":  # time_usec: UNIX µs once the receiver has the time, else since boot
            rows.append((msg.lat * 1e-7, msg.lon * 1e-7, msg.fix_type >= 3, msg.time_usec * 1e-6))
        else:
            rows.append((msg.lat * 1e-7, msg.lon * 1e-7, True, float("nan")))

    def gps_position(self) -> LogPosition | None:
        """The vehicle's position from the link's GPS_RAW_INT fixes (fix_type ≥ 3), else its
        GLOBAL_POSITION_INT, as :func:`onlinecal.io.position.log_position` reads a tlog; None before a fix.
        Safe to call from another thread than :meth:`blocks`'s (it copies the lists the link appends to)."""
        return mavlink_position([("GPS_RAW_INT on the link, fix_type ≥ 3", list(self._gps["GPS_RAW_INT"])),
                                 ("GLOBAL_POSITION_INT on the link", list(self._gps["GLOBAL_POSITION_INT"]))],
                                MAX_FIXES, "GPS_RAW_INT time_usec")

    def _is_source(self, link: _Link, key: tuple[int, int]) -> bool:
        """Is ``key`` (system, component) the vehicle read? Chosen once: the one asked for, else the first
        vehicle HEARTBEAT's system, else the first IMU source."""
        if self._source is None:
            if self.want_system is not None and key[0] != self.want_system:
                return False
            if self.want_component is not None and key[1] != self.want_component:
                return False
            if self.want_system is None and link.vehicle is not None and link.vehicle[0] != key[0]:
                return False
            self._source = key
        return key == self._source

    # -- ordering ---------------------------------------------------------------------------------
    def _fields(self, msg: Any) -> tuple[int, tuple] | None:
        """(raw µs, (acc xyz m/s², gyro xyz rad/s, mag xyz in message units, temperature °C, mag unit)) of an
        IMU message of the type read; None for a HIGHRES_IMU without new IMU fields."""
        typ = self._imu_type
        u = self.units
        if typ == "HIGHRES_IMU":
            fu = int(msg.fields_updated) or 0xFFFF
            if fu & HR_TEMP:
                self._hr_temp = float(msg.temperature)
            if not fu & (HR_ACC | HR_GYRO):
                return None
            si = 1.0 if not self._user_units else None
            ga, gg = (1.0, 1.0) if si else (u["acc"], u["gyro"])
            if fu & HR_MAG:
                self._hr_mag = (msg.xmag, msg.ymag, msg.zmag)
            mag = self._hr_mag  # held from its last update, like RAW_IMU's sample-and-hold
            return int(msg.time_usec), (msg.xacc * ga, msg.yacc * ga, msg.zacc * ga, msg.xgyro * gg,
                                        msg.ygyro * gg, msg.zgyro * gg, *mag, self._hr_temp,
                                        1.0 if self.mag_scale is None else u["mag"])
        raw = int(msg.time_usec) if typ == "RAW_IMU" else int(msg.time_boot_ms) * 1000
        temp_c = getattr(msg, "temperature", 0)
        a, g = u["acc"], u["gyro"]
        return raw, (msg.xacc * a, msg.yacc * a, msg.zacc * a, msg.xgyro * g, msg.ygyro * g, msg.zgyro * g,
                     msg.xmag, msg.ymag, msg.zmag, temp_c * 0.01 if temp_c else np.nan, u["mag"])

    def _accept(self, msg: Any) -> None:
        st = self.stats
        st["received"] += 1
        if self._full:
            return
        got = self._fields(msg)
        if got is None:
            return
        raw, fields = got
        us = raw + self._offset_us
        if us <= self._last_us:
            if us in self._recent_set:
                st["duplicates"] += 1
            elif us < self._last_us - _RESET_BEHIND_S * 1e6:
                self._behind.append((raw, fields))
                if len(self._behind) >= max(2 * self.reorder_window, 16):
                    self._clock_restart()
            else:
                st["dropped_late"] += 1
            return
        if self._behind:  # a stray far-late burst, not a restart: those packets are just late
            st["dropped_late"] += len(self._behind)
            self._behind.clear()
        if us in self._in_heap:
            st["duplicates"] += 1
            return
        if us < self._max_us:
            st["reordered"] += 1
        self._max_us = max(self._max_us, us)
        heapq.heappush(self._heap, (us, fields))
        self._in_heap.add(us)
        while len(self._heap) > self.reorder_window and not self._full:
            self._emit(*self._pop())

    def _pop(self) -> tuple[int, tuple]:
        us, fields = heapq.heappop(self._heap)
        self._in_heap.discard(us)
        return us, fields

    def _flush_heap(self) -> None:
        while self._heap and not self._full:
            self._emit(*self._pop())
        if self._full:
            self._heap.clear()
            self._in_heap.clear()

    def _clock_restart(self) -> None:
        """Many packets in a row far behind the last emitted one: the vehicle clock restarted (reboot).
        Continue the time line one sample period after the last emitted sample."""
        self._flush_heap()
        behind, self._behind = sorted(self._behind), []
        gap_us = round(SEGMENT_GAP_S * 1e6)
        shift = self._last_us + gap_us - (behind[0][0] + self._offset_us)
        bound = {"t": (self._last_us + gap_us / 2) * 1e-6, "cause": "clock restart",
                 "before_s": (self._last_us - self._offset_us) * 1e-6, "after_s": behind[0][0] * 1e-6,
                 "shift_s": (self._offset_us + shift) * 1e-6}
        self._offset_us += shift
        self._max_us = self._last_us
        self._segment_start = True  # the segment gap is neither a sample period nor data time
        self.stats["clock_resets"] += 1
        self.boundaries.append(bound)
        self._pending_bounds.append(bound)
        self._note(f"the vehicle clock went back {shift * 1e-6 - SEGMENT_GAP_S:.3f} s (reboot?) "
                   f"{self.stats['clock_resets']} time(s): a new segment each time (attitude restarted, "
                   f"calibration carried over), later samples shifted onto the time line")
        for raw, fields in behind:
            us = raw + self._offset_us
            if us > self._last_us and us not in self._in_heap:
                heapq.heappush(self._heap, (us, fields))
                self._in_heap.add(us)
            else:
                self.stats["duplicates"] += 1
        while len(self._heap) > self.reorder_window and not self._full:
            self._emit(*self._pop())

    def _emit(self, us: int, fields: tuple) -> None:
        if self._full:
            return
        if self._first_us is None:
            self._first_us = us
        ax, ay, az, gx, gy, gz, mx, my, mz, temp, m = fields
        t = us * 1e-6
        self._imu_rows.append((t, gx, gy, gz, ax, ay, az, temp, us, mx, my, mz))
        mag = (mx, my, mz)
        if mag != self._prev_mag:
            if mag == (0, 0, 0):
                self._zero_mag += 1
            elif (self._period_us and self._last_us >= 0 and self._prev_mag is not None
                  and us - self._last_us > 1.5 * self._period_us):
                # The packet(s) before this one were lost: the reading changed somewhere in the gap, not
                # necessarily here. Stamped here it would be late by up to the gap, which during a turn
                # biases the mag terms (measured: ~2-3σ on mag.bias with 10 % loss); so it is not used.
                self.stats["mag_uncertain"] += 1
            else:
                self._mag_rows.append((t, mx * m, my * m, mz * m))
        self._prev_mag = mag
        if self._block_wall is None:
            self._block_wall = time.monotonic()
        if self._last_us >= 0:
            step = us - self._last_us
            cap = 10.0 * self._last_dt_us if self._last_dt_us else _JUMP_CAP_S * 1e6
            if not self._segment_start:  # a segment's gap is no data; a jump forward counts as at most cap
                self._data_us += min(step, cap)
            if step < cap and not self._segment_start:
                self._last_dt_us = step
        self._segment_start = False
        self._last_us = us
        self._recent.append(us)
        self._recent_set.add(us)
        if len(self._recent) > self._recent_max:
            self._recent_set.discard(self._recent.popleft())
        self.stats["emitted"] += 1
        if self.duration_s is not None and self._data_us * 1e-6 >= self.duration_s:
            self._full = True

    # -- blocks -----------------------------------------------------------------------------------
    def _span_done(self) -> bool:
        """The samples waiting span block_s: a block is ready (reading stops there, so that a backlog read
        at once still comes out in blocks of block_s)."""
        rows = self._imu_rows
        return bool(rows) and rows[-1][0] - rows[0][0] + self._last_dt_us * 1e-6 >= self.block_s

    def _ready_block(self, max_samples: int) -> ImuData | None:
        now = time.monotonic()
        if self._heap and now - self._last_data >= self.block_s:
            # The stream paused: what waits for reordering will not be overtaken any more, hand it on.
            self._flush_heap()
        if not self._imu_rows:
            return None
        assert self._block_wall is not None
        if (self._span_done() or len(self._imu_rows) >= max_samples
                or now - self._block_wall >= 2 * self.block_s):
            return self._take_block(max_samples)
        return None

    def _take_block(self, max_samples: int) -> ImuData | None:
        rows, self._imu_rows = self._imu_rows[:max_samples], self._imu_rows[max_samples:]
        if self._imu_rows:
            t_end = rows[-1][0]
            k = next((i for i, r in enumerate(self._mag_rows) if r[0] > t_end), len(self._mag_rows))
            mrows, self._mag_rows = self._mag_rows[:k], self._mag_rows[k:]
        else:
            mrows, self._mag_rows = self._mag_rows, []
        self._block_wall = time.monotonic() if self._imu_rows else None
        a = np.asarray(rows, np.float64).reshape(-1, 12)
        b = np.asarray(mrows, np.float64).reshape(-1, 4)
        if a.shape[0]:
            self._count_lost(a[:, 8])
            self._pos = {"last_us": int(a[-1, 8]), "offset_us": self._offset_us, "first_us": self._first_us,
                         "data_us": self._data_us,
                         "mag": [float(v) for v in a[-1, 9:12]], "period_us": self._period_us}
        t, gyro, acc, temp = self._filter.imu(a[:, 0], a[:, 1:4], a[:, 4:7], a[:, 7])
        tm, mag = self._filter.mag(b[:, 0], b[:, 1:4])
        self.stats["mag"] += int(tm.size)
        self._update_warnings()
        t_end = t[-1] if t.size else (tm[-1] if tm.size else -np.inf)
        bounds = [b for b in self._pending_bounds if b["t"] <= t_end]
        if bounds:
            self._pending_bounds = [b for b in self._pending_bounds if b["t"] > t_end]
        if not t.size and not tm.size:
            return None
        return ImuData(t, gyro, acc, temp, tm, mag, self.url, self.warnings, [dict(b) for b in bounds])

    def _count_lost(self, us: np.ndarray) -> None:
        """Samples missing between the IMU times ``us`` (µs, one block in order) and the block before: a gap
        of k sample periods is k − 1 lost samples. The period is the median spacing of the latest block of
        ≥ 9 samples (the median ignores the gaps of a lossy link until half the packets are lost)."""
        if us.size >= 9:
            self._period_us = float(np.median(np.diff(us)))
        d = np.diff(us if self._taken_us is None else np.concatenate([[self._taken_us], us]))
        if self._period_us and d.size:
            self.stats["lost"] += int(np.sum(np.maximum(np.rint(d / self._period_us) - 1.0, 0.0)))
        self._taken_us = float(us[-1])

    # -- vehicle parameters -----------------------------------------------------------------------
    def set_params(self, params: Mapping[str, float], tries: int = 3, timeout_s: float = 1.0,
                   wait_vehicle_s: float = 5.0, types: Mapping[str, int] | None = None,
                   bytewise: bool = False) -> dict[str, dict[str, Any]]:
        """Set vehicle parameters with PARAM_SET and confirm each by the vehicle's PARAM_VALUE echo.

        MAVLink parameter protocol: ``param_id`` at most 16 characters; the value travels as a float32,
        so what can land is ``float32(value)``; a parameter is confirmed when a PARAM_VALUE of that name
        echoes exactly that. ``types``: MAV_PARAM_TYPE per name (default REAL32). An integer parameter is
        sent as its value in a float (ArduPilot's C cast) or, with ``bytewise`` (PX4's
        PARAM_ENCODE_BYTEWISE), as the int32's bytes in the float's place, and its echo is read the same
        way. Unconfirmed ones are sent again, ``tries`` rounds in all, each waiting up to ``timeout_s`` s.
        Works after :meth:`blocks` ended (the link is re-opened if it was closed); the vehicle (system,
        component) is the one whose HEARTBEAT or RAW_IMU was seen, waited for up to ``wait_vehicle_s`` s.

        Returns per name: ``value`` (the float32 sent), ``echo`` (the last value the vehicle echoed, or
        None), ``ok``, ``tries`` (PARAM_SETs sent) and ``why`` (empty when ok).
        """
        ml = self._mavlink
        types = dict(types or {})
        out: dict[str, dict[str, Any]] = {}
        wire: dict[str, float] = {}
        for name, v in params.items():
            typ = int(types.get(name, ml.MAV_PARAM_TYPE_REAL32))
            is_int = typ != ml.MAV_PARAM_TYPE_REAL32 and typ != ml.MAV_PARAM_TYPE_REAL64
            f32 = float(np.float32(v))
            why = ""
            if not name or len(name.encode("ascii", "replace")) > 16:
                why = "a MAVLink parameter name has 1 to 16 characters"
            elif not np.isfinite(f32):
                why = "not a finite float32 value"
            elif is_int and f32 != round(f32):
                why = "an integer parameter with a fractional value"
            if is_int and not why:
                f32 = float(round(f32))
            types[name] = typ
            wire[name] = _int_bits(int(f32)) if is_int and bytewise and not why else f32
            out[name] = {"value": f32, "echo": None, "ok": False, "tries": 0, "why": why}
        pending = [n for n, r in out.items() if not r["why"]]
        if not pending:
            return out
        with self._lock:
            link = self._link
            if link is None:
                try:
                    link = self._link = _Link(self._open(), time.monotonic())
                except LogError as e:
                    for n in pending:
                        out[n]["why"] = e.message
                    return out
            try:
                target = self._param_target(link, wait_vehicle_s)
                if target is None:
                    for n in pending:
                        out[n]["why"] = f"no vehicle HEARTBEAT or RAW_IMU in {wait_vehicle_s:g} s"
                    return out
                for _ in range(max(1, tries)):
                    for n in pending:
                        link.conn.mav.param_set_send(target[0], target[1], n.encode("ascii", "replace"),
                                                     wire[n], types[n])
                        out[n]["tries"] += 1
                    deadline = time.monotonic() + timeout_s
                    while pending and time.monotonic() < deadline:
                        msg = self._recv_one(link)
                        if msg is None or msg.get_type() != "PARAM_VALUE" or msg.param_id not in out:
                            continue
                        r = out[msg.param_id]
                        echo = float(msg.param_value)
                        if bytewise and msg.param_type == ml.MAV_PARAM_TYPE_INT32:
                            echo = float(_bits_int(echo))
                        r["echo"] = echo
                        if np.float32(r["echo"]) == np.float32(r["value"]) and msg.param_id in pending:
                            r["ok"] = True
                            pending.remove(msg.param_id)
                    if not pending:
                        break
            except (OSError, _LinkLost) as e:
                self._drop_link()
                for n in pending:
                    out[n]["why"] = f"link lost: {_reason(e)}"
                return out
        for n in pending:
            r = out[n]
            r["why"] = ("no PARAM_VALUE echo" if r["echo"] is None
                        else f"the vehicle echoed {r['echo']!r}, not {r['value']!r}")
        return out

    def _recv_one(self, link: _Link) -> Any:
        """One message of the link (None after ≤ 50 ms without one); heartbeats are still sent."""
        self._send_due(link, time.monotonic())
        try:
            msg = link.conn.recv_msg()
        except self._mavlink.MAVError:
            return None
        finally:
            fast, self._fast = self._fast, []  # RAW_IMU decoded in bulk: not wanted here (as before)
        if msg is None:
            if fast:
                link.last_msg = time.monotonic()
                link.got_any = True
            else:
                link.conn.select(0.05)
            return None
        link.last_msg = time.monotonic()
        link.got_any = True
        if msg.get_type() == "HEARTBEAT" and link.vehicle is None and link.conn.probably_vehicle_heartbeat(msg):
            link.vehicle = (msg.get_srcSystem(), msg.get_srcComponent())
        return msg

    def _param_target(self, link: _Link, wait_s: float) -> tuple[int, int] | None:
        """The vehicle's (system, component): from its HEARTBEAT on this link, else the RAW_IMU source."""
        deadline = time.monotonic() + wait_s
        # A re-opened udpin link can address the vehicle only once it has heard from it.
        while (link.vehicle is None or not link.got_any) and time.monotonic() < deadline:
            self._recv_one(link)
        return link.vehicle or self._source

    # -- words ------------------------------------------------------------------------------------
    def _note(self, sentence: str) -> None:
        if sentence not in self._notes:
            self._notes.append(sentence)
            self._update_warnings()

    def _update_warnings(self) -> None:
        st = self.stats
        link = []
        if st["duplicates"]:
            link.append(f"dropped {st['duplicates']} duplicate RAW_IMU messages")
        if st["dropped_late"]:
            link.append(f"dropped {st['dropped_late']} RAW_IMU messages that arrived too late to reorder")
        if st["reconnects"]:
            link.append(f"the link was silent or lost and re-opened {st['reconnects']} time(s)")
        if self._zero_mag:
            link.append(f"{self._zero_mag} all-zero mag readings (no compass yet) are not samples")
        # In place: every block shares this list and so ends up with the final sentences.
        self.warnings[:] = list(self._filter.warnings) + link + self._notes

    def _nothing_received(self) -> str:
        st, w = self.stats, f"{self.timeout_s:g} s"
        if st["received"]:
            return f"no usable RAW_IMU in {w}"
        if st["heartbeats"]:
            acked = "acknowledged" if st["ack"] else "not acknowledged"
            return (f"vehicle HEARTBEAT but no RAW_IMU in {w} (rate request {acked}; is RAW_IMU "
                    "streamed on this link?)")
        if self._last_error:
            return f"nothing received in {w} (last re-open failed: {self._last_error})"
        return f"nothing received in {w}"
