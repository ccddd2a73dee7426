"""The latitude a replay takes from a log's GPS (onlinecal.io.position), checked against files written by
someone else's encoder (pymavlink's packets, read back with pymavlink's own DataFlash reader), the real PX4 log
(which has no fix), and the replay told the same latitude by hand."""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from onlinecal.io import write_log
from onlinecal.io.base import ImuData, LogError
from onlinecal.io.position import log_position, logs_place
from onlinecal.sim import simulate
from onlinecal.sim.motion import DEFAULT_LATITUDE_DEG

DATA = Path(__file__).parents[1].parent / "shared" / "data"
os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink2  # noqa: E402


def _cli(*args: str, timeout: int = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "onlinecal", *args], capture_output=True, text=True, timeout=timeout)


def _still(n: int = 400, rate: float = 100.0) -> ImuData:
    t = np.arange(n) / rate
    return ImuData(t, np.zeros((n, 3)), np.tile([0.0, 0.0, 9.81], (n, 1)), np.full(n, 25.0), t[::2],
                   np.tile([0.2, 0.0, 0.4], (n // 2, 1)))


def _tlog_packets(path: Path, packets: list[tuple[int, bytes]]) -> None:
    with open(path, "wb") as f:
        for us, pkt in packets:
            f.write(struct.pack(">Q", 1_700_000_000_000_000 + us) + pkt)


def test_tlog_gps_raw_int_written_by_pymavlink(tmp_path: Path) -> None:
    """GPS_RAW_INT packets packed by pymavlink, MAVLink 1 and 2 mixed, between RAW_IMU: fixes below 3-D are no
    fix; a packet whose bytes were damaged (its CRC fails) is not read; the median of the 3-D fixes is returned."""
    v2 = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    pk: list[tuple[int, bytes]] = []
    lat0, lon0 = -33.8688, 151.2093  # Sydney: a southern latitude, an eastern longitude past 90°
    for k in range(200):
        us = k * 10_000
        pk.append((us, v2.raw_imu_encode(us, 0, 0, 1000, 0, 0, 0, 200, 0, 400).pack(v2)))
        if k % 20 == 0:
            fix = 1 if k < 60 else 3  # no fix for the first 0.6 s: a receiver that has not locked yet
            lat = 12.0 if fix < 3 else lat0 + 1e-6 * k
            msg = v2.gps_raw_int_encode(us, fix, round(lat * 1e7), round(lon0 * 1e7), 50_000, 90, 120, 0, 0, 10)
            pk.append((us, msg.pack(v2, force_mavlink1=k % 40 == 0)))
    bad = bytearray(v2.gps_raw_int_encode(5, 3, round(80.0 * 1e7), 0, 0, 0, 0, 0, 0, 10).pack(v2))
    bad[14] ^= 0x40  # a byte of the latitude flipped: the CRC no longer matches
    pk.insert(5, (5, bytes(bad)))
    log = tmp_path / "g.tlog"
    _tlog_packets(log, pk)
    pos = log_position(log)
    assert pos is not None and pos.source.startswith("GPS_RAW_INT")
    assert sum(p[0] == 0xFE for _, p in pk) == 5  # MAVLink 1 packets among them
    assert pos.n_fixes == 7  # k = 60, 80, ..., 180
    assert pos.latitude_deg == pytest.approx(lat0 + 1e-6 * 120, abs=1e-7)
    assert pos.longitude_deg == pytest.approx(lon0, abs=1e-7)


def test_tlog_global_position_when_no_gps_raw(tmp_path: Path) -> None:
    """No GPS_RAW_INT: the autopilot's GLOBAL_POSITION_INT, where it is not (0, 0); none of either: no position."""
    v2 = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    pk = [(k * 10_000, v2.raw_imu_encode(k * 10_000, 0, 0, 1000, 0, 0, 0, 0, 0, 0).pack(v2)) for k in range(50)]
    _tlog_packets(tmp_path / "none.tlog", pk)
    assert log_position(tmp_path / "none.tlog") is None
    pk += [(600_000, v2.global_position_int_encode(600, 0, 0, 0, 0, 0, 0, 0, 0).pack(v2)),
           (700_000, v2.global_position_int_encode(700, round(64.1466 * 1e7), round(-21.9426 * 1e7), 0, 0, 0, 0, 0,
                                                   0).pack(v2))]
    _tlog_packets(tmp_path / "glob.tlog", pk)
    pos = log_position(tmp_path / "glob.tlog")
    assert pos is not None and pos.source == "GLOBAL_POSITION_INT" and pos.n_fixes == 1
    assert pos.latitude_deg == pytest.approx(64.1466, abs=1e-7)


def test_dataflash_gps_as_pymavlink_reads_it(tmp_path: Path) -> None:
    """The GPS records the writer puts in a .bin are what pymavlink's DFReader decodes (Lat in degrees, Status
    3, instance 0), and the position read back is theirs."""
    from pymavlink import DFReader

    d = _still()
    tg = np.arange(0.0, 4.0, 0.2)
    d.series["latitude"] = (tg, 51.4779 + 1e-5 * np.arange(tg.size))
    d.series["longitude"] = (tg, np.full(tg.size, -0.0015))
    log = tmp_path / "g.bin"
    write_log(log, d)
    r = DFReader.DFReader_binary(str(log))
    seen = []
    while (m := r.recv_match(type="GPS")) is not None:
        seen.append((m.Lat, m.Lng, m.Status, m.I))
    assert len(seen) == tg.size
    assert all(s[2] == 3 and s[3] == 0 for s in seen)
    theirs = np.median([s[0] for s in seen])
    pos = log_position(log)
    assert pos is not None and pos.n_fixes == tg.size
    assert pos.latitude_deg == pytest.approx(theirs, abs=1e-7)
    assert pos.longitude_deg == pytest.approx(-0.0015, abs=1e-7)


@pytest.mark.parametrize("ext", [".bin", ".tlog", ".ulg"])
def test_no_position_without_gps(tmp_path: Path, ext: str) -> None:
    log = tmp_path / f"n{ext}"
    write_log(log, _still())
    assert log_position(log) is None
    assert log_position(tmp_path / "n.csv") is None  # the flat schema has no position


def test_missing_file_is_a_log_error(tmp_path: Path) -> None:
    with pytest.raises(LogError, match="nothing.bin"):
        log_position(tmp_path / "nothing.bin")


def test_real_px4_log_has_no_fix() -> None:
    """The real PX4 log carries vehicle_local_position with xy_global false and ref_lat 0 throughout (a flight
    without GPS): no position, not (0, 0) taken for one."""
    assert log_position(DATA / "px4-ulog" / "sample.ulg") is None


def test_logs_far_apart_are_not_one_place(tmp_path: Path) -> None:
    for name, lat in (("a", 47.0), ("b", 47.4), ("c", 60.0)):
        d = _still()
        d.series["latitude"] = (np.array([0.5, 1.0]), np.full(2, lat))
        d.series["longitude"] = (np.array([0.5, 1.0]), np.full(2, 8.0))
        write_log(tmp_path / f"{name}.tlog", d)
    pos, src, notes = logs_place([str(tmp_path / "a.tlog"), str(tmp_path / "b.tlog")])
    assert pos is not None and pos.latitude_deg == pytest.approx(47.2) and "a.tlog" in (src or "") and not notes
    assert pos.year == pytest.approx(2023.87, abs=0.01)  # the writers' date (io.base.WRITE_EPOCH_US)
    pos, src, notes = logs_place([str(tmp_path / "a.tlog"), str(tmp_path / "c.tlog")])
    assert pos is None and src is None and "different latitudes" in notes[0]


def test_simulated_gps_follows_the_flight() -> None:
    """The simulator's fixes move with the flown path: the distance between the first and the farthest fix
    equals the integrated velocity's (within the 5-Hz sampling), and the home is the default."""
    sim = simulate("fixedwing", 2, duration=120.0, imu_rate=100.0, mag_rate=50.0, gps=True)
    t, lat = sim.data.series["latitude"]
    _, lon = sim.data.series["longitude"]
    assert lat[0] == pytest.approx(DEFAULT_LATITUDE_DEG)
    north = np.radians(lat - lat[0]) * 6_371_000.0
    east = np.radians(lon - lon[0]) * 6_371_000.0 * np.cos(np.radians(lat[0]))
    traj = sim.trajectory
    v = traj.v_world
    k = np.clip(np.rint(t / traj.dt).astype(int), 0, v.shape[0] - 1)
    pos = np.vstack([np.zeros(3), np.cumsum(v[:-1] * traj.dt, axis=0)])[k]
    assert np.max(np.hypot(east, north)) > 200.0  # it flew somewhere
    assert np.allclose(east, pos[:, 0], atol=0.05) and np.allclose(north, pos[:, 1], atol=0.05)
    with pytest.raises(ValueError, match="Earth's rotation"):
        simulate("paper", 1, duration=20.0, gps=True)


def test_replay_takes_the_latitude_from_the_log(tmp_path: Path) -> None:
    """``simulate --gps`` → ``replay``: the filter is told the log's latitude and the World Magnetic Model's
    declination at the fix and says where both came from; the result is the one ``--latitude``/``--declination``
    with the same numbers give, value for value; the simulated field's declination is the one the replay is
    told; ``--latitude none`` turns it off; a fleet uses each log's own."""
    log = tmp_path / "f.tlog"
    r = _cli("simulate", "--out", str(log), "--profile", "multirotor", "--seed", "5", "--duration", "30", "--gps")
    assert r.returncode == 0, r.stderr
    truth = json.loads(Path(str(log) + ".truth.json").read_text())
    h = truth["field_world"]
    field_decl = np.degrees(np.arctan2(h[0], h[1]))  # ENU: east over north
    js = tmp_path / "gps.json"
    r = _cli("replay", str(log), "--init", "none", "--json", str(js))
    assert r.returncode in (0, 1), r.stderr
    assert "from f.tlog's GPS" in r.stderr and "World Magnetic Model (WMM2020 at 2023.9" in r.stderr
    gps = json.loads(js.read_text())
    e = gps["meta"]["online"]["observability"]["earth_rate"]
    assert e["latitude_deg"] == pytest.approx(DEFAULT_LATITUDE_DEG, abs=1e-6)
    assert "GPS_RAW_INT" in e["latitude_source"] and "WMM2020" in e["declination_source"]
    assert e["declination_deg"] == pytest.approx(field_decl, abs=1e-6) and e["declination_sigma_deg"] == 1.0
    out = {}
    for name, extra in (("hand", ["--latitude", repr(DEFAULT_LATITUDE_DEG), "--declination",
                                  repr(e["declination_deg"])]), ("off", ["--latitude", "none"])):
        js = tmp_path / f"{name}.json"
        r = _cli("replay", str(log), "--init", "none", "--json", str(js), *extra)
        assert r.returncode in (0, 1), r.stderr
        assert "GPS" not in r.stderr
        out[name] = json.loads(js.read_text())
    eh = out["hand"]["meta"]["online"]["observability"]["earth_rate"]
    assert eh["latitude_source"] == "--latitude" and eh["declination_source"] == "--declination"
    assert out["off"]["meta"]["online"]["observability"]["earth_rate"]["latitude_deg"] is None
    for s in ("gyro", "accel", "mag"):
        for k in ("bias", "scale"):
            assert np.allclose(gps[s][k], out["hand"][s][k], rtol=0, atol=1e-12)
    assert not np.allclose(gps["gyro"]["bias"], out["off"]["gyro"]["bias"], rtol=0, atol=1e-6)
    r = _cli("batch", str(log), "--json", str(tmp_path / "b.json"))
    assert r.returncode in (0, 1, 4, 5), r.stderr
    assert "vertical part is taken out of the rests' gyro bias" in r.stderr and "declination" not in r.stderr
    removed = json.loads((tmp_path / "b.json").read_text())["meta"]["batch"]["steps"]["gyro"]["figures"][
        "earth_rate_removed"]
    assert removed["latitude_deg"] == pytest.approx(DEFAULT_LATITUDE_DEG, abs=1e-6)
    r = _cli("replay", str(log), "--init", "none", "--latitude", "none", "--declination", "2")
    assert r.returncode == 2 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = _cli("replay", str(log), "--init", "none", "--jobs", "1", "--json", str(tmp_path / "fleet.jsonl"))
    assert r.returncode in (0, 1), r.stderr
    rec = json.loads((tmp_path / "fleet.jsonl").read_text().splitlines()[0])
    ef = rec["calibration"]["meta"]["online"]["observability"]["earth_rate"]
    assert ef["latitude_deg"] == pytest.approx(DEFAULT_LATITUDE_DEG, abs=1e-6) and "GPS" in ef["latitude_source"]
    assert ef["declination_deg"] == pytest.approx(field_decl, abs=1e-6)


@pytest.mark.parametrize(("lat", "lon"), [(47.397742, 8.545594), (-33.87, 151.21), (64.15, -21.94),
                                          (40.0, -105.0), (-54.8, -68.3)])
def test_wmm_declination_agrees_with_the_igrf(lat: float, lon: float) -> None:
    """The WMM's declination (pygeomag) against the IGRF's (ppigrf: another model, another implementation)
    on the writers' date: within the WMM's own stated uncertainty, and the σ the filter is told covers it."""
    import datetime

    import ppigrf

    from onlinecal.io.base import WRITE_EPOCH_US, decimal_year
    from onlinecal.place import wmm_declination

    d = wmm_declination(lat, lon, decimal_year(WRITE_EPOCH_US * 1e-6))
    be, bn, _ = ppigrf.igrf(lon, lat, 0.0, datetime.datetime.fromtimestamp(WRITE_EPOCH_US * 1e-6, datetime.UTC)
                            .replace(tzinfo=None))
    igrf = float(np.degrees(np.arctan2(np.asarray(be).item(), np.asarray(bn).item())))
    assert abs(d.deg - igrf) < d.model_sigma_deg, (d, igrf)
    assert d.model == "WMM2020" and d.note is None and d.sigma_deg >= max(1.0, d.model_sigma_deg)


def test_wmm_undated_log_uses_today() -> None:
    from onlinecal.place import wmm_declination

    d = wmm_declination(47.4, 8.5, None)
    assert d.note is not None and "not dated" in d.note and d.model in ("WMM2025",)
    with pytest.raises(ValueError, match="latitude"):
        wmm_declination(95.0, 0.0, 2024.0)
    near_pole = wmm_declination(86.5, 160.0, 2024.0)  # H of a few µT near the north magnetic pole
    assert 5.0 < near_pole.sigma_deg <= 180.0 and near_pole.sigma_deg == pytest.approx(near_pole.model_sigma_deg)


def test_simulate_gps_refusals(tmp_path: Path) -> None:
    r = _cli("simulate", "--out", str(tmp_path / "p.bin"), "--profile", "paper", "--duration", "10", "--gps")
    assert r.returncode == 2 and "Earth's rotation" in r.stderr and "Traceback" not in r.stderr
    r = _cli("simulate", "--out", str(tmp_path / "p.csv"), "--profile", "multirotor", "--duration", "10", "--gps")
    assert r.returncode == 2 and "CSV" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize("ext", [".bin", ".tlog", ".ulg"])
def test_writers_refuse_a_position_that_is_not_one(tmp_path: Path, ext: str) -> None:
    d = _still()
    d.series["latitude"] = (np.array([0.5, 1.0]), np.array([47.0, 47.0]))
    d.series["longitude"] = (np.array([0.5, 1.5]), np.array([8.0, 8.0]))
    with pytest.raises(ValueError, match="share their times"):
        write_log(tmp_path / f"a{ext}", d)
    d.series["longitude"] = (np.array([0.5, 1.0]), np.array([8.0, 8.0]))
    d.series["latitude"] = (np.array([0.5, 1.0]), np.array([47.0, 91.0]))
    with pytest.raises(ValueError, match="latitude within"):
        write_log(tmp_path / f"b{ext}", d)
