"""``mocap import``: vendors' exports to a labeled session."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DESCRIPTION = """\
Turn C3D files, OptiTrack Motive CSV exports, Qualisys QTM TSV 3D exports and Vicon Nexus CSV
exports into a labeled session (docs/format.md, 3D takes), one take per file, ready for
'mocap run'. What each file is comes from a take table (--takes: CSV with the columns
file,name,kind,du,trial,plan,commands,commands_offset_s, all but file optional) or from name
patterns (--pattern "du{du}_t{trial}": a matching file is a response take of that DU and
trial); rest, wand and ground takes are recognised by name. Without either, every other file is
a motion take for you to complete. Command logs (time_s,du,command) come from the table, from a
folder of logs named like the takes (--commands DIR: smile_DU1_trial2_commands.csv for
smile_DU1_trial2.c3d), from one file for a single take, or else from C3D analog channels named
DU<n>. DUs are named from --dus (CSV du,name[,feedback]) or numbered. Everything the import
guessed, and every repair made on the way (units converted, duplicate labels renamed, rigid
bodies ignored, missing frames filled as gaps), is printed and kept in import_report.json
beside session.toml. See docs/import.md.

Other labs' wand recordings become a session of unlabeled 2D blobs with one wand take, ready
for 'mocap calibrate' (no ground square: the world frame is the first camera's): per-blob
tables (frame, camera, x, y[, status, radius]: e.g. pyOpenLPT's wand points, whose Raw rows
are taken) and DLTdv/easyWand/Argus xypts.csv files (bottom-left origin, NaN when unseen) with
a camera profile or --image-size. --wand-offsets is required for them. A profile (an
Argus/easyWand profile .txt, an aniposelib calibration.toml or an OpenCV YAML) gives each
camera's image size and its prior intrinsics (focal length, principal point, distortion),
which 'mocap calibrate' refines (--intrinsics-mode fixed: uses them as given). --points adds
static background points (a DLTdv/easyWand xypts.csv) as a points take.

--align-commands proposes each take's commands_offset_s (the capture time of its command file's
time 0, for command logs not started with the cameras): from --sync-channel (a C3D analog
channel whose first edge marks the log's time 0) where the file has it, otherwise from the
motion against the commands, which also counts the face's own dead time (after applying such
an offset 'mocap discrepancy' cannot find one). Takes whose offsets differ by more than a frame
are flagged. '--align-commands apply' writes the offsets into session.toml; without 'apply'
they are only reported (printed and in import_report.json).

examples:
  mocap import lab/*.c3d --takes lab/takes.csv --commands lab/commands --out sessions/robot1
  mocap import lab/*.c3d --pattern "smile_DU{du}_trial{trial}" --commands lab --dus dus.csv --out s1
  mocap import trial01.c3d trial02.c3d --out sessions/robot1
  mocap import take.csv --fps 120 --commands take_commands.csv --out sessions/motive1
  mocap import trial01.c3d trial02.c3d --out s3 --align-commands apply --sync-channel SYNC
  mocap import wand_points.csv --wand-offsets 0,660 --image-size 1280x800 --out sessions/lab_wand
  mocap import wand_xypts.csv --profile profile.txt --wand-offsets 0,660 --fps 100 --out s2
  mocap import wand_xypts.csv --profile calibration.toml --points bkgd_xypts.csv \
      --wand-offsets 0,660 --out s3
"""

GUESSES_SHOWN = 40  # printed; all are in import_report.json


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("files", type=Path, nargs="*",
                   help=".c3d, Motive/Vicon .csv or QTM .tsv files (with --takes: default the "
                        "table's files)")
    p.add_argument("--out", type=Path, required=True, help="new session folder")
    p.add_argument("--takes", type=Path, default=None, metavar="CSV",
                   help="take table: file,name,kind,du,trial,plan,commands,commands_offset_s "
                        "(all but file optional)")
    p.add_argument("--pattern", action="append", default=[], metavar="PATTERN",
                   help="file-name pattern with {du}, {trial}, {plan} and * (e.g. "
                        "'du{du}_t{trial}'); repeat for several; used without --takes")
    p.add_argument("--commands", type=Path, default=None, metavar="DIR_OR_CSV",
                   help="folder of command logs matched by take name or file stem, or one "
                        "command CSV for a single file")
    p.add_argument("--dus", type=Path, default=None, metavar="CSV",
                   help="DU table: du,name[,feedback]; DUs not in it are named 'DU <n>'")
    p.add_argument("--fps", type=float, default=None, help="frame rate, where a file lacks it")
    p.add_argument("--align-commands", nargs="?", const="report", default=None,
                   choices=("report", "apply"),
                   help="propose each take's commands_offset_s; 'apply' writes them into "
                        "session.toml (default: report only)")
    p.add_argument("--sync-channel", default=None, metavar="NAME",
                   help="with --align-commands: the C3D analog channel whose first edge marks "
                        "each command log's time 0")
    p.add_argument("--wand-offsets", default=None,
                   help="wand recordings: marker offsets along the wand, mm (e.g. 0,660)")
    p.add_argument("--image-size", default=None,
                   help="wand recordings: every camera's image size WIDTHxHEIGHT, px")
    p.add_argument("--profile", type=Path, default=None,
                   help="wand recordings: camera profile (Argus/easyWand .txt, aniposelib "
                        "calibration.toml or OpenCV .yml): image size and prior intrinsics")
    p.add_argument("--intrinsics-mode", choices=("refine", "fixed"), default="refine",
                   help="wand recordings: the profile's intrinsics refined by the wand "
                        "(default) or used as given")
    p.add_argument("--points", type=Path, default=None,
                   help="wand recordings: static background points, a DLTdv/easyWand xypts.csv")


def run(args: argparse.Namespace) -> int:
    from mocap.interop.marker_data import ImportError_
    from mocap.interop.wand_points import is_blob_table, is_xypts
    from mocap.core.paths import OutputPathError, check_output_path

    if not args.files and args.takes is None:
        print("error: mocap import needs FILES or a take table (--takes)", file=sys.stderr)
        return 2
    if args.takes is not None and args.pattern:
        print("error: give --takes or --pattern, not both (the table says what each file is)",
              file=sys.stderr)
        return 2
    extra = [p for p in (args.commands, args.takes, args.dus) if p is not None]
    try:
        check_output_path(args.out, inputs=[*args.files, *extra])
    except OutputPathError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    if len(args.files) == 1 and args.takes is None and (is_blob_table(args.files[0])
                                                        or is_xypts(args.files[0])):
        try:
            return _import_wand(args)
        except ImportError_ as e:
            print(f"error: {e}", file=sys.stderr)
            return 1
    try:
        report = _import_takes(args)
    except ImportError_ as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print_report(report)
    if args.align_commands:
        return _align(args, report)
    if args.sync_channel:
        print("  note: --sync-channel is read only with --align-commands", file=sys.stderr)
    return 0


def _import_takes(args: argparse.Namespace) -> dict:
    """The labeled import (:func:`mocap.interop.session_io.import_files`): its report."""
    from mocap.interop.session_io import import_files

    return import_files(args.files, args.out, commands=args.commands, fps=args.fps,
                        takes=args.takes, patterns=args.pattern, dus=args.dus)


def print_report(report: dict) -> None:
    """What was written, guessed and noted, and what is left to complete (stdout)."""
    kinds = ", ".join(f"{n} {k}" for k, n in report["kinds"].items())
    print(f"session written to {report['session']}: {len(report['takes'])} takes ({kinds}), "
          f"{len(report['markers'])} markers at {report['fps']:g} Hz, DUs {report['dus']}")
    for n in report["notes"]:
        print(f"  note: {n}")
    guessed = report["guessed"]
    if guessed:
        print(f"guessed ({len(guessed)}; check them, all are listed in import_report.json):")
        for g in guessed[:GUESSES_SHOWN]:
            print(f"  - {g}")
        if len(guessed) > GUESSES_SHOWN:
            print(f"  ... and {len(guessed) - GUESSES_SHOWN} more")
    if report["to_complete"]:
        print("to complete in session.toml:")
        for t in report["to_complete"]:
            print(f"  - {t}")
    else:
        print(f"ready: mocap run {report['session']} --out OUT")


def _align(args: argparse.Namespace, report: dict) -> int:
    from mocap.interop.align import (
        align_session,
        alignment_lines,
        update_import_report,
        write_offsets,
    )
    from mocap.core.session import SessionError

    sources = {t["name"]: t["source"] for t in report.get("takes", []) if "source" in t}
    try:
        alignment = align_session(args.out, sources=sources, sync_channel=args.sync_channel)
    except SessionError as e:
        print(f"error: --align-commands: the imported session does not load yet ({e}); complete "
              f"session.toml, then run the import again with --align-commands", file=sys.stderr)
        return 1
    apply = args.align_commands == "apply"
    offsets = {k: v["offset_s"] for k, v in alignment["takes"].items() if v["offset_s"] is not None}
    if apply and offsets:
        try:
            write_offsets(args.out, offsets)
        except ValueError as e:
            print(f"error: --align-commands apply: {e}", file=sys.stderr)
            apply = offsets = None
    update_import_report(args.out, alignment, apply and bool(offsets))
    for line in alignment_lines(alignment, apply and bool(offsets)):
        print(line)
    return 1 if offsets is None else 0


def _import_wand(args: argparse.Namespace) -> int:
    from mocap.interop.marker_data import ImportError_
    from mocap.interop.wand_points import (
        CameraProfile,
        is_xypts,
        read_blob_table,
        read_camera_profile,
        read_points_xypts,
        read_xypts,
        write_wand_session,
    )

    path = args.files[0]
    if not args.wand_offsets:
        raise ImportError_(f"{path}: a wand recording needs --wand-offsets (mm along the wand)")
    try:
        offsets = [float(v) for v in args.wand_offsets.split(",")]
    except ValueError:
        raise ImportError_(f"--wand-offsets: expected numbers like 0,660; got {args.wand_offsets!r}") from None
    size = None
    if args.image_size:
        try:
            w, h = (int(v) for v in args.image_size.lower().split("x"))
            size = (w, h)
        except ValueError:
            raise ImportError_(f"--image-size: expected WIDTHxHEIGHT, got {args.image_size!r}") from None
    profile = (read_camera_profile(args.profile, intrinsics=args.intrinsics_mode)
               if args.profile else None)
    if is_xypts(path):
        if profile is None and size is None:
            raise ImportError_(f"{path}: DLTdv points need each camera's image height: give "
                               "--profile or --image-size")
        import pandas as pd

        n_cams = len({c.split("_")[1] for c in pd.read_csv(path, nrows=0).columns})
        cams = profile or [CameraProfile(f"cam{i + 1}", *size) for i in range(n_cams)]
        blobs = read_xypts(path, {c.id: c.height for c in cams})
    else:
        blobs = read_blob_table(path)
        if profile is None and size is None:
            raise ImportError_(f"{path}: give the cameras' image size (--image-size or --profile)")
        cams = profile or [CameraProfile(c, *size) for c in sorted(blobs["camera"].unique())]
    points = None
    if args.points is not None:
        if not args.points.is_file():
            raise ImportError_(f"--points: {args.points}: file not found")
        points = read_points_xypts(args.points, {c.id: c.height for c in cams})
    root = write_wand_session(args.out, blobs, cams, offsets, fps=args.fps or 100.0,
                              name=path.stem, source=str(path), points=points)
    print(f"session written to {root}: one wand take of {len(blobs)} blobs from "
          f"{len(cams)} cameras ({', '.join(c.id for c in cams)}); no ground square, so "
          "'mocap calibrate' puts the world frame at the first camera")
    with_prior = [c.id for c in cams if c.distortion is not None]
    if with_prior:
        print(f"  prior intrinsics ({args.intrinsics_mode}) from {args.profile.name} for "
              f"{', '.join(with_prior)}")
    if points is not None:
        print(f"  static points: {points.frame.nunique()} points, {len(points)} sightings "
              f"from {args.points.name}")
    if not args.fps:
        print("  note: no --fps given; 100 Hz assumed (only timing depends on it)")
    return 0
