"""The manifest checks: ``session.toml`` parsed into the session's records, with take headers.

Each ``_parse_*`` function validates one part of the manifest (docs/format.md) and returns
frozen records (:class:`~mocap.core.session.CameraInfo`, ``WandSpec``, ``GroundSpec``,
``DUInfo``, ``TakeInfo``); :func:`_inspect_takes` checks that every take and commands file
exists and has the right columns, reading only the header, and tells 2D from 3D. Unknown keys
and ignored columns are appended to ``notes``; every violation raises
:class:`~mocap.core.session.SessionError` naming the manifest key. Used by
:func:`mocap.core.session.load_session`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path, PureWindowsPath
from typing import Any

import numpy as np

from mocap.core.session import (
    COLUMNS_2D,
    COLUMNS_3D,
    COMMAND_COLUMNS,
    MANIFEST,
    TAKE_KINDS,
    CameraInfo,
    DUInfo,
    GroundSpec,
    SessionError,
    TakeInfo,
    WandSpec,
)
from mocap.core.session_files import (
    _MAX_INT,
    _check_columns,
    _inspect_file,
    _relative_label,
    _Source,
)

_TOP_KEYS = ("schema", "name", "fps", "cameras", "wand", "ground", "dus", "takes")
_CAMERA_KEYS = ("id", "width", "height", "focal_px", "principal_px", "distortion", "intrinsics")
INTRINSICS_MODES = ("fixed", "refine")
_WAND_KEYS = ("marker_offsets_mm",)
_GROUND_KEYS = ("markers_mm",)
_DU_KEYS = ("id", "name", "feedback")
_TAKE_KEYS = ("name", "kind", "file", "commands", "commands_offset_s", "du", "trial", "plan")
_EXTENSIONS = (".csv", ".parquet")


def _show(value: Any) -> str:
    """A manifest value as it would appear in TOML (strings double-quoted)."""
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, dict):
        return "a table"
    return repr(value)


def _ctx(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


def _note_unknown(table: Mapping[str, Any], known: Sequence[str], prefix: str, notes: list[str]):
    for key in table:
        if key not in known:
            where = f"{prefix}: " if prefix else ""
            notes.append(
                f"{MANIFEST}: {where}unknown key {key!r} ignored (known: {', '.join(known)})"
            )


def _require(table: Mapping[str, Any], key: str, prefix: str, expected: str) -> Any:
    if key not in table:
        where = f"{prefix}: " if prefix else ""
        raise SessionError(f"{MANIFEST}: {where}missing key {key!r} (expected {expected})")
    return table[key]


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _number(table, key, prefix, expected, *, positive=False, required=True) -> float | None:
    if not required and key not in table:
        return None
    value = _require(table, key, prefix, expected)
    if not _is_number(value) or not math.isfinite(value) or (positive and value <= 0):
        raise SessionError(
            f"{MANIFEST}: {_ctx(prefix, key)}: expected {expected}, got {_show(value)}"
        )
    return float(value)


def _integer(table, key, prefix, expected, *, minimum=None, required=True) -> int | None:
    """An integer value (integer-valued floats such as 1280.0 accepted), at most 2**53: the
    largest the take files' float columns hold exactly, and within numpy's int64."""
    if not required and key not in table:
        return None
    value = _require(table, key, prefix, expected)
    ok = _is_number(value) and math.isfinite(value) and float(value).is_integer()
    if not ok or (minimum is not None and value < minimum):
        raise SessionError(
            f"{MANIFEST}: {_ctx(prefix, key)}: expected {expected}, got {_show(value)}"
        )
    if abs(value) > _MAX_INT:
        raise SessionError(
            f"{MANIFEST}: {_ctx(prefix, key)}: expected {expected} of at most 2**53 "
            f"({_MAX_INT}) in size, got {_show(value)}"
        )
    return int(value)


def _string(table, key, prefix, expected, *, required=True, nonempty=True) -> str | None:
    if not required and key not in table:
        return None
    value = _require(table, key, prefix, expected)
    if not isinstance(value, str) or (nonempty and not value.strip()):
        raise SessionError(
            f"{MANIFEST}: {_ctx(prefix, key)}: expected {expected}, got {_show(value)}"
        )
    return value


def _table_array(doc, key) -> list[dict]:
    value = doc.get(key, [])
    if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
        raise SessionError(
            f"{MANIFEST}: {key}: expected an array of tables ([[{key}]]), got {_show(value)}"
        )
    return value


def _parse_cameras(doc, notes) -> tuple[CameraInfo, ...]:
    cameras: list[CameraInfo] = []
    first_index: dict[str, int] = {}
    for i, tbl in enumerate(_table_array(doc, "cameras")):
        prefix = f"cameras[{i}]"
        cam_id = _string(tbl, "id", prefix, "a unique camera id (string)")
        prefix = f"cameras[{i}] ({cam_id!r})"
        if cam_id in first_index:
            raise SessionError(
                f"{MANIFEST}: cameras[{i}].id: duplicate camera id {_show(cam_id)} (already "
                f"used by cameras[{first_index[cam_id]}]); expected unique ids"
            )
        first_index[cam_id] = i
        _note_unknown(tbl, _CAMERA_KEYS, prefix, notes)
        width = _integer(tbl, "width", prefix, "a positive integer image width, px", minimum=1)
        height = _integer(tbl, "height", prefix, "a positive integer image height, px", minimum=1)
        focal = _number(
            tbl, "focal_px", prefix, "a positive focal length, px", positive=True, required=False
        )
        principal = distortion = mode = None
        if "principal_px" in tbl:
            expected = "[cx, cy], the prior principal point, px"
            principal = _float_array(tbl["principal_px"], prefix, "principal_px", expected, ndim=1)
            if principal.size != 2:
                raise SessionError(f"{MANIFEST}: {prefix}.principal_px: expected {expected}, got "
                                   f"{_show(tbl['principal_px'])}")
            principal = (float(principal[0]), float(principal[1]))
        if "distortion" in tbl:
            expected = "[k1, k2, p1, p2, k3], OpenCV's Brown-Conrady terms (4 or 5 numbers)"
            d = _float_array(tbl["distortion"], prefix, "distortion", expected, ndim=1)
            if d.size not in (4, 5):
                raise SessionError(f"{MANIFEST}: {prefix}.distortion: expected {expected}, got "
                                   f"{_show(tbl['distortion'])}")
            distortion = tuple(float(v) for v in np.r_[d, 0.0][:5])
        if "intrinsics" in tbl:
            mode = tbl["intrinsics"]
            if mode not in INTRINSICS_MODES:
                raise SessionError(f"{MANIFEST}: {prefix}.intrinsics: expected \"fixed\" or "
                                   f"\"refine\", got {_show(mode)}")
            if principal is None and distortion is None:
                raise SessionError(f"{MANIFEST}: {prefix}.intrinsics: {_show(mode)} needs prior "
                                   "intrinsics: add principal_px and distortion (a lens profile), "
                                   "or remove the key")
        elif principal is not None or distortion is not None:
            mode = "refine"
        if mode is not None and focal is None:
            raise SessionError(f"{MANIFEST}: {prefix}: prior intrinsics need focal_px too (the "
                               "lens profile's focal length, px)")
        cameras.append(CameraInfo(id=cam_id, width=width, height=height, focal_px=focal,
                                  principal_px=principal, distortion=distortion, intrinsics=mode))
    return tuple(cameras)


def _float_array(value, prefix: str, key: str, expected: str, ndim: int) -> np.ndarray:
    def fail():
        raise SessionError(f"{MANIFEST}: {prefix}.{key}: expected {expected}, got {_show(value)}")

    if not isinstance(value, list):
        fail()
    rows = value if ndim == 2 else [value]
    for row in rows:
        if not isinstance(row, list) or not all(_is_number(v) for v in row):
            fail()
        if ndim == 2 and len(row) != 3:
            fail()
    arr = np.array(value, dtype=float)
    if arr.ndim != ndim or (ndim == 2 and arr.shape[1] != 3) or not np.all(np.isfinite(arr)):
        fail()
    arr.setflags(write=False)
    return arr


def _parse_wand(tbl, notes) -> WandSpec:
    if not isinstance(tbl, dict):
        raise SessionError(f"{MANIFEST}: wand: expected a table ([wand]), got {_show(tbl)}")
    _note_unknown(tbl, _WAND_KEYS, "wand", notes)
    expected = ("2 or more marker offsets along the wand, mm, strictly increasing (with 3 or more, "
                "gaps distinct)")
    value = _require(tbl, "marker_offsets_mm", "wand", expected)
    offsets = _float_array(value, "wand", "marker_offsets_mm", expected, ndim=1)
    where = f"{MANIFEST}: wand.marker_offsets_mm"
    if offsets.size < 2:
        raise SessionError(f"{where}: expected {expected}; got {offsets.size} marker(s)")
    gaps = np.diff(offsets)
    if np.any(gaps <= 0):
        raise SessionError(f"{where}: expected {expected}; got {_show(value)} (not increasing)")
    close = np.isclose(gaps[:, None], gaps[None, :], rtol=1e-9, atol=1e-9)
    np.fill_diagonal(close, False)
    if close.any():
        i, j = np.argwhere(close)[0]
        raise SessionError(
            f"{where}: gaps must be distinct (they tell the wand's ends apart); got {_show(value)} "
            f"whose gaps {i + 1} and {j + 1} are both {gaps[i]:g} mm"
        )
    return WandSpec(marker_offsets_mm=offsets)


def _parse_ground(tbl, notes) -> GroundSpec:
    if not isinstance(tbl, dict):
        raise SessionError(f"{MANIFEST}: ground: expected a table ([ground]), got {_show(tbl)}")
    _note_unknown(tbl, _GROUND_KEYS, "ground", notes)
    expected = "3 or more non-collinear marker positions [x, y, z], mm"
    value = _require(tbl, "markers_mm", "ground", expected)
    markers = _float_array(value, "ground", "markers_mm", expected, ndim=2)
    where = f"{MANIFEST}: ground.markers_mm"
    if markers.shape[0] < 3:
        raise SessionError(f"{where}: expected {expected}; got {markers.shape[0]} marker(s)")
    centred = markers - markers.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    if s[0] == 0 or s[1] <= 1e-6 * s[0]:
        raise SessionError(
            f"{where}: expected {expected}; got {_show(value)}, which are collinear "
            "(they cannot define the world axes)"
        )
    return GroundSpec(markers_mm=markers)


def _parse_dus(doc, notes) -> tuple[DUInfo, ...]:
    dus: list[DUInfo] = []
    first_index: dict[int, int] = {}
    for i, tbl in enumerate(_table_array(doc, "dus")):
        prefix = f"dus[{i}]"
        du_id = _integer(tbl, "id", prefix, "a unique integer DU id >= 0", minimum=0)
        if du_id in first_index:
            raise SessionError(
                f"{MANIFEST}: dus[{i}].id: duplicate DU id {du_id} (already used by "
                f"dus[{first_index[du_id]}]); expected unique ids"
            )
        first_index[du_id] = i
        prefix = f"dus[{i}] (id {du_id})"
        _note_unknown(tbl, _DU_KEYS, prefix, notes)
        name = _string(tbl, "name", prefix, "a string", required=False, nonempty=False)
        feedback = tbl.get("feedback", False)
        if not isinstance(feedback, bool):
            raise SessionError(
                f"{MANIFEST}: {prefix}.feedback: expected true or false, got {_show(feedback)}"
            )
        dus.append(DUInfo(id=du_id, name=f"DU{du_id}" if name is None else name, feedback=feedback))
    return tuple(dus)


def _parse_takes(doc, root: Path, du_ids: set[int], notes) -> tuple[TakeInfo, ...]:
    tables = _table_array(doc, "takes")
    if not tables:
        raise SessionError(f"{MANIFEST}: missing key 'takes' (expected one or more [[takes]])")
    takes: list[TakeInfo] = []
    first_index: dict[str, int] = {}
    for i, tbl in enumerate(tables):
        prefix = f"takes[{i}]"
        name = _string(tbl, "name", prefix, "a unique take name (string)")
        if name in first_index:
            raise SessionError(
                f"{MANIFEST}: takes[{i}].name: duplicate take name {_show(name)} (already used "
                f"by takes[{first_index[name]}]); expected unique names"
            )
        first_index[name] = i
        prefix = f"takes[{i}] ({name!r})"
        _note_unknown(tbl, _TAKE_KEYS, prefix, notes)
        kinds = " | ".join(TAKE_KINDS)
        kind = _require(tbl, "kind", prefix, kinds)
        if kind not in TAKE_KINDS:
            raise SessionError(
                f"{MANIFEST}: {prefix}.kind: unknown take kind {_show(kind)} (expected {kinds})"
            )
        file = _string(tbl, "file", prefix, "a take file path relative to the session folder")
        commands = _string(
            tbl,
            "commands",
            prefix,
            "a commands file path relative to the session folder",
            required=False,
        )
        du = _integer(tbl, "du", prefix, "an integer DU id", required=False)
        trial = _integer(
            tbl, "trial", prefix, "an integer trial number >= 1", minimum=1, required=False
        )
        plan = _string(tbl, "plan", prefix, "a string", required=False, nonempty=False)
        offset = _number(tbl, "commands_offset_s", prefix, "a finite number of seconds (the "
                         "capture time of the commands file's time 0)", required=False)
        if offset is not None and commands is None:
            raise SessionError(
                f"{MANIFEST}: {prefix}.commands_offset_s: the take has no 'commands' file to "
                "offset; add one or remove commands_offset_s"
            )
        if kind == "response":
            _require(tbl, "du", prefix, "the id of the DU a response take drives")
            _require(tbl, "commands", prefix, "the commands file of a response take")
        if du is not None and du not in du_ids:
            ids = ", ".join(str(d) for d in sorted(du_ids)) or "none"
            raise SessionError(
                f"{MANIFEST}: {prefix}.du: DU {du} is not in the manifest's [[dus]] (ids: {ids})"
            )
        takes.append(
            TakeInfo(
                name=name,
                kind=kind,
                file=_contained(root, file, f"{prefix}.file"),
                commands=None if commands is None else _contained(root, commands, f"{prefix}.commands"),
                du=du,
                trial=trial,
                plan=plan,
                commands_offset_s=0.0 if offset is None else offset + 0.0,
            )
        )
    return tuple(takes)


def _contained(root: Path, value: str, key: str) -> Path:
    """``root / value`` for a manifest path that is relative and stays inside the session folder
    once links are resolved (docs/format.md); otherwise a SessionError naming ``key``."""
    if "\0" in value:
        raise SessionError(f"{MANIFEST}: {key}: {_show(value)} holds a NUL character; expected a "
                           "path relative to the session folder")
    if Path(value).is_absolute() or PureWindowsPath(value).is_absolute() or value.startswith(("/", "\\")) \
            or PureWindowsPath(value).drive:
        raise SessionError(f"{MANIFEST}: {key}: {_show(value)} is an absolute path; expected a "
                           "path relative to the session folder")
    path = root / value
    try:
        resolved = path.resolve()
    except (OSError, RuntimeError) as exc:  # a link loop, a name too long
        raise SessionError(f"{MANIFEST}: {key}: {_show(value)} cannot be resolved ({exc})") from None
    if not resolved.is_relative_to(root):
        raise SessionError(f"{MANIFEST}: {key}: {_show(value)} leaves the session folder (it "
                           f"resolves to {resolved}); expected a path inside {root}")
    return path


def _inspect_takes(root: Path, takes: Sequence[TakeInfo], notes: list[str]) -> str:
    """Check every take/commands file exists and has the right header; return the dimension."""
    first: tuple[str, str, str] | None = None  # (dimension, take name, file label)
    for i, take in enumerate(takes):
        key = f"takes[{i}] ({take.name!r})"
        src = _Source(take.file, _relative_label(root, take.file))
        _check_file(src, f"{key}.file")
        columns, has_rows = _inspect_file(src)
        if "camera" in columns and "marker" in columns:
            raise SessionError(
                f"{src.label}: has both 'camera' and 'marker' columns; expected 2D detections "
                f"({', '.join(COLUMNS_2D)}) or labeled 3D markers ({', '.join(COLUMNS_3D)})"
            )
        if "marker" in columns:
            dimension, required, what = "3d", COLUMNS_3D, "labeled 3D markers"
        elif "camera" in columns:
            dimension, required, what = "2d", COLUMNS_2D, "2D detections"
        else:
            raise SessionError(
                f"{src.label}: columns {', '.join(columns)}; expected 2D detections "
                f"({', '.join(COLUMNS_2D)}) or labeled 3D markers ({', '.join(COLUMNS_3D)})"
            )
        _check_columns(src, columns, required, what, notes)
        if not has_rows:
            raise SessionError(
                f"{src.label}: no data rows (header only); expected one or more rows"
            )
        if first is None:
            first = (dimension, take.name, src.label)
        elif dimension != first[0]:
            raise SessionError(
                f"{src.label}: holds {what} ({dimension.upper()}) but take {first[1]!r} "
                f"({first[2]}) is {first[0].upper()}; all takes of a session must be one kind"
            )
        if take.commands is not None:
            csrc = _Source(take.commands, _relative_label(root, take.commands))
            _check_file(csrc, f"{key}.commands")
            ccols, _ = _inspect_file(csrc)
            _check_columns(csrc, ccols, COMMAND_COLUMNS, "commands", notes)
    assert first is not None  # _parse_takes guarantees at least one take
    return first[0]


def _check_2d_requirements(doc, cameras: Sequence[CameraInfo], takes: Sequence[TakeInfo]):
    if "cameras" not in doc:
        raise SessionError(
            f"{MANIFEST}: missing key 'cameras' (expected 2 or more [[cameras]] tables; the "
            "take files hold 2D detections)"
        )
    if len(cameras) < 2:
        raise SessionError(
            f"{MANIFEST}: cameras: expected 2 or more [[cameras]] for 2D detections, "
            f"got {len(cameras)}"
        )
    for kind, key, what in (
        ("wand", "wand", "marker_offsets_mm"),
        ("ground", "ground", "markers_mm"),
    ):
        if key not in doc:
            names = [t.name for t in takes if t.kind == kind]
            if names:
                raise SessionError(
                    f"{MANIFEST}: missing key {key!r} (expected a [{key}] table with {what}: "
                    f"the session has {kind} take {names[0]!r})"
                )


def _check_file(src: _Source, key: str) -> None:
    if src.path.suffix.lower() not in _EXTENSIONS:
        raise SessionError(
            f"{MANIFEST}: {key}: {_show(src.label)} has an unknown extension (expected .csv or "
            ".parquet)"
        )
    if not src.path.is_file():
        raise SessionError(f"{src.label}: file not found ({MANIFEST} {key})")
