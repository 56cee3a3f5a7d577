"""Cross-camera correspondence of unlabeled blobs and multi-view triangulation.

All frames of a take are processed at once by compiled kernels
(:mod:`mocap.reconstruction.correspondence_kernel`; the only Python loop runs over camera pairs).
For camera pairs in order of decreasing baseline:

1. every blob's ray defines an epipolar plane through the pair's baseline; its angle about the
   baseline is the same in both cameras for a true match, so candidates come from a sorted
   search in (frame, angle), then the symmetric epipolar distance (px, undistorted rays) is
   checked against the pair's gate;
2. each candidate pair is triangulated and projected into every other camera, where the nearest
   blob of the same frame within that camera's gate, when unused, counts as support;
3. candidates seen by at least 3 cameras are kept, one per blob (the most supported, then the
   smallest residual, wins), and their blobs leave the pool.

A second pass over the pairs then keeps, among the blobs left, the bare 2-view candidates whose
epipolar match is unique (each of their blobs has no other candidate): a marker that only two
cameras see (a shadowed nose bridge) is reconstructed with ``n_cameras`` 2 and its residual,
after 3+-view points have claimed their blobs. Which points the analyses use is not decided
here: :func:`mocap.reconstruction.camera_count.usable_samples` masks the samples seen by fewer than
``ReconstructionSettings.min_cameras`` cameras before trials are averaged.

Accepted points are triangulated from all their views (linear, then Gauss-Newton); views whose
reprojection error exceeds their camera's gate are dropped and the point re-solved. Gates are per
camera: ``max(gate_min_px, gate_sigmas x the calibration's reprojection RMS)``, so a noisy camera
gets a wider gate instead of losing its blobs.

:mod:`mocap.reconstruction.reference` keeps the former NumPy implementation (k-d trees, sorted
searches) the tests compare this one against.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc

from mocap.calib.camera import CameraRig, camera_index
from mocap.calib.triangulation_kernel import triangulate_normalized
from mocap.reconstruction import correspondence_kernel as kern
from mocap.reconstruction.settings import ReconstructionSettings  # noqa: F401  (its home before)

_UNDISTORT_ITERATIONS = 20  # as mocap.calib.camera.undistort_normalized


@dataclass(frozen=True)
class Points3D:
    """Unlabeled 3D points of a take.

    frame : (n,) int; X : (n, 3) mm; n_cameras : (n,) int; residual_px : (n,) RMS reprojection
    error over its views; blob : (n, n_cameras_rig) int index of the blob (row of the take's blob
    table) each camera contributed, -1 for none.
    """

    frame: np.ndarray
    X: np.ndarray
    n_cameras: np.ndarray
    residual_px: np.ndarray
    blob: np.ndarray

    def __len__(self) -> int:
        return int(self.frame.size)


def blob_camera_index(camera: pd.Series, camera_ids) -> np.ndarray:
    """(n,) int index into ``camera_ids`` of every blob's camera id, -1 for ids not in the list.

    As :func:`mocap.calib.camera.camera_index`: through the categories of a categorical column
    (what ``Session.read_take`` returns), in one pyarrow pass over a string column (~4 x faster
    than the categorical route on a paper take's 400 k blobs).
    """
    if isinstance(getattr(camera, "dtype", None), pd.CategoricalDtype):
        return camera_index(camera, camera_ids)
    arr = pa.array(camera, from_pandas=True)
    if not (pa.types.is_string(arr.type) or pa.types.is_large_string(arr.type)):
        return camera_index(camera, camera_ids)
    ids = pa.array([str(c) for c in camera_ids], type=arr.type)
    idx = pc.index_in(arr, value_set=ids).fill_null(-1)
    return np.asarray(idx.to_numpy(zero_copy_only=False), dtype=np.int64)


@dataclass(frozen=True)
class BlobTable:
    """A take's blobs with camera indices, normalised coordinates and world rays."""

    frame: np.ndarray  # (n,)
    cam: np.ndarray  # (n,)
    uv: np.ndarray  # (n, 2) px
    xn: np.ndarray  # (n, 2) undistorted normalised
    ray: np.ndarray  # (n, 3) unit, world

    @classmethod
    def from_frame(cls, blobs: pd.DataFrame, rig: CameraRig,
                   cam: np.ndarray | None = None) -> "BlobTable":
        """``cam`` (n,) int: :func:`blob_camera_index` of the blobs when the caller has it."""
        if cam is None:
            cam = blob_camera_index(blobs["camera"], rig.ids)
        if np.any(cam < 0):
            bad = sorted(set(blobs["camera"][cam < 0]))
            raise ValueError(f"blobs from cameras {bad} that the calibration does not have {rig.ids}")
        uv = np.empty((len(blobs), 2))
        uv[:, 0] = blobs["x"].to_numpy(np.float64)
        uv[:, 1] = blobs["y"].to_numpy(np.float64)
        rp = RigArrays.of(rig)
        xn, ray = kern.normalize_blobs(uv, cam, rp.K, rp.dist, rp.R, _UNDISTORT_ITERATIONS)
        return cls(blobs["frame"].to_numpy(np.int64), cam, uv, xn, ray)


@dataclass(frozen=True)
class RigArrays:
    """A rig packed for the kernels: K (C, 3, 3) px, dist (C, 5), R (C, 3, 3), t (C, 3) mm,
    Rt (C, 3, 4), focal (C,) px, centre (C, 3) mm."""

    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    Rt: np.ndarray
    focal: np.ndarray
    centre: np.ndarray

    @classmethod
    def of(cls, rig: CameraRig) -> "RigArrays":
        R = np.stack([c.R for c in rig]).astype(np.float64)
        t = np.stack([c.t for c in rig]).astype(np.float64)
        return cls(np.stack([c.K for c in rig]).astype(np.float64),
                   np.stack([c.dist for c in rig]).astype(np.float64), R, t,
                   np.ascontiguousarray(np.concatenate([R, t[:, :, None]], axis=2)),
                   np.array([c.focal_px for c in rig], np.float64),
                   np.stack([c.center for c in rig]).astype(np.float64))


def camera_gates(rig: CameraRig, quality: dict | None, settings: ReconstructionSettings) -> np.ndarray:
    """Per-camera matching gate, px."""
    rms = (quality or {}).get("reprojection_rms_px", {})
    return np.array([max(settings.gate_min_px, settings.gate_sigmas * float(rms.get(c.id, 0.1)))
                     for c in rig])


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """u x v of two (3,) vectors (np.cross's axis handling costs ~40 us a call)."""
    return np.array([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2],
                     u[0] * v[1] - u[1] * v[0]])


@dataclass(frozen=True)
class PairGeometry:
    """Epipolar geometry of cameras (a, b): unit baseline ``bn`` with ``e1``, ``e2`` completing an
    orthonormal basis (world), and the essential matrix ``E`` (3, 3) mapping a's normalised
    points to epipolar lines in b."""

    bn: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    E: np.ndarray

    @classmethod
    def of(cls, rig: CameraRig, a: int, b: int) -> "PairGeometry":
        ca, cb = rig[a], rig[b]
        base = cb.center - ca.center
        bn = base / np.linalg.norm(base)
        e1 = _cross(bn, np.array([0.0, 0.0, 1.0] if abs(bn[2]) < 0.9 else [1.0, 0.0, 0.0]))
        e1 /= np.linalg.norm(e1)
        e2 = _cross(bn, e1)
        R_ab = cb.R @ ca.R.T
        t_ab = cb.t - R_ab @ ca.t
        tx = np.array([[0, -t_ab[2], t_ab[1]], [t_ab[2], 0, -t_ab[0]], [-t_ab[1], t_ab[0], 0]])
        return cls(bn, e1, e2, np.ascontiguousarray(tx @ R_ab))


@dataclass(frozen=True)
class BlobIndex:
    """A take's blobs grouped by (camera, frame) for the kernels (see
    :func:`mocap.reconstruction.correspondence_kernel.bucket_index`): fidx (n,) frame - first frame,
    n_frames, ptr (C * n_frames + 1,), order (n,) and order_x (n,) blob indices, uv_x (n, 2) px
    the image points in ``order_x`` order; cells (C * n_frames, N_CELLS + 1), x0 and scale
    (C * n_frames,) the buckets' column bands."""

    fidx: np.ndarray
    n_frames: int
    ptr: np.ndarray
    order: np.ndarray
    order_x: np.ndarray
    uv_x: np.ndarray
    cells: np.ndarray
    x0: np.ndarray
    scale: np.ndarray

    @classmethod
    def of(cls, bt: BlobTable, n_cams: int) -> "BlobIndex":
        if bt.frame.size == 0:
            z = np.zeros(0, np.int64)
            return cls(z, 0, np.zeros(1, np.int64), z, z, np.zeros((0, 2)),
                       np.zeros((0, kern.N_CELLS + 1), np.int64), np.zeros(0), np.zeros(0))
        first = int(bt.frame.min())
        fidx = bt.frame - first
        n_frames = int(fidx.max()) + 1
        return cls(fidx, n_frames, *kern.bucket_index(bt.cam, fidx, bt.uv, n_cams, n_frames))


def _empty_points(C: int) -> Points3D:
    return Points3D(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64),
                    np.zeros(0), np.zeros((0, C), np.int64))


def reconstruct_points(blobs: pd.DataFrame, rig: CameraRig, quality: dict | None = None,
                       settings: ReconstructionSettings = ReconstructionSettings(), *,
                       cam: np.ndarray | None = None) -> Points3D:
    """Match blobs across cameras and triangulate every frame of a take.

    Parameters
    ----------
    blobs : a take's blobs (frame, camera, x, y); row order defines blob indices.
    rig : calibrated cameras (the same ids as the blobs' cameras).
    quality : the calibration's quality report (per-camera reprojection RMS sets the gates).
    cam : (n,) int, ``blob_camera_index(blobs["camera"], rig.ids)`` when the caller needs it
        too (a paper take's 400 k camera ids cost ~7 ms to index).
    """
    bt = BlobTable.from_frame(blobs, rig, cam)
    C = len(rig)
    rp = RigArrays.of(rig)
    gates = camera_gates(rig, quality, settings).astype(np.float64)
    index = BlobIndex.of(bt, C)
    n_blobs = bt.frame.size
    used = np.zeros(n_blobs, np.bool_)
    best = np.full(n_blobs, -1, np.int64)  # scratch of one_point_per_blob
    pairs = sorted(combinations(range(C), 2),
                   key=lambda p: -np.linalg.norm(rp.centre[p[0]] - rp.centre[p[1]]))
    accepted: list[np.ndarray] = []
    geometry: dict[tuple[int, int], PairGeometry] = {}
    # the blobs the candidate search walks: dropped from the buckets once most are used
    pool = (index.ptr, index.order)
    n_pool = n_unused = n_blobs
    # 3+-view candidates first, over every pair; then bare epipolar pairs among the blobs left
    for min_cams in (3, 2):
        for a, b in pairs:
            if n_unused < n_pool // 2:
                pool = kern.compact_buckets(*pool, used)
                n_pool = n_unused
            if (a, b) not in geometry:
                geometry[a, b] = PairGeometry.of(rig, a, b)
            views = _pair_points(bt, geometry[a, b], rp, index, pool, a, b, gates, used,
                                 settings.max_depth_mm, min_cams)
            if views.shape[0] == 0:
                continue
            views = _one_point_per_blob(views, bt, rp, best)
            if views.shape[0] == 0:
                continue
            accepted.append(views)
            kern.mark_used(views, used)
            n_unused -= int(np.count_nonzero(views >= 0))  # accepted views are all unused blobs
    if not accepted:
        return _empty_points(C)
    return _final_triangulation(np.concatenate(accepted), bt, rp, gates, 2)


def _pair_points(bt: BlobTable, geo: PairGeometry, rp: RigArrays, index: BlobIndex,
                 pool: tuple[np.ndarray, np.ndarray], a: int, b: int, gates: np.ndarray,
                 used: np.ndarray, max_depth_mm: float, min_cams: int) -> np.ndarray:
    """Candidate rows (m, C) of blob indices (-1: no view) from the unused blobs of cameras
    (a, b), each with the support ``min_cams`` asks for, in lexicographic row order.

    ``pool`` (ptr, order): the (camera, frame) buckets of at least every unused blob."""
    C = rp.K.shape[0]
    gate = max(gates[a], gates[b])
    dth = 40.0 * gate / min(rp.focal[a], rp.focal[b])  # generous window in angle, rad
    pa, pb = kern.pair_candidates(a, b, pool[0], pool[1], index.n_frames, bt.frame, bt.xn,
                                  bt.ray, used, geo.bn, geo.e1, geo.e2, geo.E, rp.focal[a],
                                  rp.focal[b], gate, dth)
    if pa.size == 0:
        return np.zeros((0, C), np.int64)
    ab = [a, b]
    X = triangulate_normalized(np.ascontiguousarray(rp.Rt[ab]), rp.focal[ab],
                               kern.pair_observations(pa, pb, bt.xn), 0)  # the pair's views only
    unique_pair = np.zeros(pa.size, np.bool_)
    if min_cams == 2:  # a bare epipolar pair is trusted only when it is its blobs' only candidate
        ua, na = np.unique(pa, return_counts=True)
        ub, nb = np.unique(pb, return_counts=True)
        unique_pair = (na[np.searchsorted(ua, pa)] == 1) & (nb[np.searchsorted(ub, pb)] == 1)
    views, keep = kern.verify_candidates(X, pa, pb, a, b, index.fidx, index.cells, index.x0,
                                         index.scale, index.order_x, index.uv_x, index.n_frames,
                                         used, rp.K, rp.dist, rp.R, rp.t,
                                         gates, float(max_depth_mm), min_cams, unique_pair)
    views = views[keep]
    # rows are distinct (one per blob pair (a, b)): this is np.unique(views, axis=0)'s order
    return views[kern.lex_order(views)]


def _solve_views(views: np.ndarray, bt: BlobTable, rp: RigArrays) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate rows views (m, C) from all their views: X (m, 3) mm, err (C, m) px."""
    X = triangulate_normalized(rp.Rt, rp.focal, kern.gather_observations(views, bt.xn), 1)
    return X, kern.reprojection_errors(X, views, bt.uv, rp.K, rp.dist, rp.R, rp.t)


def _one_point_per_blob(views: np.ndarray, bt: BlobTable, rp: RigArrays,
                        best: np.ndarray) -> np.ndarray:
    """Keep, for every blob, only its best candidate (most views, then smallest residual).

    Only rows sharing a blob with another row need a score (a row alone on its blobs wins them
    whatever its score), so only those are solved.
    """
    contested = kern.contested_rows(views, best)
    score = np.zeros(views.shape[0])
    if contested.any():
        _, err = _solve_views(views[contested], bt, rp)
        score[contested] = kern.candidate_scores(views[contested], err)
    return views[kern.one_point_per_blob(views, score, best)]


def _final_triangulation(views: np.ndarray, bt: BlobTable, rp: RigArrays, gates: np.ndarray,
                         min_cams: int) -> Points3D:
    """Points of the accepted rows views (m, C): solved from all views, re-solved without the
    views beyond their camera's gate, kept with ``min_cams`` (2) views or more; sorted by frame."""
    X, err = _solve_views(views, bt, rp)
    views, changed = kern.drop_bad_views(views, err, gates)
    if changed.any():
        X[changed], err[:, changed] = _solve_views(views[changed], bt, rp)
    n_cam, resid, frame = kern.point_summary(views, err, bt.frame)
    rows = kern.frame_order(frame, n_cam >= min_cams)
    return Points3D(frame[rows], X[rows], n_cam[rows], resid[rows], views[rows])
