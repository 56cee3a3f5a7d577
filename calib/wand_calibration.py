"""Wand calibration of a camera rig: wand finding, initialisation, bundle adjustment, world frame
and the quality report. ``calibrate_session`` runs it all on a session's ``wand`` and ``ground``
takes.

Frame subsampling: consecutive frames at 120 fps see nearly the same wand pose, so the bundle
adjustment uses at most ``max_frames`` frames, each seen by at least two cameras: first up to
``per_camera`` frames per camera spread evenly over that camera's sightings (a camera that saw
the wand rarely keeps all its frames), then frames spread evenly over the take to fill up.

Outliers (mislabeled or merged blobs): solve with a soft-L1 loss (``f_scale`` 2 px), drop every
sighting whose worst marker residual exceeds ``max(6 sigma_c, 0.6 px)`` (sigma_c estimated
robustly from the median residual of its camera, so a noisy camera is not stripped of its
sightings), re-solve by plain least squares (efficient at Gaussian noise), and repeat the trim
once.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from mocap.calib.bundle import (
    WandProblem,
    _tangent_basis,
    camera_vector,
    rig_from_vectors,
    solve_schur,
)
from mocap.calib.camera import CameraRig
from mocap.calib.initialize import CalibrationError, initial_intrinsics, initial_rig
from mocap.calib.quality import quality_report
from mocap.calib.triangulation import triangulate
from mocap.calib.wand import WandObservations, find_wand
from mocap.calib.world_frame import GroundFit, fit_ground, transform_rig

__all__ = ["CalibrationError", "CalibrationResult", "calibrate", "calibrate_session"]


@dataclass(frozen=True)
class CalibrationResult:
    """A calibrated rig in the world frame, with everything that produced it."""

    rig: CameraRig
    quality: dict
    wand: WandObservations
    used: np.ndarray  # (len(wand),) bool: sightings kept by the final bundle adjustment
    residuals_px: np.ndarray  # (n_used, n_w, 2) final reprojection residuals
    ground: GroundFit | None = None
    timings_s: dict = field(default_factory=dict)
    wand_frames: np.ndarray | None = None  # (n_ba_frames,) frames of the bundle adjustment
    wand_points_mm: np.ndarray | None = None  # (n_ba_frames, n_w, 3) fitted wand, world frame


def select_frames(obs: WandObservations, max_frames: int = 3600, per_camera: int = 120) -> np.ndarray:
    """Frames (sorted) for the bundle adjustment; see the module docstring."""
    frames, n_views = np.unique(obs.frame, return_counts=True)
    multi = frames[n_views >= 2]
    chosen: set[int] = set()
    for c in range(len(obs.camera_ids)):
        fc = np.intersect1d(obs.frame[obs.camera == c], multi)
        if fc.size:
            pick = fc[np.linspace(0, fc.size - 1, min(per_camera, fc.size)).astype(int)]
            chosen.update(pick.tolist())
    remaining = max_frames - len(chosen)
    if remaining > 0 and multi.size:
        pick = multi[np.linspace(0, multi.size - 1, min(remaining, multi.size)).astype(int)]
        chosen.update(pick.tolist())
    return np.array(sorted(chosen), dtype=np.int64)


def _initial_frames(rig: CameraRig, obs: WandObservations, frames: np.ndarray,
                    offsets_rel: np.ndarray):
    """Wand centre and direction per selected frame by triangulation with the initial rig."""
    n_w = offsets_rel.size
    local = np.searchsorted(frames, obs.frame)
    uv = np.full((len(rig), frames.size * n_w, 2), np.nan)
    sel = np.isin(obs.frame, frames)
    rows = (local[sel][:, None] * n_w + np.arange(n_w)[None]).ravel()
    cams = np.repeat(obs.camera[sel], n_w)
    uv[cams, rows] = obs.uv[sel].reshape(-1, 2)
    X = triangulate(rig, uv).X.reshape(frames.size, n_w, 3)
    u = X[:, -1] - X[:, 0]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    centre = np.mean(X - offsets_rel[None, :, None] * u[:, None, :], axis=1)
    return centre, u


def calibrate(obs: WandObservations, cameras_init, offsets_mm, *, ground_blobs=None,
              ground_markers_mm=None, max_frames: int = 3600,
              progress: Callable[[str], None] | None = None) -> CalibrationResult:
    """Calibrate from labeled wand sightings (and optionally the ground take).

    Parameters
    ----------
    obs : wand sightings from :func:`mocap.calib.wand.find_wand`.
    cameras_init : list of :class:`mocap.calib.camera.Camera` with initial intrinsics (poses ignored).
    offsets_mm : (n_w,) the wand's marker offsets, mm.
    ground_blobs, ground_markers_mm : the ground take's blobs and the square's coordinates; when
        given, the result is in the square's world frame.
    """
    say = progress or (lambda msg: None)
    timings = {}
    t0 = time.perf_counter()
    offsets = np.sort(np.asarray(offsets_mm, float))
    offsets_rel = offsets - 0.5 * (offsets[0] + offsets[-1])
    wand_length = float(offsets[-1] - offsets[0])
    cams = list(cameras_init)
    rig0 = initial_rig(obs, cams, wand_length)
    timings["initialise"] = time.perf_counter() - t0
    say(f"initial poses from essential matrices ({timings['initialise']:.1f} s)")

    frames = select_frames(obs, max_frames=max_frames)
    centre, u0 = _initial_frames(rig0, obs, frames, offsets_rel)
    good_frames = np.all(np.isfinite(centre), axis=1) & np.all(np.isfinite(u0), axis=1)
    frames, centre, u0 = frames[good_frames], centre[good_frames], u0[good_frames]
    in_ba = np.isin(obs.frame, frames)
    e1, e2 = _tangent_basis(u0)
    fixed = int(np.argmax(np.bincount(obs.camera, minlength=len(cams))))
    x0 = np.concatenate([np.concatenate([camera_vector(c) for c in rig0]),
                         np.column_stack([centre, np.zeros((frames.size, 2))]).ravel()])
    used = in_ba.copy()
    result = None
    t1 = time.perf_counter()
    stages = [("soft_l1", 2.0), ("linear", 1.0), ("linear", 1.0)]
    for stage, (loss, f_scale) in enumerate(stages):
        idx = np.flatnonzero(used)
        problem = WandProblem(
            obs_cam=obs.camera[idx], obs_frame=np.searchsorted(frames, obs.frame[idx]),
            obs_uv=obs.uv[idx], offsets=offsets_rel, u0=u0, e1=e1, e2=e2,
            n_cameras=len(cams), fixed_camera=fixed)
        result = solve_schur(problem, x0, loss=loss, f_scale=f_scale)
        x0 = np.concatenate([result.cameras.ravel(), result.frames.ravel()])
        norms = np.linalg.norm(result.residuals, axis=-1)  # (n_sightings, n_w)
        worst = norms.max(axis=1)
        # robust sigma per camera (a noisier camera keeps its wider spread)
        sigma = np.array([np.median(norms[problem.obs_cam == c]) / 1.1774
                          if np.any(problem.obs_cam == c) else 0.0 for c in range(len(cams))])
        threshold = np.maximum(6.0 * sigma, 0.6)[problem.obs_cam]
        bad = worst > threshold
        say(f"bundle adjustment stage {stage + 1} ({loss}): {idx.size} sightings, "
            f"rms {np.sqrt(np.mean(result.residuals**2)):.3f} px, {int(bad.sum())} over "
            f"6 sigma of their camera")
        if stage == len(stages) - 1 or (stage >= 1 and not bad.any()):
            break  # the residuals below belong to exactly the sightings in ``used``
        used[idx[bad]] = False
    timings["bundle_adjustment"] = time.perf_counter() - t1
    rig = rig_from_vectors(result.cameras, rig0)
    wand_pts = problem.wand_points(result.frames)
    ground = None
    if ground_blobs is not None and ground_markers_mm is not None:
        t2 = time.perf_counter()
        ground = fit_ground(rig, ground_blobs, ground_markers_mm)
        rig = transform_rig(rig, ground.R, ground.t)
        wand_pts = wand_pts @ ground.R.T + ground.t
        timings["world_frame"] = time.perf_counter() - t2
        say(f"world frame from the ground square: fit rms {ground.rms_mm:.3f} mm, "
            f"scale agreement {ground.scale:.5f}")
    quality = quality_report(rig, obs, used, result.residuals, wand_length, ground)
    timings["total"] = time.perf_counter() - t0
    quality["seconds"] = round(timings["total"], 3)
    return CalibrationResult(rig=rig, quality=quality, wand=obs, used=used,
                             residuals_px=result.residuals, ground=ground, timings_s=timings,
                             wand_frames=frames, wand_points_mm=wand_pts)


def calibrate_session(session, *, max_frames: int = 3600,
                      progress: Callable[[str], None] | None = None) -> CalibrationResult:
    """Calibrate a loaded :class:`mocap.session.Session` from its wand and ground takes."""
    wand_takes = session.takes_of_kind("wand")
    if not wand_takes:
        raise CalibrationError(f"{session.root}: the session has no 'wand' take to calibrate from")
    if session.wand is None:
        raise CalibrationError(f"{session.root}/session.toml: a [wand] table is required")
    say = progress or (lambda msg: None)
    offsets = session.wand.marker_offsets_mm
    ids = [c.id for c in session.cameras]
    cams = [initial_intrinsics(c.id, c.width, c.height, c.focal_px) for c in session.cameras]
    blobs = session.read_take(wand_takes[0].name)
    obs = find_wand(blobs, ids, offsets)
    say(f"wand found in {len(obs)} camera-frames: {obs.frames_per_camera()}")
    ground_blobs = None
    ground_markers = None
    ground_takes = session.takes_of_kind("ground")
    if ground_takes and session.ground is not None:
        ground_blobs = session.read_take(ground_takes[0].name)
        ground_markers = session.ground.markers_mm
    return calibrate(obs, cams, offsets, ground_blobs=ground_blobs,
                     ground_markers_mm=ground_markers, max_frames=max_frames, progress=progress)
