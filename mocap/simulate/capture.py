"""The virtual cameras' 2D blob detections of a take, with their true labels.

For each camera and frame: every point in front of the camera, inside the image and visible
(face markers: the skin's normal within ``MAX_VIEW_ANGLE_DEG`` of the direction to the camera;
the nose-bridge marker only in its few unshadowed cameras) is projected with the true camera
(distortion included), loses a blob with probability ``dropout``, gets Gaussian centroid noise of
``noise_px`` per axis; two blobs closer than ``merge_px`` merge into one at their mean (label -2);
ghost blobs (label -1, reflections) are added, a Poisson number per camera and frame with mean
``ghost_rate`` times the camera's mean real blob count, half uniform over the image and half
flickering at three fixed reflection spots per camera. Rows are sorted by frame and camera and
shuffled within each (frame, camera): file order carries no identity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from mocap.calib.camera import CameraRig

MAX_VIEW_ANGLE_DEG = 75.0
GHOST = -1
MERGED = -2


@dataclass(frozen=True)
class CaptureNoise:
    """Detection imperfections, per camera overridable (degraded camera)."""

    noise_px: float = 0.08
    dropout: float = 0.01
    ghost_rate: float = 0.02
    merge_px: float = 1.5


def _merge_close(frame, cam, uv, label, merge_px):
    """Merge blob pairs of one (frame, camera) closer than merge_px (vectorised, near pairs)."""
    if uv.shape[0] < 2 or merge_px <= 0:
        return uv, label, np.ones(uv.shape[0], bool)
    order = np.lexsort((uv[:, 0], cam, frame))
    f, c, p = frame[order], cam[order], uv[order]
    keep = np.ones(p.shape[0], bool)
    new_uv = p.copy()
    new_label = label[order].copy()
    for lag in (1, 2, 3):
        same = (f[lag:] == f[:-lag]) & (c[lag:] == c[:-lag])
        close = same & (np.abs(p[lag:, 0] - p[:-lag, 0]) < merge_px) & (
            np.abs(p[lag:, 1] - p[:-lag, 1]) < merge_px)
        close &= keep[lag:] & keep[:-lag]
        i = np.flatnonzero(close)
        new_uv[i] = 0.5 * (p[i] + p[i + lag])
        new_label[i] = MERGED
        keep[i + lag] = False
    inv = np.empty_like(order)
    inv[order] = np.arange(order.size)
    return new_uv[inv], new_label[inv], keep[inv]


def observe(rig: CameraRig, points: np.ndarray, rng: np.random.Generator, *,
            noise: CaptureNoise = CaptureNoise(), per_camera_noise: dict | None = None,
            normals: np.ndarray | None = None, allowed: np.ndarray | None = None,
            measurement_jitter_mm: np.ndarray | None = None) -> tuple[pd.DataFrame, np.ndarray]:
    """Blob detections of ``points`` by every camera.

    Parameters
    ----------
    points : (n_frames, n_points, 3) world mm; NaN rows are absent points.
    normals : (n_points, 3) outward normals for the view-angle test (None: spheres seen from
        anywhere, as the wand's and the ground square's markers).
    allowed : (n_cameras, n_points) bool, which camera may see which point at all (shadows) and
        (n_cameras, n_frames) masks may be folded in by the caller via NaN points.
    measurement_jitter_mm : (n_points,) extra 3D jitter sd of a point's centroid (a marker in
        shadow), drawn per frame and seen alike by every camera.
    per_camera_noise : camera id -> CaptureNoise overriding ``noise`` (a degraded camera).

    Returns
    -------
    blobs : DataFrame frame (int64), camera (str), x, y (float64 px).
    labels : (n_rows,) int32 point index per row, -1 ghost, -2 merged blob.
    """
    n_frames, n_points, _ = points.shape
    pts = points
    if measurement_jitter_mm is not None and np.any(measurement_jitter_mm > 0):
        pts = points + rng.normal(0.0, 1.0, points.shape) * measurement_jitter_mm[None, :, None]
    frames_all, cams_all, uv_all, labels_all = [], [], [], []
    for ci, cam in enumerate(rig):
        nz = (per_camera_noise or {}).get(cam.id, noise)
        uv = cam.project(pts)  # (F, P, 2)
        vis = cam.in_image(uv, margin_px=1.0) & np.all(np.isfinite(pts), axis=-1)
        if normals is not None:
            to_cam = cam.center[None, None, :] - pts
            to_cam /= np.linalg.norm(to_cam, axis=-1, keepdims=True)
            cosang = np.sum(to_cam * normals[None], axis=-1)
            vis &= cosang > np.cos(np.deg2rad(MAX_VIEW_ANGLE_DEG))
        if allowed is not None:
            vis &= allowed[ci][None, :]
        vis &= rng.random(vis.shape) >= nz.dropout
        f_idx, p_idx = np.nonzero(vis)
        xy = uv[f_idx, p_idx] + rng.normal(0.0, nz.noise_px, (f_idx.size, 2))
        lab = p_idx.astype(np.int32)
        cam_idx = np.full(f_idx.size, ci)
        xy, lab, keep = _merge_close(f_idx, cam_idx, xy, lab, nz.merge_px)
        f_idx, xy, lab = f_idx[keep], xy[keep], lab[keep]
        # ghosts
        mean_real = f_idx.size / max(n_frames, 1)
        n_ghost = rng.poisson(nz.ghost_rate * max(mean_real, 1.0), n_frames)
        g_frames = np.repeat(np.arange(n_frames), n_ghost)
        spots = np.column_stack([rng.uniform(0, cam.width - 1, 3), rng.uniform(0, cam.height - 1, 3)])
        uniform = rng.random(g_frames.size) < 0.5
        g_xy = np.where(
            uniform[:, None],
            np.column_stack([rng.uniform(0, cam.width - 1, g_frames.size),
                             rng.uniform(0, cam.height - 1, g_frames.size)]),
            spots[rng.integers(0, 3, g_frames.size)] + rng.normal(0, 0.3, (g_frames.size, 2)),
        )
        frames_all += [f_idx, g_frames]
        cams_all += [np.full(f_idx.size, ci), np.full(g_frames.size, ci)]
        uv_all += [xy, g_xy]
        labels_all += [lab, np.full(g_frames.size, GHOST, np.int32)]
    frame = np.concatenate(frames_all).astype(np.int64)
    cam = np.concatenate(cams_all)
    uv = np.concatenate(uv_all)
    labels = np.concatenate(labels_all).astype(np.int32)
    order = np.lexsort((rng.random(frame.size), cam, frame))
    ids = np.array(rig.ids, dtype=object)
    blobs = pd.DataFrame({
        "frame": frame[order],
        "camera": ids[cam[order]],
        "x": uv[order, 0],
        "y": uv[order, 1],
    })
    return blobs, labels[order]
