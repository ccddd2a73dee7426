"""The flat CSV schema of ``shared/data/README.md``: read in bounded blocks, and write.

Columns (matched by name, any order, header line required)::

    time_s [s], gyro_x..z [rad/s], acc_x..z [m/s²], mag_x..z [sensor unit], temp_c [°C]

``mag_x..z`` (all three) and ``temp_c`` may be absent; optional ``current_a`` [A] and ``throttle`` [0..1]
(``ImuData.series``; rows of their own: the time and the value, the other cells empty). Other columns are
ignored. A row carries an IMU
sample (gyro+acc, temperature optional), a mag sample, or both; cells of a sensor not sampled at that
row are empty. Errors name ``line N`` with N the line number in the file (the header is line 1).

Malformed rows (a wrong number of cells, a cell that is not a number) are skipped and counted in a warning
naming the first; a file with more malformed rows than good ones is refused (LogError naming the first).
Lines are read with a length limit: a line longer than :data:`_LINE_LIMIT` or holding NUL/control bytes
starts a binary tail (a pre-allocated logger file padded with zeros, say): reading stops there with a
warning, and the tail is never held in memory as one line.
"""

from __future__ import annotations

import math
import operator
import re
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import numpy as np

from onlinecal.io.base import Array, ImuData, LogError
from onlinecal.io.validate import LOOKAHEAD, BlockAssembler, SampleFilter, check_file

TIME = "time_s"
GYRO = ("gyro_x", "gyro_y", "gyro_z")
ACC = ("acc_x", "acc_y", "acc_z")
MAG = ("mag_x", "mag_y", "mag_z")
TEMP = "temp_c"
COLUMNS = (TIME, *GYRO, *ACC, *MAG, TEMP)
# optional series a vehicle's log carries (ImuData.series): battery current A, throttle 0..1; a row may hold
# only the time and these (written so by write_csv when the data has them)
SERIES_COLUMNS = {"current_a": "current", "throttle": "throttle"}

_HEADER_LIMIT = 1 << 16  # a header longer than this is not a header (e.g. a binary file)
_LINE_LIMIT = 1 << 12  # characters: a data row of 11 numbers is ~250; longer is binary data
_BINARY = re.compile("[\x00-\x08\x0e-\x1f\x7f\ufffd]")  # NUL, control characters, undecodable bytes


class CsvReader:
    """Streaming reader of one flat-schema CSV file.

    ``acc_scale``/``gyro_scale``/``mag_scale`` multiply the column values (default 1).
    The constructor checks that the file opens and has a usable header (LogError otherwise);
    :meth:`blocks` reads the data, a chunk of lines at a time, and may be called again to re-read.
    """

    def __init__(self, path: str | Path, acc_scale: float | None = None, gyro_scale: float | None = None,
                 mag_scale: float | None = None) -> None:
        self.path = str(path)
        self.warnings: list[str] = []
        # The columns are in SI units already; a scale, if given, multiplies them (as it replaces the
        # unit conversion of the integer formats).
        self.scale = {k: 1.0 if v is None else float(v)
                      for k, v in (("acc", acc_scale), ("gyro", gyro_scale), ("mag", mag_scale))}
        self._si_units = acc_scale is None and gyro_scale is None
        check_file(self.path)  # the same words as the other formats for a missing, empty or directory path
        with self._open() as f:
            self._names, self._col = self._read_header(f)
        self._layout()

    # -- opening and the header ---------------------------------------------------------------------
    def _open(self) -> IO[str]:
        try:
            # utf-8-sig drops a byte-order mark; undecodable bytes become U+FFFD and then fail as a
            # non-numeric cell with a line number instead of a UnicodeDecodeError.
            return open(self.path, encoding="utf-8-sig", errors="replace")
        except OSError as e:
            raise LogError(self.path, f"cannot open: {e.strerror or e}") from None

    def _read_header(self, f: IO[str]) -> tuple[list[str], dict[str, int]]:
        line = f.readline(_HEADER_LIMIT)
        if line == "":
            raise LogError(self.path, "empty file")
        if len(line) >= _HEADER_LIMIT and not line.endswith("\n"):
            raise LogError(self.path, "first line is not a CSV header (too long; binary file?)", "line 1")
        if _BINARY.search(line):
            raise LogError(self.path, "first line is not a CSV header (binary data; not a .csv file?)", "line 1")
        names = [c.strip().lower() for c in line.rstrip("\r\n").split(",")]
        col: dict[str, int] = {}
        for i, name in enumerate(names):
            if name in COLUMNS or name in SERIES_COLUMNS:
                if name in col:
                    raise LogError(self.path, f"column {name!r} appears twice in the header", "line 1")
                col[name] = i
        required = (TIME, *GYRO, *ACC)
        missing = [c for c in required if c not in col]
        if missing:
            if _is_number(names[0]):
                problem = f"no header line (expected one naming {', '.join(COLUMNS)})"
            else:
                problem = f"header lacks column(s) {', '.join(missing)}"
            raise LogError(self.path, problem, "line 1")
        have_mag = [c for c in MAG if c in col]
        if have_mag and len(have_mag) != 3:
            raise LogError(self.path, f"header has {', '.join(have_mag)} but not all of mag_x, mag_y, mag_z",
                           "line 1")
        return names, col

    def _layout(self) -> None:
        """Known columns only, in file order: rows are cut down to these before parsing, so that extra
        (possibly non-numeric) columns are ignored."""
        self._keep = sorted(self._col.values())
        self._kept_names = [self._names[i] for i in self._keep]
        self._kcol = {self._names[i]: k for k, i in enumerate(self._keep)}
        self._getter = operator.itemgetter(*self._keep) if len(self._keep) < len(self._names) else None

    # -- streaming ------------------------------------------------------------------------------------
    def blocks(self, max_samples: int = 4096) -> Iterator[ImuData]:
        """Yield ImuData blocks of at most ``max_samples`` IMU samples, in file order.

        Raises LogError for malformed rows (naming the line) and, at the end, for a log that is
        unusable as a whole (see :mod:`onlinecal.io.validate`).
        """
        filt = SampleFilter(self.path, unit="rows", lookahead=LOOKAHEAD, gaps=True,
                            limits=self._si_units)
        self.warnings = filt.warnings
        asm = BlockAssembler(self.path, filt.warnings, max_samples, filt)
        # Lines hold IMU or mag samples, so read a bit more than one block's worth per chunk.
        chunk = int(min(max(2 * max_samples, 4096), 1 << 16))
        empty_rows = 0
        self._series: dict[str, tuple[list[Array], list[Array]]] = {}
        self._bad = 0
        self._bad_first: tuple[int, str] | None = None
        self._rows = 0
        with self._open() as f:
            self._read_header(f)
            lineno = 1  # line number of the last line read
            tail = False
            while not tail:
                lines, tail = self._read_lines(f, chunk, lineno)
                if not lines:
                    break
                first = lineno + 1
                lineno += len(lines)
                vals, empty = self._parse(lines, first, filt)
                if vals.shape[0] == 0:
                    continue
                imu, mag, n_empty = self._split(vals, empty)
                empty_rows += n_empty
                asm.add(filt.imu(*imu), filt.mag(*mag) if mag is not None else None)
                yield from asm.pop()
        if empty_rows:
            filt.note(f"skipped {empty_rows} rows with no sensor values")
        if self._bad and self._bad_first is not None:
            line, problem = self._bad_first
            if 2 * self._bad > self._rows:
                raise LogError(self.path, f"{self._bad} of {self._rows} rows malformed; the first: {problem}",
                               f"line {line}")
            filt.note(f"skipped {self._bad} malformed rows (the first, line {line}: {problem})")
        if tail:
            filt.note(f"stopped reading at line {lineno + 1}: binary data (NUL or control bytes, or a line over "
                      f"{_LINE_LIMIT} characters) from there on, e.g. a pre-allocated logger file's padding")
        asm.add(*filt.flush())
        filt.finish()
        asm.series = {SERIES_COLUMNS[k]: (np.concatenate(ts), np.concatenate(xs))
                      for k, (ts, xs) in self._series.items()}
        yield from asm.pop(final=True)

    @staticmethod
    def _read_lines(f: IO[str], chunk: int, lineno: int) -> tuple[list[str], bool]:
        """Up to ``chunk`` lines, each read with a length limit; (lines, binary tail reached). The line that
        starts a binary tail is not returned."""
        out: list[str] = []
        readline = f.readline
        for _ in range(chunk):
            line = readline(_LINE_LIMIT)
            if not line:
                return out, False
            if (len(line) >= _LINE_LIMIT and not line.endswith("\n")) or _BINARY.search(line):
                return out, True
            out.append(line)
        return out, False

    def _malformed(self, line: int, problem: str) -> None:
        self._bad += 1
        if self._bad_first is None or line < self._bad_first[0]:  # cell checks come after count checks
            self._bad_first = (line, problem)

    def _parse(self, lines: list[str], first: int, filt: SampleFilter) -> tuple[Array, np.ndarray]:
        """Lines → values (n, k) of the k known columns, NaN where empty, and the empty mask (n, k)."""
        ncol = len(self._names)
        # Only the file's very last line can lack the newline: a write that was cut short.
        truncated = not lines[-1].endswith("\n") and bool(lines[-1].strip())
        rows: list[str] = []
        linenos: list[int] = []
        for k, s in enumerate(lines):
            s = s.rstrip("\r\n")
            if s.strip():
                rows.append(s)
                linenos.append(first + k)
        if not rows:
            return np.zeros((0, len(self._keep))), np.zeros((0, len(self._keep)), bool)
        self._rows += len(rows)
        counts = [s.count(",") for s in rows]
        if any(c != ncol - 1 for c in counts):
            bad = [i for i, c in enumerate(counts) if c != ncol - 1]
            if truncated and bad[-1] == len(rows) - 1:
                problem = f"expected {ncol} comma-separated columns, found {counts[-1] + 1}"
                filt.note(f"dropped line {linenos[-1]}, the last, cut short without a trailing newline "
                          f"({problem})")
                self._rows -= 1
                bad.pop()
                rows.pop()
                linenos.pop()
            for i in bad:
                self._malformed(linenos[i], f"expected {ncol} comma-separated columns, found {counts[i] + 1}")
            drop = set(bad)
            rows = [r for i, r in enumerate(rows) if i not in drop]
            linenos = [n for i, n in enumerate(linenos) if i not in drop]
            if not rows:
                return np.zeros((0, len(self._keep))), np.zeros((0, len(self._keep)), bool)
        if self._getter is not None:
            get = self._getter
            rows = [",".join(get(s.split(","))) for s in rows]
        parsed = _parse_fast(rows, len(self._keep))
        return parsed if parsed is not None else self._parse_slow(rows, linenos, truncated, filt)

    def _parse_slow(self, rows: list[str], linenos: list[int], truncated: bool,
                    filt: SampleFilter) -> tuple[Array, np.ndarray]:
        """Cell by cell: exact about empty vs literal NaN, and finds the first bad cell."""
        ncol = len(self._keep)
        vals = np.full((len(rows), ncol), np.nan)
        empty = np.zeros((len(rows), ncol), bool)
        good = np.ones(len(rows), bool)
        for r, s in enumerate(rows):
            for c, cell in enumerate(s.split(",")):
                cell = cell.strip()
                if not cell:
                    empty[r, c] = True
                    continue
                try:
                    if "_" in cell:  # float() accepts 1_000, the fast parser does not: be consistent
                        raise ValueError
                    vals[r, c] = float(cell)
                except ValueError:
                    shown = cell if len(cell) <= 40 else cell[:37] + "..."
                    problem = f"column {self._kept_names[c]!r}: {shown!r} is not a number"
                    if truncated and r == len(rows) - 1:
                        filt.note(f"dropped line {linenos[r]}, the last, cut short without a trailing "
                                  f"newline ({problem})")
                        self._rows -= 1
                    else:
                        self._malformed(linenos[r], f"{problem}")
                    good[r] = False
                    break
        return vals[good], empty[good]

    def _split(self, vals: Array, empty: np.ndarray):
        """Parsed rows → (IMU arrays, mag arrays or None, number of rows with no sensor values)."""
        col = self._kcol
        t = vals[:, col[TIME]]
        ig = [col[c] for c in GYRO]
        ia = [col[c] for c in ACC]
        imu_rows = ~np.all(empty[:, ig + ia], axis=1)
        temp = vals[:, col[TEMP]] if TEMP in col else np.full(t.shape, np.nan)
        sc = self.scale
        v = vals[imu_rows]
        imu = (t[imu_rows], v[:, ig] * sc["gyro"], v[:, ia] * sc["acc"], temp[imu_rows])
        mag = None
        any_rows = imu_rows
        if MAG[0] in col:
            im = [col[c] for c in MAG]
            mag_rows = ~np.all(empty[:, im], axis=1)
            mag = (t[mag_rows], vals[mag_rows][:, im] * sc["mag"])
            any_rows = imu_rows | mag_rows
        for name in SERIES_COLUMNS:
            if name in col:
                has = ~empty[:, col[name]] & np.isfinite(vals[:, col[name]]) & np.isfinite(t)
                if has.any():
                    acc = self._series.setdefault(name, ([], []))
                    acc[0].append(t[has])
                    acc[1].append(vals[has, col[name]])
                any_rows = any_rows | has
        return imu, mag, int(np.count_nonzero(~any_rows))


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def _parse_fast(rows: list[str], ncol: int) -> tuple[Array, np.ndarray] | None:
    """Vectorised parse of rows that all have ``ncol`` cells; None if the slow path must decide.

    Empty cells are filled with "nan" and numpy's C parser reads the lot. That is only exact when the
    text holds no literal nan/inf (then every NaN came from an empty cell), so such chunks, and any
    chunk the C parser rejects, go to the cell-by-cell path.
    """
    text = "\n".join(rows)
    if any(ch in text for ch in "nNiI"):
        return None
    # Wrap every line in commas so each empty cell shows as ",,"; two passes fill runs of empties.
    text = "," + text.replace("\n", ",\n,") + ","
    text = text.replace(",,", ",nan,").replace(",,", ",nan,")
    text = text.replace(",\n,", "\n")[1:-1]
    try:
        vals = np.loadtxt(text.split("\n"), delimiter=",", comments=None, ndmin=2, dtype=np.float64)
    except ValueError:
        return None
    if vals.shape != (len(rows), ncol):
        return None
    return vals, np.isnan(vals)


def write_csv(path: str | Path, data: ImuData) -> None:
    """Write ``data`` in the flat schema: IMU and mag rows merged in time order (IMU first on ties),
    empty cells for the sensor not sampled, floats written with repr (shortest exact round trip). A
    ``current``/``throttle`` series (``data.series``) adds a ``current_a``/``throttle`` column, its samples on
    rows of their own (time and that value only), merged in time order after the sensors' rows."""
    n, m = data.n_imu, data.n_mag
    extra = [(c, data.series[k]) for c, k in SERIES_COLUMNS.items() if k in data.series and data.series[k][0].size]
    cols = COLUMNS + tuple(c for c, _ in extra)
    t = np.concatenate([data.t_imu, data.t_mag] + [np.asarray(s[0], float) for _, s in extra])
    kind = np.concatenate([np.zeros(n, int), np.ones(m, int)] + [np.full(s[0].size, 2 + j)
                                                                 for j, (_, s) in enumerate(extra)])
    at = np.concatenate([np.arange(n), np.arange(m)] + [np.arange(s[0].size) for _, s in extra])
    order = np.argsort(t, kind="stable")
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(",".join(cols) + "\n")
        step = 1 << 15
        for s in range(0, order.size, step):
            idx = order[s:s + step]
            rows = np.full((idx.size, len(cols)), np.nan)
            rows[:, 0] = t[idx]
            k, i = kind[idx], at[idx]
            is_imu, is_mag = k == 0, k == 1
            rows[is_imu, 1:4] = data.gyro[i[is_imu]]
            rows[is_imu, 4:7] = data.acc[i[is_imu]]
            rows[is_imu, 10] = data.temp[i[is_imu]]
            rows[is_mag, 7:10] = data.mag[i[is_mag]]
            for j, (_, ser) in enumerate(extra):
                sel = k == 2 + j
                rows[sel, len(COLUMNS) + j] = np.asarray(ser[1], float)[i[sel]]
            f.write("".join(",".join(_cell(v) for v in r) + "\n" for r in rows.tolist()))


def _cell(v: float) -> str:
    # NaN marks "no sample here" in the row layout: written as an empty cell.
    return "" if math.isnan(v) else repr(v)
