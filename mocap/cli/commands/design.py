"""``mocap design``: command files that realise a motion plan, from identified responses or from
the identified face model."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DESCRIPTION = """\
Design the command plan of one DU or several at once so that the face follows a motion plan
P(t) (the paper's plans A-E, neutral to smile, then the return 1 - P; or a FILE with columns
time_s,P that may reverse anywhere). Writes a docs/format.md command file (integers 0..255, one row
per command step) that 'mocap simulate --commands' plays on the virtual face, or a robot plays.

--method paper (default): the paper's inverse response, c = R_fwd^-1(P) while rising and
R_bwd^-1(1 - P) while falling, with each DU's sigmoids as 'mocap run' identifies them
(OUT_DIR/properties.csv; a session is analysed first).

--method model: the commands are optimised through the identified face model (hysteresis under
arbitrary reversals, actuator lag, dead time, backlash, coupling, saturation, curvature: every
effect the discrepancy workflow names, or those given by --effects), so that the chosen markers'
predicted normalised displacement follows the plan (--markers). A plan with a hold is designed
with the hold at 1 and a little above (the evaluation divides each marker by the mean of its
frames within 5 % of its peak, which include the top of the rise), and the design whose take
the model predicts to track best is kept. The design's reference, its hold included, is
written next to the command file (X.reference.csv).

Each design writes X.design.json beside X.csv: what it was made from (plan, DUs, timing, the
face model's and the source session's identities, the iteration) and the tracking RMS it expects.

--refine TAKE: iterative learning control for a real robot. Play X.csv, record the take, and
pass the take file as recorded (C3D, Motive CSV, QTM TSV, session-format CSV/Parquet) with
--played-commands X.csv; or the name of a take in --measured (a session or 'mocap run' output).
The refinement checks the take, the reference and the model against X.design.json and refuses
what does not match; it prints the take's measured tracking RMS and the RMS predicted for the
next play (the measured take plus the model's predicted change of commands). The take's
tracking error updates the reference (X.reference.csv) and the commands are designed again;
a few repetitions converge (docs/design_loop.md).

--save-model FILE writes the identified face model and the session it was identified on;
--model FILE designs with it instead of identifying the model again (a refinement's
repetitions need it once), on that session only unless --model-from-other-session.

--check: for a simulated session, play the paper's and the model's designs on the same virtual
face (the session's own: its base-face family and its hidden effect in the form it was made
with), evaluate them against the plan (RMS of the normalised displacement forward and backward,
lag) and draw them side by side (X.check.png). On a face without actuator dynamics (no lag or
dead time hidden) it also prints the floor of the command grid: the face holds still between two
rows, so no command file on the grid tracks better than the plan's mean over each step, and on
the way down no lower than the set the face keeps at command 0.

Timing follows the paper unless told otherwise: --start-s 0.25 of rest, the plan over
--duration-s 2.08 (130 command steps of --step-s 0.016), a --hold-s 1.0 hold, the return over
the same duration, --tail-s 0.25 of rest.

examples:
  mocap design out/sample --plan A --dus 1,7,12 --out smile_planA.csv
  mocap design out/lag/session --plan A --dus 1,7,12 --method model --check --out smile_A.csv
  mocap design SESSION --plan relax.csv --dus 1,7,12 --method model --effects hysteresis,lag --out r.csv
  mocap design SESSION --plan A --dus 1,7,12 --method model --save-model face.model --out A1.csv
  mocap design SESSION --plan A --dus 1,7,12 --method model --model face.model \\
      --refine take_A1.c3d --played-commands A1.csv --out A2.csv
"""


def _stderr(message: str) -> None:
    print(message, file=sys.stderr)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", type=Path,
                   help="a 'mocap run' output folder (properties.csv) or a session folder")
    p.add_argument("--plan", required=True, help="motion plan: A, B, C, D, E or a CSV (time_s,P)")
    p.add_argument("--dus", required=True, help="comma-separated DU ids, e.g. 1,7,12")
    p.add_argument("--method", default="paper", choices=["paper", "model"],
                   help="paper: the paper's inverse sigmoids (default); model: optimised through "
                        "the identified face model")
    p.add_argument("--out", type=Path, required=True, help="command file to write (CSV)")
    p.add_argument("--start-s", type=float, default=0.25)
    p.add_argument("--steps", type=int, default=None, help="command steps of the plan (130)")
    p.add_argument("--duration-s", type=float, default=None,
                   help="the plan's duration, s (default 130 steps of --step-s)")
    p.add_argument("--step-s", type=float, default=0.016)
    p.add_argument("--hold-s", type=float, default=1.0)
    p.add_argument("--tail-s", type=float, default=0.25)
    g = p.add_argument_group("model-based design")
    g.add_argument("--effects", default=None,
                   help="fit the face model with exactly these effects (e.g. hysteresis,lag) "
                        "instead of running the discrepancy workflow")
    g.add_argument("--markers", default="all",
                   help="markers to track: all (default), comma-separated names, or "
                        "near:NAME:RADIUS_MM (a region)")
    g.add_argument("--headroom", type=float, default=24.0,
                   help="the full motion is the response to 255 - headroom (command units)")
    g.add_argument("--sweeps", type=int, default=0,
                   help="non-causal passes over the whole plan after the causal one (slower)")
    g.add_argument("--preview", type=int, default=None, metavar="STEPS",
                   help="command steps over which the causal pass holds and scores a candidate "
                        "(default: 2 when the model has a lag or dead time, else 1)")
    g.add_argument("--model", type=Path, default=None, metavar="FILE",
                   help="use the face model a previous --save-model wrote instead of identifying "
                        "it again (identified on SOURCE; with --refine repetitions)")
    g.add_argument("--save-model", type=Path, default=None, metavar="FILE",
                   help="write the identified face model (and the session it was identified "
                        "on) to FILE, for --model")
    g.add_argument("--jobs", type=int, default=1, help="processes for the discrepancy workflow")
    g.add_argument("--model-from-other-session", action="store_true",
                   help="use a --model identified on another session than SOURCE (refused "
                        "otherwise)")
    g.add_argument("--refine", default=None, metavar="TAKE",
                   help="a played take of the previous commands: refine them (ILC). A take file "
                        "as the lab recorded it (C3D, Motive CSV, QTM TSV, or a take CSV/Parquet "
                        "of the session format), or the name of a take in --measured")
    g.add_argument("--played-commands", type=Path, default=None, metavar="FILE",
                   help="the command file the --refine take played (a design's X.csv; its "
                        "X.design.json and X.reference.csv are read beside it). Default: the "
                        "command file beside --reference, or the --measured take's own")
    g.add_argument("--measured", type=Path, default=None,
                   help="session or 'mocap run' output holding the --refine take (default SOURCE)")
    g.add_argument("--reference", type=Path, default=None,
                   help="the played design's .reference.csv (default: the one written beside "
                        "--played-commands)")
    g.add_argument("--gain", type=float, default=0.5,
                   help="learning gain of --refine (0.5: steady under measurement noise; 1 learns "
                        "a noise-free take at once)")
    g.add_argument("--check", action="store_true",
                   help="closed loop on the virtual face of a simulated session: paper vs model")


def _timing(args):
    from mocap.analysis.design.inverse_response import PlanTiming

    steps = args.steps
    if args.duration_s is not None:
        steps = int(round(args.duration_s / args.step_s))
    return PlanTiming(start_s=args.start_s, n_steps=steps or 130, step_s=args.step_s,
                      hold_s=args.hold_s, tail_s=args.tail_s)


def _paper_rows(plan, plan_file, responses, timing, dus):
    from mocap.analysis.design.inverse_response import paper_design, paper_design_series

    if plan_file is None:
        return paper_design(plan, responses, timing, dus)
    import pandas as pd

    df = pd.read_csv(plan_file)
    return paper_design_series(df["time_s"].to_numpy(float), df["P"].to_numpy(float), responses,
                               start_s=timing.start_s, step_s=timing.step_s, dus=dus)


def run(args: argparse.Namespace) -> int:
    from mocap.analysis.design.plans import PLAN_NAMES
    from mocap.core.atomic import write_csv
    from mocap.core.paths import check_output_path, session_dir_of
    from mocap.core.session import SessionError

    plan = args.plan.upper()
    plan_file = None
    if plan not in PLAN_NAMES:
        if Path(args.plan).is_file():
            plan_file = Path(args.plan)
        else:
            print(f"error: --plan: expected one of {', '.join(PLAN_NAMES)} or a CSV file with "
                  f"columns time_s,P, got {args.plan!r}", file=sys.stderr)
            return 1
    try:
        dus = [int(d) for d in args.dus.split(",") if d.strip()]
    except ValueError:
        print(f"error: --dus: expected comma-separated integers, got {args.dus!r}", file=sys.stderr)
        return 1
    if not dus:
        print("error: --dus: expected at least one DU", file=sys.stderr)
        return 1
    if (args.preview is not None and args.preview < 1) or args.sweeps < 0:
        print(f"error: --preview/--sweeps: expected a preview of at least 1 command step and "
              f"sweeps >= 0, got {args.preview}, {args.sweeps}", file=sys.stderr)
        return 1
    if not (args.source / "properties.csv").is_file() and not (args.source / "session.toml").is_file() \
            and not (args.source / "summary.json").is_file():
        print(f"error: {args.source}: neither properties.csv (a 'mocap run' output) nor "
              "session.toml (a session) is there", file=sys.stderr)
        return 1
    if args.step_s <= 0 or (args.duration_s is not None and args.duration_s < args.step_s):
        print(f"error: --step-s/--duration-s: expected 0 < step <= duration, got {args.step_s}, "
              f"{args.duration_s}", file=sys.stderr)
        return 1
    timing = _timing(args)
    try:
        sources = [args.source, *([args.measured] if args.measured else [])]
        sessions = [s for s in map(session_dir_of, sources) if s]
        inputs = [f for f in (plan_file, args.reference, args.model) if f is not None]
        check_output_path(args.out, sessions=sessions, inputs=inputs, kind="file")
        if args.save_model is not None:
            check_output_path(args.save_model, sessions=sessions, inputs=[*inputs, args.out],
                              option="--save-model")
        if args.method == "paper":
            if args.refine or args.check or args.model or args.save_model:
                print("error: --refine, --check, --model and --save-model need --method model",
                      file=sys.stderr)
                return 1
            if plan_file is not None:
                print("note: the paper's rule on a plan with reversals jumps between its forward "
                      "and backward sigmoids (no minor loops); --method model handles them",
                      file=sys.stderr)
            from mocap.workflows.design import paper_responses

            rows = _paper_rows(plan, plan_file, paper_responses(args.source, dus, _stderr), timing,
                               dus)
            write_csv(rows, args.out, decimals=6)
            print(f"plan {args.plan} on DUs {dus}: {len(rows)} command rows over "
                  f"{float(rows.time_s.max()):.2f} s written to {args.out}")
            return 0
        return _run_model(args, plan, plan_file, dus, timing)
    except (SessionError, ValueError, OSError, KeyError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1


def _played_commands(args):
    """The command file the --refine take played: --played-commands, or the X.csv beside
    --reference X.reference.csv (None: neither)."""
    from mocap.workflows.design_loop import commands_beside_reference

    if args.played_commands is not None:
        return args.played_commands
    if args.reference is not None:
        return commands_beside_reference(args.reference)
    return None


def _read_played(args, dus):
    """(take, played command file or None, its design record or None, record file)."""
    from mocap.core.session import SessionError, load_session
    from mocap.workflows.design import played_take
    from mocap.workflows.design_loop import (
        _session_dir,
        commands_sha256,
        is_take_file,
        read_command_file,
        read_record,
        read_take_file,
        record_path,
    )

    pc = _played_commands(args)
    if is_take_file(args.refine):
        if pc is None:
            raise ValueError(f"--refine {args.refine}: a take file does not say what it played; "
                             "pass --played-commands X.csv (the command file the robot played)")
        rows = read_command_file(pc, dus)
        fps = load_session(_session_dir(args.source)).fps
        take = read_take_file(args.refine, rows, fps)
    elif Path(str(args.refine)).suffix.lower() in (".c3d", ".tsv", ".csv", ".parquet") \
            and not Path(str(args.refine)).exists():
        raise ValueError(f"--refine: no file {args.refine} (a take file, or the name of a take "
                         "in --measured)")
    else:
        take = played_take(args.measured or args.source, args.refine)
        if pc is not None:
            rows = read_command_file(pc, take.rows["du"].unique())
            if commands_sha256(rows) != commands_sha256(take.rows):
                raise ValueError(f"--refine: take {take.name}'s commands (in "
                                 f"{args.measured or args.source}) are not {pc}: pass the "
                                 "command file it played as --played-commands")
    rec_file = record_path(pc) if pc is not None else None
    record = read_record(rec_file) if rec_file is not None and rec_file.is_file() else None
    if record is None and args.reference is None:
        where = (f"no design record {rec_file} beside the played commands" if rec_file else
                 "no --played-commands")
        raise SessionError(f"--refine: {where}, and no --reference: pass --played-commands X.csv "
                           "(the played design's command file, with X.design.json and "
                           "X.reference.csv beside it) or --reference X.reference.csv; the "
                           "refinement does not guess the reference")
    return take, pc, record, rec_file


def _run_model(args, plan, plan_file, dus, timing) -> int:
    import time
    from dataclasses import asdict

    from mocap.analysis.design.model_based import (
        design_commands,
        design_plan,
        file_reference,
        marker_weights,
        plan_reference,
        refined_reference,
    )
    from mocap.analysis.design.refinement import (
        calibrated_prediction,
        measured_tracking,
        model_prediction,
    )
    from mocap.core.atomic import write_csv
    from mocap.workflows.design import (
        identify_model,
        load_model,
        model_file_session,
        read_reference,
        reference_path,
        save_model,
        write_reference,
    )
    from mocap.workflows.design_loop import (
        DesignRecord,
        _session_dir,
        check_refinement,
        check_take,
        commands_sha256,
        file_sha256,
        model_identity,
        record_path,
        session_identity,
        write_record,
    )

    say = lambda m: print(m, file=sys.stderr, flush=True)  # noqa: E731
    t0 = time.perf_counter()
    effects = None if args.effects is None else [e.strip() for e in args.effects.split(",") if e.strip()]
    # the played take before the model: a wrong take is an error at once, not after the fit
    take, played_file, record, rec_file = _read_played(args, dus) if args.refine else (None,) * 4
    source_id = session_identity(args.source)
    if args.model is not None:
        if effects is not None:
            raise ValueError("--model and --effects: the model file's effects are fixed; give one "
                             "of them")
        model, how = load_model(args.model), f"read from {args.model}"
        info = model_file_session(args.model)
        if not args.model_from_other_session and (info is None
                                                  or info.get("session_sha256") != source_id):
            on = (f"was identified on {info.get('session')}" if info else
                  "does not record the session it was identified on")
            raise ValueError(f"--model {args.model}: the model {on}, not on SOURCE "
                             f"{_session_dir(args.source)}; identify it on SOURCE (leave --model "
                             "out), or pass --model-from-other-session to use it anyway")
    else:
        model, how = identify_model(args.source, effects, jobs=args.jobs, progress=say)
    if args.save_model is not None:
        save_model(model, args.save_model, args.source)
        say(f"face model written to {args.save_model}")
    say(f"face model: {how}; effects {', '.join(model.effect_names) or 'none'} "
        f"{ {k: round(v, 4) for k, v in model.parameters().items()} } ({time.perf_counter() - t0:.1f} s)")
    ref = plan_reference(plan, timing) if plan_file is None else file_reference(plan_file, timing)
    fall = (timing.start_s + timing.duration_s + timing.hold_s) if plan_file is None else None
    markers = None
    if args.markers != "all":
        parts = args.markers.split(":")
        if parts[0] == "near":
            if len(parts) != 3:
                raise ValueError(f"--markers: expected near:NAME:RADIUS_MM, got {args.markers!r}")
            markers = ("near", parts[1], float(parts[2]))
        else:
            markers = [m.strip() for m in args.markers.split(",") if m.strip()]
    weights = marker_weights(model, dus, markers)
    plan_label = plan if plan_file is None else str(plan_file)
    plan_sha = None if plan_file is None else file_sha256(plan_file)
    timing_d = {k: float(v) for k, v in asdict(timing).items()}
    design_ref = ref
    n_eval = int(round((ref.end_s + timing.tail_s) * model.fps))  # the evaluated take
    measured = None
    if take is not None:
        reference = args.reference
        if reference is None:  # the played design's own (its record is there: _read_played)
            reference = reference_path(played_file)
            if not reference.is_file():
                raise ValueError(f"--refine: {reference} (the reference of {played_file}) is "
                                 "missing; pass --reference")
        if record is not None:
            check_refinement(record, rec_file, plan=plan_label, plan_sha256=plan_sha, dus=dus,
                             timing=timing_d, model=model, source_sha256=source_id,
                             reference_path=reference, commands_sha256=commands_sha256(take.rows))
        else:
            say("note: no design record beside the played commands: the take, --reference and "
                "the model cannot be checked against the design")
        check_take(take, model, ref, weights, say)
        ev_m = measured_tracking(take.X, take.rows, take.fps, ref)
        ev_p = model_prediction(model, take.rows, ref, n_eval)
        measured = 0.5 * (ev_m.rms_forward + ev_m.rms_backward)
        played_pred = 0.5 * (ev_p.rms_forward + ev_p.rms_backward)
        it = f"iteration {record.iteration}: " if record is not None else ""
        print(f"{it}played take {take.name}: measured tracking RMS {measured:.4f} (forward "
              f"{ev_m.rms_forward:.4f}, backward {ev_m.rms_backward:.4f}; read from the take); "
              f"the model predicted {played_pred:.4f} for its commands"
              + (f", the calibrated prediction was {record.expected_rms:.4f}"
                 if record is not None and record.expected_rms is not None else ""))
        previous = read_reference(reference, ref, model.marker_names)
        design_ref = refined_reference(model, ref, take.rows, take.X, take.marker_names,
                                       previous=previous, gain=args.gain)
        say(f"refining from take {take.name} (reference {reference} + gain {args.gain} x its "
            "tracking error)")
    t1 = time.perf_counter()
    # a first design chooses its hold level on the model's prediction (design_plan); a
    # refinement keeps the hold of the reference it refines
    design = design_commands if take is not None else design_plan
    des = design(model, design_ref, dus, step_s=timing.step_s, fall_start_s=fall,
                 weights=weights, headroom=args.headroom, sweeps=args.sweeps,
                 preview=args.preview)
    ev_next = model_prediction(model, des.rows, ref, n_eval)
    predicted = 0.5 * (ev_next.rms_forward + ev_next.rms_backward)
    expected = None
    if take is not None:
        ev_c = calibrated_prediction(model, take.rows, take.X, take.marker_names, des.rows, ref)
        expected = 0.5 * (ev_c.rms_forward + ev_c.rms_backward)
    write_csv(des.rows, args.out, decimals=6)
    ref_out = write_reference(reference_path(args.out), des.reference, model.marker_names)
    iteration = 0 if take is None else (record.iteration + 1 if record is not None else 1)
    write_record(record_path(args.out), DesignRecord(
        plan=plan_label, plan_sha256=plan_sha, dus=tuple(dus), timing=timing_d,
        markers=tuple(m for m, w in zip(model.marker_names, weights) if w > 0),
        model_sha256=model_identity(model), model_effects=tuple(model.effect_names),
        source=str(_session_dir(args.source).resolve()), source_sha256=source_id,
        iteration=iteration, commands_sha256=commands_sha256(des.rows),
        reference_sha256=file_sha256(ref_out), predicted_rms=predicted, expected_rms=expected,
        measured_rms=measured))
    if des.hold_level is not None and des.hold_level != 1.0:
        say(f"hold at {des.hold_level:.4f} of the full motion (chosen on the model's prediction "
            f"of the take: the evaluation's plateau takes in the top of the rise)")
    print(f"plan {args.plan} on DUs {dus} by the face model: {len(des.rows)} command rows over "
          f"{float(des.rows.time_s.max()):.2f} s written to {args.out} (design "
          f"{time.perf_counter() - t1:.1f} s; iteration {iteration}, record {record_path(args.out)})")
    if expected is None:
        print(f"predicted tracking RMS {predicted:.4f} (the face model's prediction of these "
              "commands; no play measured yet)")
    else:
        print(f"predicted tracking RMS of the next play {expected:.4f}: the played take's "
              f"{measured:.4f} plus the model's predicted change from the played commands to "
              f"these (the model alone predicts {predicted:.4f}: it tracks the refined "
              "reference, not the plan)")
    if args.check:
        return _check(args, plan, plan_file, dus, timing, ref, des.rows)
    return 0


def _check(args, plan, plan_file, dus, timing, ref, model_rows) -> int:
    from mocap.outputs.figures import design_comparison, save
    from mocap.analysis.design.model_based import evaluate_design, set_at_rest, tracking_floor
    from mocap.workflows.design import paper_responses, play_virtual, virtual_face_of

    sim = virtual_face_of(args.source)
    if sim is None:
        print(f"error: --check: {args.source} is not a simulated session (no truth/truth.json)",
              file=sys.stderr)
        return 1
    cfg, face = sim
    paper_rows = _paper_rows(plan, plan_file, paper_responses(args.source, dus, _stderr), timing,
                             dus)
    evs = {}
    for name, rows in (("paper", paper_rows), ("model", model_rows)):
        X = play_virtual(cfg, face, rows, ref.end_s + 0.25)
        ev = evaluate_design(X, rows, cfg.fps, ref)
        evs[name] = ev
        print(f"closed loop {name:<6} RMS forward {ev.rms_forward:.4f} backward {ev.rms_backward:.4f} "
              f"(per marker {ev.rms_markers_forward:.4f} / {ev.rms_markers_backward:.4f}), "
              f"lag {ev.lag_s * 1000:.0f} ms")
    # the floor of the command grid, where the face has no actuator dynamics (a lag smooths the
    # staircase, a dead time shifts it): the set at command 0 read on the plays that end there
    dynamic = {"lag", "deadtime"} & set(cfg.effect.name.split("+"))
    if not dynamic:
        fl = tracking_floor(ref, sorted(set(model_rows["time_s"])), cfg.fps,
                            set_at_rest(zip((paper_rows, model_rows), evs.values()), cfg.fps))
        print(f"floor of the command grid RMS forward {fl.forward:.4f} backward {fl.backward:.4f} "
              f"(no command file on it does better on this face: the held commands' staircase, "
              f"and the set of {fl.set_level:.4f} it keeps at command 0); model / floor "
              f"{0.5 * (evs['model'].rms_forward + evs['model'].rms_backward) / fl.rms:.2f}")
    fig = args.out.with_name(args.out.stem + ".check.png")
    save(design_comparison(f"plan {args.plan}, DUs {dus}, hidden effect {cfg.effect.name}", evs), fig)
    print(f"figure: {fig}")
    return 0
