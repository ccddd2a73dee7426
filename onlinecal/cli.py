"""The ``onlinecal`` command (contract: shared/spec/contract.md).

Every command turns unusable input into one line on stderr and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from . import __version__

EXIT_INPUT = 2
EXIT_UNAVAILABLE = 3


class UsageError(Exception):
    """Unusable input that is not a log (a calibration file, an option)."""


class Unavailable(Exception):
    """A command or option this version does not have yet; says so instead of a made-up answer."""


def _scales(a: argparse.Namespace) -> dict[str, float | None]:
    return {"acc_scale": a.acc_scale, "gyro_scale": a.gyro_scale, "mag_scale": a.mag_scale}


def _read_logs(paths: Sequence[str], a: argparse.Namespace) -> list[Any]:
    from .io import read_log

    return [read_log(p, **_scales(a)) for p in paths]


def _load_cal(path: str) -> Any:
    from .model import Calibration

    try:
        return Calibration.load(path)
    except FileNotFoundError as e:
        raise UsageError(f"{path}: no such file") from e
    except (ValueError, KeyError, TypeError) as e:
        raise UsageError(f"{path}: not a calibration JSON ({e})") from e


def _warn(msgs: Sequence[str]) -> None:
    for m in msgs:
        print(f"warning: {m}", file=sys.stderr)


# -- commands ---------------------------------------------------------------------------------------

def cmd_simulate(a: argparse.Namespace) -> int:
    from .io import write_log
    from .sim import simulate
    from .sim.effects import EffectError, parse_effect

    try:
        effects = [parse_effect(e) for e in a.effect]
    except EffectError as e:
        raise Unavailable(str(e)) from e
    sim = simulate(a.profile, a.seed, a.duration, a.rate, a.mag_rate, effects=effects)
    out = Path(a.out)
    if out.suffix not in (".tlog", ".csv", ".bin"):
        raise UsageError(f"{out}: extension must be .tlog, .csv or .bin")
    write_log(out, sim.data)
    sim.truth.save(str(out) + ".truth.json")
    print(f"wrote {out} ({sim.data.n_imu} IMU, {sim.data.n_mag} mag samples, {sim.data.duration:.1f} s) "
          f"and {out}.truth.json")
    return 0


def cmd_batch(a: argparse.Namespace) -> int:
    from .batch import run_batch
    from .report import truth_table

    logs = _read_logs(a.logs, a)
    t0 = time.perf_counter()
    res = run_batch(logs, g=a.gravity)
    dt = time.perf_counter() - t0
    _warn(res.warnings)
    print(truth_table(None, res.calibration, None))
    print(f"batch pipeline: {sum(d.n_imu for d in logs)} IMU samples in {dt:.2f} s")
    if a.json:
        res.calibration.save(a.json)
        print(f"wrote {a.json}")
    return 0


def _initial(a: argparse.Namespace, logs: list[Any]) -> Any:
    if a.init == "none":
        return None
    if a.init == "batch":
        from .batch import run_batch

        res = run_batch(logs)
        _warn(res.warnings)
        return res.calibration
    return _load_cal(a.init)


def _ukf() -> Any:
    try:
        from . import ukf
    except ImportError as e:  # pragma: no cover - depends on the build
        raise Unavailable(f"the online filter is not available in this build ({e})") from e
    if not hasattr(ukf, "replay"):
        raise Unavailable("the online filter is not available in this build")
    return ukf


def cmd_replay(a: argparse.Namespace) -> int:
    ukf = _ukf()
    logs = _read_logs(a.logs, a)
    init = _initial(a, logs)
    res = ukf.replay(logs, init, trace_path=a.trace)
    _warn(getattr(res, "warnings", []))
    from .report import truth_table

    print(truth_table(None, init, res.calibration))
    if a.json:
        res.calibration.save(a.json)
        print(f"wrote {a.json}")
    return 0


def cmd_run(a: argparse.Namespace) -> int:
    ukf = _ukf()
    if not hasattr(ukf, "run_live"):
        raise Unavailable("live runs are not available in this build")
    init = _load_cal(a.init) if a.init else None
    res = ukf.run_live(a.connect, init, duration_s=a.duration, json_out=a.json, **_scales(a))
    from .report import truth_table

    print(truth_table(None, init, res.calibration))
    if a.json:
        res.calibration.save(a.json)
    return 0


def cmd_compare(a: argparse.Namespace) -> int:
    from .report import compare_text

    print(compare_text(_load_cal(a.a), _load_cal(a.b)))
    return 0


def cmd_demo(a: argparse.Namespace) -> int:
    from .demo import run_demo

    return run_demo(Path(a.out), a.seed)


def cmd_diagnose(a: argparse.Namespace) -> int:
    raise Unavailable("diagnose is not implemented in this version (model-discrepancy discovery is "
                      "planned); no diagnosis was written")


def cmd_export(a: argparse.Namespace) -> int:
    raise Unavailable("export is not implemented in this version; no parameter file was written")


# -- parser -----------------------------------------------------------------------------------------

def _add_scales(p: argparse.ArgumentParser) -> None:
    p.add_argument("--acc-scale", type=float, default=None, help="multiplier to m/s^2 (default: per format)")
    p.add_argument("--gyro-scale", type=float, default=None, help="multiplier to rad/s (default: per format)")
    p.add_argument("--mag-scale", type=float, default=None, help="multiplier for mag (default: per format)")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="onlinecal", description="Online IMU calibration (Zhang et al. 2014 + UKF)")
    ap.add_argument("--version", action="version", version=f"onlinecal {__version__}")
    sub = ap.add_subparsers(dest="cmd", required=True)

    p = sub.add_parser("demo", help="simulate, calibrate (batch + online), compare with truth")
    p.add_argument("--out", default="onlinecal-demo")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(fn=cmd_demo)

    p = sub.add_parser("simulate", help="write a simulated session (.tlog/.csv/.bin) and its truth")
    p.add_argument("--out", required=True)
    p.add_argument("--profile", choices=["paper", "flight"], default="paper")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--duration", type=float, default=None)
    p.add_argument("--rate", type=float, default=100.0, help="IMU rate, Hz")
    p.add_argument("--mag-rate", type=float, default=50.0, help="magnetometer rate, Hz")
    p.add_argument("--effect", action="append", default=[], help="NAME[:key=value,...] (repeatable)")
    p.set_defaults(fn=cmd_simulate)

    p = sub.add_parser("batch", help="the paper's offline pipeline over logs of one sensor unit")
    p.add_argument("logs", nargs="+")
    p.add_argument("--json", default=None)
    p.add_argument("--gravity", type=float, default=9.80665, help="local g, m/s^2")
    _add_scales(p)
    p.set_defaults(fn=cmd_batch)

    p = sub.add_parser("replay", help="the augmented-state UKF over logs")
    p.add_argument("logs", nargs="+")
    p.add_argument("--init", default="batch", help="batch | none | CAL.json")
    p.add_argument("--json", default=None)
    p.add_argument("--trace", default=None)
    _add_scales(p)
    p.set_defaults(fn=cmd_replay)

    p = sub.add_parser("run", help="the UKF on a live MAVLink link")
    p.add_argument("--connect", required=True)
    p.add_argument("--init", default=None)
    p.add_argument("--json", default=None)
    p.add_argument("--duration", type=float, default=None)
    _add_scales(p)
    p.set_defaults(fn=cmd_run)

    p = sub.add_parser("compare", help="parameter-by-parameter difference of two calibrations")
    p.add_argument("a")
    p.add_argument("b")
    p.set_defaults(fn=cmd_compare)

    p = sub.add_parser("diagnose", help="what the model gets wrong on this data (not yet available)")
    p.add_argument("logs", nargs="+")
    p.add_argument("--json", default=None)
    p.add_argument("--report", default=None)
    p.set_defaults(fn=cmd_diagnose)

    p = sub.add_parser("export", help="vehicle parameters (not yet available)")
    p.add_argument("cal")
    p.add_argument("--format", choices=["ardupilot", "px4"], required=True)
    p.add_argument("--out", default=None)
    p.set_defaults(fn=cmd_export)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    from .batch.ellipsoid import FitError
    from .io.base import LogError

    a = build_parser().parse_args(argv)
    try:
        return int(a.fn(a))
    except (LogError, UsageError) as e:
        print(f"onlinecal {a.cmd}: {e}", file=sys.stderr)
        return EXIT_INPUT
    except FitError as e:
        print(f"onlinecal {a.cmd}: {', '.join(getattr(a, 'logs', []) or [])}: too little usable data: {e}",
              file=sys.stderr)
        return EXIT_INPUT
    except Unavailable as e:
        print(f"onlinecal {a.cmd}: {e}", file=sys.stderr)
        return EXIT_UNAVAILABLE
    except KeyboardInterrupt:
        print(f"onlinecal {a.cmd}: interrupted", file=sys.stderr)
        return 130
