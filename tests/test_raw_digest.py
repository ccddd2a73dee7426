"""The health verdict of a streamed replay reads every sample (session 18): `onlinecal.health.RawDigest`.

What was wrong: `onlinecal replay LOG --init CAL.json` (and `--init none`) streams its logs block by block and held
no samples for the health verdict, so its two checks on the raw data — gravity at rest and the rail — never ran
(`"gravity_at_rest": {"rest_blocks": 0}`). A bench file 0.3 m/s² off along z (σ 1e-3) replayed on a 150-s
multirotor flight was then called "degraded" only because the accelerometer's mean NIS happened to reach 6.15
against a band top of 6; the flight's 35-s ground rest says −0.30 m/s² against an allowance of 0.052 (the module
doc of onlinecal.health: 9 of 20 such runs keep their NIS in band). `onlinecal run` (live) likewise, and its
`--apply` set such parameters on the vehicle.

The truths: the definition of the checks applied to the whole arrays (the calibrated samples' block means and
σ computed directly, not through the digest's covariances), and a simulated flight with the wrong bias."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from onlinecal.health import RAIL_MIN, REST_ACC, REST_BLOCK, REST_RATE, RawDigest, gravity_checks, rail_checks
from onlinecal.model import Calibration, SensorCalibration
from onlinecal.sim import simulate
from onlinecal.specs import G0, rail_samples

ROOT = Path(__file__).resolve().parent.parent


def _chunked(w: np.ndarray, a: np.ndarray, bounds: list[int], rng: np.random.Generator) -> RawDigest:
    """A digest fed as a stream: logs split at ``bounds``, each in random chunk sizes (1 to 700 samples)."""
    d = RawDigest()
    edges = [0, *bounds, w.shape[0]]
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        d.new_log()
        i = lo
        while i < hi:
            j = min(hi, i + int(rng.integers(1, 700)))
            d.add(w[i:j], a[i:j])
            i = j
    return d


def _direct_rest_deviation(cal: Calibration, w: np.ndarray, a: np.ndarray) -> tuple[int, float]:
    """The gravity check's still blocks and median |f| − g from the calibrated samples themselves."""
    assert cal.gyro is not None and cal.accel is not None
    n = w.shape[0] // REST_BLOCK * REST_BLOCK
    wc = cal.gyro.apply(w[:n]).reshape(-1, REST_BLOCK, 3)
    fc = cal.accel.apply(a[:n]).reshape(-1, REST_BLOCK, 3)
    still = ((np.abs(wc.mean(1)) < REST_RATE).all(1) & (wc.std(1) < REST_RATE).all(1) & (fc.std(1) < REST_ACC).all(1))
    f = fc[still].mean(1)
    return int(still.sum()), float(np.median(np.linalg.norm(f, axis=1) - G0))


def test_a_streamed_digest_judges_as_the_whole_arrays_do() -> None:
    sim = simulate("multirotor", 2, duration=90.0, imu_rate=200.0)
    w, a = sim.data.gyro, sim.data.acc
    truth = sim.truth.calibration
    assert truth.accel is not None
    wrong = truth.replace(accel=SensorCalibration(truth.accel.bias + np.array([0.0, 0.0, 0.3]), truth.accel.matrix,
                                                  {"bias": [1e-3] * 3, "scale": [1e-4] * 3}))
    n_direct, dev_direct = _direct_rest_deviation(wrong, w, a)
    assert n_direct >= 100 and abs(dev_direct + 0.3) < 0.02  # the ground rest; the check's own premise
    whole = gravity_checks(wrong, {"gyro": w, "accel": a})
    # blocks aligned with the whole arrays' (a log boundary at a multiple of the block): the same blocks
    streamed = gravity_checks(wrong, _chunked(w, a, [REST_BLOCK * 700], np.random.default_rng(1)))
    for out, fig in (whole, streamed):
        assert fig["rest_blocks"] == n_direct
        assert fig["norm_minus_g"] == pytest.approx(dev_direct, abs=1e-9)
        assert out and out[0][0] == "degraded" and "at rest" in out[0][1]
    assert gravity_checks(truth.replace(accel=truth.accel.with_sigma({"bias": [1e-3] * 3, "scale": [1e-4] * 3})),
                          _chunked(w, a, [10_001], np.random.default_rng(2)))[0] == []
    # the rail: the flight's rates × 8 clipped at ±2 rad/s (a ±115 °/s range); counted alike from the arrays
    # and from the stream
    w = np.clip(w * 8.0, -2.0, 2.0)
    out_w, counts_w = rail_checks({"gyro": w, "accel": a})
    out_s, counts_s = rail_checks(_chunked(w, a, [7_777], np.random.default_rng(3)))
    _, at, rail = rail_samples(np.abs(w), RAIL_MIN["gyro"])  # the rule on the whole arrays, as before the digest
    n_at = int(at[:, rail].any(axis=1).sum())
    assert rail.any() and n_at >= 10
    assert counts_w == counts_s == {"gyro": n_at}
    assert out_w == out_s


@pytest.mark.slow
def test_a_streamed_replay_from_a_wrong_file_is_named_by_gravity_at_rest(tmp_path) -> None:
    log = tmp_path / "mr.csv"
    r = subprocess.run([sys.executable, "-m", "onlinecal", "simulate", "--out", str(log), "--profile",
                        "multirotor", "--duration", "120", "--rate", "200", "--seed", "4"],
                       capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    truth = Calibration.from_dict(json.loads(Path(str(log) + ".truth.json").read_text())["calibration"])
    assert truth.accel is not None
    wrong = truth.replace(accel=SensorCalibration(truth.accel.bias + np.array([0.0, 0.0, 0.3]), truth.accel.matrix,
                                                  {"bias": [1e-3] * 3, "scale": [1e-4] * 3,
                                                   "alpha": [1e-4] * 3, "xi": [1e-4] * 3}))
    init = tmp_path / "wrong.json"
    init.write_text(wrong.to_json())
    out = tmp_path / "out.json"
    r = subprocess.run([sys.executable, "-m", "onlinecal", "-q", "replay", str(log), "--init", str(init), "--json",
                        str(out)], capture_output=True, text=True, cwd=ROOT)
    h = json.loads(out.read_text())["health"]
    g = h["checks"]["gravity_at_rest"]
    assert g["rest_blocks"] >= 100 and g["norm_minus_g"] == pytest.approx(-0.3, abs=0.02)
    assert any(rs.startswith("accel: at rest") for rs in h["reasons"]), h["reasons"]
    assert r.returncode in (4, 5) and h["verdict"] != "ok"


def test_run_apply_keeps_the_vehicles_accelerometer_where_gravity_at_rest_says_it_is_off() -> None:
    """`run --apply` sets only what the samples fed do not contradict: the accelerometer's parameters of a
    calibration 0.3 m/s² off along gravity (σ 1e-3) are not sent; the gyro's are."""
    import io

    from onlinecal.ukf.live_run import LiveResult, _apply, _vehicle_params

    sim = simulate("multirotor", 2, duration=40.0, imu_rate=200.0)  # the ground rest
    truth = sim.truth.calibration
    assert truth.accel is not None
    sig = {"bias": [1e-3] * 3, "scale": [1e-4] * 3, "alpha": [1e-4] * 3, "xi": [1e-4] * 3}
    wrong = truth.replace(accel=SensorCalibration(truth.accel.bias + np.array([0.0, 0.0, 0.3]), truth.accel.matrix,
                                                  sig))
    sent: dict[str, float] = {}

    class Vehicle:
        def set_params(self, params, types=None, bytewise=False):  # type: ignore[no-untyped-def]
            sent.update(params)
            return {n: {"confirmed": True} for n in params}

    for cal, expect_acc in ((truth.replace(accel=truth.accel.with_sigma(sig)), True), (wrong, False)):
        sent.clear()
        d = RawDigest()
        d.add(sim.data.gyro, sim.data.acc)
        res = LiveResult(cal, [], {}, {}, [], raw_digest=d)
        _apply(res, "ardupilot", _vehicle_params(), Vehicle(), io.StringIO())  # type: ignore[arg-type]
        assert any(n.startswith("INS_GYROFFS") for n in sent)
        assert any(n.startswith("INS_ACC") for n in sent) is expect_acc, sorted(sent)
