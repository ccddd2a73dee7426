"""`onlinecal export`: vehicle parameters checked by running the firmware's own correction on raw data.

The firmware formulas below are written here from the firmware source, independently of
onlinecal/export.py (which is only used to produce the files):

* ArduPilot AP_Compass_Backend::rotate_field + correct_field — rotate by COMPASS_ORIENT, ``mag += OFS``,
  ``mag *= SCALE`` (when within the scale-factor limits), ``mag = [[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y,
  ODI_Z], [ODI_Y, ODI_Z, DIA_Z]] @ mag``, in milligauss;
  AP_InertialSensor_Backend::_rotate_and_correct_accel — ``accel -= ACCOFFS; accel *= ACCSCAL``;
  _rotate_and_correct_gyro — ``gyro -= GYROFFS``.
* PX4 calibration::{Accelerometer,Gyroscope,Magnetometer}::Correct — ``R·((d − OFF) ∘ SCALE)``,
  ``R·(d − OFF)``, ``R·(W·(d − OFF))`` with W from SCALE/ODIAG, in m/s², rad/s, gauss.

Parameter files are read back with pymavlink's ``MAVParmDict.load`` (ArduPilot) and with a reader of
QGroundControl's ``.params`` format written from ParameterManager::readParametersFromStream (PX4).
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from pymavlink.mavparm import MAVParmDict

from onlinecal.cli import main
from onlinecal.export import export_calibration, header_lines, vehicle_params, write_parm
from onlinecal.model import Calibration, SensorCalibration
from onlinecal.sim import simulate
from onlinecal.sim.sensors import paper_truth

DEG = math.pi / 180
F32_REL = 2e-6  # parameters are written to float32 precision (≈ 6e-8 relative), raw values are float64


# -- firmware side (from the firmware source, not from export.py) -----------------------------------

def ap_rotate(v: np.ndarray, orient: int) -> np.ndarray:
    """AP_Math Vector3::rotate for the rotations used here (vector3.cpp)."""
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    if orient == 0:
        return v
    if orient == 2:  # ROTATION_YAW_90: tmp = x; x = -y; y = tmp
        return np.stack([-y, x, z], 1)
    if orient == 16:  # ROTATION_ROLL_90: tmp = z; z = y; y = -tmp
        return np.stack([x, -z, y], 1)
    raise NotImplementedError(orient)


def ap_compass(h_mG: np.ndarray, P: dict) -> np.ndarray:
    m = ap_rotate(h_mG, int(P.get("COMPASS_ORIENT", 0)))
    m = m + np.array([P["COMPASS_OFS_X"], P["COMPASS_OFS_Y"], P["COMPASS_OFS_Z"]])
    s = P.get("COMPASS_SCALE", 0.0)
    if 1 / 1.5 <= s <= 1.5:  # have_scale_factor: COMPASS_MIN_SCALE_FACTOR..COMPASS_MAX_SCALE_FACTOR
        m = m * s
    W = np.array([
        [P["COMPASS_DIA_X"], P["COMPASS_ODI_X"], P["COMPASS_ODI_Y"]],
        [P["COMPASS_ODI_X"], P["COMPASS_DIA_Y"], P["COMPASS_ODI_Z"]],
        [P["COMPASS_ODI_Y"], P["COMPASS_ODI_Z"], P["COMPASS_DIA_Z"]],
    ])
    return m @ W.T


def ap_accel(a: np.ndarray, P: dict) -> np.ndarray:
    offs = np.array([P["INS_ACCOFFS_X"], P["INS_ACCOFFS_Y"], P["INS_ACCOFFS_Z"]])
    scal = np.array([P["INS_ACCSCAL_X"], P["INS_ACCSCAL_Y"], P["INS_ACCSCAL_Z"]])
    return (a - offs) * scal


def ap_gyro(g: np.ndarray, P: dict) -> np.ndarray:
    return g - np.array([P["INS_GYROFFS_X"], P["INS_GYROFFS_Y"], P["INS_GYROFFS_Z"]])


def px4_rot(orient: int) -> np.ndarray:
    """get_rot_matrix for the rotations used here (rot_lookup: roll, pitch, yaw → Dcm of Euler)."""
    return {0: np.eye(3), 2: np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]),
            16: np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])}[orient]


def px4_vec(P: dict, s: str, kind: str) -> np.ndarray:
    return np.array([P[f"CAL_{s}0_{ax}{kind}"] for ax in "XYZ"])


def px4_accel(a: np.ndarray, P: dict) -> np.ndarray:
    return (a - px4_vec(P, "ACC", "OFF")) * px4_vec(P, "ACC", "SCALE")


def px4_gyro(g: np.ndarray, P: dict) -> np.ndarray:
    return g - px4_vec(P, "GYRO", "OFF")


def px4_mag(h_gauss: np.ndarray, P: dict) -> np.ndarray:
    d, o = px4_vec(P, "MAG", "SCALE"), px4_vec(P, "MAG", "ODIAG")
    W = np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])
    R = px4_rot(int(P.get("CAL_MAG0_ROT", 0)))
    return (h_gauss - px4_vec(P, "MAG", "OFF")) @ W.T @ R.T


def read_qgc_params(path: Path) -> dict[str, float]:
    """QGroundControl's .params reader: '#' lines skipped, 5 tab-separated fields, type 6 int / 9 float."""
    out: dict[str, float] = {}
    for line in path.read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        f = line.split("\t")
        assert len(f) == 5, line
        assert f[0] == "1" and f[1] == "1", line
        assert f[4] in ("6", "9"), line
        out[f[2]] = float(int(f[3])) if f[4] == "6" else float(f[3])
    return out


def read_back(path: Path, fmt: str) -> dict[str, float]:
    if fmt == "ardupilot":
        P = MAVParmDict()
        assert P.load(str(path))
        return dict(P)
    return read_qgc_params(path)


def firmware(P: dict, fmt: str, gyro: np.ndarray, acc: np.ndarray, mag_gauss: np.ndarray):
    if fmt == "ardupilot":
        return ap_gyro(gyro, P), ap_accel(acc, P), ap_compass(mag_gauss * 1e3, P)
    return px4_gyro(gyro, P), px4_accel(acc, P), px4_mag(mag_gauss, P)


# -- data ---------------------------------------------------------------------------------------------

def fib(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z * z)
    p = i * math.pi * (3 - math.sqrt(5))
    return np.stack([r * np.cos(p), r * np.sin(p), z], 1)


def raw_samples(cal: Calibration, seed: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw gyro, accel, mag: a simulated session with this truth, plus raw values whose calibrated
    vectors cover all directions (so worst cases are seen)."""
    sim = simulate("paper", seed, duration=40.0, truth=cal)
    d = fib(3000)
    gyro = np.vstack([sim.data.gyro, cal.gyro.inv().apply(2.0 * d)])
    acc = np.vstack([sim.data.acc, cal.accel.inv().apply(9.80665 * d)])
    mag = np.vstack([sim.data.mag, cal.mag.inv().apply(d)])
    return gyro, acc, mag


def expressible_truth() -> Calibration:
    """Rotation and non-orthogonality zero, gyro scale 1: everything each firmware has a parameter for."""
    return Calibration(
        gyro=SensorCalibration.from_params(bias=(0.012, -0.02, 0.007)),
        accel=SensorCalibration.from_params(bias=(0.21, -0.33, 0.12), scale=(1.02, 0.97, 1.01)),
        mag=SensorCalibration.from_params(bias=(0.11, -0.19, 0.23), scale=1 / (0.48 * np.array([1.08, 0.91, 1.03]))),
        source="truth",
    )


def export_to_file(cal: Calibration, fmt: str, tmp_path: Path, mag_unit: str = "gauss"):
    exp = export_calibration(cal, fmt, mag_unit)
    path = tmp_path / ("cal.parm" if fmt == "ardupilot" else "cal.params")
    write_parm(exp.params, path, fmt, header_lines(exp, "cal.json"), exp.types)
    return exp, read_back(path, fmt)


def angle(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.arctan2(np.linalg.norm(np.cross(u, v), axis=1), np.einsum("ij,ij->i", u, v))


# -- tests --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("fmt", ["ardupilot", "px4"])
def test_expressible_calibration_is_reproduced_exactly(fmt: str, tmp_path: Path) -> None:
    cal = expressible_truth()
    exp, P = export_to_file(cal, fmt, tmp_path)
    assert P == pytest.approx(exp.params, rel=1e-6, abs=1e-9)
    gyro, acc, mag = raw_samples(cal)
    fg, fa, fm = firmware(P, fmt, gyro, acc, mag)
    # The firmware's field is in mG / gauss with the raw field's mean radius |det M|^(-1/3).
    r = abs(np.linalg.det(cal.mag.matrix)) ** (-1 / 3) * (1e3 if fmt == "ardupilot" else 1.0)
    assert exp.dropped["mag"].field_scale == pytest.approx(r, rel=1e-12)
    for name, fw, c, scale in (("gyro", fg, cal.gyro.apply(gyro), 1.0), ("accel", fa, cal.accel.apply(acc), 1.0),
                               ("mag", fm, cal.mag.apply(mag), r)):
        err = np.linalg.norm(fw / scale - c, axis=1) / np.linalg.norm(c, axis=1).max()
        assert err.max() < F32_REL, (name, err.max())
        assert exp.dropped[name].exact and exp.dropped[name].max_angle_deg < 1e-6
    assert not any("dropped" in w for w in exp.warnings)


@pytest.mark.parametrize("fmt", ["ardupilot", "px4"])
def test_dropped_part_is_exactly_the_reported_one(fmt: str, tmp_path: Path) -> None:
    cal = paper_truth(np.random.default_rng(11))  # misalignment ~1°, non-orthogonality ~0.5–1°
    exp, P = export_to_file(cal, fmt, tmp_path)
    gyro, acc, mag = raw_samples(cal)
    fg, fa, fm = firmware(P, fmt, gyro, acc, mag)
    for name, fw, c in (("gyro", fg, cal.gyro.apply(gyro)), ("accel", fa, cal.accel.apply(acc)),
                        ("mag", fm, cal.mag.apply(mag))):
        d = exp.dropped[name]
        fw = fw / d.field_scale
        # What the firmware computes is onlinecal's output times the documented dropped part E.
        assert np.abs(fw - c @ d.E.T).max() / np.abs(c).max() < F32_REL, name
        ang = np.degrees(angle(fw, c))
        # The reported worst-case angle bounds every sample and is reached by the sphere of directions.
        assert ang.max() <= d.max_angle_deg * (1 + 1e-4) + 1e-6, name
        assert ang.max() >= 0.98 * d.max_angle_deg, name
        rel = np.linalg.norm(fw - c, axis=1) / np.linalg.norm(c, axis=1)
        assert rel.max() <= d.max_rel_error * (1 + 1e-4) + 1e-6, name
        assert d.max_angle_deg > 0.3  # ~1° terms: something real was dropped and it is said so
        assert any(w.startswith(f"{name}: dropped") for w in exp.warnings)
    # The magnetometer's dropped part is a pure rotation: field norm kept, heading turned by its angle.
    dm = exp.dropped["mag"]
    assert np.allclose(dm.E @ dm.E.T, np.eye(3), atol=1e-12) and np.linalg.det(dm.E) > 0
    assert dm.max_norm_rel_error < 1e-9
    assert dm.max_angle_deg == pytest.approx(dm.rotation_deg, rel=1e-6)
    c = cal.mag.apply(mag)
    assert np.allclose(np.linalg.norm(fm, axis=1) / dm.field_scale, np.linalg.norm(c, axis=1), rtol=F32_REL)


def test_accel_scale_is_least_squares_over_directions() -> None:
    """The per-axis scale minimises the mean squared error over all force directions (module docstring)."""
    cal = paper_truth(np.random.default_rng(5))
    s = np.array([vehicle_params(cal, "ardupilot")[f"INS_ACCSCAL_{a}"] for a in "XYZ"])
    K = np.linalg.inv(cal.accel.matrix)
    u = fib(4000)

    def mse(sc: np.ndarray) -> float:
        return float(np.mean(np.sum((u @ K.T * sc - u) ** 2, axis=1)))

    base = mse(s)
    for k in range(3):
        for h in (-1e-3, 1e-3):
            ds = np.zeros(3)
            ds[k] = h
            assert mse(s + ds) > base


@pytest.mark.parametrize("fmt", ["ardupilot", "px4"])
@pytest.mark.parametrize("orient, alpha", [(2, (0, 0, math.pi / 2)), (16, (math.pi / 2, 0, 0))])
def test_mounting_at_90_degrees_maps_to_orientation(fmt: str, orient: int, alpha, tmp_path: Path) -> None:
    base = expressible_truth()
    # M = S·T_R with T_R a 90° rotation: S·R is R-conjugate symmetric for both firmwares' orders.
    cal = base.replace(mag=SensorCalibration.from_params(base.mag.bias, base.mag.scale, alpha))
    exp, P = export_to_file(cal, fmt, tmp_path)
    key = "COMPASS_ORIENT" if fmt == "ardupilot" else "CAL_MAG0_ROT"
    assert P[key] == orient
    _, _, mag = raw_samples(cal)
    _, _, fm = firmware(P, fmt, np.zeros((1, 3)), np.zeros((1, 3)), mag)
    c = cal.mag.apply(mag)
    assert np.abs(fm / exp.dropped["mag"].field_scale - c).max() < F32_REL
    assert any(key in w for w in exp.warnings)


def test_mag_unit_sets_offset_scale(tmp_path: Path) -> None:
    cal = expressible_truth()
    mg = Calibration(mag=SensorCalibration(cal.mag.bias * 1e3, cal.mag.matrix * 1e-3))  # same sensor, raw in mG
    a = vehicle_params(cal, "ardupilot")
    b = vehicle_params(mg, "ardupilot", mag_unit="mgauss")
    for k in ("COMPASS_OFS_X", "COMPASS_OFS_Y", "COMPASS_OFS_Z", "COMPASS_DIA_X", "COMPASS_ODI_Y"):
        assert b[k] == pytest.approx(a[k], rel=1e-9, abs=1e-12)
    assert a["COMPASS_OFS_X"] == pytest.approx(-cal.mag.bias[0] * 1e3)


@pytest.mark.parametrize("fmt", ["ardupilot", "px4"])
def test_cli_writes_files_in_the_tools_formats(fmt: str, tmp_path: Path, capsys) -> None:
    cal = paper_truth(np.random.default_rng(2))
    src = tmp_path / "cal.json"
    cal.save(src)
    out = tmp_path / ("v.parm" if fmt == "ardupilot" else "v.params")
    assert main(["export", str(src), "--format", fmt, "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "warning: mag: dropped" in err
    lines = out.read_text().splitlines()
    body = [ln for ln in lines if ln and not ln.startswith("#")]
    expected = vehicle_params(cal, fmt)
    if fmt == "ardupilot":
        # MAVProxy's format: NAME <whitespace> VALUE, comments with '#'.
        assert all(re.fullmatch(r"[A-Z0-9_]{1,16}\s+-?\d+(\.\d+)?(e[-+]\d+)?", ln) for ln in body), body
        P = MAVParmDict()
        assert P.load(str(out))
    else:
        assert lines[0] == "# Onboard parameters for Vehicle 1"
        assert "# Vehicle-Id Component-Id Name Value Type" in lines
        assert all(re.fullmatch(r"1\t1\t[A-Z0-9_]{1,16}\t\S+\t(6|9)", ln) for ln in body), body
        P = read_qgc_params(out)
    assert list(P) == list(expected) if fmt == "px4" else set(P) == set(expected)
    assert P == pytest.approx(expected, rel=1e-6, abs=1e-9)
    side = json.loads(Path(str(out) + ".export.json").read_text())
    assert side["schema"] == "onlinecal.export/1" and side["format"] == fmt
    assert side["dropped"]["mag"]["max_angle_deg"] > 0


def test_cli_default_output_beside_the_calibration(tmp_path: Path) -> None:
    src = tmp_path / "unit7.json"
    expressible_truth().save(src)
    assert main(["export", str(src), "--format", "px4"]) == 0
    assert (tmp_path / "unit7.params").exists() and (tmp_path / "unit7.params.export.json").exists()


@pytest.mark.parametrize("content, why", [
    ("{not json", "not a calibration JSON"),
    ('{"schema": "other/1"}', "not a calibration JSON"),
    (None, "no such file"),
])
def test_cli_bad_calibration_exits_2_with_one_line(content, why, tmp_path: Path, capsys) -> None:
    src = tmp_path / "bad.json"
    if content is not None:
        src.write_text(content)
    out = tmp_path / "x.parm"
    assert main(["export", str(src), "--format", "ardupilot", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.json" in err[0] and why in err[0] and "Traceback" not in err[0]
    assert not out.exists()


def test_cli_inverted_mag_axis_is_refused(tmp_path: Path, capsys) -> None:
    cal = expressible_truth()
    flipped = cal.replace(mag=SensorCalibration(cal.mag.bias, np.diag([1.0, 1.0, -1.0]) @ cal.mag.matrix))
    src = tmp_path / "flip.json"
    flipped.save(src)
    assert main(["export", str(src), "--format", "px4", "--out", str(tmp_path / "x.params")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "flip.json" in err[0] and "inverted axis" in err[0]
