"""Issue 12's rows on the command line, each reproduced: tracebacks and late failures on bad outputs and
options, damaged calibration files, `-` for stdout, strict JSON, compare --tol with a truth file, --quiet
after every command, library warnings routed, the health verdict in the JSON and the exit status."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def cli(*args: str, timeout: float = 300, env: dict | None = None,
        cwd: Path | None = None) -> subprocess.CompletedProcess:
    e = dict(os.environ, PYTHONPATH=str(REPO), **(env or {}))
    return subprocess.run([sys.executable, "-m", "onlinecal", *args], capture_output=True, text=True,
                          timeout=timeout, env=e, cwd=cwd)


def in_process(capsys: pytest.CaptureFixture[str], *args: str) -> subprocess.CompletedProcess:
    """The command line run by ``onlinecal.cli.main`` in this process (no interpreter start: the fast tier)."""
    from onlinecal.cli import main

    try:
        rc = main(list(args))
    except SystemExit as e:  # argparse's own refusals
        rc = int(e.code or 0)
    out, err = capsys.readouterr()
    return subprocess.CompletedProcess(list(args), rc, out, err)


def one_line(r: subprocess.CompletedProcess, code: int = 2) -> str:
    assert r.returncode == code, (r.returncode, r.stderr)
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    return lines[0]


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A paper session (.tlog + truth) and its batch calibration written by the command line."""
    d = tmp_path_factory.mktemp("rows")
    log = d / "s.tlog"
    r = cli("simulate", "--out", str(log), "--seed", "3")
    assert r.returncode == 0, r.stderr
    cal = d / "b.json"
    r = cli("batch", str(log), "--json", str(cal))
    assert r.returncode == 0, r.stderr
    return {"dir": d, "log": log, "truth": Path(str(log) + ".truth.json"), "cal": cal}


# -- unwritable outputs are refused before the work starts ------------------------------------------------

@pytest.mark.parametrize("args, path", [
    (["batch", "{log}", "--json", "/nonexistent/x.json"], "/nonexistent/x.json"),
    (["diagnose", "{log}", "--json", "/nonexistent/x.json"], "/nonexistent/x.json"),
    (["diagnose", "{log}", "--report", "/proc/x"], "/proc/x"),
    (["replay", "{log}", "--trace", "/nonexistent/t.csv"], "/nonexistent/t.csv"),
    (["replay", "{log}", "--json", "/nonexistent/x.json", "--jobs", "1"], "/nonexistent/x.json"),
    (["batch", "{log}", "--report", "{log}"], "{log}"),
    (["demo", "--out", "{log}"], "{log}"),
    (["simulate", "--out", "/nonexistent/dir/x.tlog"], "/nonexistent/dir/x.tlog"),
    (["export", "{cal}", "--format", "px4", "--out", "/nonexistent/x.params"], "/nonexistent/x.params"),
])
@pytest.mark.slow
def test_unwritable_output_refused_quickly(session: dict[str, Path], args: list[str], path: str) -> None:
    args = [a.format(log=session["log"], cal=session["cal"]) for a in args]
    t0 = time.monotonic()
    line = one_line(cli(*args))
    assert time.monotonic() - t0 < 20  # before the fit (a batch alone takes longer on this machine)
    assert path.format(log=session["log"]) in line, line


@pytest.mark.parametrize("args, option", [
    (["simulate", "--out", "x.tlog", "--rate", "0"], "--rate"),
    (["simulate", "--out", "x.tlog", "--rate", "-100"], "--rate"),
    (["simulate", "--out", "x.tlog", "--mag-rate", "0"], "--mag-rate"),
    (["simulate", "--out", "x.tlog", "--duration", "-5"], "--duration"),
    (["simulate", "--out", "x.tlog", "--duration", "nan"], "--duration"),
    (["simulate", "--out", "x.tlog", "--seed", "-1"], "--seed"),
    (["batch", "x.tlog", "--gravity", "0"], "--gravity"),
    (["batch", "x.tlog", "--acc-scale", "0"], "--acc-scale"),
    (["run", "--connect", "udpin:0.0.0.0:1", "--duration", "-5"], "--duration"),
    (["run", "--connect", "udpin:0.0.0.0:1", "--checkpoint-every", "0"], "--checkpoint-every"),
    (["compare", "a.json", "b.json", "--tol", "-1"], "--tol"),
    (["replay", "x.tlog", "--jobs", "0"], "--jobs"),
])
def test_invalid_numbers_rejected_with_one_line(tmp_path: Path, args: list[str], option: str,
                                                capsys: pytest.CaptureFixture[str], monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    r = in_process(capsys, *args)
    line = one_line(r)
    assert option in line and "must be" in line, line
    assert not (tmp_path / "x.tlog").exists()


# -- damaged calibration files, everywhere they are read ---------------------------------------------------

JUNK = {"list": "[1, 2]", "string": '"x"', "null": "null", "nested": '{"schema": "onlinecal.calibration/1", '
        '"gyro": {"bias": [[1], [2], [3]], "matrix": {"a": 1}}}',
        "duplicate": '{"schema": "onlinecal.calibration/1", "gyro": {"bias": [0,0,0]}, "gyro": null}',
        "singular": '{"schema": "onlinecal.calibration/1", "accel": {"bias": [0,0,0], '
                    '"matrix": [[1,0,0],[0,1,0],[0,0,0]]}}',
        "sigma": '{"schema": "onlinecal.calibration/1", "gyro": {"bias": [0,0,0], "sigma": {"bias": [1]}}}',
        "huge-bias": '{"schema": "onlinecal.calibration/1", "gyro": {"bias": [1e300,0,0]}}'}


@pytest.mark.slow
@pytest.mark.parametrize("kind", sorted(JUNK))
@pytest.mark.parametrize("cmd", ["export", "compare", "replay", "replay-jobs", "run"])
def test_damaged_calibration_one_line_naming_the_file(session: dict[str, Path], tmp_path: Path, kind: str,
                                                       cmd: str, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / f"{kind}.json"
    bad.write_text(JUNK[kind])
    args = {"export": ["export", str(bad), "--format", "ardupilot", "--out", str(tmp_path / "o.parm")],
            "compare": ["compare", str(session["cal"]), str(bad)],
            "replay": ["replay", str(session["log"]), "--init", str(bad)],
            "replay-jobs": ["replay", str(session["log"]), "--init", str(bad), "--jobs", "1"],
            "run": ["run", "--connect", "udpin:127.0.0.1:1", "--init", str(bad), "--duration", "1"]}[cmd]
    line = one_line(in_process(capsys, *args))
    assert str(bad) in line, line


def test_directory_as_calibration(tmp_path: Path) -> None:
    assert str(tmp_path) in one_line(cli("export", str(tmp_path), "--format", "px4"))


@pytest.mark.slow
def test_unicode_file_name_under_lang_c(session: dict[str, Path], tmp_path: Path) -> None:
    u = tmp_path / "kalibrierung-σ-µ.json"
    u.write_bytes(session["cal"].read_bytes())
    r = cli("compare", str(u), str(session["cal"]), env={"LANG": "C", "LC_ALL": "C"})
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    missing = cli("compare", str(tmp_path / "fehlt-σ.json"), str(u), env={"LANG": "C", "LC_ALL": "C"})
    assert "fehlt" in one_line(missing)


# -- output ------------------------------------------------------------------------------------------------

@pytest.mark.slow
def test_batch_json_dash_is_stdout_strict_json_with_health(session: dict[str, Path]) -> None:
    r = cli("batch", str(session["log"]), "--json", "-", "--quiet")
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout, parse_constant=lambda c: pytest.fail(f"bare {c} in the JSON"))
    assert d["health"]["verdict"] == "ok" and "health" not in d["meta"]
    assert not (Path.cwd() / "-").exists()
    assert "health of the batch calibration: ok" in r.stderr and "batch pipeline:" in r.stderr


@pytest.mark.slow
def test_batch_table_has_units_sigma_and_no_empty_columns(session: dict[str, Path]) -> None:
    r = cli("batch", str(session["log"]), "-q")
    head = r.stdout.splitlines()[0].split()
    assert head == ["parameter", "unit", "batch", "±", "3σ"], head
    row = next(ln for ln in r.stdout.splitlines() if ln.startswith("accel.bias.x"))
    assert "m/s^2" in row and "—" not in row


@pytest.mark.slow
def test_compare_accepts_truth_and_tol_sets_the_exit_status(session: dict[str, Path]) -> None:
    ok = cli("compare", str(session["truth"]), str(session["cal"]), "--tol", "1e6")
    assert ok.returncode == 0, ok.stderr
    tight = cli("compare", str(session["truth"]), str(session["cal"]), "--tol", "1e-6")
    assert tight.returncode == 1 and "beyond the tolerance" in tight.stderr
    # every column separated by at least one space (was "8.1e-071918086.3")
    for ln in ok.stdout.splitlines()[2:]:
        if ".matrix" not in ln:
            assert len(ln.split()) >= 7, ln


@pytest.mark.parametrize("cmd", [["export", "{cal}", "--format", "px4", "--out", "-"],
                                 ["compare", "{cal}", "{cal}"], ["batch", "{log}"]])
@pytest.mark.slow
def test_quiet_after_every_command(session: dict[str, Path], cmd: list[str]) -> None:
    args = [a.format(d=session["dir"], cal=session["cal"], log=session["log"]) for a in cmd]
    r = cli(*args, "--quiet")
    assert r.returncode in (0, 4) and "unrecognized" not in r.stderr, r.stderr


def test_quiet_is_accepted_after_every_subcommand() -> None:
    from onlinecal.cli import build_parser

    ap = build_parser()
    sub = next(a for a in ap._actions if isinstance(a, type(ap._subparsers._group_actions[0])))  # type: ignore[union-attr]
    for name, p in sub.choices.items():
        assert any("--quiet" in a.option_strings for a in p._actions), name


@pytest.mark.slow
def test_help_documents_exit_status_csv_schema_and_examples() -> None:
    r = cli("--help")
    text = " ".join(r.stdout.split())
    assert "4 result degraded" in text and "5 result failed" in text and "time_s,gyro_x" in text
    for cmd in ("batch", "replay", "compare", "export", "simulate"):
        h = " ".join(cli(cmd, "--help").stdout.split())
        assert "example" in h and "exit status" in h, cmd


def test_library_warnings_become_one_line_warnings(tmp_path: Path) -> None:
    code = ("import warnings, numpy as np, sys\n"
            "from onlinecal import cli\n"
            "cli._quiet_libraries()\n"
            "np.log(np.zeros(1)); np.log(np.zeros(1))\n"
            "warnings.warn('a style warning', UserWarning)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env=dict(os.environ, PYTHONPATH=str(REPO)), timeout=60)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 2 and all(ln.startswith("warning: ") for ln in lines), r.stderr
    assert "divide by zero" in lines[0] and "a style warning" in lines[1] and "line " not in r.stderr


@pytest.mark.slow
def test_export_guard_on_the_command_line(session: dict[str, Path], tmp_path: Path) -> None:
    d = json.loads(session["cal"].read_text())
    d["accel"]["sigma"]["bias"] = [0.001, 0.001, 0.37]
    cal = tmp_path / "c.json"
    cal.write_text(json.dumps(d))
    r = cli("export", str(cal), "--format", "ardupilot", "--out", str(tmp_path / "c.parm"))
    assert r.returncode == 4 and "INS_ACCOFFS_Z not written" in r.stderr, r.stderr
    text = (tmp_path / "c.parm").read_text()
    assert "\nINS_ACCOFFS_Z" not in text and "# INS_ACCOFFS_Z: NOT WRITTEN" in text
    assert "# INS_ACCOFFS_X: from accel.bias.x" in text  # every parameter says where it came from
    f = cli("export", str(cal), "--format", "ardupilot", "--out", "-", "--force")
    assert f.returncode == 0 and "\nINS_ACCOFFS_Z " in f.stdout


@pytest.mark.slow
def test_divergence_reported_on_stderr_and_in_the_verdict(session: dict[str, Path], tmp_path: Path) -> None:
    """A replay started from a wrong calibration (gyro scale 1.0 against the truth's 1.14, accel bias off by
    1 m/s²) must not end silently: its health is not ok and the reason is printed."""
    d = json.loads(session["truth"].read_text())["calibration"]
    d["accel"]["bias"] = [b + 1.0 for b in d["accel"]["bias"]]
    d["accel"].pop("matrix", None)
    d["accel"]["sigma"] = {"bias": [1e-4] * 3, "scale": [1e-5] * 3, "alpha": [1e-5] * 3, "xi": [1e-5] * 3}
    bad = tmp_path / "bad-init.json"
    bad.write_text(json.dumps(d))
    r = cli("replay", str(session["log"]), "--init", str(bad), "--json", str(tmp_path / "o.json"), "-q")
    h = json.loads((tmp_path / "o.json").read_text())["health"]
    assert r.returncode == {"ok": 0, "degraded": 4, "failed": 5}[h["verdict"]]
    assert f"health of the online calibration: {h['verdict']}" in r.stderr
    for reason in h["reasons"]:
        assert reason in r.stderr


def test_fifo_log_refused_at_once(tmp_path: Path) -> None:
    fifo = tmp_path / "pipe.tlog"
    os.mkfifo(fifo)
    t0 = time.monotonic()
    line = one_line(cli("batch", str(fifo), timeout=60))
    assert str(fifo) in line and "not a regular file" in line and time.monotonic() - t0 < 30


MARG = REPO.parent / "shared" / "data" / "marg-set1"


@pytest.mark.slow
@pytest.mark.skipif(not (MARG / "tilt-sphere.csv").is_file(), reason="measured data ../shared/data absent")
def test_issue_row_replay_tilt_sphere_is_not_trusted(tmp_path: Path) -> None:
    """`replay marg-set1/tilt-sphere.csv` printed gyro.scale.y 0.602 with no warning and exit 0, its JSON
    holding a magnetometer NIS mean of 60 589. Now its gyro scales are within 1 % of 1 (the batch of all 15 files:
    1.0016, 0.9988, 0.9982) and the verdict is not ok, with the reasons on stderr and in the JSON: degraded, exit 4
    (until session 17 failed, exit 5, on the accelerometer's gate rejecting 67 % of its updates: the platform model
    taking a hand's accelerations for gravity; the hand is now detected as a vehicle after 5 drops,
    tests/test_vehicle_handheld.py, and the magnetometer's NIS — 8× its expectation — and the rail remain)."""
    out = tmp_path / "t.json"
    r = cli("replay", str(MARG / "tilt-sphere.csv"), "--json", str(out), "-q", timeout=900)
    res = json.loads(out.read_text())
    h = res["health"]
    assert r.returncode == 4 and h["verdict"] == "degraded", r.stderr
    assert all(abs(s - 1.0) < 0.01 for s in res["gyro"]["scale"]), res["gyro"]["scale"]
    text = " | ".join(h["reasons"])
    assert "mag: mean NIS" in text and "rail" in text and "not to be trusted" in text, text
    assert "gate dropped" in res["meta"]["online"]["observability"]["vehicle"]["reason"]
    assert "health of the online calibration: degraded" in r.stderr


def test_diagnose_prints_estimated_parameters_and_gain() -> None:
    """`diagnose` printed the verdict but not the estimated value: each significant finding now has an
    `estimated:` line (its fitted parameters) and a `gain:` line."""
    from onlinecal.cli import _fmt_params

    assert _fmt_params({"sensor": "gyro", "coeff": [2e-4, -1e-4, 0.0], "seconds": 0.05}) == \
        "sensor=gyro, coeff=[ 0.0002, -0.0001,  0.    ], seconds=0.05"
    assert _fmt_params({"T0": float("nan")}) == "T0=nan"


@pytest.mark.parametrize("args", [["replay", "x.tlog", "--trace", "-"], ["replay", "x.tlog", "--report", "-"],
                                  ["demo", "--out", "-"]])
@pytest.mark.slow
def test_dash_where_a_file_is_needed(tmp_path: Path, args: list[str]) -> None:
    line = one_line(cli(*args, cwd=tmp_path))
    assert "-" in line and not (tmp_path / "-").exists()


@pytest.mark.parametrize("content", ["[1, 2]", "null", '{"schema": "onlinecal.live-checkpoint/1", "state": null}',
                                     '{"schema": "onlinecal.live-checkpoint/1"', "\x00\x01"])
@pytest.mark.slow
def test_run_resume_from_a_damaged_checkpoint(tmp_path: Path, content: str) -> None:
    ck = tmp_path / "run.ckpt"
    ck.write_text(content)
    line = one_line(cli("run", "--connect", "udpin:127.0.0.1:14998", "--checkpoint", str(ck), "--resume",
                        "--duration", "2", timeout=60))
    assert str(ck) in line and "checkpoint" in line, line
