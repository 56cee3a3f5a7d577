"""Wand calibration of a camera rig: wand finding, initialisation, bundle adjustment, world frame
and the quality report. ``calibrate_session`` runs it all on a session's ``wand`` and (optional)
``ground`` takes.

Order of work:

1. initial poses from pairwise essential matrices (:mod:`mocap.calib.initialize`), in the first
   camera's frame; for a two-marker wand the ends are then ordered across cameras
   (:mod:`mocap.calib.wand_ends`). Cameras without a focal length (``focal_search``) are tried
   from each of ``FOCAL_SEARCH`` x the image's larger side, the start whose coarse adjustment on
   a few hundred frames fits best kept;
2. a coarse robust adjustment of poses and focal lengths only (principal point at its start, no
   distortion): a full model from a rough start can wander off;
3. the full bundle adjustment with outlier trimming (below); a two-marker wand's ends are
   ordered again with the adjusted cameras and the adjustment refined;
4. intrinsics the frames do not determine (``undetermined_intrinsics``, from the adjustment's own
   covariance) are dropped along ``LADDER`` by default, or refused when asked for explicitly;
5. the world frame: the ground square's, or the first camera's (OpenCV axes, origin at its
   centre, the wand's scale) when the session has none; the report says which.

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
    PointSightings,
    WandProblem,
    _tangent_basis,
    camera_vector,
    rig_from_vectors,
    solve_schur,
)
from mocap.calib.camera import Camera, CameraRig
from mocap.calib.initialize import CalibrationError, initial_intrinsics, initial_rig
from mocap.calib.priors import prior_arrays
from mocap.calib.quality import predictive_sd, quality_report
from mocap.calib.rig_report import rig_report
from mocap.calib.static_points import StaticPoints, initial_points
from mocap.calib.triangulation import triangulate
from mocap.calib.wand import WandObservations, find_wand
from mocap.calib.wand_ends import label_ends
from mocap.calib.world_frame import GroundFit, fit_ground, transform_rig
from mocap.core.display import Summarised, Summary

__all__ = ["CalibrationError", "CalibrationResult", "IntrinsicsModel", "calibrate",
           "calibrate_session"]


@dataclass(frozen=True, repr=False)
class CalibrationResult(Summarised):
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
    points: StaticPoints | None = None  # static points' sightings given
    points_used: np.ndarray | None = None  # (len(points),) bool: kept by the final adjustment
    points_mm: np.ndarray | None = None  # (n_points, 3) fitted static points, first camera's frame


    def _summary(self) -> Summary:
        q = self.quality
        per_cam = q.get("reprojection_rms_px") or {}
        lines = [("rating", str(q.get("rating", "?"))),
                 ("reprojection", f"{q.get('reprojection_rms_px_all', float('nan')):.3g} px rms"),
                 ("wand length", f"{q.get('wand_length_mm', float('nan')):g} mm, error "
                                 f"{q.get('wand_length_error_mean_mm', float('nan')):.2g} +- "
                                 f"{q.get('wand_length_error_sd_mm', float('nan')):.2g} mm"),
                 ("sightings", f"{int(np.sum(self.used))} of {len(self.used)} used"),
                 ("world frame", str(q.get("world_frame", "?")))]
        if per_cam:
            lines.append(("per camera", ", ".join(f"{k} {v:.3g}" for k, v in
                                                   list(per_cam.items())[:12]) + " px"))
        return Summary(f"CalibrationResult: {len(self.rig)} cameras", tuple(lines),
                       more="attributes: .rig .quality .residuals_px .wand .ground")


OUTLIER_SD = 6.0  # a sighting is an outlier beyond this many sd of its predicted residual
OUTLIER_FLOOR_PX = 0.6  # ... and beyond this many px (sub-pixel noise is never an outlier)
PREDICTIVE_CAP = 3.0  # the model's predictive sd counts up to this many x the camera's noise


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
                   stages=(("soft_l1", 2.0), ("linear", 1.0), ("linear", 1.0)), *,
                   prior=None, points: StaticPoints | None = None):
    """The robust bundle adjustment of the module docstring, from ``rig0``: (result, problem,
    used, frames, extra). ``prior``: (mean, sd) (n_cameras, 13) of refined prior intrinsics;
    ``points``: static points' sightings. ``extra``: ``points_used`` (len(points),) bool,
    ``point_ids`` (the problem's points), ``dropped`` (one dict per sighting dropped: kind,
    camera, frame, worst residual and threshold px, stage)."""
    centre, u0 = _initial_frames(rig0, obs, frames, offsets_rel)
    good_frames = np.all(np.isfinite(centre), axis=1) & np.all(np.isfinite(u0), axis=1)
    frames, centre, u0 = frames[good_frames], centre[good_frames], u0[good_frames]
    in_ba = np.isin(obs.frame, frames)
    e1, e2 = _tangent_basis(u0)
    n_cams = len(rig0)
    k3 = np.array([c.dist[4] for c in rig0])
    parts = [np.concatenate([camera_vector(c) for c in rig0]),
             np.column_stack([centre, np.zeros((frames.size, 2))]).ravel()]
    point_ids = np.zeros(0, np.int64)
    pts_used = np.zeros(0, bool)
    if points is not None and len(points):
        point_ids, X = initial_points(rig0, points)
        ok = np.all(np.isfinite(X), axis=1)
        point_ids, X = point_ids[ok], X[ok]
        pts_used = np.isin(points.point, point_ids)
        parts.append(X.ravel())
    x0 = np.concatenate(parts)
    used = in_ba.copy()
    result = problem = None
    dropped: list[dict] = []
    sigma_all = None
    for stage, (loss, f_scale) in enumerate(stages):
        idx = np.flatnonzero(used)
        pidx = np.flatnonzero(pts_used)
        sightings = None
        if point_ids.size:
            sightings = PointSightings(points.camera[pidx],
                                       np.searchsorted(point_ids, points.point[pidx]),
                                       points.uv[pidx], point_ids.size)
        weight = mean = None
        if prior is not None:
            if sigma_all is None:  # the noise from the starting residuals (robust)
                r0 = WandProblem(obs_cam=obs.camera[idx],
                                 obs_frame=np.searchsorted(frames, obs.frame[idx]),
                                 obs_uv=obs.uv[idx], offsets=offsets_rel, u0=u0, e1=e1, e2=e2,
                                 n_cameras=n_cams, fixed_camera=0, k3=k3).blocks(
                    x0[:n_cams * 13 + frames.size * 5])[0]
                sigma_all = float(np.median(np.linalg.norm(r0, axis=-1)) / 1.1774)
            mean = prior[0]
            weight = np.where(np.isfinite(prior[1]), sigma_all**2 / prior[1] ** 2, 0.0)
        problem = WandProblem(
            obs_cam=obs.camera[idx], obs_frame=np.searchsorted(frames, obs.frame[idx]),
            obs_uv=obs.uv[idx], offsets=offsets_rel, u0=u0, e1=e1, e2=e2,
            n_cameras=n_cams, fixed_camera=0, fixed_params=fixed_params, k3=k3,
            prior_mean=mean, prior_weight=weight, points=sightings,
            noise_px=sigma_all if prior is not None else None)
        result = solve_schur(problem, x0, loss=loss, f_scale=f_scale)
        x0 = np.concatenate([result.cameras.ravel(), result.frames.ravel()]
                            + ([result.points.ravel()] if sightings is not None else []))
        norms = np.linalg.norm(result.residuals, axis=-1)  # (n_sightings, n_w)
        # robust sigma per camera (a noisier camera keeps its wider spread)
        sigma = np.array([np.median(norms[problem.obs_cam == c]) / 1.1774
                          if np.any(problem.obs_cam == c) else 0.0 for c in range(n_cams)])
        sigma_all = float(np.median(norms) / 1.1774)
        # judged against the model's predictive uncertainty at each image point, not only the
        # residual spread (a poorly determined image edge widens the threshold there)
        _, Jcam, _ = problem.blocks(x0)
        # the covariance is scaled by the residuals' variance, outliers included: rescale it to
        # the robust noise so that outliers do not widen their own threshold
        rms = np.sqrt(np.mean(np.concatenate([result.residuals.ravel()] + (
            [result.point_residuals.ravel()] if result.point_residuals is not None else [])) ** 2))
        scale = sigma_all / max(rms, 1e-12)
        pred = scale * predictive_sd(Jcam, problem.obs_cam, result.camera_covariance)
        # the cameras' marginal covariance ignores what the frame's other sightings pin down (an
        # upper bound, loose on long lenses whose focal length trades with distance): capped
        pred = np.minimum(pred, PREDICTIVE_CAP * sigma[problem.obs_cam, None])
        threshold = np.maximum(OUTLIER_SD * np.sqrt(sigma[problem.obs_cam, None] ** 2 + pred**2),
                               OUTLIER_FLOOR_PX)
        ratio = norms / threshold
        bad = ratio.max(axis=1) > 1.0
        pbad = np.zeros(0, bool)
        if sightings is not None:
            _, Jpc, _ = problem.point_blocks(x0)
            ppred = scale * predictive_sd(Jpc[:, None], sightings.camera,
                                          result.camera_covariance)[:, 0]
            ppred = np.minimum(ppred, PREDICTIVE_CAP * sigma[sightings.camera])
            pth = np.maximum(OUTLIER_SD * np.sqrt(sigma[sightings.camera] ** 2 + ppred**2),
                             OUTLIER_FLOOR_PX)
            pn = np.linalg.norm(result.point_residuals, axis=-1)
            pbad = pn > pth
        say(f"bundle adjustment stage {stage + 1} ({loss}): {idx.size} sightings"
            + (f" + {pidx.size} of static points" if sightings is not None else "")
            + f", rms {np.sqrt(np.mean(result.residuals**2)):.3f} px, "
            f"{int(bad.sum()) + int(pbad.sum())} over {OUTLIER_SD:g} sd of their prediction "
            f"({result.nfev} evaluations)")
        if stage == len(stages) - 1 or (stage >= 1 and not bad.any() and not pbad.any()):
            break  # the residuals below belong to exactly the sightings in ``used``
        for k in np.flatnonzero(bad):
            i = idx[k]
            w = int(np.argmax(ratio[k]))
            dropped.append({"kind": "wand", "camera": obs.camera_ids[obs.camera[i]],
                            "frame": int(obs.frame[i]), "residual_px": float(norms[k, w]),
                            "threshold_px": float(threshold[k, w]), "stage": stage + 1})
        for k in np.flatnonzero(pbad):
            dropped.append({"kind": "points", "camera": obs.camera_ids[sightings.camera[k]],
                            "frame": int(points.point[pidx[k]]), "residual_px": float(pn[k]),
                            "threshold_px": float(pth[k]), "stage": stage + 1})
        used[idx[bad]] = False
        pts_used[pidx[pbad]] = False
    return result, problem, used, frames, {"points_used": pts_used, "point_ids": point_ids,
                                           "dropped": dropped}


# the default intrinsics, and the simpler models tried in turn when the frames do not determine
# them (a principal point or distortion term whose uncertainty exceeds ``DETERMINED``)
LADDER = (IntrinsicsModel("free", "k1k2p1p2"), IntrinsicsModel("fixed", "k1k2"),
          IntrinsicsModel("fixed", "k1"), IntrinsicsModel("fixed", "none"))
DETERMINED = {"principal_point_sd_fraction": 0.02, "distortion_corner_sd_px": 1.0}


def undetermined_intrinsics(rig: CameraRig, cov: np.ndarray | None,
                            intrinsics: IntrinsicsModel,
                            reach_px: np.ndarray | None = None) -> dict[str, list[str]]:
    """Per camera, the estimated intrinsics the data leave loose: the principal point when its
    standard deviation exceeds 2 % of the image's larger side; the distortion terms when their
    joint uncertainty (their full covariance, correlations included) moves an image point at the
    edge of the data (``reach_px`` (n_cameras,): the 99th percentile distance of the camera's
    sightings from its principal point, px; default the image corner) by more than 1 px (1 sd,
    per axis), in any of 8 directions."""
    out: dict[str, list[str]] = {}
    if cov is None or not np.all(np.isfinite(cov)):
        return {c.id: ["all (singular normal equations)"] for c in rig}
    held = intrinsics.fixed_mask()
    free_d = np.flatnonzero(~held[9:13])
    for i, c in enumerate(rig):
        block = cov[i * 13:(i + 1) * 13, i * 13:(i + 1) * 13]
        sd = np.sqrt(np.maximum(np.diag(block), 0.0))
        bad = []
        if not held[7] and max(sd[7], sd[8]) > DETERMINED["principal_point_sd_fraction"] * max(
                c.width, c.height):
            bad.append(f"principal point sd {max(sd[7], sd[8]):.1f} px")
        if free_d.size:
            S = block[9 + free_d][:, 9 + free_d]
            worst = 0.0
            reach = (np.hypot(c.width, c.height) / 2.0 if reach_px is None
                     else float(reach_px[i]))
            for ang in np.arange(8) * np.pi / 4:
                x = reach * np.cos(ang) / c.K[0, 0]
                y = reach * np.sin(ang) / c.K[1, 1]
                r2 = x * x + y * y
                J = c.focal_px * np.array([[x * r2, x * r2 * r2, 2 * x * y, r2 + 2 * x * x],
                                           [y * r2, y * r2 * r2, r2 + 2 * y * y, 2 * x * y]])
                J = J[:, free_d]
                worst = max(worst, float(np.sqrt(np.trace(J @ S @ J.T) / 2.0)))
            if worst > DETERMINED["distortion_corner_sd_px"]:
                bad.append(f"distortion moves an image corner by {worst:.2f} px (1 sd)")
        if bad:
            out[c.id] = bad
    return out


def _reset_held(c: Camera, intrinsics: IntrinsicsModel) -> Camera:
    """The camera with the intrinsics a model holds reset: principal point to the image centre,
    distortion terms to 0."""
    held = intrinsics.fixed_mask()
    K = c.K.copy()
    if held[7]:
        K[0, 2], K[1, 2] = (c.width - 1) / 2.0, (c.height - 1) / 2.0
    dist = np.where(np.r_[held[9:], True], 0.0, c.dist)
    return Camera(id=c.id, width=c.width, height=c.height, K=K, dist=dist, R=c.R, t=c.t)


FOCAL_SEARCH = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0)  # x the image's larger side


def _coarse_start(obs: WandObservations, cams, wand_length: float, offsets_rel: np.ndarray,
                  coarse: np.ndarray, max_frames: int):
    """Initial rig, ends ordered (two-marker wands), and a robust adjustment of poses and focal
    lengths: (rig, ordered sightings, median reprojection error px of the worst marker)."""
    rig0 = initial_rig(obs, list(cams), wand_length, max_frames=max(max_frames, 200))
    if not obs.ordered:
        obs, _ = label_ends(obs, rig0)
    frames = select_frames(obs, max_frames=max_frames, per_camera=max(max_frames // 30, 8))
    result, _, _, _, _ = _bundle_stages(obs, rig0, frames, offsets_rel, coarse, lambda m: None,
                                     stages=(("soft_l1", 4.0),))
    score = float(np.median(np.linalg.norm(result.residuals, axis=-1).max(axis=1)))
    return rig_from_vectors(result.cameras, rig0), obs, score


def support_shortfall(obs: WandObservations, intrinsics: IntrinsicsModel, *,
                      min_frames: int = 30) -> tuple[dict[str, int], int]:
    """Cameras whose wand is seen together with another camera in fewer frames than the
    intrinsics need (``check_support``): ({camera id: frames}, frames needed)."""
    frames, n_views = np.unique(obs.frame, return_counts=True)
    multi = frames[n_views >= 2]
    need = max(min_frames, 6 * intrinsics.n_free)
    short = {}
    for c, cid in enumerate(obs.camera_ids):
        n = int(np.isin(obs.frame[obs.camera == c], multi).sum())
        if n < need:
            short[cid] = n
    return short, need


def check_support(obs: WandObservations, intrinsics: IntrinsicsModel, *, min_frames: int = 30):
    """Raise CalibrationError when the sightings cannot support the asked intrinsics.

    Each camera needs its wand seen together with another camera in ``min_frames`` frames, and
    at least 6 such frames per intrinsic parameter estimated (a hand-digitised recording of 50
    frames, of which each camera shares 30 to 45, supports a focal length and k1 k2 with the
    principal point at the image centre, not a full model).
    """
    short, need = support_shortfall(obs, intrinsics, min_frames=min_frames)
    if short:
        raise CalibrationError(
            f"wand seen together with another camera in too few frames for the intrinsics asked "
            f"(principal point {intrinsics.principal_point}, distortion {intrinsics.distortion}: "
            f"{intrinsics.n_free} per camera, {need} frames needed): {short}. Record more wand "
            "frames, or estimate fewer intrinsics (--principal-point fixed, --distortion k1 or none)")


def calibrate(obs: WandObservations, cameras_init, offsets_mm, *, ground_blobs=None,
              ground_markers_mm=None, max_frames: int = 3600,
              intrinsics: IntrinsicsModel | None = None, focal_search: bool = False,
              priors: dict | None = None, points: StaticPoints | None = None,
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
    intrinsics : which intrinsics to estimate for the cameras without priors
        (:class:`mocap.calib.bundle.IntrinsicsModel`); a model the frames do not determine is a
        CalibrationError. None (default): the richest of ``LADDER`` the frames determine
        (principal point free and k1 k2 p1 p2 first).
    focal_search : the cameras' focal lengths are unknown (no ``focal_px``): start from each of
        ``FOCAL_SEARCH`` x the image's larger side and keep the start whose coarse adjustment
        (on a few hundred frames) fits best. Long lenses (near-affine cameras) need it: their
        pairwise essential matrices barely depend on the focal length. Cameras with priors keep
        their focal length.
    priors : camera id -> :class:`mocap.calib.priors.IntrinsicPrior`: those cameras' intrinsics
        used as given ("fixed") or refined from there under the prior ("refine").
    points : static points' sightings (:mod:`mocap.calib.static_points`), extra correspondences.
    """
    say = progress or (lambda msg: None)
    timings = {}
    t0 = time.perf_counter()
    given = obs
    priors = dict(priors or {})
    offsets = np.sort(np.asarray(offsets_mm, float))
    offsets_rel = offsets - 0.5 * (offsets[0] + offsets[-1])
    wand_length = float(offsets[-1] - offsets[0])
    cams = list(cameras_init)
    has_prior = np.array([c.id in priors for c in cams])
    p_held, p_mean, p_sd = prior_arrays(cams, priors)
    prior = (p_mean, p_sd) if np.isfinite(p_sd).any() else None
    adaptive = intrinsics is None
    intrinsics = LADDER[0] if intrinsics is None else intrinsics

    model_of = [intrinsics] * len(cams)  # per camera calibrated from the wand alone
    wand_only = [i for i, c in enumerate(cams) if c.id not in priors]

    def masks():  # cameras with priors: all intrinsics estimated (refine) or held (fixed)
        m = np.stack([model_of[i].fixed_mask() for i in range(len(cams))])
        m[has_prior] = p_held[has_prior]
        return m

    def start(c):  # the prior's intrinsics, or held distortion terms at 0
        p = priors.get(c.id)
        if p is not None:
            K = [[p.focal_px, 0, p.principal_px[0]], [0, p.focal_px, p.principal_px[1]], [0, 0, 1]]
            return Camera(id=c.id, width=c.width, height=c.height, K=K, dist=p.distortion)
        return Camera(id=c.id, width=c.width, height=c.height, K=c.K,
                      dist=np.where(np.r_[intrinsics.fixed_mask()[9:], True], 0.0, c.dist))

    cams = [start(c) for c in cams]
    not_determined: dict[str, list[str]] = {}
    if adaptive:  # per camera, start from the richest model its frame count supports
        for i in wand_only:
            cid = cams[i].id
            for model in LADDER:
                short, need = support_shortfall(obs, model)
                if cid in short and model != LADDER[-1]:
                    not_determined.setdefault(cid, []).append(
                        f"{model.principal_point} principal point with {model.distortion} "
                        f"distortion: {short[cid]} frames shared with another camera, {need} "
                        "needed")
                    continue
                model_of[i] = model
                break
        cams = [c if i not in wand_only else _reset_held(c, model_of[i])
                for i, c in enumerate(cams)]
    short = {}
    for i in wand_only:
        s_i, need = support_shortfall(obs, model_of[i])
        if cams[i].id in s_i:
            short[cams[i].id] = (s_i[cams[i].id], need, model_of[i])
    if short:
        _, (_, need, m0) = next(iter(short.items()))
        raise CalibrationError(
            f"wand seen together with another camera in too few frames for the intrinsics asked "
            f"(principal point {m0.principal_point}, distortion {m0.distortion}: "
            f"{m0.n_free} per camera, {need} frames needed): "
            f"{ {k: v[0] for k, v in short.items()} }. Record more wand "
            "frames, estimate fewer intrinsics (--principal-point fixed, --distortion k1 or none) "
            "or give those cameras prior intrinsics")
    fixed_params = masks()
    # coarse first: poses and focal lengths only (principal point at its start, distortion at
    # the prior's or none), robustly; a full model from a rough start can wander off
    coarse = np.tile(IntrinsicsModel("fixed", "none").fixed_mask(), (len(cams), 1)) | fixed_params
    coarse[has_prior, 6:13] = True
    unordered = None if obs.ordered else obs
    if focal_search:
        best = None
        f0 = max(max(c.width, c.height) for c in cams)
        for factor in FOCAL_SEARCH:
            trial = [c if c.id in priors else
                     Camera(id=c.id, width=c.width, height=c.height, dist=c.dist,
                            K=[[factor * f0, 0, c.K[0, 2]], [0, factor * f0, c.K[1, 2]], [0, 0, 1]])
                     for c in cams]
            try:
                rig_c, _, score = _coarse_start(obs if unordered is None else unordered, trial,
                                                wand_length, offsets_rel, coarse, 240)
            except CalibrationError:
                continue
            say(f"focal length search: start {factor * f0:.0f} px -> coarse fit median "
                f"{score:.2f} px")
            if best is None or score < best[0]:
                best = (score, rig_c)
        if best is None:
            raise CalibrationError("no focal length from 0.5 to 32 image widths gives a consistent "
                                   "initial rig; give focal_px in session.toml")
        rig0 = best[1]
        if unordered is not None:
            obs, _ = label_ends(unordered, rig0)
    else:
        rig0, obs, _ = _coarse_start(obs if unordered is None else unordered, cams, wand_length,
                                     offsets_rel, coarse, max_frames)
    timings["initialise"] = time.perf_counter() - t0
    say(f"initial poses from essential matrices, coarse adjustment "
        f"({timings['initialise']:.1f} s)")
    if unordered is not None:
        say(f"two-marker wand: ends ordered across cameras in {len(obs)} of "
            f"{len(unordered)} sightings (epipolar votes of the initial rig)")

    t1 = time.perf_counter()
    kw = dict(prior=prior, points=points)
    frames = select_frames(obs, max_frames=max_frames)
    result, problem, used, frames, extra = _bundle_stages(obs, rig0, frames, offsets_rel,
                                                          fixed_params, say, **kw)
    rig = rig_from_vectors(result.cameras, rig0)
    if unordered is not None:  # order the ends again with the calibrated cameras, and refine
        obs, kept = label_ends(unordered, rig)
        say(f"two-marker wand: ends ordered in {int(kept.sum())} of {len(unordered)} sightings "
            "with the adjusted cameras")
        frames = select_frames(obs, max_frames=max_frames)
        result, problem, used, frames, extra = _bundle_stages(
            obs, rig, frames, offsets_rel, fixed_params, say,
            stages=(("linear", 1.0), ("linear", 1.0)), **kw)  # from adjusted cameras: not robust
        rig = rig_from_vectors(result.cameras, rig)
    reach = np.array([np.percentile(np.linalg.norm(obs.uv[obs.camera == i] - c.K[:2, 2], axis=-1),
                                    99) if np.any(obs.camera == i) else 0.0
                      for i, c in enumerate(rig)])

    def undetermined():  # per camera, against its own model; cameras with priors are determined
        out = {}
        for model in {model_of[i] for i in wand_only}:
            u = undetermined_intrinsics(rig, result.camera_covariance, model, reach)
            out.update({cid: v for cid, v in u.items() if cid not in priors
                        and model_of[rig.index(cid)] == model})
        return out

    loose = undetermined()
    while loose and adaptive:
        stepped = []
        for cid, why in loose.items():
            i = rig.index(cid)
            m = model_of[i]
            if m == LADDER[-1]:
                continue
            simpler = LADDER[LADDER.index(m) + 1] if m in LADDER else LADDER[-1]
            not_determined.setdefault(cid, []).extend(
                f"{m.principal_point} principal point with {m.distortion} distortion: {w}"
                for w in why)
            model_of[i] = simpler
            stepped.append(f"{cid} -> {simpler.principal_point} principal point, "
                           f"{simpler.distortion} distortion")
        if not stepped:
            break
        say(f"intrinsics not determined by these frames ({loose}); trying {'; '.join(stepped)}")
        fixed_params = masks()
        rig = CameraRig(tuple(c if c.id in priors else _reset_held(c, model_of[i])
                              for i, c in enumerate(rig)))
        result, problem, used, frames, extra = _bundle_stages(obs, rig, frames, offsets_rel,
                                                              fixed_params, say, **kw)
        rig = rig_from_vectors(result.cameras, rig)
        loose = undetermined()
    if loose:
        m0 = model_of[rig.index(next(iter(loose)))]
        raise CalibrationError(
            f"the wand frames do not determine the intrinsics asked (principal point "
            f"{m0.principal_point}, distortion {m0.distortion}): {loose}. Estimate "
            "fewer (--principal-point fixed, --distortion k1 or none), give prior intrinsics "
            "(--intrinsics FILE, or principal_px and distortion in session.toml), or record more "
            "wand frames reaching the image corners")
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
    # the simplest model of the cameras calibrated from the wand alone (each camera's own is in
    # intrinsics_per_camera)
    simplest = max((model_of[i] for i in wand_only),
                   key=lambda m: LADDER.index(m) if m in LADDER else -1, default=intrinsics)
    quality["intrinsics"] = {"principal_point": simplest.principal_point,
                             "distortion": simplest.distortion}
    quality["wand_markers"] = int(offsets.size)
    quality.update(rig_report(rig, obs, used, model_of, priors, result, not_determined,
                              points, extra, given=given, reach_px=reach))
    timings["total"] = time.perf_counter() - t0
    quality["seconds"] = round(timings["total"], 3)
    return CalibrationResult(rig=rig, quality=quality, wand=obs, used=used,
                             residuals_px=result.residuals, ground=ground, timings_s=timings,
                             wand_frames=frames, wand_points_mm=wand_pts,
                             camera_covariance=result.camera_covariance,
                             points=points, points_used=extra["points_used"],
                             points_mm=result.points)


def calibrate_session(session, *, max_frames: int = 3600,
                      intrinsics: IntrinsicsModel | None = None, priors: dict | None = None,
                      progress: Callable[[str], None] | None = None) -> CalibrationResult:
    """Calibrate a loaded :class:`mocap.core.session.Session` from its wand, points and ground takes.

    ``priors``: camera id -> :class:`mocap.calib.priors.IntrinsicPrior` (e.g. read from files),
    overriding the session's own (``principal_px``, ``distortion``, ``intrinsics``)."""
    from mocap.calib.priors import merge_priors, prior_from_camera_info
    from mocap.calib.static_points import combine, static_points

    wand_takes = session.takes_of_kind("wand")
    if not wand_takes:
        raise CalibrationError(f"{session.root}: the session has no 'wand' take to calibrate from")
    if session.wand is None:
        raise CalibrationError(f"{session.root}/session.toml: a [wand] table is required")
    say = progress or (lambda msg: None)
    offsets = session.wand.marker_offsets_mm
    ids = [c.id for c in session.cameras]
    own = {c.id: p for c in session.cameras if (p := prior_from_camera_info(c)) is not None}
    priors = merge_priors(own, priors or {}, session.cameras)
    focal_search = any(not c.focal_px and c.id not in priors for c in session.cameras)
    cams = [initial_intrinsics(c.id, c.width, c.height, c.focal_px) for c in session.cameras]
    blobs = session.read_take(wand_takes[0].name)
    obs = find_wand(blobs, ids, offsets)
    say(f"wand found in {len(obs)} camera-frames: {obs.frames_per_camera()}")
    if priors:
        say("prior intrinsics: " + ", ".join(f"{k} {p.mode} ({p.source})"
                                             for k, p in sorted(priors.items())))
    parts, offset = [], 0
    for take in session.takes_of_kind("points"):
        b = session.read_take(take.name)
        parts.append(static_points(b, ids, frame_offset=offset))
        offset += int(b["frame"].max()) + 1 if len(b) else 0
    points = combine(parts)
    if points is not None:
        say(f"static points: {points.n_points} points in {len(points)} sightings "
            f"(skipped: {points.skipped})")
    ground_blobs = None
    ground_markers = None
    ground_takes = session.takes_of_kind("ground")
    if ground_takes and session.ground is not None:
        ground_blobs = session.read_take(ground_takes[0].name)
        ground_markers = session.ground.markers_mm
    return calibrate(obs, cams, offsets, ground_blobs=ground_blobs,
                     ground_markers_mm=ground_markers, max_frames=max_frames,
                     intrinsics=intrinsics, focal_search=focal_search, priors=priors,
                     points=points, progress=progress)
