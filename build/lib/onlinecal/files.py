"""Output files: one atomic writer, one strict-JSON sanitiser, and the checks made before any work starts.

* :func:`sanitize` turns anything the package produces into plain RFC 8259 JSON values: non-finite floats
  become ``null`` (bare ``NaN``/``Infinity`` are invalid JSON for most parsers), numpy scalars and arrays
  plain numbers and lists, tuples lists, dict keys strings.
* :func:`dumps` is ``json.dumps`` of the sanitised object with ``allow_nan=False`` (so a missed case raises
  here instead of writing invalid JSON).
* :func:`atomic_write` writes text or bytes to a temporary file in the same directory and renames it over the
  target (POSIX ``rename`` is atomic): a crash or Ctrl-C never leaves half a file. ``-`` means stdout.
* :func:`check_output_file` / :func:`check_output_dir` say, before a long fit, whether an output can be
  written at all (the directory exists and is writable, the target is not a directory), raising
  :class:`OutputError` with one line naming the path.
"""

from __future__ import annotations

import json
import math
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

STDOUT = "-"


class OutputError(ValueError):
    """An output path that cannot be written (message names the path and the reason)."""


def sanitize(x: Any) -> Any:
    """Plain JSON values (RFC 8259): non-finite floats → None, numpy → Python, tuples → lists, keys → str."""
    if isinstance(x, dict):
        return {str(k): sanitize(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [sanitize(v) for v in x]
    if isinstance(x, np.ndarray):
        return sanitize(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, Path):
        return str(x)
    return x


def dumps(obj: Any, indent: int | None = 2) -> str:
    """Strict JSON text of ``obj`` (sanitised first; never ``NaN`` or ``Infinity``)."""
    return json.dumps(sanitize(obj), indent=indent, allow_nan=False, ensure_ascii=False)


def atomic_write(path: str | Path, data: str | bytes, oserror: bool = False) -> None:
    """Write ``data`` to ``path`` atomically (temp file in the same directory, fsync, rename); ``-``: stdout.

    The temporary name is unique (``tempfile.mkstemp``), so two writers never share it, and it is removed
    when the write fails; the directory is fsynced after the rename. Raises :class:`OutputError` (a
    ``ValueError``) naming the path when it cannot be written, or the ``OSError`` itself with ``oserror``.
    """
    if str(path) == STDOUT:
        if isinstance(data, bytes):
            sys.stdout.flush()
            sys.stdout.buffer.write(data)
            sys.stdout.buffer.flush()
        else:
            sys.stdout.write(data)
            sys.stdout.flush()
        return
    p = Path(path)
    raw = data.encode("utf-8") if isinstance(data, str) else data
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent if str(p.parent) else ".")
    except OSError as e:
        if oserror:
            raise
        raise OutputError(f"{path}: cannot write ({e.strerror or e})") from None
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(raw)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o644)  # mkstemp makes 0600; an output file is an ordinary, readable file
        os.replace(tmp, p)
        _fsync_dir(p.parent if str(p.parent) else Path("."))
    except BaseException as e:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(e, OSError) and not oserror:
            raise OutputError(f"{path}: cannot write ({e.strerror or e})") from None
        raise


def _fsync_dir(d: Path) -> None:
    """Make the rename itself durable (not every platform/filesystem lets a directory be opened)."""
    try:
        fd = os.open(d, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def write_json(path: str | Path, obj: Any) -> None:
    """Strict JSON of ``obj`` (:func:`dumps`) written atomically to ``path`` (``-``: stdout)."""
    atomic_write(path, dumps(obj) + "\n")


def check_output_file(path: str | Path | None, option: str = "", exist_ok: bool = True) -> None:
    """Raise :class:`OutputError` unless ``path`` can be written (``-`` and None always pass).

    Checked: the parent directory exists and is a writable directory, the path itself is not a directory
    (nor an existing non-regular file such as /proc entries), and, with ``exist_ok=False``, does not exist.
    """
    if path is None or str(path) == STDOUT:
        return
    p = Path(path)
    pre = f"{option} {path}" if option else str(path)
    if str(path) == "":
        raise OutputError(f"{option or 'output'}: empty file name")
    parent = p.parent if str(p.parent) else Path(".")
    if p.is_dir():
        raise OutputError(f"{pre}: is a directory, not a file")
    if p.exists() and not exist_ok:
        raise OutputError(f"{pre}: already exists (give a new name)")
    if p.exists() and not p.is_file():
        raise OutputError(f"{pre}: not a regular file")
    if not parent.is_dir():
        raise OutputError(f"{pre}: directory {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK) or str(parent.resolve()).startswith(("/proc", "/sys")):
        raise OutputError(f"{pre}: directory {parent} is not writable")
    if p.exists() and not os.access(p, os.W_OK):
        raise OutputError(f"{pre}: not writable")


def check_output_dir(path: str | Path | None, option: str = "", must_be_new: bool = False) -> None:
    """Raise :class:`OutputError` unless ``path`` is, or can be created as, a writable directory."""
    if path is None:
        return
    p = Path(path)
    pre = f"{option} {path}" if option else str(path)
    if str(path) in ("", STDOUT):
        raise OutputError(f"{option or 'output'}: {path!r} is not a directory name")
    if p.exists() and not p.is_dir():
        raise OutputError(f"{pre}: exists and is not a directory")
    if p.exists() and must_be_new and any(p.iterdir()):
        raise OutputError(f"{pre}: directory is not empty")
    probe = p
    while not probe.exists():  # the nearest existing ancestor must let us create the rest
        probe = probe.parent if str(probe.parent) else Path(".")
        if probe == probe.parent and not probe.exists():
            break
    if not probe.is_dir():
        raise OutputError(f"{pre}: {probe} is not a directory")
    if not os.access(probe, os.W_OK | os.X_OK) or str(probe.resolve()).startswith(("/proc", "/sys")):
        raise OutputError(f"{pre}: {probe} is not writable")
