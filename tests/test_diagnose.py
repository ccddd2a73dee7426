"""diagnose: hidden effects are found (right effect, sensor, axis, parameter within 20 %, held-out gain), clean
sessions give ``none`` in ≥ 19 of 20 seeds, two hidden effects are both found, JSON/CLI/report contract.

Every hidden effect and its size are drawn per seed by ``random_effect`` (effects_spec.md test ranges), so no
test can pass by naming a fixed answer. Full paper sessions (309 s, 100 Hz) throughout.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from onlinecal.cli import main
from onlinecal.diagnose import SCHEMA, diagnose
from onlinecal.io import write_log
from onlinecal.sim import simulate
from onlinecal.sim.effects import EFFECTS, random_effect

PRIMARY = {"temperature_bias": ["coeff"], "bias_drift": ["density"], "g_sensitivity": ["coeff"],
           "time_offset": ["seconds"], "saturation": ["limit"], "scale_nonlinearity": ["coeff"]}


def _hidden(name: str, seed: int):
    rng = np.random.default_rng(1000 + seed)
    clean = simulate("paper", seed) if name == "saturation" else None
    eff = random_effect(name, rng, clean)
    sim = simulate("paper", seed, effects=[eff])
    return sim, sim.truth.effects[0], diagnose([sim.data], check=False, ukf=False)


def _matches(f, truth: dict) -> list[str]:
    """What is wrong with finding f against the truth's describe() dict (empty: it matches)."""
    bad = []
    if f.effect != truth["effect"]:
        return [f"effect {f.effect} != {truth['effect']}"]
    if f.sensor != truth["sensor"]:
        bad.append(f"sensor {f.sensor} != {truth['sensor']}")
    if truth["effect"] not in ("time_offset", "saturation", "lever_arm") and f.axis != truth["axis"]:
        bad.append(f"axis {f.axis} != {truth['axis']}")
    if truth["effect"] == "lever_arm":
        r = np.array([truth[k] for k in "xyz"])
        e = np.array([f.parameters[k] for k in "xyz"])
        if np.linalg.norm(e - r) > 0.2 * np.linalg.norm(r):
            bad.append(f"lever arm {e} vs {r}")
    for k in PRIMARY.get(truth["effect"], []):
        if abs(f.parameters[k] - truth[k]) > 0.2 * abs(truth[k]):
            bad.append(f"{k} {f.parameters[k]:.4g} vs truth {truth[k]:.4g}")
    return bad


@pytest.mark.slow
@pytest.mark.parametrize("seed", [21, 22])
@pytest.mark.parametrize("name", EFFECTS)
def test_hidden_effect_is_the_verdict(name: str, seed: int) -> None:
    sim, truth, diag = _hidden(name, seed)
    assert diag.verdict == name, (truth, [(f.effect, f.score, f.threshold) for f in diag.findings[:4]])
    top = diag.significant[0]
    assert _matches(top, truth) == [], (truth, top.parameters)
    if name != "saturation":  # saturation's model censors rows; its gain is counted in clipped samples
        assert top.gain["loglik_gain"] > 0 and top.gain["bic_delta"] < 0
    if name not in ("saturation", "axis_sign"):
        assert top.gain["heldout_rms_after"] < top.gain["heldout_rms_before"]
        assert top.score > top.threshold >= top.null_score


@pytest.mark.slow
def test_clean_sessions_verdict_none_in_19_of_20() -> None:
    verdicts = [diagnose([simulate("paper", 100 + s).data], check=False, seed=s, ukf=False).verdict for s in range(20)]
    assert sum(v == "none" for v in verdicts) >= 19, verdicts


@pytest.mark.slow
@pytest.mark.parametrize("seed", [31, 32])
def test_two_hidden_effects_are_both_significant(seed: int) -> None:
    rng = np.random.default_rng(2000 + seed)
    # two different linear effects on different sensors or roles (drawn per seed)
    pool = ["temperature_bias", "g_sensitivity", "time_offset", "scale_nonlinearity", "lever_arm", "bias_drift"]
    a, b = rng.choice(pool, 2, replace=False)
    effs = [random_effect(str(a), rng), random_effect(str(b), rng)]
    sim = simulate("paper", seed, effects=effs)
    diag = diagnose([sim.data], check=False, ukf=False)
    found = {f.effect for f in diag.significant}
    assert {a, b} <= found, (sim.truth.effects, [(f.effect, f.score) for f in diag.findings[:5]])


@pytest.mark.slow
def test_cli_json_report_and_extension(tmp_path) -> None:
    rng = np.random.default_rng(7)
    eff = random_effect("g_sensitivity", rng)
    sim = simulate("paper", 41, effects=[eff])
    log = tmp_path / "s.csv"
    write_log(log, sim.data)
    out, rep = tmp_path / "d.json", tmp_path / "rep"
    # exit 0/4/5 by the health verdict (the extended model's UKF NIS is part of it)
    assert main(["diagnose", str(log), "--json", str(out), "--report", str(rep)]) in (0, 4, 5)
    d = json.loads(out.read_text())
    assert d["schema"] == SCHEMA
    assert d["verdict"] == "g_sensitivity"
    assert d["findings"][0]["significant"] and d["findings"][0]["effect"] == d["verdict"]
    for f in d["findings"]:
        assert set(f) >= {"effect", "sensor", "axis", "score", "significant", "parameters", "gain", "evidence"}
        assert set(f["gain"]) >= {"heldout_rms_before", "heldout_rms_after", "loglik_gain", "bic_delta"}
    scores = [f["score"] for f in d["findings"] if f["significant"]]
    assert scores == sorted(scores, reverse=True)
    ext = d["extended_calibration"]["extensions"]["g_sensitivity"]
    assert abs(np.mean(ext["coeff"]) - eff.coeff) < 0.2 * abs(eff.coeff) or \
        abs(ext["coeff"] - eff.coeff) < 0.2 * abs(eff.coeff)
    # the simulator with the extension reproduces the channel the paper model got wrong
    chk = d["simulation_check"]["channels"]
    worst = d["simulation_check"]["worst_channel"]
    c = chk[worst]
    assert abs(c["simulated_extended_rms"] - c["measured_rms"]) < abs(c["simulated_rms"] - c["measured_rms"])
    assert (rep / "report.md").exists() and (rep / "channels.png").exists()
    assert "g_sensitivity" in (rep / "report.md").read_text()


def test_unreadable_log_exits_2(tmp_path, capsys) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("not,a,log\n1,2\n")
    assert main(["diagnose", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.csv" in err[0]


def test_real_session_with_little_motion_does_not_crash(data_dir) -> None:
    from onlinecal.io import read_log

    d = read_log(data_dir / "marg-set1" / "unmoved-x-pointing-up.csv")
    diag = diagnose([d], check=False, ukf=False)
    assert diag.verdict in EFFECTS + ("none",)
    assert any("rotation" in u for u in diag.untestable)
    json.loads(diag.to_json())


@pytest.mark.slow
def test_extended_calibration_improves_replay_and_ukf_nis(tmp_path, capsys) -> None:
    """A hidden gyro temperature_bias (coefficient drawn per seed): diagnose writes the extended calibration and
    the UKF's NIS before/after; ``replay --init extended.json`` (the extension applied to the log by
    onlinecal.apply_ext) ends with the gyro bias on the affected axis closer to the truth, and far more
    precise, than ``replay --init baseline.json`` (which, with no term for the drift, widens its bias's random
    walk to it: honest, not precise)."""
    from onlinecal.model import Calibration
    from onlinecal.sim.effects import TemperatureBias

    rng = np.random.default_rng(4242)
    k = int(rng.integers(3))
    coeff = float(rng.uniform(4e-4, 1e-3) * rng.choice([-1, 1]))
    sim = simulate("paper", 43, effects=[TemperatureBias(sensor="gyro", axis="xyz"[k], coeff=coeff)])
    log = tmp_path / "s.csv"
    write_log(log, sim.data)
    dj = tmp_path / "d.json"
    assert main(["diagnose", str(log), "--json", str(dj)]) == 0
    d = json.loads(dj.read_text())
    assert d["verdict"] == "temperature_bias"
    top = d["findings"][0]
    # the UKF with the extension (here: its temperature state) is consistent where the paper model's is not
    g = top["gain"]
    before, after = d["baseline"]["ukf"], d["ukf_extended"]
    assert after["extra_states"] == ["temperature_bias:gyro"]
    assert g["ukf_nis_before"] == before["nis_mean"] and g["ukf_nis_after"] == after["nis_mean"]
    assert g["ukf_nis_after"] < g["ukf_nis_before"]
    assert abs(g["ukf_nis_after"] - 3.0) < abs(g["ukf_nis_before"] - 3.0)
    ext = d["extended_calibration"]["extensions"]["temperature_bias"]
    base_p, ext_p = tmp_path / "baseline.json", tmp_path / "extended.json"
    base_p.write_text(json.dumps(d["baseline"]["calibration"]))
    ext_p.write_text(json.dumps(d["extended_calibration"]))
    out = {}
    for name, init in (("base", base_p), ("ext", ext_p)):
        o = tmp_path / f"{name}.online.json"
        # exit 0/4/5 by the health verdict: the paper model's replay of this data is not consistent
        assert main(["replay", str(log), "--init", str(init), "--json", str(o)]) in (0, 4, 5)
        out[name] = Calibration.load(o)
    assert "extensions applied" in capsys.readouterr().err
    assert out["ext"].extensions == Calibration.from_dict(d["extended_calibration"]).extensions
    # truth: the simulator's bias is at 25 °C; the data corrected by the fitted extension (coefficient ĉ)
    # holds b25 + c(T − 25) − ĉ(T − T0), which is the bias at T0 only where ĉ = c: the filter ends on its
    # value at the last temperature (a coefficient off by 0.14 of its σ moves it by 2e-5 rad/s over 8 °C)
    b25 = sim.truth.calibration.gyro.bias[k]
    t_end = float(sim.data.temp[-1])
    b_corr_end = b25 + coeff * (t_end - 25.0) - ext["coeff"] * (t_end - ext["T0"])
    err_ext = abs(out["ext"].gyro.bias[k] - b_corr_end)
    assert err_ext < 3 * out["ext"].gyro.sigma["bias"][k], (err_ext, out["ext"].gyro.sigma["bias"])
    # the paper model has no term for the drift. Before session 10 its replay ended confidently off (the bias's
    # random walk the spec's) and its NIS above the extension's. Since then the filter measures the drift at rest
    # (event bias_walk, docs/flight.md) and widens the bias's random walk to it: the paper model's bias is then
    # honest (within its 3σ of the value at the session's end), but ~20× less precise than with the extension,
    # which needs no walk; their NIS are alike (the walk absorbs the drift), so precision is the comparison.
    b_end = b25 + coeff * (sim.data.temp[-1] - 25.0)
    s_base, s_ext = out["base"].gyro.sigma["bias"][k], out["ext"].gyro.sigma["bias"][k]
    err_base = abs(out["base"].gyro.bias[k] - b_end)
    walks = {n: [e for e in c.meta["online"]["events"] if e["kind"] == "bias_walk"] for n, c in out.items()}
    assert walks["base"] and not walks["ext"], walks
    assert err_base <= 3 * s_base, (err_base, s_base)
    assert err_ext < err_base and s_ext < 0.2 * s_base, (err_ext, err_base, s_ext, s_base)


def test_live_extensions_pointwise_per_block_and_time_offset_refused(tmp_path, capsys) -> None:
    """Live runs apply the pointwise extensions block by block (identical to the whole-log correction for
    temperature_bias and a mag re-stamp) and refuse a gyro/accel time_offset with exit 2 before connecting."""
    from onlinecal.apply_ext import BlockCorrector, check_live
    from onlinecal.extensions import correct

    sim = simulate("paper", 44, duration=20.0)
    cal = sim.truth.calibration.replace(extensions={
        "temperature_bias": {"sensor": "gyro", "axis": "y", "coeff": 7e-4, "T0": 26.0},
        "time_offset": {"sensor": "mag", "seconds": 0.03}})
    whole = correct(sim.data, cal.extensions, calibration=cal)
    corr = BlockCorrector(cal)
    parts = [corr(sim.data.slice_imu(i, i + 25)) for i in range(0, sim.data.n_imu, 25)]
    assert np.allclose(np.concatenate([p.gyro for p in parts]), whole.gyro, rtol=0, atol=1e-15)
    assert np.allclose(np.concatenate([p.t_mag for p in parts]), whole.t_mag, rtol=0, atol=1e-12)
    assert any("temperature_bias" in n for n in check_live(cal))
    bad = cal.replace(extensions={"time_offset": {"sensor": "accel", "seconds": 0.01}})
    p = tmp_path / "bad.json"
    bad.save(p)
    assert main(["run", "--connect", "udpin:127.0.0.1:1", "--init", str(p), "--duration", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "time_offset" in err[0] and "live" in err[0]
