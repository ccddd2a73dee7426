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
    from .sim.effects import EffectError, check_combination, parse_effect

    try:
        effects = [parse_effect(e) for e in a.effect]
        check_combination(effects)
        sim = simulate(a.profile, a.seed, a.duration, a.rate, a.mag_rate, effects=effects)
    except EffectError as e:  # the message names the spec and what is wrong with it
        raise UsageError(f"--effect: {e}") from e
    out = Path(a.out)
    if out.suffix not in (".tlog", ".csv", ".bin"):
        raise UsageError(f"{out}: extension must be .tlog, .csv or .bin")
    write_log(out, sim.data)
    sim.truth.save(str(out) + ".truth.json")
    print(f"wrote {out} ({sim.data.n_imu} IMU, {sim.data.n_mag} mag samples, {sim.data.duration:.1f} s) "
          f"and {out}.truth.json")
    return 0


def _report_dir(path: str) -> Path:
    p = Path(path)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UsageError(f"{path}: cannot create the report directory ({e.strerror or e})") from e
    return p


def cmd_batch(a: argparse.Namespace) -> int:
    from .batch import run_batch
    from .progress import stages
    from .report import truth_table, write_report

    report = _report_dir(a.report) if a.report else None
    steps = [f"read {Path(p).name}" for p in a.logs] + ["batch pipeline"] + (["report"] * 5 if report else [])
    with stages(steps, desc="batch") as st:
        logs = []
        for p in a.logs:
            st.next(f"read {Path(p).name}")
            logs += _read_logs([p], a)
        st.next("batch pipeline")
        t0 = time.perf_counter()
        res = run_batch(logs, g=a.gravity)
        dt = time.perf_counter() - t0
        written = write_report(report, logs, "batch", batch=res, g=a.gravity, progress=st) if report else []
    _warn(res.warnings)
    print(truth_table(None, res.calibration, None))
    print(f"batch pipeline: {sum(d.n_imu for d in logs)} IMU samples in {dt:.2f} s")
    return _wrote(res.calibration, a.json, report, written)


def _wrote(cal: Any, json_path: str | None, report: Any, written: list[str]) -> int:
    """Save ``cal`` to ``--json`` if asked, name the files written, exit 0 (batch and replay)."""
    if json_path:
        cal.save(json_path)
        print(f"wrote {json_path}")
    if report:
        print(f"wrote {report}/ ({', '.join(written)})")
    return 0


def _initial(a: argparse.Namespace, logs: list[Any]) -> tuple[Any, Any]:
    """The filter's start for ``--init``: (calibration or None, the BatchResult when it came from the batch)."""
    if a.init == "none":
        return None, None
    if a.init == "batch":
        from .batch import run_batch

        res = run_batch(logs)
        _warn(res.warnings)
        return res.calibration, res
    return _load_cal(a.init), None


def _ukf() -> Any:
    try:
        from . import ukf
    except ImportError as e:  # pragma: no cover - depends on the build
        raise Unavailable(f"the online filter is not available in this build ({e})") from e
    if not hasattr(ukf, "replay"):
        raise Unavailable("the online filter is not available in this build")
    return ukf


def cmd_replay(a: argparse.Namespace) -> int:
    if a.jobs is not None or a.executor != "process" or a.scheduler:
        return _replay_fleet(a)
    _ukf()
    import bisect
    import itertools

    from .fleet import replay_chunked
    from .progress import bar
    from .report import truth_table, write_report

    report = _report_dir(a.report) if a.report else None
    with bar(len(a.logs), desc="read", unit="logs") as pb:
        logs = []
        for p in a.logs:
            logs += _read_logs([p], a)
            pb.update()
    init, batch = _initial(a, logs)
    from .apply_ext import prepare

    try:
        logs, ext_notes = prepare(logs, init)
    except ValueError as e:
        raise UsageError(f"--init {a.init}: {e}") from None
    _warn(ext_notes)
    ends = list(itertools.accumulate(d.n_imu for d in logs))

    def show(i: int, n: int) -> None:
        k = min(bisect.bisect_right(ends, i), len(logs) - 1)
        pb.set(i, note=f"log {k + 1}/{len(logs)} {Path(logs[k].source).name}" if len(logs) > 1 else None)

    with bar(sum(d.n_imu for d in logs), desc="replay", unit="samples") as pb:
        res = replay_chunked(logs, init, trace_path=a.trace, on_progress=show)
    _warn(getattr(res, "warnings", []))
    if ext_notes and init is not None and not res.calibration.extensions:
        # the filter saw corrected data: its calibration holds together with the extensions it was given
        res.calibration = res.calibration.replace(extensions=init.extensions)
    written: list[str] = []
    if report:
        from .progress import stages

        with stages(["report"] * 9, desc="report") as st:
            written = write_report(report, logs, "replay", batch=batch, online=res,
                                   init=None if batch is not None else init, progress=st)
    print(truth_table(None, init, res.calibration))
    return _wrote(res.calibration, a.json, report, written)


def _replay_fleet(a: argparse.Namespace) -> int:
    """``replay --jobs N`` / ``--executor dask``: every log an independent unit (see onlinecal.fleet)."""
    import json

    from .fleet import DaskMissing, SchedulerUnreachable, fleet_summary, require_dask, run_fleet, summary_table
    from .progress import bar

    if a.executor == "dask":
        try:
            require_dask()
        except DaskMissing as e:
            raise Unavailable(str(e)) from e
    if a.report or a.trace:
        raise UsageError("--report and --trace belong to a single replay; with --jobs/--executor every log is "
                         "replayed on its own and reported as one JSON line (--json OUT)")
    if a.scheduler and a.executor != "dask":
        raise UsageError("--scheduler is the address of a dask scheduler: use it with --executor dask")
    init: Any = a.init if a.init in ("batch", "none") else _load_cal(a.init).to_dict()
    jobs = a.jobs if a.jobs is not None else 1
    to_stdout = a.json == "-"
    try:
        fh = sys.stdout if to_stdout else (open(a.json, "w") if a.json else None)
    except OSError as e:
        raise UsageError(f"{a.json}: cannot write ({e.strerror or e})") from e

    def on_record(rec: dict[str, Any]) -> None:
        if fh is not None:
            fh.write(json.dumps(rec, allow_nan=False) + "\n")
            fh.flush()

    try:
        with bar(len(a.logs), desc=f"replay ×{jobs} {a.executor}", unit="logs") as pb:
            recs = run_fleet(a.logs, init, jobs, a.executor, a.scheduler, _scales(a), on_record=on_record,
                             on_progress=lambda n, note: pb.set(n, note))
    except DaskMissing as e:
        raise Unavailable(str(e)) from e
    except SchedulerUnreachable as e:
        raise UsageError(str(e)) from e
    finally:
        if fh is not None and not to_stdout:
            fh.close()
    print(summary_table(fleet_summary(recs)), file=sys.stderr if to_stdout else sys.stdout)
    if a.json and not to_stdout:
        print(f"wrote {a.json} ({len(recs)} lines)")
    bad = [r for r in recs if not r["ok"]]
    for r in bad:
        print(f"onlinecal replay: {r['error']}", file=sys.stderr)
    return EXIT_INPUT if bad else 0


def cmd_run(a: argparse.Namespace) -> int:
    """The UKF on a live link (onlinecal.ukf.live_run): result JSON at the end, checkpoints, --apply.
    Exit 0; 1 when --apply could not confirm every parameter; 2 for unusable input."""
    ukf = _ukf()
    if not hasattr(ukf, "run_live"):
        raise Unavailable("live runs are not available in this build")
    if a.resume and not a.checkpoint:
        raise UsageError("--resume needs --checkpoint FILE")
    for opt, v in (("--checkpoint-every", a.checkpoint_every), ("--rate", a.rate)):
        if not v >= 0 or (opt == "--checkpoint-every" and v == 0):
            raise UsageError(f"{opt}: must be a positive number, got {v:g}")
    if a.duration is not None and not a.duration > 0:
        raise UsageError(f"--duration: must be a positive number of seconds, got {a.duration:g}")
    init = _load_cal(a.init) if a.init else None
    from .apply_ext import check_live, live_transform

    try:
        _warn(check_live(init))
    except ValueError as e:
        raise UsageError(f"--init {a.init}: {e}") from None
    try:
        res = ukf.run_live(a.connect, init, duration_s=a.duration, json_out=a.json, trace_out=a.trace,
                           checkpoint=a.checkpoint, checkpoint_every_s=a.checkpoint_every, resume=a.resume,
                           rate_hz=a.rate, apply=a.apply, transform=live_transform(init), **_scales(a))
        if init is not None and init.extensions and not res.calibration.extensions:
            res.calibration = res.calibration.replace(extensions=init.extensions)
            if a.json:
                res.calibration.save(a.json)
    except ImportError as e:
        raise Unavailable(str(e)) from e
    except OSError as e:  # the JSON, trace or checkpoint file cannot be written
        raise UsageError(f"{e.filename or '?'}: cannot write ({e.strerror or e})") from e
    from .report import truth_table

    _warn(res.warnings)
    print(truth_table(None, init, res.calibration))
    ln = res.link
    print(f"link: received {ln['received']}, lost {ln['lost']}, duplicates {ln['duplicates']}, "
          f"reordered {ln['reordered']}, late {ln['dropped_late']}, reconnects {ln['reconnects']}, "
          f"resumes {ln['resumes']}; ended: {res.stop_reason}")
    if res.missing_motion:
        print("still needed: " + "; ".join(res.missing_motion))
    if a.json:
        print(f"wrote {a.json}")
    if res.apply_error:
        print(f"onlinecal run: --apply: {res.apply_error}; nothing was set", file=sys.stderr)
        return 1
    if res.applied is not None:
        bad = res.apply_failed
        print(f"applied {len(res.applied) - len(bad)} of {len(res.applied)} {res.apply_format} parameters "
              "(each confirmed by the vehicle's PARAM_VALUE)")
        for n in bad:
            print(f"onlinecal run: {n} not confirmed: {res.applied[n]['why']}", file=sys.stderr)
        if bad:
            return 1
    return 0


def cmd_compare(a: argparse.Namespace) -> int:
    from .report import compare_text

    print(compare_text(_load_cal(a.a), _load_cal(a.b)))
    return 0


def cmd_demo(a: argparse.Namespace) -> int:
    from .demo import run_demo

    return run_demo(Path(a.out), a.seed)


def cmd_diagnose(a: argparse.Namespace) -> int:
    from .diagnose import diagnose

    logs = _read_logs(a.logs, a)
    diag = diagnose(logs, g=a.gravity, seed=a.seed,
                    calibration=_load_cal(a.init) if getattr(a, "init", None) else None)
    print(f"verdict: {diag.verdict}")
    for f in diag.findings:
        if f.significant:
            print(f"  {f.effect} ({f.sensor}{'/' + f.axis if f.axis else ''}): score {f.score:.1f} nats — {f.evidence}")
    for u in diag.untestable:
        print(f"  not testable: {u}")
    ub, ua = diag.baseline.get("ukf") or {}, diag.ukf_extended or {}
    if "nis_mean" in ub:
        print(f"  UKF NIS (window mean, expected 3): paper model {ub['nis_mean']:.3g}"
              + (f", extended {ua['nis_mean']:.3g}" if "nis_mean" in ua else ""))
    elif "error" in ub:
        print(f"  UKF stage: {ub['error']}")
    print(f"diagnose: {sum(d.n_imu for d in logs)} IMU samples in {diag.timing.get('total', 0):.1f} s")
    if a.json:
        diag.save(a.json)
        print(f"wrote {a.json}")
    if a.report:
        from .diagnose.report import write_report

        path = write_report(diag, Path(a.report))
        print(f"wrote {path}")
    return 0


def cmd_export(a: argparse.Namespace) -> int:
    import json

    from .export import ExportError, export_calibration, header_lines, render_parm, write_parm

    try:
        cal = _load_cal(a.cal)
    except OSError as e:
        raise UsageError(f"{a.cal}: cannot read ({e.strerror or e})") from e
    try:
        exp = export_calibration(cal, a.format, a.mag_unit)
    except ExportError as e:
        raise UsageError(f"{a.cal}: {e}") from e
    header = header_lines(exp, Path(a.cal).name)
    if a.out == "-":
        sys.stdout.write(render_parm(exp.params, exp.fmt, header, exp.types))
        _warn(exp.warnings)
        return 0
    out = Path(a.out) if a.out else Path(a.cal).with_suffix(".parm" if a.format == "ardupilot" else ".params")
    side = out.with_name(out.name + ".export.json")
    try:
        write_parm(exp.params, out, exp.fmt, header, exp.types)
        side.write_text(json.dumps(exp.report(), indent=2) + "\n")
    except OSError as e:
        raise UsageError(f"{out}: cannot write ({e.strerror or e})") from e
    _warn(exp.warnings)
    print(f"wrote {out} ({len(exp.params)} parameters) and {side}")
    return 0


# -- parser -----------------------------------------------------------------------------------------

def _add_scales(p: argparse.ArgumentParser) -> None:
    p.add_argument("--acc-scale", type=float, default=None, help="multiplier to m/s^2 (default: per format)")
    p.add_argument("--gyro-scale", type=float, default=None, help="multiplier to rad/s (default: per format)")
    p.add_argument("--mag-scale", type=float, default=None, help="multiplier for mag (default: per format)")


def _add_quiet(p: argparse.ArgumentParser) -> None:
    # SUPPRESS: given after the command it sets a.quiet; absent, the global flag's value stays
    p.add_argument("--quiet", "-q", action="store_true", default=argparse.SUPPRESS, help="no progress bars")


def _positive_int(s: str) -> int:
    try:
        n = int(s)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, not {s!r}")
    return n


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="onlinecal", description="Online IMU calibration (Zhang et al. 2014 + UKF)")
    ap.add_argument("--version", action="version", version=f"onlinecal {__version__}")
    ap.add_argument("--quiet", "-q", action="store_true",
                    help="no progress bars (they are also off when stderr is not a terminal)")
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
    p.add_argument("--report", default=None, metavar="DIR", help="write PNG figures and report.md into DIR")
    _add_quiet(p)
    _add_scales(p)
    p.set_defaults(fn=cmd_batch)

    p = sub.add_parser("replay", help="the augmented-state UKF over logs")
    p.add_argument("logs", nargs="+")
    p.add_argument("--init", default="batch", help="batch | none | CAL.json")
    p.add_argument("--json", default=None,
                   help="calibration JSON; with --jobs/--executor: JSON Lines, one object per log ('-': stdout)")
    p.add_argument("--trace", default=None)
    p.add_argument("--report", default=None, metavar="DIR", help="write PNG figures and report.md into DIR")
    p.add_argument("--jobs", type=_positive_int, default=None, metavar="N",
                   help="fleet mode: every log an independent unit, N in parallel (one JSON line per log)")
    p.add_argument("--executor", choices=["process", "dask"], default="process",
                   help="fleet mode on local processes or on dask.distributed (extra onlinecal[dask])")
    p.add_argument("--scheduler", default=None, metavar="ADDR",
                   help="dask scheduler address (default: a LocalCluster of --jobs workers)")
    _add_quiet(p)
    _add_scales(p)
    p.set_defaults(fn=cmd_replay)

    p = sub.add_parser("run", help="the UKF on a live MAVLink link (docs/live.md)")
    p.add_argument("--connect", required=True, metavar="URL",
                   help="pymavlink connection: udpin:0.0.0.0:14550, tcp:127.0.0.1:5760, /dev/ttyACM0,115200")
    p.add_argument("--init", default=None, metavar="CAL.json", help="start calibration (default: cold start)")
    p.add_argument("--json", default=None, metavar="OUT", help="calibration JSON written at the end")
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="s of vehicle time from the first sample (default: until Ctrl-C)")
    p.add_argument("--trace", default=None, metavar="OUT.csv", help="trace CSV, appended as the run goes")
    p.add_argument("--checkpoint", default=None, metavar="FILE", help="write the run's state there")
    p.add_argument("--checkpoint-every", type=float, default=10.0, metavar="S",
                   help="wall seconds between checkpoints (default 10)")
    p.add_argument("--resume", action="store_true", help="continue from --checkpoint FILE")
    p.add_argument("--rate", type=float, default=100.0, metavar="HZ",
                   help="RAW_IMU rate asked of the vehicle (SET_MESSAGE_INTERVAL; 0: ask nothing; default 100)")
    p.add_argument("--apply", choices=["ardupilot", "px4"], default=None,
                   help="afterwards, set the calibration as vehicle parameters (PARAM_SET, each confirmed)")
    _add_scales(p)
    p.set_defaults(fn=cmd_run)

    p = sub.add_parser("compare", help="parameter-by-parameter difference of two calibrations")
    p.add_argument("a")
    p.add_argument("b")
    p.set_defaults(fn=cmd_compare)

    p = sub.add_parser("diagnose", help="what the model gets wrong on this data, the cause, the extended model")
    p.add_argument("logs", nargs="+")
    p.add_argument("--json", default=None)
    p.add_argument("--report", default=None, help="directory for report.md and plots")
    p.add_argument("--gravity", type=float, default=9.80665, help="local g, m/s^2")
    p.add_argument("--seed", type=int, default=0, help="seed of the re-simulation's noise")
    p.add_argument("--init", default=None, metavar="CAL.json",
                   help="baseline calibration (e.g. a bench calibration) instead of the batch fit on these logs")
    _add_scales(p)
    p.set_defaults(fn=cmd_diagnose)

    p = sub.add_parser("export", help="vehicle parameters (ArduPilot .parm, PX4/QGroundControl .params)")
    p.add_argument("cal")
    p.add_argument("--format", choices=["ardupilot", "px4"], required=True)
    p.add_argument("--out", default=None,
                   help="parameter file (default CAL.parm / CAL.params beside CAL.json; '-' for stdout)")
    p.add_argument("--mag-unit", choices=["gauss", "mgauss", "uT", "nT", "T"], default="gauss",
                   help="unit of the raw magnetometer values the calibration was fitted on (default gauss: "
                        "what the .tlog and .bin readers produce)")
    p.set_defaults(fn=cmd_export)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    from .batch.ellipsoid import FitError
    from .io.base import LogError

    a = build_parser().parse_args(argv)
    from .progress import set_quiet

    set_quiet(getattr(a, "quiet", False))
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
