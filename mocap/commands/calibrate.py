"""``mocap calibrate``: wand calibration of a session's camera rig."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DESCRIPTION = """\
Calibrate the camera rig from the session's wand take (a waved wand of collinear markers, the
manifest's [wand]) and ground take (the square that sets the world frame, the manifest's
[ground]), with no prior knowledge of where the cameras are. Writes calibration.toml (docs/outputs.md)
with a quality report; progress goes to stderr.

examples:
  mocap calibrate sample_data/session --out calibration.toml
  mocap calibrate sample_data/session --out calib.toml --opencv-dir calib_yaml/
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("session_dir", type=Path, help="session folder holding session.toml")
    p.add_argument("--out", type=Path, required=True, help="calibration.toml to write")
    p.add_argument("--opencv-dir", type=Path, default=None,
                   help="also write one OpenCV FileStorage YAML per camera into this folder")
    p.add_argument("--max-frames", type=int, default=3600,
                   help="most wand frames in the bundle adjustment (default 3600)")


def run(args: argparse.Namespace) -> int:
    from mocap.calib.calibration_file import write_calibration
    from mocap.calib.opencv_yaml import write_opencv_yaml
    from mocap.calib.wand_calibration import CalibrationError, calibrate_session
    from mocap.paths import check_output_path
    from mocap.session import SessionError, load_session

    def say(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    try:
        check_output_path(args.out, sessions=[args.session_dir])
        if args.opencv_dir is not None:
            check_output_path(args.opencv_dir, sessions=[args.session_dir], option="--opencv-dir")
        session = load_session(args.session_dir)
        if session.dimension != "2d":
            raise CalibrationError(f"{args.session_dir}: a labeled 3D session has no cameras to calibrate")
        result = calibrate_session(session, max_frames=args.max_frames, progress=say)
    except (SessionError, CalibrationError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    write_calibration(args.out, result.rig, result.quality)
    if args.opencv_dir:
        for cam in result.rig:
            write_opencv_yaml(cam, args.opencv_dir / f"{cam.id}.yml")
    q = result.quality
    print(f"calibration {q['rating']}: reprojection rms {q['reprojection_rms_px_all']:.3f} px, "
          f"wand length error {q['wand_length_error_mean_mm']:+.4f} +- "
          f"{q['wand_length_error_sd_mm']:.4f} mm; written to {args.out}")
    return 0
