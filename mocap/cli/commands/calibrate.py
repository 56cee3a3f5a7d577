"""``mocap calibrate``: wand calibration of a session's camera rig."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DESCRIPTION = """\
Calibrate the camera rig from the session's wand take (a waved wand of 2 or more collinear
markers, the manifest's [wand]; with 2 the ends are told apart by geometry) and ground take
(the square that sets the world frame, the manifest's [ground]; without one the world frame is
the first camera's, scaled by the wand), with no prior knowledge of where the cameras are.
Cameras without focal_px get their focal length searched. Intrinsics: by default, per camera,
the richest model its frames determine (principal point free and k1 k2 p1 p2, else principal point at the
image centre with k1 k2, k1, or none); --principal-point / --distortion ask for one model (an
error when the frames cannot determine it). Prior intrinsics (a lens profile or a board
calibration) come from the manifest (principal_px, distortion, intrinsics) or from
--intrinsics FILE (an aniposelib calibration.toml, an OpenCV YAML, an Argus/easyWand profile;
repeatable, matched by camera id): used as given (--intrinsics-mode fixed) or refined by the
wand under the prior (refine; the report says by how much). Static points (points takes) add
correspondences. Writes calibration.toml (docs/outputs.md) with a quality
report, and on request the same cameras as aniposelib's calibration.toml (anipose, Pose2Sim,
caliscope), DLT coefficients (easyWand, DLTdv, Argus; linear: no distortion) or OpenCV YAML;
progress goes to stderr.

examples:
  mocap calibrate sample_data/session --out calibration.toml
  mocap calibrate sample_data/session --out calib.toml --opencv-dir calib_yaml/
  mocap calibrate lab_wand --out calib.toml --principal-point fixed --distortion k1 \
      --anipose anipose_calibration.toml --dlt wand_dltCoefs.csv
  mocap calibrate lab_wand --out calib.toml --intrinsics lens_profile.txt --intrinsics-mode fixed
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("session_dir", type=Path, help="session folder holding session.toml")
    p.add_argument("--out", type=Path, required=True, help="calibration.toml to write")
    p.add_argument("--opencv-dir", type=Path, default=None,
                   help="also write one OpenCV FileStorage YAML per camera into this folder")
    p.add_argument("--max-frames", type=int, default=3600,
                   help="most wand frames in the bundle adjustment (default 3600)")
    p.add_argument("--principal-point", choices=("free", "fixed"), default=None,
                   help="estimate the principal point, or hold it at the image centre")
    p.add_argument("--distortion", choices=("none", "k1", "k1k2", "k1k2p1p2"), default=None,
                   help="Brown-Conrady terms to estimate (default: the richest the frames determine)")
    p.add_argument("--intrinsics", type=Path, action="append", default=None, metavar="FILE",
                   help="prior intrinsics per camera id: aniposelib calibration.toml, OpenCV "
                        "YAML or Argus/easyWand profile (repeatable; overrides the manifest's)")
    p.add_argument("--intrinsics-mode", choices=("refine", "fixed"), default="refine",
                   help="--intrinsics used as given (fixed) or refined by the wand (default)")
    p.add_argument("--anipose", type=Path, default=None,
                   help="also write aniposelib's calibration.toml layout here")
    p.add_argument("--anipose-units", choices=("mm", "m"), default="mm",
                   help="translation unit of --anipose (Pose2Sim reads metres; default mm)")
    p.add_argument("--dlt", type=Path, default=None,
                   help="also write 11 DLT coefficients per camera (easyWand's CSV, bottom-left "
                        "origin; the linear model drops distortion)")


def run(args: argparse.Namespace) -> int:
    from mocap.calib.calibration_file import write_calibration
    from mocap.calib.opencv_yaml import write_opencv_yaml
    from mocap.calib.priors import PriorFileError, read_priors
    from mocap.calib.interchange import write_anipose, write_dlt_csv
    from mocap.calib.wand_calibration import CalibrationError, IntrinsicsModel, calibrate_session
    from mocap.core.paths import check_output_path
    from mocap.core.session import SessionError, load_session

    def say(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    try:
        check_output_path(args.out, sessions=[args.session_dir], kind="file")
        if args.opencv_dir is not None:
            check_output_path(args.opencv_dir, sessions=[args.session_dir], option="--opencv-dir",
                              kind="folder")
        session = load_session(args.session_dir)
        if session.dimension != "2d":
            raise CalibrationError(f"{args.session_dir}: a labeled 3D session has no cameras to calibrate")
        intrinsics = None
        if args.principal_point or args.distortion:
            intrinsics = IntrinsicsModel(args.principal_point or "free",
                                         args.distortion or "k1k2p1p2")
        priors = {}
        for path in args.intrinsics or []:
            priors.update(read_priors(path, mode=args.intrinsics_mode))
        result = calibrate_session(session, max_frames=args.max_frames, intrinsics=intrinsics,
                                   priors=priors, progress=say)
    except (SessionError, CalibrationError, PriorFileError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    write_calibration(args.out, result.rig, result.quality)
    if args.opencv_dir:
        for cam in result.rig:
            write_opencv_yaml(cam, args.opencv_dir / f"{cam.id}.yml")
    if args.anipose:
        write_anipose(args.anipose, result.rig, units=args.anipose_units,
                      metadata={"error": result.quality["reprojection_rms_px_all"]})
    if args.dlt:
        write_dlt_csv(args.dlt, result.rig)
    q = result.quality
    print(f"calibration {q['rating']}: reprojection rms {q['reprojection_rms_px_all']:.3f} px, "
          f"wand length error {q['wand_length_error_mean_mm']:+.4f} +- "
          f"{q['wand_length_error_sd_mm']:.4f} mm; written to {args.out}")
    print(f"world frame: {q['world_frame']}; intrinsics: principal point "
          f"{q['intrinsics']['principal_point']}, distortion {q['intrinsics']['distortion']}")
    for cid, v in q["intrinsics_per_camera"].items():
        line = f"  {cid}: intrinsics from the {v['source']}"
        if v["source"] == "wand" and "distortion_determined_image_share" in v:
            line += (f"; distortion determined within {v['distortion_determined_within_px']:.0f} "
                     f"px of the principal point ({v['distortion_determined_image_share']:.0%} of "
                     "the image)")
        if v["not_determined"]:
            line += "; not determined: " + "; ".join(v["not_determined"])
        ref = q["prior_refinement"].get(cid, {}).get("parameters")
        if ref:
            line += "; refined: " + ", ".join(f"{k} {p['change']:+.3g} (wand share "
                                              f"{p['wand_share']:.2f})" for k, p in ref.items())
        cov = q["coverage"][cid]
        s = q["sightings"][cid]
        line += (f"; image covered {cov['both']:.0%}; sightings {s['used']} used, "
                 f"{s['dropped']} dropped, {s['single_camera']} seen by this camera alone")
        print(line)
    for cid, d in q["dropped"].items():
        print(f"  {cid}: dropped as outliers ({len(d['frame'])}, residual over 6 sd of its "
              "prediction): " + "; ".join(
                  f"frame {f} ({k}) {r:.2f} > {t:.2f} px" for f, k, r, t in
                  list(zip(d["frame"], d["kind"], d["residual_px"], d["threshold_px"]))[:10])
              + (" ..." if len(d["frame"]) > 10 else ""))
    return 0
