"""The ``onlinecal`` command (contract: shared/spec/contract.md).

Every command turns unusable input into one line on stderr and exit status 2, never a traceback. Outputs
are checked before the work starts, written atomically (:mod:`onlinecal.files`), strict JSON, and ``-``
means stdout for every JSON output (the human-readable text then goes to stderr).

Exit status (also in ``onlinecal --help`` and the README): 0 the result is healthy; 1 ``compare --tol``
found a difference beyond the tolerance, or ``run --apply`` could not confirm every parameter; 2 unusable
input (a log, a calibration file, an option, an output path); 3 an optional component is missing; 4 the
result is *degraded* and 5 it *failed* its health check (:mod:`onlinecal.health`; the reasons are printed
and stored under ``"health"`` in the JSON; ``export`` returns 4 when it withheld a parameter); 70 an
internal error (a bug, said in one line); 130 interrupted.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

from . import __version__

EXIT_DIFFER = 1
EXIT_INPUT = 2
EXIT_UNAVAILABLE = 3
EXIT_DEGRADED = 4
EXIT_FAILED = 5
EXIT_INTERNAL = 70  # EX_SOFTWARE: a bug, said in one line (never expected; the fuzz test asserts it)
EXIT_STATUS_TEXT = (
    "exit status: 0 healthy result; 1 compare --tol beyond tolerance, or run --apply not confirmed; "
    "2 unusable input (log, calibration file, option, output path); 3 optional component missing; "
    "4 result degraded (export: a parameter withheld); 5 result failed its health check (reasons printed and "
    "in the JSON's \"health\"); 70 internal error (a bug); 130 interrupted"
)


class UsageError(Exception):
    """Unusable input that is not a log (a calibration file, an option)."""


class Unavailable(Exception):
    """A command or option this version does not have yet; says so instead of a made-up answer."""


def _scales(a: argparse.Namespace) -> dict[str, Any]:
    # --imu (helper io): the IMU instance, passed to every reader and to the live source with the scales
    return {"acc_scale": a.acc_scale, "gyro_scale": a.gyro_scale, "mag_scale": a.mag_scale,
            "imu": getattr(a, "imu", 0)}


def _check_regular(p: str) -> None:
    import stat

    try:
        mode = os.stat(p).st_mode
    except OSError:
        return  # missing: the reader's own one-line message
    if stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode) or stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        # a FIFO or device never ends: reading it would hang instead of refusing it
        raise UsageError(f"{p}: not a regular file (a FIFO, socket or device); give a log file")


def _read_logs(paths: Sequence[str], a: argparse.Namespace) -> list[Any]:
    from .io import read_log

    for p in paths:
        _check_regular(p)
    return [read_log(p, **_scales(a)) for p in paths]


def _read_for_batch(paths: Sequence[str], a: argparse.Namespace) -> tuple[list[Any], list[Any]]:
    """The logs for the batch in bounded memory (onlinecal.batch.reduce, issue 16.5): a log over the budget
    becomes its kept stretches. Returns (logs, the reductions made)."""
    from .batch.reduce import read_reduced

    logs: list[Any] = []
    reds: list[Any] = []
    for p in paths:
        _check_regular(p)
        got, red = read_reduced(p, **_scales(a))
        logs += got
        reds += [red] if red is not None else []
    return logs, reds


def _load_cal(path: str) -> Any:
    """A validated calibration (or simulator truth) file; one line naming the file and field otherwise."""
    from .calfile import CalFileError, load_calibration

    try:
        return load_calibration(path)
    except CalFileError as e:
        raise UsageError(str(e)) from None


def _warn(msgs: Sequence[str]) -> None:
    for m in msgs:
        print(f"warning: {m}", file=sys.stderr)


def _check_out(path: str | None, option: str, *, directory: bool = False, exist_ok: bool = True,
               dash: bool = True) -> None:
    """Refuse an output that cannot be written, before any work (one line naming option and path).
    ``dash``: ``-`` (stdout) is accepted (every JSON output); a trace or checkpoint needs a file."""
    from .files import OutputError, check_output_dir, check_output_file

    if path == "-" and not dash:
        raise UsageError(f"{option} -: this output cannot go to stdout; give a file name")
    try:
        if directory:
            check_output_dir(path, option)
        else:
            check_output_file(path, option, exist_ok=exist_ok)
    except OutputError as e:
        raise UsageError(str(e)) from None


def _human(json_path: str | None) -> Any:
    """Where the human-readable text goes: stderr when the JSON goes to stdout (``--json -``)."""
    return sys.stderr if json_path == "-" else sys.stdout


def _save_result(cal: Any, health: dict[str, Any] | None, path: str) -> None:
    """Write ``cal`` as strict JSON with its health verdict (the calibration's typed ``health`` field)."""
    from .files import OutputError, write_json

    if health is not None:
        cal = cal.replace(health=health)
    obj = cal.to_dict()
    try:
        write_json(path, obj)
    except OutputError as e:
        raise UsageError(str(e)) from None


def _show_health(health: dict[str, Any], what: str) -> int:
    """Print the verdict (stderr: it is a diagnostic) and return its exit status."""
    from .health import exit_status

    print(f"health of the {what}: {health['verdict']}", file=sys.stderr)
    for r in health.get("reasons", []):
        print(f"  - {r}", file=sys.stderr)
    und = health.get("checks", {}).get("undetermined") or []
    if und:
        print(f"  note: not determined by the data (start value kept, σ wide): {', '.join(und)}", file=sys.stderr)
    return exit_status(health)


def _raw(logs: Sequence[Any] | None) -> dict[str, Any] | None:
    """Raw gyro and accel samples of the logs, for the health verdict's rail (saturation) check."""
    import numpy as np

    logs = [d for d in (logs or []) if getattr(d, "n_imu", 0)]
    if not logs:
        return None
    return {"gyro": np.concatenate([d.gyro for d in logs]), "accel": np.concatenate([d.acc for d in logs])}


def _mag_raw(logs: Sequence[Any]) -> Any:
    import numpy as np

    mags = [d.mag for d in logs if getattr(d, "n_mag", 0)]
    return np.concatenate(mags) if mags else None


# -- commands ---------------------------------------------------------------------------------------

def cmd_simulate(a: argparse.Namespace) -> int:
    from .io import write_log
    from .sim import ProfileError, simulate
    from .sim.effects import EffectError, check_combination, parse_effect

    out = Path(a.out)
    if out.suffix not in (".tlog", ".csv", ".bin", ".ulg"):
        raise UsageError(f"{out}: extension must be .tlog, .csv, .bin or .ulg")
    _check_out(a.out, "--out")
    _check_out(str(out) + ".truth.json", "--out")
    try:
        effects = [parse_effect(e) for e in a.effect]
        check_combination(effects)
        lat = {} if a.latitude is None else ({"earth_rate": False} if a.latitude == "none" else
                                              {"earth_rate": True, "latitude": a.latitude})
        if a.gps and out.suffix == ".csv":
            raise UsageError("--gps: a CSV log has no position columns; write .bin, .tlog or .ulg")
        sim = simulate(a.profile, a.seed, a.duration, a.rate, a.mag_rate, effects=effects, **lat,
                       declination=a.declination, gps=a.gps)
    except EffectError as e:  # the message names the spec and what is wrong with it
        raise UsageError(f"--effect: {e}") from e
    except ProfileError as e:
        raise UsageError(f"--profile: {e}") from e
    if sim.data.n_imu == 0:
        raise UsageError(f"--duration {a.duration:g} at --rate {a.rate:g} Hz gives no IMU sample")
    try:
        write_log(out, sim.data)
        sim.truth.save(str(out) + ".truth.json")
    except OSError as e:
        raise UsageError(f"{e.filename or out}: cannot write ({e.strerror or e})") from None
    print(f"wrote {out} ({sim.data.n_imu} IMU, {sim.data.n_mag} mag samples, {sim.data.duration:.1f} s) "
          f"and {out}.truth.json")
    return 0


def _print_observability(cal: Any, out: Any = None) -> None:
    """What the data determined and what not, in words (meta.online.observability, issue 10), to ``out``
    (stdout by default; stderr when the JSON goes to stdout)."""
    from .ukf.vehicle import observability_text

    rep = (cal.meta or {}).get("online", {}).get("observability")
    if rep:
        for line in observability_text(rep):
            print(line, file=out or sys.stdout)


def _report_dir(path: str) -> Path:
    p = Path(path)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UsageError(f"{path}: cannot create the report directory ({e.strerror or e})") from e
    return p


def cmd_batch(a: argparse.Namespace) -> int:
    from .batch import run_batch
    from .health import assess
    from .progress import stages
    from .report import truth_table, write_report

    _check_out(a.json, "--json")
    _check_out(a.report, "--report", directory=True)
    _latitude_deg(a)  # the logs' GPS read (its line printed) before the work starts
    report = _report_dir(a.report) if a.report else None
    steps = [f"read {Path(p).name}" for p in a.logs] + ["batch pipeline"] + (["report"] * 5 if report else [])
    with stages(steps, desc="batch") as st:
        logs, reds = [], []
        for p in a.logs:
            st.next(f"read {Path(p).name}")
            if report:
                logs += _read_logs([p], a)  # the report plots whole logs
            else:
                got, red = _read_for_batch([p], a)
                logs += got
                reds += red
        st.next("batch pipeline")
        t0 = time.perf_counter()
        res = run_batch(logs, g=a.gravity, reduced=reds, latitude_deg=_latitude_deg(a))
        dt = time.perf_counter() - t0
        written = write_report(report, logs, "batch", batch=res, g=a.gravity, progress=st) if report else []
    _warn(res.warnings)
    health = assess(res.calibration, mag_raw=_mag_raw(logs), raw=_raw(logs))
    out = _human(a.json)
    print(truth_table(None, res.calibration, None), file=out)
    print(f"batch pipeline: {sum(d.n_imu for d in logs)} IMU samples in {dt:.2f} s", file=out)
    _wrote(res.calibration, health, a.json, report, written)
    return _show_health(health, "batch calibration")


def _wrote(cal: Any, health: dict[str, Any] | None, json_path: str | None, report: Any, written: list[str]) -> None:
    """Save ``cal`` (with its health) to ``--json`` if asked and name the files written (batch and replay)."""
    out = _human(json_path)
    if json_path:
        _save_result(cal, health, json_path)
        if json_path != "-":
            print(f"wrote {json_path}", file=out)
    if report:
        print(f"wrote {report}/ ({', '.join(written)})", file=out)


def _initial(a: argparse.Namespace, logs: list[Any]) -> tuple[Any, Any]:
    """The filter's start for ``--init``: (calibration or None, the BatchResult when it came from the batch)."""
    if a.init == "none":
        return None, None
    if a.init == "batch":
        from .batch import run_batch
        from .health import filter_start
        from .progress import spinner

        with spinner("batch (the filter's start)"):
            res = run_batch(logs, latitude_deg=_latitude_deg(a))
        _warn(res.warnings)
        start, notes = filter_start(res.calibration, _mag_raw(logs))
        _warn(notes)
        return start, res
    return _load_cal(a.init), None


def _ukf() -> Any:
    try:
        from . import ukf
    except ImportError as e:  # pragma: no cover - depends on the build
        raise Unavailable(f"the online filter is not available in this build ({e})") from e
    if not hasattr(ukf, "replay"):
        raise Unavailable("the online filter is not available in this build")
    return ukf


def _warm_kernels() -> None:
    """Start compiling the filter's kernels in worker processes where numba's cache does not hold them yet
    (onlinecal.ukf.warmup: a first run), so that it overlaps what the command does before the filter runs —
    the batch, reading the logs, waiting for the link. Called once the command's input has been accepted."""
    from .ukf import warmup

    warmup.start()


def online_health(res: Any, logs: Sequence[Any] | None = None, mag_start: str | None = None,
                  start: Any = None, digest: Any = None) -> dict[str, Any]:
    """Health of an online result (replay, run, fleet): NIS, events, observability, ranges, mag coverage.
    ``mag_start``: "file" (started from a calibration file), "batch" (from the batch of these logs), None;
    ``start``: that calibration, for the cross-check (onlinecal.health.start_checks); ``digest``: the raw
    samples' :class:`onlinecal.health.RawDigest` where they were streamed (gravity at rest and the rail read
    from it instead of ``logs``)."""
    from .health import assess

    return assess(res.calibration, events=getattr(res, "events", None), nis=getattr(res, "nis", None),
                  observability=getattr(res, "observability", None),
                  mag_raw=_mag_raw(logs) if logs else None, raw=digest if digest is not None else _raw(logs),
                  mag_start=mag_start, start=start)


def cmd_replay(a: argparse.Namespace) -> int:
    if a.jobs is not None or a.executor != "process" or a.scheduler:
        return _replay_fleet(a)
    _ukf()
    import bisect
    import itertools

    from .fleet import replay_chunked
    from .progress import bar
    from .report import write_report

    if a.init not in ("batch", "none"):
        _load_cal(a.init)  # a bad --init file is refused before the logs are read
    _check_out(a.json, "--json")
    _check_out(a.trace, "--trace", dash=False)
    _check_out(a.report, "--report", directory=True)
    _ukf_config(a)  # the logs' GPS read, --declination without a latitude refused, before the logs are read
    report = _report_dir(a.report) if a.report else None
    if report is None:
        # helper io: constant memory in the logs' length; the batch start on the logs' reduced stretches
        streamed = _replay_streamed(a)
        if streamed is not None:
            return streamed
    with bar(len(a.logs), desc="read", unit="logs") as pb:
        logs = []
        for p in a.logs:
            logs += _read_logs([p], a)
            pb.update()
    from .batch.clock import regularise_for_filter

    # the filter's clock, said once (the batch and the replay then see sample times)
    fixed = [regularise_for_filter(d) for d in logs]
    logs = [d for d, _ in fixed]
    _warn([n for _, notes in fixed for n in notes])
    _warm_kernels()
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
        try:
            res = replay_chunked(logs, init, trace_path=a.trace, on_progress=show, config=_ukf_config(a))
        except OSError as e:  # the trace file went away under us
            raise UsageError(f"{e.filename or a.trace}: cannot write ({e.strerror or e})") from None
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
    return _replay_result(a, res, init, "init" if batch is None else "batch", logs, report, written)


def _replay_streamed(a: argparse.Namespace) -> int | None:
    """``replay`` without the batch step (helper io): every log streamed block by block through the filter
    (onlinecal.ukf.replay.replay_stream), so memory does not grow with the logs' length. None when the start
    calibration carries extensions that need whole logs (the caller then reads them whole)."""
    from .batch.clock import ReclockedReader
    from .health import RawDigest
    from .io import open_log
    from .progress import bar
    from .ukf.replay import replay_stream

    # every file checked before the work starts; burst-read stamps replaced by a fitted clock as the batch does
    readers = [ReclockedReader(open_log(p, **_scales(a))) for p in a.logs]
    _warm_kernels()
    label, logs, init = "init", None, None
    bres_warnings: list[str] = []
    if a.init == "batch":
        from .batch import run_batch
        from .health import filter_start
        from .progress import spinner

        with spinner("batch (the filter's start)"):
            logs, reds = _read_for_batch(a.logs, a)
            bres = run_batch(logs, reduced=reds, latitude_deg=_latitude_deg(a))
        _warn(bres.warnings)
        bres_warnings = list(bres.warnings)
        init, notes = filter_start(bres.calibration, _mag_raw(logs))
        _warn(notes)
        del bres
        label = "batch"  # the kept stretches (the whole of a short log) serve the health verdict
    elif a.init != "none":
        init = _load_cal(a.init)
    if init is not None and init.extensions:
        return None
    from .fleet import REPLAY_CHUNK

    with bar(None, desc="replay", unit="samples") as pb:
        def show(i: int, n: int) -> None:
            pb.set(i)

        digest = RawDigest()  # what the health verdict reads of the samples (gravity at rest, the rail)

        def tapped(blocks: Iterable[Any]) -> Iterator[Any]:
            digest.new_log()
            for blk in blocks:
                digest.add(blk.gyro, blk.acc)
                yield blk

        res = replay_stream((tapped(r.blocks(REPLAY_CHUNK)) for r in readers), init, chunk=REPLAY_CHUNK,
                            trace_path=a.trace, on_progress=show, config=_ukf_config(a))
    said = set(bres_warnings)
    for r in readers:
        # the clock's sentences name the file already (the batch start said them too: not twice)
        _warn([f"{r.path}: {w}" for w in r.warnings if w not in r.notes] + [w for w in r.notes if w not in said])
    _warn(res.warnings)
    return _replay_result(a, res, init, label, logs, None, [], digest)


def _replay_result(a: argparse.Namespace, res: Any, start: Any, label: str, logs: Sequence[Any] | None,
                   report: Any, written: list[str], digest: Any = None) -> int:
    """The end of every ``replay`` (whole logs or streamed): health verdict, start · online table, what the
    data did not determine, the files written; the exit status by the verdict. ``digest``: the streamed logs'
    :class:`onlinecal.health.RawDigest` (every sample, where ``logs`` are the batch's kept stretches or none)."""
    from .report import truth_table

    health = online_health(res, logs, None if start is None else ("batch" if label == "batch" else "file"), start,
                           digest)
    print(truth_table(None, start, res.calibration, labels=(label, "online")), file=_human(a.json))
    _print_observability(res.calibration, _human(a.json))
    _wrote(res.calibration, health, a.json, report, written)
    return _show_health(health, "online calibration")


# s of IMU data a live run holds back waiting for the vehicle's GPS fix before its filter starts (run without
# --latitude): a vehicle that has a fix streams GPS_RAW_INT at ≥ 1 Hz; one without costs a 3-s later start
LIVE_GPS_WAIT_S = 3.0


def _latitude_deg(a: argparse.Namespace) -> float | None:
    """The latitude the command is told (``--latitude``, or the logs' GPS: :func:`_ukf_config`), or None: the
    batch takes the Earth rotation's vertical part out of its gyro bias with it."""
    config = _ukf_config(a)
    return None if config is None else config.latitude_deg


def _ukf_config(a: argparse.Namespace) -> Any:
    """The filter's configuration from the command line, or None for the defaults: ``--latitude DEG``, else
    (replay) the logs' GPS with the World Magnetic Model's declination there (onlinecal.place; ``--latitude
    none`` turns that off), ``--declination``. Decided once per command (the GPS read once, its lines printed
    once)."""
    cached = getattr(a, "_ukf_config_made", None)
    if cached is not None:
        return cached[0]
    from .place import TAKEN_OUT, TAKEN_OUT_BATCH, earth_rate_config, told_line

    try:
        config, source, declination_line, warnings = earth_rate_config(
            getattr(a, "latitude", None), getattr(a, "declination", None), list(getattr(a, "logs", None) or []))
    except ValueError as e:
        raise UsageError(str(e)) from None
    _warn(warnings)
    batch = not hasattr(a, "declination")  # batch: the vertical part of the rests' bias; no declination
    if source is not None:
        effect = TAKEN_OUT_BATCH if batch else TAKEN_OUT
        print(f"onlinecal: {told_line(config.latitude_deg, source, effect)}", file=sys.stderr)
    if declination_line is not None and not batch:
        print(f"onlinecal: {declination_line}", file=sys.stderr)
    a._ukf_config_made = (config,)
    return config


def _replay_fleet(a: argparse.Namespace) -> int:
    """``replay --jobs N`` / ``--executor dask``: every log an independent unit (see onlinecal.fleet)."""
    from .files import dumps
    from .fleet import DaskMissing, SchedulerUnreachable, fleet_summary, require_dask, run_fleet, summary_table
    from .health import EXIT_STATUS, combine
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
    if (a.latitude is not None and a.latitude != "none") or a.declination is not None:
        raise UsageError("--latitude DEG and --declination belong to a single replay or run (the logs of a fleet "
                         "are anywhere: each is told its own GPS fix's latitude; --latitude none turns that off)")
    init: Any = a.init if a.init in ("batch", "none") else _load_cal(a.init).to_dict()
    _check_out(a.json, "--json")
    jobs = a.jobs if a.jobs is not None else 1
    to_stdout = a.json == "-"
    lines: list[str] = []

    def on_record(rec: dict[str, Any]) -> None:
        line = dumps(rec, indent=None)
        if to_stdout:
            sys.stdout.write(line + "\n")
            sys.stdout.flush()
        else:
            lines.append(line)

    try:
        with bar(len(a.logs), desc=f"replay ×{jobs} {a.executor}", unit="logs") as pb:
            recs = run_fleet(a.logs, init, jobs, a.executor, a.scheduler, _scales(a), on_record=on_record,
                             on_progress=lambda n, note: pb.set(n, note), gps=a.latitude != "none")
    except DaskMissing as e:
        raise Unavailable(str(e)) from e
    except SchedulerUnreachable as e:
        raise UsageError(str(e)) from e
    finally:
        if a.json and not to_stdout and lines:
            from .files import OutputError, atomic_write

            try:
                atomic_write(a.json, "\n".join(lines) + "\n")
            except OutputError as e:
                raise UsageError(str(e)) from None
    print(summary_table(fleet_summary(recs)), file=sys.stderr if to_stdout else sys.stdout)
    if a.json and not to_stdout:
        print(f"wrote {a.json} ({len(recs)} lines)")
    errors = [r for r in recs if r.get("error")]
    for r in errors:
        print(f"onlinecal replay: {r['error']}", file=sys.stderr)
    for r in recs:
        h = r.get("health")
        if not r.get("error") and h and h.get("verdict") != "ok":
            print(f"onlinecal replay: {r['log']}: health {h['verdict']}: {'; '.join(h.get('reasons', []))}",
                  file=sys.stderr)
    if errors:
        return EXIT_INPUT
    return EXIT_STATUS[combine(r.get("health") for r in recs)]


def cmd_run(a: argparse.Namespace) -> int:
    """The UKF on a live link (onlinecal.ukf.live_run): result JSON at the end, checkpoints, --apply.
    Exit 0 (or 4/5 by the result's health); 1 when --apply could not confirm every parameter; 2 for
    unusable input."""
    ukf = _ukf()
    if not hasattr(ukf, "run_live"):
        raise Unavailable("live runs are not available in this build")
    if a.resume and not a.checkpoint:
        raise UsageError("--resume needs --checkpoint FILE")
    if a.idle_timeout == float("inf"):
        raise UsageError(f"--idle-timeout: must be a finite number of seconds >= 0, got {a.idle_timeout:g}")
    init = _load_cal(a.init) if a.init else None
    _check_out(a.json, "--json")
    _check_out(a.trace, "--trace", dash=False)
    _check_out(a.checkpoint, "--checkpoint", dash=False)
    from .apply_ext import check_live, live_transform

    try:
        _warn(check_live(init))
    except ValueError as e:
        raise UsageError(f"--init {a.init}: {e}") from None
    json_file = None if a.json == "-" else a.json
    _warm_kernels()
    try:
        # --declination without --latitude: for the vehicle's GPS fix, when it comes (run waits for it)
        gps_decl = a.declination if a.latitude is None else None
        config = None if gps_decl is not None else _ukf_config(a)
        res = ukf.run_live(a.connect, init, config=config, duration_s=a.duration, json_out=json_file,
                           trace_out=a.trace,
                           checkpoint=a.checkpoint, checkpoint_every_s=a.checkpoint_every, resume=a.resume,
                           rate_hz=a.rate, apply=a.apply, transform=live_transform(init),
                           idle_timeout_s=a.idle_timeout or None, source_system=a.sysid, source_component=a.compid,
                           gps_wait_s=LIVE_GPS_WAIT_S if a.latitude is None else 0.0, gps_declination=gps_decl,
                           **_scales(a))
        if init is not None and init.extensions and not res.calibration.extensions:
            res.calibration = res.calibration.replace(extensions=init.extensions)
    except ImportError as e:
        raise Unavailable(str(e)) from e
    except OSError as e:  # the JSON, trace or checkpoint file cannot be written
        raise UsageError(f"{e.filename or '?'}: cannot write ({e.strerror or e})") from e
    if init is not None and init.extensions and not res.calibration.extensions:
        res.calibration = res.calibration.replace(extensions=init.extensions)
    health = online_health(res, digest=getattr(res, "raw_digest", None))
    if a.json:
        _save_result(res.calibration, health, a.json)
    from .report import truth_table

    out = _human(a.json)
    _warn(res.warnings)
    print(truth_table(None, init, res.calibration, labels=("init", "online")), file=out)
    ln = res.link
    print(f"link: received {ln['received']}, lost {ln['lost']}, duplicates {ln['duplicates']}, "
          f"reordered {ln['reordered']}, late {ln['dropped_late']}, reconnects {ln['reconnects']}, "
          f"resumes {ln['resumes']}; ended: {res.stop_reason}", file=out)
    _print_observability(res.calibration, out)
    if res.missing_motion:
        print("still needed: " + "; ".join(res.missing_motion), file=out)
    if a.json and a.json != "-":
        print(f"wrote {a.json}", file=out)
    status = _show_health(health, "online calibration")
    if res.apply_error:
        print(f"onlinecal run: --apply: {res.apply_error}; nothing was set", file=sys.stderr)
        return EXIT_DIFFER
    if res.applied is not None:
        bad = res.apply_failed
        print(f"applied {len(res.applied) - len(bad)} of {len(res.applied)} {res.apply_format} parameters "
              "(each confirmed by the vehicle's PARAM_VALUE)", file=out)
        for n in bad:
            print(f"onlinecal run: {n} not confirmed: {res.applied[n]['why']}", file=sys.stderr)
        if bad:
            return EXIT_DIFFER
    return status


def cmd_compare(a: argparse.Namespace) -> int:
    from .report import compare, compare_text

    ca, cb = _load_cal(a.a), _load_cal(a.b)
    rows = compare(ca, cb, a.tol, a.abs_tol)
    print(compare_text(ca, cb, rows=rows))
    if a.tol is None and a.abs_tol is None:
        return 0
    beyond = [r for r in rows if r.get("beyond")]
    if beyond:
        print(f"onlinecal compare: {len(beyond)} parameter(s) differ beyond the tolerance: "
              + ", ".join(f"{r['sensor']}.{r['param']}.{r['axis']}" for r in beyond[:8])
              + (" …" if len(beyond) > 8 else ""), file=sys.stderr)
        return EXIT_DIFFER
    return 0


def cmd_demo(a: argparse.Namespace) -> int:
    from .demo import run_demo

    _check_out(a.out, "--out", directory=True)
    return run_demo(Path(a.out), a.seed)


def cmd_diagnose(a: argparse.Namespace) -> int:
    from .diagnose import diagnose
    from .health import assess
    from .progress import spinner

    _check_out(a.json, "--json")
    _check_out(a.report, "--report", directory=True)
    out = _human(a.json)
    init = _load_cal(a.init) if a.init else None  # a bad --init file is refused before the logs are read
    from .diagnose.sample import bounded_sample

    logs = _read_logs(a.logs, a)
    n_imu = sum(d.n_imu for d in logs)
    # a long log is diagnosed on a bounded sample of itself (diagnose/sample.py); taken here, so that the whole
    # log is not held while the diagnosis runs (its health below is judged on the same sample)
    logs, sampled = bounded_sample(logs)
    with spinner("diagnose (batch, detectors, re-simulation, UKF)"):
        diag = diagnose(logs, g=a.gravity, seed=a.seed, calibration=init, sampled=sampled)
    print(f"verdict: {diag.verdict}", file=out)
    for f in diag.findings:
        if not f.significant:
            continue
        print(f"  {f.effect} ({f.sensor}{'/' + f.axis if f.axis else ''}): score {f.score:.1f} nats — {f.evidence}",
              file=out)
        params = _fmt_params(f.parameters)
        if params:
            print(f"    estimated: {params}", file=out)
        g = f.gain or {}
        gain = [f"held-out RMS {g['heldout_rms_before']:.4g} → {g['heldout_rms_after']:.4g}"
                if _finite(g.get("heldout_rms_before")) and _finite(g.get("heldout_rms_after")) else "",
                f"log-likelihood gain {g['loglik_gain']:.1f} nats" if _finite(g.get("loglik_gain")) else "",
                f"ΔBIC {g['bic_delta']:.1f}" if _finite(g.get("bic_delta")) else "",
                f"UKF NIS {g['ukf_nis_before']:.3g} → {g['ukf_nis_after']:.3g}"
                if _finite(g.get("ukf_nis_before")) and _finite(g.get("ukf_nis_after")) else ""]
        if any(gain):
            print(f"    gain: {', '.join(x for x in gain if x)}", file=out)
    for u in diag.untestable:
        print(f"  not testable: {u}", file=out)
    if diag.baseline.get("bounded_sample"):
        from .diagnose.sample import note

        print(f"  {note(diag.baseline['bounded_sample'])}", file=out)
    for e in diag.baseline.get("excluded", []):
        from .diagnose.gaps import excluded_text

        print(f"  {excluded_text(e)}", file=out)
    ub, ua = diag.baseline.get("ukf") or {}, diag.ukf_extended or {}
    nis: dict[str, Any] = {}
    if "nis_mean" in ub:
        print(f"  UKF NIS (window mean, expected 3): paper model {ub['nis_mean']:.3g}"
              + (f", extended {ua['nis_mean']:.3g}" if "nis_mean" in ua else ""), file=out)
        best = ua if "nis_mean" in ua else ub
        nis = {"ukf (the model as diagnosed)": {"mean": best["nis_mean"], "windows": 99}}
    elif "error" in ub:
        print(f"  UKF stage: {ub['error']}", file=out)
    print(f"diagnose: {n_imu} IMU samples in {diag.timing.get('total', 0):.1f} s", file=out)
    health = assess(diag.calibration, nis=nis, events=[], mag_raw=_mag_raw(logs), raw=_raw(logs))
    if a.json:
        from .files import OutputError, write_json

        try:
            write_json(a.json, {**diag.to_dict(), "health": health})
        except OutputError as e:
            raise UsageError(str(e)) from None
        if a.json != "-":
            print(f"wrote {a.json}", file=out)
    if a.report:
        from .diagnose.report import write_report

        path = write_report(diag, Path(a.report))
        print(f"wrote {path}", file=out)
    return _show_health(health, "diagnosed calibration")


def _finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


def _fmt_params(p: dict[str, Any]) -> str:
    """A finding's fitted parameters as ``key=value`` (lists rounded to 4 significant digits)."""
    import numpy as np

    out = []
    for k, v in (p or {}).items():
        if isinstance(v, (list, tuple, np.ndarray)):
            try:
                arr = np.asarray(v, float)
                out.append(f"{k}=" + np.array2string(arr, precision=4, separator=", "))
                continue
            except (TypeError, ValueError):
                pass
        out.append(f"{k}={v:.4g}" if _finite(v) else f"{k}={v}")
    return ", ".join(out)


def cmd_export(a: argparse.Namespace) -> int:
    from .calfile import CalFileError, load_onboard_params
    from .export import ExportError, export_calibration, header_lines, render_parm
    from .files import OutputError, atomic_write, dumps

    cal = _load_cal(a.cal)
    onboard = None
    if a.onboard:
        try:
            onboard = load_onboard_params(a.onboard)
        except CalFileError as e:
            raise UsageError(str(e)) from None
    out = a.out if a.out else str(Path(a.cal).with_suffix(".parm" if a.format == "ardupilot" else ".params"))
    side = None if out == "-" else out + ".export.json"
    _check_out(out, "--out")
    _check_out(side, "--out")
    health = dict(cal.health) if cal.health is not None else None
    try:
        exp = export_calibration(cal, a.format, a.mag_unit, onboard=onboard, force=a.force, health=health)
    except ExportError as e:
        raise UsageError(f"{a.cal}: {e}") from e
    header = header_lines(exp, Path(a.cal).name)
    try:
        atomic_write(out, render_parm(exp.params, exp.fmt, header, exp.types))
        if side is not None:
            atomic_write(side, dumps(exp.report()) + "\n")
    except OutputError as e:
        raise UsageError(str(e)) from None
    _warn(exp.warnings)
    for name, why in exp.withheld.items():
        print(f"onlinecal export: {name} not written: {why}", file=sys.stderr)
    if out != "-":
        print(f"wrote {out} ({len(exp.params)} parameters"
              + (f", {len(exp.withheld)} withheld" if exp.withheld else "") + f") and {side}")
    if not exp.params:
        print("onlinecal export: no parameter is supported by the calibration's σ and health "
              "(--force writes them anyway)", file=sys.stderr)
        return EXIT_DEGRADED
    return EXIT_DEGRADED if exp.withheld else 0


# -- parser -----------------------------------------------------------------------------------------

class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``onlinecal simulate: --rate: must be ...``), exit 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_INPUT, f"{self.prog}: {message} (see {self.prog} --help)\n")


def _number(kind: str, lo: float | None = None, lo_open: bool = True, integer: bool = False) -> Any:
    """An argparse type: a finite number (int when ``integer``) above ``lo`` (open or closed)."""
    def parse(s: str) -> float | int:
        try:
            v: float | int = int(s) if integer else float(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {kind}, not {s!r}") from None
        if not math.isfinite(v) or (lo is not None and (v <= lo if lo_open else v < lo)):
            raise argparse.ArgumentTypeError(f"must be {kind}, not {s!r}")
        return v
    parse.__name__ = kind  # argparse names the type in its messages
    return parse


_POS = _number("a positive number", 0.0)
_NONNEG = _number("a number ≥ 0", 0.0, lo_open=False)
_SEED = _number("an integer ≥ 0", 0, lo_open=False, integer=True)
_POS_INT = _number("a positive integer", 0, integer=True)


def _scale_factor(s: str) -> float:
    v = _number("a finite non-zero number")(s)
    if v == 0:
        raise argparse.ArgumentTypeError(f"must be a finite non-zero number, not {s!r}")
    return float(v)


def _positive_int(s: str) -> int:
    return int(_POS_INT(s))


def _add_latitude(p: argparse.ArgumentParser, from_logs: bool, declination: bool = True) -> None:
    default = ("default: the logs' GPS where they have a 3-D fix, else not known (the gyro bias keeps an "
               "allowance for it); none: not taken out even where a log has GPS" if from_logs else
               "default: the vehicle's GPS_RAW_INT fix if one arrives within the first 3 s of data (the filter "
               "starts then), else not known; none: not taken out, no wait")
    what = ("the Earth's rotation is taken out of the gyro (its vertical part at once, the horizontal once a "
            "magnetometer holds the heading)" if declination else
            "the Earth rotation's vertical part is taken out of the rests' gyro bias (eqs. 34-35)")
    p.add_argument("--latitude", type=_latitude, default=None, metavar="DEG|none",
                   help=f"where the vehicle is (degrees, north positive): {what}; {default}")
    if not declination:
        return
    p.add_argument("--declination", type=_declination_deg, default=None, metavar="DEG",
                   help="with a latitude: the magnetic declination, east positive, taken as known to 1 deg; "
                        "default: the World Magnetic Model's at the GPS fix (± max(1 deg, its own)), else unknown, "
                        "0 ± 15 deg")


def _degrees(what: str, limit: float, or_none: bool = False) -> Callable[[str], Any]:
    """An argparse type: an angle in degrees within ±``limit`` (``what`` names it in the error); with
    ``or_none`` also ``none``/``off``, returned as "none"."""
    span = f"a {what} in degrees (−{limit:g}…{limit:g})" + (" or none" if or_none else "")

    def parse(s: str) -> float | str:
        if or_none and s.strip().lower() in ("none", "off"):
            return "none"
        v = float(_number(span)(s))
        if not abs(v) <= limit:
            raise argparse.ArgumentTypeError(f"must be {span}, not {s!r}")
        return v

    return parse


_declination_deg = _degrees("declination", 180.0)  # replay/run/simulate --declination
_latitude = _degrees("latitude", 90.0, or_none=True)  # --latitude: none, no Earth rate (simulate), not taken out


def _add_scales(p: argparse.ArgumentParser) -> None:
    p.add_argument("--acc-scale", type=_scale_factor, default=None, metavar="K",
                   help="multiplier from the log's accelerometer unit to m/s^2 (default: per format)")
    p.add_argument("--gyro-scale", type=_scale_factor, default=None, metavar="K",
                   help="multiplier from the log's gyro unit to rad/s (default: per format)")
    p.add_argument("--mag-scale", type=_scale_factor, default=None, metavar="K",
                   help="multiplier for the magnetometer (default: per format; any fixed unit works)")
    # the IMU instance of multi-IMU logs and links
    p.add_argument("--imu", type=_nonneg_int, default=0, metavar="N",
                   help="IMU instance to read: .bin IMU I=N (IMU2/IMU3 in old logs), .tlog/link RAW_IMU or "
                        "HIGHRES_IMU id N or SCALED_IMU/2/3, .ulg sensor topic instance N (default 0)")


def _add_quiet(p: argparse.ArgumentParser) -> None:
    # SUPPRESS: given after the command it sets a.quiet; absent, the global flag's value stays
    p.add_argument("--quiet", "-q", action="store_true", default=argparse.SUPPRESS,
                   help="no progress bars (also accepted before the command)")


def _add_json(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--json", default=None, metavar="OUT",
                   help=f"write {what} as strict JSON, with its \"health\" verdict ('-': stdout, the table "
                        "then goes to stderr)")


CSV_SCHEMA = ("CSV logs: header time_s,gyro_x,gyro_y,gyro_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z,temp_c "
              "(s, rad/s, m/s^2, any fixed mag unit, degC); empty cells where a sensor has no sample in that row.")

_EXAMPLES = {
    "demo": "example: onlinecal demo --out /tmp/demo --seed 3",
    "simulate": "examples: onlinecal simulate --out s.tlog --seed 1\n"
                "          onlinecal simulate --out s.ulg --seed 1   # PX4 ULog: sensor_accel/gyro/mag + CAL_*\n"
                "          onlinecal simulate --out f.csv --profile flight --duration 120 --rate 200 "
                "--effect time_offset:sensor=mag,seconds=0.05",
    "batch": "examples: onlinecal batch session.tlog --json cal.json --report rep/\n"
             "          onlinecal batch statics.csv turns.csv --json - | jq .health",
    "replay": "examples: onlinecal replay flight.bin --init cal.json --json online.json --trace t.csv\n"
              "          onlinecal replay logs/*.tlog --jobs 4 --json fleet.jsonl",
    "run": "example: onlinecal run --connect udpin:0.0.0.0:14550 --duration 300 --json live.json "
           "--checkpoint run.ckpt",
    "compare": "examples: onlinecal compare batch.json online.json\n"
               "          onlinecal compare session.tlog.truth.json batch.json --tol 5   # exit 1 beyond 5 sigma",
    "diagnose": "examples: onlinecal diagnose session.csv --json diag.json --report diag/\n"
                "          onlinecal diagnose gappy.bin --json - | jq .baseline.excluded   "
                "# NaN bursts and logging gaps cut out and named",
    "export": "examples: onlinecal export cal.json --format ardupilot --out cal.parm\n"
              "          onlinecal export cal.json --format px4 --onboard vehicle.params --out -\n"
              "          (a mag_current extension in cal.json is written as COMPASS_MOT_*/COMPASS_MOTCT or "
              "CAL_MAGn_*COMP/CAL_MAG_COMP_TYP)",
}


def _nonneg_int(s: str) -> int:
    """argparse type: an integer >= 0."""
    return int(_SEED(s))


def build_parser() -> argparse.ArgumentParser:
    import textwrap

    fmt = argparse.RawDescriptionHelpFormatter
    status = textwrap.fill(EXIT_STATUS_TEXT, 100)
    csv = textwrap.fill(CSV_SCHEMA, 100)
    ap = _Parser(prog="onlinecal", description="Online IMU calibration (Zhang et al. 2014 + UKF)",
                 epilog=status + "\n\n" + csv, formatter_class=fmt)
    ap.add_argument("--version", action="version", version=f"onlinecal {__version__}")
    ap.add_argument("--quiet", "-q", action="store_true",
                    help="no progress bars (they are also off when stderr is not a terminal)")
    sub = ap.add_subparsers(dest="cmd", required=True, parser_class=_Parser)

    def command(name: str, help_: str) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_, description=help_, formatter_class=fmt,
                           epilog=_EXAMPLES.get(name, "") + "\n\n" + status)
        _add_quiet(p)
        return p

    p = command("demo", "simulate, calibrate (batch + online), compare with truth")
    p.add_argument("--out", default="onlinecal-demo", metavar="DIR", help="output directory (default ./onlinecal-demo)")
    p.add_argument("--seed", type=_SEED, default=0, help="simulation seed (default 0)")
    p.set_defaults(fn=cmd_demo)

    p = command("simulate", "write a simulated session (.tlog/.csv/.bin/.ulg) and its truth (FILE.truth.json)")
    p.add_argument("--out", required=True, metavar="FILE", help="FILE.tlog, FILE.csv, FILE.bin or FILE.ulg")
    p.add_argument("--profile", default="paper",
                   help="paper | flight | multirotor | fixedwing, vehicles with options "
                        "NAME[:vibration=M/S2,mag_interference=F,rest=S]")
    p.add_argument("--seed", type=_SEED, default=0)
    p.add_argument("--duration", type=_POS, default=None, metavar="S", help="seconds (default: the profile's)")
    p.add_argument("--rate", type=_POS, default=100.0, metavar="HZ", help="IMU rate, Hz (default 100)")
    p.add_argument("--mag-rate", type=_POS, default=50.0, metavar="HZ", help="magnetometer rate, Hz (default 50)")
    p.add_argument("--effect", action="append", default=[], metavar="SPEC",
                   help="NAME[:key=value,...] (repeatable; names in the README's effect table)")
    p.add_argument("--latitude", type=_latitude, default=None, metavar="DEG|none",
                   help="the gyro senses the Earth's rotation at this latitude; none: not at all (default: the "
                        "profile's — multirotor and fixedwing at 47.397742°, paper and flight none)")
    p.add_argument("--declination", type=_declination_deg, default=None, metavar="DEG",
                   help="the field's horizontal part DEG east of true north (the Earth's rotation stays on true "
                        "north; default 0, with --gps the World Magnetic Model's at the logged home)")
    p.add_argument("--gps", action="store_true",
                   help="log the vehicle's GPS position (5 Hz, a 3-D fix; .bin/.tlog/.ulg): a replay then takes the "
                        "Earth's rotation out at its latitude. Needs a gyro that senses it (a vehicle profile, or "
                        "--latitude DEG)")
    p.set_defaults(fn=cmd_simulate)

    p = command("batch", "the paper's offline pipeline over logs of one sensor unit")
    p.add_argument("logs", nargs="+", metavar="LOG", help=".tlog, .bin, .ulg or .csv. " + CSV_SCHEMA)
    _add_json(p, "the calibration")
    p.add_argument("--gravity", type=_POS, default=9.80665, metavar="G", help="local g, m/s^2 (default 9.80665)")
    p.add_argument("--report", default=None, metavar="DIR", help="write PNG figures and report.md into DIR")
    _add_latitude(p, from_logs=True, declination=False)
    _add_scales(p)
    p.set_defaults(fn=cmd_batch)

    p = command("replay", "the augmented-state UKF over logs")
    p.add_argument("logs", nargs="+", metavar="LOG", help=".tlog, .bin, .ulg or .csv")
    p.add_argument("--init", default="batch", metavar="batch|none|CAL.json",
                   help="the filter's start: the batch pipeline on the same logs (default), a cold start, or "
                        "a calibration JSON (a simulator truth file also works)")
    p.add_argument("--json", default=None, metavar="OUT",
                   help="calibration JSON with its \"health\"; with --jobs/--executor: JSON Lines, one object "
                        "per log ('-': stdout)")
    p.add_argument("--trace", default=None, metavar="OUT.csv", help="the filter's state over time, CSV")
    p.add_argument("--report", default=None, metavar="DIR", help="write PNG figures and report.md into DIR")
    p.add_argument("--jobs", type=_positive_int, default=None, metavar="N",
                   help="fleet mode: every log an independent unit, N in parallel (one JSON line per log)")
    p.add_argument("--executor", choices=["process", "dask"], default="process",
                   help="fleet mode on local processes or on dask.distributed (extra onlinecal[dask])")
    p.add_argument("--scheduler", default=None, metavar="ADDR",
                   help="dask scheduler address (default: a LocalCluster of --jobs workers)")
    _add_latitude(p, from_logs=True)
    _add_scales(p)
    p.set_defaults(fn=cmd_replay)

    p = command("run", "the UKF on a live MAVLink link (docs/live.md)")
    p.add_argument("--connect", required=True, metavar="URL",
                   help="pymavlink connection: udpin:0.0.0.0:14550, tcp:127.0.0.1:5760, /dev/ttyACM0,115200")
    p.add_argument("--init", default=None, metavar="CAL.json", help="start calibration (default: cold start)")
    _add_json(p, "the calibration at the end")
    p.add_argument("--duration", type=_POS, default=None, metavar="S",
                   help="s of vehicle time from the first sample (default: until Ctrl-C)")
    p.add_argument("--trace", default=None, metavar="OUT.csv", help="trace CSV, appended as the run goes")
    p.add_argument("--checkpoint", default=None, metavar="FILE", help="write the run's state there")
    p.add_argument("--checkpoint-every", type=_POS, default=10.0, metavar="S",
                   help="wall seconds between checkpoints (default 10)")
    p.add_argument("--resume", action="store_true", help="continue from --checkpoint FILE")
    # end of an idle link, and the vehicle to read when several send
    p.add_argument("--idle-timeout", type=_NONNEG, default=10.0, metavar="S",
                   help="end the run, with its result, after S seconds without IMU data (0: never; default 10)")
    p.add_argument("--sysid", type=_nonneg_int, default=None, metavar="N",
                   help="read the vehicle with this MAVLink system id (default: the first HEARTBEAT's)")
    p.add_argument("--compid", type=_nonneg_int, default=None, metavar="N",
                   help="... and this component id (default: the first one seen)")
    p.add_argument("--rate", type=_NONNEG, default=100.0, metavar="HZ",
                   help="RAW_IMU rate asked of the vehicle (SET_MESSAGE_INTERVAL; 0: ask nothing; default 100)")
    p.add_argument("--apply", choices=["ardupilot", "px4"], default=None,
                   help="afterwards, set the calibration as vehicle parameters (PARAM_SET, each confirmed)")
    _add_latitude(p, from_logs=False)
    _add_scales(p)
    p.set_defaults(fn=cmd_run)

    p = command("compare", "parameter-by-parameter difference of two calibrations (or a truth file)")
    p.add_argument("a", metavar="A.json", help="calibration JSON or simulator truth file (FILE.truth.json)")
    p.add_argument("b", metavar="B.json", help="calibration JSON or simulator truth file")
    p.add_argument("--tol", type=_POS, default=None, metavar="N",
                   help="exit 1 when a parameter with a σ differs by more than N σ (σ of A and B combined)")
    p.add_argument("--abs-tol", type=_POS, default=None, metavar="X",
                   help="exit 1 when a parameter without σ differs by more than X in its unit")
    p.set_defaults(fn=cmd_compare)

    p = command("diagnose", "what the model gets wrong on this data, the cause, the extended model")
    p.add_argument("logs", nargs="+", metavar="LOG", help=".tlog, .bin, .ulg or .csv")
    _add_json(p, "the diagnosis")
    p.add_argument("--report", default=None, metavar="DIR", help="directory for report.md and plots")
    p.add_argument("--gravity", type=_POS, default=9.80665, metavar="G", help="local g, m/s^2")
    p.add_argument("--seed", type=_SEED, default=0, help="seed of the re-simulation's noise")
    p.add_argument("--init", default=None, metavar="CAL.json",
                   help="baseline calibration (e.g. a bench calibration) instead of the batch fit on these logs")
    _add_scales(p)
    p.set_defaults(fn=cmd_diagnose)

    p = command("export", "vehicle parameters (ArduPilot .parm, PX4/QGroundControl .params)")
    p.add_argument("cal", metavar="CAL.json")
    p.add_argument("--format", choices=["ardupilot", "px4"], required=True)
    p.add_argument("--out", default=None, metavar="FILE",
                   help="parameter file (default CAL.parm / CAL.params beside CAL.json; '-' for stdout)")
    p.add_argument("--mag-unit", choices=["gauss", "mgauss", "uT", "nT", "T"], default="gauss",
                   help="unit of the raw magnetometer values the calibration was fitted on (default gauss: "
                        "what the .tlog and .bin readers produce)")
    p.add_argument("--onboard", default=None, metavar="PARAMS",
                   help="the vehicle's parameters in effect when the log was recorded (.parm or .params); the "
                        "calibration was fitted on data those had already corrected (a .bin's IMU/MAG), so the "
                        "export composes with them instead of correcting twice")
    p.add_argument("--force", action="store_true",
                   help="write every parameter even where its σ or the result's health does not support it")
    p.set_defaults(fn=cmd_export)
    return ap


_seen_warnings: set[str] = set()


def _one_line_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                      file: Any = None, line: str | None = None) -> None:
    """Library warnings (numpy, scipy, matplotlib) as the tool's own one-line warnings, each once."""
    text = str(message).strip().splitlines()[0] if str(message).strip() else category.__name__
    if text in _seen_warnings:
        return
    _seen_warnings.add(text)
    print(f"warning: {text} ({category.__name__} in {Path(filename).stem})", file=sys.stderr)


def _quiet_libraries() -> None:
    import logging
    import warnings

    warnings.showwarning = _one_line_warning
    warnings.simplefilter("default")
    warnings.simplefilter("ignore", ResourceWarning)  # an unclosed file at exit is ours to fix, not the user's to read
    logging.getLogger("matplotlib").setLevel(logging.ERROR)
    for s in (sys.stdout, sys.stderr):  # a unicode file name or σ under LANG=C: never a UnicodeEncodeError
        try:
            s.reconfigure(errors="backslashreplace")  # type: ignore[union-attr]
        except (AttributeError, ValueError):
            pass


def main(argv: Sequence[str] | None = None) -> int:
    from .batch.ellipsoid import FitError
    from .calfile import CalFileError
    from .files import OutputError
    from .io.base import LogError

    _quiet_libraries()
    a = build_parser().parse_args(argv)
    from .progress import set_quiet

    set_quiet(getattr(a, "quiet", False))
    try:
        return int(a.fn(a))
    except (LogError, UsageError, CalFileError, OutputError) as e:
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
    except OSError as e:  # a file that vanished or cannot be read mid-run: input, not a bug
        print(f"onlinecal {a.cmd}: {e.filename or ''}{': ' if e.filename else ''}{e.strerror or e}", file=sys.stderr)
        return EXIT_INPUT
    except MemoryError:
        print(f"onlinecal {a.cmd}: out of memory (is the input far larger than a log?)", file=sys.stderr)
        return EXIT_INPUT
    except Exception as e:  # noqa: BLE001 - never a traceback; ONLINECAL_DEBUG=1 shows it
        if os.environ.get("ONLINECAL_DEBUG"):
            raise
        print(f"onlinecal {a.cmd}: internal error: {type(e).__name__}: {e} (a bug: please report it with the "
              "command line; ONLINECAL_DEBUG=1 shows the traceback)", file=sys.stderr)
        return EXIT_INTERNAL
