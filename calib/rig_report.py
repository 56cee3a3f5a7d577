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
  ``dropped``: each one (kind wand or points, frame, residual and the threshold it exceeded,
  px: 6 sd of the residual predicted at that image point, from the camera's noise and the
  model's uncertainty there, at least 0.6 px);
- ``sightings_not_in_adjustment``: wand sightings of frames the adjustment did not use (seen
  by a single camera, or left out by the frame subsampling) -- not dropped, not judged;
- ``points``: static points used, sightings skipped and why, reprojection RMS per camera.
"""

from __future__ import annotations

import numpy as np

from mocap.calib.priors import refinement_report
from mocap.calib.quality import coverage_share


def rig_report(rig, obs, used, intrinsics, priors, result, not_determined, points, extra) -> dict:
    """The per-camera report (module docstring); ``obs`` the ordered wand sightings, ``used``
    the final adjustment's, ``result`` its :class:`mocap.calib.bundle.BundleResult`."""
    per_cam, coverage, dropped_n = {}, {}, {}
    for i, c in enumerate(rig):
        p = priors.get(c.id)
        if p is not None:
            per_cam[c.id] = {"source": f"prior {'fixed' if p.mode == 'fixed' else 'refined'}",
                             "file": p.source,
                             "principal_point": "prior" if p.mode == "fixed" else "prior, refined",
                             "distortion": "prior" if p.mode == "fixed" else "prior, refined",
                             "not_determined": []}
        else:
            per_cam[c.id] = {"source": "wand",
                             "principal_point": ("estimated" if intrinsics.principal_point == "free"
                                                 else "fixed at the image centre"),
                             "distortion": intrinsics.distortion,
                             "not_determined": list(not_determined.get(c.id, []))}
        w = obs.uv[obs.camera == i]
        pts = (points.uv[(points.camera == i) & extra["points_used"]] if points is not None
               else np.zeros((0, 2)))
        coverage[c.id] = {"wand": coverage_share(w, c.width, c.height),
                          "points": coverage_share(pts, c.width, c.height),
                          "both": coverage_share(np.concatenate([w.reshape(-1, 2), pts]),
                                                 c.width, c.height)}
        dropped_n[c.id] = sum(1 for d in extra["dropped"] if d["camera"] == c.id)
    in_frames = np.isin(obs.frame, obs.frame[used])
    out = {"intrinsics_per_camera": per_cam,
           "prior_refinement": refinement_report(rig, priors, result.camera_covariance),
           "coverage": coverage,
           "sightings_dropped": dropped_n,
           "dropped": extra["dropped"],
           "sightings_not_in_adjustment": int(np.sum(~in_frames))}
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
