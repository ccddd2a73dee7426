"""A live run: the online calibrator on a MAVLink link (``onlinecal run``), un-losable through checkpoints.

The blocks of :class:`onlinecal.io.live.LiveSource` (RAW_IMU in time order; duplicates dropped, reordering
repaired, loss left as gaps in time) go into the same :class:`OnlineCalibrator` that ``replay`` uses; the
calibrator handles the gaps (each IMU step integrates over the real Δt; a gap longer than
``UKFConfig.max_gap_s`` restarts the attitude).

Checkpoints: every ``checkpoint_every_s`` wall seconds (and at the end) the filter state
(:meth:`OnlineCalibrator.get_state`), the source position (:meth:`LiveSource.position`: the last sample
fed, the clock shift, the held mag triple) and the link counters are written to FILE atomically: FILE.tmp
written, fsync'ed, ``os.replace``'d onto FILE (and the directory fsync'ed), so FILE is always the old or
the new checkpoint, never half of one. ``resume`` loads FILE and continues on the same vehicle time line:
samples at or before the checkpoint are not fed again, what was lost while nothing ran is a gap.
"""

from __future__ import annotations

import json
import math
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from ..health import RawDigest
from ..io.base import ImuData, LogError, split_boundaries
from ..io.mavlink import MAV_PARAM_TYPE_INT32
from ..model import Calibration
from .filter import OnlineCalibrator, UKFConfig
from .live_files import CHECKPOINT_SCHEMA as CHECKPOINT_SCHEMA  # re-exported
from .live_files import (
    COUNTERS,
    DigestFile,
    TraceCsv,
    digest_path,
    load_checkpoint,
    load_digest,
    status_line,
    write_atomic,
)
from .replay import OnlineResult

if TYPE_CHECKING:
    from ..io.live import LiveSource

_END = object()  # end of the link reader's queue


@dataclass
class LiveResult(OnlineResult):
    """What a live run produced: an :class:`OnlineResult` plus the link counters (summed over resumes),
    why the stream ended, the checkpoints written, the resumes so far, the link's warnings and, with
    ``apply``, the per-parameter PARAM_SET report of :meth:`LiveSource.set_params`."""

    link: dict[str, Any] = field(default_factory=dict)
    stop_reason: str | None = None
    checkpoints: int = 0
    resumes: int = 0
    applied: dict[str, dict[str, Any]] | None = None
    apply_format: str | None = None
    warnings: list[str] = field(default_factory=list)
    apply_error: str | None = None
    raw_digest: RawDigest | None = None  # the samples fed, for the health verdict (onlinecal.cli.online_health)

    @property
    def apply_failed(self) -> list[str]:
        """Names of the parameters the vehicle did not confirm (empty without ``apply``)."""
        return [n for n, r in (self.applied or {}).items() if not r["ok"]]


def _vehicle_params() -> tuple[Callable[..., dict[str, float]], frozenset[str]]:
    """``onlinecal.export.vehicle_params`` and the names of its integer parameters, imported when asked
    for (ImportError names what is missing)."""
    try:
        from ..export import vehicle_params
    except ImportError as e:
        raise ImportError(f"--apply needs onlinecal.export.vehicle_params, which this build lacks ({e})") from e
    from .. import export

    return vehicle_params, frozenset(getattr(export, "INT32_PARAMS", ()))


def run_live(url: str, init: Calibration | None = None, *, config: UKFConfig | None = None,
             duration_s: float | None = None, json_out: str | Path | None = None,
             trace_out: str | Path | None = None, checkpoint: str | Path | None = None,
             checkpoint_every_s: float = 10.0, resume: bool = False, rate_hz: float = 100.0,
             apply: str | None = None, status_every_s: float | None = None,
             acc_scale: float | None = None, gyro_scale: float | None = None, mag_scale: float | None = None,
             source_options: dict[str, Any] | None = None, log: TextIO | None = None,
             transform: Callable[[ImuData], ImuData] | None = None, idle_timeout_s: float | None = 10.0,
             imu: int = 0, source_system: int | None = None,
             source_component: int | None = None, gps_wait_s: float = 0.0,
             gps_declination: float | None = None) -> LiveResult:
    """Calibrate online from the live link ``url`` until ``duration_s`` s of vehicle time (from the first
    sample, across resumes), or Ctrl-C / SIGTERM, which end the run cleanly with a result.

    ``init``: start calibration (None: cold start); ignored when resuming (the checkpoint carries its
    own). ``json_out``: the calibration JSON (every parameter with σ), written atomically at the end.
    ``trace_out``: trace CSV, appended as the run goes. ``checkpoint``: checkpoint FILE, written every
    ``checkpoint_every_s`` wall seconds while data flows and at the end; ``resume``: continue from it (a
    missing FILE starts a new run, with a note; an unusable one is a LogError). ``rate_hz``: RAW_IMU
    rate asked of the vehicle (SET_MESSAGE_INTERVAL; 0 asks nothing). ``apply``: 'ardupilot' | 'px4':
    afterwards, set the calibration as vehicle parameters and confirm each (see ``LiveResult.applied``).
    ``status_every_s``: link/motion status line period on ``log`` (default stderr; 5 s on a terminal,
    30 s otherwise; 0: none). ``source_options``: more LiveSource arguments (``reorder_window``,
    ``reconnect_s``, ``block_s``, ``timeout_s``). ``transform``: applied to every block before the filter
    sees it, on the filter's thread (the model extensions' per-block corrections, ``apply_ext.live_transform``).
    ``idle_timeout_s``: the run ends, with its result, after this many seconds without an IMU message (None:
    never; a LogError when nothing arrived at all). ``imu``: IMU instance; ``source_system``/
    ``source_component``: the vehicle read when several send (default: the first vehicle HEARTBEAT's).
    ``gps_wait_s``: a new run whose ``config`` has no latitude holds the link's first blocks back until the
    vehicle's GPS_RAW_INT (or GLOBAL_POSITION_INT) gives a fix, or this many seconds of IMU data passed, and
    then starts the filter told the fix's latitude and ``gps_declination`` (deg, ± 1°) or else the World
    Magnetic Model's declination there (:func:`onlinecal.place.config_at`) — or, without a fix, as it was
    (0: no wait, the default here; the command line waits 3 s).
    A vehicle clock restart (reboot, also between a checkpoint and ``resume``) is a clock segment: the
    attitude restarts there, the calibration carries over, and the result names it in
    ``meta["online"]["segments"]``.

    Raises LogError when the link cannot be opened, the checkpoint is unusable, or no sample arrived.
    """
    out = log if log is not None else sys.stderr
    _check(apply, resume, checkpoint, checkpoint_every_s)
    exporter = _vehicle_params() if apply else None  # fail before the run, not after it
    if status_every_s is None:
        status_every_s = 5.0 if out.isatty() else 30.0
    ck, cal, duration_s = _start(checkpoint, resume, init, config, duration_s, out)
    # the samples' raw digest of a resumed run, before the link opens (a damaged entry is a LogError like the rest)
    restored = load_digest(ck, checkpoint) if ck is not None and checkpoint is not None else None
    from ..io.live import LiveSource
    opts = {"timeout_s": idle_timeout_s, **(source_options or {})}
    wait_gps = ck is None and gps_wait_s > 0 and cal.config.latitude_deg is None
    src = LiveSource(url, rate_hz=rate_hz, duration_s=duration_s, acc_scale=acc_scale, gyro_scale=gyro_scale,
                     mag_scale=mag_scale, imu=imu, source_system=source_system, source_component=source_component,
                     ask_gps=wait_gps, **opts)
    run = _LiveRun(url, cal, src, ck, checkpoint, rate_hz, duration_s, TraceCsv(trace_out, resume=ck is not None),
                   transform, out)
    if restored is not None:
        run.digest, run.rows_file, lost = restored
        if lost is not None:
            print(f"onlinecal run: warning: {lost}", file=out, flush=True)
            run.notes.append(lost)
    if wait_gps:
        run.wait_for_gps(gps_wait_s, lambda c: OnlineCalibrator(init, c), gps_declination)
    if ck is not None:
        try:
            src.resume_from(ck["source"])
        except ValueError as e:
            src.close()
            raise LogError(str(checkpoint), f"damaged checkpoint ({e})") from None
    try:
        run.stream(checkpoint_every_s, status_every_s)
        result = run.finish(json_out)
        if apply is not None and exporter is not None:
            _apply(result, apply, exporter, src, out)
        return result
    finally:
        src.close()


def _check(apply: str | None, resume: bool, checkpoint: str | Path | None, checkpoint_every_s: float) -> None:
    """ValueError for arguments of :func:`run_live` that do not go together."""
    if apply is not None and apply not in ("ardupilot", "px4"):
        raise ValueError(f"apply must be 'ardupilot' or 'px4', got {apply!r}")
    if resume and checkpoint is None:
        raise ValueError("resume needs a checkpoint file")
    if not checkpoint_every_s > 0:
        raise ValueError("checkpoint_every_s must be > 0")


def _start(checkpoint: str | Path | None, resume: bool, init: Calibration | None, config: UKFConfig | None,
           duration_s: float | None, out: TextIO) -> tuple[dict[str, Any] | None, OnlineCalibrator, float | None]:
    """The checkpoint to resume from (None: a new run), the calibrator, and the run's duration (a resumed
    run keeps the checkpoint's unless given)."""
    ck: dict[str, Any] | None = None
    if resume and checkpoint is not None and not Path(checkpoint).exists():
        print(f"onlinecal run: {checkpoint}: no checkpoint yet, starting a new run", file=out)
    elif resume and checkpoint is not None:
        ck, cal = load_checkpoint(checkpoint)
        if init is not None:
            print("onlinecal run: --init is ignored when resuming (the checkpoint has its own)", file=out)
        if config is not None and config.latitude_deg != cal.config.latitude_deg:
            print(f"onlinecal run: --latitude is ignored when resuming (the checkpoint's filter has "
                  f"{cal.config.latitude_deg if cal.config.latitude_deg is not None else 'none'})", file=out)
        if duration_s is None:
            duration_s = ck.get("duration_s")
        return ck, cal, duration_s
    return ck, OnlineCalibrator(init, config), duration_s


class _LiveRun:
    """One live run: the link read in its own thread, its blocks fed to the calibrator, checkpoints and
    status lines on wall-clock timers, the counters and clock segments carried over from a checkpoint."""

    def __init__(self, url: str, cal: OnlineCalibrator, src: LiveSource, ck: dict[str, Any] | None,
                 checkpoint: str | Path | None, rate_hz: float, duration_s: float | None, trace: TraceCsv,
                 transform: Callable[[ImuData], ImuData] | None, out: TextIO) -> None:
        self.url, self.cal, self.src, self.ck, self.checkpoint = url, cal, src, ck, checkpoint
        self.rate_hz, self.duration_s, self.trace, self.transform, self.out = rate_hz, duration_s, trace, transform, out
        self.base: dict[str, Any] = dict(ck["link"]) if ck else {}
        self.resumes = int(self.base.get("resumes", 0)) + (1 if ck else 0)
        self.fed: dict[str, Any] = dict(ck["fed"]) if ck else {"imu": 0, "t_first": None, "t_last": None}
        self.segments: list[dict[str, Any]] = list(ck.get("segments", [])) if ck else []
        self.n_ckpt = 0
        self.pos_fed: dict[str, Any] | None = ck["source"] if ck else None  # source position of the last block fed
        self.stopped: list[int] = []
        self.t0 = time.perf_counter()
        self.gps_wait_s = 0.0
        self.make_cal: Callable[[UKFConfig], OnlineCalibrator] | None = None
        self.gps_declination: float | None = None
        self.held: list[tuple[ImuData, dict[str, Any]]] = []  # blocks held back while waiting for a GPS fix
        # what the health verdict reads of the samples fed (gravity at rest, the rail): in the checkpoint, its
        # block rows appended to FILE.digest (a resumed run's verdict judges every sample fed since the start)
        self.digest = RawDigest()
        self.rows_file: DigestFile | None = DigestFile(digest_path(checkpoint)) if checkpoint is not None else None
        self.notes: list[str] = []  # warnings of this run beside the link's (a raw digest that was not restored)

    def wait_for_gps(self, wait_s: float, make_cal: Callable[[UKFConfig], OnlineCalibrator],
                     declination: float | None = None) -> None:
        """Hold the first blocks back until the link gives a GPS fix or ``wait_s`` s of data passed; the
        calibrator is then made anew by ``make_cal`` with the fix's place and ``declination`` (None: the
        WMM's) (:meth:`_release`)."""
        self.gps_wait_s, self.make_cal, self.gps_declination = float(wait_s), make_cal, declination

    def _offer(self, block: ImuData, pos: dict[str, Any]) -> bool:
        """:meth:`_take`, or hold the block while waiting for a GPS fix."""
        if self.gps_wait_s <= 0:
            return self._take(block, pos)
        self.held.append((block, pos))
        times = [b.t_imu for b, _ in self.held if b.n_imu]
        span = float(times[-1][-1] - times[0][0]) if times else 0.0
        if self.src.gps_position() is None and span < self.gps_wait_s:
            return False
        return self._release()

    def _release(self) -> bool:
        """End the wait for a GPS fix: the filter made with the fix's place (or as it was, with a line saying
        so), then the held blocks fed in order."""
        if self.gps_wait_s <= 0:
            return False
        where = self.src.gps_position()
        if where is not None and self.make_cal is not None:
            from ..place import config_at, told_line

            source = f"the vehicle's GPS ({where.source}; {where.n_fixes} fix{'es' if where.n_fixes != 1 else ''})"
            config, declination_line = config_at(where, source, self.gps_declination, self.cal.config)
            self.cal = self.make_cal(config)
            for line in (told_line(where.latitude_deg, source), declination_line):
                if line is not None:
                    print(f"onlinecal run: {line}", file=self.out, flush=True)
        else:
            print(f"onlinecal run: no GPS fix on the link within {self.gps_wait_s:g} s of data: the Earth's rotation "
                  "is not taken out of the gyro (give --latitude)", file=self.out, flush=True)
        self.gps_wait_s = 0.0
        held, self.held = self.held, []
        return any([self._take(b, p) for b, p in held])

    def link_stats(self) -> dict[str, Any]:
        st = dict(self.src.stats)
        for k in COUNTERS:
            st[k] = int(self.base.get(k, 0)) + int(st.get(k, 0))
        st["resumes"] = self.resumes
        return st

    def data_s(self) -> float:
        fed = self.fed
        return float(fed["t_last"] - fed["t_first"]) if fed["t_first"] is not None else 0.0

    def save_checkpoint(self) -> None:
        pos = self.pos_fed
        if self.checkpoint is None or pos is None:
            return
        self.trace.add(self.cal.trace_rows(clear=True))  # rows go to the CSV, not into every checkpoint
        digest = None
        if self.rows_file is not None:
            self.rows_file.append(self.digest.rows(self.rows_file.written or 0))  # durable before the checkpoint
            digest = {"file": self.rows_file.path.name, "state": self.digest.state()}
        payload = {"schema": CHECKPOINT_SCHEMA, "written": datetime.now(UTC).isoformat(),
                   "url": self.url, "rate_hz": self.rate_hz, "duration_s": self.duration_s, "source": pos,
                   "link": self.link_stats(), "fed": self.fed, "segments": self.segments,
                   "filter": self.cal.get_state(), "digest": digest}
        write_atomic(self.checkpoint, json.dumps(payload))
        self.n_ckpt += 1

    def _on_signal(self, signum: int, frame: Any) -> None:
        # Ctrl-C / SIGTERM end the stream; the run then finishes normally (flush, result, checkpoint).
        self.stopped.append(signum)
        self.src.stop()

    def _read_link(self, q: queue.Queue[Any]) -> None:
        try:
            for block in self.src.blocks():
                q.put((block, self.src.position()))  # the position as of this very block
        except BaseException as e:  # handed to the main thread, which raises it
            q.put(e)
        finally:
            q.put(_END)

    def _take(self, block: ImuData, pos: dict[str, Any]) -> bool:
        """Feed one block of the link (a vehicle clock restart inside it starts a new log); True when it
        held samples (the checkpoint is then out of date)."""
        if not (block.n_imu or block.n_mag):
            return False
        self.segments += [dict(b) for b in block.boundaries]
        for new_segment, piece in split_boundaries(block):
            if new_segment:
                self.cal.new_log()  # a vehicle reboot: the attitude restarts, the calibration stays
                self.digest.new_log()
            fed = self.transform(piece) if self.transform is not None else piece
            self.cal.feed(fed)
            if fed.n_imu:
                self.digest.add(fed.gyro, fed.acc)
        self.pos_fed = pos
        if block.n_imu:
            self.fed["imu"] += block.n_imu
            if self.fed["t_first"] is None:
                self.fed["t_first"] = float(block.t_imu[0])
            self.fed["t_last"] = float(block.t_imu[-1])
        return True

    def stream(self, checkpoint_every_s: float, status_every_s: float) -> None:
        """Read the link until it ends (duration, idle timeout, Ctrl-C / SIGTERM), feeding every block."""
        old: dict[signal.Signals, Any] = {}
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                old[sig] = signal.signal(sig, self._on_signal)
        print(f"onlinecal run: link open on {self.url}" + (f", resumed from {self.checkpoint}" if self.ck else "")
              + " (Ctrl-C ends the run with a result)", file=self.out, flush=True)
        # The link is read in its own thread: the socket is drained while the filter computes or a checkpoint
        # is fsync'ed, so a stall here costs memory (the queue), never packets (a full kernel buffer).
        q: queue.Queue[Any] = queue.Queue()
        reader = threading.Thread(target=self._read_link, args=(q,), name="onlinecal-link", daemon=True)
        self.t0 = time.perf_counter()
        now = time.monotonic()
        next_ckpt = now + checkpoint_every_s
        next_status = now + status_every_s if status_every_s > 0 else math.inf
        dirty = False
        try:
            reader.start()
            while True:
                try:
                    item = q.get(timeout=0.2)
                except queue.Empty:
                    item = None
                if item is _END:
                    dirty = self._release() or dirty  # a stream shorter than the wait for a GPS fix
                    break
                if isinstance(item, BaseException):
                    raise item
                if item is not None and self._offer(*item):
                    dirty = True
                now = time.monotonic()
                if dirty and now >= next_ckpt:
                    self.save_checkpoint()
                    dirty = False
                    next_ckpt = now + checkpoint_every_s
                if now >= next_status:
                    print(status_line(self.link_stats(), self.data_s(), self.cal.missing_motion(), self.resumes),
                          file=self.out, flush=True)
                    next_status = now + status_every_s
        finally:
            self.src.stop()
            reader.join(5.0)
            for sig, h in old.items():
                signal.signal(sig, h)

    def finish(self, json_out: str | Path | None) -> LiveResult:
        """After the stream: flush the filter, write the calibration JSON, the last checkpoint and trace
        rows, and the final status line; the result. LogError when no sample arrived."""
        cal = self.cal
        if self.fed["imu"] == 0:
            raise LogError(self.url, "no RAW_IMU sample received: no calibration written")
        cal.flush()
        wall = time.perf_counter() - self.t0
        res_cal = cal.result()
        stats = self.link_stats()
        stats["stop_reason"] = "interrupted" if self.stopped else self.src.stats["stop_reason"]
        online = {**res_cal.meta.get("online", {}), "link": {k: stats[k] for k in (*COUNTERS, "resumes")}}
        if self.segments:
            online["segments"] = [dict(b) for b in self.segments]
        res_cal = res_cal.replace(meta={**res_cal.meta, "online": online})  # calibrations are immutable
        if json_out is not None:
            write_atomic(json_out, res_cal.to_json() + "\n")
        self.save_checkpoint()
        self.trace.add(cal.trace_rows(clear=True))
        data_s = self.data_s()
        print(status_line(stats, data_s, cal.missing_motion(), self.resumes), file=self.out, flush=True)
        result = LiveResult(res_cal, list(cal.events), cal.nis_summary(), cal.observability(),
                            cal.missing_motion(), [], int(self.fed["imu"]), wall, data_s, None, link=stats,
                            stop_reason=stats["stop_reason"], checkpoints=self.n_ckpt, resumes=self.resumes,
                            warnings=list(self.src.warnings) + self.notes)
        result.boundaries = [dict(b) for b in self.segments]
        result.raw_digest = self.digest
        return result


def _apply(result: LiveResult, apply: str, exporter: tuple[Callable[..., dict[str, float]], frozenset[str]],
           src: LiveSource, out: TextIO) -> None:
    """Set the result's calibration as ``apply`` ('ardupilot' | 'px4') parameters on the vehicle and record
    each parameter's confirmation (or why the calibration cannot be expressed) in ``result``. The parameters
    of a sensor the health verdict names are not set (:func:`onlinecal.export.guard`: the verdict of the
    result's calibration, its NIS and events, and here also gravity at rest and the rail read from the samples
    fed): the vehicle keeps its own."""
    from ..health import VERDICTS, gravity_checks, rail_checks

    vehicle_params, int_names = exporter
    result.apply_format = apply
    found = gravity_checks(result.calibration, result.raw_digest)[0] + rail_checks(result.raw_digest)[0]
    health = ({"verdict": max((v for v, _ in found), key=VERDICTS.index), "reasons": [r for _, r in found]}
              if found else None)
    try:
        params = vehicle_params(result.calibration, apply, health=health)
    except ValueError as e:  # export.ExportError: not expressible in the firmware's parameters
        result.apply_error = f"the calibration cannot be set as {apply} parameters: {e}"
        result.applied = {}
        return
    print(f"onlinecal run: setting {len(params)} {apply} parameters on the vehicle", file=out, flush=True)
    types = {n: MAV_PARAM_TYPE_INT32 for n in params if n in int_names}
    result.applied = src.set_params(params, types=types, bytewise=apply == "px4")
