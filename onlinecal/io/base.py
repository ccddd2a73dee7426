"""The one data type every reader produces and every stage consumes, and the reader errors.

Units inside the package: time s, gyro rad/s, accel m/s² (specific force), mag in the unit read,
temperature °C (NaN where absent). IMU (gyro+accel+temp) and magnetometer keep separate clocks.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


_LINE_BREAKS = re.compile(r"[\n\r\v\f\x1c\x1d\x1e\x85\u2028\u2029]+")  # what str.splitlines splits on
_MESSAGE_LIMIT = 300  # characters of ``message`` kept (a library's exception text can be long)


def _one_line(text: str, limit: int | None = None) -> str:
    text = _LINE_BREAKS.sub(" ", text)
    return text if limit is None or len(text) <= limit else text[:limit - 3] + "..."


class LogError(Exception):
    """Unusable input. ``str()`` is the one line the CLI prints: ``path: where: problem``.

    ``message`` and ``where`` are kept to one line (line breaks, e.g. from a wrapped library exception,
    become spaces) and ``message`` to at most ``_MESSAGE_LIMIT`` characters.
    """

    def __init__(self, path: str, message: str, where: str | None = None) -> None:
        self.path = str(path)
        self.message = _one_line(str(message), _MESSAGE_LIMIT)
        self.where = _one_line(str(where)) if where else None
        head = _one_line(self.path)
        super().__init__(f"{head}: {self.where}: {self.message}" if self.where else f"{head}: {self.message}")


@dataclass
class ImuData:
    """A stretch of one sensor unit's samples.

    t_imu (N,) s · gyro (N, 3) rad/s · acc (N, 3) m/s² · temp (N,) °C (NaN if absent)
    t_mag (M,) s · mag (M, 3) sensor unit · source: file it came from · warnings: what the reader
    dropped or repaired, one sentence each.
    """

    t_imu: Array
    gyro: Array
    acc: Array
    temp: Array
    t_mag: Array
    mag: Array
    source: str = ""
    warnings: list[str] = field(default_factory=list)

    @classmethod
    def empty(cls, source: str = "") -> ImuData:
        z = np.zeros(0)
        z3 = np.zeros((0, 3))
        return cls(z, z3, z3.copy(), z.copy(), z.copy(), z3.copy(), source)

    @property
    def n_imu(self) -> int:
        return int(self.t_imu.shape[0])

    @property
    def n_mag(self) -> int:
        return int(self.t_mag.shape[0])

    @property
    def has_mag(self) -> bool:
        return self.n_mag > 0

    @property
    def duration(self) -> float:
        ts = [t for t in (self.t_imu, self.t_mag) if t.size]
        if not ts:
            return 0.0
        return float(max(t[-1] for t in ts) - min(t[0] for t in ts))

    @property
    def imu_rate(self) -> float:
        """Mean IMU sample rate, Hz: samples per second over the log (a logger that stamps buffered
        reads in bursts has a median period far shorter than its real one)."""
        if self.n_imu < 2 or self.t_imu[-1] <= self.t_imu[0]:
            return float("nan")
        return float((self.n_imu - 1) / (self.t_imu[-1] - self.t_imu[0]))

    def slice_imu(self, i0: int, i1: int) -> ImuData:
        """Samples of IMU rows i0:i1 and the mag samples from t_imu[i0] up to (not including) t_imu[i1].

        The mag window runs to the next chunk's first IMU stamp, and the first/last chunk take the mag samples
        before/after all IMU samples, so consecutive slices partition the mag samples: none is lost or doubled
        when a log is fed in chunks.
        """
        n = self.n_imu
        i0, i1 = max(0, min(i0, n)), max(0, min(i1, n))
        t = self.t_imu[i0:i1]
        if t.size:
            lo = -np.inf if i0 == 0 else self.t_imu[i0]
            hi = np.inf if i1 >= n else self.t_imu[i1]
            m = (self.t_mag >= lo) & (self.t_mag < hi)
        else:
            m = np.zeros(self.n_mag, bool)
        return ImuData(
            t, self.gyro[i0:i1], self.acc[i0:i1], self.temp[i0:i1], self.t_mag[m], self.mag[m],
            self.source, list(self.warnings),
        )

    @staticmethod
    def concat(blocks: Iterable[ImuData], source: str | None = None) -> ImuData:
        """Join consecutive blocks of one log (times must already be increasing)."""
        bl = list(blocks)
        if not bl:
            return ImuData.empty(source or "")
        warnings: list[str] = []
        for b in bl:
            for w in b.warnings:
                if w not in warnings:
                    warnings.append(w)
        return ImuData(
            np.concatenate([b.t_imu for b in bl]),
            np.concatenate([b.gyro for b in bl]).reshape(-1, 3),
            np.concatenate([b.acc for b in bl]).reshape(-1, 3),
            np.concatenate([b.temp for b in bl]),
            np.concatenate([b.t_mag for b in bl]),
            np.concatenate([b.mag for b in bl]).reshape(-1, 3),
            source if source is not None else bl[0].source,
            warnings,
        )


class LogReader(Protocol):
    """What every format's reader offers: stream a log in blocks of bounded size.

    Memory is constant in the length of the log: each block holds at most ``max_samples`` IMU
    samples (plus the mag samples in the same time span). Warnings about dropped or repaired samples
    accumulate in ``warnings`` and are copied onto each block.
    """

    path: str
    warnings: list[str]

    def blocks(self, max_samples: int = 4096) -> Iterator[ImuData]: ...
