"""``mocap schedule``: an identification battery of command files for a real robot."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DESCRIPTION = """\
Write an identification battery as docs/format.md command files, to play on a robot (or on the
virtual face with 'mocap simulate --commands'): per DU the paper's trapezoid (100 steps of 50 ms),
the same at a fast rate (25 ms steps) and a slow one (0.3 s steps), and a partial sweep with
reversals inside the range (0 -> 80 % -> 30 % -> 100 % -> 10 % -> 60 % -> 0); per DU pair both
trapezoids at once and shifted by 1.25 s. The paper's trapezoid alone cannot tell a lag from a
wider hysteresis, nor show backlash or coupling: these takes can. A README.md in OUT lists the
files, what each exposes and the total duration.

example:
  mocap schedule --dus 1,4,7 --pairs 1-7,4-7 --out battery/
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dus", required=True, help="comma-separated DU ids")
    p.add_argument("--pairs", default="", help="DU pairs to co-activate, e.g. 1-7,4-7")
    p.add_argument("--out", type=Path, required=True, help="output folder")


def run(args: argparse.Namespace) -> int:
    from mocap.core.atomic import write_csv, write_text
    from mocap.core.paths import OutputPathError, check_output_path
    from mocap.core.schedules import identification_battery, trapezoid

    try:
        dus = [int(d) for d in args.dus.split(",") if d.strip()]
        pairs = [tuple(int(x) for x in p.split("-")) for p in args.pairs.split(",") if p.strip()]
        if any(len(p) != 2 for p in pairs):
            raise ValueError(args.pairs)
    except ValueError:
        print(f"error: --dus 1,4,7 and --pairs 1-7,4-7 expected, got {args.dus!r} {args.pairs!r}",
              file=sys.stderr)
        return 1
    try:
        check_output_path(args.out)
    except OutputPathError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    lines = ["# Identification battery", "", "| file | DUs | exposes | duration (s) |", "|---|---|---|---|"]
    total = 0.0
    takes = [(f"du{du:02d}_trapezoid", (du,), trapezoid(du), "the paper's static response")
             for du in dus]
    takes += [(b.name, b.dus, b.rows, b.purpose) for b in identification_battery(dus, pairs)]
    for name, take_dus, rows, purpose in takes:
        write_csv(rows.sort_values("time_s", kind="stable"), args.out / f"{name}.csv", decimals=6)
        dur = float(rows["time_s"].max()) + 0.5
        total += dur
        lines.append(f"| {name}.csv | {', '.join(map(str, take_dus))} | {purpose} | {dur:.2f} |")
    lines += ["", f"Total: {len(takes)} takes, {total:.1f} s of commands (plus rest between takes).",
              "Each file holds one row per command step (time_s, du, command); a DU holds 0 "
              "until its first row. Record each as a 'motion' take (the trapezoids as 'response' "
              "takes with du and trial), repeating the trapezoid at the start, middle and end of "
              "the session to expose drift."]
    write_text(args.out / "README.md", "\n".join(lines) + "\n")
    print(f"{len(takes)} command files ({total:.0f} s) written to {args.out}")
    return 0
