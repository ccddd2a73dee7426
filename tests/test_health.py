"""Health verdict, validated calibration files, guarded export with onboard composition, strict JSON, the
atomic writer (issue 12 items 1, 2, 5; issue 14 item 7). Expected values come from the construction of
each case (physics, a firmware formula written out here), never from the code under test."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest

from onlinecal.calfile import CalFileError, load_calibration, load_onboard_params
from onlinecal.export import export_calibration
from onlinecal.files import OutputError, atomic_write, check_output_dir, check_output_file, dumps, sanitize
from onlinecal.health import assess, exit_status, mag_coverage
from onlinecal.model import Calibration, SensorCalibration

S = SensorCalibration.from_params
SIG = {"bias": [1e-4] * 3, "scale": [1e-4] * 3, "alpha": [1e-4] * 3, "xi": [1e-4] * 3}


def good(**over: SensorCalibration) -> Calibration:
    """A plausible unit: gyro scale 1.14 (the simulator's), accel within 2 %, mag in gauss (field 0.48 G)."""
    kw = {"gyro": S(bias=(0.003, 0.16, 0.06), scale=(1.14, 1.14, 1.15), sigma=SIG),
          "accel": S(bias=(0.28, -0.37, 0.18), scale=(0.98, 1.02, 1.0), sigma=SIG),
          "mag": S(bias=(0.24, 0.09, 0.07), scale=(1.9, 2.3, 1.96), sigma=SIG)}
    kw.update(over)
    return Calibration(**kw, source="online")


def online_meta(nis_mean: dict[str, float], events: list | None = None) -> dict:
    return {"online": {"nis": {"band": [2.26, 3.87], **{s: {"mean": m, "windows": 30, "updates": 3000}
                                                          for s, m in nis_mean.items()}},
                       "events": events or []}}


# -- 1. the verdict ----------------------------------------------------------------------------------

def test_plausible_consistent_result_is_ok() -> None:
    h = assess(good().replace(meta=online_meta({"accel": 2.1, "mag": 2.9})))
    assert h["verdict"] == "ok" and h["reasons"] == [] and exit_status(h) == 0
    json.loads(dumps(h))  # plain JSON


def test_issue_row_mag_nis_60589_fails() -> None:
    """replay tilt-sphere.csv: magnetometer NIS mean 60 589 (3 expected) and no warning → failed, even from
    the single NIS window that run produced (and its gate rejecting 115 of 238 updates)."""
    h = assess(good().replace(meta=online_meta({"accel": 3.1, "mag": 60589.0})))
    assert h["verdict"] == "failed" and exit_status(h) == 5
    assert any(r.startswith("mag: mean NIS 6.059e+04") for r in h["reasons"]), h["reasons"]
    one = {"online": {"nis": {"mag": {"mean": 60589.0, "windows": 1, "updates": 123, "rejected": 115}}}}
    h1 = assess(good().replace(meta=one))
    assert h1["verdict"] == "failed" and len(h1["reasons"]) == 2, h1["reasons"]
    assert "rejected 115 of 238 updates (48 %)" in h1["reasons"][0]


@pytest.mark.parametrize("rej, verdict", [(0, "ok"), (3, "ok"), (40, "degraded"), (250, "failed")])
def test_gate_rejections(rej: int, verdict: str) -> None:
    meta = {"online": {"nis": {"accel": {"mean": 3.0, "windows": 30, "updates": 300, "rejected": rej}}}}
    assert assess(good().replace(meta=meta))["verdict"] == verdict


@pytest.mark.parametrize("m, verdict", [(1.6, "ok"), (5.9, "ok"), (7.0, "degraded"), (1.2, "degraded"),
                                        (29.0, "degraded"), (31.0, "failed")])
def test_nis_band(m: float, verdict: str) -> None:
    assert assess(good().replace(meta=online_meta({"accel": m})))["verdict"] == verdict


def test_issue_row_flight_wreck_fails_with_each_reason() -> None:
    """batch flight.tlog: mag bias (−27.4, 15.6, 56.5) on a 0.48 G field, mag scale z 1e-6, ξx = π/2."""
    wreck = S(bias=(-27.4, 15.6, 56.5), scale=(2.0, 2.1, 1e-6), xi=(1.5708, 0.0, 0.0))
    h = assess(good(mag=wreck))
    assert h["verdict"] == "failed"
    text = " | ".join(h["reasons"])
    assert "axis scales" in text and "hard-iron bias" in text and "ξ x +1.57" in text, text


@pytest.mark.parametrize("sensor, kw, words", [
    ("gyro", {"scale": (0.3, 1.0, 1.0)}, "scale x 0.3"),
    ("gyro", {"scale": (1.0, 1.0, 2.5)}, "scale z 2.5"),
    ("gyro", {"bias": (2.0, 0.0, 0.0)}, "bias 2 rad/s"),
    ("accel", {"bias": (0.0, 5.0, 0.0)}, "bias 5 m/s²"),
])
def test_physical_ranges(sensor: str, kw: dict, words: str) -> None:
    h = assess(good(**{sensor: S(**kw)}))
    assert h["verdict"] == "failed" and any(words in r for r in h["reasons"]), h["reasons"]


def test_divergence_and_saturation_are_visible() -> None:
    ev = [{"t": 12.0, "kind": "divergence", "detail": "accel NIS window mean 99 far above its band"},
          {"t": 40.0, "kind": "saturation", "detail": "gyro at its rail ±[4.366]: its update skipped"}]
    h = assess(good().replace(meta=online_meta({"accel": 3.0}, ev)))
    assert h["verdict"] == "degraded" and h["checks"]["divergences"] == 1 and h["checks"]["saturation"] == 1
    assert any("diverged 1 time" in r and "t = 12.0 s" in r for r in h["reasons"])
    assert any("gyro" in r and "rail" in r for r in h["reasons"])


def test_rail_in_the_raw_data() -> None:
    """A gyro reading pinned at ±4.366 rad/s for many samples is saturation; a peak reached once is not."""
    rng = np.random.default_rng(2)
    g = rng.normal(0, 1.0, size=(5000, 3))
    assert assess(good(), raw={"gyro": g})["verdict"] == "ok"
    g[100:300, 1] = 4.366
    h = assess(good(), raw={"gyro": g})
    assert h["verdict"] == "degraded" and h["checks"]["rail_samples"] == {"gyro": 200}
    assert "y ±4.366" in h["reasons"][0]


MARG = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "marg-set1"


@pytest.mark.skipif(not (MARG / "tilt-sphere.csv").is_file(), reason="measured data ../shared/data absent")
def test_issue_row_real_tilt_sphere_gyro_rail() -> None:
    """The measured tilt-sphere session: `diagnose` found 187 gyro samples at the ±4.366 rad/s rail."""
    from onlinecal.io import read_log

    d = read_log(MARG / "tilt-sphere.csv")
    h = assess(good(), raw={"gyro": d.gyro, "accel": d.acc})
    assert h["checks"]["rail_samples"].get("gyro", 0) >= 187, h["checks"]
    assert any("4.366" in r for r in h["reasons"])


def test_undetermined_terms_are_named_not_degrading() -> None:
    obs = {"gyro.scale.x": {"ratio": 0.9}, "gyro.scale.y": {"ratio": 0.01}, "dip": {"ratio": 0.9}}
    h = assess(good(), observability=obs)
    assert h["verdict"] == "ok" and h["checks"]["undetermined"] == ["gyro.scale.x"]
    assert "gyro.scale.x" in h["notes"][0]


def test_mag_coverage_on_constructed_directions() -> None:
    rng = np.random.default_rng(1)
    sphere = rng.normal(size=(5000, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    assert mag_coverage(sphere) == 1.0
    cap = sphere[sphere[:, 2] > 0.8]  # a cap of 10 % of the sphere's area
    assert mag_coverage(cap) < 0.25
    cal = good()
    raw_cap = cal.mag.inv().apply(cap / np.linalg.norm(cap, axis=1, keepdims=True))
    h = assess(cal, mag_raw=raw_cap)
    assert h["verdict"] == "degraded" and any("directions" in r for r in h["reasons"])


# -- 5. calibration files validated on load ------------------------------------------------------------

def _write(tmp_path: Path, text: str, name: str = "cal.json") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


VALID = good().to_dict()


def _with(path: str, value: object) -> str:
    d = json.loads(json.dumps(VALID))
    cur = d
    keys = path.split(".")
    for k in keys[:-1]:
        cur = cur[k]
    cur[keys[-1]] = value
    return json.dumps(d)


@pytest.mark.parametrize("text, words", [
    ("[1, 2, 3]", "expected a JSON object"),
    ('"calibration"', "expected a JSON object"),
    ("null", "expected a JSON object"),
    ('{"schema": "onlinecal.calibration/1", "gyro": {"bias": {"a": [1]}, "matrix": [[1]]}}', "gyro.bias"),
    ('{"schema": "onlinecal.calibration/1", "schema": "x"}', "duplicate key 'schema'"),
    (_with("gyro.matrix", [[0, 0, 0], [0, 0, 0], [0, 0, 0]]), "gyro.matrix: singular"),
    (_with("accel.matrix", [[1, 2, 3], [2, 4, 6], [0, 0, 1]]), "accel.matrix"),
    (_with("mag.sigma.bias", [1, 2]), "mag.sigma.bias: expected 3 numbers"),
    (_with("mag.sigma.scale", [-1, 2, 3]), "mag.sigma.scale: negative"),
    (_with("gyro.bias", [1e308, 0, 0]), "gyro.bias"),
    (_with("gyro", "junk"), "gyro: expected an object"),
    (_with("extensions", [1]), "extensions"),
    ('{"schema": "onlinecal.calibration/1", "gyro": {"bias": [NaN, 0, 0]}}', "not a calibration JSON"),
    ('{"schema": "onlinecal.calibration/1"}', "holds no sensor"),
])
def test_damaged_calibration_names_file_and_field(tmp_path: Path, text: str, words: str) -> None:
    p = _write(tmp_path, text)
    with pytest.raises(CalFileError) as e:
        load_calibration(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}: ") and words in msg and "\n" not in msg, msg


def test_directory_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(CalFileError, match="is a directory"):
        load_calibration(tmp_path)
    with pytest.raises(CalFileError, match="no such file"):
        load_calibration(tmp_path / "none.json")


def test_truth_file_reads_as_its_calibration(tmp_path: Path) -> None:
    truth = {"schema": "onlinecal.truth/1", "profile": "paper", "calibration": VALID}
    cal = load_calibration(_write(tmp_path, json.dumps(truth)))
    assert np.array_equal(cal.gyro.matrix, good().gyro.matrix)


def test_health_travels_with_the_file(tmp_path: Path) -> None:
    d = dict(VALID, health={"verdict": "degraded", "reasons": ["mag: x"]})
    assert load_calibration(_write(tmp_path, json.dumps(d))).health["verdict"] == "degraded"


# -- 2. guarded export and composition -------------------------------------------------------------------

def test_issue_row_static_log_accel_offset_sigma_0_37_is_withheld() -> None:
    """After a 5-second static log: INS_ACCOFFS_Z 0.127 with σ 0.37 was written."""
    sig = dict(SIG, bias=[0.001, 0.001, 0.37])
    cal = good(accel=S(bias=(0.01, 0.02, 0.12717734), sigma=sig))
    exp = export_calibration(cal, "ardupilot")
    assert "INS_ACCOFFS_Z" not in exp.params and "σ 0.37" in exp.withheld["INS_ACCOFFS_Z"]
    assert "INS_ACCOFFS_X" in exp.params and "INS_ACCOFFS_Y" in exp.params
    forced = export_calibration(cal, "ardupilot", force=True)
    assert forced.params["INS_ACCOFFS_Z"] == pytest.approx(0.12717734)


def test_issue_row_flight_wreck_mag_is_not_written() -> None:
    """COMPASS_OFS_X 27405.488 with only a COMPASS_OFFS_MAX remark: the mag block is withheld."""
    cal = good(mag=S(bias=(-27.4, 15.6, 56.5), scale=(2.0, 2.1, 1.9), sigma=SIG))
    exp = export_calibration(cal, "ardupilot")
    assert not any(n.startswith("COMPASS_") for n in exp.params)
    assert exp.withheld["COMPASS_OFS_X"].startswith("health: mag: hard-iron bias")
    assert "INS_GYROFFS_X" in exp.params  # the other sensors are still written


def test_undetermined_term_from_stored_health_is_withheld() -> None:
    cal = good()
    exp = export_calibration(cal, "px4", health={"verdict": "ok", "reasons": [],
                                                "checks": {"undetermined": ["accel.scale.y"]}})
    assert "CAL_ACC0_YSCALE" in exp.withheld and "CAL_ACC0_XSCALE" in exp.params


@pytest.mark.parametrize("fmt", ["ardupilot", "px4"])
def test_onboard_composition_equals_exporting_the_raw_truth(fmt: str) -> None:
    """Data logged after the firmware's own correction F (raw − f) and calibrated by c = M' (corrected − b'):
    exporting M', b' with the onboard parameters must give the parameters of the raw sensor's calibration."""
    truth = good(gyro=S(bias=(0.01, -0.02, 0.03), sigma=SIG),
                 accel=S(bias=(0.2, -0.3, 0.1), scale=(1.02, 0.97, 1.01), sigma=SIG),
                 mag=S(bias=(0.11, -0.19, 0.23), scale=(2.0, 2.2, 1.9), sigma=SIG))
    if fmt == "ardupilot":  # corrected = (raw − OFFS)·SCAL; gyro raw − GYROFFS; mG: W (raw·1000 + OFS)
        onboard = {"INS_ACCOFFS_X": 0.05, "INS_ACCOFFS_Y": -0.1, "INS_ACCOFFS_Z": 0.02, "INS_ACCSCAL_X": 1.01,
                   "INS_ACCSCAL_Y": 0.99, "INS_ACCSCAL_Z": 1.0, "INS_GYROFFS_X": 0.004, "INS_GYROFFS_Y": 0.0,
                   "INS_GYROFFS_Z": -0.003, "COMPASS_OFS_X": -50.0, "COMPASS_OFS_Y": 20.0, "COMPASS_OFS_Z": 10.0,
                   "COMPASS_DIA_X": 1.05, "COMPASS_DIA_Y": 0.95, "COMPASS_DIA_Z": 1.0, "COMPASS_ODI_X": 0.01,
                   "COMPASS_ODI_Y": 0.0, "COMPASS_ODI_Z": -0.02}
        fa, Fa = np.array([0.05, -0.1, 0.02]), np.diag([1.01, 0.99, 1.0])
        fg = np.array([0.004, 0.0, -0.003])
        fm = -np.array([-50.0, 20.0, 10.0]) / 1000.0
    else:  # corrected = (data − OFF)·SCALE; gyro data − OFF; mag W (data − OFF)
        onboard = {"CAL_ACC0_XOFF": 0.05, "CAL_ACC0_YOFF": -0.1, "CAL_ACC0_ZOFF": 0.02, "CAL_ACC0_XSCALE": 1.01,
                   "CAL_ACC0_YSCALE": 0.99, "CAL_ACC0_ZSCALE": 1.0, "CAL_GYRO0_XOFF": 0.004,
                   "CAL_GYRO0_YOFF": 0.0, "CAL_GYRO0_ZOFF": -0.003, "CAL_MAG0_XOFF": -0.05, "CAL_MAG0_YOFF": 0.02,
                   "CAL_MAG0_ZOFF": 0.01, "CAL_MAG0_XSCALE": 1.05, "CAL_MAG0_YSCALE": 0.95, "CAL_MAG0_ZSCALE": 1.0,
                   "CAL_MAG0_XODIAG": 0.01, "CAL_MAG0_YODIAG": 0.0, "CAL_MAG0_ZODIAG": -0.02}
        fa, Fa = np.array([0.05, -0.1, 0.02]), np.diag([1.01, 0.99, 1.0])
        fg = np.array([0.004, 0.0, -0.003])
        fm = np.array([-0.05, 0.02, 0.01])
    Wm = np.array([[1.05, 0.01, 0.0], [0.01, 0.95, -0.02], [0.0, -0.02, 1.0]])

    def fitted_on_corrected(c: SensorCalibration, f: np.ndarray, F: np.ndarray) -> SensorCalibration:
        # M (raw − b) = M' (F (raw − f) − b')  ⇒  M' = M F⁻¹, b' = F (b − f)
        return SensorCalibration(F @ (c.bias - f), c.matrix @ np.linalg.inv(F), c.sigma)

    seen = Calibration(gyro=fitted_on_corrected(truth.gyro, fg, np.eye(3)),
                       accel=fitted_on_corrected(truth.accel, fa, Fa),
                       mag=fitted_on_corrected(truth.mag, fm, Wm), source="batch")
    want = export_calibration(truth, fmt).params
    got = export_calibration(seen, fmt, onboard=onboard)
    assert got.composed and set(got.params) == set(want)
    for n, v in want.items():
        assert got.params[n] == pytest.approx(v, rel=1e-9, abs=1e-9), n
    naive = export_calibration(seen, fmt).params  # without --onboard the correction would be applied twice
    assert max(abs(naive[n] - want[n]) for n in want) > 1e-3


def test_onboard_params_file_formats(tmp_path: Path) -> None:
    ap = _write(tmp_path, "# comment\nINS_ACCOFFS_X 0.5\nCOMPASS_OFS_Y,-12\n", "v.parm")
    assert load_onboard_params(ap) == {"INS_ACCOFFS_X": 0.5, "COMPASS_OFS_Y": -12.0}
    qgc = _write(tmp_path, "# Onboard parameters\n1\t1\tCAL_ACC0_XOFF\t0.25\t9\n", "v.params")
    assert load_onboard_params(qgc) == {"CAL_ACC0_XOFF": 0.25}
    bad = _write(tmp_path, "INS_ACCOFFS_X nan\n", "b.parm")
    with pytest.raises(CalFileError, match="line 1"):
        load_onboard_params(bad)


def test_export_never_writes_inf_or_nan() -> None:
    cal = good(accel=S(bias=(1e35, 0, 0)))
    with pytest.raises(ValueError, match="INS_ACCOFFS_X would be"):
        export_calibration(cal, "ardupilot", force=True)


# -- 14.7: one sanitiser, one atomic writer ------------------------------------------------------------

def test_sanitiser_gives_strict_json() -> None:
    obj = {"a": float("nan"), "b": [np.float32(1.5), np.inf], "c": np.array([[1, 2]]), 3: (np.int64(4),)}
    text = dumps(obj)
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"a": None, "b": [1.5, None], "c": [[1, 2]], "3": [4]}
    assert sanitize(-math.inf) is None


def test_atomic_writer_replaces_whole_and_leaves_nothing_on_failure(tmp_path: Path) -> None:
    p = tmp_path / "out.json"
    p.write_text("old")
    atomic_write(p, "new")
    assert p.read_text() == "new" and sorted(os.listdir(tmp_path)) == ["out.json"]
    with pytest.raises(OutputError, match="nonexistent"):
        atomic_write(tmp_path / "nonexistent" / "x.json", "x")
    assert sorted(os.listdir(tmp_path)) == ["out.json"]


def test_output_checks(tmp_path: Path) -> None:
    check_output_file(tmp_path / "new.json")
    check_output_file("-")
    for bad, words in [("/nonexistent/x.json", "does not exist"), (str(tmp_path), "is a directory")]:
        with pytest.raises(OutputError, match=words):
            check_output_file(bad, "--json")
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(OutputError, match="not a directory"):
        check_output_dir(f, "--out")
    with pytest.raises(OutputError, match="not writable"):
        check_output_dir("/proc/x", "--report")
    check_output_dir(tmp_path / "a" / "b")


def test_unknown_sigma_round_trips_as_null(tmp_path: Path) -> None:
    """A σ the filter could not give (NaN) is written as null (strict JSON) and read back as unknown."""
    cal = good(gyro=S(bias=(0.01, 0, 0), sigma={"bias": [1e-4, float("nan"), 1e-4]}))
    p = tmp_path / "c.json"
    cal.save(p)
    assert "NaN" not in p.read_text() and json.loads(p.read_text())["gyro"]["sigma"]["bias"][1] is None
    back = load_calibration(p)
    assert np.isnan(back.gyro.sigma["bias"][1]) and back.gyro.sigma["bias"][0] == 1e-4
