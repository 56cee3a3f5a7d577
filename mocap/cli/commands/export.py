"""``mocap export``: labeled trajectories to C3D."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DESCRIPTION = """\
Write the labeled trajectories of a 'mocap run' output (or of a labeled session) as C3D: marker
labels, the capture rate, mm, gaps marked invalid (residual -1), and each DU's commands as an
analog channel DU<nn> at the point rate. Opens in Vicon Nexus, Visual3D, Mokka, ezc3d, c3d.

examples:
  mocap export out/sample --c3d out/c3d/             # every take, one file each
  mocap export out/sample --c3d du04_t01.c3d --take du04_t01
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", type=Path, help="'mocap run' output folder or labeled session")
    p.add_argument("--c3d", type=Path, required=True, help="a .c3d file (one take) or a folder")
    p.add_argument("--take", action="append", default=None, help="take to export (repeatable)")


def run(args: argparse.Namespace) -> int:
    from mocap.interop.marker_data import ImportError_
    from mocap.interop.session_io import export_c3d
    from mocap.core.paths import check_output_path, session_dir_of
    from mocap.core.session import SessionError

    try:
        check_output_path(args.c3d, sessions=[s for s in [session_dir_of(args.source)] if s],
                          option="--c3d")
        written = export_c3d(args.source, args.c3d, args.take)
    except (ImportError_, SessionError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(f"{len(written)} C3D file(s) written: {', '.join(str(w) for w in written[:5])}"
          + (" ..." if len(written) > 5 else ""))
    return 0
