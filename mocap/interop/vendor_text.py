"""Readers for vendors' text exports of labeled 3D markers (layouts in shared/notes/vendor-formats.md).

- OptiTrack Motive CSV (format versions 1.21 to 1.25): the key/value row, then the Type, Name,
  (ID, Parent), measurement and axis rows, found by content (the axis row starts ``Frame,``).
  Only ``Marker`` position columns are kept: rigid bodies, bones and their markers are ignored
  and unlabeled markers left out (they cannot be followed across takes), each with a note.
  ``Length Units`` (Meters by default) are converted to mm. A shared ``Asset:`` prefix is
  dropped from the names (noted).
- Qualisys QTM TSV 3D export: ``KEY<TAB>value`` header lines (``FILE_VERSION`` absent before
  2.0.0), ``MARKER_NAMES``, the column row ``Frame<TAB>Time<TAB>n1 X...`` (an SMPTE column and
  trailing tabs allowed), data in mm. Empty cells and 0.000 triplets are gaps (noted). A
  header-less export (data only) needs the frame rate from the caller; its markers are named
  ``M001``...
- Vicon Nexus CSV export: the ``Trajectories`` section (title, rate, labels, ``Frame,Sub Frame``
  axis row, units row, data); other sections are ignored with a note.

All: blank cells are gaps; missing frame numbers become NaN rows (noted); a truncated last row,
a row of the wrong width or a non-numeric cell is an error naming the file and line.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from mocap.interop.marker_data import ImportError_, MarkerData, unique_names, unit_scale


def _lines(path: Path) -> list[str]:
    try:
        text = path.read_text(encoding="utf-8-sig", errors="strict")
    except UnicodeDecodeError as e:
        raise ImportError_(f"{path}: not a text export ({e})") from None
    except FileNotFoundError:
        raise ImportError_(f"{path}: file not found") from None
    lines = text.splitlines()
    if not lines:
        raise ImportError_(f"{path}: empty file")
    if not text.endswith("\n") and len(lines) > 1:
        # a last line cut short: fewer fields than the line before it
        sep = "\t" if "\t" in lines[-2] else ","
        if len(lines[-1].rstrip(sep).split(sep)) < len(lines[-2].rstrip(sep).split(sep)):
            raise ImportError_(f"{path} line {len(lines)}: truncated row (the file ends mid-row)")
    return lines


def _numeric_block(path: Path, rows: list[str], first_line: int, sep: str, width: int) -> np.ndarray:
    """Parse data rows into floats (n_rows, width); blank -> NaN; errors name the line.

    Parsed in one pass by pandas' C reader; only when that fails is the file walked cell by cell
    to name the offending line and column.
    """
    import io

    import pandas as pd

    if not rows:
        return np.zeros((0, width))
    trimmed = pd.Series(rows, dtype=object).str.rstrip(sep + " ")  # trailing empty cells
    n_cells = trimmed.str.count(re.escape(sep)) + 1
    wide = np.flatnonzero(n_cells.to_numpy() > width)
    if wide.size:
        i = int(wide[0])
        raise ImportError_(f"{path} line {first_line + i}: {int(n_cells.iloc[i])} cells, expected {width}")
    try:
        table = pd.read_csv(io.StringIO("\n".join(trimmed)), sep=sep, header=None, names=range(width),
                            dtype=float, skip_blank_lines=False, skipinitialspace=True,
                            engine="c")
        out = table.to_numpy(dtype=float)
        if out.shape[0] != len(rows):
            out = None
    except (ValueError, OverflowError, pd.errors.ParserError):
        out = None
    if out is None:
        out = _numeric_block_slow(path, rows, first_line, sep, width)
    infinite = np.isinf(out)
    if infinite.any():
        i, j = (int(k[0]) for k in np.nonzero(infinite))
        raise ImportError_(f"{path} line {first_line + i}, column {j + 1}: expected a finite "
                           f"number, got {out[i, j]}")
    return out


def _numeric_block_slow(path: Path, rows: list[str], first_line: int, sep: str, width: int) -> np.ndarray:
    """Cell by cell: used only to locate what the fast parser refused."""
    out = np.full((len(rows), width), np.nan)
    for i, row in enumerate(rows):
        for j, cell in enumerate(row.rstrip(sep + " ").split(sep)[:width]):
            cell = cell.strip()
            if cell == "":
                continue
            try:
                out[i, j] = float(cell)
            except ValueError:
                raise ImportError_(f"{path} line {first_line + i}, column {j + 1}: expected a "
                                   f"number, got {cell!r}") from None
    return out


MAX_MISSING_FRAMES = 1_000_000  # a frame number further ahead is a damaged cell, not a gap


def _rate(value: str | None, fps: float | None, where: str) -> float | None:
    """A frame rate cell (Hz) as a positive finite float; ``fps`` (the caller's) when the cell is
    absent or blank; an ImportError_ naming ``where`` when it is not a rate."""
    if value is None or not str(value).strip():
        return fps
    try:
        rate = float(value)
    except ValueError:
        raise ImportError_(f"{where}: frame rate {value!r} is not a number") from None
    if not np.isfinite(rate) or rate <= 0:
        raise ImportError_(f"{where}: expected a positive frame rate, got {value!r}")
    return rate


def _fill_missing_frames(path: Path, frames: np.ndarray, X: np.ndarray, notes: list[str],
                         first_line: int):
    """Check the frame column (integers, increasing) and insert missing frames as gaps.

    ``first_line`` is the file line of the first data row (messages name lines)."""
    if frames.size == 0:
        raise ImportError_(f"{path}: no data rows")
    bad = np.flatnonzero(~np.isfinite(frames) | (frames != np.round(frames)) | (np.abs(frames) > 2**53))
    if bad.size:
        i = int(bad[0])
        raise ImportError_(f"{path} line {first_line + i}: frame number {frames[i]:g} is not an "
                           "integer (a blank line or a damaged cell)")
    frames = frames.astype(np.int64)
    if np.any(np.diff(frames) <= 0):
        k = int(np.flatnonzero(np.diff(frames) <= 0)[0])
        raise ImportError_(f"{path} line {first_line + k + 1}: frame numbers not increasing "
                           f"(frame {frames[k + 1]} after {frames[k]})")
    jump = np.diff(frames)
    if jump.size and int(jump.sum()) - jump.size > MAX_MISSING_FRAMES:
        k = int(np.argmax(jump))
        raise ImportError_(f"{path} line {first_line + k + 1}: frame numbers jump from {frames[k]} "
                           f"to {frames[k + 1]} (more than {MAX_MISSING_FRAMES} missing frames)")
    full = np.arange(frames[0], frames[-1] + 1)
    if full.size != frames.size:
        notes.append(f"{path}: {full.size - frames.size} missing frame(s) between {frames[0]} and "
                     f"{frames[-1]} inserted as gaps")
        Y = np.full((full.size,) + X.shape[1:], np.nan)
        Y[frames - frames[0]] = X
        X = Y
    return int(frames[0]), X


def _drop_shared_prefix(names: list[str], path: Path, what: str, notes: list[str]) -> list[str]:
    """Drop a ``Prefix:`` every name shares (one asset or subject), noting it."""
    prefixes = {n.split(":", 1)[0] for n in names if ":" in n}
    if len(prefixes) == 1 and all(":" in n for n in names):
        notes.append(f"{path}: {what} prefix '{prefixes.pop()}:' dropped from marker names")
        return [n.split(":", 1)[1] for n in names]
    return names


def read_motive_csv(path: str | os.PathLike, fps: float | None = None) -> MarkerData:
    path = Path(path)
    lines = _lines(path)
    notes: list[str] = []
    head = lines[0].split(",")
    meta = {head[i].strip(): head[i + 1].strip() for i in range(0, len(head) - 1, 2)}
    if "Format Version" not in meta:
        raise ImportError_(f"{path} line 1: expected Motive's header ('Format Version,1.23,...')")
    axis_row = next((i for i, ln in enumerate(lines) if ln.startswith("Frame,")), None)
    if axis_row is None:
        raise ImportError_(f"{path}: no column row starting 'Frame,' (Motive CSV export)")
    header = [ln.split(",") for ln in lines[1:axis_row]]
    types = next((r for r in header if any(c in ("Marker", "Rigid Body", "Unlabeled Marker",
                                                    "Rigid Body Marker", "Bone", "Bone Marker")
                                           for c in r)), None)
    if types is None:
        raise ImportError_(f"{path}: no Type row (Marker, Rigid Body, ...) above line {axis_row + 1}")
    if header.index(types) + 1 >= len(header):
        raise ImportError_(f"{path} line {axis_row}: no Name row below the Type row (Motive CSV "
                           "export)")
    names_row = header[header.index(types) + 1]
    measure = next((r for r in header if "Position" in r), None)
    axes = lines[axis_row].split(",")
    width = len(axes)
    key = "Export Frame Rate" if meta.get("Export Frame Rate") else "Capture Frame Rate"
    rate = _rate(meta.get(key), fps, f"{path} line 1 '{key}'")
    if rate is None:
        raise ImportError_(f"{path}: no frame rate in the header: give it (--fps)")
    scale = unit_scale(meta.get("Length Units", "Meters"), f"{path} line 1 'Length Units'")
    if scale != 1.0:
        notes.append(f"{path}: coordinates converted from {meta.get('Length Units', 'Meters')} to mm")
    cols: dict[str, dict[str, int]] = {}
    ignored = set()
    for j in range(2, width):
        t = types[j].strip() if j < len(types) else ""
        name = names_row[j].strip() if j < len(names_row) else ""
        m = measure[j].strip() if measure is not None and j < len(measure) else "Position"
        if t != "Marker":
            if t:
                ignored.add(t)
            continue
        if m != "Position":
            continue
        axis = axes[j].strip().upper()
        key, k = name, 1
        while axis in cols.get(key, {}):  # the same label again: a second marker, kept apart
            k += 1
            key = f"{name}~{k}"
        if k > 1 and key not in cols:
            notes.append(f"{path}: duplicate label {name!r} (column {j + 1}) renamed {key!r}")
        cols.setdefault(key, {})[axis] = j
    for t in sorted(ignored):
        notes.append(f"{path}: '{t}' columns ignored (only labeled markers are imported)")
    if not cols:
        raise ImportError_(f"{path}: no labeled 'Marker' position columns")
    data = _numeric_block(path, lines[axis_row + 1:], axis_row + 2, ",", width)
    names = list(cols)
    X = np.stack([np.stack([data[:, cols[n].get(a, -1)] if a in cols[n] else np.full(len(data), np.nan)
                            for a in "XYZ"], axis=-1) for n in names], axis=1) * scale
    names = _drop_shared_prefix(names, path, "asset", notes)
    names = unique_names(names, str(path), notes)
    first, X = _fill_missing_frames(path, data[:, 0], X, notes, axis_row + 2)
    return MarkerData(names, X, rate, first, {}, notes, str(path))


def read_qtm_tsv(path: str | os.PathLike, fps: float | None = None) -> MarkerData:
    path = Path(path)
    lines = _lines(path)
    notes: list[str] = []
    meta: dict[str, list[str]] = {}
    i = 0
    while i < len(lines) and lines[i] and re.match(r"^[A-Z_]+(\t|$)", lines[i]):
        parts = lines[i].rstrip("\t").split("\t")
        meta[parts[0]] = parts[1:]
        i += 1
    freq_line = next((k + 1 for k in range(i) if lines[k].startswith("FREQUENCY")), 0)
    rate = _rate((meta.get("FREQUENCY") or [""])[0], fps, f"{path} line {freq_line} 'FREQUENCY'")
    if "FILE_VERSION" not in meta and meta:
        notes.append(f"{path}: no FILE_VERSION (a QTM export older than 2.0.0)")
    if i < len(lines) and lines[i].startswith("Frame\t"):
        colrow = lines[i].rstrip("\t").split("\t")
        start = i + 1
    else:
        colrow = None
        start = i
    if rate is None:
        raise ImportError_(f"{path}: no FREQUENCY line: give the frame rate (--fps)")
    if not meta:
        notes.append(f"{path}: header-less export (data only): markers named M001...")
    rows = [ln for ln in lines[start:]]
    if colrow is not None:
        width = len(colrow)
        data = _numeric_block(path, rows, start + 1, "\t", width)
        names = meta.get("MARKER_NAMES")
        cells = [c.strip() for c in colrow]
        if names is None:
            names = [c[:-2] for c in cells if c.endswith(" X")]
        # the k-th marker of a name takes the k-th columns of that name (duplicate labels stay
        # apart)
        seen: dict[str, int] = {}
        idx = []
        for n in names:
            k = seen.get(n, 0)
            seen[n] = k + 1
            try:
                idx.append([[j for j, c in enumerate(cells) if c == f"{n} {a}"][k] for a in "XYZ"])
            except IndexError:
                raise ImportError_(f"{path} line {start}: no X, Y, Z columns for marker {n!r}"
                                   + (f" (occurrence {k + 1})" if k else "")) from None
        X = np.stack([data[:, cols] for cols in idx], axis=1)
        frames = data[:, cells.index("Frame")]
    else:
        if not rows:
            raise ImportError_(f"{path}: no data rows after the header (line {start})")
        count = (meta.get("NO_OF_MARKERS") or ["0"])[0]
        if not count.strip().isdigit():
            raise ImportError_(f"{path}: NO_OF_MARKERS {count!r} is not a whole number")
        n_markers = int(count)
        first_cells = rows[0].rstrip("\t").split("\t")
        width = len(first_cells)
        data = _numeric_block(path, rows, start + 1, "\t", width)
        n_markers = n_markers or width // 3
        if 3 * n_markers > width or n_markers == 0:
            raise ImportError_(f"{path} line {start + 1}: {width} columns, expected 3 per marker "
                               f"for {n_markers or 'one or more'} markers")
        X = data[:, : 3 * n_markers].reshape(len(data), n_markers, 3)
        names = meta.get("MARKER_NAMES") or [f"M{k + 1:03d}" for k in range(n_markers)]
        if len(names) != n_markers:
            raise ImportError_(f"{path}: MARKER_NAMES lists {len(names)} names for {n_markers} "
                               "markers")
        frames = np.arange(1, len(data) + 1)
    zero = np.all(X == 0.0, axis=-1)
    if zero.any():
        notes.append(f"{path}: {int(zero.sum())} samples of 0.000, 0.000, 0.000 read as gaps")
        X[zero] = np.nan
    names = unique_names(list(names), str(path), notes)
    first, X = _fill_missing_frames(path, frames, X, notes, start + 1)
    return MarkerData(names, X, float(rate), first, {}, notes, str(path))


def read_vicon_csv(path: str | os.PathLike, fps: float | None = None) -> MarkerData:
    path = Path(path)
    lines = _lines(path)
    notes: list[str] = []
    try:
        top = next(i for i, ln in enumerate(lines) if ln.split(",")[0].strip() == "Trajectories")
    except StopIteration:
        raise ImportError_(f"{path}: no 'Trajectories' section (Vicon Nexus CSV export)") from None
    if top + 5 > len(lines):
        raise ImportError_(f"{path} line {len(lines)}: the Trajectories header ends early (expected "
                           "title, rate, labels, 'Frame,Sub Frame,...' and units lines)")
    rate = _rate(lines[top + 1].split(",")[0], fps, f"{path} line {top + 2}")
    labels = lines[top + 2].split(",")
    axes = lines[top + 3].split(",")
    if axes[:2] != ["Frame", "Sub Frame"]:
        raise ImportError_(f"{path} line {top + 4}: expected 'Frame,Sub Frame,X,Y,Z,...'")
    units = lines[top + 4].split(",")
    width = len(axes)
    if width < 5 or (width - 2) % 3:
        raise ImportError_(f"{path} line {top + 4}: {width} columns, expected Frame, Sub Frame and "
                           "X, Y, Z per marker")
    end = next((i for i in range(top + 5, len(lines)) if not lines[i].strip(", ")), len(lines))
    if end < len(lines):
        others = [ln.split(",")[0] for ln in lines[end:] if ln.split(",")[0].strip() in
                  ("Devices", "Model Outputs", "Joints", "Segments", "Trajectories")]
        if others:
            notes.append(f"{path}: sections {others} ignored (only Trajectories are imported)")
    data = _numeric_block(path, lines[top + 5: end], top + 6, ",", width)
    names, cols = [], []
    for j in range(2, width, 3):
        names.append(labels[j].strip() if j < len(labels) else f"col{j}")
        cols.append(j)
    scale = unit_scale(units[2] if len(units) > 2 and units[2].strip() else "mm", f"{path} line {top + 5}")
    X = np.stack([data[:, j: j + 3] for j in cols], axis=1) * scale
    names = _drop_shared_prefix(names, path, "subject", notes)
    names = unique_names(names, str(path), notes)
    first, X = _fill_missing_frames(path, data[:, 0], X, notes, top + 6)
    if rate is None:
        raise ImportError_(f"{path} line {top + 2}: no frame rate: give it (--fps)")
    return MarkerData(names, X, rate, first, {}, notes, str(path))


def sniff(path: str | os.PathLike):
    """The reader for a file, from its extension and first line."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext == ".c3d":
        from mocap.interop.c3d_file import read_c3d

        return read_c3d
    if ext == ".tsv":
        return read_qtm_tsv
    if ext == ".csv":
        first = _lines(path)[0]
        if first.startswith("Format Version"):
            return read_motive_csv
        if first.split(",")[0].strip() in ("Trajectories", "Devices"):
            return read_vicon_csv
        raise ImportError_(f"{path} line 1: not a Motive ('Format Version,...') or Vicon Nexus "
                           "('Trajectories') CSV export")
    raise ImportError_(f"{path}: unknown file type {ext!r} (expected .c3d, .csv or .tsv)")
