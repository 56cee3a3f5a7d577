"""Tiny valid sessions (FORMAT.md) for tests, with hooks to break exactly one thing.

Build a :class:`SessionSpec` with :func:`session_2d` or :func:`session_3d`, change one thing
(``spec.manifest`` is a plain dict in TOML shape; ``spec.files`` maps a path relative to the
session folder to its table), write it with :meth:`SessionSpec.write`, and for damage no table
can express (a truncated line, a corrupt value) edit the written text with :func:`replace_line`
or :func:`append_text`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

FPS = 100.0
CAMERAS = ("cam1", "cam2")
MARKERS = ("M001", "M002", "M003")
N_FRAMES = 5


# --------------------------------------------------------------------------------------------
# A minimal TOML writer (the standard library reads TOML but does not write it)


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(f"cannot write {value!r} as TOML")


def _is_table_array(value) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(v, dict) for v in value)


def toml_dumps(doc: dict) -> str:
    """``doc`` as TOML: scalars first, then ``[table]`` and ``[[array of tables]]`` sections."""
    lines = [
        f"{k} = {_toml_value(v)}"
        for k, v in doc.items()
        if not isinstance(v, dict) and not _is_table_array(v)
    ]
    for key, value in doc.items():
        if isinstance(value, dict):
            lines += ["", f"[{key}]"] + [f"{k} = {_toml_value(v)}" for k, v in value.items()]
        elif _is_table_array(value):
            for table in value:
                lines += ["", f"[[{key}]]"]
                lines += [f"{k} = {_toml_value(v)}" for k, v in table.items()]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------
# Tables


def blobs_2d(n_frames: int = N_FRAMES, seed: int = 0) -> pd.DataFrame:
    """2D detections: three blobs per camera per frame, px."""
    rng = np.random.default_rng(seed)
    frame, camera = np.meshgrid(
        np.arange(n_frames), np.repeat(CAMERAS, len(MARKERS)), indexing="ij"
    )
    n = frame.size
    return pd.DataFrame(
        {
            "frame": frame.ravel().astype(np.int64),
            "camera": camera.ravel().astype(str),
            "x": rng.uniform(100.0, 1100.0, n).round(3),
            "y": rng.uniform(100.0, 900.0, n).round(3),
        }
    )


def markers_3d(n_frames: int = N_FRAMES, seed: int = 0) -> pd.DataFrame:
    """Labeled 3D markers, mm, with gaps (NaN) at frame 1 for M002 and frame 3 for M003."""
    rng = np.random.default_rng(seed)
    frame, marker = np.meshgrid(np.arange(n_frames), MARKERS, indexing="ij")
    df = pd.DataFrame(
        {
            "frame": frame.ravel().astype(np.int64),
            "marker": marker.ravel().astype(str),
            "x": rng.uniform(-50.0, 50.0, frame.size).round(3),
            "y": rng.uniform(-50.0, 50.0, frame.size).round(3),
            "z": rng.uniform(0.0, 30.0, frame.size).round(3),
        }
    )
    gap = ((df["frame"] == 1) & (df["marker"] == "M002")) | (
        (df["frame"] == 3) & (df["marker"] == "M003")
    )
    df.loc[gap, ["x", "y", "z"]] = np.nan
    return df


def commands_response(du: int = 4) -> pd.DataFrame:
    """A short trapezoid on one DU: 0 at 0 s, 13 at 0.02 s, 26 at 0.03 s."""
    return pd.DataFrame({"time_s": [0.0, 0.02, 0.03], "du": [du] * 3, "command": [0, 13, 26]})


def commands_motion() -> pd.DataFrame:
    """Two DUs driven together."""
    return pd.DataFrame(
        {
            "time_s": [0.0, 0.01, 0.01, 0.04],
            "du": [1, 1, 4, 4],
            "command": [0, 100, 50, 0],
        }
    )


def marker_template() -> pd.DataFrame:
    return pd.DataFrame(
        {
            "name": list(MARKERS),
            "x": [0.0, 20.0, -20.0],
            "y": [0.0, 5.0, 5.0],
            "z": [10.0, 8.0, 8.0],
        }
    )


# --------------------------------------------------------------------------------------------
# Sessions


@dataclass
class SessionSpec:
    """A session before it is written: the manifest dict, the data tables, the template."""

    manifest: dict
    files: dict[str, pd.DataFrame]
    markers: pd.DataFrame | None = None
    extra_text: dict[str, str] = field(default_factory=dict)

    def take(self, name: str) -> dict:
        """The manifest table of take ``name`` (edit it in place to break the take)."""
        return next(t for t in self.manifest["takes"] if t["name"] == name)

    def take_file(self, name: str) -> str:
        return self.take(name)["file"]

    def table(self, take_name: str) -> pd.DataFrame:
        """The data table of take ``take_name`` (edit it in place)."""
        return self.files[self.take_file(take_name)]

    def write(self, root: Path) -> Path:
        """Write the session into ``root`` (created); return ``root``."""
        root = Path(root)
        (root / "takes").mkdir(parents=True, exist_ok=True)
        (root / "session.toml").write_text(toml_dumps(self.manifest), encoding="utf-8")
        for rel, df in self.files.items():
            path = root / rel
            path.parent.mkdir(parents=True, exist_ok=True)
            if rel.endswith(".parquet"):
                df.to_parquet(path, index=False)
            else:
                df.to_csv(path, index=False)
        for rel, text in self.extra_text.items():
            (root / rel).write_text(text, encoding="utf-8")
        if self.markers is not None:
            self.markers.to_csv(root / "markers.csv", index=False)
        return root


def _ext(fmt: str, i: int) -> str:
    if fmt == "mixed":
        return ".csv" if i % 2 == 0 else ".parquet"
    return {"csv": ".csv", "parquet": ".parquet"}[fmt]


def _dus() -> list[dict]:
    return [
        {"id": 1, "name": "upper eyelid lowering", "feedback": True},
        {"id": 4, "name": "lip corner raiser", "feedback": False},
    ]


def session_2d(fmt: str = "csv") -> SessionSpec:
    """A valid 2D session: 2 cameras, wand, ground, rest, one response and one motion take.

    ``fmt`` is ``"csv"``, ``"parquet"`` or ``"mixed"`` (take files alternate); command files
    are CSV.
    """
    kinds = [
        ("wand", "wand"),
        ("ground", "ground"),
        ("rest", "rest"),
        ("du04_t01", "response"),
        ("smile_A", "motion"),
    ]
    takes, files = [], {}
    for i, (name, kind) in enumerate(kinds):
        file = f"takes/{name}{_ext(fmt, i)}"
        take = {"name": name, "kind": kind, "file": file}
        files[file] = blobs_2d(seed=i)
        if kind == "response":
            take.update(commands=f"takes/{name}_commands.csv", du=4, trial=1)
            files[take["commands"]] = commands_response(4)
        elif kind == "motion":
            take.update(commands=f"takes/{name}_commands.csv", plan="A")
            files[take["commands"]] = commands_motion()
        takes.append(take)
    manifest = {
        "schema": "mocap-session/1",
        "name": "tiny-2d",
        "fps": FPS,
        "cameras": [
            {"id": "cam1", "width": 1280, "height": 1024, "focal_px": 1200.0},
            {"id": "cam2", "width": 1280, "height": 1024},
        ],
        "wand": {"marker_offsets_mm": [0.0, 45.0, 125.0]},
        "ground": {"markers_mm": [[0.0, 0.0, 0.0], [120.0, 0.0, 0.0], [0.0, 0.0, 80.0]]},
        "dus": _dus(),
        "takes": takes,
    }
    return SessionSpec(manifest=manifest, files=files, markers=marker_template())


def session_3d(fmt: str = "csv") -> SessionSpec:
    """A valid 3D (labeled markers) session: no cameras, wand or ground; rest, response,
    motion takes, with NaN gaps; a marker template."""
    kinds = [("rest", "rest"), ("du04_t01", "response"), ("smile_A", "motion")]
    takes, files = [], {}
    for i, (name, kind) in enumerate(kinds):
        file = f"takes/{name}{_ext(fmt, i)}"
        take = {"name": name, "kind": kind, "file": file}
        files[file] = markers_3d(seed=i)
        if kind == "response":
            take.update(commands=f"takes/{name}_commands.csv", du=4, trial=1)
            files[take["commands"]] = commands_response(4)
        elif kind == "motion":
            take.update(commands=f"takes/{name}_commands.csv", plan="A")
            files[take["commands"]] = commands_motion()
        takes.append(take)
    manifest = {
        "schema": "mocap-session/1",
        "name": "tiny-3d",
        "fps": FPS,
        "dus": _dus(),
        "takes": takes,
    }
    return SessionSpec(manifest=manifest, files=files, markers=marker_template())


# --------------------------------------------------------------------------------------------
# Damage to written text


def replace_line(path: Path, line_number: int, text: str) -> None:
    """Replace 1-based line ``line_number`` of a text file with ``text``."""
    lines = Path(path).read_text(encoding="utf-8").splitlines()
    lines[line_number - 1] = text
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


def append_text(path: Path, text: str) -> None:
    """Append ``text`` verbatim (no newline added) to a file."""
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(text)
