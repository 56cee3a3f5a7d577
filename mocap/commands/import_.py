"""``mocap import``: vendors' exports to a labeled session."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DESCRIPTION = """\
Turn C3D files, OptiTrack Motive CSV exports, Qualisys QTM TSV 3D exports and Vicon Nexus CSV
exports into a labeled session (docs/format.md, 3D takes), one take per file. Commands come from C3D
analog channels named DU<n> or from --commands (one file only). The manifest is written for you
to complete (take kinds, DU names); every repair made on the way (units converted, duplicate
labels renamed, rigid bodies ignored, missing frames filled as gaps) is listed in
import_report.json and printed.

examples:
  mocap import trial01.c3d trial02.c3d --out sessions/robot1
  mocap import take.csv --fps 120 --commands take_commands.csv --out sessions/motive1
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("files", type=Path, nargs="+", help=".c3d, Motive/Vicon .csv or QTM .tsv files")
    p.add_argument("--out", type=Path, required=True, help="new session folder")
    p.add_argument("--commands", type=Path, default=None, help="command CSV for a single file")
    p.add_argument("--fps", type=float, default=None, help="frame rate, where a file lacks it")


def run(args: argparse.Namespace) -> int:
    from mocap.interop.marker_data import ImportError_
    from mocap.interop.session_io import import_files
    from mocap.paths import OutputPathError, check_output_path

    try:
        check_output_path(args.out, inputs=[*args.files, *([args.commands] if args.commands else [])])
    except OutputPathError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    try:
        report = import_files(args.files, args.out, commands=args.commands, fps=args.fps)
    except ImportError_ as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(f"session written to {report['session']}: {len(report['takes'])} takes, "
          f"{len(report['markers'])} markers at {report['fps']:g} Hz, DUs {report['dus']}")
    for n in report["notes"]:
        print(f"  note: {n}")
    print("to complete in session.toml:")
    for t in report["to_complete"]:
        print(f"  - {t}")
    return 0
