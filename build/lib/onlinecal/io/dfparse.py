"""A DataFlash (``.bin``) record parser of our own: bounded memory, numpy-decoded, one pass over the file.

Layout (ArduPilot's, as pymavlink's ``DFReader_binary`` reads it): every record is the header bytes
0xA3 0x95, a one-byte message type, then the fields packed little-endian without padding. Type 0x80 is
``FMT`` (89 bytes: Type, Length, Name[4], Format[16], Columns[64]); each FMT record defines the length,
format characters and column names of one message type, and may come anywhere before that type's first
record (ArduPilot writes them on demand).

The file is read in chunks of :data:`CHUNK` bytes. A compiled walk (numba) steps from record to record by
the declared lengths; a byte where no record of a known type starts is skipped one at a time until one
does (pymavlink's resynchronisation on the header, counted in ``skipped``). The records of the wanted
types between two FMT records are then gathered and decoded at once as numpy structured arrays (the
dtype built from the FMT's format characters), so memory is one chunk plus the decoded rows of it,
whatever the log's length, and no Python code runs per record.

Like pymavlink's indexer, reading stops at a FMT record that declares a length under 3 bytes (a corrupt
one: the header alone is 3): ``stopped_at`` is then its byte offset.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

HEAD1, HEAD2 = 0xA3, 0x95
FMT_TYPE = 0x80
FMT_LEN = 89
CHUNK = 1 << 20  # bytes read at a time
# DataFlash format characters: numpy dtype (little-endian) and the multiplier pymavlink applies on access.
FORMAT_CHARS: dict[str, tuple[Any, float | None]] = {
    "a": (("<i2", (32,)), None), "b": ("i1", None), "B": ("u1", None), "g": ("<f2", None), "h": ("<i2", None),
    "H": ("<u2", None), "i": ("<i4", None), "I": ("<u4", None), "f": ("<f4", None), "n": ("S4", None),
    "N": ("S16", None), "Z": ("S64", None), "c": ("<i2", 0.01), "C": ("<u2", 0.01), "e": ("<i4", 0.01),
    "E": ("<u4", 0.01), "L": ("<i4", 1e-7), "d": ("<f8", None), "M": ("i1", None), "q": ("<i8", None),
    "Q": ("<u8", None),
}


def _cstr(b: bytes) -> str:
    """A NUL-terminated string field."""
    return b.split(b"\0", 1)[0].decode("ascii", errors="replace")


@dataclass
class Format:
    """One message type as its FMT record defines it. ``dtype`` is None when the record cannot be decoded
    (``problem`` says why: an unknown format character, a declared length its format does not fill)."""

    type: int
    name: str
    length: int
    format: str
    columns: list[str]
    at: int  # byte offset of the FMT record
    dtype: np.dtype | None = None
    mults: dict[str, float] = field(default_factory=dict)
    problem: str = ""
    extra_columns: list[str] = field(default_factory=list)  # named columns with no format character

    @classmethod
    def parse(cls, rec: bytes, at: int) -> Format:
        """From the 89 bytes of a FMT record at byte ``at``."""
        ftype, length = rec[3], rec[4]
        name, fmt, cols = _cstr(rec[5:9]), _cstr(rec[9:25]), _cstr(rec[25:89])
        columns = cols.split(",") if cols else []
        f = cls(ftype, name, length, fmt, columns, at)
        fields: list[tuple[Any, ...]] = [("_h1", "u1"), ("_h2", "u1"), ("_id", "u1")]
        for k, c in enumerate(fmt):
            if c not in FORMAT_CHARS:
                f.problem = f"Unsupported format char: '{c}' in message {name}"
                return f
            np_t, mul = FORMAT_CHARS[c]
            col = columns[k] if k < len(columns) else f"_col{k}"
            if col in {n for n, *_ in fields}:  # a repeated column name: the first one holds
                col = f"_dup{k}"
            fields.append((col, *np_t) if isinstance(np_t, tuple) else (col, np_t))
            if mul is not None:
                f.mults[col] = mul
        f.extra_columns = columns[len(fmt):]
        dt = np.dtype(fields)  # packed: no padding
        if dt.itemsize != length:
            f.problem = (f"its FMT record declares {length} bytes but its format {fmt!r} packs "
                         f"{dt.itemsize}")
            return f
        f.dtype = dt
        return f

    def has(self, col: str) -> bool:
        return self.dtype is not None and self.dtype.names is not None and col in self.dtype.names

    def values(self, rows: NDArray[Any], col: str) -> NDArray[np.float64]:
        """Column ``col`` of decoded ``rows`` as float64, with pymavlink's multiplier applied."""
        v = rows[col].astype(np.float64)
        mul = self.mults.get(col)
        return v * mul if mul is not None else v


_WALK: Any = None


def _walker() -> Any:
    """The compiled record walk (built on first use; numba caches it on disk)."""
    global _WALK
    if _WALK is None:
        # kernels points numba's cache at a writable directory: imported before numba is
        importlib.import_module("onlinecal.ukf.kernels")
        from numba import njit

        @njit(cache=True, nogil=True)
        def walk(buf, pos, end, lengths, out):  # pragma: no cover - compiled
            """Record offsets from ``pos`` into ``out`` until the buffer ends, ``out`` is full or a FMT
            record has been taken (returned last). Returns (n, pos, skipped bytes, of them zero, code): code 0 the
            buffer ends (or a record runs past it), 1 a FMT record ended the run, 2 ``out`` is full."""
            n = 0
            skipped = 0
            zeros = 0
            cap = out.shape[0]
            while pos + 3 <= end:
                if n == cap:
                    return n, pos, skipped, zeros, 2
                if buf[pos] == 0xA3 and buf[pos + 1] == 0x95:
                    typ = buf[pos + 2]
                    ln = lengths[typ]
                    if ln >= 3:
                        if pos + ln > end:
                            return n, pos, skipped, zeros, 0
                        out[n] = pos
                        n += 1
                        pos += ln
                        if typ == 0x80:
                            return n, pos, skipped, zeros, 1
                        continue
                skipped += 1
                if buf[pos] == 0:
                    zeros += 1
                pos += 1
            return n, pos, skipped, zeros, 0

        _WALK = walk
    return _WALK


@dataclass
class Records:
    """Decoded records of one message type from one stretch of the log (between FMT records)."""

    fmt: Format
    rows: NDArray[Any]  # structured, fmt.dtype
    offsets: NDArray[np.int64]  # byte offset of each record
    ordinal: NDArray[np.int64]  # 1-based rank of each record among the records of the wanted types


class DataflashParser:
    """Streams the records of the message types named in ``wanted`` from a DataFlash log.

    After the iteration: ``n_records`` (records of any known type), ``skipped`` (bytes that began no
    record, a truncated last record excluded), ``stopped_at`` (the byte of a FMT record declaring a length
    under 3, where reading stopped; None), ``data_len`` (the file's size), ``formats`` (type → Format)."""

    def __init__(self, path: str, wanted: set[str]) -> None:
        self.path = path
        self.wanted = set(wanted)
        self.formats: dict[int, Format] = {}
        self.n_records = 0
        self.n_wanted = 0
        self.skipped = 0
        self.skipped_zero = 0  # of the skipped bytes, those that are 0 (an erased or pre-allocated stretch)
        self.stopped_at: int | None = None
        self.data_len = 0

    def __iter__(self) -> Iterator[list[Records]]:
        """Per stretch of the log (at most 65536 records, between FMT records): the wanted types' records."""
        walk = _walker()
        lengths = np.full(256, -1, np.int64)
        lengths[FMT_TYPE] = FMT_LEN
        out = np.empty(1 << 16, np.int64)
        buf = np.empty(0, np.uint8)
        base = 0  # file offset of buf[0]
        with open(self.path, "rb") as fh:
            fh.seek(0, 2)
            self.data_len = fh.tell()
            fh.seek(0)
            eof = False
            pos = 0
            while True:
                if not eof:
                    new = fh.read(CHUNK)
                    eof = len(new) < CHUNK
                    buf = np.concatenate([buf[pos:], np.frombuffer(new, np.uint8)])
                    base += pos
                    pos = 0
                while True:
                    n, pos, skipped, zeros, code = walk(buf, pos, buf.size, lengths, out)
                    self.skipped += int(skipped)
                    self.skipped_zero += int(zeros)
                    self.n_records += int(n)
                    offs = out[:n].copy()
                    if code == 1:
                        fmt_at = int(offs[-1])
                        offs = offs[:-1]
                    got = list(self._decode(buf, offs, base))
                    if got:
                        yield got
                    if code == 1:
                        f = Format.parse(bytes(buf[fmt_at:fmt_at + FMT_LEN]), base + fmt_at)
                        if f.length < 3:
                            self.stopped_at = base + fmt_at
                            self.n_records -= 1  # pymavlink's index ends before it
                            return
                        if f.type != FMT_TYPE:
                            self.formats[f.type] = f
                            lengths[f.type] = f.length
                    if code == 0:
                        break
                if eof:
                    return

    def _decode(self, buf: NDArray[np.uint8], offs: NDArray[np.int64], base: int) -> Iterator[Records]:
        if not offs.size:
            return
        types = buf[offs + 2]
        want = np.zeros(256, bool)
        for t, f in self.formats.items():
            want[t] = f.name in self.wanted
        sel = want[types]
        if not sel.any():
            return
        ordinal = self.n_wanted + np.cumsum(sel)
        self.n_wanted += int(sel.sum())
        for t in np.unique(types[sel]):
            f = self.formats[int(t)]
            k = types == t
            o = offs[k]
            if f.dtype is None:
                rows = np.zeros(o.size, np.dtype([("_h1", "u1")]))
            else:
                win = sliding_window_view(buf, f.length)
                rows = np.ascontiguousarray(win[o]).view(f.dtype).reshape(-1)
            yield Records(f, rows, o + base, ordinal[k])
