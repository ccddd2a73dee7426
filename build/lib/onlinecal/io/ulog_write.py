"""PX4 ULog (``.ulg``) writer for simulated sessions. pyulog is the reader (:mod:`onlinecal.io.ulog`); the
file is written here from the ULog specification (PX4 docs, "ULog File Format"), so that a read-back
through pyulog is a check by an independent implementation.

Layout written (all little-endian; every message after the header is ``uint16 msg_size, uint8 msg_type``
then ``msg_size`` bytes)::

    header   'ULog' 0x01 0x12 0x35, uint8 version = 1, uint64 timestamp (µs)        16 bytes
    'B'      flag bits: uint8 compat[8], uint8 incompat[8], uint64 appended_offsets[3] (all zero)
    'F'      one format per topic: "sensor_accel:uint64_t timestamp;...;"
    'I'      info: uint8 key_len, "char[n] sys_name", value bytes
    'P'      parameters: uint8 key_len, "float NAME" | "int32_t NAME", 4 value bytes
    'A'      add logged message: uint8 multi_id, uint16 msg_id, topic name
    'D'      data: uint16 msg_id, the packed fields (no implicit padding), in time order over all topics

Topics, with PX4's field names and units (uORB ``msg/SensorAccel.msg`` etc.): ``sensor_accel`` (x, y, z m/s²),
``sensor_gyro`` (x, y, z rad/s), ``sensor_mag`` (x, y, z gauss), each with ``timestamp`` and
``timestamp_sample`` (µs since boot), ``device_id``, ``temperature`` (°C, NaN when unknown) and
``error_count``. These are the raw driver topics, before PX4 applies its CAL_* calibration.

Parameters: the vehicle's onboard calibration, which PX4 applies after these topics. A simulated vehicle
has none, so the identity is written (CAL_ACC0/GYRO0/MAG0 ``_ID`` = the topics' device ids, offsets 0,
scales 1, ODIAG 0, CAL_MAG0_ROT 0), overridden by ``data.params`` where the data carries parameters.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from onlinecal.io.base import WRITE_EPOCH_US, ImuData, gps_fixes

ULOG_MAGIC = b"ULog\x01\x12\x35"
ULOG_VERSION = 1

# Device ids written in the topics and in CAL_<S>0_ID (PX4 applies CAL_<S>0_* only to the sensor whose
# device id matches); arbitrary but fixed so the files are reproducible.
DEVICE_ID = {"sensor_accel": 0x240011, "sensor_gyro": 0x240012, "sensor_mag": 0x0C0013}

# (ULog type, numpy type) of each field, in the uORB order of PX4's msg/Sensor{Accel,Gyro,Mag}.msg. The
# trailing _padding0 is in the format (the uORB struct's size) but, as PX4's logger does, not in the data:
# the spec drops padding at the end of a record (pyulog counts a longer record as corrupt).
_COMMON = [("uint64_t", "<u8", "timestamp"), ("uint64_t", "<u8", "timestamp_sample"),
           ("uint32_t", "<u4", "device_id"), ("float", "<f4", "x"), ("float", "<f4", "y"), ("float", "<f4", "z"),
           ("float", "<f4", "temperature"), ("uint32_t", "<u4", "error_count")]
TOPICS: dict[str, list[tuple[str, str, str]]] = {
    "sensor_accel": _COMMON + [("uint8_t[3]", "3u1", "clip_counter"), ("uint8_t", "u1", "samples"),
                               ("uint8_t[4]", "4u1", "_padding0")],
    "sensor_gyro": _COMMON + [("uint8_t[3]", "3u1", "clip_counter"), ("uint8_t", "u1", "samples"),
                              ("uint8_t[4]", "4u1", "_padding0")],
    "sensor_mag": _COMMON + [("bool", "u1", "is_external"), ("uint8_t[7]", "7u1", "_padding0")],
}
# a vehicle's series (ImuData.series), written only where the data has them: battery_status.current_a (A;
# PX4's msg/BatteryStatus.msg, its first fields) and actuator_controls_0.control[3] (the throttle, 0..1; PX4's
# msg/ActuatorControls.msg before v1.14)
SERIES_TOPICS: dict[str, list[tuple[str, str, str]]] = {
    "battery_status": [("uint64_t", "<u8", "timestamp"), ("float", "<f4", "voltage_v"),
                       ("float", "<f4", "current_a")],
    "actuator_controls_0": [("uint64_t", "<u8", "timestamp"), ("uint64_t", "<u8", "timestamp_sample"),
                            ("float[8]", "8<f4", "control")],
}
SERIES_OF = {"battery_status": "current", "actuator_controls_0": "throttle"}
# the position (ImuData.series "latitude"/"longitude", deg): vehicle_gps_position's first fields as PX4 before
# v1.14 logged them (lat/lon int32 1e-7 deg, fix_type 3 = a 3-D fix)
GPS_TOPIC = [("uint64_t", "<u8", "timestamp"), ("uint64_t", "<u8", "time_utc_usec"), ("int32_t", "<i4", "lat"),
             ("int32_t", "<i4", "lon"), ("int32_t", "<i4", "alt"), ("uint8_t", "u1", "fix_type")]
SERIES_TOPICS["vehicle_gps_position"] = GPS_TOPIC
_MSG_ID = {name: i for i, name in enumerate(list(TOPICS) + list(SERIES_TOPICS))}


def _msg(msg_type: bytes, payload: bytes) -> bytes:
    """One definitions-section message: uint16 size, uint8 type, payload."""
    return struct.pack("<HB", len(payload), msg_type[0]) + payload


def _format_message(name: str) -> bytes:
    fields = "".join(f"{ut} {fn};" for ut, _, fn in {**TOPICS, **SERIES_TOPICS}[name])
    return _msg(b"F", f"{name}:{fields}".encode())


def _key_value(key: str, value: bytes) -> bytes:
    k = key.encode()
    return bytes([len(k)]) + k + value


def default_params() -> dict[str, float | int]:
    """PX4's calibration parameters for a vehicle with no onboard calibration (identity), ids matching the
    topics' device ids. int values are written as int32_t parameters, float as float."""
    p: dict[str, float | int] = {"CAL_ACC0_ID": DEVICE_ID["sensor_accel"], "CAL_GYRO0_ID": DEVICE_ID["sensor_gyro"],
                                 "CAL_MAG0_ID": DEVICE_ID["sensor_mag"], "CAL_MAG0_ROT": 0}
    for ax in "XYZ":
        p[f"CAL_ACC0_{ax}OFF"] = 0.0
        p[f"CAL_ACC0_{ax}SCALE"] = 1.0
        p[f"CAL_GYRO0_{ax}OFF"] = 0.0
        p[f"CAL_MAG0_{ax}OFF"] = 0.0
        p[f"CAL_MAG0_{ax}SCALE"] = 1.0
        p[f"CAL_MAG0_{ax}ODIAG"] = 0.0
    return p


def _records(name: str, usec: NDArray[np.int64], xyz: NDArray[np.float64],
             temp: NDArray[np.float64]) -> NDArray[np.uint8]:
    """(N, 3 + record size) bytes: each row a whole 'D' message (size, type, msg_id, packed fields)."""
    fields = [f for f in TOPICS[name] if not f[2].startswith("_padding")]
    dt = np.dtype([("msg_size", "<u2"), ("msg_type", "u1"), ("msg_id", "<u2")] + [(fn, nt) for _, nt, fn in fields])
    rec = np.zeros(usec.size, dt)
    rec["msg_size"] = dt.itemsize - 3
    rec["msg_type"] = ord("D")
    rec["msg_id"] = _MSG_ID[name]
    rec["timestamp"] = usec
    rec["timestamp_sample"] = usec
    rec["device_id"] = DEVICE_ID[name]
    for k, c in enumerate("xyz"):
        rec[c] = xyz[:, k]
    rec["temperature"] = temp
    if name == "sensor_accel" or name == "sensor_gyro":
        rec["samples"] = 1
    return rec.view(np.uint8).reshape(usec.size, dt.itemsize)


def _series_records(name: str, usec: NDArray[np.int64], x: NDArray[Any],
                    lon: NDArray[np.int64] | None = None) -> NDArray[np.uint8]:
    """(K, 3 + record size) bytes of a series topic: current_a, control[3] (the throttle), or a GPS fix
    (``x`` the latitude, ``lon`` the longitude, 1e-7 deg: :func:`onlinecal.io.base.gps_fixes`)."""
    fields = SERIES_TOPICS[name]
    dt = np.dtype([("msg_size", "<u2"), ("msg_type", "u1"), ("msg_id", "<u2")] + [(fn, nt) for _, nt, fn in fields])
    rec = np.zeros(usec.size, dt)
    rec["msg_size"] = dt.itemsize - 3
    rec["msg_type"] = ord("D")
    rec["msg_id"] = _MSG_ID[name]
    rec["timestamp"] = usec
    if name == "vehicle_gps_position":  # x, lon: 1e-7 deg (io.base.gps_fixes)
        rec["lat"], rec["lon"] = x, lon
        rec["fix_type"] = 3
        rec["time_utc_usec"] = WRITE_EPOCH_US + usec  # the UTC time the receiver reports
    elif name == "battery_status":
        rec["current_a"] = x
    else:
        rec["timestamp_sample"] = usec
        rec["control"][:, 3] = x
    return rec.view(np.uint8).reshape(usec.size, dt.itemsize)


def _usec(t: NDArray[np.float64], what: str) -> NDArray[np.int64]:
    t = np.asarray(t, np.float64)
    if t.size and (not np.all(np.isfinite(t)) or t.min() < 0):
        raise ValueError(f"write_ulog needs finite, non-negative {what} times")
    return np.rint(t * 1e6).astype(np.int64)


def write_ulog(path: str | Path, data: ImuData, sys_name: str = "onlinecal simulate") -> None:
    """Write ``data`` as a PX4 ULog of the raw topics sensor_accel, sensor_gyro (one sample per IMU sample,
    same stamps) and sensor_mag (its own clock), with the calibration parameters (module docstring); a
    ``current``/``throttle`` series as battery_status.current_a / actuator_controls_0.control[3], a
    ``latitude``/``longitude`` series (deg) as vehicle_gps_position with a 3-D fix.

    Shapes/units: t_imu (N,) s ≥ 0 → µs (rounded); gyro (N, 3) rad/s, acc (N, 3) m/s², mag (M, 3) gauss → float32;
    temp (N,) °C (NaN stays NaN: PX4's "unknown"). The 'D' messages of all topics are merged in time order
    (gyro, then accel, then mag on equal stamps) with one vectorised scatter, no per-sample loop.
    """
    ui, um = _usec(data.t_imu, "IMU"), _usec(data.t_mag, "magnetometer")
    temp = np.asarray(data.temp, np.float64)
    parts = [_records("sensor_gyro", ui, data.gyro, temp), _records("sensor_accel", ui, data.acc, temp)]
    stamps = [ui, ui]
    if data.n_mag:
        parts.append(_records("sensor_mag", um, data.mag, np.full(um.size, np.nan)))
        stamps.append(um)
    series = [n for n, k in SERIES_OF.items() if k in data.series and np.asarray(data.series[k][0]).size]
    for name in series:
        ts, xs = data.series[SERIES_OF[name]]
        us = _usec(np.asarray(ts, np.float64), SERIES_OF[name])
        parts.append(_series_records(name, us, np.asarray(xs, np.float64)))
        stamps.append(us)
    gps = gps_fixes(data)
    if gps is not None:
        us = gps[0]
        parts.append(_series_records("vehicle_gps_position", us, gps[1], gps[2]))
        stamps.append(us)
        series.append("vehicle_gps_position")
    topic_of = np.concatenate([np.full(s.size, k) for k, s in enumerate(stamps)])
    order = np.lexsort((topic_of, np.concatenate(stamps)))  # time, then topic: a stable merge
    sizes = np.array([p.shape[1] for p in parts])[topic_of[order]]
    offsets = np.empty(order.size, np.int64)
    offsets[order] = np.concatenate([[0], np.cumsum(sizes)[:-1]]) if order.size else np.zeros(0, np.int64)
    body = np.empty(int(sizes.sum()), np.uint8)
    first = 0
    for p in parts:  # a scatter per topic and 65536 rows (bounded index memory), not per sample
        cols = np.arange(p.shape[1])
        for i in range(0, p.shape[0], 1 << 16):
            rows = p[i:i + (1 << 16)]
            body[offsets[first + i:first + i + rows.shape[0]][:, None] + cols] = rows
        first += p.shape[0]

    params: dict[str, float | int] = default_params()
    for name, val in data.params.items():  # a log read back holds floats: ids and rotations stay int32
        params[name] = int(val) if name.endswith(("_ID", "_ROT")) and float(val).is_integer() else float(val)
    start = int(min((s[0] for s in stamps if s.size), default=0))
    head = bytearray(ULOG_MAGIC + bytes([ULOG_VERSION]) + struct.pack("<Q", start))
    head += _msg(b"B", bytes(16) + struct.pack("<3Q", 0, 0, 0))
    for name in list(TOPICS) + series:
        head += _format_message(name)
    for key, value in (("sys_name", sys_name), ("ver_hw", "SITL")):
        v = value.encode()
        head += _msg(b"I", _key_value(f"char[{len(v)}] {key}", v))
    for name, val in params.items():
        if isinstance(val, (int, np.integer)) and not isinstance(val, bool):
            head += _msg(b"P", _key_value(f"int32_t {name}", struct.pack("<i", int(val))))
        else:
            head += _msg(b"P", _key_value(f"float {name}", struct.pack("<f", float(val))))
    for name in list(TOPICS) + series:
        head += _msg(b"A", struct.pack("<BH", 0, _MSG_ID[name]) + name.encode())
    with open(path, "wb") as f:
        f.write(head)
        f.write(body.tobytes())
