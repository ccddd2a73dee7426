"""Issue 11, the gyro on hand-held sessions: closure, bias per recording, clipping, clock, Ferraris turns.

Truth for the closure figures is the project's out-of-fit check, ``../shared/tools/gyro_closure.py``, run as
a subprocess on the batch's calibration JSON (or on a copy of a log): its physics, not ours. Where the
issue's bar (median ≤ 3°, max ≤ 8° over the 12 moving files) is not met, the tests assert the evidence
(docs/results.md, "Issue 11, the gyro").
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from onlinecal.batch import gyro as gy
from onlinecal.batch.segment import Segmentation
from onlinecal.io import ImuData, read_log


# -- fast: the clipping tools on a synthetic turn with a known excess ------------------------------------------
def _turn_with_peak(peak: float, rail: float = 4.3657, rate: float = 100.0) -> tuple[ImuData, float]:
    """A turn about body z whose rate is a smooth bump of height ``peak`` rad/s, clipped at ``rail``; a
    world-fixed field seen by a 75 Hz magnetometer. Returns (data, rotation lost to clipping in deg)."""
    t = np.arange(0.0, 4.0, 1 / rate)
    wz = peak * np.exp(-0.5 * ((t - 2.0) / 0.12) ** 2)
    ang = np.concatenate([[0.0], np.cumsum(0.5 * (wz[1:] + wz[:-1]) * np.diff(t))])
    gyro = np.zeros((t.size, 3))
    gyro[:, 2] = np.clip(wz, -rail, rail)
    lost = float(np.degrees(np.sum(0.5 * ((wz - gyro[:, 2])[1:] + (wz - gyro[:, 2])[:-1]) * np.diff(t))))
    tm = np.arange(0.0, 4.0, 1 / 75.0)
    am = np.interp(tm, t, ang)
    h = np.array([0.45, 0.0, -0.3])  # world field: horizontal part along x, dip down
    # body sees the world vector turned by −angle about z
    mag = np.column_stack([h[0] * np.cos(am), -h[0] * np.sin(am), np.full(tm.size, h[2])])
    acc = np.tile([0.0, 0.0, 9.80665], (t.size, 1))
    return ImuData(t, gyro, acc, np.full(t.size, 25.0), tm, mag, "synthetic.csv"), lost


def _seg(d: ImuData) -> Segmentation:
    return Segmentation(d, [], [], [], 0.0, 0.0, np.zeros(3), 0.0)


def test_clipped_turn_is_found_and_its_lost_rotation_restored_from_the_field():
    d, lost = _turn_with_peak(7.0)
    rails = gy.gyro_rails([_seg(d)])
    assert np.isfinite(rails[2]) and abs(rails[2] - 4.3657) < 1e-3 and np.isnan(rails[:2]).all()
    mask, runs = gy.clipped_stretches(d, rails)
    assert len(runs) == 1 and runs[0].axes == "z" and mask.sum() == runs[0].i1 - runs[0].i0 >= 10
    from onlinecal.model import SensorCalibration

    mag = SensorCalibration(np.zeros(3), np.eye(3))
    wb = gy.bridge_clipped(d, np.eye(3), np.zeros(3), mag, rails, runs)
    assert lost > 15.0  # the clipping loses a real rotation here
    assert runs[0].lost_deg is not None and abs(runs[0].lost_deg - lost) <= 0.15 * lost
    # the bridged rates integrate to the true turn within the bridge's own shape error
    true_turn = np.degrees(np.sum(0.5 * (wb[1:, 2] + wb[:-1, 2]) * np.diff(d.t_imu)))
    clipped_turn = np.degrees(np.sum(0.5 * (d.gyro[1:, 2] + d.gyro[:-1, 2]) * np.diff(d.t_imu)))
    assert abs(true_turn - (clipped_turn + lost)) <= 0.15 * lost


def test_a_peak_reached_once_is_not_a_rail():
    d, _ = _turn_with_peak(3.0)  # below the rail: the largest value occurs once
    assert np.isnan(gy.gyro_rails([_seg(d)])).all()


# -- slow: the MARG set and the Ferraris session -------------------------------------------------------------
def _tool(data_dir: Path) -> Path:
    p = data_dir.parent / "tools" / "gyro_closure.py"
    if not p.is_file():
        pytest.skip(f"gyro_closure.py not present at {p}")
    return p


def _closure(data_dir: Path, cal: dict, logs: list[Path], tmp_path: Path) -> dict[str, float]:
    """The external check as a subprocess: file name → closure error (deg)."""
    cj = tmp_path / f"cal-{len(list(tmp_path.iterdir()))}.json"
    cj.write_text(json.dumps(cal))
    out = subprocess.run([sys.executable, str(_tool(data_dir)), str(cj), *map(str, logs)], capture_output=True,
                         text=True, check=True).stdout
    res = {}
    for line in out.splitlines():
        m = re.match(r"(.*): turned .* deg, closure error ([0-9.]+) deg", line)
        assert m, line
        res[Path(m.group(1)).name] = float(m.group(2))
    assert len(res) == len(logs)
    return res


def _write_csv(path: Path, d: ImuData, t_imu: np.ndarray, gyro: np.ndarray, t_mag: np.ndarray) -> None:
    """``d`` as the flat CSV schema (../shared/data/README.md) with the given IMU times, gyro and mag times."""
    n, m = t_imu.size, t_mag.size
    rows = np.full((n + m, 11), np.nan)
    rows[:n, 0], rows[:n, 1:4], rows[:n, 4:7], rows[:n, 10] = t_imu, gyro, d.acc, d.temp
    rows[n:, 0], rows[n:, 7:10] = t_mag, d.mag
    rows = rows[np.argsort(rows[:, 0], kind="stable")]
    body = "\n".join(",".join("" if np.isnan(x) else repr(float(x)) for x in r) for r in rows)
    path.write_text("time_s,gyro_x,gyro_y,gyro_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z,temp_c\n" + body + "\n")


@pytest.fixture(scope="module")
def marg_batch(data_dir):
    from onlinecal.batch import run_batch

    files = sorted((data_dir / "marg-set1").glob("*.csv"))
    assert len(files) == 15
    logs = {f.name: read_log(f) for f in files}
    return files, logs, run_batch(list(logs.values()))


def _cal(res) -> dict:
    return json.loads(json.dumps(res.calibration.to_dict()))


@pytest.mark.slow
def test_unmoved_files_close_with_the_rests_bias_and_with_their_own(marg_batch, data_dir, tmp_path):
    """At rest the gyro integrates only its bias error: 63–70 s at 2.4 mrad/s (the joint fit's bias) closed
    at 8.7–9.7°. With the rests' bias (eqs. 34–35) the pooled calibration closes them within 3.5°, and with
    each file's own rest bias (samples ≥ 1 s from the check's end windows) within 1°."""
    files, _, res = marg_batch
    cal = _cal(res)
    un = [f for f in files if f.name in ("unmoved-x-pointing-forward.csv", "unmoved-x-pointing-up.csv")]
    pooled = _closure(data_dir, cal, un, tmp_path)
    assert max(pooled.values()) <= 3.5, pooled
    per = {Path(k).name: c for k, c in gy.per_file_calibrations(res.calibration).items()}
    assert sorted(per) == ["unmoved-x-pointing-forward.csv", "unmoved-x-pointing-up.csv",
                           "unmoved-z-pointing-left.csv"]
    for f in un:
        p = tmp_path / f"own-{f.name}.json"
        per[f.name].save(p)  # the per-file calibration JSON the check reads
        own = _closure(data_dir, json.loads(p.read_text()), [f], tmp_path)[f.name]
        assert own <= 1.0, (f.name, own)


@pytest.mark.slow
def test_bias_per_recording_is_measured_where_a_file_rests_and_differs_between_recordings(marg_batch):
    _, _, res = marg_batch
    bpf = {Path(k).name: v for k, v in res.steps["gyro"].figures["bias_per_file"].items()}
    assert len(bpf) == 15
    rest = {k: v for k, v in bpf.items() if v["bias"] is not None}
    assert sorted(rest) == ["unmoved-x-pointing-forward.csv", "unmoved-x-pointing-up.csv",
                            "unmoved-z-pointing-left.csv"]
    assert all(v["why"] for k, v in bpf.items() if k not in rest)  # a moving file says why it has none
    b = np.array([v["bias"] for v in rest.values()])
    s = np.array([v["sigma"] for v in rest.values()])
    assert (s < 2e-4).all()
    # a real per-recording difference: the x biases differ by far more than their σ (0.6 vs 0.05 mrad/s)
    i, j = np.unravel_index(np.argmax(np.abs(b[:, None, 0] - b[None, :, 0])), (3, 3))
    assert abs(b[i, 0] - b[j, 0]) > 5 * np.hypot(s[i, 0], s[j, 0])


@pytest.mark.slow
def test_moving_files_close_better_and_the_tilts_meet_the_bar(marg_batch, data_dir, tmp_path):
    """Median over the 12 moving files 8.3° (session 4) → ≤ 6°; the issue's bar (median ≤ 3°) is not met,
    the per-file evidence is in the tests below. Where a file meets the 3° bar it is asserted."""
    files, _, res = marg_batch
    moving = [f for f in files if not f.name.startswith("unmoved")]
    c = _closure(data_dir, _cal(res), moving, tmp_path)
    assert np.median(list(c.values())) <= 6.0, c
    for n in ("tilt-around-x-pointing-up.csv", "tilt-around-y-pointing-up.csv"):
        assert c[n] <= 3.0, (n, c[n])
    assert c["tilt-around-z-pointing-up.csv"] <= 4.0


@pytest.mark.slow
def test_tilt_sphere_is_clipped_and_the_lost_rotation_explains_its_closure(marg_batch, data_dir, tmp_path):
    """tilt-sphere rails the ±250 °/s gyro; the batch names the file and the clipped times, and the rotation
    that the field kinematics put into the clipped stretches, restored in a copy of the log, more than halves
    the external check's closure error (which stays above the 8° bar as recorded)."""
    files, logs, res = marg_batch
    name = "tilt-sphere.csv"
    w = [x for x in res.warnings if x.startswith("gyro: ") and name in x and "rail" in x]
    assert len(w) == 1 and re.search(r"(\d+) samples at the gyro's rail", w[0])
    assert int(re.search(r"(\d+) samples at the gyro's rail", w[0]).group(1)) >= 100
    assert re.search(r"at \d+\.\d\d–\d+\.\d\d s", w[0])  # the clipped times
    clipped = {Path(k).name: v for k, v in res.steps["gyro"].figures["clipped"].items()}
    assert clipped[name]["lost_deg_total"] > 40.0
    seg = next(s for s in res.segmentations if Path(s.data.source).name == name)
    rails = gy.gyro_rails(res.segmentations)
    _, runs = gy.clipped_stretches(seg.data, rails)
    cal = res.calibration
    wb = gy.bridge_clipped(seg.data, cal.gyro.matrix, cal.gyro.bias, cal.mag, rails, runs)
    d = logs[name]
    assert d.n_imu == seg.data.n_imu
    p = tmp_path / name
    _write_csv(p, d, d.t_imu, wb, d.t_mag)  # the recorded stamps, the bridged rates
    src = next(f for f in files if f.name == name)
    before = _closure(data_dir, _cal(res), [src], tmp_path)[name]
    after = _closure(data_dir, _cal(res), [p], tmp_path)[name]
    assert before > 8.0  # the bar is not met as recorded ...
    assert after < 0.6 * before, (before, after)  # ... and the clipping accounts for most of the error


@pytest.mark.slow
def test_one_axis_turns_of_the_2ms_setup_close_on_the_batch_clock(marg_batch, data_dir, tmp_path):
    """The three rotate-360ccw files (median Δt ≈ 2 ms set-up) close at 11–14° on the check's clock
    (span/(N − 1) of the read stamps); re-stamped with the batch's fitted sample clock (0.7–0.9 % slower)
    the same check closes each at under 0.7× that: their closure measures the clock."""
    from onlinecal.batch.clock import regularise_clock

    files, logs, res = marg_batch
    rot = [f for f in files if f.name.startswith("rotate-360ccw")]
    before = _closure(data_dir, _cal(res), rot, tmp_path)
    paths = []
    for f in rot:
        dc, notes = regularise_clock(logs[f.name])
        assert notes  # burst-read stamps: a fitted clock
        p = tmp_path / f.name
        _write_csv(p, dc, dc.t_imu, dc.gyro, dc.t_mag)
        paths.append(p)
    after = _closure(data_dir, _cal(res), paths, tmp_path)
    for n in before:
        assert before[n] > 8.0 and after[n] < 0.7 * before[n], (n, before[n], after[n])


@pytest.mark.slow
def test_ferraris_y_turn_is_short_by_the_faces_and_x_z_are_at_360(data_dir):
    """Each turn with the row of the gyro matrix for its axis rescaled by what the 9 face-to-face
    transitions alone want (the turns left out: a scale not fitted to them). x and z land within 1° of
    360°; y at ≈ 355.7°, and a 360° y turn is more than 3σ from what the faces say."""
    from onlinecal.batch import run_batch

    d = read_log(data_dir / "ferraris" / "imucal-example-session.csv")
    sec = {k: (v["start"], v["end"]) for k, v in
           json.loads((data_dir / "ferraris" / "manual-sections.json").read_text()).items()}
    res = run_batch([d])
    c, seg = res.calibration, res.segmentations[0]
    turns = {k: next(i for i, m in enumerate(seg.motions) if m.i0 <= a and m.i1 >= b)
             for k, (a, b) in sec.items() if k.endswith("_rot")}
    skip = {(0, i) for i in turns.values()}
    for k, i in turns.items():
        ax = "xyz".index(k[0])
        m = seg.motions[i]
        w = c.gyro.apply(d.gyro[m.i0:m.i1])
        ang = float(-np.degrees(np.sum(0.5 * (w[1:, ax] + w[:-1, ax]) * np.diff(d.t_imu[m.i0:m.i1]))))
        f, sd, n = gy.axis_gain_from_transitions([seg], c.gyro.matrix, c.gyro.bias, c.accel, None, ax, skip)
        assert n == 9 and 0 < sd < 0.005
        if k == "y_rot":
            assert abs(360.0 / ang - f) > 3 * sd, (ang, f, sd)
            assert 354.0 <= ang * f <= 358.0
        else:
            assert abs(ang * f - 360.0) <= 1.0, (k, ang, f)


@pytest.mark.slow
def test_the_checks_end_windows_are_not_held_still_on_the_moving_files(marg_batch, data_dir):
    """The check's premise ("both ends must be held roughly still") measured: the accelerometer samples of
    each half-second end window, turned by the calibrated gyro into the window's middle frame, scatter by the
    noise alone on the unmoved files and by several times more on every moving file (docs/results.md, "The
    check's own ends"): hand accelerations of the size that moves the check's references by degrees."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("gyro_closure", _tool(data_dir))
    assert spec is not None and spec.loader is not None
    gc = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gc)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "docs"))
    from results_gyro import end_window_scatter

    files, _, res = marg_batch
    cal = _cal(res)
    still = [x for f in files if f.name.startswith("unmoved") for x, _ in end_window_scatter(gc, f, cal)]
    moving = {f.name: max(x for x, _ in end_window_scatter(gc, f, cal))
              for f in files if not f.name.startswith("unmoved")}
    assert len(still) == 6 and max(still) < 0.6, still  # the MPU6050's noise, ~0.04 m/s² against 9.8
    assert min(moving.values()) > 1.5 * max(still), moving
    assert np.median(list(moving.values())) > 1.5, moving
