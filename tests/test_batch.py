"""Many sessions on a Dask LocalCluster; one failure does not stop the others."""

from __future__ import annotations

import json

from conftest import make_session
from mocap.cli import main


def test_batch_runs_sessions_and_reports_failures(tmp_path, capsys):
    kw = dict(du_ids=(4,), n_trials=2, n_markers=15, motion_plans=(), battery=False, labeled=True)
    a = make_session(tmp_path / "robot_a", seed=1, **kw) / "session"
    b = make_session(tmp_path / "robot_b", seed=2, **kw) / "session"
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "session.toml").write_text('schema = "mocap-session/0"\n')
    rc = main(["batch", str(a), str(b), str(broken), "--out", str(tmp_path / "out"), "--workers", "2"])
    assert rc == 1
    summary = json.loads((tmp_path / "out" / "batch.json").read_text())
    assert summary["ok"] == 2 and summary["failed"] == 1
    bad = next(r for r in summary["sessions"] if not r["ok"])
    assert "schema" in bad["error"]
    for name in ("robot_a", "robot_b"):
        assert (tmp_path / "out" / name / "properties.csv").is_file()
        # the figure writers reach the Dask workers (passed in, pickled by reference)
        assert (tmp_path / "out" / name / "figures" / "property_chart.png").stat().st_size > 5000
    assert "FAILED" in capsys.readouterr().out
