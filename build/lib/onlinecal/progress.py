"""Progress bars on stderr (tqdm) for anything that runs more than a second.

Off when ``--quiet`` was given (:func:`set_quiet`) and off when the stream is not a terminal (pipes, files,
CI logs), so machine-readable output is never interleaved with bar redraws. A bar draws nothing during its
first ``delay_s`` (0.5 s), so quick steps do not flicker, and it is redrawn every ``tick_s`` by a
background ticker even while a long step reports nothing, so the elapsed time never freezes.

API (used by ``demo``, ``batch``, ``replay``, ``diagnose`` and the fleet)::

    from onlinecal.progress import bar, stages

    with bar(total=n_samples, desc="replay", unit="samples") as pb:   # a counted quantity
        for block in blocks:
            ...
            pb.update(len(block))          # or pb.set(done)

    with stages(["read", "segment", "fit", "report"], desc="batch") as st:   # named steps
        st.next("read"); ...
        st.next("fit"); ...

Both are no-ops (cheap, draw nothing) when disabled; :func:`enabled` says whether a bar would be drawn.
On a normal exit a bar ends at 100 %; on an exception it stays where the work stopped.
"""

from __future__ import annotations

import io
import os
import sys
import threading
from collections.abc import Sequence
from types import TracebackType
from typing import Any, TextIO

from tqdm import tqdm

_QUIET = False


def set_quiet(quiet: bool) -> None:
    """Turn every progress bar of this process off (``--quiet``) or back on."""
    global _QUIET
    _QUIET = bool(quiet)


def enabled(stream: TextIO | None = None) -> bool:
    """Whether a bar would be drawn on ``stream`` (default stderr): not quiet and a terminal."""
    s = sys.stderr if stream is None else stream
    if _QUIET:
        return False
    try:
        return bool(s.isatty())
    except (AttributeError, ValueError):  # closed or not a file
        return False


def _columns(stream: TextIO) -> int:
    """The terminal's width; a pseudo-terminal without a size (0 columns, 0 rows) would make tqdm draw
    nothing, so such a terminal gets 120 columns (and every bar ``nrows=20``)."""
    try:
        n = os.get_terminal_size(stream.fileno()).columns
    except (AttributeError, ValueError, OSError, io.UnsupportedOperation):
        n = 0
    return n if n >= 40 else 120


class Progress:
    """One tqdm bar: ``desc [#####.....]  42% 12/30 unit [00:03<00:04]  note``.

    ``total`` None draws a counter without percentage.
    """

    def __init__(self, total: float | None, desc: str = "", unit: str = "", stream: TextIO | None = None,
                 enable: bool | None = None, delay_s: float = 0.5, min_interval_s: float = 0.1,
                 tick_s: float = 0.5, width: int = 24) -> None:
        self.stream = sys.stderr if stream is None else stream
        self.on = enabled(self.stream) if enable is None else bool(enable)
        self.total = total
        self.n = 0.0
        self.note = ""
        self._bar: Any = None
        self._stop = threading.Event()
        self._ticker: threading.Thread | None = None
        if not self.on:
            return
        fmt = ("{desc} [{bar:" + str(width) + "}] {percentage:3.0f}% {n_fmt}/{total_fmt} " + unit
               + " [{elapsed}<{remaining}]{postfix}") if total else ("{desc} {n_fmt} " + unit + " [{elapsed}]{postfix}")
        self._bar = tqdm(total=total, desc=desc, file=self.stream, delay=delay_s, mininterval=min_interval_s,
                         ascii=".#", bar_format=fmt, ncols=_columns(self.stream), nrows=20, leave=True)
        if tick_s > 0:
            self._ticker = threading.Thread(target=self._tick, args=(tick_s,), daemon=True)
            self._ticker.start()

    def _tick(self, every: float) -> None:
        # a step that reports nothing for a while still shows its elapsed time moving
        while not self._stop.wait(every):
            b = self._bar
            if b is not None:
                try:
                    b.refresh()
                except (ValueError, OSError):  # the stream was closed under us
                    return

    def update(self, n: float = 1) -> None:
        self.set(self.n + n)

    def set(self, n: float, note: str | None = None) -> None:
        self.n = n
        if note is not None:
            self.note = note
        b = self._bar
        if b is not None:
            if note is not None:
                b.set_postfix_str(note, refresh=False)
            b.update(n - b.n)

    def close(self, complete: bool = True) -> None:
        """Stop the ticker, draw the final state (100 % when ``complete``) and end the line."""
        self._stop.set()
        if self._ticker is not None:
            self._ticker.join(timeout=2.0)
        b = self._bar
        if b is not None:
            if complete and self.total:
                b.update(self.total - b.n)
            b.close()
        self._bar = None
        self.on = False

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        self.close(complete=et is None)


class Stages(Progress):
    """A bar over named steps: ``next(name)`` finishes the step before and starts ``name``."""

    def __init__(self, names: Sequence[str], desc: str = "", **kw: Any) -> None:
        super().__init__(len(names), desc, unit="steps", **kw)
        self.names = list(names)
        self._i = -1

    def next(self, name: str | None = None) -> None:
        self._i += 1
        label = name if name is not None else (self.names[self._i] if self._i < len(self.names) else "")
        self.set(min(self._i, len(self.names)), note=label)

    def __enter__(self) -> Stages:
        return self


def bar(total: float | None, desc: str = "", unit: str = "", **kw: Any) -> Progress:
    """A :class:`Progress` on stderr, drawn only when :func:`enabled`."""
    return Progress(total, desc, unit, **kw)


def stages(names: Sequence[str], desc: str = "", **kw: Any) -> Stages:
    """A :class:`Stages` bar on stderr, drawn only when :func:`enabled`."""
    return Stages(names, desc, **kw)


def spinner(desc: str, **kw: Any) -> Progress:
    """A bar without a total for one long step whose progress is not counted (elapsed time ticks)."""
    return Progress(None, desc, "", **kw)
