"""Initial camera poses from wand sightings, with no prior on where the cameras are.

1. Intrinsics: ``focal_px`` from the manifest when given, else the image's larger side (a lens of
   about 53 degrees horizontal field of view); principal point at the image centre; no
   distortion.
2. Every camera pair that saw the wand in the same frames (at least ``min_shared`` frames) gets a
   relative pose from the essential matrix of the wand-marker correspondences (OpenCV's
   five-point solver in RANSAC, then ``recoverPose``), and a metric scale from the wand's length
   (median over the triangulated frames).
   Two-marker wands (ends alike, ``obs.ordered`` False): each shared frame offers both end
   assignments (four putative matches, half of them wrong); RANSAC finds the essential matrix
   the right half agrees on, and each frame keeps the assignment with the smaller epipolar
   error (:func:`mocap.calib.wand_ends.choose_pair_assignment`).
3. The camera graph (edges weighted by RANSAC inliers) is reduced to its maximum spanning tree,
   rooted at the camera with the most sightings, and relative poses are chained along it. The
   rig is returned in the first camera's frame (OpenCV axes, origin at its centre): the gauge
   of the bundle adjustment, and the world frame of a session without a ground square.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree

from mocap.calib.camera import Camera, CameraRig
from mocap.calib.wand import WandObservations
from mocap.calib.wand_ends import choose_pair_assignment


class CalibrationError(RuntimeError):
    """Calibration cannot proceed; the message says what is wrong and what to do."""


@dataclass(frozen=True)
class PairPose:
    a: int
    b: int
    R: np.ndarray  # b from a
    t: np.ndarray  # mm
    inliers: int
    shared_frames: int


def initial_intrinsics(camera_id: str, width: int, height: int, focal_px: float | None) -> Camera:
    f = float(focal_px) if focal_px else float(max(width, height))
    K = [[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]]
    return Camera(id=camera_id, width=width, height=height, K=K)


def _shared(obs: WandObservations, a: int, b: int):
    fa = obs.frame[obs.camera == a]
    fb = obs.frame[obs.camera == b]
    common, ia, ib = np.intersect1d(fa, fb, return_indices=True)
    ua = obs.uv[obs.camera == a][ia]
    ub = obs.uv[obs.camera == b][ib]
    return common, ua, ub


def pair_pose(obs: WandObservations, cams: list[Camera], a: int, b: int, wand_length_mm: float,
              *, max_frames: int = 600, seed: int = 0) -> PairPose | None:
    """Relative pose of camera b with respect to camera a (metric), or None if unreliable."""
    common, ua, ub = _shared(obs, a, b)
    if common.size < 8:
        return None
    if common.size > max_frames:
        keep = np.linspace(0, common.size - 1, max_frames).astype(int)
        ua, ub = ua[keep], ub[keep]
    f = 0.5 * (cams[a].focal_px + cams[b].focal_px)
    cv2.setRNGSeed(seed)
    if not obs.ordered:  # ends alike: both assignments are putative matches
        pa_, pb_ = cams[a].normalize(ua), cams[b].normalize(ub)
        na4 = np.concatenate([pa_, pa_]).reshape(-1, 2)
        nb4 = np.concatenate([pb_, pb_[:, ::-1]]).reshape(-1, 2)
        E, _ = cv2.findEssentialMat(na4, nb4, np.eye(3), method=cv2.RANSAC, prob=0.9999,
                                    threshold=4.0 / f, maxIters=5000)
        if E is None or E.shape != (3, 3):
            return None
        swap, _ = choose_pair_assignment(E[:3], pa_, pb_)
        ub = np.where(swap[:, None, None], ub[:, ::-1], ub)
    na = cams[a].normalize(ua).reshape(-1, 2)
    nb = cams[b].normalize(ub).reshape(-1, 2)
    E, mask = cv2.findEssentialMat(na, nb, np.eye(3), method=cv2.RANSAC, prob=0.9999,
                                   threshold=4.0 / f, maxIters=5000)
    if E is None or E.shape != (3, 3):
        return None
    n_in, R, t, mask2 = cv2.recoverPose(E, na, nb, np.eye(3), mask=mask.copy())
    if n_in < 12:
        return None
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = np.hstack([R, t])
    Xh = cv2.triangulatePoints(P1, P2, na.T, nb.T)
    X = (Xh[:3] / Xh[3]).T.reshape(-1, ua.shape[1], 3)
    lengths = np.linalg.norm(X[:, -1] - X[:, 0], axis=1)
    good = mask2.ravel().reshape(-1, ua.shape[1]).all(axis=1) & np.isfinite(lengths) & (lengths > 0)
    if good.sum() < 4:
        return None
    scale = wand_length_mm / np.median(lengths[good])
    return PairPose(a, b, R, t.ravel() * scale, int(n_in), int(common.size))


def initial_rig(obs: WandObservations, cams: list[Camera], wand_length_mm: float, *,
                max_frames: int = 600) -> CameraRig:
    """Chain pairwise poses over the maximum spanning tree of the camera graph.

    Raises CalibrationError naming cameras that never saw the wand, or the disconnected groups.
    """
    n = len(cams)
    seen = np.bincount(obs.camera, minlength=n)
    never = [cams[i].id for i in range(n) if seen[i] < 8]
    if never:
        raise CalibrationError(
            f"cameras {never} saw the whole wand in fewer than 8 frames; wave the wand through "
            "their field of view (all markers visible) and record the wand take again")
    poses: dict[tuple[int, int], PairPose] = {}
    weight = np.zeros((n, n))
    for a in range(n):
        for b in range(a + 1, n):
            p = pair_pose(obs, cams, a, b, wand_length_mm, max_frames=max_frames)
            if p is not None:
                poses[(a, b)] = p
                weight[a, b] = weight[b, a] = p.inliers
    n_comp, comp = connected_components(csr_matrix(weight > 0), directed=False)
    if n_comp > 1:
        groups = [[cams[i].id for i in range(n) if comp[i] == k] for k in range(n_comp)]
        raise CalibrationError(
            f"the cameras form {n_comp} groups that never saw the wand at the same time: "
            f"{groups}; these cameras could not be paired. Wave the wand where the groups' "
            "fields of view overlap")
    tree = minimum_spanning_tree(csr_matrix(np.where(weight > 0, 1.0 / (weight + 1.0), 0.0)))
    tree = ((tree + tree.T) > 0).astype(float)
    root = int(np.argmax(seen))
    order, pred = breadth_first_order(tree, root, directed=False)
    R = {root: np.eye(3)}
    t = {root: np.zeros(3)}
    for node in order[1:]:
        parent = int(pred[node])
        if (parent, node) in poses:
            p = poses[(parent, node)]
            R_rel, t_rel = p.R, p.t
        else:
            p = poses[(node, parent)]
            R_rel, t_rel = p.R.T, -p.R.T @ p.t
        R[node] = R_rel @ R[parent]
        t[node] = R_rel @ t[parent] + t_rel
    out = []
    # re-express in the first camera's frame: X0 = R[0] X + t[0]
    R0, t0 = R[0], t[0]
    for i, c in enumerate(cams):
        Ri = R[i] @ R0.T
        u, _, vt = np.linalg.svd(Ri)
        Ri = u @ vt
        out.append(Camera(id=c.id, width=c.width, height=c.height, K=c.K, dist=c.dist,
                          R=Ri, t=t[i] - Ri @ t0))
    return CameraRig(tuple(out))
