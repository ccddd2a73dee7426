"""PX4 ULog (``.ulg``) logs, read through pyulog (PX4's own parser); written (simulated sessions) by
:mod:`onlinecal.io.ulog_write`.

What is read, for IMU instance ``imu`` (the topics' multi-instance, default 0):

* raw driver topics when logged: ``sensor_gyro`` (rad/s) and ``sensor_accel`` (m/s²) of that instance, and
  ``sensor_mag`` instance 0 (gauss; the primary compass), time ``timestamp_sample`` where the topic has it,
  else ``timestamp`` (µs since boot). PX4 applies its calibration after these topics, so they are what a
  calibrator wants. The IMU sample times are the gyro's; the accelerometer (its own clock and rate) is
  linearly interpolated onto them. The temperature is the gyro's (NaN where absent).
* otherwise ``sensor_combined`` (gyro_rad, accelerometer_m_s2 at ``timestamp`` + the accelerometer's relative
  stamp, and in old logs magnetometer_ga, a mag sample whenever its own stamp changes), with a warning: PX4
  has already applied its own calibration (CAL_* parameters) to these values, so a calibration fitted on
  them is a residual on top of PX4's.

The log's parameters (all of them, CAL_ACC0_XOFF ... included) become ``ImuData.params``.

Memory: pyulog loads the topics it is asked for whole (numpy arrays, a few tens of bytes per sample); the
blocks handed on are bounded as for the other formats.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from onlinecal.io.base import ImuData, LogError
from onlinecal.io.validate import LOOKAHEAD, BlockAssembler, SampleFilter, check_file, probe_head

ULOG_MAGIC = b"ULog\x01\x12\x35"
_RELATIVE_INVALID = 2147483647  # PX4's RELATIVE_TIMESTAMP_INVALID
_TOPICS = ["sensor_gyro", "sensor_accel", "sensor_mag", "sensor_combined", "battery_status", "actuator_controls_0"]


class UlogReader:
    """Streaming (in blocks) reader of one IMU instance and the primary compass of a PX4 ``.ulg`` log."""

    def __init__(self, path: str | Path, acc_scale: float | None = None, gyro_scale: float | None = None,
                 mag_scale: float | None = None, imu: int = 0) -> None:
        self.path = str(path)
        self.imu = int(imu)
        self.warnings: list[str] = []
        self.scale = {k: 1.0 if v is None else float(v)
                      for k, v in (("acc", acc_scale), ("gyro", gyro_scale), ("mag", mag_scale))}
        self._si_units = acc_scale is None and gyro_scale is None
        self.source: str | None = None  # "raw sensor topics" | "sensor_combined"
        check_file(self.path)
        probe_head(self.path, lambda head: head.startswith(ULOG_MAGIC),
                   "no ULog header in {span} (it starts with the bytes 'ULog'); not a PX4 .ulg log?")

    def _load(self) -> Any:
        try:
            from pyulog import ULog
        except ImportError as e:  # pragma: no cover - pyulog is a dependency
            raise LogError(self.path, f"reading .ulg needs pyulog ({e})") from None
        try:
            return ULog(self.path, message_name_filter_list=_TOPICS)
        except Exception as e:  # pyulog's own failures on a damaged file
            raise LogError(self.path, f"pyulog cannot read it: {type(e).__name__}: {e}") from None

    def blocks(self, max_samples: int = 4096) -> Iterator[ImuData]:
        """Yield ImuData blocks of at most ``max_samples`` IMU samples, in time order."""
        ulog = self._load()
        filt = SampleFilter(self.path, unit="samples", lookahead=LOOKAHEAD, gaps=True, limits=self._si_units)
        self.warnings = filt.warnings
        asm = BlockAssembler(self.path, filt.warnings, max_samples, filt)
        asm.params = {k: float(v) for k, v in ulog.initial_parameters.items()
                      if isinstance(v, (int, float)) and np.isfinite(v)}
        topics: dict[tuple[str, int], Any] = {(d.name, d.multi_id): d.data for d in ulog.data_list}
        instances = sorted(i for n, i in topics if n == "sensor_gyro")
        try:
            yield from self._read(topics, instances, filt, asm, max_samples)
        except (KeyError, ValueError) as e:
            raise LogError(self.path, f"unusable sensor topic: {type(e).__name__}: {e}") from None

    def _read(self, topics: dict[tuple[str, int], Any], instances: list[int], filt: SampleFilter,
              asm: BlockAssembler, max_samples: int) -> Iterator[ImuData]:
        if ("sensor_gyro", self.imu) in topics and ("sensor_accel", self.imu) in topics:
            self.source = f"sensor_gyro/sensor_accel instance {self.imu}"
            t, gyro, acc, temp = _raw_imu(topics[("sensor_gyro", self.imu)], topics[("sensor_accel", self.imu)])
            m = topics.get(("sensor_mag", 0))
            tm, mag = _raw_mag(m) if m is not None else (np.zeros(0), np.zeros((0, 3)))
            if len(instances) > 1:
                filt.note(f"read IMU instance {self.imu} of {len(instances)} (sensor_gyro instances "
                          f"{', '.join(map(str, instances))}); --imu N picks another")
        elif ("sensor_combined", 0) in topics and self.imu == 0:
            self.source = "sensor_combined"
            t, gyro, acc, temp, tm, mag = _combined(topics[("sensor_combined", 0)])
            m = topics.get(("sensor_mag", 0))
            if m is not None and not tm.size:
                tm, mag = _raw_mag(m)
            cal = sorted(k for k in asm.params if k.startswith("CAL_"))
            filt.note("no raw sensor topics (sensor_gyro/sensor_accel) in the log: read sensor_combined, whose "
                      "values PX4 has already corrected with its own calibration"
                      + (f" ({len(cal)} CAL_* parameters in the log)" if cal else "")
                      + "; a calibration fitted here is a residual on top of PX4's")
        else:
            have = sorted({n for n, _ in topics})
            want = f"sensor_gyro/sensor_accel instance {self.imu}" if self.imu else "sensor_gyro/sensor_accel " \
                "or sensor_combined"
            raise LogError(self.path, f"no {want} in the log (it holds {', '.join(have) or 'none of them'})")
        s = self.scale
        step = max(1, min(max_samples, 1 << 14))
        jm = 0
        for i in range(0, t.size, step):
            last = i + step >= t.size
            j_end = tm.size if last else int(np.searchsorted(tm, t[i + step - 1], side="right"))
            j, jm = slice(jm, j_end), j_end
            asm.add(filt.imu(t[i:i + step], gyro[i:i + step] * s["gyro"], acc[i:i + step] * s["acc"],
                             temp[i:i + step]),
                    filt.mag(tm[j], mag[j] * s["mag"]))
            yield from asm.pop()
        asm.add(*filt.flush())
        filt.finish()
        asm.series = _series(topics)
        yield from asm.pop(final=True)


def _series(topics: dict[tuple[str, int], Any]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """ImuData.series: ``current`` from battery_status instance 0 ``current_a`` (A; −1 = not measured, left out),
    ``throttle`` from actuator_controls_0 ``control[3]`` (0..1), at ``timestamp`` (µs since boot)."""
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for (topic, field), name in ((("battery_status", "current_a"), "current"),
                                 (("actuator_controls_0", "control[3]"), "throttle")):
        d = topics.get((topic, 0))
        if d is None or field not in d or "timestamp" not in d:
            continue
        t, x = np.asarray(d["timestamp"], np.float64) * 1e-6, np.asarray(d[field], np.float64)
        ok = np.isfinite(x) & (x >= 0 if name == "current" else np.isfinite(x))
        if ok.any():
            out[name] = (t[ok], x[ok])
    return out


def _xyz(d: dict[str, np.ndarray], *names: str) -> np.ndarray | None:
    """(N, 3) of the first field family present: ``name[0..2]`` or ``x``/``y``/``z`` style names."""
    for n in names:
        if f"{n}[0]" in d:
            return np.column_stack([d[f"{n}[{k}]"] for k in range(3)]).astype(np.float64)
        if n == "xyz" and all(c in d for c in "xyz"):
            return np.column_stack([d[c] for c in "xyz"]).astype(np.float64)
    return None


def _stamp(d: dict[str, np.ndarray]) -> np.ndarray:
    return np.asarray(d["timestamp_sample"] if "timestamp_sample" in d else d["timestamp"], np.float64) * 1e-6


def _raw_imu(g: dict[str, np.ndarray], a: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
    """sensor_gyro + sensor_accel → (t, gyro, acc, temp), the accelerometer interpolated onto the gyro times."""
    t, ta = _stamp(g), _stamp(a)
    gyro, acc = _xyz(g, "xyz"), _xyz(a, "xyz")
    if gyro is None or acc is None:
        raise ValueError("sensor_gyro/sensor_accel without x, y, z fields")
    order, order_a = np.argsort(t, kind="stable"), np.argsort(ta, kind="stable")
    t, gyro, ta, acc = t[order], gyro[order], ta[order_a], acc[order_a]
    acc_i = np.column_stack([np.interp(t, ta, acc[:, k], left=np.nan, right=np.nan) for k in range(3)])
    temp = np.asarray(g["temperature"], np.float64)[order] if "temperature" in g else np.full(t.size, np.nan)
    return t, gyro, acc_i, temp


def _raw_mag(m: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    mag = _xyz(m, "xyz")
    if mag is None:
        return np.zeros(0), np.zeros((0, 3))
    t = _stamp(m)
    order = np.argsort(t, kind="stable")
    return t[order], mag[order]


def _combined(c: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
    """sensor_combined → (t, gyro, acc, temp, t_mag, mag): the IMU at ``timestamp`` (the gyro's), the
    accelerometer interpolated from its own stamps, the old logs' magnetometer a sample per new stamp."""
    t = np.asarray(c["timestamp"], np.float64) * 1e-6
    gyro, acc = _xyz(c, "gyro_rad"), _xyz(c, "accelerometer_m_s2")
    if gyro is None or acc is None:
        raise ValueError("sensor_combined without gyro_rad/accelerometer_m_s2")
    rel = np.asarray(c.get("accelerometer_timestamp_relative", np.zeros(t.size)), np.float64)
    ta = t + np.where(rel == _RELATIVE_INVALID, 0.0, rel) * 1e-6
    if np.all(np.diff(ta) > 0):
        acc = np.column_stack([np.interp(t, ta, acc[:, k]) for k in range(3)])
    temp = np.full(t.size, np.nan)
    mag = _xyz(c, "magnetometer_ga")
    if mag is None or "magnetometer_timestamp_relative" not in c:
        return t, gyro, acc, temp, np.zeros(0), np.zeros((0, 3))
    mrel = np.asarray(c["magnetometer_timestamp_relative"], np.float64)
    ok = mrel != _RELATIVE_INVALID
    tm = t + mrel * 1e-6
    new = ok & np.concatenate([[True], np.abs(np.diff(tm)) > 1e-7])  # the held reading repeats: one sample each
    return t, gyro, acc, temp, tm[new], mag[new]
