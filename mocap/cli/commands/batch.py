"""``mocap batch``: many sessions in parallel on Dask."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DESCRIPTION = """\
Run 'mocap run' on many sessions in parallel with Dask (dask.distributed): a local cluster of
worker processes by default, or an existing cluster with --scheduler. Each session's results go
to ROOT/<session name>/; a session that fails is reported and does not stop the others;
ROOT/batch.json sums up. Exit status 1 if any session failed.

examples:
  mocap batch sessions/day1 sessions/day2 sessions/day3 --out results/
  mocap batch sessions/* --out results/ --scheduler tcp://10.0.0.5:8786
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("sessions", type=Path, nargs="+", help="session folders")
    p.add_argument("--out", type=Path, required=True, help="root folder for the results")
    p.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler")
    p.add_argument("--workers", type=int, default=None,
                   help="local worker processes (default: one per core, at most one per session)")


def run(args: argparse.Namespace) -> int:
    from mocap.workflows.batch import run_batch
    from mocap.core.paths import OutputPathError, check_output_path
    from mocap.outputs.run_writers import WRITERS

    try:
        check_output_path(args.out, sessions=args.sessions)
    except OutputPathError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    summary = run_batch(args.sessions, args.out, scheduler=args.scheduler, workers=args.workers,
                        progress=lambda m: print(m, file=sys.stderr, flush=True),
                        writers=WRITERS)
    print(f"{summary['ok']} sessions done, {summary['failed']} failed in {summary['seconds']} s; "
          f"summary in {args.out / 'batch.json'}")
    for r in summary["sessions"]:
        if not r["ok"]:
            print(f"  FAILED {r['session']}: {r['error']}")
    return 1 if summary["failed"] else 0
