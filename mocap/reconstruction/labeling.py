"""Marker identities: found on the rest take, followed frame to frame in every take.

Linking: each 3D point is joined to its mutual nearest neighbour in the next frame when closer
than ``link_gate_mm`` (a face marker moves well under 1 mm per frame at 120 fps, markers sit
about 8 mm apart); points left without a successor are joined across gaps of up to
``max_gap_frames`` frames the same way. The chains (connected components of the link graph) are
tracklets. Both steps run over all frames in one compiled call
(:mod:`mocap.reconstruction.labeling_kernel`).

Assignment: tracklets are taken in order of their first frame; those starting together are
assigned to the free markers (whose previous tracklet has ended) by optimal assignment
(Hungarian, ``scipy.optimize.linear_sum_assignment``) on the distance between the tracklet's first
position and the marker's last known position (its rest position before it is first seen), within
``start_gate_mm``. Unassigned tracklets (ghost points, fragments) are left out and counted.

Marker naming (``identify_markers``): the rest take's tracklets present in at least
``min_presence`` of its frames are the markers, at their median positions. With a ``markers.csv``
template they take the template's names by optimal assignment within ``template_gate_mm``
(template markers with no match are reported missing; extra markers are named ``X001``...).
Without a template they are named ``M001``, ``M002``... in reading order: by world height (y,
descending, rounded to 0.5 mm) then x ascending.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from mocap.reconstruction.settings import LabelSettings
from mocap.core.display import Summarised, Summary

if TYPE_CHECKING:
    from mocap.reconstruction.correspondence import Points3D

# The compiled kernels and scipy's solvers are imported by the functions that use them, so that
# the result types below load without them (a reused run reads them back from its cache).


@dataclass(frozen=True)
class MarkerSet:
    """The session's markers: names and rest positions (n_markers, 3) mm."""

    names: tuple[str, ...]
    rest_mm: np.ndarray
    missing_from_template: tuple[str, ...] = ()


@dataclass(frozen=True)
class TakeStats:
    """Counts of one take's reconstruction.

    points: 3D points (raw takes) or reconstructed marker-frames (labeled 3D input);
    labeled_points: those given a marker; unlabeled_points: ghosts and fragments left out;
    tracklets: chains of linked points; missing_marker_frames: (frame, marker) pairs not
    reconstructed; interpolated_marker_frames: gap samples filled (``fill_gaps_frames``);
    blobs: the take's 2D blobs; matched_blobs: those in a 3D point.
    """

    points: int
    labeled_points: int
    unlabeled_points: int = 0
    tracklets: int = 0
    missing_marker_frames: int = 0
    interpolated_marker_frames: int = 0
    blobs: int = 0
    matched_blobs: int = 0


@dataclass(frozen=True, repr=False)
class LabeledTake(Summarised):
    """Dense labeled trajectories of one take.

    X : (n_frames, n_markers, 3) mm, NaN where not reconstructed; n_cameras : (n_frames,
    n_markers) int (0 where missing); residual_px : (n_frames, n_markers) (NaN where missing);
    interpolated : (n_frames, n_markers) bool, gap samples filled by interpolation;
    views : (n_cameras_rig, n_markers) int, frames in which each camera contributed to each
    marker (None for 3D input); blob_marker : (n_blobs,) int, the marker each blob of the take was
    labeled as, -1 for blobs in no labeled point (None for 3D input).
    """

    X: np.ndarray
    n_cameras: np.ndarray
    residual_px: np.ndarray
    interpolated: np.ndarray
    stats: TakeStats
    views: np.ndarray | None = None
    blob_marker: np.ndarray | None = None

    def _summary(self) -> Summary:
        n_frames, n_markers = self.X.shape[:2]
        seen = np.isfinite(self.X[..., 0])
        return Summary(f"LabeledTake: {n_frames} frames x {n_markers} markers",
                       (("seen", f"{seen.mean():.1%} of marker-frames"),
                        ("stats", f"{self.stats.labeled_points:,} labeled points, "
                                  f"{self.stats.missing_marker_frames:,} marker-frames missing")),
                       more="attributes: .X (n_frames, n_markers, 3) mm .n_cameras .residual_px "
                            ".interpolated .stats")


def link_tracklets(frame: np.ndarray, X: np.ndarray, settings: LabelSettings = LabelSettings()) -> np.ndarray:
    """Tracklet id (n,) of each point, by mutual nearest-neighbour links between frames.

    frame (n,) int; X (n, 3) mm. Tracklets are numbered in order of their lowest point index.
    """
    from mocap.reconstruction.labeling_kernel import chain_labels, link_chains

    n = frame.size
    if n == 0:
        return np.zeros(0, np.int64)
    first = int(frame.min())
    fidx = np.ascontiguousarray(frame - first, dtype=np.int64)
    nxt, prv = link_chains(fidx, np.ascontiguousarray(X, dtype=np.float64), int(fidx.max()) + 1,
                           float(settings.link_gate_mm), int(settings.max_gap_frames))
    return chain_labels(nxt, prv)


def _tracklet_table(frame, X, comp):
    order = np.lexsort((frame, comp))
    c = comp[order]
    starts = np.flatnonzero(np.r_[True, c[1:] != c[:-1]])
    ends = np.r_[starts[1:], c.size] - 1
    return order, starts, ends


def identify_markers(points: Points3D, n_frames: int, template: pd.DataFrame | None = None,
                     settings: LabelSettings = LabelSettings()) -> MarkerSet:
    """The markers of a session from its rest take (see the module docstring)."""
    from scipy.optimize import linear_sum_assignment
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    comp = link_tracklets(points.frame, points.X, settings)
    order, starts, ends = _tracklet_table(points.frame, points.X, comp)
    # merge tracklets of one still marker split by gaps: cluster their medians
    med = np.array([np.median(points.X[order[s:e + 1]], axis=0) for s, e in zip(starts, ends)])
    size = ends - starts + 1
    tree = cKDTree(med)
    pairs = tree.query_pairs(r=1.0, output_type="ndarray")
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(med),) * 2)
    _, cluster = connected_components(g, directed=False)
    presence = np.bincount(cluster, weights=size)
    keep = np.flatnonzero(presence >= settings.min_presence * n_frames)
    rest = np.array([np.average(med[cluster == k], axis=0, weights=size[cluster == k]) for k in keep])
    rest = rest.reshape(-1, 3)
    if template is not None and len(template):
        tpos = template[["x", "y", "z"]].to_numpy(float)
        tnames = template["name"].astype(str).to_numpy()
        cost = np.linalg.norm(tpos[:, None] - rest[None], axis=-1)
        ti, ri = linear_sum_assignment(np.where(cost < settings.template_gate_mm, cost, 1e6))
        good = cost[ti, ri] < settings.template_gate_mm
        ti, ri = ti[good], ri[good]
        names = [None] * len(rest)
        for a, b in zip(ti, ri):
            names[b] = tnames[a]
        extra = 1
        for k in range(len(names)):
            if names[k] is None:
                names[k] = f"X{extra:03d}"
                extra += 1
        missing = tuple(sorted(set(tnames) - set(tnames[ti])))
        # template order for the named ones, extras after
        rank = {n: i for i, n in enumerate(tnames)}
        o = sorted(range(len(names)), key=lambda k: (rank.get(names[k], len(rank) + k)))
        return MarkerSet(tuple(names[k] for k in o), rest[o], missing)
    o = np.lexsort((rest[:, 0], -np.round(rest[:, 1] * 2.0) / 2.0))
    return MarkerSet(tuple(f"M{k + 1:03d}" for k in range(len(o))), rest[o])


def label_take(points: Points3D, markers: MarkerSet, n_frames: int,
               settings: LabelSettings = LabelSettings(), fill_gaps_frames: int = 0,
               n_blobs: int | None = None) -> LabeledTake:
    """Follow the markers through a take (see the module docstring).

    ``n_blobs`` (the take's blob count) enables ``blob_marker``, each blob's marker label.
    """
    from scipy.optimize import linear_sum_assignment

    M = len(markers.names)
    X = np.full((n_frames, M, 3), np.nan)
    ncam = np.zeros((n_frames, M), np.int64)
    resid = np.full((n_frames, M), np.nan)
    comp = link_tracklets(points.frame, points.X, settings)
    order, starts, ends = _tracklet_table(points.frame, points.X, comp)
    f_sorted = points.frame[order]
    first_frame = f_sorted[starts]
    last_frame = f_sorted[ends]
    first_pos = points.X[order[starts]]
    last_known = markers.rest_mm.copy()
    busy_until = np.full(M, -1)
    assigned = np.full(starts.size, -1)
    for s in np.unique(first_frame):
        tk = np.flatnonzero(first_frame == s)
        free = np.flatnonzero(busy_until < s)
        if free.size == 0:
            continue
        cost = np.linalg.norm(first_pos[tk][:, None] - last_known[free][None], axis=-1)
        ti, mi = linear_sum_assignment(np.where(cost < settings.start_gate_mm, cost, 1e6))
        ok = cost[ti, mi] < settings.start_gate_mm
        for a, m in zip(tk[ti[ok]], free[mi[ok]]):
            assigned[a] = m
            busy_until[m] = last_frame[a]
            last_known[m] = points.X[order[ends[a]]]
    # scatter every assigned tracklet's points
    lab_of_point = np.full(points.frame.size, -1)
    tr_of_sorted = np.repeat(np.arange(starts.size), ends - starts + 1)
    lab_of_point[order] = assigned[tr_of_sorted]
    sel = lab_of_point >= 0
    fr, mk = points.frame[sel], lab_of_point[sel]
    X[fr, mk] = points.X[sel]
    ncam[fr, mk] = points.n_cameras[sel]
    resid[fr, mk] = points.residual_px[sel]
    interp = np.zeros((n_frames, M), bool)
    if fill_gaps_frames > 0:
        X, interp = fill_gaps(X, fill_gaps_frames)
    stats = TakeStats(
        points=int(points.frame.size),
        labeled_points=int(sel.sum()),
        unlabeled_points=int((~sel).sum()),
        tracklets=int(starts.size),
        missing_marker_frames=int(np.isnan(X[..., 0]).sum()),
        interpolated_marker_frames=int(interp.sum()),
    )
    C = points.blob.shape[1]
    views = np.zeros((C, M), np.int64)
    pb = points.blob[sel]
    for c in range(C):
        views[c] = np.bincount(mk[pb[:, c] >= 0], minlength=M)
    blob_marker = None
    if n_blobs is not None:
        blob_marker = np.full(n_blobs, -1, np.int64)
        has = pb >= 0
        blob_marker[pb[has]] = np.broadcast_to(mk[:, None], pb.shape)[has]
    return LabeledTake(X, ncam, resid, interp, stats, views, blob_marker)


def fill_gaps(X: np.ndarray, max_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Linearly interpolate interior gaps of at most ``max_frames`` frames; return (X, filled)."""
    X = X.copy()
    n_frames, M, _ = X.shape
    missing = np.isnan(X[..., 0])
    filled = np.zeros_like(missing)
    t = np.arange(n_frames)
    for m in np.flatnonzero(missing.any(axis=0) & ~missing.all(axis=0)):
        miss = missing[:, m]
        # run lengths of gaps
        edges = np.diff(np.r_[0, miss.astype(int), 0])
        g0 = np.flatnonzero(edges == 1)
        g1 = np.flatnonzero(edges == -1)
        short = (g1 - g0 <= max_frames) & (g0 > 0) & (g1 < n_frames)
        mask = np.zeros(n_frames, bool)
        for a, b in zip(g0[short], g1[short]):
            mask[a:b] = True
        if mask.any():
            good = ~miss
            for k in range(3):
                X[mask, m, k] = np.interp(t[mask], t[good], X[good, m, k])
            filled[mask, m] = True
    return X, filled


def _trajectory_columns(labeled: LabeledTake, marker) -> dict:
    """docs/outputs.md's columns in order, ``marker`` the (n_frames * M,) marker column given."""
    n_frames, M, _ = labeled.X.shape
    return {
        "frame": np.repeat(np.arange(n_frames, dtype=np.int64), M),
        "marker": marker,
        "x": labeled.X[..., 0].ravel(),
        "y": labeled.X[..., 1].ravel(),
        "z": labeled.X[..., 2].ravel(),
        "n_cameras": labeled.n_cameras.ravel(),
        "residual_px": labeled.residual_px.ravel(),
        "interpolated": labeled.interpolated.ravel(),
    }


def trajectories_frame(labeled: LabeledTake, names) -> pd.DataFrame:
    """Long table per docs/outputs.md: frame, marker, x, y, z, n_cameras, residual_px, interpolated."""
    n_frames = labeled.X.shape[0]
    return pd.DataFrame(_trajectory_columns(labeled, np.tile(np.asarray(names, dtype=object),
                                                             n_frames)))


def trajectories_table(labeled: LabeledTake, names):
    """:func:`trajectories_frame` as an Arrow table, for writing: the marker column decoded from
    a dictionary of the names in Arrow (no per-row Python strings). Read back with pandas it is
    the same frame."""
    import pyarrow as pa

    n_frames, M, _ = labeled.X.shape
    idx = pa.array(np.tile(np.arange(M, dtype=np.int32), n_frames))
    marker = pa.DictionaryArray.from_arrays(idx, pa.array([str(n) for n in names],
                                                          pa.large_string()))
    return pa.table(_trajectory_columns(labeled, marker.cast(pa.large_string())))
