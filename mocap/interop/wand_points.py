"""Other labs' wand recordings to a docs/format.md session of unlabeled 2D blobs.

Two layouts are read:

- **per-blob tables** (one row per detected blob), such as pyOpenLPT's wand-point CSV: columns
  ``Frame, Camera, X, Y`` (case-insensitive; ``Radius`` and ``Status`` optional). When a
  ``Status`` column is present only its ``Raw`` rows are taken: every blob the detector found,
  reflections and split blobs included (the ``Filtered_*`` rows are the recording tool's own
  choice of wand blobs, which the calibration must make by itself). X and Y are pixels with the
  origin at the top-left pixel's centre, as docs/format.md's.
- **DLTdv / easyWand / Argus point files** (``*xypts.csv``): one row per frame, columns
  ``pt<k>_cam<c>_X, pt<k>_cam<c>_Y`` for wand end ``k`` (1, 2) and camera ``c``, NaN where the
  point was not digitised. Their pixel origin is the bottom-left, 1-based as MATLAB's (DLTdv):
  ``x = X - 1``, ``y = height - Y`` (so the image height of every camera is needed). The two
  ends are written as two unlabeled blobs: which end is which is the calibration's business.
- **background points** (DLTdv / easyWand ``*xypts.csv`` of static points): the same columns;
  every (row, point) digitised in a camera is one distinct static point, written as one frame
  of a ``points`` take (frame ``row * n_points + k - 1``).
- **camera profiles**: an Argus / easyWand profile (``.txt``, one row per camera,
  ``camera focal_px width height cx cy aspect_ratio k1 k2 t1 t2 k3``), an aniposelib
  ``calibration.toml`` or an OpenCV YAML (:mod:`mocap.calib.priors` reads them all). The
  focal length, principal point and distortion become the session's prior intrinsics
  (``focal_px``, ``principal_px``, ``distortion``, ``intrinsics = "refine"`` unless asked
  ``"fixed"``); a profile of 6 columns (no distortion) gives the focal length only, as a
  starting guess.

The session written holds ``session.toml`` (cameras, ``[wand]``, no ``[ground]``: the world frame
is then the first camera's) and ``takes/wand.csv``. Nothing is overwritten.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from mocap.core.atomic import write_csv, write_text
from mocap.interop.marker_data import ImportError_

XYPTS = re.compile(r"^pt(\d+)_cam(\d+)_([XY])$", re.IGNORECASE)


@dataclass(frozen=True)
class CameraProfile:
    """One camera of a profile file (px): image size, focal length and, when the profile gives
    them, the prior principal point (top-left origin) and distortion ``k1 k2 p1 p2 k3`` with
    how the calibration uses them (``intrinsics``: "fixed" or "refine")."""

    id: str
    width: int
    height: int
    focal_px: float | None = None
    principal_px: tuple[float, float] | None = None
    distortion: tuple[float, ...] | None = None
    intrinsics: str | None = None


def is_blob_table(path: str | os.PathLike) -> bool:
    """True when the file's header names frame, camera, x and y columns."""
    head = _header(path)
    return {"frame", "camera", "x", "y"} <= {h.lower() for h in head}


def is_xypts(path: str | os.PathLike) -> bool:
    """True when the file's header is DLTdv's ``pt1_cam1_X, ...``."""
    head = _header(path)
    return bool(head) and all(XYPTS.match(h) for h in head)


def _header(path) -> list[str]:
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            line = fh.readline()
    except OSError:
        return []
    return [h.strip().strip('"') for h in line.strip().split(",")]


def read_blob_table(path: str | os.PathLike) -> pd.DataFrame:
    """A per-blob table's detections: frame, camera (``cam<id>``), x, y [, radius_px].

    Raises ImportError_ naming the file and what is missing.
    """
    path = Path(path)
    df = pd.read_csv(path)
    cols = {c.lower(): c for c in df.columns}
    missing = [c for c in ("frame", "camera", "x", "y") if c not in cols]
    if missing:
        raise ImportError_(f"{path}: expected columns Frame, Camera, X, Y; missing {missing}")
    if "status" in cols:
        status = df[cols["status"]].astype(str)
        if (status == "Raw").any():
            df = df[status == "Raw"]
    out = pd.DataFrame({
        "frame": pd.to_numeric(df[cols["frame"]], errors="coerce"),
        "camera": [_camera_id(v) for v in df[cols["camera"]]],
        "x": pd.to_numeric(df[cols["x"]], errors="coerce"),
        "y": pd.to_numeric(df[cols["y"]], errors="coerce"),
    })
    if "radius" in cols:
        out["radius_px"] = pd.to_numeric(df[cols["radius"]], errors="coerce").to_numpy()
    bad = ~np.isfinite(out[["frame", "x", "y"]].to_numpy(float)).all(axis=1)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise ImportError_(f"{path}: data row {row + 1}: frame, x and y must be numbers")
    out["frame"] = out["frame"].astype(np.int64)
    if (out["frame"] < 0).any():
        raise ImportError_(f"{path}: frames must be 0 or more")
    return out.sort_values(["frame", "camera"], kind="stable").reset_index(drop=True)


def _camera_id(v) -> str:
    s = str(v).strip()
    return f"cam{s}" if re.fullmatch(r"\d+", s) else s


def read_xypts(path: str | os.PathLike, heights: dict[str, int]) -> pd.DataFrame:
    """A DLTdv/easyWand ``xypts.csv``: every digitised point as a blob (frame, camera, x, y),
    converted to docs/format.md's top-left origin; ``heights`` gives each camera's (``cam<c>``)
    image height, px."""
    path = Path(path)
    df = pd.read_csv(path)
    rows = []
    cams = set()
    for col in df.columns:
        m = XYPTS.match(str(col).strip())
        if not m:
            raise ImportError_(f"{path}: column {col!r}: expected pt<k>_cam<c>_X or _Y")
        cams.add(int(m.group(2)))
    for c in sorted(cams):
        cid = f"cam{c}"
        if cid not in heights:
            raise ImportError_(f"{path}: camera {c}: its image height is needed to move the "
                               "bottom-left origin to the top-left (give --image-size or a profile)")
        pts = sorted({int(XYPTS.match(str(k).strip()).group(1)) for k in df.columns
                      if int(XYPTS.match(str(k).strip()).group(2)) == c})
        for k in pts:
            X = pd.to_numeric(df[f"pt{k}_cam{c}_X"], errors="coerce").to_numpy(float)
            Y = pd.to_numeric(df[f"pt{k}_cam{c}_Y"], errors="coerce").to_numpy(float)
            ok = np.isfinite(X) & np.isfinite(Y)
            frames = np.flatnonzero(ok)
            rows.append(pd.DataFrame({"frame": frames, "camera": cid, "x": X[ok] - 1.0,
                                      "y": heights[cid] - Y[ok]}))
    if not rows:
        raise ImportError_(f"{path}: no digitised points")
    out = pd.concat(rows, ignore_index=True)
    return out.sort_values(["frame", "camera"], kind="stable").reset_index(drop=True)


def read_camera_profile(path: str | os.PathLike, *, intrinsics: str = "refine"
                        ) -> list[CameraProfile]:
    """Cameras of a profile file (see the module docstring): an Argus / easyWand ``.txt``, an
    aniposelib ``calibration.toml`` or an OpenCV ``.yml``/``.yaml``/``.xml``.

    Raises ImportError_ naming the file and the row or key."""
    from mocap.calib.priors import PriorFileError, read_priors

    path = Path(path)
    try:
        priors = read_priors(path, mode=intrinsics)
    except PriorFileError as e:
        raise ImportError_(str(e)) from None
    out = []
    for cid, p in priors.items():
        if p.size is None:
            raise ImportError_(f"{path}: camera {cid!r} has no image size (image_width and "
                               "image_height); give --image-size instead")
        w, h = p.size
        if not p.distortion_given:  # focal length and principal point only: a starting guess
            out.append(CameraProfile(cid, w, h, p.focal_px))
        else:
            out.append(CameraProfile(cid, w, h, p.focal_px, p.principal_px, p.distortion,
                                     intrinsics))
    return out


def read_points_xypts(path: str | os.PathLike, heights: dict[str, int]) -> pd.DataFrame:
    """A DLTdv / easyWand background-point ``xypts.csv`` as a ``points`` take: frame (one per
    distinct point: ``row * n_points + k - 1``), camera, x, y (top-left origin, px)."""
    path = Path(path)
    if not is_xypts(path):
        raise ImportError_(f"{path}: expected DLTdv columns pt<k>_cam<c>_X, pt<k>_cam<c>_Y")
    df = pd.read_csv(path)
    keys = [XYPTS.match(str(c).strip()) for c in df.columns]
    n_pts = max(int(m.group(1)) for m in keys)
    rows = []
    for c in sorted({int(m.group(2)) for m in keys}):
        cid = f"cam{c}"
        if cid not in heights:
            raise ImportError_(f"{path}: camera {c}: its image height is needed to move the "
                               "bottom-left origin to the top-left (give --image-size or a profile)")
        for k in range(1, n_pts + 1):
            if f"pt{k}_cam{c}_X" not in df.columns:
                continue
            X = pd.to_numeric(df[f"pt{k}_cam{c}_X"], errors="coerce").to_numpy(float)
            Y = pd.to_numeric(df[f"pt{k}_cam{c}_Y"], errors="coerce").to_numpy(float)
            ok = np.flatnonzero(np.isfinite(X) & np.isfinite(Y))
            rows.append(pd.DataFrame({"frame": ok * n_pts + k - 1, "camera": cid,
                                      "x": X[ok] - 1.0, "y": heights[cid] - Y[ok]}))
    out = pd.concat(rows, ignore_index=True) if rows else pd.DataFrame()
    if out.empty:
        raise ImportError_(f"{path}: no digitised points")
    return out.sort_values(["frame", "camera"], kind="stable").reset_index(drop=True)


def write_wand_session(out: str | os.PathLike, blobs: pd.DataFrame, cameras: list[CameraProfile],
                       offsets_mm, *, fps: float = 100.0, name: str = "imported-wand",
                       source: str = "", points: pd.DataFrame | None = None) -> Path:
    """Write a session of one ``wand`` take of unlabeled blobs (and, given ``points``, a
    ``points`` take of static points); returns the session folder."""
    out = Path(out)
    if (out / "session.toml").exists():
        raise ImportError_(f"{out}: already holds a session; choose a new folder")
    ids = {c.id for c in cameras}
    unknown = sorted(set(blobs["camera"]) - ids)
    if unknown:
        raise ImportError_(f"{source or 'blobs'}: cameras {unknown} have no image size "
                           f"(known: {sorted(ids)})")
    if points is not None and sorted(set(points["camera"]) - ids):
        raise ImportError_(f"static points: cameras {sorted(set(points['camera']) - ids)} have no "
                           f"image size (known: {sorted(ids)})")
    offsets = [float(v) for v in offsets_mm]
    if len(offsets) < 2 or np.any(np.diff(offsets) <= 0):
        raise ImportError_(f"wand offsets: expected 2 or more increasing values, mm; got {offsets}")
    write_csv(blobs[["frame", "camera", "x", "y"]], out / "takes" / "wand.csv", decimals=4)
    lines = ['schema = "mocap-session/1"', f'name = "{name}"', f"fps = {float(fps)!r}", ""]
    if source:
        lines.insert(0, f"# imported from {Path(source).name} by mocap import")
    for c in cameras:
        lines += ["[[cameras]]", f'id = "{c.id}"', f"width = {c.width}", f"height = {c.height}"]
        if c.focal_px:
            lines.append(f"focal_px = {float(c.focal_px)!r}")
        if c.principal_px is not None:
            lines.append(f"principal_px = [{float(c.principal_px[0])!r}, "
                         f"{float(c.principal_px[1])!r}]")
        if c.distortion is not None:
            lines.append("distortion = [" + ", ".join(repr(float(v)) for v in c.distortion) + "]")
        if c.intrinsics is not None and (c.principal_px is not None or c.distortion is not None):
            lines.append(f'intrinsics = "{c.intrinsics}"')
        lines.append("")
    lines += ["[wand]", f"marker_offsets_mm = {offsets}", "",
              "[[takes]]", 'name = "wand"', 'kind = "wand"', 'file = "takes/wand.csv"', ""]
    if points is not None:
        write_csv(points[["frame", "camera", "x", "y"]], out / "takes" / "points.csv", decimals=4)
        lines += ["[[takes]]", 'name = "points"', 'kind = "points"', 'file = "takes/points.csv"', ""]
    write_text(out / "session.toml", "\n".join(lines))
    return out
