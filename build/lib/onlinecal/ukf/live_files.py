"""The files of a live run (:mod:`.live_run`): the checkpoint (written atomically, read back with every
part checked), the trace CSV appended as the run goes, and the status line.

A checkpoint holds the filter state (:meth:`OnlineCalibrator.get_state`), the source position
(:meth:`onlinecal.io.live.LiveSource.position`), the link counters summed over resumes and the clock
segments. It is written to FILE.tmp, fsync'ed and ``os.replace``'d onto FILE (the directory fsync'ed), so
FILE is always the old or the new checkpoint, never half of one.
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from ..io.base import LogError
from .filter import OnlineCalibrator

CHECKPOINT_SCHEMA = "onlinecal.live-checkpoint/1"
# Link counters that add up over the runs of one calibration (a resumed run continues them).
COUNTERS = ("received", "emitted", "lost", "mag", "mag_uncertain", "duplicates", "reordered", "dropped_late",
             "reconnects", "ack", "interval_requests", "heartbeats", "ignored", "bad_data", "clock_resets")


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


class TraceCsv:
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


def status_line(link: dict[str, Any], data_s: float, missing: list[str], resumes: int) -> str:
    """The periodic one-line status of a live run: data time, link counters, the motion still needed."""
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
