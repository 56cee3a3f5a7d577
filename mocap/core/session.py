"""The session loader: a capture session directory (docs/format.md, ``mocap-session/1``) as objects.

A session directory holds ``session.toml`` (the manifest), an optional ``markers.csv`` (the
marker template) and one file per take. :func:`load_session` reads and validates the manifest,
checks that every take and commands file exists and reads only each take file's column header
(to tell 2D detections from labeled 3D markers). Take bodies are read on demand by
:meth:`Session.read_take` and :meth:`Session.read_commands`, which validate them fully. The
manifest checks live in :mod:`mocap.core.manifest`, the file readers in
:mod:`mocap.core.session_files`.

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

import math
import tomllib
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

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
        from mocap.core.session_files import _read_take_2d, _read_take_3d, _Source

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
            from mocap.core.session_files import _read_commands, _Source

            src = _Source(take.commands, self._label(take.commands))
            cached = self._commands[name] = _read_commands(src, self.du_ids)
        return cached.copy()

    def n_frames(self, name: str) -> int:
        """Number of frames of a take: its largest ``frame`` + 1 (reads the take once)."""
        if name not in self._n_frames:
            self.read_take(name)
        return self._n_frames[name]

    def _label(self, path: Path) -> str:
        from mocap.core.session_files import _relative_label

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
    # imported here, not at the top: the manifest checks and file readers import this module
    from mocap.core.manifest import (
        _TOP_KEYS,
        _check_2d_requirements,
        _contained,
        _inspect_takes,
        _note_unknown,
        _number,
        _parse_cameras,
        _parse_dus,
        _parse_ground,
        _parse_takes,
        _parse_wand,
        _show,
    )
    from mocap.core.session_files import _read_markers, _Source

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
