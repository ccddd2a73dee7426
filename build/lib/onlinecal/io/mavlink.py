"""MAVLink units and constants in one place, taken from pymavlink's own dialect (never retyped numbers).

Units of the integer IMU messages (MAVLink common.xml: RAW_IMU, SCALED_IMU, SCALED_IMU2/3):

* acc: milli-g (``ACC_UNIT`` m/s² per count, with standard gravity ``G0``)
* gyro: milli-rad/s (``GYRO_UNIT`` rad/s per count)
* mag: milli-gauss (``MAG_UNIT`` gauss per count)
* temperature: centi-°C (``TEMP_UNIT`` °C per count; 0 means "not provided")

HIGHRES_IMU carries SI values already (m/s², rad/s, gauss, °C); its ``fields_updated`` bits are the
``HIGHRES_IMU_UPDATED_*`` flags (0 = all fields valid, as old senders leave it).
"""

from __future__ import annotations

import os
from typing import Any

G0 = 9.80665  # m/s², standard gravity: MAVLink's "milli-g" is this g
ACC_UNIT = G0 * 1e-3
GYRO_UNIT = 1e-3
MAG_UNIT = 1e-3
TEMP_UNIT = 0.01


def mavutil_v2() -> Any:
    """pymavlink's mavutil with the MAVLink 2 parser (which also reads MAVLink 1 packets).

    pymavlink switches to MAVLink 2 itself only when the very first packet of a file is MAVLink 2
    (and then sets MAVLINK20 for the whole process); a tlog starting with a v1 packet would lose its
    later v2 packets. Selecting v2 up front is the same global switch, made deterministic.
    """
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    if getattr(mavutil.mavlink, "WIRE_PROTOCOL_VERSION", "1.0") != "2.0":
        mavutil.set_dialect(mavutil.current_dialect or "ardupilotmega")
    return mavutil


def _dialect() -> Any:
    from pymavlink.dialects.v20 import ardupilotmega

    return ardupilotmega


_ml = _dialect()
MAV_CMD_SET_MESSAGE_INTERVAL: int = _ml.MAV_CMD_SET_MESSAGE_INTERVAL
MAV_COMP_ID_MISSIONPLANNER: int = _ml.MAV_COMP_ID_MISSIONPLANNER  # what a ground station calls itself
MAV_PARAM_TYPE_INT32: int = _ml.MAV_PARAM_TYPE_INT32
MAV_PARAM_TYPE_REAL32: int = _ml.MAV_PARAM_TYPE_REAL32
MSG_ID = {
    "RAW_IMU": _ml.MAVLINK_MSG_ID_RAW_IMU,
    "SCALED_IMU": _ml.MAVLINK_MSG_ID_SCALED_IMU,
    "SCALED_IMU2": _ml.MAVLINK_MSG_ID_SCALED_IMU2,
    "SCALED_IMU3": _ml.MAVLINK_MSG_ID_SCALED_IMU3,
    "HIGHRES_IMU": _ml.MAVLINK_MSG_ID_HIGHRES_IMU,
}
IMU_MESSAGES = tuple(MSG_ID)
GPS_RAW_INT_ID: int = _ml.MAVLINK_MSG_ID_GPS_RAW_INT  # the vehicle's GPS fix (onlinecal.io.position, run)
# IMU instance of each message type (RAW_IMU and HIGHRES_IMU carry theirs in the ``id`` field).
SCALED_INSTANCE = {"SCALED_IMU": 0, "SCALED_IMU2": 1, "SCALED_IMU3": 2}
HR_ACC = _ml.HIGHRES_IMU_UPDATED_XACC | _ml.HIGHRES_IMU_UPDATED_YACC | _ml.HIGHRES_IMU_UPDATED_ZACC
HR_GYRO = _ml.HIGHRES_IMU_UPDATED_XGYRO | _ml.HIGHRES_IMU_UPDATED_YGYRO | _ml.HIGHRES_IMU_UPDATED_ZGYRO
HR_MAG = _ml.HIGHRES_IMU_UPDATED_XMAG | _ml.HIGHRES_IMU_UPDATED_YMAG | _ml.HIGHRES_IMU_UPDATED_ZMAG
HR_TEMP = _ml.HIGHRES_IMU_UPDATED_TEMPERATURE
del _ml


def imu_instance(msg: Any, typ: str) -> int:
    """The IMU instance a RAW_IMU / SCALED_IMU* / HIGHRES_IMU message belongs to (0-based)."""
    if typ in SCALED_INSTANCE:
        return SCALED_INSTANCE[typ]
    return int(getattr(msg, "id", 0) or 0)
