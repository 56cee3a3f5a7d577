"""``mocap discrepancy``: where the face model and the measurement disagree, and why."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

DESCRIPTION = """\
Fit the face model (the paper's sigmoids with a Prandtl-Ishlinskii hysteresis density, each
marker's own path and a bias shift per take, for any command series on any DUs) on the
session's commanded takes, predict every take held out (two-fold cross-validation over takes),
localise where the residuals exceed the measurement's own noise (per take, DU, marker and phase
of the command), try every candidate effect (lag, deadtime, backlash, coupling, drift,
saturation; hysteresis and curvature too from a smaller base), name the one that explains the gap on
held-out takes (BIC margin 10) with its parameter and uncertainty, add it and repeat until nothing
significant is left. A backlash the hysteresis density absorbed (no held-out gain) is read as
the widest actuator dead band the takes allow, the onset of a forced play's profile, and named
with the alternative that the skin holds the band. Says which effects the takes cannot test
(e.g. coupling without multi-DU takes). Writes OUT/discrepancy.json, discrepancy.md, figures/
and discrepancy.rrd (Rerun; open it with 'mocap replay OUT').

A raw (2D) session is reconstructed first (into OUT/reconstruction); a labeled session or a
'mocap run' output folder is read directly.

examples:
  mocap discrepancy out/run --out out/discrepancy              # a mocap run's output
  mocap simulate out/lag --preset small --effect lag --labeled
  mocap discrepancy out/lag/session --out out/lag_discrepancy   # names 'lag', tau about 0.08 s
  mocap discrepancy SESSION --out OUT --base static             # start without hysteresis
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    from mocap.analysis.model.effects import CATALOGUE

    p.add_argument("path", type=Path, help="session directory or mocap run output directory")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--base", choices=["face", "paper", "static"], default="face",
                   help="starting model: what every face has (default: a hysteresis density, "
                        "each marker's own path, a bias shift per take), the paper's (hysteresis, "
                        "straight paths: curvature becomes a candidate) or static (no hysteresis "
                        "either)")
    p.add_argument("--effects", default=None,
                   help="candidate effects, comma-separated (default: the missing effects, "
                        f"plus what the base leaves out; known: {', '.join(CATALOGUE)})")
    p.add_argument("--margin", type=float, default=10.0, help="held-out BIC units to name an effect (10)")
    p.add_argument("--max-steps", type=int, default=4, help="effects to add at most (4)")
    p.add_argument("--jobs", type=int, default=None,
                   help="processes over the base fits and the candidate effects (default: all cores)")
    p.add_argument("--no-recording", action="store_true", help="do not write discrepancy.rrd")
    p.add_argument("--quiet", action="store_true", help="no progress messages")


def run(args: argparse.Namespace) -> int:
    from mocap.analysis.discrepancy.settings import DiscrepancySettings
    from mocap.analysis.model.effects import CATALOGUE
    from mocap.workflows.discrepancy.results import run as run_workflow
    from mocap.outputs.discrepancy import WRITERS
    from mocap.core.paths import check_output_path, session_dir_of
    from mocap.core.session import SessionError

    from mocap.analysis.model.effects import BASE, CANDIDATES

    base = {"face": BASE, "paper": ("hysteresis",), "static": ()}[args.base]
    if args.effects is None:
        names = [n for n in BASE if n not in base and n != "takeshift"] + list(CANDIDATES)
    else:
        names = [e.strip() for e in args.effects.split(",") if e.strip()]
    bad = [e for e in names if e not in CATALOGUE]
    if bad:
        print(f"error: --effects: unknown {', '.join(bad)} (known: {', '.join(CATALOGUE)})",
              file=sys.stderr)
        return 2
    settings = DiscrepancySettings(base=base,
                                   candidates=tuple(names), margin=args.margin,
                                   max_steps=args.max_steps,
                                   jobs=args.jobs or os.cpu_count() or 1)
    say = (lambda m: None) if args.quiet else (lambda m: print(m, file=sys.stderr, flush=True))
    try:
        check_output_path(args.out, sessions=[s for s in [session_dir_of(args.path)] if s],
                          kind="folder")
        res = run_workflow(args.path, args.out, settings, progress=say,
                           recording=not args.no_recording, writers=WRITERS)
    except (SessionError, ValueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(f"{'named ' + ', '.join(res.named) if res.named else 'no missing effect found'}; "
          f"held-out RMS {res.stages[0]['heldout_rms_mm']:.4f} -> {res.final_heldout_rms_mm:.4f} mm "
          f"(noise floor {res.noise_floor_mm:.4f} mm); {args.out / 'discrepancy.md'}")
    return 0
