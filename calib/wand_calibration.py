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
    IntrinsicsModel,
    WandProblem,
    _tangent_basis,
    camera_vector,
    rig_from_vectors,
    solve_schur,
)
from mocap.calib.camera import Camera, CameraRig
from mocap.calib.initialize import CalibrationError, initial_intrinsics, initial_rig
from mocap.calib.quality import quality_report
from mocap.calib.triangulation import triangulate
from mocap.calib.wand import WandObservations, find_wand
from mocap.calib.wand_ends import label_ends
from mocap.calib.world_frame import GroundFit, fit_ground, transform_rig

__all__ = ["CalibrationError", "CalibrationResult", "IntrinsicsModel", "calibrate",
           "calibrate_session"]


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
    # (n_cameras * 13, n_cameras * 13): the bundle adjustment's parameters (rvec, t mm, f, cx,
    # cy, k1, k2, p1, p2 per camera) in the first camera's frame, before any ground transform
    camera_covariance: np.ndarray | None = None


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


def _bundle_stages(obs: WandObservations, rig0: CameraRig, frames: np.ndarray,
                   offsets_rel: np.ndarray, fixed_params: np.ndarray, say,
                   stages=(("soft_l1", 2.0), ("linear", 1.0), ("linear", 1.0))):
    """The robust bundle adjustment of the module docstring, from ``rig0``: (result, problem,
    used, frames)."""
    centre, u0 = _initial_frames(rig0, obs, frames, offsets_rel)
    good_frames = np.all(np.isfinite(centre), axis=1) & np.all(np.isfinite(u0), axis=1)
    frames, centre, u0 = frames[good_frames], centre[good_frames], u0[good_frames]
    in_ba = np.isin(obs.frame, frames)
    e1, e2 = _tangent_basis(u0)
    n_cams = len(rig0)
    x0 = np.concatenate([np.concatenate([camera_vector(c) for c in rig0]),
                         np.column_stack([centre, np.zeros((frames.size, 2))]).ravel()])
    used = in_ba.copy()
    result = problem = None
    for stage, (loss, f_scale) in enumerate(stages):
        idx = np.flatnonzero(used)
        problem = WandProblem(
            obs_cam=obs.camera[idx], obs_frame=np.searchsorted(frames, obs.frame[idx]),
            obs_uv=obs.uv[idx], offsets=offsets_rel, u0=u0, e1=e1, e2=e2,
            n_cameras=n_cams, fixed_camera=0, fixed_params=fixed_params)
        result = solve_schur(problem, x0, loss=loss, f_scale=f_scale)
        x0 = np.concatenate([result.cameras.ravel(), result.frames.ravel()])
        norms = np.linalg.norm(result.residuals, axis=-1)  # (n_sightings, n_w)
        worst = norms.max(axis=1)
        # robust sigma per camera (a noisier camera keeps its wider spread)
        sigma = np.array([np.median(norms[problem.obs_cam == c]) / 1.1774
                          if np.any(problem.obs_cam == c) else 0.0 for c in range(n_cams)])
        threshold = np.maximum(6.0 * sigma, 0.6)[problem.obs_cam]
        bad = worst > threshold
        say(f"bundle adjustment stage {stage + 1} ({loss}): {idx.size} sightings, "
            f"rms {np.sqrt(np.mean(result.residuals**2)):.3f} px, {int(bad.sum())} over "
            f"6 sigma of their camera ({result.nfev} evaluations)")
        if stage == len(stages) - 1 or (stage >= 1 and not bad.any()):
            break  # the residuals below belong to exactly the sightings in ``used``
        used[idx[bad]] = False
    return result, problem, used, frames


def check_support(obs: WandObservations, intrinsics: IntrinsicsModel, *, min_frames: int = 50):
    """Raise CalibrationError when the sightings cannot support the asked intrinsics.

    Each camera needs its wand seen together with another camera in ``min_frames`` frames, and
    at least 10 sightings per intrinsic parameter estimated (a hand-digitised recording of 50
    frames supports focal length, principal point and k1 k2, not a full model on few frames).
    """
    frames, n_views = np.unique(obs.frame, return_counts=True)
    multi = frames[n_views >= 2]
    need = max(min_frames, 10 * intrinsics.n_free)
    short = {}
    for c, cid in enumerate(obs.camera_ids):
        n = int(np.isin(obs.frame[obs.camera == c], multi).sum())
        if n < need:
            short[cid] = n
    if short:
        raise CalibrationError(
            f"wand seen together with another camera in too few frames for the intrinsics asked "
            f"(principal point {intrinsics.principal_point}, distortion {intrinsics.distortion}: "
            f"{intrinsics.n_free} per camera, {need} frames needed): {short}. Record more wand "
            "frames, or estimate fewer intrinsics (--principal-point fixed, --distortion k1 or none)")


def calibrate(obs: WandObservations, cameras_init, offsets_mm, *, ground_blobs=None,
              ground_markers_mm=None, max_frames: int = 3600,
              intrinsics: IntrinsicsModel = IntrinsicsModel(),
              progress: Callable[[str], None] | None = None) -> CalibrationResult:
    """Calibrate from wand sightings (and optionally the ground take).

    Parameters
    ----------
    obs : wand sightings from :func:`mocap.calib.wand.find_wand` (two-marker wands: unordered
        ends, ordered here by :func:`mocap.calib.wand_ends.label_ends`).
    cameras_init : list of :class:`mocap.calib.camera.Camera` with initial intrinsics (poses ignored).
    offsets_mm : (n_w,) the wand's marker offsets, mm.
    ground_blobs, ground_markers_mm : the ground take's blobs and the square's coordinates; when
        given, the result is in the square's world frame; otherwise in the first camera's
        (OpenCV axes, origin at its centre), the scale set by the wand.
    intrinsics : which intrinsics to estimate (:class:`mocap.calib.bundle.IntrinsicsModel`).
    """
    say = progress or (lambda msg: None)
    timings = {}
    t0 = time.perf_counter()
    offsets = np.sort(np.asarray(offsets_mm, float))
    offsets_rel = offsets - 0.5 * (offsets[0] + offsets[-1])
    wand_length = float(offsets[-1] - offsets[0])
    cams = list(cameras_init)
    fixed_params = np.tile(intrinsics.fixed_mask(), (len(cams), 1))
    # held distortion terms start (and stay) at 0
    cams = [Camera(id=c.id, width=c.width, height=c.height, K=c.K,
                   dist=np.where(np.r_[intrinsics.fixed_mask()[9:], True], 0.0, c.dist))
            for c in cams]
    rig0 = initial_rig(obs, cams, wand_length)
    check_support(obs, intrinsics)
    timings["initialise"] = time.perf_counter() - t0
    say(f"initial poses from essential matrices ({timings['initialise']:.1f} s)")
    unordered = None
    if not obs.ordered:
        unordered = obs
        obs, kept = label_ends(unordered, rig0)
        say(f"two-marker wand: ends ordered across cameras in {int(kept.sum())} of "
            f"{len(unordered)} sightings (epipolar votes of the initial rig)")

    t1 = time.perf_counter()
    frames = select_frames(obs, max_frames=max_frames)
    # coarse first: poses and focal lengths only (principal point at its start, no distortion),
    # robustly; a full model from a rough start can wander off (a strongly distorted lens)
    coarse = np.tile(IntrinsicsModel("fixed", "none").fixed_mask(), (len(cams), 1)) | fixed_params
    result, _, _, _ = _bundle_stages(obs, rig0, frames, offsets_rel, coarse, say,
                                     stages=(("soft_l1", 4.0),))
    rig0 = rig_from_vectors(result.cameras, rig0)
    result, problem, used, frames = _bundle_stages(obs, rig0, frames, offsets_rel, fixed_params, say)
    rig = rig_from_vectors(result.cameras, rig0)
    if unordered is not None:  # order the ends again with the calibrated cameras, and refine
        obs, kept = label_ends(unordered, rig)
        say(f"two-marker wand: ends ordered in {int(kept.sum())} of {len(unordered)} sightings "
            "with the adjusted cameras")
        frames = select_frames(obs, max_frames=max_frames)
        result, problem, used, frames = _bundle_stages(
            obs, rig, frames, offsets_rel, fixed_params, say,
            stages=(("linear", 1.0), ("linear", 1.0)))  # from adjusted cameras: no robust stage
        rig = rig_from_vectors(result.cameras, rig)
    timings["bundle_adjustment"] = time.perf_counter() - t1
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
        world = "ground square"
    else:
        world = (f"first camera ({rig[0].id}): OpenCV axes, origin at its centre; no ground "
                 "square, the scale is the wand's")
        say(f"world frame: {world}")
    quality = quality_report(rig, obs, used, result.residuals, wand_length, ground)
    quality["world_frame"] = world
    quality["intrinsics"] = {"principal_point": intrinsics.principal_point,
                             "distortion": intrinsics.distortion}
    quality["wand_markers"] = int(offsets.size)
    timings["total"] = time.perf_counter() - t0
    quality["seconds"] = round(timings["total"], 3)
    return CalibrationResult(rig=rig, quality=quality, wand=obs, used=used,
                             residuals_px=result.residuals, ground=ground, timings_s=timings,
                             wand_frames=frames, wand_points_mm=wand_pts,
                             camera_covariance=result.camera_covariance)


def calibrate_session(session, *, max_frames: int = 3600,
                      intrinsics: IntrinsicsModel = IntrinsicsModel(),
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
                     ground_markers_mm=ground_markers, max_frames=max_frames,
                     intrinsics=intrinsics, progress=progress)
