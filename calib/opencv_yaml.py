"""Per-camera calibration files in OpenCV's FileStorage YAML.

Keys: ``camera_id`` (string), ``image_width``, ``image_height`` (int), ``camera_matrix`` (3x3),
``distortion_coefficients`` (1x5: k1 k2 p1 p2 k3), ``rotation_matrix`` (3x3) and
``translation_vector`` (3x1, mm), camera-from-world as everywhere in the package. OpenCV writes
doubles with 17 significant digits, so a write-read round trip is exact.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from mocap.calib.camera import Camera
from mocap.core.atomic import atomic_path


def write_opencv_yaml(camera: Camera, path: str | os.PathLike) -> Path:
    """Write one camera to an OpenCV FileStorage YAML file (atomically)."""
    with atomic_path(path) as tmp:
        yml = tmp.with_suffix(".yml")  # FileStorage picks the format from the extension
        fs = cv2.FileStorage(str(yml), cv2.FILE_STORAGE_WRITE)
        fs.write("camera_id", camera.id)
        fs.write("image_width", int(camera.width))
        fs.write("image_height", int(camera.height))
        fs.write("camera_matrix", np.asarray(camera.K, np.float64))
        fs.write("distortion_coefficients", np.asarray(camera.dist, np.float64).reshape(1, 5))
        fs.write("rotation_matrix", np.asarray(camera.R, np.float64))
        fs.write("translation_vector", np.asarray(camera.t, np.float64).reshape(3, 1))
        fs.release()
        os.replace(yml, tmp)
    return Path(path)


def read_opencv_yaml(path: str | os.PathLike) -> Camera:
    """Read a camera written by :func:`write_opencv_yaml` (or OpenCV with the same keys)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        def mat(key):
            node = fs.getNode(key)
            if node.empty():
                raise ValueError(f"{path}: missing key {key!r}")
            return node.mat()

        def num(key):
            node = fs.getNode(key)
            if node.empty():
                raise ValueError(f"{path}: missing key {key!r}")
            return node.real()

        cid = fs.getNode("camera_id").string() or path.stem
        return Camera(id=cid, width=int(num("image_width")), height=int(num("image_height")),
                      K=mat("camera_matrix"), dist=mat("distortion_coefficients").ravel(),
                      R=mat("rotation_matrix"), t=mat("translation_vector").ravel())
    finally:
        fs.release()
