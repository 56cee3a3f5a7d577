"""The command line: every command documents itself with an example."""

from __future__ import annotations

import pandas as pd
import pytest

from mocap.cli import COMMANDS, main


def test_top_level_help_lists_every_command(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    for name in COMMANDS:
        assert name in out


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_command_has_help_with_an_example(name, capsys):
    with pytest.raises(SystemExit) as e:
        main([name, "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "example" in out and f"mocap {name}" in out


def test_no_command_prints_help(capsys):
    assert main([]) == 2
    assert "COMMAND" in capsys.readouterr().out


def test_schedule_writes_the_battery(tmp_path):
    assert main(["schedule", "--dus", "1,4", "--pairs", "1-4", "--out", str(tmp_path)]) == 0
    files = sorted(p.name for p in tmp_path.glob("*.csv"))
    assert "du01_trapezoid.csv" in files and "du01_du04_sync.csv" in files and len(files) == 10
    rows = pd.read_csv(tmp_path / "du04_minor.csv")
    assert list(rows.columns) == ["time_s", "du", "command"]
    assert rows["command"].between(0, 255).all() and (rows["du"] == 4).all()
    assert "Total" in (tmp_path / "README.md").read_text()
    assert main(["schedule", "--dus", "x", "--out", str(tmp_path)]) == 1


def test_one_blas_thread_unless_the_user_chose(monkeypatch):
    from mocap.cli import single_threaded_blas

    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    monkeypatch.setenv("OMP_NUM_THREADS", "4")
    single_threaded_blas()
    import os

    assert os.environ["OPENBLAS_NUM_THREADS"] == "1"
    assert os.environ["OMP_NUM_THREADS"] == "4"  # the user's choice stays
