"""The calibration report's per-camera part: where each camera's intrinsics came from, what the
wand determined, how much of the image the wand and the static points covered, and every
sighting left out with the reason.

Keys added to the quality report (all per camera id):

- ``intrinsics_per_camera``: ``source`` ("prior fixed", "prior refined" or "wand"), the file
  the prior came from, ``principal_point`` and ``distortion`` (what was estimated), and
  ``not_determined``: each richer model the wand did not determine for this camera, with the
  reason (a principal point's sd, or how far the distortion terms' uncertainty moves the edge of
  the data), empty when everything asked was determined;
- ``prior_refinement``: for refined priors, per intrinsic the prior, the estimate, the change,
  the prior's and the posterior's sd and the wand's share of the information
  (:func:`mocap.calib.priors.refinement_report`);
- ``coverage``: the share of the image's 8 x 8 cells holding a wand sighting (``wand``), a
  static point (``points``), and either (``both``);
- ``sightings_dropped``: per camera the count of sightings the outlier test removed, and
  ``dropped``: per camera, columns over each one (``kind`` wand or points, ``frame``,
  ``residual_px`` and the ``threshold_px`` it exceeded: 6 sd of the residual predicted at
  that image point, from the camera's noise and the model's uncertainty there, at least
  0.6 px; ``stage`` of the adjustment);
- ``sightings``: per camera the wand sightings found, used, dropped (above), seen in a frame
  no other camera saw (``single_camera``: no correspondence, unusable), and ``other`` (ends not
  ordered consistently with the other cameras, or frames left out by the subsampling);
- ``sightings_not_in_adjustment``: ordered wand sightings of frames the adjustment did not use;
- for cameras calibrated from the wand alone, ``distortion_determined_within_px``: how far from
  the principal point the sightings reach (99th percentile), within which the distortion
  estimate is judged; ``distortion_determined_image_share``: the share of the image inside that
  radius (beyond it the distortion is extrapolated, not determined);
- ``points``: static points used, sightings skipped and why, reprojection RMS per camera.
"""

from __future__ import annotations

import numpy as np

from mocap.calib.priors import refinement_report
from mocap.calib.quality import coverage_share


def image_share_within(camera, radius_px: float) -> float:
    """Share of the image's pixels within ``radius_px`` of the camera's principal point (on a
    64 x 64 grid of pixel centres)."""
    x = (np.arange(64) + 0.5) / 64 * camera.width
    y = (np.arange(64) + 0.5) / 64 * camera.height
    d = np.hypot(x[None, :] - camera.K[0, 2], y[:, None] - camera.K[1, 2])
    return float(np.mean(d <= radius_px))


def rig_report(rig, obs, used, models, priors, result, not_determined, points, extra, *,
               given=None, reach_px=None) -> dict:
    """The per-camera report (module docstring); ``models`` each camera's
    :class:`mocap.calib.bundle.IntrinsicsModel` (cameras without priors); ``obs`` the ordered
    wand sightings, ``used``
    the final adjustment's, ``result`` its :class:`mocap.calib.bundle.BundleResult`, ``given``
    the wand sightings found (before their ends were ordered), ``reach_px`` (n_cameras,) how far
    from each principal point the sightings reach (99th percentile, px)."""
    per_cam, coverage, dropped_n = {}, {}, {}
    given = obs if given is None else given
    g_frames, g_views = np.unique(given.frame, return_counts=True)
    single = np.isin(given.frame, g_frames[g_views == 1])
    accounted = {}
    for i, c in enumerate(rig):
        p = priors.get(c.id)
        if p is not None:
            per_cam[c.id] = {"source": f"prior {'fixed' if p.mode == 'fixed' else 'refined'}",
                             "file": p.source,
                             "principal_point": "prior" if p.mode == "fixed" else "prior, refined",
                             "distortion": "prior" if p.mode == "fixed" else "prior, refined",
                             "not_determined": []}
        else:
            intrinsics = models[i]
            per_cam[c.id] = {"source": "wand",
                             "principal_point": ("estimated" if intrinsics.principal_point == "free"
                                                 else "fixed at the image centre"),
                             "distortion": intrinsics.distortion,
                             "not_determined": list(not_determined.get(c.id, []))}
            if reach_px is not None and intrinsics.distortion != "none":
                per_cam[c.id]["distortion_determined_within_px"] = float(reach_px[i])
                per_cam[c.id]["distortion_determined_image_share"] = image_share_within(
                    c, float(reach_px[i]))
        n_given = int(np.sum(given.camera == i))
        n_single = int(np.sum(single & (given.camera == i)))
        n_used = int(np.sum(used & (obs.camera == i)))
        w = obs.uv[obs.camera == i]
        pts = (points.uv[(points.camera == i) & extra["points_used"]] if points is not None
               else np.zeros((0, 2)))
        coverage[c.id] = {"wand": coverage_share(w, c.width, c.height),
                          "points": coverage_share(pts, c.width, c.height),
                          "both": coverage_share(np.concatenate([w.reshape(-1, 2), pts]),
                                                 c.width, c.height)}
        dropped_n[c.id] = sum(1 for d in extra["dropped"] if d["camera"] == c.id)
        accounted[c.id] = {"found": n_given, "used": n_used, "dropped": dropped_n[c.id],
                           "single_camera": n_single,
                           "other": n_given - n_used - dropped_n[c.id] - n_single}
    in_frames = np.isin(obs.frame, obs.frame[used])
    out = {"intrinsics_per_camera": per_cam,
           "prior_refinement": refinement_report(rig, priors, result.camera_covariance),
           "coverage": coverage,
           "sightings_dropped": dropped_n,
           "dropped": _columns(extra["dropped"], [c.id for c in rig]),
           "sightings_not_in_adjustment": int(np.sum(~in_frames)),
           "sightings": accounted}
    if points is not None:
        pu = extra["points_used"]
        rms = {}
        cam_used = points.camera[pu]
        for i, c in enumerate(rig):
            r = (result.point_residuals[cam_used == i] if result.point_residuals is not None
                 else np.zeros((0, 2)))
            rms[c.id] = float(np.sqrt(np.mean(r**2))) if r.size else float("nan")
        out["points"] = {"points": int(extra["point_ids"].size), "sightings": int(pu.sum()),
                         "skipped": dict(points.skipped), "reprojection_rms_px": rms}
    return out


def _columns(dropped: list[dict], ids) -> dict:
    """The dropped sightings per camera as columns (a TOML-friendly table per camera)."""
    out = {}
    for cid in ids:
        rows = [d for d in dropped if d["camera"] == cid]
        if rows:
            out[cid] = {k: [d[k] for d in rows]
                        for k in ("kind", "frame", "residual_px", "threshold_px", "stage")}
    return out
