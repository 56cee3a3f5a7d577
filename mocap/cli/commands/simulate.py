"""``mocap simulate``: write a virtual capture session with known truth."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

DESCRIPTION = """\
Make a virtual capture session: a virtual face (markers, DUs with sigmoid responses and
Prandtl-Ishlinskii hysteresis) filmed by a virtual camera rig (distortion, centroid noise,
dropouts, ghost blobs, occlusion). Writes OUT_DIR/session (the input format) and OUT_DIR/truth
(true cameras, trajectories, blob labels, face parameters, hidden effect), which the pipeline
never reads.

examples:
  mocap simulate out/small --preset small --seed 1
  mocap simulate out/lag --preset small --effect lag --strength 0.1
  mocap simulate out/two --preset small --effect lag,drift       # two hidden effects at once
  mocap simulate out/pb --preset small --face-family preisach-bow --labeled --labeled-noise-mm 0.03
  mocap simulate out/any --preset small --face-family random     # the family goes to truth/ only
  mocap simulate out/alt --preset small --effect coupling --effect-form alt
  mocap simulate out/paper --preset paper            # the full study, Parquet takes
  mocap simulate out/designed --preset small --commands commands.csv
  mocap simulate out/rod --preset small --wand-offsets 0,200 --no-ground   # easyWand-style rig
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    from mocap.simulate.effects import EFFECTS
    from mocap.simulate.families import FAMILY_NAMES

    p.add_argument("out_dir", type=Path, help="output folder (session/ and truth/ are written in it)")
    p.add_argument("--preset", default="small", choices=["small", "sample", "paper"],
                   help="size of the study (default: small)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--effect", default="none",
                   help="hidden effect(s) applied to the true face, comma-separated, among "
                        f"{', '.join(sorted(EFFECTS))} (default none)")
    p.add_argument("--strength", default=None,
                   help="the effect's parameter, one per effect, comma-separated (default: each "
                        "effect's default strength)")
    p.add_argument("--face-family", default=None, choices=FAMILY_NAMES, metavar="NAME",
                   help="the base face's family: hysteresis-path among "
                        f"{', '.join(FAMILY_NAMES[1:-1])}; pi (default: PI hysteresis, "
                        "straight paths); random (drawn from the seed, named in truth/ only)")
    p.add_argument("--effect-form", choices=["model", "alt", "alt2"], default="model",
                   help="the hidden effects' equations: model (default); alt, a second form "
                        "with the same parameters that the analysis model does not share; alt2, "
                        "a third form where one is written (coupling: strain-stiffening skin), "
                        "else alt")
    p.add_argument("--labeled", action="store_true", help="write labeled 3D takes (no cameras)")
    p.add_argument("--labeled-noise-mm", type=float, default=None,
                   help="measurement noise sd per axis of labeled takes, mm (default 0.02)")
    p.add_argument("--format", choices=["csv", "parquet"], default=None, help="take file format")
    p.add_argument("--trials", type=int, default=None, help="response trials per DU")
    p.add_argument("--markers", type=int, default=None, help="number of face markers")
    p.add_argument("--dus", default=None, help="comma-separated DU ids (e.g. 1,4,7,12)")
    p.add_argument("--noise-px", type=float, default=None, help="2D centroid noise sd, px (0.08)")
    p.add_argument("--degrade-camera", default=None,
                   help="camera id with high noise, dropouts and ghosts (audit tests)")
    p.add_argument("--commands", type=Path, action="append", default=[],
                   help="a command file (time_s,du,command) to play as an extra motion take")
    p.add_argument("--no-battery", action="store_true", help="omit the identification battery")
    p.add_argument("--wand-offsets", default=None,
                   help="wand marker offsets, mm, comma-separated (default 0,50,150; two values "
                        "make an easyWand/Argus rod whose ends look alike)")
    p.add_argument("--no-ground", action="store_true",
                   help="no ground square: the session's world frame is the first camera's")
    p.add_argument("--force", action="store_true", help="write into a non-empty OUT_DIR")


def simulated(out: Path) -> bool:
    """Whether ``out/session`` was written by this command (so ``--force`` may replace it): its
    ``truth/truth.json`` is beside it, or its manifest carries the simulator's name
    (``virtual-face-<preset>-seed<n>``; the committed sample session has no truth folder)."""
    import tomllib

    if (out / "truth" / "truth.json").is_file():
        return True
    try:
        with open(out / "session" / "session.toml", "rb") as fh:
            name = tomllib.load(fh).get("name", "")
    except (OSError, ValueError):
        return False
    return isinstance(name, str) and name.startswith("virtual-face-")


def run(args: argparse.Namespace) -> int:
    import dataclasses
    import sys

    from mocap.core.paths import OutputPathError, check_output_path
    from mocap.simulate import preset, simulate
    from mocap.simulate.capture import CaptureNoise
    from mocap.simulate.effects import make_effect
    from mocap.simulate.session_writer import print_progress

    out = args.out_dir
    try:
        check_output_path(out, inputs=args.commands, option="OUT_DIR", kind="folder")
        if (out / "session" / "session.toml").is_file() and not simulated(out):
            # OUT_DIR/session is a real session, not one this command wrote: --force or not
            raise OutputPathError(f"OUT_DIR {out}: contains the session folder {out / 'session'}, "
                                  "which is not a simulated one; outputs never go into a raw "
                                  "session: choose another folder")
    except OutputPathError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    if (out / "session").exists() and any((out / "session").iterdir()) and not args.force:
        print(f"error: {out / 'session'} exists and is not empty (use --force to overwrite)",
              file=sys.stderr)
        return 1
    try:
        overrides = dict(
            seed=args.seed,
            effect=make_effect(args.effect, args.strength, args.effect_form),
            labeled=args.labeled or None,
            labeled_noise_mm=args.labeled_noise_mm,
            face_family=args.face_family,
            take_format=args.format,
            n_trials=args.trials,
            n_markers=args.markers,
            du_ids=tuple(int(d) for d in args.dus.split(",")) if args.dus else None,
            degrade_camera=args.degrade_camera,
            extra_commands=tuple(args.commands) or None,
            battery=False if args.no_battery else None,
            wand_offsets_mm=(tuple(float(v) for v in args.wand_offsets.split(","))
                             if args.wand_offsets else None),
            ground=False if args.no_ground else None,
        )
        cfg = preset(args.preset, **overrides)
        if args.noise_px is not None:
            cfg = dataclasses.replace(cfg, noise=dataclasses.replace(CaptureNoise(), noise_px=args.noise_px))
        summary = simulate(cfg, out, progress=print_progress)
        from mocap.workflows.truth_properties import write_true_properties

        write_true_properties(cfg, out)
    except (ValueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(json.dumps(summary, indent=2))
    return 0
