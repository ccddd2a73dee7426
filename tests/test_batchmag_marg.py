"""Issue 11's magnetometer and accelerometer bars on MARG set 1 (../shared/data/marg-set1, all 15 files pooled
as `onlinecal batch` is used): what is met is asserted at the issue's bar; where it is not met, the cause is
asserted with its evidence (a field that changes at one sensor direction, a per-file field), never a
loosened bar. docs/results.md (docs/make_results.py) reports the same figures in full."""

from __future__ import annotations

import numpy as np
import pytest

from onlinecal.batch import run_batch
from onlinecal.batch.ellipsoid import fit_norm_lm, sphere_bin_weights
from onlinecal.batch.sensors import quasi_static_holds, within_direction_spread
from onlinecal.io import read_log
from onlinecal.sim.motion import G0

MAG_BAR = 1.0  # % std/mean of the calibrated norm per moving file (issue 11)
ACC_BAR = 0.5  # % of g, static norm of the unmoved files (issue 11)
NOISE = 0.3  # % the HMC5883L's own norm scatter at rest (the unmoved files: 0.20–0.37 %)
# the moving files whose spread the pooled batch brings within the bar (docs/results.md)
MET = ("rotate-360ccw-around-x-pointing-forward.csv", "rotate-360ccw-around-z-pointing-up.csv",
       "tilt-around-x-pointing-up.csv", "tilt-around-y-pointing-left.csv", "tilt-around-y-pointing-up.csv")
PANS = ("pan-x-pointing-forward.csv", "pan-y-pointing-left.csv", "pan-z-pointing-up.csv")


@pytest.fixture(scope="module")
def marg(data_dir):
    logs = {p.name: read_log(p) for p in sorted((data_dir / "marg-set1").glob("*.csv"))}
    assert len(logs) == 15
    return logs, run_batch(list(logs.values()))


def _spread(m: np.ndarray) -> float:
    n = np.linalg.norm(m, axis=1)
    return float(100 * n.std() / n.mean())


def test_mag_spread_within_the_bar_where_met(marg):
    logs, res = marg
    mag = res.calibration.mag
    for name in MET:
        assert _spread(mag.apply(logs[name].mag)) <= MAG_BAR, name


def test_mag_file_with_another_field_is_named_and_left_out(marg):
    """The per-file field check: `unmoved-x-pointing-up` reads a field about 32 % stronger than the others
    with the pooled calibration; the batch names it and keeps it out of the shape fit."""
    logs, res = marg
    n = np.linalg.norm(res.calibration.mag.apply(logs["unmoved-x-pointing-up.csv"].mag), axis=1)
    assert np.median(n) > 1.2
    assert any("unmoved-x-pointing-up.csv" in w and "left out of the magnetometer fit" in w
               for w in res.steps["mag"].warnings)
    assert res.steps["mag"].figures["files_excluded"] == 1


def test_pans_see_a_field_that_changes_at_one_direction(marg):
    """Why the pans miss the bar: much of their norm scatter sits at one sensor direction (3° cells), far
    above the sensor's noise — a field that changed at the sensor, which no ellipsoid removes. In
    `pan-y-pointing-left` the lowest and highest norms lie a few degrees apart and differ by over 5 %, while
    every other file that saw both directions reads them within 1 % of each other, with the same
    calibration."""
    logs, res = marg
    mag = res.calibration.mag
    for name in PANS:
        s = _spread(mag.apply(logs[name].mag))
        assert s > MAG_BAR, name  # not met (the cause below)
        within, share = within_direction_spread(mag.apply(logs[name].mag))
        assert share > 0.9 and within > 2 * NOISE, (name, within)
    m = mag.apply(logs["pan-y-pointing-left.csv"].mag)
    n = np.linalg.norm(m, axis=1)
    u = m / n[:, None]
    ends = []
    for sel in (n < np.percentile(n, 15), n > np.percentile(n, 85)):
        c = u[sel].mean(0)
        ends.append((c / np.linalg.norm(c), float(np.median(n[sel]))))
    sep = np.degrees(np.arccos(np.clip(ends[0][0] @ ends[1][0], -1, 1)))
    assert sep < 8 and ends[1][1] / ends[0][1] - 1 > 0.05, (sep, ends)
    ratios = []
    for name, d in logs.items():
        if name == "pan-y-pointing-left.csv":
            continue
        mm = mag.apply(d.mag)
        nn = np.linalg.norm(mm, axis=1)
        near = [(mm / nn[:, None]) @ c > np.cos(np.radians(5)) for c, _ in ends]
        if min(int(v.sum()) for v in near) >= 20:
            ratios.append(np.median(nn[near[1]]) / np.median(nn[near[0]]) - 1)
    assert len(ratios) >= 5 and max(abs(r) for r in ratios) < 0.01, ratios


def test_turns_and_tilts_scatter_little_at_one_direction(marg):
    """The tilts and turns: their scatter at one direction is within twice the sensor's noise (what is left
    depends on the direction, i.e. on the shape), unlike the pans'."""
    logs, res = marg
    mag = res.calibration.mag
    for name, d in logs.items():
        if name.startswith(("tilt", "rotate")):
            within, _ = within_direction_spread(mag.apply(d.mag))
            assert within < 2 * NOISE, (name, within)


def test_within_direction_spread_on_constructed_fields():
    """A constant field seen from every direction: near the noise; the same with a 10 % field step in half
    the samples (a disturbance at the same directions): the step shows."""
    rng = np.random.default_rng(0)
    u = rng.normal(size=(50000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    m = u * (1 + rng.normal(0, 0.003, (u.shape[0], 1)))
    w0, share = within_direction_spread(m)
    assert share > 0.9 and 0.2 < w0 < 0.4
    m2 = m * np.where(np.arange(u.shape[0]) % 2 == 0, 1.0, 1.1)[:, None]
    w1, _ = within_direction_spread(m2)
    assert w1 > 4.0


def test_accel_held_out_static_norm(marg):
    """The accelerometer fitted (bias + per-axis scale, eq. 32) on the moving files' quasi-static holds
    only, checked on the unmoved files' static norm, which the fit never saw: within 0.5 % of g on every
    one (raw: up to 3.8 % off). The batch's own fit of those three files is exact by construction."""
    logs, _ = marg
    moving = [d for k, d in logs.items() if not k.startswith("unmoved")]
    holds = np.concatenate([quasi_static_holds(d.acc, d.gyro, d.imu_rate) for d in moving])
    w = sphere_bin_weights(holds, per_bin=20)
    k = w > 0
    assert k.sum() > 50  # many attitudes, not three
    fit = fit_norm_lm(holds[k], G0, np.zeros(3), np.eye(3) * G0 / np.linalg.norm(holds, axis=1).mean(),
                      model="diag", weights=w[k])
    raw_off = []
    for name, d in logs.items():
        if name.startswith("unmoved"):
            a = ((d.acc - fit.o) @ fit.M.T).mean(0)
            assert abs(np.linalg.norm(a) / G0 - 1) * 100 < ACC_BAR, name
            raw_off.append(abs(np.linalg.norm(d.acc.mean(0)) / G0 - 1) * 100)
    assert max(raw_off) > 3 * ACC_BAR  # the check could fail: raw, the bar is missed
