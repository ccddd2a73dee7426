"""The bulk RAW_IMU decoder of the live link (onlinecal.io.live.RawImuFrames) against pymavlink's own parser:
on datagrams written by pymavlink (MAVLink 1 and 2, signed and unsigned, truncated payloads, several frames
per datagram) with junk, corrupt and foreign frames interleaved, the decoder plus pymavlink on what it leaves
gives the very messages pymavlink alone gives, field by field and in order."""

from __future__ import annotations

import numpy as np
import pytest

from onlinecal.io.live import RawImuFrames
from onlinecal.io.mavlink import mavutil_v2

ml = mavutil_v2().mavlink


def _packer(sysid: int = 1, comp: int = 1, signed: bool = False):
    mav = ml.MAVLink(None, srcSystem=sysid, srcComponent=comp)
    if signed:
        mav.signing.secret_key = bytes(range(32))
        mav.signing.link_id = 3
        mav.signing.sign_outgoing = True
    return mav


def _raw_imu(mav, rng: np.random.Generator, v1: bool = False, zeros: bool = False) -> bytes:
    """One RAW_IMU frame packed by pymavlink; ``zeros``: id and temperature 0, so that MAVLink 2 truncates the
    payload's trailing zero bytes."""
    h = [int(v) for v in rng.integers(-32768, 32767, 9)]
    msg = ml.MAVLink_raw_imu_message(int(rng.integers(0, 2**63)), *h, 0 if zeros else int(rng.integers(0, 3)),
                                     0 if zeros else int(rng.integers(-32768, 32767)))
    return bytes(msg.pack(mav, force_mavlink1=v1))


def _heartbeat(mav, v1: bool = False) -> bytes:
    msg = ml.MAVLink_heartbeat_message(ml.MAV_TYPE_QUADROTOR, ml.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4, 3)
    return bytes(msg.pack(mav, force_mavlink1=v1))


def _datagrams(seed: int) -> list[bytes]:
    rng = np.random.default_rng(seed)
    plain, other, signed = _packer(), _packer(7, 42), _packer(signed=True)
    out: list[bytes] = []
    for k in range(400):
        kind = k % 10
        f: bytes | bytearray
        if kind == 0:
            out.append(_raw_imu(plain, rng, v1=True))
        elif kind == 1:
            out.append(_raw_imu(signed, rng))
        elif kind == 2:
            out.append(_raw_imu(plain, rng, zeros=True))
        elif kind == 3:  # several frames in one datagram, a heartbeat among them
            out.append(_raw_imu(plain, rng) + _raw_imu(other, rng, v1=True) + _heartbeat(plain) + _raw_imu(plain, rng))
        elif kind == 4:  # junk: random bytes, then a start-of-frame byte with random bytes after it
            out.append(bytes(rng.integers(0, 256, int(rng.integers(1, 60)), dtype=np.uint8)))
            out.append(bytes([0xFD]) + bytes(rng.integers(0, 256, 20, dtype=np.uint8)))
        elif kind == 5:  # a corrupt CRC, then a good frame in the same datagram
            f = bytearray(_raw_imu(plain, rng))
            f[-1] ^= 0x5A
            out.append(bytes(f) + _raw_imu(plain, rng))
        elif kind == 6:  # a payload byte flipped (the CRC must catch it)
            f = bytearray(_raw_imu(plain, rng, v1=True))
            f[10] ^= 0x01
            out.append(bytes(f))
        elif kind == 7:  # cut short
            f = _raw_imu(plain, rng)
            out.append(f[: int(rng.integers(1, len(f)))])
        elif kind == 8:
            out.append(_heartbeat(plain, v1=True) + _raw_imu(plain, rng))
        else:
            out.append(_raw_imu(other, rng))
    return out


def _pymavlink(data: bytes) -> list:
    """pymavlink's parse of one datagram on a fresh parser (what the live link's framing amounts to)."""
    p = ml.MAVLink(None)
    p.robust_parsing = True
    return p.parse_buffer(data) or []


def _view(m) -> tuple:
    if m.get_type() == "BAD_DATA":
        return ("BAD_DATA",)
    d = m.to_dict()
    return (m.get_type(), m.get_srcSystem(), m.get_srcComponent(), tuple(sorted(d.items())))


@pytest.mark.parametrize("seed", [0, 1])
def test_bulk_decode_equals_pymavlink(seed):
    frames = RawImuFrames(ml)
    assert frames.usable
    n_fast = n_imu = 0
    for dg in _datagrams(seed):
        ref = [_view(m) for m in _pymavlink(dg)]
        fast, rest = frames.split(dg)
        got = [_view(m) for m in fast] + [_view(m) for m in _pymavlink(rest)]
        assert got == ref, dg.hex()
        # the fields carry pymavlink's types: ints, not numpy scalars or floats
        for m in fast:
            assert all(type(getattr(m, f)) is int for f in m.FIELDS)
        n_fast += len(fast)
        n_imu += sum(r[0] == "RAW_IMU" for r in ref)
    # the bulk way took every RAW_IMU ahead of any other frame in its datagram: per 10 datagrams, one each
    # of kinds 0, 1, 2, 9 and the first two of kind 3 (6 of the 9 RAW_IMU; the others follow a heartbeat or
    # a corrupt frame and are pymavlink's)
    assert (n_fast, n_imu) == (6 * 40, 9 * 40)


def test_every_well_formed_raw_imu_is_taken_and_others_are_left():
    rng = np.random.default_rng(2)
    frames = RawImuFrames(ml)
    for mav, v1, zeros in [(_packer(), True, False), (_packer(), False, False), (_packer(), False, True),
                           (_packer(signed=True), False, False), (_packer(3, 200), True, True)]:
        f = _raw_imu(mav, rng, v1=v1, zeros=zeros)
        fast, rest = frames.split(f + f)
        assert len(fast) == 2 and rest == b""
        assert fast[0].get_srcSystem() == mav.srcSystem and fast[0].get_srcComponent() == mav.srcComponent
    # a signed frame is left to pymavlink where the link verifies signatures
    f = _raw_imu(_packer(signed=True), rng)
    assert frames.split(f, signed_ok=False) == ([], f)
    hb = _heartbeat(_packer())
    assert frames.split(hb) == ([], hb)
