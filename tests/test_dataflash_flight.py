"""Issue 10.5: real ArduPilot flight logs. IMU instances (the ``I`` field and the old IMU2/IMU3 names),
``--imu N``, PARM as ``ImuData.params`` with a warning when it holds the firmware's own calibration, the
current / throttle / arming series. No real .bin flight is in shared/data: the logs here are written record by
record in ArduPilot's DataFlash layout (FMT records, then messages), and read back with pymavlink's DFReader."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from onlinecal.io import LogError, open_log, read_log
from onlinecal.io.dataflash import FMT_FORMAT, FMT_ID, HEAD, _fmt_record, _record_dtype

IMU_NEW = ("IMU", "QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz")
IMU_OLD = ("IMU", "QffffffIIf", "TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T")  # ArduPilot 3.x, no I
IMU2_OLD = ("IMU2", "QffffffIIf", "TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T")
MAG = ("MAG", "QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S")
PARM = ("PARM", "QNff", "TimeUS,Name,Value,Default")
BAT = ("BAT", "QBfff", "TimeUS,Inst,Volt,VoltR,Curr")
CTUN = ("CTUN", "Qfff", "TimeUS,ThI,ThO,ThH")
ARM = ("ARM", "QBIBB", "TimeUS,ArmState,ArmChecks,Forced,Method")


class Writer:
    """DataFlash records in the order written: FMT first for each type, then the messages."""

    def __init__(self) -> None:
        self.buf = bytearray(_fmt_record(FMT_ID, *FMT_FORMAT))
        self.ids: dict[str, tuple[int, np.dtype]] = {}

    def fmt(self, spec: tuple[str, str, str]) -> None:
        name, fmt, cols = spec
        mid = 100 + len(self.ids)
        self.ids[name] = (mid, _record_dtype(fmt, cols))
        self.buf += _fmt_record(mid, name, fmt, cols)

    def put(self, name: str, **fields: object) -> None:
        mid, dt = self.ids[name]
        rec = np.zeros(1, dt)
        rec["h1"], rec["h2"], rec["id"] = HEAD[0], HEAD[1], mid
        for k, v in fields.items():
            rec[k] = v.encode() if isinstance(v, str) else v
        self.buf += rec.tobytes()

    def save(self, path: Path) -> Path:
        path.write_bytes(bytes(self.buf))
        return path


def flight(tmp_path: Path, old_names: bool = False, params: dict[str, float] | None = None) -> Path:
    """20 s at 50 Hz: two IMUs (instance 1 reads gyro + 0.05 rad/s on x, acc z 9.9), one compass at 10 Hz,
    battery current 10 Hz, throttle 10 Hz, armed at 5 s and disarmed at 15 s."""
    w = Writer()
    for spec in ((IMU_OLD, IMU2_OLD) if old_names else (IMU_NEW,)) + (MAG, PARM, BAT, CTUN, ARM):
        w.fmt(spec)
    for name, value in (params or {}).items():
        w.put("PARM", TimeUS=1000, Name=name, Value=value, Default=0.0)
    rng = np.random.default_rng(0)
    for k in range(1000):
        us = 100_000 + k * 20_000
        for inst in (0, 1):
            g = rng.normal(0, 0.01, 3) + [0.05 * inst, 0, 0]
            f = {"TimeUS": us, "GyrX": g[0], "GyrY": g[1], "GyrZ": g[2], "AccX": 0.1, "AccY": -0.1,
                 "AccZ": -9.8 - 0.1 * inst, "T": 40.0 + inst}
            if old_names:
                w.put("IMU2" if inst else "IMU", **f)
            else:
                w.put("IMU", I=inst, **f)
        if k % 5 == 0:
            w.put("MAG", TimeUS=us + 1000, I=0, MagX=200, MagY=-50, MagZ=400, Health=1)
            thr = 0.0 if us < 5e6 or us > 15e6 else 0.55
            w.put("BAT", TimeUS=us + 2000, Inst=0, Volt=16.0, VoltR=16.2, Curr=1.0 + 30.0 * thr)
            w.put("CTUN", TimeUS=us + 3000, ThI=thr, ThO=thr, ThH=0.5)
        if us == 5_000_000:
            w.put("ARM", TimeUS=us, ArmState=1)
        if us == 15_000_000:
            w.put("ARM", TimeUS=us, ArmState=0)
    return w.save(tmp_path / ("old.bin" if old_names else "flight.bin"))


@pytest.mark.parametrize("old_names", [False, True])
def test_imu_instances_by_i_field_and_by_old_names(tmp_path, old_names):
    p = flight(tmp_path, old_names)
    first, second = read_log(p), read_log(p, imu=1)
    assert first.n_imu == second.n_imu == 1000 and first.n_mag == second.n_mag == 200
    assert np.mean(first.gyro[:, 0]) == pytest.approx(0.0, abs=2e-3)
    assert np.mean(second.gyro[:, 0]) == pytest.approx(0.05, abs=2e-3)  # the other chip, told apart
    assert np.mean(second.acc[:, 2]) == pytest.approx(-9.9, abs=1e-5)
    assert np.nanmean(second.temp) == pytest.approx(41.0)
    assert any("ignored IMU instance 1" in w for w in first.warnings)
    with pytest.raises(LogError) as e:
        read_log(p, imu=2)
    assert "no IMU instance 2 in the log (instances: 0, 1)" in e.value.message or \
        "no IMU instance 2 in the log (instances: 1)" in e.value.message


def test_parm_becomes_params_and_a_non_default_calibration_is_warned(tmp_path):
    onboard = {"INS_ACCOFFS_X": 0.12, "INS_ACCSCAL_X": 1.0, "COMPASS_OFS_X": -35.0, "FRAME_CLASS": 1.0}
    d = read_log(flight(tmp_path, params=onboard))
    assert d.params == pytest.approx(onboard)
    said = [w for w in d.warnings if "firmware's own calibration" in w]
    assert len(said) == 1
    assert "INS_ACCOFFS_X=0.12" in said[0] and "COMPASS_OFS_X=-35" in said[0]
    assert "INS_ACCSCAL_X" not in said[0] and "FRAME_CLASS" not in said[0]  # at their defaults / not calibration
    clean = read_log(flight(tmp_path, params={"INS_ACCOFFS_X": 0.0, "INS_ACCSCAL_X": 1.0}))
    assert clean.params and not any("firmware's own calibration" in w for w in clean.warnings)


def test_a_log_without_parm_has_empty_params(tmp_path):
    d = read_log(flight(tmp_path))
    assert d.params == {}


def test_current_throttle_and_arming_series(tmp_path):
    d = read_log(flight(tmp_path))
    t_c, cur = d.series["current"]
    t_h, thr = d.series["throttle"]
    t_a, armed = d.series["armed"]
    assert t_c.size == t_h.size == 200
    flying = (t_h - 0.003 >= 5.0 - 1e-9) & (t_h - 0.003 <= 15.0 + 1e-9)  # CTUN is logged 3 ms after its tick
    assert thr[flying] == pytest.approx(0.55) and np.all(thr[~flying] == 0.0)
    assert cur[flying] == pytest.approx(1.0 + 30.0 * 0.55)
    assert list(armed) == [1.0, 0.0] and list(t_a) == pytest.approx([5.0, 15.0])
    # the series are on the final streamed block only (bounded memory for the IMU blocks)
    blocks = list(open_log(flight(tmp_path)).blocks(max_samples=300))
    assert [bool(b.series) for b in blocks] == [False] * (len(blocks) - 1) + [True]
