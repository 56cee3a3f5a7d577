"""`mocap design` on a session leaves no temporary run behind (issue #18's bug)."""

from __future__ import annotations

import tempfile

import pandas as pd
from conftest import make_session

from mocap.cli import main


def test_design_on_a_session_removes_its_temporary_run(tmp_path, monkeypatch):
    make_session(tmp_path / "sim", du_ids=(4,), n_trials=2, n_markers=24, battery=False,
                 motion_plans=(), labeled=True, seed=2)
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))  # where mkdtemp would leave it
    out = tmp_path / "du04_planA.csv"
    assert main(["design", str(tmp_path / "sim" / "session"), "--plan", "A", "--dus", "4",
                 "--out", str(out)]) == 0
    rows = pd.read_csv(out)
    assert set(rows["du"]) == {4} and rows["command"].between(0, 255).all()
    assert list(scratch.iterdir()) == []  # the pipeline ran in scratch and was cleaned up
