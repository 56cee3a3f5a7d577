"""``calibration.toml`` (OUTPUTS.md) read and write.

One ``[[cameras]]`` table per camera (``id``, ``width``, ``height``, ``K``, ``dist``, ``R``,
``t``) and an optional ``[quality]`` table of scalars, lists and per-camera sub-tables. Floats
are written with ``repr`` so a write-read round trip is exact.
"""

from __future__ import annotations

import math
import os
import tomllib
from pathlib import Path
from typing import Any

from mocap.calib.camera import Camera, CameraRig
from mocap.atomic import write_text


class CalibrationFileError(ValueError):
    """A calibration file that does not follow OUTPUTS.md; the message names file and key."""


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(int(v))
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(float(v))  # float() drops numpy's "np.float64(...)" repr
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if hasattr(v, "tolist"):
        return _value(v.tolist())
    raise TypeError(f"cannot write {type(v).__name__} to TOML: {v!r}")


def _table(prefix: str, d: dict) -> list[str]:
    lines = [f"[{prefix}]"] if prefix else []
    subtables = []
    for k, v in d.items():
        if isinstance(v, dict):
            subtables.append((k, v))
        else:
            lines.append(f"{k} = {_value(v)}")
    for k, v in subtables:
        lines.append("")
        lines.extend(_table(f"{prefix}.{k}" if prefix else k, v))
    return lines


def dumps(rig: CameraRig, quality: dict | None = None, header: dict | None = None) -> str:
    """The text of a calibration.toml for ``rig`` (and optional ``quality``/``header`` keys)."""
    lines = ["# facemocap calibration: OpenCV conventions, x_cam = R @ X_world + t, mm and px"]
    for k, v in (header or {}).items():
        lines.append(f"{k} = {_value(v)}")
    for cam in rig:
        lines.append("")
        lines.append("[[cameras]]")
        for k, v in cam.to_dict().items():
            lines.append(f"{k} = {_value(v)}")
    if quality:
        lines.append("")
        lines.extend(_table("quality", quality))
    return "\n".join(lines) + "\n"


def write_calibration(
    path: str | os.PathLike, rig: CameraRig, quality: dict | None = None, header: dict | None = None
) -> Path:
    """Write ``rig`` (and ``quality``) to ``path`` atomically."""
    return write_text(path, dumps(rig, quality, header))


def read_toml(path: Path) -> dict:
    """A TOML file's tables; a missing file or bad TOML is a CalibrationFileError naming it."""
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise CalibrationFileError(f"{path}: file not found") from None
    except tomllib.TOMLDecodeError as e:
        raise CalibrationFileError(f"{path}: not valid TOML ({e})") from None


def read_calibration(path: str | os.PathLike) -> tuple[CameraRig, dict]:
    """Read a calibration.toml: ``(rig, quality)``; errors name the file and the camera/key."""
    path = Path(path)
    data = read_toml(path)
    tables = data.get("cameras")
    if not isinstance(tables, list) or not tables:
        raise CalibrationFileError(f"{path}: expected one or more [[cameras]] tables, got none")
    cams = []
    for i, t in enumerate(tables):
        missing = [k for k in ("id", "width", "height", "K", "R", "t") if k not in t]
        if missing:
            raise CalibrationFileError(f"{path}: [[cameras]] #{i + 1}: missing keys {missing}")
        try:
            cams.append(Camera.from_dict(t))
        except (ValueError, TypeError) as e:
            raise CalibrationFileError(f"{path}: [[cameras]] #{i + 1} ({t.get('id')}): {e}") from None
    try:
        rig = CameraRig(tuple(cams))
    except ValueError as e:
        raise CalibrationFileError(f"{path}: {e}") from None
    return rig, dict(data.get("quality", {}))
