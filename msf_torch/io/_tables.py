"""Private helpers shared by the readers: a line-aware text-table parser and stream cleaning.

The parser keeps the 1-based physical line number of every data row, so every error names
``file:line: field``. Conversion is vectorised (``np.array(rows, dtype=float64)``, which uses
Python's ``float`` grammar) and only falls back to a per-cell loop to locate a bad cell.

Stream cleaning applies the io rules once for every format: non-finite samples are dropped
and counted, backwards timestamps raise (or are stably sorted on request), exactly repeated
timestamps keep the first sample.
"""

from __future__ import annotations

__all__ = [
    "Table",
    "read_table",
    "check_columns",
    "CleanReport",
    "clean_stream",
    "check_quaternions",
    "normalise_quaternions",
    "stream_from_arrays",
    "MAX_REPORTED_LINES",
    "path_name",
    "read_text",
    "shown",
    "split_lines",
]

import csv
import dataclasses
import math
import os
import re
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from msf_torch.io.errors import DataError

NPZ_ERRORS = (
    OSError,
    ValueError,
    EOFError,
    SyntaxError,
    KeyError,
    NotImplementedError,
    OverflowError,
    MemoryError,
    zipfile.BadZipFile,
    zlib.error,
)
"""What numpy's and zipfile's parsers raise on a damaged ``.npz`` archive or member."""

MAX_REPORTED_LINES = 5
"""How many dropped line numbers (or sample indices) per stream are kept in ``meta``."""

_LINE_BREAK = re.compile(r"\r\n|\r|\n")
"""Line ends as editors count them (universal newlines); other characters that
``str.splitlines`` breaks at (form feed, U+2028, ...) stay inside their line."""


@dataclass
class Table:
    """A parsed text table.

    Attributes:
        path: the file, as a string (used in error messages).
        header: column names (stripped), or None for a headerless table.
        header_line: 1-based line of the header, or None.
        rows: data rows as lists of stripped cell strings, all of the same length.
        lines: (N,) int64 1-based line number of each row.
    """

    path: str
    header: list[str] | None
    header_line: int | None
    rows: list[list[str]]
    lines: np.ndarray

    def __len__(self) -> int:
        return len(self.rows)

    def index(self, name: str) -> int:
        """Column index of ``name`` (the header must contain it; see :func:`check_columns`)."""
        assert self.header is not None
        return self.header.index(name)

    def _column_names(self, idx: list[int]) -> list[str]:
        if self.header is None:
            return [f"column {i + 1}" for i in idx]
        return [self.header[i] for i in idx]

    def floats(self, columns: list[str] | list[int]) -> np.ndarray:
        """Convert the given columns (names or indices) to a (N, k) float64 array.

        Raises:
            DataError: naming the line and column of the first cell that is not a number.
        """
        idx = [c if isinstance(c, int) else self.index(c) for c in columns]
        width = len(self.rows[0]) if self.rows else 0
        if idx == list(range(width)):
            cells: list[list[str]] = self.rows
        else:
            cells = [[row[i] for i in idx] for row in self.rows]
        if not cells:
            return np.zeros((0, len(idx)), dtype=np.float64)
        try:
            return np.array(cells, dtype=np.float64)
        except ValueError:
            pass
        names = self._column_names(idx)
        out = np.empty((len(cells), len(idx)), dtype=np.float64)
        for r, row in enumerate(cells):
            for c, cell in enumerate(row):
                try:
                    out[r, c] = float(cell)
                except ValueError:
                    problem = "empty cell" if cell == "" else f"not a number: {shown(cell)}"
                    raise DataError(
                        self.path, problem, line=int(self.lines[r]), field=names[c]
                    ) from None
        return out

    def finite_floats(self, columns: list[str], what: str = "rows") -> np.ndarray:
        """Like :meth:`floats`, for a file that must hold at least one row of finite numbers.

        ``what`` names the rows in the empty-file error (e.g. ``"poses"``).

        Returns:
            (N, len(columns)) float64 array, N >= 1, every entry finite.

        Raises:
            DataError: an empty table, or naming the line and column of the first
                non-finite value.
        """
        if len(self) == 0:
            raise DataError(self.path, f"no {what} in the file")
        data = self.floats(columns)
        bad = np.argwhere(~np.isfinite(data))
        if bad.size:
            r, c = (int(x) for x in bad[0])
            raise DataError(
                self.path,
                f"non-finite value {float(data[r, c])!r}",
                line=int(self.lines[r]),
                field=columns[c],
            )
        return data

    def ints(self, column: str | int) -> np.ndarray:
        """Convert one column to a (N,) int64 array (exact; for nanosecond timestamps).

        Raises:
            DataError: naming the line and column of the first cell that is not an integer.
        """
        i = column if isinstance(column, int) else self.index(column)
        name = self._column_names([i])[0]
        out = np.empty(len(self.rows), dtype=np.int64)
        for r, row in enumerate(self.rows):
            try:
                out[r] = int(row[i])
            except (ValueError, OverflowError):
                raise DataError(
                    self.path,
                    f"not an integer: {shown(row[i])}",
                    line=int(self.lines[r]),
                    field=name,
                ) from None
        return out

    def strings(self, column: str | int) -> list[str]:
        """One column as a list of strings."""
        i = column if isinstance(column, int) else self.index(column)
        return [row[i] for row in self.rows]


def read_text(path: str | os.PathLike[str]) -> str:
    """The whole of a UTF-8 text file (a leading byte-order mark dropped).

    Raises:
        DataError: no such file, a folder, or bytes that are not UTF-8 (naming the line of
            the first bad byte).
    """
    try:
        data = Path(path).read_bytes()
    except FileNotFoundError:
        raise DataError(path, "no such file") from None
    except IsADirectoryError:
        raise DataError(path, "is a folder, expected a file") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        line = len(split_lines(data[: err.start].decode("utf-8-sig", errors="replace")))
        raise DataError(
            path, f"not a UTF-8 text file ({err.reason}: byte {data[err.start]:#04x})", line=line
        ) from None


def split_lines(text: str) -> list[str]:
    """``text`` cut at ``\\r\\n``, ``\\r`` and ``\\n`` only: line ``k`` of the result is the line
    an editor shows as ``k + 1``, which every error message names."""
    return _LINE_BREAK.split(text)


def shown(cell: str, limit: int = 40) -> str:
    """``repr`` of a cell for an error message, shortened to about ``limit`` characters."""
    if len(cell) <= limit:
        return repr(cell)
    return f"{cell[:limit]!r}... ({len(cell)} characters)"


def read_table(
    path: str | os.PathLike[str],
    *,
    delimiter: str | None = ",",
    header: str = "line",
    comment: str = "#",
    ncols: int | None = None,
    names: list[str] | None = None,
) -> Table:
    """Read a delimited text table, keeping line numbers.

    Blank lines and lines starting with ``comment`` are skipped (after the header).

    Args:
        path: the file.
        delimiter: a one-character CSV delimiter (quotes honoured, no newlines inside
            cells), or None to split on runs of whitespace.
        header: ``"line"``: the first non-blank, non-comment line is the header;
            ``"hash"``: the first non-blank line is the header even when it starts with
            ``comment`` (EuRoC's ``#timestamp [ns],...``); ``"none"``: no header.
        ncols: required number of columns for a headerless table (None: take the first
            row's, or ``len(names)``).
        names: column names of a headerless table (used in errors; sets ``Table.header``
            with ``header_line`` None).

    Returns:
        a :class:`Table`; every row has as many cells as the header.

    Raises:
        DataError: missing file, empty header, a row with the wrong number of columns.
    """
    path_str = os.fspath(path)
    text = read_text(path)
    kept: list[str] = []
    numbers: list[int] = []
    head: list[str] | None = None
    head_line: int | None = None
    want_header = header in ("line", "hash")
    for number, raw in enumerate(split_lines(text), start=1):
        line = raw.strip()
        if not line:
            continue
        if want_header and head is None:
            if line.startswith(comment):
                if header == "line":
                    continue
                line = line[len(comment) :]
            head = _split_one(path_str, line, number, delimiter)
            head_line = number
            continue
        if line.startswith(comment):
            continue
        kept.append(line)
        numbers.append(number)
    if want_header and head is None:
        raise DataError(path_str, "empty file: no header line")
    if delimiter is None:
        rows = [line.split() for line in kept]
    else:
        reader = csv.reader(kept, delimiter=delimiter)
        try:
            rows = [[cell.strip() for cell in row] for row in reader]
        except csv.Error as err:
            raise DataError(
                path_str, f"malformed CSV ({err})", line=numbers[reader.line_num - 1]
            ) from None
        if len(rows) != len(kept):
            raise DataError(path_str, "unbalanced quotes: a quoted cell spans lines")
    width: int | None
    if head is not None:
        width = len(head)
        names = head
    elif names is not None:
        width = len(names)
        head = list(names)
    else:
        width = ncols if ncols is not None else (len(rows[0]) if rows else None)
    lines = np.asarray(numbers, dtype=np.int64)
    if width is not None:
        for r, row in enumerate(rows):
            if len(row) != width:
                expect = f" ({', '.join(names)})" if names is not None else ""
                raise DataError(
                    path_str,
                    f"expected {width} columns{expect}, got {len(row)}",
                    line=int(lines[r]),
                )
    return Table(path=path_str, header=head, header_line=head_line, rows=rows, lines=lines)


def _split_one(path: str, line: str, number: int, delimiter: str | None) -> list[str]:
    """Cells of one line (the header); a CSV error becomes a DataError naming the line."""
    if delimiter is None:
        return line.split()
    try:
        return [cell.strip() for cell in next(csv.reader([line], delimiter=delimiter))]
    except csv.Error as err:
        raise DataError(path, f"malformed CSV ({err})", line=number) from None


def check_columns(
    table: Table,
    required: list[str],
    groups: list[list[list[str]]] | None = None,
) -> list[str]:
    """Check a table's header against a schema; return the optional columns present.

    Args:
        table: a table with a header.
        required: columns that must be present (any order).
        groups: alternatives for the optional columns: a list of choice-sets, each a list of
            column groups; the header may contain none of a choice-set's columns or exactly
            one whole group of it. E.g. ``[[["sigma_x", "sigma_y", "sigma_z"]]]``.

    Returns:
        the optional columns that were found (one group per choice-set, flattened).

    Raises:
        DataError: a missing required column, a duplicated or unknown column, a partial
            optional group, or two alternatives at once; the error names the header line
            and the column.
    """
    assert table.header is not None
    header = table.header
    seen: set[str] = set()
    for name in header:
        if name in seen:
            raise DataError(table.path, "column appears twice", line=table.header_line, field=name)
        seen.add(name)
    for name in required:
        if name not in seen:
            raise DataError(
                table.path,
                f"missing column (the header has: {', '.join(header)}; required: "
                f"{', '.join(required)})",
                line=table.header_line,
                field=name,
            )
    found: list[str] = []
    known = set(required)
    for choices in groups or []:
        for group in choices:
            known.update(group)
        present = [g for g in choices if any(c in seen for c in g)]
        if len(present) > 1:
            raise DataError(
                table.path,
                "give one set of optional columns, not several: "
                + " | ".join(", ".join(g) for g in present),
                line=table.header_line,
            )
        if present:
            group = present[0]
            for name in group:
                if name not in seen:
                    raise DataError(
                        table.path,
                        f"missing column: the optional columns {', '.join(group)} come together",
                        line=table.header_line,
                        field=name,
                    )
            found.extend(group)
    for name in header:
        if name not in known:
            raise DataError(
                table.path,
                f"unknown column (expected: {', '.join(sorted(known, key=_order(required)))})",
                line=table.header_line,
                field=name,
            )
    return found


def _order(required: list[str]):
    def key(name: str) -> tuple[int, str]:
        return (required.index(name), "") if name in required else (len(required), name)

    return key


@dataclass
class CleanReport:
    """What the cleaning rules did, per stream; becomes part of ``Sequence.meta``.

    Attributes:
        dropped_nonfinite: stream -> number of samples with NaN/inf values dropped.
        dropped_lines: stream -> first few 1-based line numbers of those (text files).
        dropped_indices: stream -> first few 0-based sample indices of those (binary files).
        dropped_duplicates: stream -> samples dropped for repeating the previous timestamp.
        sorted: stream -> number of backwards time steps fixed by sorting (``sort=True``).
    """

    dropped_nonfinite: dict[str, int] = field(default_factory=dict)
    dropped_lines: dict[str, list[int]] = field(default_factory=dict)
    dropped_indices: dict[str, list[int]] = field(default_factory=dict)
    dropped_duplicates: dict[str, int] = field(default_factory=dict)
    sorted: dict[str, int] = field(default_factory=dict)

    def to_meta(self) -> dict[str, Any]:
        """The report as plain ``meta`` entries (empty line/index dicts are left out)."""
        out: dict[str, Any] = {
            "dropped_nonfinite": dict(self.dropped_nonfinite),
            "dropped_duplicates": dict(self.dropped_duplicates),
            "sorted": dict(self.sorted),
        }
        if self.dropped_lines:
            out["dropped_lines"] = dict(self.dropped_lines)
        if self.dropped_indices:
            out["dropped_indices"] = dict(self.dropped_indices)
        return out


def _where(lines: np.ndarray | None, i: int, prefix: str, name: str) -> dict[str, Any]:
    """Keyword arguments for DataError locating sample ``i``."""
    if lines is not None:
        return {"line": int(lines[i]), "field": name}
    return {"field": f"{prefix}{name}"}


def clean_stream(
    report: CleanReport,
    stream: str,
    path: str,
    arrays: dict[str, np.ndarray],
    *,
    lines: np.ndarray | None = None,
    sort: bool = False,
    nan_ok: tuple[str, ...] = (),
    field_prefix: str = "",
    time_name: str = "t",
) -> dict[str, np.ndarray]:
    """Apply the io rules to one stream and record what was done in ``report``.

    1. Samples with a NaN or inf in ``t`` or any value are dropped (fields in ``nan_ok``,
       uncertainties, may be NaN meaning "not given"; inf still drops).
    2. Timestamps must not go backwards: DataError naming the line, unless ``sort``, in which
       case the stream is stably sorted by time.
    3. A sample whose timestamp exactly equals the previous one is dropped (first kept).

    Args:
        report: accumulates counts for ``Sequence.meta``.
        stream: stream name used as the report key, e.g. ``"imu"``.
        path: file named in errors.
        arrays: field -> (N, ...) float64 arrays; must contain ``"t"`` (N,) in s.
        lines: (N,) 1-based line numbers (text files) or None (binary files: errors and
            the report use 0-based sample indices).
        sort: sort instead of raising on backwards time.
        nan_ok: fields where NaN is allowed.
        field_prefix: prefix for field names in errors without line numbers (``"imu/"``).
        time_name: name of the time column in errors.

    Returns:
        the cleaned arrays (same keys).
    """
    t = arrays["t"]
    n = t.shape[0]
    good = np.isfinite(t)
    for key, value in arrays.items():
        if key == "t":
            continue
        flat = value.reshape(n, math.prod(value.shape[1:]))
        if key in nan_ok:
            good &= ~np.isinf(flat).any(axis=1)
        else:
            good &= np.isfinite(flat).all(axis=1)
    dropped = np.flatnonzero(~good)
    report.dropped_nonfinite[stream] = int(dropped.size)
    if dropped.size:
        first = dropped[:MAX_REPORTED_LINES]
        if lines is not None:
            report.dropped_lines[stream] = [int(x) for x in lines[first]]
        else:
            report.dropped_indices[stream] = [int(x) for x in first]
        arrays = {k: v[good] for k, v in arrays.items()}
        lines = lines[good] if lines is not None else None
        index = np.flatnonzero(good)
    else:
        index = np.arange(n)
    t = arrays["t"]
    back = np.flatnonzero(t[1:] < t[:-1]) + 1
    report.sorted[stream] = int(back.size) if sort else 0
    if back.size:
        i = int(back[0])
        if not sort:
            if lines is not None:
                before = f"line {int(lines[i - 1])}"
                here = ""
            else:
                before = f"sample {int(index[i - 1])}"
                here = f"sample {int(index[i])}: "
            raise DataError(
                path,
                f"{here}time goes backwards: {float(t[i])!r} s comes after "
                f"{float(t[i - 1])!r} s on "
                f"{before} (to sort by time instead: --sort for msf run and msf eval, "
                f"sort=True when loading)",
                **_where(lines, i, field_prefix, time_name),
            )
        order = np.argsort(t, kind="stable")
        arrays = {k: v[order] for k, v in arrays.items()}
        t = arrays["t"]
    keep = np.ones(t.shape[0], dtype=bool)
    keep[1:] = t[1:] != t[:-1]
    report.dropped_duplicates[stream] = int((~keep).sum())
    if not keep.all():
        arrays = {k: v[keep] for k, v in arrays.items()}
    return arrays


def check_quaternions(
    path: str,
    quat: np.ndarray,
    *,
    lines: np.ndarray | None = None,
    field_prefix: str = "",
    name: str = "qw",
) -> None:
    """Raise DataError at the first finite quaternion (N, 4) with norm below 1e-6."""
    norm = np.linalg.norm(quat, axis=-1)
    bad = np.flatnonzero(np.isfinite(norm) & (norm < 1e-6))
    if bad.size:
        i = int(bad[0])
        where = "" if lines is not None else f"sample {i}: "
        raise DataError(
            path,
            f"{where}quaternion {quat[i].tolist()} has (near) zero norm",
            **_where(lines, i, field_prefix, name),
        )


def normalise_quaternions(quat: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions scaled to unit norm (rows must be finite, non-zero).

    Rows whose squared norm overflows or underflows (entries near 1e300 or 1e-300) are
    divided by their largest entry first, so they too come out unit.
    """
    if quat.shape[0] == 0:
        return quat
    norm = np.linalg.norm(quat, axis=-1, keepdims=True)
    odd = ~np.isfinite(norm) | (norm < 1e-100)
    if odd.any():
        largest = np.abs(quat).max(axis=-1, keepdims=True)
        quat = np.where(odd, quat / np.where(odd, largest, 1.0), quat)
        norm = np.linalg.norm(quat, axis=-1, keepdims=True)
    return quat / norm


def stream_from_arrays(kind: type, arrays: dict[str, np.ndarray]) -> Any:
    """Build a stream dataclass with B = 1 from (N, ...) arrays: float64 tensors (1, N, ...)
    and an all-True mask (1, N)."""
    fields = {}
    n = arrays["t"].shape[0]
    for f in dataclasses.fields(kind):
        if f.name == "mask":
            fields["mask"] = torch.ones((1, n), dtype=torch.bool)
        else:
            fields[f.name] = torch.as_tensor(
                np.ascontiguousarray(arrays[f.name]), dtype=torch.float64
            ).unsqueeze(0)
    return kind(**fields)


def path_name(path: str | os.PathLike[str]) -> str:
    """A sequence name from a file or folder path: the stem (``run1.npz`` -> ``run1``)."""
    p = Path(path)
    return p.stem if p.suffix else p.name
