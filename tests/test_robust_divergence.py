"""Issue 16, item 4: a divergence is visible (one stderr line each, the health verdict) and escapable (a
restart from a widened prior, the cold prior on a second divergence soon after), and a negative or NaN
NIS is a numerical failure, not a statistic that passes the gate (:mod:`onlinecal.ukf.divergence`)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from onlinecal.health import assess
from onlinecal.model import PARAMS, SENSORS, Calibration
from onlinecal.sim import simulate
from onlinecal.ukf import OnlineCalibrator
from onlinecal.ukf import divergence as dv
from onlinecal.ukf.config import UKFConfig
from onlinecal.ukf.layout import SENSOR_SLICE
from onlinecal.ukf.replay import replay

REPO = Path(__file__).resolve().parents[1]

# the σ a batch result of the paper session typically has (tests/test_ukf.py's offset prior)
BATCH_SIGMA = {"gyro": {"bias": 2e-3, "scale": 5e-3, "alpha": 5e-3, "xi": 5e-3},
               "accel": {"bias": 0.03, "scale": 3e-3, "alpha": 5e-3, "xi": 5e-3},
               "mag": {"bias": 3e-3, "scale": 0.02, "alpha": 5e-3, "xi": 5e-3}}


def _wrong_start(truth: Calibration, case: str) -> Calibration:
    """The truth spoiled the way issue 16 names (a confident, wrong start): gyro scale × 0.5 and/or the
    magnetometer's bias moved by 3× the field (raw field = 1 / mean scale), with a batch result's σ."""
    out = {}
    for s in SENSORS:
        p = {k: np.array(v, float) for k, v in truth.sensor(s).params().items()}
        if s == "gyro" and case in ("gyro", "both"):
            p["scale"] = p["scale"] * 0.5
        if s == "mag" and case in ("mag", "both"):
            u = np.array([1.0, -1.0, 0.5]) / np.linalg.norm([1.0, -1.0, 0.5])
            p["bias"] = p["bias"] + 3.0 / float(np.mean(p["scale"])) * u
        out[s] = type(truth.sensor(s)).from_params(p["bias"], p["scale"], p["alpha"], p["xi"],
                                                   sigma={k: [BATCH_SIGMA[s][k]] * 3 for k in PARAMS})
    return Calibration(source="batch", **out)


def _z(cal: Calibration, truth: Calibration) -> np.ndarray:
    """|estimate − truth| / σ of every term (36)."""
    z = []
    for s in SENSORS:
        e, t = cal.sensor(s), truth.sensor(s)
        for p in PARAMS:
            z.append(np.abs(np.asarray(e.params()[p]) - np.asarray(t.params()[p])) / np.asarray(e.sigma[p]))
    return np.concatenate(z)


# -- the policy, as pure functions ------------------------------------------------------------------------

@pytest.mark.parametrize("nis, bad", [(-5.0, "negative"), (-1e-3, "negative"), (math.nan, "NaN"),
                                      (math.inf, "infinite"), (0.0, None), (2.9, None), (1e7, None)])
def test_a_negative_or_nan_nis_is_a_numerical_failure(nis: float, bad: str | None) -> None:
    why = dv.nis_failure(nis)
    assert (why is None) if bad is None else (why is not None and bad in why)


def test_the_restart_widens_to_the_cold_prior_and_escalates_on_a_second_divergence() -> None:
    log = dv.DivergenceLog()
    x_est, x_start = np.array([0.6, 1e-3]), np.array([0.5, 0.0])
    sig_start, x_cold, sig_cold = np.array([5e-3, 1e-4]), np.array([1.0, 0.0]), np.array([0.2, 0.2])
    cover = np.array([True, True])
    good = [[10.0, 3.0], [20.0, 3.1], [30.0, 2.9], [40.0, 500.0], [50.0, 600.0], [60.0, 700.0]]
    r = dv.plan_restart(log, 60.0, x_est, x_start, sig_start, x_cold, sig_cold, good, 3.87, 5.0, False, cover)
    # the data agreed with the start at first: the start, with σ ≥ the cold σ and reaching the cold mean
    assert r.kind == "widened" and r.source == "start" and np.array_equal(r.x, x_start)
    assert np.all(r.sigma >= sig_cold) and r.sigma[0] >= abs(x_est[0] - x_cold[0])
    # a second divergence 100 s later: the cold prior
    r2 = dv.plan_restart(log, 160.0, x_est, x_start, sig_start, x_cold, sig_cold, good, 3.87, 5.0, False, cover)
    assert r2.kind == "cold" and np.array_equal(r2.x, x_cold) and np.array_equal(r2.sigma, sig_cold)
    # one long after (and a NIS bad from the outset): widened again, from the estimate
    bad = [[300.0, 400.0], [310.0, 500.0], [320.0, 600.0]]
    r3 = dv.plan_restart(log, 400.0, x_est, x_start, sig_start, x_cold, sig_cold, bad, 3.87, 5.0, False, cover)
    assert r3.kind == "widened" and r3.source == "estimate" and np.array_equal(r3.x, x_est)
    assert log.count == 3
    # a non-finite estimate restarts from the start; a numerical failure keeps a finite estimate
    r4 = dv.plan_restart(dv.DivergenceLog(), 0.0, np.array([np.nan, 0.0]), x_start, sig_start, x_cold, sig_cold,
                         bad, 3.87, 5.0, True, cover)
    assert r4.source == "start" and np.all(np.isfinite(r4.sigma))
    r5 = dv.plan_restart(dv.DivergenceLog(), 0.0, x_est, x_start, sig_start, x_cold, sig_cold, good, 3.87, 5.0,
                         True, cover)
    assert r5.source == "estimate"


def test_a_magnetometer_divergence_restarts_the_magnetometer_and_gyro_terms_only_while_the_accel_is_fine() -> None:
    consider = np.zeros(46, bool)
    consider[SENSOR_SLICE["accel"].start + 6 : SENSOR_SLICE["accel"].start + 9] = True  # a gauge: accel alpha
    idx = dv.restart_indices(consider, True, True)
    assert set(idx) == set(range(3, 15)) | set(range(27, 40))
    every = dv.restart_indices(consider, True, False)
    assert set(every) == set(range(3, 40)) - set(range(21, 24))
    assert set(dv.restart_indices(consider, False, False)) == set(range(3, 27)) - set(range(21, 24))
    assert dv.mag_alone("mag", {"bad_run": 0}) and not dv.mag_alone("mag", {"bad_run": 2})
    assert not dv.mag_alone("accel", {"bad_run": 0}) and not dv.mag_alone(None, {"bad_run": 0})


# -- in the filter -------------------------------------------------------------------------------------------

def _restarted_exactly(cal: OnlineCalibrator) -> bool:
    """The calibration states are the restart's prior, untouched by an update (not a posterior)."""
    sl = np.arange(3, 27)  # gyro and accel (a cold start: the magnetometer may still be uncalibrated)
    return bool(np.array_equal(cal.x[sl], cal.prior_x[sl])
                and np.allclose(np.sqrt(np.diag(cal.P)[sl]), cal.prior_sigma[sl], rtol=1e-12))


def test_a_divergence_declared_by_the_nis_windows_restarts_the_state() -> None:
    """The NIS windows declare a divergence during an update: the state after that block is the restart's
    widened prior, not the diverged posterior committed over it (the bug d1c88cd fixed: only the attitude
    restarted)."""
    sim = simulate("paper", 2, duration=50.0)
    cal = OnlineCalibrator(None)
    cal.new_log()
    cal.feed(sim.data.slice_imu(0, 4000))
    cold_sig = dv.cold_prior(cal.config, cal.x)[1]
    assert not _restarted_exactly(cal)  # the filter has moved away from its prior
    cal._nis.record = lambda s, nis, t, inflated=0.0, held=False: f"{s} NIS window mean forced"  # type: ignore[method-assign]
    i = 4000
    with pytest.warns(dv.DivergenceWarning, match="diverged at t ="):
        while not any(e["kind"] == "divergence" for e in cal.events) and i < 4500:
            cal.feed(sim.data.slice_imu(i, i + 10))  # one filter block at a time
            i += 10
    assert any(e["kind"] == "divergence" for e in cal.events)
    assert _restarted_exactly(cal)
    free = np.arange(3, 27)[~cal.lay.consider[3:27]]  # the gauge's consider states are held at their start
    assert np.all(cal.prior_sigma[free] >= cold_sig[free])


def test_a_negative_nis_is_a_divergence_in_the_filter(monkeypatch: pytest.MonkeyPatch) -> None:
    """An update whose NIS is negative (an indefinite innovation covariance) passed the gate ("ok") and the
    windows; now it is a numerical failure: a divergence, and its posterior is not committed."""
    import onlinecal.ukf.step as flt  # the gated update's module
    from onlinecal.ukf import fastpath

    sim = simulate("paper", 2, duration=50.0)
    cal = OnlineCalibrator(None)
    cal.new_log()
    cal.feed(sim.data.slice_imu(0, 4000))
    real = flt.update

    def negative(*a, **k):  # type: ignore[no-untyped-def]
        res = real(*a, **k)
        res.nis = [(s, -4.0, st) for s, _, st in res.nis]
        return res

    monkeypatch.setattr(flt, "update", negative)
    monkeypatch.setattr(fastpath, "_enabled", False)  # the patched update is the general path's (.ukf.fastpath)
    with pytest.warns(dv.DivergenceWarning, match="negative"):
        i = 4000
        while not any(e["kind"] == "divergence" for e in cal.events) and i < 4500:
            cal.feed(sim.data.slice_imu(i, i + 10))
            i += 10
    div = [e for e in cal.events if e["kind"] == "divergence"]
    assert div and "negative" in div[0]["detail"] and "numerical failure" in div[0]["detail"]
    assert _restarted_exactly(cal)


# -- end to end: a wrong start can be left --------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("case, seed", [("gyro", 1), ("mag", 1), ("both", 2)])
def test_replay_from_a_wrong_calibration_is_left_or_flagged(case: str, seed: int) -> None:
    """Issue 16: started from gyro scale × 0.5 and/or a magnetometer bias 3 fields off, the filter ended
    219σ (gyro) and 10 784σ (mag) from the truth after 13–14 restarts to the same start. Now: every term within
    3σ of the truth or the health not ok (with the divergences named): the issue's expectation. Measured
    (docs/robustness.md): the worst term 2.7–220σ over seeds 1–2; every run far off is "failed" or
    "degraded", none "ok"; the restarts are 2–3 per run instead of 13–14."""
    sim = simulate("paper", seed)
    truth = sim.truth.calibration
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        res = replay([sim.data], _wrong_start(truth, case), UKFConfig())
    div = [e for e in res.events if e["kind"] == "divergence"]
    lines = [x for x in w if issubclass(x.category, dv.DivergenceWarning)]
    assert div and len(lines) == len(div)  # one warning per divergence
    z = _z(res.calibration, truth)
    h = assess(res.calibration, events=res.events, nis=res.nis)
    assert np.all(z < 3.0) or (h["verdict"] != "ok" and any("diverged" in r for r in h["reasons"]))
    assert len(div) <= 5  # not one restart every 30 s to the same start as before (13-14 in 309 s)


@pytest.mark.slow
def test_cli_prints_each_divergence_on_one_stderr_line(tmp_path: Path) -> None:
    """`replay --init WRONG.json`: each divergence one line on stderr, the verdict not ok, exit 4 or 5."""
    env = dict(os.environ, PYTHONPATH=str(REPO))

    def cli(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "onlinecal", *args], capture_output=True, text=True,
                              timeout=600, env=env)

    log = tmp_path / "s.tlog"
    assert cli("simulate", "--out", str(log), "--seed", "1").returncode == 0
    truth = Calibration.from_dict(json.loads(Path(str(log) + ".truth.json").read_text())["calibration"])
    init = tmp_path / "wrong.json"
    _wrong_start(truth, "gyro").save(init)
    out = tmp_path / "o.json"
    r = cli("replay", str(log), "--init", str(init), "--json", str(out), "-q")
    assert "Traceback" not in r.stderr
    h = json.loads(out.read_text())["health"]
    assert h["verdict"] != "ok" and r.returncode in (4, 5)
    lines = [x for x in r.stderr.splitlines() if "diverged at t =" in x]
    n = int(next(x for x in h["reasons"] if "diverged" in x).split("diverged ")[1].split(" time")[0])
    assert n >= 1 and len(lines) == n, r.stderr
