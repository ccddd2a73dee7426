"""Replay of recorded logs through the online calibrator, as fast as the data allows, and the trace writer."""

from __future__ import annotations

import csv
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..io.base import ImuData, split_boundaries
from ..model import Calibration
from .config import UKFConfig

if TYPE_CHECKING:
    from .filter import OnlineCalibrator


@dataclass
class OnlineResult:
    """What a replay produced: the calibration (source "online", σ for every parameter), the events
    (divergences, gaps, the mag cold start), the NIS summary, per-parameter observability (posterior σ /
    prior σ), the motions still missing, the trace rows, and the speed (samples, wall time, log time).
    ``boundaries``: the clock segments met (each with ``log``, the index of its log; see ImuData.boundaries),
    also in ``calibration.meta["online"]["segments"]``. ``warnings``: one sentence per boundary met."""

    calibration: Calibration
    events: list[dict[str, Any]]
    nis: dict[str, Any]
    observability: dict[str, dict[str, Any]]
    missing_motion: list[str]
    trace: list[dict[str, float]] = field(default_factory=list)
    n_imu: int = 0
    wall_s: float = 0.0
    log_s: float = 0.0
    state: dict[str, Any] | None = None
    boundaries: list[dict[str, Any]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def realtime_factor(self) -> float:
        return self.log_s / self.wall_s if self.wall_s > 0 else float("inf")


def replay(logs: list[ImuData], init: Calibration | None = None, config: UKFConfig | None = None,
           chunk: int | None = None, trace_path: str | Path | None = None,
           keep_state: bool = False,
           on_progress: Callable[[int, int], None] | None = None) -> OnlineResult:
    """Run the UKF over logs in order (each log restarts the attitude, the calibration carries over).

    A log's clock-segment boundaries (a vehicle reboot, a clock jump: ``ImuData.boundaries``) restart the
    attitude as a new log does, and the samples either side are never fed as one stretch.
    ``chunk``: feed the logs in blocks of this many IMU samples (None: each log in one call — the
    calibrator cuts its own filter blocks either way). ``trace_path``: write the trace CSV there.
    ``on_progress(samples_done, samples_total)``: called after every block fed, across all logs.
    Burst-read stamps are replaced by a fitted sample clock first (:func:`.batch.clock.regularise_for_filter`,
    a sentence in ``warnings`` for each).
    """
    from ..batch.clock import regularise_for_filter

    # burst-read stamps (a logger's read times) would set the filter's rate and blocks from the bursts and
    # integrate the gyro on the wrong instants: the fitted clock the batch uses (issue 10)
    fixed = [regularise_for_filter(d) for d in logs]
    logs = [d for d, _ in fixed]
    total = int(sum(d.n_imu for d in logs))
    res = replay_stream(([d] for d in logs), init, config, chunk, trace_path, keep_state, on_progress, total)
    res.warnings = [n for _, notes in fixed for n in notes] + res.warnings
    return res


def replay_stream(logs: Iterable[Iterable[ImuData]], init: Calibration | None = None,
                  config: UKFConfig | None = None, chunk: int | None = None,
                  trace_path: str | Path | None = None, keep_state: bool = False,
                  on_progress: Callable[[int, int], None] | None = None, total: int = 0) -> OnlineResult:
    """:func:`replay` over logs given as streams of blocks (e.g. ``open_log(p).blocks()``), so memory does
    not grow with a log's length: each block is fed and dropped. ``total``: the sample count reported to
    ``on_progress`` (0 when unknown)."""
    from .filter import OnlineCalibrator  # the filter and its kernels load here, not with the package

    cal = OnlineCalibrator(init, config)
    t0 = time.perf_counter()
    log_s = 0.0
    done = 0
    bounds: list[dict[str, Any]] = []
    for k, blocks in enumerate(logs):
        cal.new_log()
        last: float | None = None  # latest sample time of the current segment
        for block in blocks:
            bounds += [{"log": k, "source": block.source, **b} for b in block.boundaries]
            for new_segment, piece in split_boundaries(block):
                if new_segment:
                    cal.new_log()  # the attitude restarts, the calibration carries over
                    last = None
                done = _feed(cal, piece, chunk, done, total, on_progress)
                span = _span(piece)
                if span is not None:
                    log_s += span[1] - (span[0] if last is None else last)
                    last = span[1]
        cal.flush()
    wall = time.perf_counter() - t0
    rows = cal.trace_rows()
    if trace_path is not None:
        write_trace(trace_path, rows)
    res_cal = cal.result()
    if bounds:
        online = {**res_cal.meta.get("online", {}), "segments": [dict(b) for b in bounds]}
        res_cal = res_cal.replace(meta={**res_cal.meta, "online": online})  # calibrations are immutable
    said = [f"{Path(b['source']).name}: new segment at t={b['t']:.3f} s ({b['cause']}: raw clock "
            f"{b['before_s']:.3f} s -> {b['after_s']:.3f} s): attitude restarted, calibration carried over"
            for b in bounds]
    return OnlineResult(res_cal, list(cal.events), cal.nis_summary(), cal.observability(),
                        cal.missing_motion(), rows, cal._n_imu, wall, log_s,
                        cal.get_state() if keep_state else None, bounds, said)


def _feed(cal: OnlineCalibrator, d: ImuData, chunk: int | None, done: int, total: int,
          on_progress: Callable[[int, int], None] | None) -> int:
    """Feed ``d`` (in blocks of ``chunk`` IMU samples, or whole); returns the samples done so far."""
    if chunk is None:
        cal.feed(d)
        done += d.n_imu
        if on_progress is not None:
            on_progress(done, total)
        return done
    for i in range(0, d.n_imu, chunk):
        cal.feed(d.slice_imu(i, i + chunk))
        if on_progress is not None:
            on_progress(done + min(i + chunk, d.n_imu), total)
    return done + d.n_imu


def _span(d: ImuData) -> tuple[float, float] | None:
    """(first, last) sample time of ``d`` over both sensors, None when empty."""
    ts = [t for t in (d.t_imu, d.t_mag) if t.size]
    if not ts:
        return None
    return min(float(t[0]) for t in ts), max(float(t[-1]) for t in ts)


def write_trace(path: str | Path, rows: list[dict[str, float]]) -> None:
    """Trace CSV: one row per ``trace_every_s`` with t, every estimate and its σ (``name.sigma``), NIS."""
    p = Path(path)
    if not rows:
        p.write_text("t\n")
        return
    with p.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0].keys()))
        w.writeheader()
        w.writerows(rows)
