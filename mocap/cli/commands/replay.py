"""``mocap replay``: open a run's Rerun recording in the viewer."""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from pathlib import Path

DESCRIPTION = """\
Open OUT_DIR/session.rrd (written by 'mocap run') in the Rerun viewer: the camera rig, the 2D
blobs by role, the wand, the labeled 3D markers and their paths for every take, the commands,
the response curves with their fitted sigmoids, the property chart and the rejections, on the
capture's own timeline. Where no display is available it prints how to open the file elsewhere.

example:
  mocap replay out/sample
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("out_dir", type=Path,
                   help="a 'mocap run' or 'mocap discrepancy' output folder (or an .rrd file)")


def run(args: argparse.Namespace) -> int:
    rrd = args.out_dir if args.out_dir.suffix == ".rrd" else args.out_dir / "session.rrd"
    if not rrd.is_file() and (args.out_dir / "discrepancy.rrd").is_file():
        rrd = args.out_dir / "discrepancy.rrd"  # a 'mocap discrepancy' output folder
    if not rrd.is_file():
        print(f"error: {rrd}: no recording (run 'mocap run SESSION --out {args.out_dir}' without "
              "--no-rrd first)", file=sys.stderr)
        return 1
    viewer = shutil.which("rerun")
    has_display = bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
                       or sys.platform in ("darwin", "win32"))
    if not has_display or viewer is None:
        print(f"No display here. Copy {rrd} to a machine with a screen and run:\n"
              f"  rerun {rrd.name}\n"
              f"(the 'rerun' viewer comes with 'pip install rerun-sdk'), or serve it to a browser:\n"
              f"  rerun --web-viewer {rrd}")
        return 0
    subprocess.Popen([viewer, str(rrd)])
    print(f"opened {rrd} in the Rerun viewer")
    return 0
