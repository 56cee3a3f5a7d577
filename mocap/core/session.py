"""The session loader: a capture session directory (docs/format.md, ``mocap-session/1``) as objects.

A session directory holds ``session.toml`` (the manifest), an optional ``markers.csv`` (the
marker template) and one file per take. :func:`load_session` reads and validates the manifest,
checks that every take and commands file exists and reads only each take file's column header
(to tell 2D detections from labeled 3D markers). Take bodies are read on demand by
:meth:`Session.read_take` and :meth:`Session.read_commands`, which validate them fully.

Conventions, stated once here:

- Units: mm (3D positions, wand offsets, ground markers), px (2D detections, image sizes, focal
  lengths), s (``time_s``, ``frame / fps``), command units (integers 0..255).
- 2D take table: one row per detected blob, columns ``frame`` (int64, 0 at the take's first
  frame), ``camera`` (str, a manifest camera id), ``x``, ``y`` (float64 px, finite).
- 3D take table: one row per marker sample, columns ``frame`` (int64), ``marker`` (str),
  ``x``, ``y``, ``z`` (float64 mm, NaN when the marker was not seen).
- Commands table: one row per command change, ``time_s`` (float64 s, >= 0 in the file), ``du``
  (int64, a manifest DU id), ``command`` (int64, 0..255). Frame ``f`` is driven by the last row
  with ``time_s <= f / fps + 1e-9`` (:func:`command_matrix`).
- Command / capture alignment: a take's ``commands_offset_s = o`` (default 0) is the capture
  time of its command file's time 0, so a row acts at capture time ``o + time_s`` (command time =
  capture time - o; o < 0 when the log started before the cameras). :meth:`Session.read_commands`
  is the one place that applies it: every stage pairing frames with commands reads them there,
  in capture time. :meth:`Session.read_command_log` gives the file's own times.
- Every violation of the contract raises :class:`SessionError` whose message names the file,
  the row (CSV: 1-based line number, the header being line 1; Parquet: 1-based row) or the
  manifest key, and what was expected versus what was found.
- Unknown manifest keys and ignored extra columns are collected in ``Session.warnings`` and
  emitted once as :class:`SessionWarning`.
"""

from __future__ import annotations

import csv
import json
import math
import tomllib
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path, PureWindowsPath
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from mocap.core.display import Summarised, Summary

__all__ = [
    "SCHEMA",
    "TAKE_KINDS",
    "CameraInfo",
    "DUInfo",
    "GroundSpec",
    "Session",
    "SessionError",
    "SessionWarning",
    "TakeInfo",
    "WandSpec",
    "command_matrix",
    "load_session",
]

SCHEMA = "mocap-session/1"
MANIFEST = "session.toml"
MARKERS_FILE = "markers.csv"
TAKE_KINDS = ("wand", "points", "ground", "rest", "response", "motion")
COLUMNS_2D = ("frame", "camera", "x", "y")
COLUMNS_3D = ("frame", "marker", "x", "y", "z")
COMMAND_COLUMNS = ("time_s", "du", "command")
MARKER_COLUMNS = ("name", "x", "y", "z")
COMMAND_MIN = 0
COMMAND_MAX = 255
TIME_TOLERANCE_S = 1e-9
"""Frame ``f`` is driven by the last command row with ``time_s <= f / fps + TIME_TOLERANCE_S``."""

_TOP_KEYS = ("schema", "name", "fps", "cameras", "wand", "ground", "dus", "takes")
_CAMERA_KEYS = ("id", "width", "height", "focal_px", "principal_px", "distortion", "intrinsics")
INTRINSICS_MODES = ("fixed", "refine")
_WAND_KEYS = ("marker_offsets_mm",)
_GROUND_KEYS = ("markers_mm",)
_DU_KEYS = ("id", "name", "feedback")
_TAKE_KEYS = ("name", "kind", "file", "commands", "commands_offset_s", "du", "trial", "plan")
_EXTENSIONS = (".csv", ".parquet")
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


class SessionError(Exception):
    """A session violates the input contract (docs/format.md).

    The message names the file, the row or manifest key, and what was expected versus found.
    """


class SessionWarning(UserWarning):
    """Something in a session was ignored (an unknown manifest key, an extra column)."""


# --------------------------------------------------------------------------------------------
# Data types


@dataclass(frozen=True)
class CameraInfo:
    """A camera as the manifest declares it.

    Attributes
    ----------
    id : unique camera id, as used in the take files' ``camera`` column.
    width, height : image size, px (positive integers).
    focal_px : nominal focal length from the lens spec, px (a starting guess within ~10 %),
        or None when the manifest gives none; with ``principal_px`` or ``distortion`` it is part
        of the prior intrinsics.
    principal_px : (2,) prior principal point, px (top-left pixel's centre origin), or None.
    distortion : (5,) prior Brown-Conrady ``k1 k2 p1 p2 k3`` (OpenCV's), or None.
    intrinsics : "fixed" (priors used as given) or "refine" (the wand adjusts them; the default
        when a prior is given); None when the camera has no prior intrinsics.
    """

    id: str
    width: int
    height: int
    focal_px: float | None
    principal_px: tuple[float, float] | None = None
    distortion: tuple[float, float, float, float, float] | None = None
    intrinsics: str | None = None

    @property
    def has_prior(self) -> bool:
        """True when the manifest gives prior intrinsics (a principal point or distortion)."""
        return self.principal_px is not None or self.distortion is not None


@dataclass(frozen=True, eq=False)
class WandSpec:
    """The calibration wand: collinear markers at known distances along it.

    Attributes
    ----------
    marker_offsets_mm : (n_markers,) read-only float array, mm from one end, strictly
        increasing as given, n_markers >= 2; with 3 or more, all gaps between neighbours
        distinct (they tell the ends apart). Two markers: a T-wand or easyWand/Argus rod, whose
        ends look alike (the calibration tells them apart by geometry).
    """

    marker_offsets_mm: np.ndarray


@dataclass(frozen=True, eq=False)
class GroundSpec:
    """The ground square that defines the world frame.

    Attributes
    ----------
    markers_mm : (n_markers, 3) read-only float array, world coordinates of the marker
        centres, mm; n_markers >= 3, not collinear.
    """

    markers_mm: np.ndarray


@dataclass(frozen=True)
class DUInfo:
    """A deformation unit (actuator).

    Attributes
    ----------
    id : the DU's integer id, as used in command files' ``du`` column.
    name : free text (``"DU<id>"`` when the manifest gives none).
    feedback : closed loop (potentiometer) when True; False when open loop or not given.
    """

    id: int
    name: str
    feedback: bool


@dataclass(frozen=True)
class TakeInfo:
    """A take as the manifest declares it (its data is read by :meth:`Session.read_take`).

    Attributes
    ----------
    name : unique take name.
    kind : one of ``wand``, ``points``, ``ground``, ``rest``, ``response``, ``motion``.
    file : path of the take file (resolved against the session directory).
    commands : path of the commands file, or None.
    du : the driven DU's id (required for ``response`` takes), or None.
    trial : trial number (from 1), or None.
    plan : free label of the motion plan, or None.
    commands_offset_s : capture time (s from the take's first frame) of the commands file's
        time 0: a row acts at capture time ``commands_offset_s + time_s``. 0 when the command log
        and the cameras started together (the default).
    """

    name: str
    kind: str
    file: Path
    commands: Path | None
    du: int | None
    trial: int | None
    plan: str | None
    commands_offset_s: float = 0.0


@dataclass(frozen=True, eq=False, repr=False)
class Session(Summarised):
    """A loaded, manifest-validated capture session; take data is read lazily.

    Attributes
    ----------
    root : the session directory (absolute).
    name : the manifest's free-text name (the directory name when absent).
    fps : capture rate of every take, frames per second (> 0).
    cameras : the manifest's cameras, in manifest order (empty for a 3D session without any).
    wand, ground : the calibration objects, or None when the manifest has none.
    dus : the manifest's deformation units, in manifest order.
    takes : the manifest's takes, in manifest order.
    marker_template : ``markers.csv`` as a DataFrame (``name`` str; ``x``, ``y``, ``z``
        float64 mm), or None when the session has none.
    dimension : ``"2d"`` (blob detections) or ``"3d"`` (labeled markers), same for all takes.
    warnings : messages about ignored content (unknown keys, extra columns).
    """

    root: Path
    name: str
    fps: float
    cameras: tuple[CameraInfo, ...]
    wand: WandSpec | None
    ground: GroundSpec | None
    dus: tuple[DUInfo, ...]
    takes: tuple[TakeInfo, ...]
    marker_template: pd.DataFrame | None
    dimension: str
    warnings: tuple[str, ...] = ()
    _n_frames: dict[str, int] = field(default_factory=dict, init=False, repr=False)
    _commands: dict[str, pd.DataFrame] = field(default_factory=dict, init=False, repr=False)

    def __getstate__(self) -> dict:
        # pickled to every worker with every take: the commands read so far stay here
        return {**self.__dict__, "_commands": {}}

    def _summary(self) -> Summary:
        from mocap.core.display import counts

        dus = ", ".join(f"{d.id}" + (f" {d.name}" if d.name else "") for d in self.dus[:8])
        lines = [("folder", str(self.root)),
                 ("data", f"{'2D blobs' if self.dimension == '2d' else '3D labeled markers'}, "
                          f"{self.fps:g} fps"),
                 ("takes", counts((t.kind for t in self.takes), "takes")),
                 ("DUs", f"{len(self.dus)}" + (f": {dus}" if dus else "")
                  + (" ..." if len(self.dus) > 8 else ""))]
        if self.cameras:
            lines.append(("cameras", f"{len(self.cameras)}: "
                                     + ", ".join(c.id for c in self.cameras[:12])
                                     + (" ..." if len(self.cameras) > 12 else "")))
        if self.marker_template is not None:
            lines.append(("markers", f"{len(self.marker_template)} in markers.csv"))
        if self.warnings:
            lines.append(("warnings", f"{len(self.warnings)} (.warnings)"))
        return Summary(f"Session {self.name!r}", tuple(lines),
                       more="attributes: .takes .dus .cameras .wand .ground .marker_template; "
                            ".read_take(name) .read_commands(name)")

    @property
    def camera_ids(self) -> tuple[str, ...]:
        """The camera ids, in manifest order."""
        return tuple(c.id for c in self.cameras)

    @property
    def du_ids(self) -> tuple[int, ...]:
        """The DU ids, in manifest order (the column order for :func:`command_matrix`)."""
        return tuple(d.id for d in self.dus)

    def take(self, name: str) -> TakeInfo:
        """The take called ``name``; SessionError when the manifest has none."""
        for t in self.takes:
            if t.name == name:
                return t
        names = ", ".join(t.name for t in self.takes)
        raise SessionError(f"{MANIFEST}: no take named {name!r} (takes: {names})")

    def takes_of_kind(self, kind: str) -> list[TakeInfo]:
        """The takes of ``kind`` (one of :data:`TAKE_KINDS`), in manifest order."""
        if kind not in TAKE_KINDS:
            raise ValueError(f"kind: expected one of {', '.join(TAKE_KINDS)}, got {kind!r}")
        return [t for t in self.takes if t.kind == kind]

    def read_take(self, name: str) -> pd.DataFrame:
        """Read and validate a take's data.

        Returns
        -------
        DataFrame in file order. 2D: ``frame`` int64, ``camera`` categorical (categories: the
        manifest's camera ids, in its order), ``x``, ``y`` float64 px (finite). 3D: ``frame``
        int64, ``marker`` str, ``x``, ``y``, ``z`` float64 mm (NaN when the marker was not
        seen).

        Raises
        ------
        SessionError
            On any contract violation, naming the file and the offending row.
        """
        take = self.take(name)
        src = _Source(take.file, self._label(take.file))
        if self.dimension == "2d":
            df = _read_take_2d(src, self.camera_ids)
        else:
            df = _read_take_3d(src)
        self._n_frames[name] = int(df["frame"].max()) + 1
        return df

    def read_commands(self, name: str) -> pd.DataFrame:
        """A take's commands in capture time: the one reader every stage pairing a take's
        frames with its commands goes through.

        Each row's ``time_s`` is the capture time it acts at (s from the take's first frame):
        the file's ``time_s`` plus the take's ``commands_offset_s`` (command time = capture
        time - offset). With no offset it is the file as written.

        Returns
        -------
        DataFrame in file order: ``time_s`` float64 s (capture time; negative for rows logged
        before the take's first frame, which then drive it from its first frame), ``du`` int64
        (a manifest DU id), ``command`` int64 (0..255). May have zero rows (every DU then holds
        0).

        Raises
        ------
        SessionError
            When the take has no commands file, or on any contract violation in it.

        A file is read and checked once per Session (a run validates every commands file, then
        its trials and its recording read them again); each call returns a fresh copy.
        """
        rows = self.read_command_log(name)
        offset = self.take(name).commands_offset_s
        if offset:  # to the nanosecond: 0.3 - 0.25 reads as 0.05, as the file's 0.05 would
            rows["time_s"] = np.round(rows["time_s"].to_numpy(float) + offset, 9)
        return rows

    def read_command_log(self, name: str) -> pd.DataFrame:
        """A take's commands file as written (its own clock: ``time_s`` >= 0), validated; no
        offset applied. Only for estimating or checking an offset: pairing commands with
        frames goes through :meth:`read_commands`."""
        cached = self._commands.get(name)
        if cached is None:
            take = self.take(name)
            if take.commands is None:
                raise SessionError(
                    f"{MANIFEST}: take {name!r} has no 'commands' file (kind {take.kind!r})"
                )
            src = _Source(take.commands, self._label(take.commands))
            cached = self._commands[name] = _read_commands(src, self.du_ids)
        return cached.copy()

    def n_frames(self, name: str) -> int:
        """Number of frames of a take: its largest ``frame`` + 1 (reads the take once)."""
        if name not in self._n_frames:
            self.read_take(name)
        return self._n_frames[name]

    def _label(self, path: Path) -> str:
        return _relative_label(self.root, path)


# --------------------------------------------------------------------------------------------
# Loading


def load_session(path: str | Path) -> Session:
    """Load a session directory: validate the manifest and every take's header.

    Take bodies are not read (see :meth:`Session.read_take`); ``markers.csv``, being small, is
    read and validated here.

    Parameters
    ----------
    path : the session directory (holding ``session.toml``).

    Returns
    -------
    Session

    Raises
    ------
    SessionError
        When the manifest or a take header violates the contract (docs/format.md).
    """
    root = Path(path).resolve()
    if not root.is_dir():
        raise SessionError(f"{path}: not a directory (expected a session folder with {MANIFEST})")
    manifest_path = root / MANIFEST
    if not manifest_path.is_file():
        raise SessionError(
            f'{MANIFEST}: missing in {root} (expected the session manifest, schema = "{SCHEMA}")'
        )
    try:
        doc = tomllib.loads(manifest_path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise SessionError(f"{MANIFEST}: not valid TOML ({exc})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SessionError(f"{MANIFEST}: cannot be read ({exc})") from None

    notes: list[str] = []
    _note_unknown(doc, _TOP_KEYS, "", notes)

    if "schema" not in doc:
        raise SessionError(f"{MANIFEST}: missing key 'schema' (expected \"{SCHEMA}\")")
    if doc["schema"] != SCHEMA:
        raise SessionError(f'{MANIFEST}: schema: expected "{SCHEMA}", got {_show(doc["schema"])}')
    name = doc.get("name", root.name)
    if not isinstance(name, str):
        raise SessionError(f"{MANIFEST}: name: expected a string, got {_show(name)}")
    fps = _number(doc, "fps", "", "a positive number, frames per second", positive=True)

    cameras = _parse_cameras(doc, notes)
    wand = _parse_wand(doc["wand"], notes) if "wand" in doc else None
    ground = _parse_ground(doc["ground"], notes) if "ground" in doc else None
    dus = _parse_dus(doc, notes)
    takes = _parse_takes(doc, root, {d.id for d in dus}, notes)

    dimension = _inspect_takes(root, takes, notes)
    if dimension == "2d":
        _check_2d_requirements(doc, cameras, takes)

    markers = None
    if (root / MARKERS_FILE).exists():
        _contained(root, MARKERS_FILE, MARKERS_FILE)
        markers = _read_markers(_Source(root / MARKERS_FILE, MARKERS_FILE), notes)

    for note in notes:
        warnings.warn(note, SessionWarning, stacklevel=2)
    return Session(
        root=root,
        name=name,
        fps=fps,
        cameras=cameras,
        wand=wand,
        ground=ground,
        dus=dus,
        takes=takes,
        marker_template=markers,
        dimension=dimension,
        warnings=tuple(notes),
    )


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


# --------------------------------------------------------------------------------------------
# Files


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


def _check_file(src: _Source, key: str) -> None:
    if src.path.suffix.lower() not in _EXTENSIONS:
        raise SessionError(
            f"{MANIFEST}: {key}: {_show(src.label)} has an unknown extension (expected .csv or "
            ".parquet)"
        )
    if not src.path.is_file():
        raise SessionError(f"{src.label}: file not found ({MANIFEST} {key})")


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


# --------------------------------------------------------------------------------------------
# Commands to frames


def command_matrix(
    commands: pd.DataFrame, fps: float, n_frames: int, dus: Sequence[int]
) -> np.ndarray:
    """The command of each DU at each frame of a take.

    Frame ``f`` (time ``f / fps``) is driven by the last row of its DU with
    ``time_s <= f / fps + 1e-9`` (rows with equal ``time_s``: the later one in the table wins);
    a DU with no such row holds 0. Rows for DUs not in ``dus`` and rows after the last frame
    are ignored.

    Parameters
    ----------
    commands : DataFrame with ``time_s`` (s), ``du`` and ``command`` columns, as returned by
        :meth:`Session.read_commands` (any row order).
    fps : capture rate, frames per second (> 0).
    n_frames : number of frames of the take (>= 0).
    dus : DU ids, one output column each, in this order.

    Returns
    -------
    (n_frames, len(dus)) int64 array of command values.
    """
    fps = float(fps)
    if not math.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps: expected a positive number, got {fps!r}")
    if int(n_frames) != n_frames or n_frames < 0:
        raise ValueError(f"n_frames: expected an integer >= 0, got {n_frames!r}")
    missing = [c for c in COMMAND_COLUMNS if c not in commands.columns]
    if missing:
        raise ValueError(f"commands: expected columns {COMMAND_COLUMNS}, missing {missing}")
    from mocap.core.schedules import sample_commands

    times = np.arange(int(n_frames)) / fps
    return sample_commands(commands, list(dus), times).astype(np.int64)
