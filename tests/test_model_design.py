"""Model-based motion design (issue #11) in closed loop on virtual faces with known truth.

A small labeled session (DUs 1, 7, 12 with the identification battery) is simulated, the face
model is identified from it (hysteresis, plus the lag on the lag face), commands are designed by
the paper's inverse sigmoids (identified from the true trapezoid responses, as 'mocap run' would)
and through the model, and both are played on the same virtual face with its hidden effect
(noise-free: the simulator's true positions) and evaluated against the plan.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from mocap.analysis.design.inverse_response import PlanTiming, SigmoidPair, paper_design, paper_design_series
from mocap.analysis.design.model_based import (
    command_times,
    design_commands,
    debiased_delta,
    HOLD_LIFTS,
    default_preview,
    design_plan,
    evaluate_design,
    file_reference,
    hold_lift,
    marker_weights,
    plan_reference,
    plants,
    refined_reference,
    rest_state,
    set_at_rest,
    simulate_steps,
    tracking_floor,
    with_hold,
)
from mocap.analysis.design.plans import PLAN_NAMES
from conftest import make_session
from mocap.cli import main
from mocap.workflows.design import identify_model, load_model, play_virtual, save_model, virtual_face_of
from mocap.workflows.truth_properties import true_properties

DUS = (1, 7, 12)
FACE = dict(du_ids=DUS, n_markers=20, n_trials=2, labeled=True, motion_plans=(), seed=3)
TIMING = PlanTiming()
FALL_S = TIMING.start_s + TIMING.duration_s + TIMING.hold_s


def rms(ev) -> float:
    return 0.5 * (ev.rms_forward + ev.rms_backward)


class Face:
    """A simulated session, its identified model, its true face and the paper's responses."""

    def __init__(self, root, effect, effects, **face):
        make_session(root, effect=effect, **{**FACE, **face})
        self.root = root
        self.model, _ = identify_model(root / "session", effects)
        self.cfg, self.face = virtual_face_of(root / "session")
        props = true_properties(self.cfg, self.face).set_index("du")
        self.responses = {d: SigmoidPair(props.loc[d, "alpha_fwd"], props.loc[d, "beta_fwd"],
                                         props.loc[d, "alpha_bwd"], props.loc[d, "beta_bwd"])
                          for d in DUS}

    def play(self, rows, ref):
        X = play_virtual(self.cfg, self.face, rows, ref.end_s + 0.25)
        return X, evaluate_design(X, rows, self.cfg.fps, ref)


@pytest.fixture(scope="module")
def lag_face(tmp_path_factory):
    from mocap.simulate.effects import make_effect

    return Face(tmp_path_factory.mktemp("lag_face"), make_effect("lag"), ["hysteresis", "lag"])


@pytest.fixture(scope="module")
def plain_face(tmp_path_factory):
    """Nothing hidden, on a base the model does not share: Preisach hysteresis (a non-uniform
    relay density), straight marker paths, per-marker scatter and per-take bias shifts; the model
    is the workflow's base (hysteresis, per-marker paths, per-take shifts)."""
    from mocap.simulate.effects import HiddenEffect

    return Face(tmp_path_factory.mktemp("plain_face"), HiddenEffect(),
                ["hysteresis", "curvature", "takeshift"], face_family="preisach-straight")


def assert_valid_command_file(rows: pd.DataFrame, step_s: float, dus=DUS):
    assert list(rows.columns) == ["time_s", "du", "command"]
    assert pd.api.types.is_integer_dtype(rows["command"]) and rows["command"].between(0, 255).all()
    assert set(rows["du"]) == set(dus)
    for _, g in rows.groupby("du"):
        t = g["time_s"].to_numpy()
        assert t[0] == 0.0 and g["command"].iloc[0] == 0
        gaps = np.diff(t)
        assert np.all(gaps >= step_s - 1e-9)  # never faster than the rig's step
        # the rise and the return each on their own grid of command steps
        assert np.all(np.isclose(gaps[1:], step_s) | (gaps[1:] < 2 * step_s))


# ----------------------------------------------------------------------------------------------
# the stepped plant is the face model


def _random_steps(fps: float, n_steps: int, sd: float, seed: int):
    """Random-walk commands of every DU, one command step every 4 frames from 0.1 s: (step_s,
    levels (n_steps, n_dus), rows, n_frames, fractions inside a step, the frames at them)."""
    step_s = 4 / fps
    rng = np.random.default_rng(seed)
    levels = np.clip(np.cumsum(rng.normal(0, sd, (n_steps, len(DUS))), axis=0) + 120, 0,
                     255).astype(int)
    t = np.arange(n_steps) * step_s + 0.1
    rows = pd.concat([pd.DataFrame({"time_s": np.r_[0.0, t], "du": d, "command": np.r_[0, levels[:, n]]})
                      for n, d in enumerate(DUS)], ignore_index=True)
    n_frames = int(round((t[-1] + step_s) * fps))
    frac = np.array([0.25, 0.5, 0.75])
    frames = np.round((t[:, None] + frac[None] * step_s) * fps).astype(int).ravel()
    return step_s, levels, rows, n_frames, frac, frames


def test_stepped_plant_matches_the_face_model(lag_face):
    """Stepping the model between command steps gives the model's own response to random
    commands (hysteresis with reversals everywhere, and the lag), read at frames inside the steps."""
    from mocap.analysis.model.face_model import take_tables

    model = lag_face.model
    step_s, levels, rows, n_frames, frac, frames = _random_steps(model.fps, 60, 40.0, seed=1)
    fps = model.fps
    for n, p in enumerate(plants(model, DUS)):
        y, _ = simulate_steps(p, rest_state(p), levels[None, :, n].astype(float),
                              np.full(60, step_s), frac)
        tables = take_tables(rows[rows.du == p.du], [p.du], n_frames, fps, model.effects)
        y_model = model.response(tables, [p.du], 1)[frames, 0][:, p.markers]
        assert np.max(np.abs(y[0] - y_model)) < 0.002, p.du


@pytest.mark.parametrize("form", ["play", "stick-slip"])
def test_stepped_plant_matches_the_face_model_with_a_dead_band(lag_face, form):
    """The same with a dead band of 10 command units behind the lag, in either of its forms:
    the stick-slip one holds after each reversal and releases with a jump (its state carries the
    direction of the last motion from step to step)."""
    from mocap.analysis.model.face_model import take_tables
    from mocap.analysis.model.effects import Backlash, StickSlipBacklash

    cls = StickSlipBacklash if form == "stick-slip" else Backlash
    model = lag_face.model.with_effects(lag_face.model.effects + (cls(10.0),))
    step_s, levels, rows, n_frames, frac, frames = _random_steps(model.fps, 80, 25.0, seed=2)
    fps = model.fps
    held = 0
    for n, p in enumerate(plants(model, DUS)):
        assert p.stick_slip == (form == "stick-slip") and p.backlash == 10.0
        y, _ = simulate_steps(p, rest_state(p), levels[None, :, n].astype(float),
                              np.full(80, step_s), frac)
        tables = take_tables(rows[rows.du == p.du], [p.du], n_frames, fps, model.effects)
        y_model = model.response(tables, [p.du], 1)[frames, 0][:, p.markers]
        assert np.max(np.abs(y[0] - y_model)) < 0.002, p.du
        # the dead band acted: the response differs from the model without it
        plain = take_tables(rows[rows.du == p.du], [p.du], n_frames, fps, lag_face.model.effects)
        held += int(np.max(np.abs(lag_face.model.response(plain, [p.du], 1)[frames, 0][:, p.markers]
                                  - y_model)) > 0.01)
    assert held == len(DUS)


# ----------------------------------------------------------------------------------------------
# the criteria


@pytest.fixture(scope="module")
def lag_plans(lag_face):
    """Plans A-E on the lag face, each played twice: the paper method's commands and the model's
    first design. Per plan: (reference, paper evaluation, model design, played X, model
    evaluation); the first design is both the one judged against the paper and the first step of
    the refinement (computed once for both tests)."""
    out = {}
    for plan in PLAN_NAMES:
        ref = plan_reference(plan, TIMING)
        _, ev_p = lag_face.play(paper_design(plan, lag_face.responses, TIMING, DUS), ref)
        des = design_plan(lag_face.model, ref, DUS, step_s=TIMING.step_s, fall_start_s=FALL_S)
        X, ev_m = lag_face.play(des.rows, ref)
        out[plan] = (ref, ev_p, des, X, ev_m)
    return out


def test_model_design_beats_the_paper_on_a_lagging_face(lag_face, lag_plans):
    """Plans A-E on DUs 1+7+12 of a face with a hidden 80 ms lag: tracking RMS at most a third
    of the paper method's; the commands are valid command files."""
    assert lag_face.model.effect("lag") is not None
    assert abs(lag_face.model.effect("lag").value - 0.08) < 0.02
    assert sorted(lag_plans) == sorted(PLAN_NAMES)
    for plan, (_, ev_p, des, _, ev_m) in lag_plans.items():
        assert_valid_command_file(des.rows, TIMING.step_s)
        assert rms(ev_m) <= rms(ev_p) / 3, (plan, rms(ev_m), rms(ev_p))
        assert abs(ev_m.lag_s) <= 0.02, (plan, ev_m.lag_s)  # the paper lags up to 42 ms


def test_refinement_converges_to_a_fifth_of_the_paper(lag_face, lag_plans):
    """Iterative learning control from played takes: at most 5 repetitions bring every plan's
    tracking RMS to at most a fifth of the paper method's."""
    assert sorted(lag_plans) == sorted(PLAN_NAMES)
    for plan, (ref0, ev_p, des, X, ev) in lag_plans.items():
        target = rms(ev_p) / 5
        ref, history = des.reference, [rms(ev)]  # the first design's hold
        for _ in range(5):
            if history[-1] <= target:
                break
            ref = refined_reference(lag_face.model, ref0, des.rows, X, lag_face.face.marker_names,
                                    previous=ref)
            des = design_commands(lag_face.model, ref, DUS, step_s=TIMING.step_s,
                                  fall_start_s=FALL_S)
            assert_valid_command_file(des.rows, TIMING.step_s)
            X, ev = lag_face.play(des.rows, ref0)
            history.append(rms(ev))
        assert history[-1] <= target, (plan, history, rms(ev_p))


@pytest.fixture(scope="module")
def plain_plans(plain_face):
    """Plans A-E on the plain face: (reference, paper evaluation, the model's design with its
    hold chosen on the model, its evaluation, the design with the hold at 1, its evaluation)."""
    out = {}
    for plan in PLAN_NAMES:
        ref = plan_reference(plan, TIMING)
        _, ev_p = plain_face.play(paper_design(plan, plain_face.responses, TIMING, DUS), ref)
        des = design_plan(plain_face.model, ref, DUS, step_s=TIMING.step_s, fall_start_s=FALL_S)
        flat = des.tried[0]  # the hold at 1: what design_commands makes of the plan itself
        out[plan] = (ref, ev_p, des, plain_face.play(des.rows, ref)[1], flat,
                     plain_face.play(flat.rows, ref)[1])
    return out


def test_design_plan_tries_each_hold_as_design_commands_would(lag_face, lag_plans):
    """design_plan replays the rise it shares between hold levels instead of searching it again:
    each level's commands are exactly design_commands' for the plan with that hold, and the one
    kept is the one the model predicts to score best."""
    ref, _, des, _, _ = lag_plans["C"]
    levels = [t.level for t in des.tried]
    assert levels == sorted(levels) and levels[0] == 1.0 and len(levels) == len(HOLD_LIFTS)
    assert des.hold_level == min(des.tried, key=lambda t: t.predicted_rms).level
    top = des.tried[-1]
    alone = design_commands(lag_face.model, with_hold(ref, top.level), DUS, step_s=TIMING.step_s,
                            fall_start_s=FALL_S)
    pd.testing.assert_frame_equal(alone.rows, top.rows)
    kept = next(t for t in des.tried if t.level == des.hold_level)
    pd.testing.assert_frame_equal(des.rows, kept.rows)
    # with a non-causal pass after the causal one, on a short plan (20 steps, a 0.2 s hold)
    short = PlanTiming(n_steps=20, hold_s=0.2)
    ref = plan_reference("E", short)
    fall = short.start_s + short.duration_s + short.hold_s
    des = design_plan(lag_face.model, ref, DUS, step_s=short.step_s, fall_start_s=fall, sweeps=1,
                      preview=2)
    for t in des.tried[1:]:
        alone = design_commands(lag_face.model, with_hold(ref, t.level), DUS, step_s=short.step_s,
                                fall_start_s=fall, sweeps=1, preview=2)
        pd.testing.assert_frame_equal(alone.rows, t.rows)


def test_the_causal_pass_previews_two_steps_where_the_model_has_actuator_dynamics(lag_face,
                                                                                   plain_face):
    """The default preview follows the identified model, not the face: 2 command steps with a
    lag or a dead time, 1 (greedy) without; the designs made with the default are those made
    with it given explicitly."""
    lagged, plain = lag_face.model, plain_face.model
    assert lagged.effect("lag") is not None and default_preview(lagged) == 2
    assert lagged.effect("deadtime") is None and plain.effect("lag") is None
    assert default_preview(plain) == 1
    without = lagged.with_effects(tuple(e for e in lagged.effects if e.name != "lag"))
    assert default_preview(without) == 1
    ref = plan_reference("E", PlanTiming(n_steps=20, hold_s=0.2))
    for model, preview in ((lagged, 2), (plain, 1)):
        a = design_commands(model, ref, DUS, step_s=TIMING.step_s)
        b = design_commands(model, ref, DUS, step_s=TIMING.step_s, preview=preview)
        c = design_commands(model, ref, DUS, step_s=TIMING.step_s, preview=3 - preview)
        pd.testing.assert_frame_equal(a.rows, b.rows)
        assert not a.rows.equals(c.rows)


def test_model_design_beats_the_paper_on_a_face_without_effects(plain_face, plain_plans):
    """Nothing hidden, on a base family the model does not share: the model's design tracks
    plans B-E at most a third of the paper method's RMS on the true face, the paper's sigmoids
    at their best (the true face's). Plan A's fast rise meets the command grid's floor (the
    staircase of rows every 16 ms on a face that responds at once): it is held to twice that
    floor instead (test_no_command_file_beats_the_tracking_floor_on_a_face_that_responds_at_once)."""
    assert not {"lag", "deadtime", "backlash"} & set(plain_face.model.effect_names)
    ratios = {plan: rms(ev_m) / rms(ev_p) for plan, (_, ev_p, _, ev_m, _, _) in plain_plans.items()}
    for plan, (_, _, des, _, _, _) in plain_plans.items():
        assert_valid_command_file(des.rows, TIMING.step_s)
        assert plan == "A" or ratios[plan] <= 1 / 3, ratios


def test_hold_level_is_chosen_on_the_model_of_the_face(plain_plans):
    """The evaluation divides each marker by the mean of its displacement over the frames within
    5 % of its largest, which takes in the top of the rise: on straight marker paths a design
    that holds at 1 reads high on the hold and on the upper rise. The model's prediction lifts
    the hold there (by about hold_lift(): 0.0075 for plans A and E, 0.0084 for B and D), and the
    lifted design tracks better on the true face, most where the rise ends slowly (B, D)."""
    for plan, (ref, _, des, ev_m, flat, ev_flat) in plain_plans.items():
        assert des.hold_level is not None and flat.level == 1.0
        assert des.hold_level <= 1 + 1.5 * hold_lift(ref) + 1e-12
        held = des.reference.at(np.array([TIMING.start_s + TIMING.duration_s + 0.1]), 1)[0, 0]
        assert held == pytest.approx(des.hold_level)
        assert rms(ev_m) <= rms(ev_flat) * 1.01, (plan, rms(ev_m), rms(ev_flat))
        if plan in "BD":
            assert des.hold_level > 1.0 + 0.5 * hold_lift(ref) - 1e-12, (plan, des.hold_level)
            assert rms(ev_m) <= 0.9 * rms(ev_flat), (plan, rms(ev_m), rms(ev_flat))


def test_tracking_floor_is_the_best_staircase_on_the_grid():
    """The floor against a plain frame loop: each frame driven by the last row at or before it,
    each step's level the plan's mean over its frames (over the fall no lower than the set);
    no other staircase on the grid does better."""
    ref = plan_reference("A", TIMING)
    fps = 120.0
    times = command_times(ref, TIMING.step_s, FALL_S)
    set_level = 0.007
    fl = tracking_floor(ref, times, fps, set_level)
    n = int(np.ceil(ref.end_s * fps)) + 1
    t = np.arange(n) / fps
    ideal = np.interp(t, ref.t_s, ref.ideal)
    owner = []
    for tf in t:
        k = 0
        for i, tr in enumerate(times):
            if tr <= tf + 1e-9:
                k = i + 1
        owner.append(k)
    owner = np.array(owner)
    levels = {k: ideal[owner == k].mean() for k in set(owner.tolist())}
    best = np.array([levels[k] for k in owner])

    def score(stairs):
        out = []
        for (a, b), lo in ((ref.rise, -np.inf), (ref.fall, set_level)):
            sl = slice(int(round(a * fps)), int(round(b * fps)))
            out.append(np.sqrt(np.mean((np.maximum(stairs[sl], lo) - ideal[sl]) ** 2)))
        return out

    fwd, bwd = score(best)
    assert fl.forward == pytest.approx(fwd, rel=1e-9) and fl.backward == pytest.approx(bwd, rel=1e-9)
    assert 0.003 < fl.forward < 0.006  # a 16 ms staircase at 120 fps on plan A's rise
    assert fl.backward > tracking_floor(ref, times, fps, 0.0).backward  # the set costs on the fall
    rng = np.random.default_rng(0)
    for _ in range(20):
        jitter = {k: rng.normal(0.0, 0.01) for k in levels}
        other = best + np.array([jitter[k] for k in owner])
        assert 0.5 * sum(score(other)) >= fl.rms


def test_no_command_file_beats_the_tracking_floor_on_a_face_that_responds_at_once(plain_face,
                                                                                  plain_plans):
    """On the plain face (nothing hidden: no actuator dynamics) the paper's design of plan A,
    the model's and commands scattered around them all track no better than the floor of their
    command grid, with the set read on those plays (they all end at command 0); the model's
    design comes within a factor 2 of it."""
    rng = np.random.default_rng(1)
    ref, des = plain_plans["A"][0], plain_plans["A"][2]
    played = []
    for rows in (paper_design("A", plain_face.responses, TIMING, DUS), des.rows):
        c = rows["command"].to_numpy()
        moved = np.clip(c + rng.integers(-6, 7, c.size), 0, 255)
        moved[(c == 0)] = 0  # rest stays at rest: every file ends at command 0
        for r in (rows, rows.assign(command=moved)):
            played.append((r, plain_face.play(r, ref)[1]))
    set_level = set_at_rest(played, plain_face.cfg.fps)
    assert 0.0 < set_level < 0.05, set_level
    fl = tracking_floor(ref, command_times(ref, TIMING.step_s, FALL_S), plain_face.cfg.fps,
                        set_level)
    for _, ev in played:
        assert rms(ev) >= fl.rms, (rms(ev), fl)
    assert rms(played[2][1]) <= 2 * fl.rms, (rms(played[2][1]), fl)


def test_model_design_with_coupled_dus(tmp_path_factory):
    """DUs sharing skin (hidden coupling 0.35, identified by the model): the DUs' commands are
    chosen together through the model's interaction, and track far better than the paper's."""
    from mocap.simulate.effects import make_effect

    face = Face(tmp_path_factory.mktemp("coupled_face"), make_effect("coupling"),
                ["hysteresis", "coupling"])
    assert abs(face.model.parameters()["kappa"] - 0.35) < 0.1  # read from the pair vectors
    for plan in "AE":
        ref = plan_reference(plan, TIMING)
        _, ev_p = face.play(paper_design(plan, face.responses, TIMING, DUS), ref)
        des = design_commands(face.model, ref, DUS, step_s=TIMING.step_s, fall_start_s=FALL_S)
        _, ev_m = face.play(des.rows, ref)
        assert rms(ev_m) <= rms(ev_p) / 2, (plan, rms(ev_m), rms(ev_p))


def test_plan_with_a_reversal_in_the_middle(lag_face, tmp_path):
    """A smile that relaxes half-way and comes back (a plan FILE): the model's minor loops and
    lag let the design follow it; the paper's rule (branch switch at the reversal) cannot."""
    s = np.linspace(0.0, 3.0, 301)
    P = np.interp(s, [0, 1.0, 1.6, 2.4, 3.0], [0, 0.9, 0.45, 0.85, 0.0])
    f = tmp_path / "relax.csv"
    pd.DataFrame({"time_s": s, "P": P}).to_csv(f, index=False)
    ref = file_reference(f, TIMING)
    des = design_commands(lag_face.model, ref, DUS, step_s=TIMING.step_s)
    assert_valid_command_file(des.rows, TIMING.step_s)
    paper = paper_design_series(s, P, lag_face.responses, start_s=TIMING.start_s,
                                step_s=TIMING.step_s, dus=DUS)
    _, ev_m = lag_face.play(des.rows, ref)
    _, ev_p = lag_face.play(paper, ref)
    assert ev_m.rms_forward < 0.02
    assert ev_m.rms_forward <= ev_p.rms_forward / 3, (ev_m.rms_forward, ev_p.rms_forward)


def test_marker_choice_and_errors(lag_face, tmp_path):
    model = lag_face.model
    w_all = marker_weights(model, DUS)
    assert np.isclose(w_all.sum(), 1.0) and (w_all > 0).sum() > 10
    name = model.marker_names[int(np.argmax(w_all))]
    w_near = marker_weights(model, DUS, ("near", name, 15.0))
    assert 0 < (w_near > 0).sum() < (w_all > 0).sum()
    w_named = marker_weights(model, DUS, [name])
    assert w_named[model.marker_names.index(name)] == 1.0
    with pytest.raises(ValueError, match="not in the model"):
        marker_weights(model, DUS, ["NOPE"])
    with pytest.raises(ValueError, match="no DUs"):
        design_commands(model, plan_reference("A"), [99])
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="preview"):
            design_commands(model, plan_reference("A"), DUS, preview=bad)
    bad = tmp_path / "bad.csv"
    pd.DataFrame({"time_s": [0, 1, 2], "P": [0, 1.5, 0]}).to_csv(bad, index=False)
    with pytest.raises(ValueError, match="row 3"):
        file_reference(bad)


# ----------------------------------------------------------------------------------------------
# the command line


def test_design_check_reports_the_floor_of_the_command_grid(plain_face, tmp_path, capsys):
    """--check on a face without actuator dynamics prints the grid's floor, and the played model
    design sits above it."""
    model_file = save_model(plain_face.model, tmp_path / "plain.model",
                            source=plain_face.root / "session")
    out = tmp_path / "smile_A.csv"
    assert main(["design", str(plain_face.root / "session"), "--plan", "A", "--dus", "1,7,12",
                 "--method", "model", "--model", str(model_file), "--check", "--out", str(out)]) == 0
    line = [x for x in capsys.readouterr().out.splitlines() if x.startswith("floor of the command")]
    assert len(line) == 1, line
    ratio = float(line[0].rsplit("model / floor", 1)[1])
    assert 1.0 <= ratio <= 2.0, line[0]


def test_design_cli_model_check_and_refine(lag_face, tmp_path, capsys):
    src = lag_face.root / "session"
    out = tmp_path / "smile_planA.csv"
    model_file = tmp_path / "lag_face.model"
    assert main(["design", str(src), "--plan", "A", "--dus", "1,7,12", "--method", "model",
                 "--effects", "hysteresis,lag", "--check", "--save-model", str(model_file),
                 "--out", str(out)]) == 0
    text = capsys.readouterr().out
    # the command line identifies the model as the library does (the fixture's), and saves it
    saved = load_model(model_file)
    assert saved.parameters() == lag_face.model.parameters()
    for name in ("alpha", "beta", "r", "D", "B", "density", "branch"):
        np.testing.assert_array_equal(getattr(saved, name), getattr(lag_face.model, name))
    assert "closed loop model" in text and (tmp_path / "smile_planA.check.png").is_file()
    assert "floor of the command grid" not in text  # a lag smooths the staircase: no floor
    rows = pd.read_csv(out)
    assert_valid_command_file(rows, TIMING.step_s)
    assert (tmp_path / "smile_planA.reference.csv").is_file()
    # play it on the robot (a new session with the file as a motion take) and refine from it
    played = tmp_path / "played"
    from mocap.simulate.effects import make_effect

    make_session(played, effect=make_effect("lag"), battery=False, extra_commands=(out,),
                 **{**FACE, "n_trials": 1})
    out2 = tmp_path / "smile_planA_2.csv"
    # the refinement designs with the saved model (identifying it again would give the same)
    assert main(["design", str(src), "--plan", "A", "--dus", "1,7,12", "--method", "model",
                 "--model", str(model_file), "--refine", "commands_01_smile_planA",
                 "--measured", str(played / "session"), "--reference",
                 str(tmp_path / "smile_planA.reference.csv"), "--out", str(out2)]) == 0
    rows2 = pd.read_csv(out2)
    assert_valid_command_file(rows2, TIMING.step_s)
    assert not rows2["command"].equals(rows["command"])
    ref = plan_reference("A", TIMING)
    _, ev1 = lag_face.play(rows, ref)
    _, ev2 = lag_face.play(rows2, ref)
    # a noisy played take (0.02 mm labeled noise) still improves the design
    assert rms(ev2) < rms(ev1)
    assert main(["design", str(src), "--plan", "A", "--dus", "1,7,12", "--method", "model",
                 "--effects", "hysteresis,lag", "--refine", "nope", "--out", str(out2)]) == 1
    assert "no commanded take 'nope'" in capsys.readouterr().err
    assert main(["design", str(src), "--plan", "A", "--dus", "1,7,12", "--method", "model",
                 "--effects", "wobble", "--out", str(out2)]) == 1
    assert "unknown wobble" in capsys.readouterr().err
    assert main(["design", str(src), "--plan", "A", "--dus", "1,7,12", "--method", "model",
                 "--model", str(out), "--out", str(out2)]) == 1
    assert "expected a face model file" in capsys.readouterr().err
    assert main(["design", str(src), "--plan", "A", "--dus", "1,7,12", "--method", "model",
                 "--model", str(model_file), "--effects", "lag", "--out", str(out2)]) == 1
    assert "give one of them" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------
# a base-face family the model does not share (issue #15)


def test_closed_loop_plays_the_sessions_own_family_face(tmp_path):
    """The --check face is the session's: its family and its effect's alternative form
    (truth/face.parquet and truth.json), not the default pi face with the model-form effect."""
    from mocap.simulate.effects import make_effect
    from mocap.simulate.session_writer import face_table

    make_session(tmp_path, face_family="preisach-offchord", effect=make_effect("lag", form="alt"),
                 du_ids=(1, 7), n_markers=12, n_trials=1, labeled=True, motion_plans=(),
                 battery=False, seed=5)
    cfg, face = virtual_face_of(tmp_path / "session")
    assert face.family.name == "preisach-offchord" and cfg.effect.form == "alt"
    truth = pd.read_parquet(tmp_path / "truth" / "face.parquet")
    mine = face_table(face)
    for col in ("peak_x", "alpha", "beta", "r_half", "alpha_bwd", "path_x"):
        np.testing.assert_allclose(mine[col].to_numpy(), truth[col].to_numpy(), atol=1e-9)


def test_model_design_on_a_bouc_wen_bowed_face_with_an_alt_lag(tmp_path):
    """A face of another family (Bouc-Wen hysteresis, bowed marker paths, per-marker scatter and
    per-take bias shifts) with a hidden second-order lag (an equation the model does not share):
    the model identified from the session (the workflow's base: hysteresis, per-marker paths and
    per-take shifts; plus its first-order lag) designs plans A-E that track at most a third of
    the paper method's RMS on the TRUE face (the simulator plays both designs), with the paper's
    sigmoids at their best (the true face's): 0.04-0.11 of it on plans B-E, 0.29 on plan A, whose
    fast rise is where the model's first-order lag departs most from the face's second-order one
    (0.31 with a greedy causal pass instead of the default two-step preview; 0.33 at 40 markers
    before it; benchmarks/design_sweep.md)."""
    from mocap.simulate.effects import make_effect

    make_session(tmp_path, face_family="boucwen-bow", effect=make_effect("lag", form="alt"),
                 du_ids=DUS, n_markers=20, n_trials=2, labeled=True, labeled_noise_mm=0.03,
                 motion_plans=(), seed=1)
    model, _ = identify_model(tmp_path / "session", ["hysteresis", "curvature", "takeshift", "lag"])
    cfg, face = virtual_face_of(tmp_path / "session")
    assert face.family.name == "boucwen-bow"
    props = true_properties(cfg, face).set_index("du")
    responses = {d: SigmoidPair(props.loc[d, "alpha_fwd"], props.loc[d, "beta_fwd"],
                                props.loc[d, "alpha_bwd"], props.loc[d, "beta_bwd"]) for d in DUS}
    for plan in PLAN_NAMES:
        ref = plan_reference(plan, TIMING)
        des = design_plan(model, ref, DUS, step_s=TIMING.step_s, fall_start_s=FALL_S)
        assert_valid_command_file(des.rows, TIMING.step_s)
        paper = paper_design(plan, responses, TIMING, DUS)
        ev_p = evaluate_design(play_virtual(cfg, face, paper, ref.end_s + 0.25), paper, cfg.fps, ref)
        ev_m = evaluate_design(play_virtual(cfg, face, des.rows, ref.end_s + 0.25), des.rows,
                               cfg.fps, ref)
        assert rms(ev_m) <= rms(ev_p) / 3, (plan, rms(ev_m), rms(ev_p))
        # bowed paths: the plateau already reads high, the model keeps the hold near 1 (a lift
        # of hold_lift() made plan B 45 % worse on the PI bowed face)
        flat = des.tried[0].rows  # the plan's own hold, designed on the way
        assert des.tried[0].level == 1.0
        ev_f = evaluate_design(play_virtual(cfg, face, flat, ref.end_s + 0.25), flat, cfg.fps, ref)
        assert rms(ev_m) <= rms(ev_f) * 1.02, (plan, des.hold_level, rms(ev_m), rms(ev_f))


def test_two_step_preview_tracks_a_second_order_lag_better_than_greedy(tmp_path):
    """Why the default preview is 2 with a lag: on a straight-path PI face whose hidden lag is
    second order (an equation the model's first-order lag does not share), the default design
    of plans D and E, played on the TRUE face, tracks at most 0.9 of the greedy design's RMS
    (measured 0.66 and 0.80) and at most a third of the paper method's (0.05 and 0.24; greedy
    plan E 0.30). Scored by the simulator, not by the model that chose the commands."""
    from mocap.simulate.effects import make_effect

    make_session(tmp_path, face_family="pi-straight", effect=make_effect("lag", form="alt"),
                 du_ids=DUS, n_markers=20, n_trials=2, labeled=True, labeled_noise_mm=0.03,
                 motion_plans=(), seed=1)
    model, _ = identify_model(tmp_path / "session", ["hysteresis", "curvature", "takeshift", "lag"])
    assert default_preview(model) == 2
    cfg, face = virtual_face_of(tmp_path / "session")
    props = true_properties(cfg, face).set_index("du")
    responses = {d: SigmoidPair(props.loc[d, "alpha_fwd"], props.loc[d, "beta_fwd"],
                                props.loc[d, "alpha_bwd"], props.loc[d, "beta_bwd"]) for d in DUS}

    def played(rows, ref):
        X = play_virtual(cfg, face, rows, ref.end_s + 0.25)
        return rms(evaluate_design(X, rows, cfg.fps, ref))

    for plan in "DE":
        ref = plan_reference(plan, TIMING)
        paper = played(paper_design(plan, responses, TIMING, DUS), ref)
        default, greedy = (played(design_plan(model, ref, DUS, step_s=TIMING.step_s,
                                              fall_start_s=FALL_S, **kw).rows, ref)
                           for kw in ({}, {"preview": 1}))
        assert default <= 0.9 * greedy, (plan, default, greedy)
        assert default <= paper / 3, (plan, default, paper)


def test_debiased_delta_has_no_noise_bias_for_the_refinement_to_learn():
    """A measured take's normalised displacement as the refinement reads it, against the
    evaluation's on the noise-free positions (numpy-made face of bowed paths, tests/
    synthetic_faces.py; 20 markers moving 0.15-3 mm, one trapezoid, 0.03 mm noise per axis, 40
    draws; the evaluation's reading computed plainly here): the markers' mean error, which the refinement would learn as a tracking error, is
    within 0.004 on the hold and at rest (measured: -0.0012 and -0.0008; the plain reading of the
    noisy take: -0.039 on the hold, where its plateau keeps the frames whose noise is high, and
    +0.094 at rest, where |d| of noise is positive). Noise-free data give the evaluation's
    reading."""
    from synthetic_faces import FPS, make_take

    def plain_delta(X, command):
        # the evaluation's normalised displacement, plainly: |x - rest| over the mean of
        # |x - rest| on the frames whose 6-frame mean (frames f-2..f+3) is within 5 % of its
        # largest; rest the mean over the frames before the first command change
        lead = int(np.flatnonzero(np.diff(command) != 0)[0]) + 1
        length = np.linalg.norm(X - X[:lead].mean(axis=0), axis=-1)
        out = np.empty_like(length)
        for m in range(length.shape[1]):
            x = length[:, m]
            s = np.array([x[max(0, f - 2): f + 4].mean() for f in range(x.size)])
            out[:, m] = x / x[s >= 0.95 * s.max()].mean()
        return out

    rng = np.random.default_rng(3)
    take = make_take(rng, family="bow", n_markers=20, n_trials=1, lead_s=0.25, tail_s=0.6)
    X = take.trials[0]
    truth = plain_delta(X, take.series)
    np.testing.assert_allclose(debiased_delta(X, take.series)[0], truth, atol=1e-9)
    ours, plain = [], []
    for _ in range(40):
        Xn = X + rng.normal(0.0, 0.03, X.shape)
        ours.append(debiased_delta(Xn, take.series, max_select_frames=int(0.5 * FPS))[0] - truth)
        plain.append(plain_delta(Xn, take.series) - truth)
    t = np.arange(X.shape[0]) / FPS
    hold = (take.series == 255) & (t > t[np.argmax(take.series == 255)] + 0.25)
    rest = (t < 0.25) | (t > take.time_s[-1] + 0.1)
    for name, err in (("ours", ours), ("plain", plain)):
        b = np.nanmean(np.array(err), axis=(0, 2))  # the markers' mean error per frame
        bias = float(np.mean(b[hold])), float(np.mean(b[rest]))
        if name == "ours":
            assert max(map(abs, bias)) < 0.004, bias
        else:  # what the correction removes
            assert bias[0] < -0.006 and bias[1] > 0.006, bias
    # missing samples stay missing; a marker never seen has no plateau
    Xn[100:160, 3] = np.nan
    Xn[:, 7] = np.nan
    delta, peak, _ = debiased_delta(Xn, take.series)
    seen = np.isfinite(Xn[..., 0])
    assert np.isnan(delta[~seen]).all() and np.isfinite(delta[seen]).all()
    assert np.isnan(peak[7]) and np.isfinite(np.delete(peak, 7)).all()


def test_refinement_from_noisy_takes_learns_the_designs_mean_error(plain_face):
    """One refinement from a take measured with 0.03 mm noise on the plain face (2 trials, 20
    markers, Preisach straight; the true positions score it). The signal-to-noise weights that
    keep the small markers' noise out of the learnt error average the markers in other weights
    than the design's; the model's prediction as a control variate restores the design's mean
    (only the model's error is read in those weights). Measured, model / paper RMS after one
    play: plan C 0.108 with it, 0.132 without (noise-free plays: 0.072); plan D 0.126 and 0.158
    (0.098)."""
    from mocap.workflows.design import play_virtual_take

    for plan in ("C", "D"):
        ref = plan_reference(plan, TIMING)
        _, ev_p = plain_face.play(paper_design(plan, plain_face.responses, TIMING, DUS), ref)
        des = design_plan(plain_face.model, ref, DUS, step_s=TIMING.step_s, fall_start_s=FALL_S)
        _, X = play_virtual_take(plain_face.cfg, plain_face.face, des.rows, ref.end_s + 0.25, 0.03,
                                 seed=100, trial_variation=False)
        ratio = {}
        for control in (True, False):
            r1 = refined_reference(plain_face.model, ref, des.rows, X, plain_face.face.marker_names,
                                   previous=des.reference, control=control)
            rows = design_commands(plain_face.model, r1, DUS, step_s=TIMING.step_s,
                                   fall_start_s=FALL_S).rows
            ratio[control] = rms(plain_face.play(rows, ref)[1]) / rms(ev_p)
        assert ratio[True] <= 0.13 and ratio[True] < ratio[False] - 0.015, (plan, ratio)
