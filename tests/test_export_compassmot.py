"""Issue 13.2: a calibration carrying a ``mag_current`` extension (compassmot) exports COMPASS_MOT_X/Y/Z +
COMPASS_MOTCT (ArduPilot) and CAL_MAGn_xCOMP + CAL_MAG_COMP_TYP (PX4). Checked the firmware's way: the
parameters read back from the written file and applied with each firmware's correction (written here from
the firmware source, not from export.py) take the interference out of the field."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pymavlink.mavparm import MAVParmDict

from onlinecal.export import export_calibration
from onlinecal.model import Calibration, SensorCalibration

K = [2.0e-3, -1.5e-3, 4.0e-3]  # gauss per A: raw = true + K·current
K_SIG = [1e-4, 1e-4, 1e-4]


def _cal(ext: dict | None) -> Calibration:
    """A magnetometer with a general matrix (rotation and non-orthogonality, so the soft iron is not the
    identity) and bias; σ small enough for every term to be written."""
    sig = {"bias": [1e-4] * 3, "scale": [1e-4] * 3, "alpha": [1e-4] * 3, "xi": [1e-4] * 3}
    mag = SensorCalibration.from_params(bias=(0.11, -0.19, 0.23), scale=1 / (0.48 * np.array([1.08, 0.91, 1.03])),
                                        alpha=(0.03, -0.05, 0.02), xi=(0.01, 0.02, -0.015), sigma=sig)
    return Calibration(mag=mag, source="cal", extensions=({"mag_current": ext} if ext else {}))


def _ap_compass(h_mG: np.ndarray, P: dict, current: np.ndarray) -> np.ndarray:
    """AP_Compass_Backend::correct_field (orientation none): mag += OFS; mag = soft_iron·mag; then
    mag += COMPASS_MOT·current when COMPASS_MOTCT = 2 (current)."""
    m = h_mG + np.array([P["COMPASS_OFS_X"], P["COMPASS_OFS_Y"], P["COMPASS_OFS_Z"]])
    W = np.array([[P["COMPASS_DIA_X"], P["COMPASS_ODI_X"], P["COMPASS_ODI_Y"]],
                  [P["COMPASS_ODI_X"], P["COMPASS_DIA_Y"], P["COMPASS_ODI_Z"]],
                  [P["COMPASS_ODI_Y"], P["COMPASS_ODI_Z"], P["COMPASS_DIA_Z"]]])
    m = m @ W.T
    if P.get("COMPASS_MOTCT", 0) == 2:
        m = m + current[:, None] * np.array([P["COMPASS_MOT_X"], P["COMPASS_MOT_Y"], P["COMPASS_MOT_Z"]])
    return m


def _px4_mag(h_g: np.ndarray, P: dict, current: np.ndarray) -> np.ndarray:
    """calibration::Magnetometer::Correct (rotation none): scale·((data + power·comp) − offset), the power
    in kA for CAL_MAG_COMP_TYP = 2 (current)."""
    v = lambda kind: np.array([P[f"CAL_MAG0_{a}{kind}"] for a in "XYZ"])  # noqa: E731
    d, o = v("SCALE"), v("ODIAG")
    W = np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])
    x = h_g
    if P.get("CAL_MAG_COMP_TYP", 0) == 2:
        x = x + (current / 1e3)[:, None] * v("COMP")
    return (x - v("OFF")) @ W.T


def _read(path: Path, fmt: str) -> dict[str, float]:
    if fmt == "ardupilot":
        P = MAVParmDict()
        assert P.load(str(path))
        return dict(P)
    out = {}
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            f = line.split("\t")
            out[f[2]] = float(int(f[3])) if f[4] == "6" else float(f[3])
    return out


def _export_cli(cal: Calibration, fmt: str, tmp_path: Path, *extra: str) -> tuple[subprocess.CompletedProcess, dict]:
    cj = tmp_path / "cal.json"
    cal.save(str(cj))
    assert "mag_current" in json.loads(cj.read_text()).get("extensions", {}) or not cal.extensions
    out = tmp_path / ("cal.parm" if fmt == "ardupilot" else "cal.params")
    r = subprocess.run([sys.executable, "-m", "onlinecal", "export", str(cj), "--format", fmt, "--out", str(out),
                        *extra], capture_output=True, text=True, timeout=120)
    assert "Traceback" not in r.stderr, r.stderr
    return r, (_read(out, fmt) if out.exists() else {})


@pytest.mark.parametrize("fmt", ["ardupilot", "px4"])
def test_written_parameters_take_the_interference_out(fmt: str, tmp_path: Path) -> None:
    cal = _cal({"coeff": K, "basis": "current", "coeff_sigma": K_SIG})
    r, P = _export_cli(cal, fmt, tmp_path)
    assert r.returncode == 0, r.stderr
    names = (["COMPASS_MOT_X", "COMPASS_MOT_Y", "COMPASS_MOT_Z", "COMPASS_MOTCT"] if fmt == "ardupilot"
             else ["CAL_MAG0_XCOMP", "CAL_MAG0_YCOMP", "CAL_MAG0_ZCOMP", "CAL_MAG_COMP_TYP"])
    assert all(n in P for n in names) and P[names[3]] == 2
    rng = np.random.default_rng(3)
    h = rng.normal(0, 0.3, (2000, 3)) + np.array([0.1, -0.2, 0.25])  # interference-free raw field, gauss
    amps = rng.uniform(0, 60, 2000)
    raw = h + amps[:, None] * np.array(K)
    fw = _ap_compass if fmt == "ardupilot" else _px4_mag
    unit = 1e3 if fmt == "ardupilot" else 1.0
    want = fw(h * unit, {**P, names[3]: 0}, np.zeros(2000))  # the firmware's field without interference
    got = fw(raw * unit, P, amps)
    without = fw(raw * unit, {**P, names[3]: 0}, amps)
    err, before = np.abs(got - want).max(), np.abs(without - want).max()
    assert before > 0.1 * unit  # the interference is large (up to 0.24 G at 60 A)
    assert err < 2e-6 * before  # float32 parameters


@pytest.mark.slow
def test_coefficient_within_its_noise_is_withheld(tmp_path: Path) -> None:
    cal = _cal({"coeff": [1e-5, -2e-5, 1e-5], "basis": "current", "coeff_sigma": [1e-5] * 3})
    r, P = _export_cli(cal, "ardupilot", tmp_path)
    assert r.returncode == 4 and "COMPASS_MOT_X not written" in r.stderr and "σ of zero" in r.stderr
    assert "COMPASS_MOT_X" not in P and "COMPASS_OFS_X" in P
    r, P = _export_cli(cal, "ardupilot", tmp_path, "--force")
    assert r.returncode == 0 and "COMPASS_MOT_X" in P and "--force" in r.stderr


def test_no_extension_no_motor_parameters_and_throttle_basis() -> None:
    exp = export_calibration(_cal(None), "ardupilot")
    assert not any(n.startswith("COMPASS_MOT") for n in exp.params)
    exp = export_calibration(_cal({"coeff": [0.05, 0, -0.1], "basis": "throttle", "instance": 2}), "px4")
    assert exp.params["CAL_MAG_COMP_TYP"] == 1 and exp.params["CAL_MAG1_ZCOMP"] == pytest.approx(0.1)
    assert not any("no firmware parameter" in w for w in exp.warnings)
    assert any("carries no σ" in w for w in exp.warnings)


def test_composed_with_onboard_is_withheld_and_bad_entries_refused(tmp_path: Path) -> None:
    cal = _cal({"coeff": K, "basis": "current", "coeff_sigma": K_SIG})
    exp = export_calibration(cal, "ardupilot", onboard={"COMPASS_OFS_X": 10.0})
    assert "COMPASS_MOT_X" in exp.withheld and "already corrected" in exp.withheld["COMPASS_MOT_X"]
    bad = tmp_path / "bad.json"
    d = _cal(None).to_dict()
    d["extensions"] = {"mag_current": {"coeff": [1, 2], "basis": "current"}}
    bad.write_text(json.dumps(d))
    r = subprocess.run([sys.executable, "-m", "onlinecal", "export", str(bad), "--format", "px4"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "mag_current" in r.stderr and "list of 3" in r.stderr


def test_correct_removes_the_interference_with_the_logs_current_series() -> None:
    from onlinecal.extensions import correct
    from onlinecal.io.base import ImuData

    t = np.arange(0, 10, 0.01)
    tm = np.arange(0, 10, 0.02)
    h = np.tile([0.2, -0.1, 0.4], (tm.size, 1))
    amps_t = np.linspace(0, 10, 11)
    amps = np.interp(tm, amps_t, 5.0 * amps_t)
    raw = h + amps[:, None] * np.array(K)
    d = ImuData(t, np.zeros((t.size, 3)), np.zeros((t.size, 3)), np.full(t.size, np.nan), tm, raw, "x",
                series={"current": (amps_t, 5.0 * amps_t)})
    ext = {"mag_current": {"coeff": K, "basis": "current"}}
    assert np.allclose(correct(d, ext).mag, h, atol=1e-12)
    with pytest.raises(ValueError, match="without a current series"):
        correct(ImuData(t, d.gyro, d.acc, d.temp, tm, raw, "x"), ext)
