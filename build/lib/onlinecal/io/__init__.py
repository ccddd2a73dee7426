"""Log readers and writers, chosen by file extension: ``.csv`` (flat schema), ``.tlog`` (MAVLink
telemetry), ``.bin`` (ArduPilot DataFlash), ``.ulg`` (PX4 ULog: read through pyulog, written by
:mod:`onlinecal.io.ulog_write`). Every reader streams :class:`ImuData` blocks and raises
only :class:`LogError` for unusable input; the shared drop policy is in :mod:`onlinecal.io.validate`.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from onlinecal.io.base import ImuData, LogError, LogReader
from onlinecal.io.csv import CsvReader, write_csv
from onlinecal.io.dataflash import DataflashReader, write_dataflash
from onlinecal.io.tlog import TlogReader, write_tlog

__all__ = [
    "BlockJoiner", "CsvReader", "DataflashReader", "ImuData", "LogError", "LogReader", "TlogReader", "open_log",
    "read_log", "write_csv", "write_dataflash", "write_log", "write_tlog",
]

EXTENSIONS = (".csv", ".tlog", ".bin", ".ulg")


def _ext(path: str | Path) -> str:
    return Path(path).suffix.lower()


def open_log(path: str | Path, acc_scale: float | None = None, gyro_scale: float | None = None,
             mag_scale: float | None = None, imu: int = 0) -> LogReader:
    """A streaming reader for ``path`` chosen by its extension (.csv, .tlog, .bin).

    The scales multiply the raw values in place of the format's default unit conversion (see
    :mod:`onlinecal.io.tlog`, :mod:`onlinecal.io.dataflash`); for CSV, whose columns are already in
    SI units, a given scale multiplies the column values. Raises LogError for an unknown extension, a
    missing or empty file, or (CSV) an unusable header. ``imu``: the IMU instance to read from a multi-IMU
    log (.bin: IMU ``I``/IMU2/IMU3; .tlog: RAW_IMU/HIGHRES_IMU id, SCALED_IMU/2/3; .ulg: the sensor topics'
    multi-instance); a CSV holds one IMU (``imu`` must be 0).
    """
    ext = _ext(path)
    if ext == ".csv":
        if imu:
            raise LogError(str(path), f"a CSV log holds one IMU; --imu {imu} is for .bin/.tlog/.ulg logs")
        return CsvReader(path, acc_scale, gyro_scale, mag_scale)
    if ext == ".tlog":
        return TlogReader(path, acc_scale, gyro_scale, mag_scale, imu=imu)
    if ext == ".bin":
        return DataflashReader(path, acc_scale, gyro_scale, mag_scale, imu=imu)
    if ext == ".ulg":
        from onlinecal.io.ulog import UlogReader

        return UlogReader(path, acc_scale, gyro_scale, mag_scale, imu=imu)
    raise LogError(str(path), f"unknown log format {ext or '(no extension)'!r}; expected one of "
                   f"{', '.join(EXTENSIONS)}")


_COLUMNS = ("t_imu", "gyro", "acc", "temp", "t_mag", "mag")  # ImuData's sample arrays


class BlockJoiner:
    """Blocks of one log joined as :func:`read_log` joins them: the samples column by column (each list freed
    once joined: the peak is the log plus one array of it; ImuData.concat of the blocks would hold the blocks
    and the joined log at once, twice the log), the blocks' warnings, boundaries, params and series."""

    def __init__(self) -> None:
        self.cols: dict[str, list[np.ndarray]] = {k: [] for k in _COLUMNS}
        self.heads: list[ImuData] = []

    def add(self, b: ImuData) -> None:
        for k in _COLUMNS:
            self.cols[k].append(getattr(b, k))
        # the block without its samples (fresh empty arrays: a view [:0] would keep the block alive)
        e1, e3 = np.zeros(0), np.zeros((0, 3))
        self.heads.append(replace(b, t_imu=e1, gyro=e3, acc=e3, temp=e1, t_mag=e1, mag=e3))

    def _join(self, k: str) -> np.ndarray:
        parts = self.cols.pop(k)
        shape = (-1, 3) if k in ("gyro", "acc", "mag") else (-1,)
        return np.concatenate(parts).reshape(shape) if parts else np.zeros((0, 3) if len(shape) == 2 else 0)

    def result(self, reader: LogReader, source: str) -> ImuData:
        """The joined log with the reader's warnings (the joiner is spent)."""
        data = ImuData.concat(self.heads, source=source)  # warnings, boundaries, params, series
        self.heads = []
        joined: dict[str, Any] = {k: self._join(k) if self.cols[k] else getattr(data, k) for k in _COLUMNS}
        data = replace(data, **joined)
        data.warnings = list(reader.warnings)
        return data


def read_log(path: str | Path, acc_scale: float | None = None, gyro_scale: float | None = None,
             mag_scale: float | None = None, max_samples: int = 1 << 16, imu: int = 0) -> ImuData:
    """The whole log as one ImuData (the concatenation of the reader's blocks), warnings, clock-segment
    boundaries, parameters and series included."""
    reader = open_log(path, acc_scale, gyro_scale, mag_scale, imu=imu)
    joiner = BlockJoiner()
    for b in reader.blocks(max_samples):
        joiner.add(b)
        del b
    return joiner.result(reader, str(path))


def write_log(path: str | Path, data: ImuData) -> None:
    """Write ``data`` in the format of the extension: .csv (exact), .tlog (RAW_IMU, int16 units:
    1 mG, 1 mrad/s, 1 mgauss), .bin (DataFlash: float32 IMU, int16 mgauss MAG), .ulg (PX4 ULog: float32
    sensor_accel/sensor_gyro/sensor_mag, µs stamps, the CAL_* parameters)."""
    ext = _ext(path)
    if ext == ".csv":
        write_csv(path, data)
    elif ext == ".tlog":
        write_tlog(path, data)
    elif ext == ".bin":
        write_dataflash(path, data)
    elif ext == ".ulg":
        from onlinecal.io.ulog_write import write_ulog

        write_ulog(path, data)
    else:
        raise ValueError(f"cannot write {ext or 'files without an extension'!r}; "
                         f"use one of {', '.join(EXTENSIONS)}")
