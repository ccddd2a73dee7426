"""A small progress bar on stderr for anything that runs more than a couple of seconds.

Off when ``--quiet`` was given (:func:`set_quiet`) and off when the stream is not a terminal (pipes, files,
CI logs), so machine-readable output is never interleaved with bar redraws. The bar draws nothing during
its first ``delay_s`` (0.5 s), so quick steps do not flicker.

API (used by ``batch``, ``replay`` and open to ``diagnose``)::

    from onlinecal.progress import bar, stages

    with bar(total=n_samples, desc="replay", unit="samples") as pb:   # a counted quantity
        for block in blocks:
            ...
            pb.update(len(block))          # or pb.set(done)

    with stages(["read", "segment", "fit", "report"], desc="batch") as st:   # named steps
        st.next("read"); ...
        st.next("fit"); ...

Both are no-ops (cheap, draw nothing) when disabled; :func:`enabled` says whether a bar would be drawn.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from types import TracebackType
from typing import TextIO

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


def _fmt_s(s: float) -> str:
    s = max(0.0, s)
    return f"{s:.0f}s" if s < 60 else f"{int(s // 60)}m{int(s % 60):02d}s"


class Progress:
    """One bar: ``desc [#####.....]  42%  12/30 unit  3s<4s``.

    ``total`` None draws a counter without percentage. Redraws at most every ``min_interval_s``.
    """

    def __init__(self, total: float | None, desc: str = "", unit: str = "", stream: TextIO | None = None,
                 enable: bool | None = None, delay_s: float = 0.5, min_interval_s: float = 0.1,
                 width: int = 24) -> None:
        self.stream = sys.stderr if stream is None else stream
        self.on = enabled(self.stream) if enable is None else bool(enable)
        self.total = total
        self.desc = desc
        self.unit = unit
        self.n = 0.0
        self.note = ""
        self.width = width
        self.delay_s = delay_s
        self.min_interval_s = min_interval_s
        self._t0 = time.monotonic()
        self._last = -1e9
        self._drawn = False

    def update(self, n: float = 1) -> None:
        self.set(self.n + n)

    def set(self, n: float, note: str | None = None) -> None:
        self.n = n
        if note is not None:
            self.note = note
        if self.on:
            now = time.monotonic()
            if now - self._t0 >= self.delay_s and now - self._last >= self.min_interval_s:
                self._draw(now)

    def _line(self, now: float) -> str:
        el = now - self._t0
        if self.total:
            f = min(1.0, max(0.0, self.n / self.total))
            k = int(round(f * self.width))
            eta = el * (1 - f) / f if f > 0 else float("nan")
            tail = f"<{_fmt_s(eta)}" if f > 0 and f < 1 else ""
            body = (f"[{'#' * k}{'.' * (self.width - k)}] {100 * f:3.0f}%  "
                    f"{self.n:.0f}/{self.total:.0f} {self.unit}  {_fmt_s(el)}{tail}")
        else:
            body = f"{self.n:.0f} {self.unit}  {_fmt_s(el)}"
        return f"{self.desc} {body}" + (f"  {self.note}" if self.note else "")

    def _draw(self, now: float) -> None:
        line = self._line(now)
        self.stream.write("\r" + line[:200] + "\x1b[K")
        self.stream.flush()
        self._last = now
        self._drawn = True

    def close(self) -> None:
        """Draw the final state (only if the bar was ever shown) and end the line."""
        if self.on and self._drawn:
            self._draw(time.monotonic())
            self.stream.write("\n")
            self.stream.flush()
        self.on = False

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        self.close()


class Stages(Progress):
    """A bar over named steps: ``next(name)`` finishes the step before and starts ``name``."""

    def __init__(self, names: Sequence[str], desc: str = "", **kw: object) -> None:
        super().__init__(len(names), desc, unit="steps", **kw)  # type: ignore[arg-type]
        self.names = list(names)
        self._i = -1

    def next(self, name: str | None = None) -> None:
        self._i += 1
        label = name if name is not None else (self.names[self._i] if self._i < len(self.names) else "")
        self.set(self._i, note=label)


def bar(total: float | None, desc: str = "", unit: str = "", **kw: object) -> Progress:
    """A :class:`Progress` on stderr, drawn only when :func:`enabled`."""
    return Progress(total, desc, unit, **kw)  # type: ignore[arg-type]


def stages(names: Sequence[str], desc: str = "", **kw: object) -> Stages:
    """A :class:`Stages` bar on stderr, drawn only when :func:`enabled`."""
    return Stages(names, desc, **kw)
