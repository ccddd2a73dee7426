"""A fuzz test of the command line (issue 12 item 6): random commands, options and values, derandomised
(fixed seed), bounded in count and time. Every outcome must be a documented exit status with, for bad
input, one line on stderr — never a traceback, never the internal-error status 70."""

from __future__ import annotations

import random
import time

import pytest

from onlinecal.cli import EXIT_INTERNAL, main

DOCUMENTED = {0, 1, 2, 3, 4, 5}
NUMBERS = ["0", "-1", "-100", "1e309", "nan", "inf", "-inf", "abc", "", "1", "0.5", "3", "1e-9", "99999999999"]


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    d = tmp_path_factory.mktemp("fuzz")
    junk = d / "junk.tlog"
    junk.write_bytes(b"\x00\x01garbage" * 300)
    tiny = d / "tiny.csv"
    tiny.write_text("time_s,gyro_x,gyro_y,gyro_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z,temp_c\n"
                    + "".join(f"{i / 100},0,0,0,0,0,9.8,,,,25\n" for i in range(50)))
    badjson = d / "bad.json"
    badjson.write_text('{"schema": "onlinecal.calibration/1", "gyro": {"bias": [1, 2]}}')
    listjson = d / "list.json"
    listjson.write_text("[]")
    cal = d / "cal.json"
    cal.write_text('{"schema": "onlinecal.calibration/1", "gyro": {"bias": [0.01, 0, 0], '
                   '"matrix": [[1,0,0],[0,1,0],[0,0,1]]}, "accel": {"bias": [0.1, 0, 0]}}')
    folder = d / "folder"
    folder.mkdir()
    uni = d / "ünïcødé-σ.csv"
    uni.write_text(tiny.read_text())
    return {"junk": str(junk), "tiny": str(tiny), "badjson": str(badjson), "listjson": str(listjson),
            "cal": str(cal), "folder": str(folder), "uni": str(uni), "missing": str(d / "missing.tlog"),
            "out": str(d / "out"), "dir": str(d)}


def _case(rng: random.Random, f: dict[str, str], k: int) -> list[str]:
    """One random command line. Commands that would run a full fit or wait on a link get inputs that end
    them early (junk or tiny logs, a bad --init), so the budget goes to many cases."""
    logs = [f["junk"], f["tiny"], f["uni"], f["folder"], f["missing"]]
    cals = [f["badjson"], f["listjson"], f["cal"], f["folder"], f["missing"]]
    outs = ["-", "/nonexistent/x", "/proc/x", f["folder"], f"{f['out']}{k}.json", ""]
    def num() -> str:  # half the values valid, so the fuzz also reaches past the option checks
        return rng.choice(["1", "2.5", "9.81"]) if rng.random() < 0.5 else rng.choice(NUMBERS)

    def cal() -> str:
        return f["cal"] if rng.random() < 0.5 else rng.choice(cals)

    cmd = rng.choice(["simulate", "batch", "replay", "diagnose", "compare", "export", "demo", "run", "bogus"])
    a: list[str] = []
    if rng.random() < 0.2:
        a.append("--quiet")
    a.append(cmd)
    if cmd == "simulate":
        a += ["--out", rng.choice([f"{f['out']}{k}.tlog", f"{f['out']}{k}.csv", f"{f['out']}{k}.txt",
                                   "/nonexistent/d/x.tlog", f["folder"]])]
        a += ["--duration", rng.choice(["2", "0", "-5", "nan", "1e-3"])]
        for opt in rng.sample(["--rate", "--mag-rate", "--seed", "--profile", "--effect"], rng.randint(0, 3)):
            a += [opt, {"--profile": rng.choice(["paper", "flight", "boat"]),
                        "--effect": rng.choice(["bias_drift", "time_offset:seconds=x", "nope", "saturation"]),
                        "--seed": rng.choice(["1", "-1", "x"])}.get(opt, num())]
    elif cmd in ("batch", "replay", "diagnose"):
        a += rng.sample(logs, rng.randint(1, 2))
        for opt in rng.sample(["--json", "--gravity", "--acc-scale", "--report", "--init", "--jobs", "--trace"],
                              rng.randint(0, 3)):
            if opt in ("--init", "--jobs", "--trace") and cmd != "replay":
                continue
            a += [opt, {"--json": rng.choice(outs), "--report": rng.choice(outs),
                        "--trace": rng.choice(outs), "--init": rng.choice(["batch", "none", *cals])}.get(opt, num())]
    elif cmd == "compare":
        a += [cal(), cal()]
        if rng.random() < 0.5:
            a += [rng.choice(["--tol", "--abs-tol"]), num()]
    elif cmd == "export":
        a += [cal(), "--format", rng.choice(["ardupilot", "px4", "px4", "ardupilot", "betaflight"])]
        for opt in rng.sample(["--out", "--mag-unit", "--onboard", "--force"], rng.randint(0, 3)):
            a += {"--out": ["--out", rng.choice([*outs, "-", "-"])],
                  "--mag-unit": ["--mag-unit", rng.choice(["uT", "furlong"])],
                  "--onboard": ["--onboard", rng.choice([f["junk"], f["tiny"], f["missing"]])],
                  "--force": ["--force"]}[opt]
    elif cmd == "demo":
        a += ["--out", rng.choice([f["junk"], "/proc/x", ""]), "--seed", num()]  # never a full demo
    elif cmd == "run":
        a += ["--connect", rng.choice(["udpin:127.0.0.1:1", "nonsense://", "/dev/null"]),
              "--init", rng.choice(cals[:2] + cals[3:]), "--duration", num()]
    if rng.random() < 0.1:
        a.append(rng.choice(["--no-such-option", "--quiet", "-q"]))
    return a


def test_cli_fuzz_never_a_traceback(files: dict[str, str], capsys: pytest.CaptureFixture[str]) -> None:
    rng = random.Random(20261123)
    t0 = time.monotonic()
    seen: dict[int, int] = {}
    n = 0
    for k in range(80):
        if time.monotonic() - t0 > 150:  # bounded in time on a shared machine; the count is in the message
            break
        args = _case(rng, files, k)
        try:
            rc = main(args)
        except SystemExit as e:  # argparse: usage errors (2) and --help (0)
            rc = int(e.code or 0)
        out, err = capsys.readouterr()
        n += 1
        seen[rc] = seen.get(rc, 0) + 1
        assert "Traceback" not in err, (args, err)
        assert rc != EXIT_INTERNAL and rc in DOCUMENTED, (args, rc, err)
        if rc == 2:
            lines = [ln for ln in err.strip().splitlines() if not ln.startswith(("warning:", "health", "  "))]
            assert len(lines) == 1 and lines[0].startswith("onlinecal"), (args, err)
    assert n >= 30, f"only {n} cases in the time budget"
    assert seen.get(2, 0) > 0 and len(seen) >= 2, seen  # the fuzz reached both refusals and other outcomes
