"""The world frame from the ground square: find its markers, fit its known coordinates.

The ``ground`` take shows the square lying still. Per camera, its markers are the blob clusters
present in most frames (ghosts flicker; a reflection that persists is ruled out below); cluster
centres are matched across cameras by triangulating every pair of candidates and keeping 3D
points that reproject onto a cluster in at least ``min_cameras`` cameras. The known square is then
matched to those points by the assignment with the smallest rigid-fit error (all permutations:
squares have few markers), and a rigid transform (Kabsch/Umeyama without scale) maps the
calibration's frame onto the world frame. The scale the wand set is kept; the scale a similarity
fit would have chosen is reported as the agreement between wand and square.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import permutations

import numpy as np
import pandas as pd

from mocap.calib.camera import Camera, CameraRig
from mocap.calib.initialize import CalibrationError
from mocap.calib.triangulation import triangulate


@dataclass(frozen=True)
class GroundFit:
    """The rigid map world <- calibration frame: X_world = R @ X + t, and its quality."""

    R: np.ndarray
    t: np.ndarray
    points_mm: np.ndarray  # (n, 3) the square's markers as measured, calibration frame
    rms_mm: float  # rigid-fit RMS against the known coordinates
    scale: float  # similarity-fit scale (1 = wand and square agree)
    n_cameras: np.ndarray  # (n,) cameras that saw each marker


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = False):
    """Least-squares (similarity) transform dst ~ s R src + t; returns (R, t, s)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (a**2).sum(1).mean()) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return R, t, s


def static_clusters(blobs: pd.DataFrame, camera_ids, *, radius_px: float = 2.0,
                    min_presence: float = 0.5) -> dict[str, np.ndarray]:
    """Per camera, centres (k, 2) of blob clusters present in at least ``min_presence`` of frames."""
    n_frames = int(blobs["frame"].max()) + 1
    out = {}
    for cid in camera_ids:
        b = blobs[blobs["camera"] == cid]
        xy = b[["x", "y"]].to_numpy(float)
        fr = b["frame"].to_numpy()
        centres = []
        used = np.zeros(len(b), bool)
        # greedy: densest grid cell first; a still marker has ~n_frames blobs within the radius
        if len(b):
            cell = np.floor(xy / radius_px).astype(np.int64)
            keys, inv, counts = np.unique(cell, axis=0, return_inverse=True, return_counts=True)
            for k in np.argsort(-counts):
                if counts[k] < min_presence * n_frames * 0.25:
                    break
                seed = xy[(inv.ravel() == k) & ~used]
                if seed.size == 0:
                    continue
                c = np.median(seed, axis=0)
                near = (np.linalg.norm(xy - c, axis=1) < radius_px) & ~used
                if np.unique(fr[near]).size >= min_presence * n_frames:
                    c = np.median(xy[near], axis=0)
                    centres.append(c)
                used |= near
        out[cid] = np.array(centres).reshape(-1, 2)
    return out


def locate_static_points(rig: CameraRig, clusters: dict[str, np.ndarray], *,
                         tol_px: float = 2.0, min_cameras: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """3D points (k, 3) consistent with clusters in >= min_cameras cameras, and their counts."""
    cams = list(rig)
    found: list[np.ndarray] = []
    counts: list[int] = []
    for i in range(len(cams)):
        for j in range(i + 1, len(cams)):
            ci, cj = clusters[cams[i].id], clusters[cams[j].id]
            for a in ci:
                for b in cj:
                    uv = np.full((len(cams), 1, 2), np.nan)
                    uv[i, 0], uv[j, 0] = a, b
                    X = triangulate(rig, uv).X[0]
                    if not np.all(np.isfinite(X)):
                        continue
                    # support: a cluster within tol in each camera
                    uv_all = np.full((len(cams), 1, 2), np.nan)
                    for k, cam in enumerate(cams):
                        p = cam.project(X)
                        cl = clusters[cam.id]
                        if cl.size == 0:
                            continue
                        d = np.linalg.norm(cl - p, axis=1)
                        if d.min() < tol_px * 3:
                            uv_all[k, 0] = cl[np.argmin(d)]
                    n = int(np.isfinite(uv_all[:, 0, 0]).sum())
                    if n < min_cameras:
                        continue
                    tri = triangulate(rig, uv_all)
                    if tri.residual_px[0] > tol_px:
                        continue
                    X = tri.X[0]
                    if any(np.linalg.norm(X - f) < 3.0 for f in found):
                        continue
                    found.append(X)
                    counts.append(n)
    return np.array(found).reshape(-1, 3), np.array(counts, dtype=int)


def fit_ground(rig: CameraRig, blobs: pd.DataFrame, markers_mm: np.ndarray) -> GroundFit:
    """Locate the ground square in its take and fit the world frame to it."""
    known = np.asarray(markers_mm, float)
    clusters = static_clusters(blobs, rig.ids)
    pts, counts = locate_static_points(rig, clusters)
    n = known.shape[0]
    if pts.shape[0] < n:
        raise CalibrationError(
            f"ground take: found {pts.shape[0]} still markers seen by 3 or more cameras, the "
            f"manifest's [ground] has {n}; check that the square is in view of the cameras")
    best = None
    cand_idx = np.argsort(-counts)[: min(len(pts), 8)]
    for perm in permutations(cand_idx, n):
        src = pts[list(perm)]
        R, t, _ = umeyama(src, known)
        rms = float(np.sqrt(np.mean(np.sum((src @ R.T + t - known) ** 2, axis=1))))
        if best is None or rms < best[0]:
            best = (rms, list(perm), R, t)
    rms, perm, R, t = best
    src = pts[perm]
    _, _, s = umeyama(src, known, with_scale=True)
    if rms > 5.0:
        raise CalibrationError(
            f"ground take: no assignment of the still markers matches the manifest's [ground] "
            f"square (best rigid fit RMS {rms:.1f} mm); check markers_mm")
    return GroundFit(R=R, t=t, points_mm=src, rms_mm=rms, scale=s, n_cameras=counts[perm])


def transform_rig(rig: CameraRig, R_w: np.ndarray, t_w: np.ndarray) -> CameraRig:
    """Express cameras in the frame X_w = R_w X + t_w: x_cam = R R_w^T X_w + (t - R R_w^T t_w)."""
    out = []
    for c in rig:
        R = c.R @ R_w.T
        out.append(Camera(id=c.id, width=c.width, height=c.height, K=c.K, dist=c.dist,
                          R=R, t=c.t - R @ t_w))
    return CameraRig(tuple(out))
