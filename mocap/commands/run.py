"""``mocap run``: process a session, raw camera exports to results (docs/outputs.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DESCRIPTION = """\
Process a capture session (docs/format.md) and write the results (docs/outputs.md) into OUT_DIR.
The raw session is never modified; every output file is written atomically.

examples:
  mocap run sample_data/session --out out/sample
  mocap run sample_data/session --out out/fast --no-rrd --min-cameras 2
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("session_dir", type=Path, help="session folder holding session.toml")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--jobs", type=int, default=None,
                   help="processes reconstructing takes in parallel (default: all cores)")
    p.add_argument("--no-rrd", action="store_true", help="skip the Rerun recording (session.rrd)")
    p.add_argument("--all-blobs", action="store_true",
                   help="record the 2D blobs of every take (default: wand, rest, first response)")
    p.add_argument("--min-cameras", type=int, default=3,
                   help="cameras a sample needs to enter the analyses (default 3, as the paper; "
                        "2 is the minimum); points two cameras see are always in the trajectories")
    p.add_argument("--fill-gaps", type=int, default=0, metavar="FRAMES",
                   help="interpolate gaps up to FRAMES frames (flagged in the trajectories)")


def run(args: argparse.Namespace) -> int:
    from mocap.calib.wand_calibration import CalibrationError
    from mocap.paths import check_output_path
    from mocap.pipeline import run_session
    from mocap.session import SessionError

    def say(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    from mocap.pipeline import RunSettings
    from mocap.reconstruct.correspondence import ReconstructionSettings

    settings = RunSettings(reconstruction=ReconstructionSettings(min_cameras=args.min_cameras),
                           fill_gaps_frames=args.fill_gaps, recording=not args.no_rrd,
                           record_blobs="all" if args.all_blobs else "subset")
    if args.jobs is not None:
        import dataclasses

        settings = dataclasses.replace(settings, jobs=max(1, args.jobs))
    try:
        check_output_path(args.out, sessions=[args.session_dir])
        result = run_session(args.session_dir, args.out, progress=say, settings=settings)
    except (SessionError, CalibrationError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    s = result.summary
    print(f"{s['session']['name']}: {sum(s['counts']['takes'].values())} takes, "
          f"{s['counts']['rows']} face-take rows; stages: {', '.join(s['stages'])}; "
          f"results in {result.out_dir}")
    a = result.audit or {}
    print(f"audit verdict: {a.get('verdict')}")
    if a.get("missing_markers"):
        print(f"  markers in markers.csv never reconstructed: {', '.join(a['missing_markers'])}")
    for f in a.get("flagged", []):
        if f["kind"] == "marker" and f["item"] not in a.get("missing_markers", []):
            print(f"  marker {f['item']}: {f['verdict']} ({f['why']})")
    return 0
