"""``mocap design``: command files that realise a motion plan, from identified responses."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DESCRIPTION = """\
Design the command plan of one DU or several at once so that the face follows a motion plan
P(t) (the paper's plans A-E, neutral to smile, then the return 1 - P), by the paper's inverse
response: c = R_fwd^-1(P) while rising, R_bwd^-1(1 - P) while falling, with each DU's forward
and backward sigmoids as identified by 'mocap run' (OUT_DIR/properties.csv). Writes a FORMAT.md
command file that 'mocap simulate --commands' plays on the virtual face, or a robot plays.

Timing follows the paper unless told otherwise: --start-s 0.25 of rest, the plan over 130
command steps of --step-s 0.016 (2.08 s), a --hold-s 1.0 hold, the return over the same steps.

examples:
  mocap design out/sample --plan A --dus 1,7,12 --out smile_planA.csv
  mocap design out/sample --plan E --dus 4 --step-s 0.02 --out du04_planE.csv
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", type=Path,
                   help="a 'mocap run' output folder (properties.csv) or a session folder")
    p.add_argument("--plan", required=True, help="motion plan: A, B, C, D or E")
    p.add_argument("--dus", required=True, help="comma-separated DU ids, e.g. 1,7,12")
    p.add_argument("--method", default="paper", choices=["paper"],
                   help="paper: METHOD.md's inverse sigmoids (default)")
    p.add_argument("--out", type=Path, required=True, help="command file to write (CSV)")
    p.add_argument("--start-s", type=float, default=0.25)
    p.add_argument("--steps", type=int, default=130)
    p.add_argument("--step-s", type=float, default=0.016)
    p.add_argument("--hold-s", type=float, default=1.0)
    p.add_argument("--tail-s", type=float, default=0.25)


def run(args: argparse.Namespace) -> int:
    import tempfile

    import pandas as pd

    from analysis.design import PlanTiming, SigmoidPair, paper_design
    from analysis.plans import PLAN_NAMES
    from mocap.atomic import write_csv

    plan = args.plan.upper()
    if plan not in PLAN_NAMES:
        print(f"error: --plan: expected one of {', '.join(PLAN_NAMES)}, got {args.plan!r}", file=sys.stderr)
        return 1
    try:
        dus = [int(d) for d in args.dus.split(",") if d.strip()]
    except ValueError:
        print(f"error: --dus: expected comma-separated integers, got {args.dus!r}", file=sys.stderr)
        return 1
    props_path = args.source / "properties.csv"
    if not props_path.is_file():
        if not (args.source / "session.toml").is_file():
            print(f"error: {args.source}: neither properties.csv (a 'mocap run' output) nor "
                  "session.toml (a session) is there", file=sys.stderr)
            return 1
        from mocap.pipeline import run_session

        work = Path(tempfile.mkdtemp(prefix="mocap-design-"))
        print(f"identifying the responses of {args.source} (results in {work})", file=sys.stderr)
        run_session(args.source, work, progress=lambda m: print(m, file=sys.stderr))
        props_path = work / "properties.csv"
    props = pd.read_csv(props_path).set_index("du")
    missing = [d for d in dus if d not in props.index]
    if missing:
        print(f"error: {props_path}: no identified response for DUs {missing} "
              f"(has {sorted(props.index)})", file=sys.stderr)
        return 1
    responses = {d: SigmoidPair(props.loc[d, "alpha_fwd"], props.loc[d, "beta_fwd"],
                                props.loc[d, "alpha_bwd"], props.loc[d, "beta_bwd"]) for d in dus}
    timing = PlanTiming(start_s=args.start_s, n_steps=args.steps, step_s=args.step_s,
                        hold_s=args.hold_s, tail_s=args.tail_s)
    rows = paper_design(plan, responses, timing, dus)
    write_csv(rows, args.out, decimals=6)
    print(f"plan {plan} on DUs {dus}: {len(rows)} command rows over {timing.total_s:.2f} s "
          f"written to {args.out}")
    return 0
