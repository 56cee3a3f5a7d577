"""The calibration's quality report, in the style of commercial systems.

- reprojection RMS per camera (px, per image axis: sqrt(mean(dx^2 + dy^2) / 2), directly
  comparable with a centroid noise sigma) over the sightings the final solve kept;
- wand-length error over frames: every frame's wand markers are triangulated freely (no rigid
  model) with the calibrated rig, and the end-to-end length compared with the manifest's (mean
  and standard deviation, mm);
- estimated 3D point error (mm): the wand-length standard deviation over sqrt(2) (the length is
  the difference of two independent point errors along the wand);
- frames used per camera, sightings rejected as outliers;
- a rating with documented thresholds (``RATING``) of the rig as a whole: excellent when the
  median camera's RMS is under 0.15 px and the wand-length sd under 0.05 mm; good under 0.4 px
  and 0.2 mm; else poor. (A single bad camera shows in its own RMS, which the audit rates per
  camera; it does not condemn the rest of the rig.)
"""

from __future__ import annotations

import numpy as np

from mocap.calib.camera import CameraRig
from mocap.calib.triangulation import triangulate
from mocap.calib.wand import WandObservations

RATING = {
    "excellent": {"max_reprojection_rms_px": 0.15, "max_wand_length_sd_mm": 0.05},
    "good": {"max_reprojection_rms_px": 0.4, "max_wand_length_sd_mm": 0.2},
}


def wand_lengths(rig: CameraRig, obs: WandObservations) -> tuple[np.ndarray, np.ndarray]:
    """Frames and the freely triangulated end-to-end wand length (mm) in each (>= 2 cameras)."""
    frames = np.unique(obs.frame)
    n_w = obs.uv.shape[1]
    local = np.searchsorted(frames, obs.frame)
    uv = np.full((len(rig), frames.size * n_w, 2), np.nan)
    rows = (local[:, None] * n_w + np.arange(n_w)[None]).ravel()
    uv[np.repeat(obs.camera, n_w), rows] = obs.uv.reshape(-1, 2)
    X = triangulate(rig, uv).X.reshape(frames.size, n_w, 3)
    return frames, np.linalg.norm(X[:, -1] - X[:, 0], axis=1)


def rate(per_camera_rms: dict, wand_sd_mm: float) -> str:
    worst = float(np.median(list(per_camera_rms.values()))) if per_camera_rms else np.inf
    for name in ("excellent", "good"):
        th = RATING[name]
        if worst <= th["max_reprojection_rms_px"] and wand_sd_mm <= th["max_wand_length_sd_mm"]:
            return name
    return "poor"


def quality_report(rig: CameraRig, obs: WandObservations, used: np.ndarray,
                   residuals: np.ndarray, wand_length_mm: float, ground=None) -> dict:
    cam_used = obs.camera[used]
    rms = {}
    frames_used = {}
    for i, cid in enumerate(obs.camera_ids):
        r = residuals[cam_used == i]
        rms[cid] = float(np.sqrt(np.mean(r**2))) if r.size else float("nan")
        frames_used[cid] = int(np.sum(cam_used == i))
    kept = obs.select(used)
    _, lengths = wand_lengths(rig, kept)
    lengths = lengths[np.isfinite(lengths)]
    err = lengths - wand_length_mm
    sd = float(np.std(err, ddof=1)) if err.size > 1 else float("nan")
    q = {
        "reprojection_rms_px": rms,
        "reprojection_rms_px_all": float(np.sqrt(np.mean(residuals**2))),
        "wand_length_mm": wand_length_mm,
        "wand_length_error_mean_mm": float(np.mean(err)) if err.size else float("nan"),
        "wand_length_error_sd_mm": sd,
        "point_error_mm": sd / np.sqrt(2.0),
        "frames_used": frames_used,
        "wand_frames": int(err.size),
        "sightings_found": int(len(obs)),
        "sightings_rejected": int(np.sum(~used & np.isin(obs.frame, obs.frame[used]))),
        "rating": rate(rms, sd),
        "rating_thresholds": RATING,
    }
    if ground is not None:
        q["ground_fit_rms_mm"] = float(ground.rms_mm)
        q["ground_scale_agreement"] = float(ground.scale)
    return q


def pose_agreement(a, b) -> dict:
    """How far two calibrations of one rig (e.g. from two halves of a wand take) disagree on
    every camera's pose relative to the first camera, against their own uncertainty.

    ``a``, ``b``: :class:`mocap.calib.wand_calibration.CalibrationResult` in the first camera's
    frame (no ground square), with ``camera_covariance``. Per camera ``j > 0``: the difference
    of its 6 pose parameters (rotation vector, rad; translation, the wand's units) and
    ``chi2 = d^T (S_a + S_b)^-1 d`` with 6 degrees of freedom (about 6 when the two agree as
    their covariances predict; the 99 % point is 16.8); plus the rotation angle between the two
    (deg) and the centre distance relative to the camera's distance from the first camera.
    """
    from mocap.calib.bundle import N_CAM, camera_vector

    out = {}
    for j in range(1, len(a.rig)):
        va, vb = camera_vector(a.rig[j])[:6], camera_vector(b.rig[j])[:6]
        sl = slice(j * N_CAM, j * N_CAM + 6)
        S = a.camera_covariance[sl, sl] + b.camera_covariance[sl, sl]
        d = va - vb
        chi2 = float(d @ np.linalg.solve(S, d))
        Ra, Rb = a.rig[j].R, b.rig[j].R
        ang = float(np.degrees(np.arccos(np.clip((np.trace(Ra @ Rb.T) - 1) / 2, -1, 1))))
        ca, cb = a.rig[j].center, b.rig[j].center
        out[a.rig[j].id] = {"chi2_6dof": chi2, "rotation_deg": ang,
                            "centre_shift_relative": float(np.linalg.norm(ca - cb)
                                                           / np.linalg.norm(ca)),
                            "rotation_sd_deg": float(np.degrees(np.sqrt(np.trace(S[:3, :3]))))}
    return out


COVERAGE_GRID = (8, 8)  # cells across and down the image


def coverage_share(uv: np.ndarray, width: int, height: int, grid=COVERAGE_GRID) -> float:
    """Share of the image's ``grid`` cells (8 x 8) holding at least one of the points uv
    (n, 2) px."""
    uv = np.asarray(uv, float).reshape(-1, 2)
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    if uv.size == 0:
        return 0.0
    i = np.clip((uv[:, 0] + 0.5) / width * grid[0], 0, grid[0] - 1).astype(int)
    j = np.clip((uv[:, 1] + 0.5) / height * grid[1], 0, grid[1] - 1).astype(int)
    return float(np.unique(j * grid[0] + i).size / (grid[0] * grid[1]))


def predictive_sd(Jcam: np.ndarray, cam: np.ndarray, cov: np.ndarray | None) -> np.ndarray:
    """Per image point, the sd (px, per axis) of its projection that the cameras' parameter
    uncertainty implies: ``sqrt(trace(J S J^T) / 2)`` with J (n, k, 2, 13) the projection's
    Jacobian with respect to its camera (n sightings of k points) and S its camera's 13 x 13
    block of ``cov`` (the bundle adjustment's). Returns (n, k); zeros when cov is None."""
    if cov is None or not np.all(np.isfinite(cov)):
        return np.zeros(Jcam.shape[:2])
    n_cam = cov.shape[0] // 13
    blocks = np.stack([cov[c * 13:(c + 1) * 13, c * 13:(c + 1) * 13] for c in range(n_cam)])
    JS = np.einsum("nkai,nij->nkaj", Jcam, blocks[cam])
    var = np.einsum("nkaj,nkaj->nk", JS, Jcam) / 2.0
    return np.sqrt(np.maximum(var, 0.0))
