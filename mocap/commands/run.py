"""``mocap run``: process a session, raw camera exports to results (OUTPUTS.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DESCRIPTION = """\
Process a capture session (FORMAT.md) and write the results (OUTPUTS.md) into OUT_DIR.
The raw session is never modified; every output file is written atomically.

example:
  mocap run sample_data/session --out out/sample
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("session_dir", type=Path, help="session folder holding session.toml")
    p.add_argument("--out", type=Path, required=True, help="output folder")


def run(args: argparse.Namespace) -> int:
    from calib.wand_calibration import CalibrationError
    from mocap.pipeline import run_session
    from mocap.session import SessionError

    def say(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    try:
        result = run_session(args.session_dir, args.out, progress=say)
    except (SessionError, CalibrationError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    s = result.summary
    print(f"{s['session']['name']}: {sum(s['counts']['takes'].values())} takes, "
          f"{s['counts']['rows']} rows; stages: {', '.join(s['stages'])}; "
          f"results in {result.out_dir}")
    return 0
