"""The session's data files (take files, commands files, ``markers.csv``): validated reads.

CSV or Parquet; CSV read by pyarrow with typed columns, and on failure checked row by row to
name the offending line. Readers return pandas DataFrames in file order with the columns and
units of :mod:`mocap.core.session`'s conventions (2D take: ``frame`` int64, ``camera``
categorical, ``x``, ``y`` float64 px; 3D take: ``frame``, ``marker``, ``x``, ``y``, ``z`` float64
mm with NaN when unseen; commands: ``time_s`` float64 s, ``du``, ``command`` int64; markers:
``name``, ``x``, ``y``, ``z`` float64 mm). Every violation raises
:class:`~mocap.core.session.SessionError` naming the file and the row (CSV: 1-based line, the
header being line 1; Parquet: 1-based row).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from mocap.core.session import COMMAND_MAX, COMMAND_MIN, MARKER_COLUMNS, SessionError

_MAX_INT = 2**53  # largest integer a float64 column holds exactly
# Tokens read as "no value" in numeric CSV columns (pyarrow's defaults, as its fast path does).
_NULL_TOKENS = frozenset(
    [
        "",
        "#N/A",
        "#N/A N/A",
        "#NA",
        "-1.#IND",
        "-1.#QNAN",
        "-NaN",
        "-nan",
        "1.#IND",
        "1.#QNAN",
        "N/A",
        "NA",
        "NULL",
        "NaN",
        "n/a",
        "nan",
        "null",
    ]
)
_NULL_ARRAY = pa.array(sorted(_NULL_TOKENS), pa.string())


@dataclass(frozen=True)
class _Source:
    """A data file and how messages name it."""

    path: Path
    label: str

    @property
    def is_csv(self) -> bool:
        return self.path.suffix.lower() == ".csv"

    def where(self, row: int) -> str:
        """``label line N`` (CSV, header = line 1) or ``label row N`` (Parquet) of data row
        ``row`` (0-based)."""
        if self.is_csv:
            return f"{self.label} line {_csv_line_of_row(self, row)}"
        return f"{self.label} row {row + 1}"


def _inspect_file(src: _Source) -> tuple[list[str], bool]:
    """The file's column names, and whether it has any data row; reads only the header."""
    if src.is_csv:
        return _csv_header(src)
    try:
        meta = pq.read_metadata(src.path)
    except (OSError, pa.ArrowException) as exc:
        raise SessionError(f"{src.label}: not a readable Parquet file ({exc})") from None
    return list(meta.schema.to_arrow_schema().names), meta.num_rows > 0


def _csv_header(src: _Source) -> tuple[list[str], bool]:
    try:
        with open(src.path, newline="", encoding="utf-8-sig") as fh:
            line = fh.readline()
            has_rows = False
            for rest in fh:
                if rest.strip("\r\n"):
                    has_rows = True
                    break
    except (OSError, UnicodeDecodeError) as exc:
        raise SessionError(f"{src.label}: cannot be read as UTF-8 text ({exc})") from None
    if not line.strip():
        raise SessionError(f"{src.label} line 1: empty; expected a header line of column names")
    columns = [c.strip() for c in next(csv.reader([line]))]
    dupes = sorted({c for c in columns if columns.count(c) > 1})
    if dupes:
        raise SessionError(f"{src.label} line 1: duplicate column(s) {', '.join(dupes)}")
    return columns, has_rows


def _csv_rows(src: _Source):
    """Yield ``(line_number, fields)`` for non-empty CSV rows, header included (line 1).

    Error path only: a Python loop over the file, used when fields may be quoted.
    """
    try:
        with open(src.path, newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh)
            for fields in reader:
                if fields:
                    yield reader.line_num, fields
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise SessionError(f"{src.label}: cannot be read as UTF-8 CSV ({exc})") from None


def _csv_lines(src: _Source) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The file's bytes, and the byte offsets where each physical line starts and ends.

    Error path only (reads the whole file into memory, vectorised).

    Returns
    -------
    data : (n_bytes,) uint8; starts, ends : (n_lines,) int64, ``ends`` exclusive of the
    newline (and of a carriage return before it).
    """
    try:
        data = np.fromfile(src.path, dtype=np.uint8)
    except OSError as exc:
        raise SessionError(f"{src.label}: cannot be read ({exc})") from None
    newlines = np.flatnonzero(data == 10)
    starts = np.concatenate([[0], newlines + 1])
    ends = np.concatenate([newlines, [data.size]])
    if starts[-1] == data.size:  # the file ends with a newline: no line after it
        starts, ends = starts[:-1], ends[:-1]
    cr = (ends > starts) & (data[np.maximum(ends - 1, 0)] == 13)
    ends = ends - cr
    return data, starts.astype(np.int64), ends.astype(np.int64)


def _csv_line_of_row(src: _Source, row: int) -> int:
    """1-based line number of 0-based data row ``row`` (blank lines skipped, as pyarrow does;
    the header is line 1)."""
    _, starts, ends = _csv_lines(src)
    filled = np.flatnonzero(ends > starts) + 1
    return int(filled[row + 1]) if row + 1 < filled.size else row + 2


def _diagnose_csv_structure(src: _Source, n_columns: int) -> None:
    """Raise naming the first row whose field count differs from the header's."""
    data, starts, ends = _csv_lines(src)
    if np.any(data == ord('"')):  # quoted fields may hold commas: let the csv module count
        bad_rows = [(line, len(f)) for line, f in _csv_rows(src) if len(f) != n_columns]
        last = max((line for line, _ in _csv_rows(src)), default=0)
    else:
        commas = np.flatnonzero(data == ord(","))
        line_of_comma = np.searchsorted(starts, commas, side="right") - 1
        inside = commas < ends[line_of_comma]
        n_fields = np.bincount(line_of_comma[inside], minlength=starts.size) + 1
        filled = ends > starts
        wrong = np.flatnonzero(filled & (n_fields != n_columns))
        bad_rows = [(int(wrong[0]) + 1, int(n_fields[wrong[0]]))] if wrong.size else []
        last = int(np.flatnonzero(filled)[-1]) + 1 if filled.any() else 0
    if not bad_rows:
        return
    line, got = bad_rows[0]
    hint = "; the file looks truncated mid-row" if line == last else ""
    raise SessionError(
        f"{src.label} line {line}: {got} field(s), expected {n_columns} (the header's "
        f"columns){hint}"
    )


def _read_columns(src: _Source, spec: Mapping[str, str]) -> pa.Table:
    """Read the columns of ``spec`` (name -> "num" | "str" | "dict") as an Arrow table ("dict":
    strings, read from Parquet as a dictionary: a column of few distinct values, such as camera
    ids, then costs one check per value instead of per row; :func:`_camera_column`).

    CSV is read by pyarrow with typed columns; when that fails (a malformed row, a value that
    is not a number), the file is checked row by row to name the offending line, then read as
    text and converted leniently. Column types are normalised by :func:`_float_column` and
    :func:`_string_column`.
    """
    names = list(spec)
    if src.is_csv:
        header, _ = _csv_header(src)
        read_opts = pacsv.ReadOptions(column_names=header, skip_rows=1)
        typed = {n: pa.float64() if spec[n] == "num" else pa.string() for n in names}
        try:
            return pacsv.read_csv(
                src.path,
                read_options=read_opts,
                convert_options=pacsv.ConvertOptions(
                    include_columns=names, column_types=typed, strings_can_be_null=False
                ),
            )
        except pa.ArrowInvalid:
            pass
        _diagnose_csv_structure(src, len(header))
        try:
            return pacsv.read_csv(
                src.path,
                read_options=read_opts,
                convert_options=pacsv.ConvertOptions(
                    include_columns=names,
                    column_types={n: pa.string() for n in names},
                    strings_can_be_null=False,
                ),
            )
        except (OSError, pa.ArrowException) as exc:
            raise SessionError(f"{src.label}: cannot be read as CSV ({exc})") from None
    try:
        return pq.read_table(src.path, columns=names,
                             read_dictionary=[n for n in names if spec[n] == "dict"] or None)
    except (OSError, pa.ArrowException) as exc:
        raise SessionError(f"{src.label}: cannot be read as Parquet ({exc})") from None


def _float_column(src: _Source, table: pa.Table, name: str) -> np.ndarray:
    """Column ``name`` as float64 (missing values NaN); SessionError naming a non-number."""
    col = table.column(name)
    kind = col.type
    if pa.types.is_floating(kind) or pa.types.is_integer(kind) or pa.types.is_decimal(kind):
        return pc.cast(col, pa.float64()).to_numpy(zero_copy_only=False)
    if pa.types.is_dictionary(kind):
        col = pc.cast(col, pa.string())
        kind = col.type
    if pa.types.is_string(kind) or pa.types.is_large_string(kind):
        return _parse_floats(src, name, col)
    raise SessionError(f"{src.label}: column {name!r} has type {kind}, expected numbers")


def _parse_floats(src: _Source, name: str, col: pa.ChunkedArray) -> np.ndarray:
    """Parse a text column as float64: whitespace trimmed, null tokens (``""``, ``NaN``, ...)
    as NaN. A value that is not a number is located by bisection (vectorised casts)."""
    text = pc.utf8_trim_whitespace(col)
    nullish = pc.or_kleene(pc.is_null(text), pc.is_in(text, value_set=_NULL_ARRAY))
    text = pc.if_else(nullish, pa.scalar(None, text.type), text)
    try:
        return pc.cast(text, pa.float64()).to_numpy(zero_copy_only=False)
    except pa.ArrowInvalid:
        pass
    lo, hi = 0, len(text)  # the first unparsable value lies in [lo, hi)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        try:
            pc.cast(text.slice(lo, mid - lo), pa.float64())
            lo = mid
        except pa.ArrowInvalid:
            hi = mid
    raise SessionError(f"{src.where(lo)}: {name} {col[lo].as_py()!r} is not a number")


def _string_column(src: _Source, table: pa.Table, name: str) -> pa.ChunkedArray:
    """Column ``name`` as Arrow strings, whitespace-trimmed; SessionError on a missing value."""
    col = table.column(name)
    if pa.types.is_dictionary(col.type) or pa.types.is_large_string(col.type):
        col = pc.cast(col, pa.string())
    if not pa.types.is_string(col.type):
        raise SessionError(f"{src.label}: column {name!r} has type {col.type}, expected strings")
    if col.null_count:
        i = int(np.argmax(col.is_null().to_numpy(zero_copy_only=False)))
        raise SessionError(f"{src.where(i)}: {name} is missing, expected a string")
    try:  # Parquet readers do not check that string bytes are UTF-8 (pyarrow's CSV reader
        # does); Arrow's string kernels need it. About 3 ms per 400 k values.
        if not src.is_csv:
            col.validate(full=True)
    except pa.ArrowInvalid:
        lo, hi = 0, len(col)  # the first value that is not UTF-8 lies in [lo, hi)
        while hi - lo > 1:
            mid = (lo + hi) // 2
            try:
                col.slice(lo, mid - lo).validate(full=True)
                lo = mid
            except pa.ArrowInvalid:
                hi = mid
        raw = pc.cast(col.slice(lo, 1), pa.binary())[0].as_py()
        raise SessionError(
            f"{src.where(lo)}: {name} {raw!r} is not UTF-8 text (a damaged file?)"
        ) from None
    return pc.utf8_trim_whitespace(col)


def _camera_column(src: _Source, table: pa.Table, name: str, camera_ids: Sequence[str]
                   ) -> pd.Categorical:
    """Column ``name`` as a Categorical whose categories are ``camera_ids`` (the manifest's
    order), whitespace-trimmed; SessionError naming the row of a missing value, of bytes that
    are not UTF-8 or of an id not in the manifest. A dictionary column (Parquet's usual encoding
    of such a column) is checked on its distinct values (a paper take: 400 k rows, 6 values),
    any other through :func:`_string_column`."""
    col = table.column(name)
    if not pa.types.is_dictionary(col.type):
        col = pc.dictionary_encode(_string_column(src, table, name))
    elif not (pa.types.is_string(col.type.value_type)
              or pa.types.is_large_string(col.type.value_type)):
        raise SessionError(f"{src.label}: column {name!r} has type {col.type}, expected strings")
    col = col.unify_dictionaries()
    if col.null_count:
        i = int(np.argmax(col.is_null().to_numpy(zero_copy_only=False)))
        raise SessionError(f"{src.where(i)}: {name} is missing, expected a string")
    values = col.chunk(0).dictionary
    rows = np.concatenate([c.indices.to_numpy(zero_copy_only=False) for c in col.chunks])
    if pa.types.is_large_string(values.type):
        values = pc.cast(values, pa.string())
    try:  # Parquet readers do not check that string bytes are UTF-8; Arrow's kernels need it
        values.validate(full=True)
    except pa.ArrowInvalid:
        for j in range(len(values)):
            try:
                values.slice(j, 1).validate(full=True)
            except pa.ArrowInvalid:
                i = int(np.argmax(rows == j))
                raw = pc.cast(values.slice(j, 1), pa.binary())[0].as_py()
                raise SessionError(
                    f"{src.where(i)}: {name} {raw!r} is not UTF-8 text (a damaged file?)"
                ) from None
    trimmed = pc.utf8_trim_whitespace(values).to_pylist()
    lookup = pd.Index(list(camera_ids)).get_indexer(trimmed)
    codes = lookup[rows]
    if (codes < 0).any():
        i = int(np.argmax(codes < 0))
        raise SessionError(
            f"{src.where(i)}: camera {trimmed[rows[i]]!r} is not in the manifest "
            f"(cameras: {', '.join(camera_ids)})"
        )
    return pd.Categorical.from_codes(codes, categories=list(camera_ids))


def _show_number(value: float) -> str:
    value = float(value)
    return str(int(value)) if math.isfinite(value) and value.is_integer() else repr(value)


def _integer_values(src, name, values, *, minimum=None, maximum=None, expected) -> np.ndarray:
    """Check a float64 column holds integers within bounds; return it as int64."""
    bad = ~np.isfinite(values)
    with np.errstate(invalid="ignore"):
        bad |= values != np.floor(values)
        if minimum is not None:
            bad |= values < minimum
        if maximum is not None:
            bad |= values > maximum
    if bad.any():
        i = int(np.argmax(bad))
        v = values[i]
        if np.isnan(v):
            problem = f"{name} is empty"
        elif not np.isfinite(v) or v != np.floor(v):
            problem = f"{name} {_show_number(v)} is not an integer"
        elif minimum is not None and v < minimum:
            below = "negative" if minimum == 0 else f"below {minimum}"
            problem = f"{name} {_show_number(v)} is {below}"
        else:
            problem = f"{name} {_show_number(v)} is above {maximum}"
        raise SessionError(f"{src.where(i)}: {problem} (expected {expected})")
    return values.astype(np.int64)


def _frame_column(src: _Source, table: pa.Table) -> np.ndarray:
    """The ``frame`` column as int64 (integers from 0 to 2**53); SessionError naming the row of
    any other value. An integer column with no missing value is checked as it is, without the
    float64 round trip the general path (text, floats) takes."""
    col = table.column("frame")
    if pa.types.is_integer(col.type) and col.null_count == 0:
        values = col.to_numpy()
        if values.min() >= 0 and values.max() <= _MAX_INT:
            return values.astype(np.int64, copy=False)
    return _integer_values(src, "frame", _float_column(src, table, "frame"), minimum=0,
                           maximum=_MAX_INT, expected="an integer frame >= 0")


def _finite_values(src, name, values, *, allow_nan: bool, expected: str) -> None:
    bad = np.isinf(values) if allow_nan else ~np.isfinite(values)
    if bad.any():
        i = int(np.argmax(bad))
        v = values[i]
        problem = f"{name} is empty or NaN" if np.isnan(v) else f"{name} {float(v)!r} is infinite"
        raise SessionError(f"{src.where(i)}: {problem} (expected {expected})")


def _check_not_empty(src: _Source, table: pa.Table, what: str) -> None:
    if table.num_rows == 0:
        raise SessionError(f"{src.label}: no data rows (header only); expected one or more {what}")


def _read_take_2d(src: _Source, camera_ids: Sequence[str]) -> pd.DataFrame:
    table = _read_columns(src, {"frame": "num", "camera": "dict", "x": "num", "y": "num"})
    _check_not_empty(src, table, "detections")
    frame = _frame_column(src, table)
    camera = _camera_column(src, table, "camera", camera_ids)
    x = _float_column(src, table, "x")
    y = _float_column(src, table, "y")
    for name, values in (("x", x), ("y", y)):
        _finite_values(
            src,
            name,
            values,
            allow_nan=False,
            expected="a finite blob coordinate, px; 2D detections cannot be missing",
        )
    return pd.DataFrame({"frame": frame, "camera": camera, "x": x, "y": y})


def _read_take_3d(src: _Source) -> pd.DataFrame:
    table = _read_columns(
        src, {"frame": "num", "marker": "str", "x": "num", "y": "num", "z": "num"}
    )
    _check_not_empty(src, table, "marker samples")
    frame = _frame_column(src, table)
    marker = _string_column(src, table, "marker")
    empty = pc.equal(pc.utf8_length(marker), 0)
    if pc.any(empty).as_py():
        i = int(np.argmax(empty.to_numpy(zero_copy_only=False)))
        raise SessionError(f"{src.where(i)}: marker name is empty (expected a marker name)")
    out = {"frame": frame, "marker": marker.to_pandas()}
    for name in ("x", "y", "z"):
        values = _float_column(src, table, name)
        _finite_values(
            src,
            name,
            values,
            allow_nan=True,
            expected="a position in mm, or empty/NaN when not seen",
        )
        out[name] = values
    return pd.DataFrame(out)


def _read_commands(src: _Source, du_ids: Sequence[int]) -> pd.DataFrame:
    table = _read_columns(src, {"time_s": "num", "du": "num", "command": "num"})
    time_s = _float_column(src, table, "time_s")
    bad = ~np.isfinite(time_s) | (time_s < 0)
    if bad.any():
        i = int(np.argmax(bad))
        v = time_s[i]
        problem = (
            "time_s is empty"
            if np.isnan(v)
            else f"time_s {_show_number(v)} is " + ("negative" if v < 0 else "infinite")
        )
        raise SessionError(
            f"{src.where(i)}: {problem} (expected seconds >= 0 from the take's first frame)"
        )
    du = _integer_values(
        src, "du", _float_column(src, table, "du"), maximum=_MAX_INT, expected="an integer DU id"
    )
    unknown = ~np.isin(du, np.asarray(du_ids, dtype=np.int64))
    if unknown.any():
        i = int(np.argmax(unknown))
        ids = ", ".join(str(d) for d in du_ids) or "none"
        raise SessionError(
            f"{src.where(i)}: du {du[i]} is not in the manifest's [[dus]] (ids: {ids})"
        )
    command = _integer_values(
        src,
        "command",
        _float_column(src, table, "command"),
        minimum=COMMAND_MIN,
        maximum=COMMAND_MAX,
        expected=f"an integer command {COMMAND_MIN}..{COMMAND_MAX}",
    )
    return pd.DataFrame({"time_s": time_s, "du": du, "command": command})


def _read_markers(src: _Source, notes: list[str]) -> pd.DataFrame:
    columns, has_rows = _csv_header(src)
    _check_columns(src, columns, MARKER_COLUMNS, "the marker template", notes)
    if not has_rows:
        raise SessionError(f"{src.label}: no data rows (header only); expected one per marker")
    table = _read_columns(src, {"name": "str", "x": "num", "y": "num", "z": "num"})
    names = _string_column(src, table, "name").to_pandas()
    empty = (names == "").to_numpy()
    if empty.any():
        raise SessionError(
            f"{src.where(int(np.argmax(empty)))}: name is empty (expected a unique marker name)"
        )
    dup = names.duplicated().to_numpy()
    if dup.any():
        i = int(np.argmax(dup))
        raise SessionError(
            f"{src.where(i)}: duplicate marker name {names.iloc[i]!r} (expected unique names)"
        )
    out = {"name": names}
    for name in ("x", "y", "z"):
        values = _float_column(src, table, name)
        _finite_values(src, name, values, allow_nan=False, expected="a finite rest position, mm")
        out[name] = values
    return pd.DataFrame(out)



def _check_columns(src, columns, required, what, notes) -> None:
    missing = [c for c in required if c not in columns]
    if missing:
        raise SessionError(
            f"{src.label}: missing column(s) {', '.join(repr(c) for c in missing)} (expected "
            f"{what}: {', '.join(required)}; got {', '.join(columns) or 'none'})"
        )
    extra = [c for c in columns if c not in required]
    if extra:
        notes.append(f"{src.label}: extra column(s) {', '.join(repr(c) for c in extra)} ignored")


def _relative_label(root: Path, path: Path) -> str:
    try:
        return path.relative_to(root).as_posix()
    except ValueError:
        return str(path)
