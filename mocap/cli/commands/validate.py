"""``mocap validate``: check a session directory against the input contract and summarise it."""

from __future__ import annotations

import argparse
import sys
import warnings
from dataclasses import dataclass

import numpy as np

DESCRIPTION = """\
Check a capture session directory against the input contract (docs/format.md): the manifest
(session.toml), every take file and every commands file, row by row. Prints a one-screen
summary (cameras, takes by kind with frames and rows, DUs, warnings) and exits 0; on the first
contract violation prints "error: <file> <line/key>: <what was expected>" and exits 1.

example:
  mocap validate sample_data/session
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("session_dir", metavar="SESSION_DIR", help="the session directory")


@dataclass(frozen=True)
class _KindSummary:
    takes: int
    frames: int
    rows: int
    seen: int
    command_rows: int


def _summarise_takes(session) -> dict[str, _KindSummary]:
    """Read every take (and commands file) fully; totals by kind, in manifest kind order."""
    totals: dict[str, list[int]] = {}
    for take in session.takes:
        df = session.read_take(take.name)
        if session.dimension == "3d":
            seen = int(np.isfinite(df[["x", "y", "z"]].to_numpy()).all(axis=1).sum())
        else:
            seen = len(df)
        commands = len(session.read_commands(take.name)) if take.commands is not None else 0
        t = totals.setdefault(take.kind, [0, 0, 0, 0, 0])
        t[0] += 1
        t[1] += session.n_frames(take.name)
        t[2] += len(df)
        t[3] += seen
        t[4] += commands
    return {kind: _KindSummary(*v) for kind, v in totals.items()}


def _summary(session, by_kind: dict[str, _KindSummary]) -> str:
    lines = [
        f"session   {session.name}",
        f"folder    {session.root}",
        f"fps       {session.fps:g}",
    ]
    if session.dimension == "2d":
        lines.append("data      2D blob detections (frame, camera, x, y)")
    else:
        lines.append("data      labeled 3D markers (frame, marker, x, y, z)")
    if session.cameras or session.dimension == "2d":
        lines.append(f"cameras   {len(session.cameras)}")
    else:
        lines.append("cameras   none (labeled 3D data needs none)")
    for cam in session.cameras:
        focal = "none" if cam.focal_px is None else f"{cam.focal_px:g} px"
        lines.append(f"  {cam.id:<10} {cam.width} x {cam.height} px   focal {focal}")
    if session.wand is not None:
        offsets = ", ".join(f"{v:g}" for v in session.wand.marker_offsets_mm)
        lines.append(f"wand      {session.wand.marker_offsets_mm.size} markers at {offsets} mm")
    if session.ground is not None:
        lines.append(f"ground    {session.ground.markers_mm.shape[0]} markers")
    rows_name = "blobs" if session.dimension == "2d" else "samples"
    lines.append(f"takes     {len(session.takes)}")
    lines.append(
        f"  {'kind':<10} {'takes':>5} {'frames':>9} {rows_name:>11}"
        + ("" if session.dimension == "2d" else f" {'seen':>11}")
        + f" {'commands':>9}"
    )
    for kind, s in by_kind.items():
        seen = "" if session.dimension == "2d" else f" {s.seen:>11}"
        lines.append(
            f"  {kind:<10} {s.takes:>5} {s.frames:>9} {s.rows:>11}{seen} {s.command_rows:>9}"
        )
    lines.append(f"DUs       {len(session.dus)}")
    for du in session.dus:
        loop = "feedback" if du.feedback else "open loop"
        lines.append(f"  {du.id:<4} {du.name}  ({loop})")
    if session.marker_template is not None:
        lines.append(f"markers   markers.csv: {len(session.marker_template)} markers")
    else:
        lines.append("markers   no markers.csv (markers will be named by the package)")
    lines.append(f"warnings  {len(session.warnings) or 'none'}")
    lines += [f"  - {w}" for w in session.warnings]
    lines.append("ok: the session meets the input contract")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from mocap.core.session import SessionError, SessionWarning, load_session

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SessionWarning)  # listed in the summary instead
            session = load_session(args.session_dir)
        by_kind = _summarise_takes(session)
    except SessionError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(_summary(session, by_kind))
    return 0
