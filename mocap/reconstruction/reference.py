"""NumPy references of the compiled reconstruction kernels (the implementations they replaced).

Kept only so the tests can check that the compiled paths give the same results, not used by the
pipeline:

- :func:`reconstruct_points_reference`: cross-camera correspondence and triangulation (k-d trees
  and sorted searches), the signature and result of
  :func:`mocap.reconstruction.correspondence.reconstruct_points`, about 10 x slower;
- :func:`link_tracklets_reference`: tracklet linking (k-d tree, connected components), as
  :func:`mocap.reconstruction.labeling.link_tracklets`.
"""

from __future__ import annotations

from itertools import combinations

import numpy as np
import pandas as pd
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from mocap.calib.camera import CameraRig, camera_index
from mocap.calib.triangulation_kernel import triangulate_normalized
from mocap.reconstruction.correspondence import (
    BlobTable,
    Points3D,
    ReconstructionSettings,
    camera_gates,
)
from mocap.reconstruction.labeling import LabelSettings

_FRAME_SPACING = 1.0e6  # px: keeps k-d tree neighbours within one frame


def blob_table_reference(blobs: pd.DataFrame, rig: CameraRig) -> BlobTable:
    """The blob table computed with the cameras' NumPy methods."""
    cam = camera_index(blobs["camera"], rig.ids)
    uv = blobs[["x", "y"]].to_numpy(np.float64)
    xn = np.empty_like(uv)
    ray = np.empty((uv.shape[0], 3))
    for i, c in enumerate(rig):
        s = cam == i
        xn[s] = c.normalize(uv[s])
        d = np.column_stack([xn[s], np.ones(s.sum())]) @ c.R
        ray[s] = d / np.linalg.norm(d, axis=1, keepdims=True)
    return BlobTable(blobs["frame"].to_numpy(np.int64), cam, uv, xn, ray)


def _pair_candidates(bt: BlobTable, rig: CameraRig, a: int, b: int, ia: np.ndarray,
                     ib: np.ndarray, gate_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Blob index pairs (of ia, ib) passing the symmetric epipolar test."""
    ca, cb = rig[a], rig[b]
    base = cb.center - ca.center
    bn = base / np.linalg.norm(base)
    e1 = np.cross(bn, [0.0, 0.0, 1.0] if abs(bn[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(bn, e1)

    def angle(rays):
        n = np.cross(bn, rays)
        return np.arctan2(n @ e2, n @ e1) + np.pi  # [0, 2 pi]

    th_a, th_b = angle(bt.ray[ia]), angle(bt.ray[ib])
    key_a = bt.frame[ia] * 8.0 + th_a
    key_b = bt.frame[ib] * 8.0 + th_b
    order = np.argsort(key_b)
    key_b, ib_sorted = key_b[order], ib[order]
    # generous window in angle; the exact test follows
    dth = 40.0 * gate_px / min(ca.focal_px, cb.focal_px)
    lo = np.searchsorted(key_b, key_a - dth)
    hi = np.searchsorted(key_b, key_a + dth)
    n = hi - lo
    ra = np.repeat(np.arange(ia.size), n)
    offs = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
    rb = lo[ra] + offs
    pa, pb = ia[ra], ib_sorted[rb]
    # symmetric epipolar distance with E = [t]x R (b from a)
    R_ab = cb.R @ ca.R.T
    t_ab = cb.t - R_ab @ ca.t
    tx = np.array([[0, -t_ab[2], t_ab[1]], [t_ab[2], 0, -t_ab[0]], [-t_ab[1], t_ab[0], 0]])
    E = tx @ R_ab
    xa = np.column_stack([bt.xn[pa], np.ones(pa.size)])
    xb = np.column_stack([bt.xn[pb], np.ones(pb.size)])
    la = xa @ E.T  # lines in b
    lb = xb @ E  # lines in a
    alg = np.abs(np.sum(xb * la, axis=1))
    db = alg / np.hypot(la[:, 0], la[:, 1]) * cb.focal_px
    da = alg / np.hypot(lb[:, 0], lb[:, 1]) * ca.focal_px
    ok = (db < gate_px) & (da < gate_px)
    return pa[ok], pb[ok]


def reconstruct_points_reference(blobs: pd.DataFrame, rig: CameraRig, quality: dict | None = None,
                       settings: ReconstructionSettings = ReconstructionSettings()) -> Points3D:
    """Match blobs across cameras and triangulate every frame of a take.

    Parameters
    ----------
    blobs : a take's blobs (frame, camera, x, y); row order defines blob indices.
    rig : calibrated cameras (the same ids as the blobs' cameras).
    quality : the calibration's quality report (per-camera reprojection RMS sets the gates).
    """
    bt = blob_table_reference(blobs, rig)
    C = len(rig)
    gates = camera_gates(rig, quality, settings)
    used = np.zeros(bt.frame.size, bool)
    trees = []
    for c in range(C):
        idx = np.flatnonzero(bt.cam == c)
        pts = np.column_stack([bt.frame[idx] * _FRAME_SPACING, bt.uv[idx]])
        trees.append((cKDTree(pts) if idx.size else None, idx))
    Rt = np.stack([np.hstack([c.R, c.t[:, None]]) for c in rig])
    focal = np.array([c.focal_px for c in rig])
    centres = np.stack([c.center for c in rig])
    pairs = sorted(combinations(range(C), 2),
                   key=lambda p: -np.linalg.norm(centres[p[0]] - centres[p[1]]))
    accepted: list[np.ndarray] = []
    # 3+-view candidates over every pair first, then unique bare pairs among the blobs left
    for min_cams in (3, 2):
        for a, b in pairs:
            ia = np.flatnonzero((bt.cam == a) & ~used)
            ib = np.flatnonzero((bt.cam == b) & ~used)
            if ia.size == 0 or ib.size == 0:
                continue
            pa, pb = _pair_candidates(bt, rig, a, b, ia, ib, max(gates[a], gates[b]))
            if pa.size == 0:
                continue
            n = pa.size
            xn = np.full((C, n, 2), np.nan)
            xn[a], xn[b] = bt.xn[pa], bt.xn[pb]
            X = triangulate_normalized(Rt, focal, xn, 0)
            views = np.full((n, C), -1, np.int64)
            views[:, a], views[:, b] = pa, pb
            depth_ok = np.ones(n, bool)
            for c in (a, b):
                z = (X @ rig[c].R.T + rig[c].t)[:, 2]
                depth_ok &= (z > 0) & (z < settings.max_depth_mm)
            for c in range(C):
                if c in (a, b) or trees[c][0] is None:
                    continue
                uv = rig[c].project(X)
                q = np.column_stack([bt.frame[pa] * _FRAME_SPACING, uv])
                good = np.all(np.isfinite(q), axis=1)
                dist = np.full(n, np.inf)
                j = np.full(n, -1)
                if good.any():
                    dist[good], j[good] = trees[c][0].query(q[good], k=1, distance_upper_bound=gates[c])
                hit = np.isfinite(dist)
                blob_c = np.where(hit, trees[c][1][np.minimum(j, trees[c][1].size - 1)], -1)
                hit &= blob_c >= 0
                hit[hit] &= ~used[blob_c[hit]]
                views[hit, c] = blob_c[hit]
            support = (views >= 0).sum(axis=1)
            keep = depth_ok & (support >= min_cams)
            if min_cams == 2:
                # a bare epipolar pair is trusted only when it is its blobs' only candidate
                ua, ca_ = np.unique(pa, return_counts=True)
                ub, cb_ = np.unique(pb, return_counts=True)
                uniq = (ca_[np.searchsorted(ua, pa)] == 1) & (cb_[np.searchsorted(ub, pb)] == 1)
                keep = depth_ok & ((support >= 3) | uniq)
            if not keep.any():
                continue
            views, X = views[keep], X[keep]
            views = _one_point_per_blob(views, bt, rig, Rt, focal)
            if views.size == 0:
                continue
            accepted.append(views)
            used[views[views >= 0]] = True
    if not accepted:
        return Points3D(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64),
                        np.zeros(0), np.zeros((0, C), np.int64))
    views = np.concatenate(accepted)
    return _final_triangulation(views, bt, rig, Rt, focal, gates, 2)


def _solve_views(views, bt, rig, Rt, focal):
    n, C = views.shape
    xn = np.full((C, n, 2), np.nan)
    uv = np.full((C, n, 2), np.nan)
    for c in range(C):
        s = views[:, c] >= 0
        xn[c, s] = bt.xn[views[s, c]]
        uv[c, s] = bt.uv[views[s, c]]
    X = triangulate_normalized(Rt, focal, xn, 1)
    err = np.linalg.norm(rig.project(X) - uv, axis=-1)  # (C, n)
    return X, err


def _one_point_per_blob(views, bt, rig, Rt, focal):
    """Keep, for every blob, only its best candidate (most views, then smallest residual)."""
    views = np.unique(views, axis=0)
    X, err = _solve_views(views, bt, rig, Rt, focal)
    support = (views >= 0).sum(axis=1)
    with np.errstate(invalid="ignore"):
        resid = np.sqrt(np.nanmean(err**2, axis=0))
    score = support * 1e3 - np.nan_to_num(resid, nan=1e3)
    alive = np.ones(views.shape[0], bool)
    for _ in range(3):
        rows, cols = np.nonzero((views >= 0) & alive[:, None])
        blob = views[rows, cols]
        order = np.lexsort((-score[rows], blob))
        first = np.ones(order.size, bool)
        first[1:] = blob[order][1:] != blob[order][:-1]
        winner_rows = rows[order][first]
        is_winner = np.zeros(views.shape[0], bool)
        # a candidate survives when it wins every blob it uses
        wins = np.zeros(views.shape[0], np.int64)
        np.add.at(wins, winner_rows, 1)
        is_winner = wins == ((views >= 0) & alive[:, None]).sum(axis=1)
        new_alive = alive & is_winner
        if np.array_equal(new_alive, alive):
            break
        alive = new_alive
    return views[alive]


def _final_triangulation(views, bt, rig, Rt, focal, gates, min_cams) -> Points3D:
    X, err = _solve_views(views, bt, rig, Rt, focal)
    bad = (views >= 0) & (err.T > gates[None, :])
    if bad.any():
        views = np.where(bad, -1, views)
        X, err = _solve_views(views, bt, rig, Rt, focal)
    n_cam = (views >= 0).sum(axis=1)
    keep = n_cam >= min_cams
    views, X, err, n_cam = views[keep], X[keep], err[:, keep], n_cam[keep]
    e2 = np.where(views.T >= 0, err**2, 0.0)
    resid = np.sqrt(e2.sum(axis=0) / np.maximum(n_cam, 1))
    frame = bt.frame[np.max(views, axis=1)]
    order = np.argsort(frame, kind="stable")
    return Points3D(frame[order], X[order], n_cam[order], resid[order], views[order])


def link_tracklets_reference(frame: np.ndarray, X: np.ndarray, settings: LabelSettings = LabelSettings()) -> np.ndarray:
    """Tracklet id (n,) of each point, by mutual nearest-neighbour links between frames."""
    n = frame.size
    if n == 0:
        return np.zeros(0, np.int64)
    big = 1.0e6  # mm between frames in the k-d tree
    pts = np.column_stack([frame * big, X])
    tree = cKDTree(pts)
    src, dst = [], []
    has_next = np.zeros(n, bool)
    has_prev = np.zeros(n, bool)
    for gap in range(1, settings.max_gap_frames + 2):
        cand = np.flatnonzero(~has_next) if gap > 1 else np.arange(n)
        if cand.size == 0:
            break
        fwd_q = pts[cand].copy()
        fwd_q[:, 0] += gap * big
        d, j = tree.query(fwd_q, k=1, distance_upper_bound=settings.link_gate_mm)
        ok = np.isfinite(d)
        i_, j_ = cand[ok], j[ok]
        ok2 = ~has_prev[j_]
        i_, j_ = i_[ok2], j_[ok2]
        # mutual: j's nearest neighbour `gap` frames back is i
        back = pts[j_].copy()
        back[:, 0] -= gap * big
        d2, i2 = tree.query(back, k=1, distance_upper_bound=settings.link_gate_mm)
        mutual = np.isfinite(d2) & (i2 == i_)
        i_, j_ = i_[mutual], j_[mutual]
        # one link per target
        _, first = np.unique(j_, return_index=True)
        i_, j_ = i_[first], j_[first]
        src.append(i_)
        dst.append(j_)
        has_next[i_] = True
        has_prev[j_] = True
    s = np.concatenate(src)
    t = np.concatenate(dst)
    g = coo_matrix((np.ones(s.size), (s, t)), shape=(n, n))
    _, comp = connected_components(g, directed=False)
    return comp
