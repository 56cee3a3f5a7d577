"""Motion design in closed loop on the virtual face: identify, design, play, evaluate."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from mocap.analysis.design.inverse_response import PlanTiming, SigmoidPair, paper_design
from conftest import make_session
from mocap.cli import main
from mocap.workflows.run.pipeline import run_session
from mocap.outputs.run_writers import WRITERS

FACE = dict(du_ids=(1, 4, 7, 11, 12), n_trials=3, n_markers=60, battery=False, motion_plans=(),
            labeled=True, seed=5)


def test_design_rows_are_valid_command_files():
    timing = PlanTiming()
    rows = paper_design("B", {1: SigmoidPair(0.03, 140, 0.03, 120),
                              7: SigmoidPair(0.045, 160, 0.045, 90)}, timing)
    assert set(rows["du"]) == {1, 7}
    assert pd.api.types.is_integer_dtype(rows["command"]) and rows["command"].between(0, 255).all()
    for _, g in rows.groupby("du"):
        t = g["time_s"].to_numpy()
        steps = np.diff(t[1:])
        # the rig's step time is respected (one row per step; the hold is a single gap)
        assert np.all(np.isclose(steps, timing.step_s) | np.isclose(steps, timing.step_s + timing.hold_s))
        c = g["command"].to_numpy()
        assert c[: timing.n_steps + 1].tolist() == sorted(c[: timing.n_steps + 1])  # rising
        assert c[timing.n_steps + 1:].tolist() == sorted(c[timing.n_steps + 1:], reverse=True)


def test_design_cli_errors(tmp_path, capsys):
    assert main(["design", str(tmp_path), "--plan", "A", "--dus", "4", "--out", str(tmp_path / "c.csv")]) == 1
    assert "neither properties.csv" in capsys.readouterr().err
    assert main(["design", str(tmp_path), "--plan", "Z", "--dus", "4", "--out", str(tmp_path / "c.csv")]) == 1
    assert "expected one of" in capsys.readouterr().err
    for bad in (["--preview", "0"], ["--sweeps", "-1"]):
        assert main(["design", str(tmp_path), "--plan", "A", "--dus", "4", "--method", "model",
                     "--out", str(tmp_path / "c.csv"), *bad]) == 1
        assert "--preview/--sweeps" in capsys.readouterr().err


@pytest.fixture(scope="module")
def closed_loop(tmp_path_factory):
    root = tmp_path_factory.mktemp("closed_loop")
    make_session(root / "ident", **FACE)
    run_session(root / "ident" / "session", root / "ident_out")
    files = []
    for plan in "ABCDE":
        for dus, name in (("4", "du04"), ("11", "du11"), ("1,7,12", "smile")):
            f = root / f"{name}_plan{plan}.csv"
            assert main(["design", str(root / "ident_out"), "--plan", plan, "--dus", dus,
                         "--out", str(f)]) == 0
            files.append(f)
    make_session(root / "play", **FACE, extra_commands=tuple(files))
    res = run_session(root / "play" / "session", root / "play_out", writers=WRITERS)
    out = {}
    for take, plan, ev in res.analysis.motions:
        kind = "du04" if "du04" in take else "du11" if "du11" in take else "smile"
        out[(kind, plan)] = ev
    return out, root


def test_closed_loop_reproduces_the_papers_findings(closed_loop):
    evs, root = closed_loop
    assert len(evs) == 15
    rms = {k: 0.5 * (ev.rms_forward + ev.rms_backward) for k, ev in evs.items()}
    spread = {k: float(np.nanmean(ev.std)) for k, ev in evs.items()}
    mean = lambda kind, d: np.mean([d[(kind, p)] for p in "ABCDE"])  # noqa: E731
    # the 3-DU smile follows its plans closely
    assert all(rms[("smile", p)] < 0.06 for p in "ABCDE")
    # the very sensitive DU 4 tracks worst on average
    assert mean("du04", rms) > mean("du11", rms) > mean("smile", rms)
    # the high-dyssynchrony DU 11 follows on average, with the largest spread over markers
    assert mean("du11", rms) < 0.08
    assert all(spread[("du11", p)] > spread[("du04", p)] for p in "ABCDE")
    assert (root / "play_out" / "figures" / "motion_commands_01_du04_planA.png").is_file()
