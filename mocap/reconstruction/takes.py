"""Takes to labeled trajectories: the reconstruction stage's typed results.

``reconstruct_take`` turns one raw take (its blob table) into a :class:`TakeReconstruction`
(labeled trajectories, counts, capture statistics for the audit and, on request, each blob's
role for the recording); ``labeled_take`` does the same for a labeled 3D take. Both are pure:
the run's stages (:mod:`mocap.workflows.run.stages`) read the files and run takes in parallel,
the composer (:mod:`mocap.workflows.run.pipeline`) writes and caches the results.
:class:`Reconstruction` gathers a session's takes.

Shapes: ``n_frames`` (frames of the take), ``n_markers`` (the session's markers),
``n_cameras`` (the rig's cameras), ``n_blobs`` (rows of the take's blob table). Units: mm, px.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Iterator, Mapping

import numpy as np
import pandas as pd

from mocap.reconstruction.labeling import LabeledTake, MarkerSet, TakeStats
from mocap.reconstruction.settings import LabelSettings, ReconstructionSettings
from mocap.core.display import Summarised, Summary


def _readonly(*arrays):
    for a in arrays:
        if isinstance(a, np.ndarray):
            a.flags.writeable = False


@dataclass(frozen=True)
class CaptureCounts:
    """What the cameras saw, summed over takes (the audit's input).

    marker_frames : (n_markers,) frames in which each marker was reconstructed; frames : int,
    frames of the takes; gaps : (n_markers,) runs of missing frames; longest_gap : (n_markers,)
    longest run; camera_blobs : (n_cameras,) blobs per camera; camera_labeled_blobs :
    (n_cameras,) blobs that ended in a labeled marker; views : (n_cameras, n_markers) frames in
    which each camera contributed to each marker. The camera fields are None for 3D input.
    """

    marker_frames: np.ndarray
    frames: int
    gaps: np.ndarray
    longest_gap: np.ndarray
    camera_blobs: np.ndarray | None = None
    camera_labeled_blobs: np.ndarray | None = None
    views: np.ndarray | None = None

    def __post_init__(self):
        _readonly(self.marker_frames, self.gaps, self.longest_gap, self.camera_blobs,
                  self.camera_labeled_blobs, self.views)

    @classmethod
    def of_take(cls, missing: np.ndarray, camera_blobs=None, camera_labeled_blobs=None,
                views=None) -> "CaptureCounts":
        """From a take's (n_frames, n_markers) ``missing`` mask (and its camera counts)."""
        return cls((~missing).sum(axis=0), int(missing.shape[0]), gap_counts(missing),
                   longest_gaps(missing), camera_blobs, camera_labeled_blobs, views)

    def __add__(self, other: "CaptureCounts") -> "CaptureCounts":
        def add(a, b):
            return None if a is None or b is None else a + b

        return CaptureCounts(self.marker_frames + other.marker_frames, self.frames + other.frames,
                             self.gaps + other.gaps, np.maximum(self.longest_gap, other.longest_gap),
                             add(self.camera_blobs, other.camera_blobs),
                             add(self.camera_labeled_blobs, other.camera_labeled_blobs),
                             add(self.views, other.views))


@dataclass(frozen=True)
class BlobRoles:
    """Each blob of a take and what became of it (for the recording): frame, camera (index
    into the rig), x, y (px), all (n_blobs,); role (n_blobs,) int8: 0 in a labeled marker, 1 in
    a 3D point left unlabeled, 2 in no point (a ghost)."""

    frame: np.ndarray
    camera: np.ndarray
    x: np.ndarray
    y: np.ndarray
    role: np.ndarray


@dataclass(frozen=True)
class TakeReconstruction:
    """One take reconstructed: its labeled trajectories, their capture counts and (raw takes
    kept for the recording) its blobs' roles."""

    name: str
    labeled: LabeledTake
    capture: CaptureCounts
    roles: BlobRoles | None = None


class LazyTakes(Mapping):
    """Take name -> LabeledTake, each made by its loader on first access and then kept (a
    reused run reads a take's trajectories back only when something asks for them). Safe to
    read from several threads (a run's recording is written beside its trials): each take is
    loaded once, under a lock of its own, so threads reading different takes do not wait on
    each other."""

    def __init__(self, loaders: Mapping[str, Callable[[], LabeledTake]]):
        import threading

        self._loaders = dict(loaders)
        self._loaded: dict[str, LabeledTake] = {}
        self._locks = {name: threading.Lock() for name in self._loaders}

    def __getitem__(self, name: str) -> LabeledTake:
        take = self._loaded.get(name)
        if take is not None:
            return take
        with self._locks[name]:  # KeyError for a name with no loader, as a mapping should
            if name not in self._loaded:
                self._loaded[name] = self._loaders[name]()
            return self._loaded[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._loaders)

    def __len__(self) -> int:
        return len(self._loaders)


@dataclass(frozen=True, repr=False)
class Reconstruction(Summarised):
    """A session's face takes (rest, response, motion) as labeled trajectories.

    markers : the session's markers; takes : take name -> LabeledTake, in session order (a
    ``LazyTakes`` when read back from an earlier run); stats : take name -> its counts;
    capture : counts summed over the takes; noise_per_marker_mm : (n_markers, 3) per-axis sd
    over the rest take (None without one), noise_floor_mm its mean; blob_roles : take -> roles,
    for the takes the recording shows.
    """

    markers: MarkerSet
    takes: Mapping[str, LabeledTake]
    stats: Mapping[str, TakeStats]
    capture: CaptureCounts
    noise_floor_mm: float | None
    noise_per_marker_mm: np.ndarray | None
    blob_roles: Mapping[str, BlobRoles]

    @property
    def labeled_points(self) -> int:
        return int(sum(s.labeled_points for s in self.stats.values()))

    def _summary(self) -> Summary:
        import pandas as pd

        rows = [{"take": n, "labeled_points": s.labeled_points,
                 "missing_marker_frames": s.missing_marker_frames}
                for n, s in self.stats.items()]
        floor = (f"{self.noise_floor_mm:.3g} mm" if self.noise_floor_mm is not None
                 else "no rest take")
        return Summary(f"Reconstruction: {len(self.markers.names)} markers, {len(self.takes)} "
                       "face takes",
                       (("labeled points", f"{self.labeled_points:,}"), ("noise floor", floor)),
                       pd.DataFrame(rows), "takes",
                       "attributes: .takes[name].X (n_frames, n_markers, 3) mm .markers .stats")


def gap_counts(missing: np.ndarray) -> np.ndarray:
    """(n_markers,) runs of missing frames per marker; missing (n_frames, n_markers) bool."""
    starts = missing[1:] & ~missing[:-1]
    return starts.sum(axis=0) + missing[0]


def longest_gaps(missing: np.ndarray) -> np.ndarray:
    """(n_markers,) longest run of missing frames per marker (vectorised run lengths)."""
    n = missing.shape[0]
    # the run length at a missing frame is its distance to the last frame that was seen
    idx = np.where(~missing, np.arange(n)[:, None], -1)
    run_len = np.arange(n)[:, None] - np.maximum.accumulate(idx, axis=0)
    return np.where(missing, run_len, 0).max(axis=0)


def take_frame_count(df: pd.DataFrame) -> int:
    return int(df["frame"].max()) + 1


def reconstruct_take(name: str, blobs: pd.DataFrame, rig, quality: dict, markers: MarkerSet, *,
                     reconstruction: ReconstructionSettings = ReconstructionSettings(),
                     labels: LabelSettings = LabelSettings(), fill_gaps_frames: int = 0,
                     record: bool = False) -> TakeReconstruction:
    """One raw take's blobs (frame, camera, x, y) to labeled trajectories.

    Independent of every other take once the rig is calibrated and the markers are known (the
    composer runs takes in parallel). ``record``: keep each blob's role for the recording.
    """
    # the compiled correspondence search is imported here: the result types above load without it
    from mocap.reconstruction.correspondence import blob_camera_index, reconstruct_points
    from mocap.reconstruction.labeling import label_take

    n_frames = take_frame_count(blobs)
    cam_idx = blob_camera_index(blobs["camera"], rig.ids)
    pts = reconstruct_points(blobs, rig, quality, reconstruction, cam=cam_idx)
    lab = label_take(pts, markers, n_frames, labels, fill_gaps_frames, n_blobs=len(blobs))
    missing = np.isnan(lab.X[..., 0])
    capture = CaptureCounts.of_take(
        missing, np.bincount(cam_idx, minlength=len(rig)),
        np.bincount(cam_idx[lab.blob_marker >= 0], minlength=len(rig)), lab.views)
    roles = None
    if record:
        role = np.full(len(blobs), 2, np.int8)  # in no 3D point: a ghost
        role[pts.blob[pts.blob >= 0]] = 1  # in a point that got no marker
        role[lab.blob_marker >= 0] = 0  # labeled
        roles = BlobRoles(blobs["frame"].to_numpy(), cam_idx, blobs["x"].to_numpy(),
                          blobs["y"].to_numpy(), role)
    stats = replace(lab.stats, blobs=int(len(blobs)), matched_blobs=int((pts.blob >= 0).sum()))
    # the per-blob labels served the counts and roles above; the take keeps its trajectories
    return TakeReconstruction(name, replace(lab, stats=stats, blob_marker=None), capture, roles)


def labeled_take(name: str, lab: LabeledTake) -> TakeReconstruction:
    """A labeled 3D take (``mocap.reconstruction.labeled_input.dense_from_3d``) as a take result."""
    return TakeReconstruction(name, lab, CaptureCounts.of_take(np.isnan(lab.X[..., 0])))


def labeled_take_from_table(table, names, stats: TakeStats, views: np.ndarray | None) -> LabeledTake:
    """The inverse of :func:`mocap.reconstruction.labeling.trajectories_frame`: a trajectories
    table (a ``pyarrow.Table``, frame-major, the markers in ``names`` order in every frame) back
    to a LabeledTake, without going through pandas."""
    M = len(names)
    marker = table.column("marker").combine_chunks()
    if hasattr(marker, "dictionary"):  # read with read_dictionary=["marker"]: compare codes
        codes = marker.indices.to_numpy(zero_copy_only=False)
        labels = np.asarray(marker.dictionary.to_pylist(), dtype=object)
    else:
        labels, codes = np.unique(np.asarray(marker.to_pylist(), dtype=object), return_inverse=True)
    n = len(codes) // max(M, 1)
    if M == 0 or len(codes) != n * M or not np.array_equal(labels[codes[:M]].astype(str),
                                                           np.asarray(names, dtype=str)) \
            or not (codes.reshape(n, M) == codes[:M]).all():
        raise ValueError(f"expected a trajectories table of the markers {list(names)[:5]}... in "
                         f"every frame, got {len(codes)} rows")

    def col(name, dtype):
        return table.column(name).to_numpy().astype(dtype, copy=False).reshape(n, M)

    X = np.stack([col(c, np.float64) for c in "xyz"], axis=-1)
    return LabeledTake(X, col("n_cameras", np.int64), col("residual_px", np.float64),
                       col("interpolated", bool), stats, views)
