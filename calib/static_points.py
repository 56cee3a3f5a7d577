"""Static points with known correspondence (a session's ``points`` takes) for the calibration.

A ``points`` take holds one distinct static point per frame (background points digitised in each
view, an LED placed at several spots), at most one blob per camera. Each point seen by two or more
cameras adds its sightings to the bundle adjustment as an unknown 3D position (3 parameters):
correspondences that tie the cameras together where the wand was thin, without scale.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from mocap.calib.camera import CameraRig, camera_index
from mocap.calib.triangulation import triangulate


@dataclass(frozen=True)
class StaticPoints:
    """The usable sightings of static points.

    camera_ids : the rig's camera ids, giving the meaning of ``camera``.
    camera : (m,) camera index of each sighting.
    point : (m,) the point's frame number in its take (its identity).
    uv : (m, 2) px, raw (distorted) image positions.
    skipped : why sightings were left out: {"several_blobs": n (a camera with 2 or more blobs in
        a point's frame: which is the point is unknown), "one_camera": n (a point seen by a
        single camera adds no correspondence)}.
    """

    camera_ids: tuple[str, ...]
    camera: np.ndarray
    point: np.ndarray
    uv: np.ndarray
    skipped: dict

    def __len__(self) -> int:
        return int(self.camera.size)

    @property
    def n_points(self) -> int:
        return int(np.unique(self.point).size)

    def select(self, mask: np.ndarray) -> "StaticPoints":
        return StaticPoints(self.camera_ids, self.camera[mask], self.point[mask], self.uv[mask],
                            self.skipped)


def static_points(blobs: pd.DataFrame, camera_ids, *, frame_offset: int = 0) -> StaticPoints:
    """A ``points`` take's blobs (frame, camera, x, y) as :class:`StaticPoints`; several takes
    are told apart by ``frame_offset`` (added to the frame numbers)."""
    ids = tuple(camera_ids)
    b = blobs[blobs["camera"].isin(ids)]
    n = b.groupby(["frame", "camera"])["x"].transform("size").to_numpy()
    several = int(np.sum(n > 1))
    b = b[n == 1]
    views = b.groupby("frame")["camera"].transform("size").to_numpy()
    one = int(np.sum(views < 2))
    b = b[views >= 2]
    return StaticPoints(ids, camera_index(b["camera"].to_numpy(), ids),
                        b["frame"].to_numpy(np.int64) + frame_offset,
                        b[["x", "y"]].to_numpy(float), {"several_blobs": several, "one_camera": one})


def combine(parts: list[StaticPoints]) -> StaticPoints | None:
    if not parts:
        return None
    skipped = {k: sum(p.skipped[k] for p in parts) for k in parts[0].skipped}
    return StaticPoints(parts[0].camera_ids, np.concatenate([p.camera for p in parts]),
                        np.concatenate([p.point for p in parts]),
                        np.concatenate([p.uv for p in parts]), skipped)


def initial_points(rig: CameraRig, pts: StaticPoints) -> tuple[np.ndarray, np.ndarray]:
    """Points (sorted ids (P,)) and their positions (P, 3) mm triangulated with ``rig``; NaN
    where the triangulation fails."""
    ids = np.unique(pts.point)
    local = np.searchsorted(ids, pts.point)
    uv = np.full((len(rig), ids.size, 2), np.nan)
    uv[pts.camera, local] = pts.uv
    return ids, triangulate(rig, uv).X
