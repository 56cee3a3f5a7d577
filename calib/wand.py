"""Finding a calibration wand among unlabeled 2D blobs.

Two-marker wands (a T-wand, an easyWand/Argus rod): the ends look alike, so a camera and frame
with exactly two blobs is a sighting whose end order is unknown (``ordered=False``); groups with
more blobs (reflections) are left out here. :mod:`mocap.calib.wand_ends` tells the ends apart
across cameras from the epipolar geometry.

A wand with ``n >= 3`` carries collinear markers at known offsets along it, with all gaps distinct,
so its two ends can be told apart. In each camera and frame, among the blobs (with ghosts and
dropouts), we look for ``n`` blobs that are collinear (interior blobs within ``line_tol_px`` of
the line through the outer two, plus 2 % of the wand's image length for lens distortion) and whose
gaps along the line match the wand's gaps in proportion (within ``ratio_tol``) in one orientation
clearly better than in the other. A (camera, frame) with no such set, or with two, is skipped:
the camera did not see the whole wand there.

Vectorised: (camera, frame) groups are padded to a fixed size per blob count and every
combination of ``n`` blobs is tested at once; groups with more than ``max_blobs`` blobs are
skipped (a wand in a field of reflections is not worth the risk).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
import pandas as pd


@dataclass(frozen=True)
class WandObservations:
    """Labeled wand sightings.

    Attributes
    ----------
    camera_ids : (n_cameras,) the rig's camera ids, giving the meaning of ``camera``.
    camera : (n_obs,) int camera index of each sighting.
    frame : (n_obs,) int frame of each sighting.
    uv : (n_obs, n_wand_markers, 2) px, the wand's markers in offset order (raw, distorted).
    ordered : False when the ends of each sighting are in an unknown order (a two-marker wand
        before :func:`mocap.calib.wand_ends.label_ends`); the order is then the blobs'.
    """

    camera_ids: tuple[str, ...]
    camera: np.ndarray
    frame: np.ndarray
    uv: np.ndarray
    ordered: bool = True

    def __len__(self) -> int:
        return int(self.camera.size)

    def select(self, mask: np.ndarray) -> "WandObservations":
        return WandObservations(self.camera_ids, self.camera[mask], self.frame[mask], self.uv[mask],
                                self.ordered)

    def frames_per_camera(self) -> dict[str, int]:
        counts = np.bincount(self.camera, minlength=len(self.camera_ids))
        return {cid: int(n) for cid, n in zip(self.camera_ids, counts)}


def _score_sets(pts: np.ndarray, gaps: np.ndarray, line_tol_px: float, ratio_tol: float):
    """Test candidate blob sets.

    pts : (..., n, 2) candidate sets (any order). Returns ``ok`` (...,) and ``ordered``
    (..., n, 2), the set in wand-offset order where ``ok``.
    """
    n = pts.shape[-2]
    # the two blobs farthest apart are the ends
    d = np.linalg.norm(pts[..., :, None, :] - pts[..., None, :, :], axis=-1)
    flat = d.reshape(d.shape[:-2] + (n * n,))
    k = np.argmax(flat, axis=-1)
    i0, i1 = k // n, k % n
    p0 = np.take_along_axis(pts, i0[..., None, None].repeat(2, -1), axis=-2)[..., 0, :]
    p1 = np.take_along_axis(pts, i1[..., None, None].repeat(2, -1), axis=-2)[..., 0, :]
    axis = p1 - p0
    length = np.linalg.norm(axis, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = axis / length[..., None]
    rel = pts - p0[..., None, :]
    along = np.einsum("...nk,...k->...n", rel, u)
    across = np.abs(rel[..., 0] * u[..., None, 1] - rel[..., 1] * u[..., None, 0])
    collinear = np.all(across <= line_tol_px + 0.02 * length[..., None], axis=-1)
    order = np.argsort(along, axis=-1)
    ordered = np.take_along_axis(pts, order[..., None].repeat(2, -1), axis=-2)
    s = np.take_along_axis(along, order, axis=-1)
    g = np.diff(s, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        g = g / g.sum(axis=-1, keepdims=True)
    ref = gaps / gaps.sum()
    err_fwd = np.max(np.abs(g - ref), axis=-1)
    err_rev = np.max(np.abs(g - ref[::-1]), axis=-1)
    fwd_ok = (err_fwd < ratio_tol) & (err_rev > 2.0 * err_fwd)
    rev_ok = (err_rev < ratio_tol) & (err_fwd > 2.0 * err_rev)
    ordered = np.where(rev_ok[..., None, None], ordered[..., ::-1, :], ordered)
    ok = collinear & (fwd_ok | rev_ok) & (length > 10.0)
    return ok, ordered


def find_wand(blobs: pd.DataFrame, camera_ids, offsets_mm, *, line_tol_px: float = 2.0,
              ratio_tol: float = 0.12, max_blobs: int = 8) -> WandObservations:
    """Find and label the wand in every camera and frame.

    Parameters
    ----------
    blobs : DataFrame with frame, camera, x, y (a ``wand`` take).
    camera_ids : the rig's camera ids (order defines camera indices).
    offsets_mm : (n_wand_markers,) marker offsets along the wand, mm (with 3 or more, all gaps
        distinct; with 2, the sightings come back with ``ordered=False``).

    Returns
    -------
    WandObservations, sorted by camera then frame.
    """
    camera_ids = tuple(camera_ids)
    offsets = np.sort(np.asarray(offsets_mm, float))
    n_w = offsets.size
    gaps = np.diff(offsets)
    from mocap.calib.camera import camera_index

    cam = camera_index(blobs["camera"], camera_ids)
    if np.any(cam < 0):
        unknown = sorted(set(blobs["camera"][cam < 0]))
        raise ValueError(f"wand blobs: cameras {unknown} are not in the rig {list(camera_ids)}")
    frame = blobs["frame"].to_numpy(np.int64)
    xy = blobs[["x", "y"]].to_numpy(float)
    n_frames = int(frame.max()) + 1 if frame.size else 0
    key = cam * n_frames + frame
    order = np.argsort(key, kind="stable")
    key, xy = key[order], xy[order]
    uniq, start, count = np.unique(key, return_index=True, return_counts=True)
    out_cam, out_frame, out_uv = [], [], []
    if n_w == 2:  # ends alike: exactly two blobs, far enough apart to be a wand
        groups = np.flatnonzero(count == 2)
        pts = xy[start[groups][:, None] + np.arange(2)[None, :]]
        ok = np.linalg.norm(pts[:, 1] - pts[:, 0], axis=1) > 10.0
        k = uniq[groups[ok]]
        o = np.lexsort((k % n_frames, k // n_frames))
        return WandObservations(camera_ids, (k // n_frames)[o], (k % n_frames)[o], pts[ok][o],
                                ordered=False)
    for size in range(n_w, max_blobs + 1):
        groups = np.flatnonzero(count == size)
        if groups.size == 0:
            continue
        idx = start[groups][:, None] + np.arange(size)[None, :]
        pts = xy[idx]  # (G, size, 2)
        combos = np.array(list(combinations(range(size), n_w)))  # (K, n_w)
        cand = pts[:, combos]  # (G, K, n_w, 2)
        ok, ordered = _score_sets(cand, gaps, line_tol_px, ratio_tol)
        unique = ok.sum(axis=1) == 1
        best = np.argmax(ok, axis=1)
        sel = np.flatnonzero(unique)
        out_uv.append(ordered[sel, best[sel]])
        k = uniq[groups[sel]]
        out_cam.append(k // n_frames)
        out_frame.append(k % n_frames)
    if not out_uv:
        return WandObservations(camera_ids, np.zeros(0, np.int64), np.zeros(0, np.int64),
                                np.zeros((0, n_w, 2)))
    camera = np.concatenate(out_cam)
    frames = np.concatenate(out_frame)
    uv = np.concatenate(out_uv)
    o = np.lexsort((frames, camera))
    return WandObservations(camera_ids, camera[o], frames[o], uv[o])
