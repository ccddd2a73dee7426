"""The one data type every reader produces and every stage consumes, and the reader errors.

Units inside the package: time s, gyro rad/s, accel m/s² (specific force), mag in the unit read,
temperature °C (NaN where absent). IMU (gyro+accel+temp) and magnetometer keep separate clocks.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

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

    boundaries: clock-segment boundaries (a vehicle reboot that restarted the clock, or a jump forward far
    beyond the gaps seen), each a dict with ``t`` (s, on this data's time line: the samples at or after it
    belong to the new segment; a restarted clock is shifted so the time line keeps increasing, with a gap),
    ``cause`` ("clock restart" | "clock jump"), ``before_s``/``after_s`` (the raw stamps either side).
    A consumer re-initialises the attitude at each and carries the calibration over
    (:func:`split_boundaries`). A streamed block that starts a new segment carries its boundary with
    ``t`` ≤ its first time.
    params: the log's firmware parameters (name → value; DataFlash PARM, ULog parameters), empty when the
    log has none. series: optional per-log series (name → (t (K,) s, values (K,))), e.g. ``current`` A,
    ``throttle`` 0..1, ``armed`` 0/1, empty when absent.
    """

    t_imu: Array
    gyro: Array
    acc: Array
    temp: Array
    t_mag: Array
    mag: Array
    source: str = ""
    warnings: list[str] = field(default_factory=list)
    boundaries: list[dict[str, Any]] = field(default_factory=list)
    params: dict[str, float] = field(default_factory=dict)
    series: dict[str, tuple[Array, Array]] = field(default_factory=dict)

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
            self.source, list(self.warnings), params=self.params,
        )

    @staticmethod
    def concat(blocks: Iterable[ImuData], source: str | None = None) -> ImuData:
        """Join consecutive blocks of one log (times must already be increasing)."""
        bl = list(blocks)
        if not bl:
            return ImuData.empty(source or "")
        warnings: list[str] = []
        bounds: list[dict[str, Any]] = []
        params: dict[str, float] = {}
        series: dict[str, list[tuple[Array, Array]]] = {}
        for b in bl:
            for w in b.warnings:
                if w not in warnings:
                    warnings.append(w)
            for s in b.boundaries:
                if all(s["t"] != o["t"] for o in bounds):
                    bounds.append(dict(s))
            params.update(b.params)
            for k, v in b.series.items():
                series.setdefault(k, []).append(v)
        joined = {k: (np.concatenate([a for a, _ in v]), np.concatenate([b for _, b in v])) for k, v in series.items()}
        return ImuData(
            np.concatenate([b.t_imu for b in bl]),
            np.concatenate([b.gyro for b in bl]).reshape(-1, 3),
            np.concatenate([b.acc for b in bl]).reshape(-1, 3),
            np.concatenate([b.temp for b in bl]),
            np.concatenate([b.t_mag for b in bl]),
            np.concatenate([b.mag for b in bl]).reshape(-1, 3),
            source if source is not None else bl[0].source,
            warnings,
            sorted(bounds, key=lambda s: s["t"]),
            params,
            joined,
        )


def split_boundaries(data: ImuData) -> list[tuple[bool, ImuData]]:
    """``data`` cut at its clock-segment boundaries: [(starts_new_segment, piece), ...] in time order.

    A piece holds the IMU samples with time in [boundary, next boundary) and the mag samples of the same
    span (a mag sample is never fed across a boundary). ``starts_new_segment`` is True for every piece
    that follows a boundary (including a streamed block whose boundary lies before its first sample), so
    the caller restarts the attitude there. The pieces carry no boundaries themselves.
    """
    if not data.boundaries:
        return [(False, data)]
    cuts = sorted(float(b["t"]) for b in data.boundaries)
    edges = [-np.inf, *cuts, np.inf]
    out: list[tuple[bool, ImuData]] = []
    for k in range(len(edges) - 1):
        lo, hi = edges[k], edges[k + 1]
        mi = (data.t_imu >= lo) & (data.t_imu < hi)
        mm = (data.t_mag >= lo) & (data.t_mag < hi)
        if k == 0 and not mi.any() and not mm.any():
            continue  # a block that starts with its boundary: nothing before it
        piece = ImuData(data.t_imu[mi], data.gyro[mi], data.acc[mi], data.temp[mi], data.t_mag[mm], data.mag[mm],
                        data.source, data.warnings, params=data.params, series=data.series)
        out.append((k > 0, piece))
    return out


# The wall-clock time the writers put on a log (tlog stamps, DataFlash GPS week/ms, ULog time_utc_usec): a
# fixed base so that written files are reproducible; a log's date matters to the World Magnetic Model only.
WRITE_EPOCH_US = 1_700_000_000_000_000  # 2023-11-14 22:13:20 UTC
GPS_EPOCH_UNIX_S = 315_964_800  # 1980-01-06 00:00:00 UTC, the GPS week count's origin (leap seconds ignored)


def decimal_year(unix_s: float) -> float:
    """A UNIX time (s) as a decimal year, e.g. 2023.87 (what the World Magnetic Model takes)."""
    import datetime as _dt

    t = _dt.datetime.fromtimestamp(float(unix_s), tz=_dt.UTC)
    y0 = _dt.datetime(t.year, 1, 1, tzinfo=_dt.UTC)
    y1 = _dt.datetime(t.year + 1, 1, 1, tzinfo=_dt.UTC)
    return t.year + (t - y0).total_seconds() / (y1 - y0).total_seconds()


def gps_fixes(data: ImuData) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``data.series`` "latitude"/"longitude" (deg) as every writer stores a fix: (t µs, latitude 1e-7 deg,
    longitude 1e-7 deg), int64 each (MAVLink GPS_RAW_INT, DataFlash format ``L``, PX4's lat/lon), or None when
    the data has no position. Raises ValueError where they are not one time line of finite values."""
    if "latitude" not in data.series or "longitude" not in data.series:
        return None
    (t, lat), (t2, lon) = ((np.asarray(a, np.float64), np.asarray(b, np.float64))
                           for a, b in (data.series["latitude"], data.series["longitude"]))
    if t.shape != t2.shape or not np.array_equal(t, t2):
        raise ValueError("the latitude and longitude series must share their times")
    if t.size and (not np.all(np.isfinite(t)) or t.min() < 0 or np.abs(lat).max() > 90 or np.abs(lon).max() > 180):
        raise ValueError("a GPS position needs finite, non-negative times and a latitude within ±90°, "
                         "a longitude within ±180°")
    if not t.size:
        return None
    us, lat_e7, lon_e7 = (np.rint(x * k).astype(np.int64) for x, k in ((t, 1e6), (lat, 1e7), (lon, 1e7)))
    return us, lat_e7, lon_e7


class LogReader(Protocol):
    """What every format's reader offers: stream a log in blocks of bounded size.

    Memory is constant in the length of the log: each block holds at most ``max_samples`` IMU
    samples (plus the mag samples in the same time span). Warnings about dropped or repaired samples
    accumulate in ``warnings`` and are copied onto each block.
    """

    path: str
    warnings: list[str]

    def blocks(self, max_samples: int = 4096) -> Iterator[ImuData]: ...
