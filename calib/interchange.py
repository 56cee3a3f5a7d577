"""Calibration files of the field's other tools, both ways.

**aniposelib's ``calibration.toml``** (what anipose, Pose2Sim and caliscope read): one table per
camera, ``[cam_0]``, ``[cam_1]``, ... with ``name`` (string), ``size`` ([width, height] px),
``matrix`` (3x3 K, px), ``distortion`` ([k1, k2, p1, p2, k3], OpenCV's), ``rotation`` (Rodrigues
vector of R, camera-from-world) and ``translation`` (t), OpenCV's convention
``x_cam = R X + t`` as ours; plus ``[metadata]``. The layout has no unit of its own: translations
are in the unit of the object that was measured (anipose's board, usually mm); Pose2Sim expects
metres. ``units`` says which is written or read ("mm" or "m").

**DLT coefficients** (easyWand, DLTdv, Argus): the 11 coefficients ``L1..L11`` of the linear
camera ``u = (L1 X + L2 Y + L3 Z + L4) / (L9 X + L10 Y + L11 Z + 1)``,
``v = (L5 X + L6 Y + L7 Z + L8) / (L9 X + L10 Y + L11 Z + 1)``, i.e. ``K [R | t]`` scaled so its
last entry is 1. What the linear model loses: lens distortion (the DLT projects to the
*undistorted* image; use it with undistorted points, or keep the Brown-Conrady terms elsewhere),
and nothing else (skew and unequal pixel scales are representable). Pixel origin: DLTdv and
easyWand work in MATLAB's image coordinates, origin at the bottom-left, 1-based
(``u = x + 1``, ``v = height - y``), which ``origin="bottom-left"`` (default) applies; ``"top-left"``
keeps ours. The file is easyWand's ``*_dltCoefs.csv``: 11 rows, one column per camera.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from mocap.core.atomic import write_text
from mocap.calib.calibration_file import CalibrationFileError, read_toml
from mocap.calib.camera import Camera, CameraRig, rodrigues_from_rotation, rotation_from_rodrigues

UNITS_MM = {"mm": 1.0, "m": 1000.0}


def _units(units: str) -> float:
    if units not in UNITS_MM:
        raise ValueError(f"units: expected 'mm' or 'm', got {units!r}")
    return UNITS_MM[units]


def _num(v: float) -> str:
    v = float(v)
    if not math.isfinite(v):
        raise ValueError(f"cannot write a non-finite number to a calibration file: {v}")
    return repr(v)


def _list(a) -> str:
    a = np.asarray(a)
    if a.ndim == 1:
        return "[" + ", ".join(_num(x) for x in a) + "]"
    return "[" + ", ".join(_list(r) for r in a) + "]"


def anipose_text(rig: CameraRig, *, units: str = "mm", metadata: dict | None = None) -> str:
    """The text of an aniposelib calibration.toml for ``rig``."""
    to_unit = 1.0 / _units(units)
    lines = [f"# facemocap calibration in aniposelib's layout; translation in {units}"]
    for i, c in enumerate(rig):
        name = c.id.replace("\\", "\\\\").replace('"', '\\"')
        lines += [f"[cam_{i}]", f'name = "{name}"', f"size = [{c.width}, {c.height}]",
                  f"matrix = {_list(c.K)}", f"distortion = {_list(c.dist)}",
                  f"rotation = {_list(rodrigues_from_rotation(c.R))}",
                  f"translation = {_list(c.t * to_unit)}", ""]
    lines.append("[metadata]")
    lines.append("adjusted = true")
    for k, v in (metadata or {}).items():
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            lines.append(f"{k} = {_num(v)}")
        elif isinstance(v, str):
            lines.append(f'{k} = "{v}"')
    return "\n".join(lines) + "\n"


def write_anipose(path: str | os.PathLike, rig: CameraRig, *, units: str = "mm",
                  metadata: dict | None = None) -> Path:
    """Write ``rig`` as an aniposelib calibration.toml (atomically)."""
    return write_text(path, anipose_text(rig, units=units, metadata=metadata))


def read_anipose(path: str | os.PathLike, *, units: str = "mm") -> CameraRig:
    """Read an aniposelib calibration.toml (cameras in ``[cam_<k>]`` order; translation in
    ``units``). Errors name the file and the table."""
    path = Path(path)
    scale = _units(units)
    data = read_toml(path)
    keys = sorted((k for k in data if k.startswith("cam_") and isinstance(data[k], dict)),
                  key=lambda k: int(k[4:]) if k[4:].isdigit() else 10**9)
    if not keys:
        raise CalibrationFileError(f"{path}: expected [cam_0], [cam_1], ... tables, got none")
    cams = []
    for k in keys:
        t = data[k]
        missing = [m for m in ("size", "matrix", "rotation", "translation") if m not in t]
        if missing:
            raise CalibrationFileError(f"{path}: [{k}]: missing keys {missing}")
        dist = np.zeros(5)
        d = np.asarray(t.get("distortion", []), float).ravel()
        if d.size > 5:
            raise CalibrationFileError(f"{path}: [{k}].distortion: expected up to 5 OpenCV "
                                       f"coefficients (k1 k2 p1 p2 k3), got {d.size}")
        dist[: d.size] = d
        try:
            w, h = (int(v) for v in t["size"])
            cams.append(Camera(id=str(t.get("name", k)), width=w, height=h, K=t["matrix"],
                               dist=dist, R=rotation_from_rodrigues(np.asarray(t["rotation"], float)),
                               t=np.asarray(t["translation"], float) * scale))
        except (ValueError, TypeError) as e:
            raise CalibrationFileError(f"{path}: [{k}]: {e}") from None
    return CameraRig(tuple(cams))


def _origin_matrix(camera: Camera, origin: str) -> np.ndarray:
    """Map from our pixels (top-left origin, 0-based) to the DLT file's."""
    if origin == "top-left":
        return np.eye(3)
    if origin == "bottom-left":
        return np.array([[1.0, 0.0, 1.0], [0.0, -1.0, float(camera.height)], [0.0, 0.0, 1.0]])
    raise ValueError(f"origin: expected 'bottom-left' or 'top-left', got {origin!r}")


def dlt_coefficients(camera: Camera, *, origin: str = "bottom-left") -> np.ndarray:
    """The 11 DLT coefficients (11,) of ``camera`` (world mm -> the file's pixels), distortion
    dropped (see the module docstring)."""
    P = _origin_matrix(camera, origin) @ camera.K @ np.hstack([camera.R, camera.t[:, None]])
    return (P / P[2, 3]).ravel()[:11]


def dlt_project(L: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Project world points (..., 3) with DLT coefficients (11,) -> (..., 2) in the file's pixels."""
    P = np.append(np.asarray(L, float), 1.0).reshape(3, 4)
    h = np.asarray(X, float) @ P[:, :3].T + P[:, 3]
    return h[..., :2] / h[..., 2:3]


def camera_from_dlt(L: np.ndarray, *, camera_id: str, width: int, height: int,
                    origin: str = "bottom-left") -> Camera:
    """A distortion-free Camera from DLT coefficients: ``P = K [R | t]`` by RQ decomposition
    (K upper triangular with a positive diagonal; R a rotation)."""
    P = np.append(np.asarray(L, float), 1.0).reshape(3, 4)
    like = Camera(id=camera_id, width=width, height=height, K=np.eye(3))
    P = np.linalg.inv(_origin_matrix(like, origin)) @ P
    M = P[:, :3]
    # RQ via QR of the flipped transpose
    flip = np.eye(3)[::-1]
    Q, Rm = np.linalg.qr((flip @ M).T)
    K = flip @ Rm.T @ flip
    R = flip @ Q.T
    D = np.diag(np.sign(np.diag(K)))
    K, R = K @ D, D @ R
    t = np.linalg.solve(K, P[:, 3])
    if np.linalg.det(R) < 0:  # P is defined up to scale: take -P
        R, t = -R, -t
    return Camera(id=camera_id, width=width, height=height, K=K / K[2, 2], R=R, t=t)


def write_dlt_csv(path: str | os.PathLike, rig: CameraRig, *, origin: str = "bottom-left") -> Path:
    """easyWand's ``*_dltCoefs.csv``: 11 rows, one column per camera (in rig order)."""
    L = np.stack([dlt_coefficients(c, origin=origin) for c in rig], axis=1)  # (11, n_cameras)
    text = "\n".join(",".join(repr(float(v)) for v in row) for row in L) + "\n"
    return write_text(path, text)


def read_dlt_csv(path: str | os.PathLike, cameras: list[tuple[str, int, int]], *,
                 origin: str = "bottom-left") -> CameraRig:
    """Read a DLT coefficient CSV; ``cameras``: (id, width, height) per column."""
    path = Path(path)
    try:
        L = np.loadtxt(path, delimiter=",", ndmin=2)
    except (OSError, ValueError) as e:
        raise CalibrationFileError(f"{path}: expected 11 rows of comma-separated numbers ({e})") from None
    if L.shape[0] != 11:
        raise CalibrationFileError(f"{path}: expected 11 rows (L1..L11), got {L.shape[0]}")
    if L.shape[1] != len(cameras):
        raise CalibrationFileError(f"{path}: {L.shape[1]} camera columns, {len(cameras)} cameras given")
    return CameraRig(tuple(camera_from_dlt(L[:, i], camera_id=cid, width=w, height=h, origin=origin)
                           for i, (cid, w, h) in enumerate(cameras)))
