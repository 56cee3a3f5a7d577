"""``mocap audit``: capture-quality audit of a session."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DESCRIPTION = """\
Audit a capture before trusting its analysis: the calibration's quality; per camera its blob
count, ghost rate and dropout rate; per marker the cameras that see it, its gaps, noise floor and
across-trial spread; the markers and trajectories rejected and why; the takes whose motion and
commands look misaligned (set their commands_offset_s); a pass / warn / fail verdict per item
(thresholds in mocap/workflows/audit.py and in audit.json). Writes audit.md, audit.json and
figures into --out (the session is only read). 'mocap run' writes the same audit.

example:
  mocap audit sample_data/session --out out/audit
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("session_dir", type=Path, help="session folder holding session.toml")
    p.add_argument("--out", type=Path, required=True, help="output folder")


def run(args: argparse.Namespace) -> int:
    from mocap.calib.wand_calibration import CalibrationError
    from mocap.core.paths import check_output_path
    from mocap.workflows.run.pipeline import run_session
    from mocap.workflows.run.settings import RunSettings
    from mocap.workflows.run.lock import OutputInUse
    from mocap.outputs.run_writers import WRITERS
    from mocap.core.session import SessionError

    try:
        check_output_path(args.out, sessions=[args.session_dir], kind="folder")
        res = run_session(args.session_dir, args.out, settings=RunSettings(analyze=False),
                          progress=lambda m: print(m, file=sys.stderr, flush=True),
                          writers=WRITERS)
    except (SessionError, CalibrationError, OutputInUse) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    a = res.summary["audit"]
    if (res.audit or {}).get("nothing_to_analyse"):
        print(f"warning: {res.audit['nothing_to_analyse']}", file=sys.stderr)
    print(f"audit verdict: {a['verdict']}")
    for f in a["flagged"]:
        print(f"  {f['verdict']:4s} {f['kind']} {f['item']}: {f['why']}")
    print(f"details in {args.out / 'audit.md'}")
    return 0
