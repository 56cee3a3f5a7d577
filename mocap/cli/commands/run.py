"""``mocap run``: process a session, raw camera exports to results (docs/outputs.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DESCRIPTION = """\
Process a capture session (docs/format.md) and write the results (docs/outputs.md) into OUT_DIR.
The raw session is never modified; every output file is written atomically.

Settings come from their defaults, then --config FILE (TOML), then the flags below;
--print-config lists every setting with its default and meaning (a valid --config file), and
summary.json records the effective ones. A rerun into the same OUT_DIR reuses every result
whose inputs (files, settings, code) did not change and says so; a killed run resumes from the
takes it finished; --force recomputes everything. One run at a time per OUT_DIR.

examples:
  mocap run sample_data/session --out out/sample
  mocap run sample_data/session --out out/fast --no-recording --min-cameras 2
  mocap run --print-config > run.toml
  mocap run sample_data/session --out out/sample --config run.toml --bootstrap-samples 50
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    from mocap.workflows.run.settings import add_flags

    p.add_argument("session_dir", type=Path, nargs="?", help="session folder holding session.toml")
    p.add_argument("--out", type=Path, help="output folder (required to run)")
    p.add_argument("--config", type=Path, metavar="TOML", help="settings file (see --print-config)")
    p.add_argument("--print-config", action="store_true",
                   help="print every setting with its default and meaning, then exit")
    p.add_argument("--force", action="store_true",
                   help="recompute everything, reusing nothing from an earlier run in OUT_DIR")
    p.add_argument("--quiet", action="store_true", help="no progress bars, no step messages")
    add_flags(p)
    legacy = p.add_argument_group("older spellings")
    legacy.add_argument("--no-rrd", dest="setting:recording", action="store_const", const=False,
                        help="= --no-recording")
    legacy.add_argument("--all-blobs", dest="setting:record_blobs", action="store_const",
                        const="all", help="= --record-blobs all")
    legacy.add_argument("--fill-gaps", dest="setting:fill_gaps_frames", type=int, metavar="FRAMES",
                        help="= --fill-gaps-frames FRAMES")


def settings_from(args: argparse.Namespace):
    """The effective settings: defaults < --config < flags."""
    from mocap.workflows.run.settings import RunSettings, flag_values, from_toml, with_values

    settings = from_toml(args.config) if args.config is not None else RunSettings()
    return with_values(settings, flag_values(args), "command line")


def run(args: argparse.Namespace) -> int:
    from mocap.calib.wand_calibration import CalibrationError
    from mocap.core.paths import OutputPathError, check_output_path
    from mocap.workflows.run.pipeline import run_session
    from mocap.workflows.run.lock import OutputInUse
    from mocap.outputs.run_writers import WRITERS
    from mocap.workflows.run.settings import describe
    from mocap.core.session import SessionError

    if args.print_config:
        print(describe(), end="")
        return 0
    if args.session_dir is None or args.out is None:
        print("error: mocap run needs SESSION_DIR and --out OUT_DIR (or --print-config)",
              file=sys.stderr)
        return 2

    def say(msg: str) -> None:
        from tqdm import tqdm

        tqdm.write(msg, file=sys.stderr)

    try:
        settings = settings_from(args)
    except (ValueError, TypeError, KeyError, OSError) as e:
        print(f"error: {str(e).strip(chr(34) + chr(39))}", file=sys.stderr)
        return 1
    try:
        check_output_path(args.out, sessions=[args.session_dir], kind="folder")
        result = run_session(args.session_dir, args.out, progress=None if args.quiet else say,
                             settings=settings, bars=False if args.quiet else None,
                             force=args.force, writers=WRITERS)
    except (SessionError, CalibrationError, OutputInUse, OutputPathError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    except OSError as e:  # writing the outputs (a full disk, a folder made read-only)
        kept = (f"\nwhat was finished is kept in {args.out}: the same command resumes from it"
                if Path(args.out).is_dir() and any(Path(args.out).iterdir()) else "")
        print(f"error: {e}{kept}", file=sys.stderr)
        return 1
    s = result.summary
    a = result.audit or {}
    if a.get("nothing_to_analyse"):
        print(f"warning: {a['nothing_to_analyse']}", file=sys.stderr)
    print(f"{s['session']['name']}: {sum(s['counts']['takes'].values())} takes, "
          f"{s['counts']['rows']} face-take rows; stages: {', '.join(s['stages'])}; "
          f"results in {result.out_dir}")
    print(f"audit verdict: {a.get('verdict')}"
          + (" (nothing to analyse)" if a.get("nothing_to_analyse") else ""))
    if a.get("missing_markers"):
        print(f"  markers in markers.csv never reconstructed: {', '.join(a['missing_markers'])}")
    for f in a.get("flagged", []):
        if f["kind"] == "marker" and f["item"] not in a.get("missing_markers", []):
            print(f"  marker {f['item']}: {f['verdict']} ({f['why']})")
    if result.reused:
        print(f"reused from the earlier run: {', '.join(result.reused)}; "
              f"computed: {', '.join(result.computed) or 'nothing'}")
    return 0
