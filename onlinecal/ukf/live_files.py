"""The files of a live run (:mod:`.live_run`): the checkpoint (written atomically, read back with every
part checked), the trace CSV appended as the run goes, and the status line.

A checkpoint holds the filter state (:meth:`OnlineCalibrator.get_state`), the source position
(:meth:`onlinecal.io.live.LiveSource.position`), the link counters summed over resumes and the clock
segments, and the raw digest's small part (:meth:`onlinecal.health.RawDigest.state`: what the health verdict
reads of the samples fed, gravity at rest and the rail) with the count of its block rows, which are appended to
FILE.digest (:class:`DigestFile`). It is written to FILE.tmp, fsync'ed and ``os.replace``'d onto FILE (the
directory fsync'ed), so FILE is always the old or the new checkpoint, never half of one.
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..health import RawDigest
from ..io.base import LogError
from .filter import OnlineCalibrator

CHECKPOINT_SCHEMA = "onlinecal.live-checkpoint/2"
# /1: no raw digest (before session 20): resumed, its health verdict judges the samples fed since the resume
CHECKPOINT_SCHEMAS = ("onlinecal.live-checkpoint/1", CHECKPOINT_SCHEMA)
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
    if not isinstance(ck, dict) or ck.get("schema") not in CHECKPOINT_SCHEMAS:
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


def digest_path(checkpoint: str | Path) -> Path:
    """Where the block rows of a checkpoint's raw digest are kept: FILE.digest."""
    return Path(str(checkpoint) + ".digest")


def load_digest(ck: dict[str, Any], checkpoint: str | Path) -> tuple[RawDigest, DigestFile, str | None]:
    """The raw digest a checkpoint ``ck`` (read from ``checkpoint``) records, its rows file ready to append to, and
    a warning line where the digest could not be restored (a /1 checkpoint has none; FILE.digest missing, not a
    digest or short): the digest then starts empty and the health verdict judges the samples fed from here on —
    the calibration itself is resumed either way. LogError (one line) when the checkpoint's own digest entry is
    malformed (a damaged checkpoint, as any other part of it)."""
    rows_file = DigestFile(digest_path(checkpoint))
    entry = ck.get("digest")
    if entry is None:
        return RawDigest(), rows_file, (f"{checkpoint}: a checkpoint without the samples' raw digest (schema "
                                        f"{ck.get('schema')}): the health verdict judges the samples fed from this "
                                        "resume on")
    try:
        state = entry["state"]
        blocks = int(state["blocks"])
        if blocks < 0:
            raise ValueError(f"{blocks} blocks")
        RawDigest.from_state(state, np.zeros((blocks, RawDigest.ROW)))  # the small part checked before the file
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as e:
        raise LogError(str(checkpoint), f"damaged checkpoint (raw digest: {type(e).__name__}: {e})") from None
    try:
        rows = rows_file.resume(blocks)
    except ValueError as e:
        rows_file = DigestFile(rows_file.path)  # started anew at the first checkpoint
        return RawDigest(), rows_file, (f"{e}: the samples' raw digest is lost, the health verdict judges the samples "
                                        "fed from this resume on")
    return RawDigest.from_state(state, rows), rows_file, None


class DigestFile:
    """The raw digest's block rows (:meth:`onlinecal.health.RawDigest.rows`) beside the checkpoint, in FILE.digest:
    a header line, then rows of :attr:`RawDigest.ROW <onlinecal.health.RawDigest.ROW>` little-endian float64.

    The rows only grow (24 numbers per 50 samples: 5.5 MB for an hour at 400 Hz), so they are appended and
    fsync'ed before each checkpoint, which records how many belong to it; rewriting them whole into every
    checkpoint would write the hour's digest ~360 times. A crash between the append and the checkpoint's rename
    leaves rows past the count the checkpoint on disk records: a resume cuts them off (their samples are the
    ones after the checkpoint, not fed again)."""

    MAGIC = b"onlinecal.raw-digest/1\n"

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.written: int | None = None  # rows in the file that belong to this run (None: not started)

    def append(self, rows: np.ndarray) -> None:
        """Append ``rows`` (k, ROW) and make them durable (fsync); the first call of a new run starts the file."""
        data = np.ascontiguousarray(rows, dtype="<f8").tobytes()
        with self.path.open("wb" if self.written is None else "ab") as fh:
            if self.written is None:
                fh.write(self.MAGIC)
                self.written = 0
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        self.written += int(rows.shape[0])

    def resume(self, blocks: int) -> np.ndarray:
        """The first ``blocks`` rows (those the checkpoint records), the file cut to them so that the run appends
        after them. ValueError (one line) when the file is missing, not a digest, or short."""
        row = RawDigest.ROW
        try:
            raw = self.path.read_bytes()
        except FileNotFoundError:
            raise ValueError(f"{self.path}: missing") from None
        except OSError as e:
            raise ValueError(f"{self.path}: unreadable ({e.strerror or e})") from None
        if not raw.startswith(self.MAGIC):
            raise ValueError(f"{self.path}: not a raw digest (no {self.MAGIC.decode().strip()!r} header)")
        need = len(self.MAGIC) + 8 * row * blocks
        if len(raw) < need:
            have = (len(raw) - len(self.MAGIC)) // (8 * row)
            raise ValueError(f"{self.path}: holds {have} of the {blocks} blocks the checkpoint records")
        rows = np.frombuffer(raw[len(self.MAGIC): need], dtype="<f8").reshape(blocks, row).astype(float)
        if len(raw) > need:
            with self.path.open("r+b") as fh:
                fh.truncate(need)
                os.fsync(fh.fileno())
        self.written = blocks
        return rows


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
