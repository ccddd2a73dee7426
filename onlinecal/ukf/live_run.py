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

import contextlib
import csv
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
from typing import Any, TextIO

import numpy as np

from ..io.base import ImuData, LogError, split_boundaries
from ..io.mavlink import MAV_PARAM_TYPE_INT32
from ..model import Calibration
from .filter import OnlineCalibrator, UKFConfig
from .replay import OnlineResult

CHECKPOINT_SCHEMA = "onlinecal.live-checkpoint/1"
# Link counters that add up over the runs of one calibration (a resumed run continues them).
_COUNTERS = ("received", "emitted", "lost", "mag", "mag_uncertain", "duplicates", "reordered", "dropped_late",
             "reconnects", "ack", "interval_requests", "heartbeats", "ignored", "bad_data", "clock_resets")
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

    @property
    def apply_failed(self) -> list[str]:
        """Names of the parameters the vehicle did not confirm (empty without ``apply``)."""
        return [n for n, r in (self.applied or {}).items() if not r["ok"]]


def write_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` so that a crash at any moment leaves the old or the new file: PATH.tmp,
    fsync, os.replace, then fsync of the directory (the rename itself made durable)."""
    from ..files import atomic_write  # the package's one writer (callers here handle its OSError)

    atomic_write(path, text, oserror=True)


def load_checkpoint(path: str | Path) -> tuple[dict[str, Any], OnlineCalibrator]:
    """Read a checkpoint and rebuild its calibrator. LogError(path, one line) when it is unusable."""
    p = str(path)
    try:
        text = Path(p).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise LogError(p, "no such checkpoint") from None
    except (OSError, UnicodeDecodeError) as e:
        raise LogError(p, f"unreadable checkpoint ({getattr(e, 'strerror', None) or e})") from None
    try:
        ck = json.loads(text)
    except ValueError as e:
        raise LogError(p, f"not a checkpoint: invalid JSON ({e})") from None
    if not isinstance(ck, dict) or ck.get("schema") != CHECKPOINT_SCHEMA:
        got = ck.get("schema") if isinstance(ck, dict) else type(ck).__name__
        raise LogError(p, f"not a checkpoint (schema {got!r}, expected {CHECKPOINT_SCHEMA!r})")
    try:
        st = ck["filter"]
        n = np.asarray(st["x"], float).size
        if np.shape(st["P"]) != (n, n):
            raise ValueError(f"the covariance is {np.shape(st['P'])}, not {n}×{n}")
        cal = OnlineCalibrator.from_state(st)
        cal.result()  # every part of the state in use once, here rather than an hour into the run
        pos = ck["source"]
        int(pos["last_us"]), int(pos["offset_us"])
        int(ck["fed"]["imu"])
    except (KeyError, TypeError, ValueError, IndexError, AttributeError, np.linalg.LinAlgError) as e:
        raise LogError(p, f"damaged checkpoint ({type(e).__name__}: {e})") from None
    return ck, cal


def _vehicle_params() -> tuple[Callable[[Calibration, str], dict[str, float]], frozenset[str]]:
    """``onlinecal.export.vehicle_params`` and the names of its integer parameters, imported when asked
    for (ImportError names what is missing)."""
    try:
        from ..export import vehicle_params
    except ImportError as e:
        raise ImportError(f"--apply needs onlinecal.export.vehicle_params, which this build lacks ({e})") from e
    from .. import export

    return vehicle_params, frozenset(getattr(export, "INT32_PARAMS", ()))


class _Trace:
    """Trace rows appended to a CSV as the run goes (so the checkpoint need not carry them). On resume, rows
    at or before the last time already in the file are skipped (they were written after the checkpoint)."""

    def __init__(self, path: str | Path | None, resume: bool) -> None:
        self.path = None if path is None else Path(path)
        self.fields: list[str] | None = None
        self.last_t = -math.inf
        if self.path is not None and resume and self.path.is_file():
            with self.path.open(newline="") as fh:
                r = csv.DictReader(fh)
                self.fields = list(r.fieldnames or []) or None
                for row in r:
                    with contextlib.suppress(KeyError, TypeError, ValueError):
                        self.last_t = max(self.last_t, float(row["t"]))
        elif self.path is not None:
            self.path.write_text("")

    def add(self, rows: list[dict[str, float]]) -> None:
        rows = [r for r in rows if r["t"] > self.last_t]
        if self.path is None or not rows:
            return
        new = self.fields is None
        if new:
            self.fields = list(rows[0].keys())
        with self.path.open("a", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=self.fields or [], extrasaction="ignore")
            if new:
                w.writeheader()
            w.writerows(rows)
        self.last_t = rows[-1]["t"]


def _status(link: dict[str, Any], data_s: float, missing: list[str], resumes: int) -> str:
    got = link["emitted"] + link["lost"]
    lost_pc = 100.0 * link["lost"] / got if got else 0.0
    line = (f"onlinecal run: {data_s:7.1f} s of data | received {link['received']}, lost {link['lost']} "
            f"({lost_pc:.1f} %), duplicates {link['duplicates']}, reordered {link['reordered']}, "
            f"late {link['dropped_late']}, reconnects {link['reconnects']}")
    if resumes:
        line += f", resumes {resumes}"
    if missing:
        line += " | still needed: " + "; ".join(missing[:3]) + (" …" if len(missing) > 3 else "")
    return line


def run_live(url: str, init: Calibration | None = None, *, config: UKFConfig | None = None,
             duration_s: float | None = None, json_out: str | Path | None = None,
             trace_out: str | Path | None = None, checkpoint: str | Path | None = None,
             checkpoint_every_s: float = 10.0, resume: bool = False, rate_hz: float = 100.0,
             apply: str | None = None, status_every_s: float | None = None,
             acc_scale: float | None = None, gyro_scale: float | None = None, mag_scale: float | None = None,
             source_options: dict[str, Any] | None = None, log: TextIO | None = None,
             transform: Callable[[ImuData], ImuData] | None = None, idle_timeout_s: float | None = 10.0,
             imu: int = 0, source_system: int | None = None,
             source_component: int | None = None) -> LiveResult:
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
    A vehicle clock restart (reboot, also between a checkpoint and ``resume``) is a clock segment: the
    attitude restarts there, the calibration carries over, and the result names it in
    ``meta["online"]["segments"]``.

    Raises LogError when the link cannot be opened, the checkpoint is unusable, or no sample arrived.
    """
    from ..io.live import LiveSource

    out = log if log is not None else sys.stderr
    if apply is not None and apply not in ("ardupilot", "px4"):
        raise ValueError(f"apply must be 'ardupilot' or 'px4', got {apply!r}")
    if resume and checkpoint is None:
        raise ValueError("resume needs a checkpoint file")
    if not checkpoint_every_s > 0:
        raise ValueError("checkpoint_every_s must be > 0")
    exporter = _vehicle_params() if apply else None  # fail before the run, not after it
    if status_every_s is None:
        status_every_s = 5.0 if out.isatty() else 30.0

    ck: dict[str, Any] | None = None
    if resume and checkpoint is not None and not Path(checkpoint).exists():
        print(f"onlinecal run: {checkpoint}: no checkpoint yet, starting a new run", file=out)
    elif resume and checkpoint is not None:
        ck, cal = load_checkpoint(checkpoint)
        if init is not None:
            print("onlinecal run: --init is ignored when resuming (the checkpoint has its own)", file=out)
        if duration_s is None:
            duration_s = ck.get("duration_s")
    if ck is None:
        cal = OnlineCalibrator(init, config)
    base = dict(ck["link"]) if ck else {}
    resumes = int(base.get("resumes", 0)) + (1 if ck else 0)
    fed: dict[str, Any] = dict(ck["fed"]) if ck else {"imu": 0, "t_first": None, "t_last": None}
    trace = _Trace(trace_out, resume=ck is not None)

    opts = dict(source_options or {})
    opts.setdefault("timeout_s", idle_timeout_s)
    src = LiveSource(url, rate_hz=rate_hz, duration_s=duration_s, acc_scale=acc_scale, gyro_scale=gyro_scale,
                     mag_scale=mag_scale, imu=imu, source_system=source_system, source_component=source_component,
                     **opts)
    segments: list[dict[str, Any]] = list(ck.get("segments", [])) if ck else []
    if ck is not None:
        try:
            src.resume_from(ck["source"])
        except ValueError as e:
            src.close()
            raise LogError(str(checkpoint), f"damaged checkpoint ({e})") from None

    def link_stats() -> dict[str, Any]:
        st = dict(src.stats)
        for k in _COUNTERS:
            st[k] = int(base.get(k, 0)) + int(st.get(k, 0))
        st["resumes"] = resumes
        return st

    n_ckpt = 0
    pos_fed: dict[str, Any] | None = ck["source"] if ck else None  # source position of the last block fed

    def save_checkpoint() -> None:
        nonlocal n_ckpt
        pos = pos_fed
        if checkpoint is None or pos is None:
            return
        trace.add(cal.trace_rows(clear=True))  # rows go to the CSV, not into every checkpoint
        payload = {"schema": CHECKPOINT_SCHEMA, "written": datetime.now(UTC).isoformat(),
                   "url": url, "rate_hz": rate_hz, "duration_s": duration_s, "source": pos,
                   "link": link_stats(), "fed": fed, "segments": segments, "filter": cal.get_state()}
        write_atomic(checkpoint, json.dumps(payload))
        n_ckpt += 1

    # Ctrl-C / SIGTERM end the stream; the run then finishes normally (flush, result, checkpoint).
    stopped: list[int] = []

    def on_signal(signum: int, frame: Any) -> None:
        stopped.append(signum)
        src.stop()

    old: dict[signal.Signals, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            old[sig] = signal.signal(sig, on_signal)
    print(f"onlinecal run: link open on {url}" + (f", resumed from {checkpoint}" if ck else "")
          + " (Ctrl-C ends the run with a result)", file=out, flush=True)
    # The link is read in its own thread: the socket is drained while the filter computes or a checkpoint
    # is fsync'ed, so a stall here costs memory (the queue), never packets (a full kernel buffer).
    q: queue.Queue[Any] = queue.Queue()

    def read_link() -> None:
        try:
            for block in src.blocks():
                q.put((block, src.position()))  # the position as of this very block
        except BaseException as e:  # handed to the main thread, which raises it
            q.put(e)
        finally:
            q.put(_END)

    reader = threading.Thread(target=read_link, name="onlinecal-link", daemon=True)
    t0 = time.perf_counter()
    now = time.monotonic()
    next_ckpt = now + checkpoint_every_s
    next_status = now + status_every_s if status_every_s > 0 else math.inf
    dirty = False
    try:
        reader.start()
        try:
            while True:
                try:
                    item = q.get(timeout=0.2)
                except queue.Empty:
                    item = None
                if item is _END:
                    break
                if isinstance(item, BaseException):
                    raise item
                if item is not None:
                    block, pos = item
                    if block.n_imu or block.n_mag:
                        segments += [dict(b) for b in block.boundaries]
                        for new_segment, piece in split_boundaries(block):
                            if new_segment:
                                cal.new_log()  # a vehicle reboot: the attitude restarts, the calibration stays
                            cal.feed(transform(piece) if transform is not None else piece)
                        pos_fed, dirty = pos, True
                        if block.n_imu:
                            fed["imu"] += block.n_imu
                            if fed["t_first"] is None:
                                fed["t_first"] = float(block.t_imu[0])
                            fed["t_last"] = float(block.t_imu[-1])
                now = time.monotonic()
                if dirty and now >= next_ckpt:
                    save_checkpoint()
                    dirty = False
                    next_ckpt = now + checkpoint_every_s
                if now >= next_status:
                    data_s = (fed["t_last"] - fed["t_first"]) if fed["t_first"] is not None else 0.0
                    print(_status(link_stats(), data_s, cal.missing_motion(), resumes), file=out, flush=True)
                    next_status = now + status_every_s
        finally:
            src.stop()
            reader.join(5.0)
            for sig, h in old.items():
                signal.signal(sig, h)
        if fed["imu"] == 0:
            raise LogError(url, "no RAW_IMU sample received: no calibration written")
        cal.flush()
        wall = time.perf_counter() - t0
        res_cal = cal.result()
        stats = link_stats()
        stats["stop_reason"] = "interrupted" if stopped else src.stats["stop_reason"]
        online = {**res_cal.meta.get("online", {}), "link": {k: stats[k] for k in (*_COUNTERS, "resumes")}}
        if segments:
            online["segments"] = [dict(b) for b in segments]
        res_cal = res_cal.replace(meta={**res_cal.meta, "online": online})  # calibrations are immutable
        if json_out is not None:
            write_atomic(json_out, res_cal.to_json() + "\n")
        save_checkpoint()
        trace.add(cal.trace_rows(clear=True))
        data_s = (fed["t_last"] - fed["t_first"]) if fed["t_first"] is not None else 0.0
        print(_status(stats, data_s, cal.missing_motion(), resumes), file=out, flush=True)
        result = LiveResult(res_cal, list(cal.events), cal.nis_summary(), cal.observability(),
                            cal.missing_motion(), [], int(fed["imu"]), wall, data_s, None, link=stats,
                            stop_reason=stats["stop_reason"], checkpoints=n_ckpt, resumes=resumes,
                            warnings=list(src.warnings))
        result.boundaries = [dict(b) for b in segments]
        if apply is not None and exporter is not None:
            vehicle_params, int_names = exporter
            result.apply_format = apply
            try:
                params = vehicle_params(res_cal, apply)
            except ValueError as e:  # export.ExportError: not expressible in the firmware's parameters
                result.apply_error = f"the calibration cannot be set as {apply} parameters: {e}"
                result.applied = {}
                return result
            print(f"onlinecal run: setting {len(params)} {apply} parameters on the vehicle", file=out, flush=True)
            types = {n: MAV_PARAM_TYPE_INT32 for n in params if n in int_names}
            result.applied = src.set_params(params, types=types, bytewise=apply == "px4")
        return result
    finally:
        src.close()

