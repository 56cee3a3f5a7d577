"""Command / capture alignment: ``commands_offset_s`` and ``mocap import --align-commands``.

A small labeled session is simulated once (a face without dead time); every command file is
then shifted by 0.25 s by hand (the log started 0.25 s before the cameras), with and without
``commands_offset_s = -0.25`` typed into the manifest.
"""

from __future__ import annotations

import re
import shutil
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from mocap.core.session import SessionError, command_matrix, load_session

SHIFT_S = 0.25
FPS = 120.0


def _shift_session(src: Path, dst: Path, offset: float | None) -> Path:
    """A copy of ``src`` whose command files all start 0.25 s later (written here with pandas),
    with ``commands_offset_s = offset`` after every commands line when ``offset`` is given."""
    shutil.copytree(src, dst)
    for f in (dst / "takes").glob("*_commands.csv"):
        rows = pd.read_csv(f)
        rows["time_s"] = rows["time_s"] + SHIFT_S
        rows.to_csv(f, index=False, float_format="%.17g")
    if offset is not None:
        text = (dst / "session.toml").read_text()
        text = re.sub(r"^(commands = .*)$", rf"\1\ncommands_offset_s = {offset!r}", text,
                      flags=re.MULTILINE)
        (dst / "session.toml").write_text(text)
    return dst


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    """(unshifted, shifted with the offset, shifted without it) session folders."""
    from mocap.simulate import simulate
    from mocap.simulate.config import preset

    root = tmp_path_factory.mktemp("align")
    cfg = preset("small", seed=5, du_ids=(4, 7), n_markers=20, n_trials=2, battery=False,
                 motion_plans=("A",), motion_dus=(4, 7), labeled=True, ground=False)
    simulate(cfg, root / "sim")
    base = root / "sim" / "session"
    return (base, _shift_session(base, root / "offset", -SHIFT_S),
            _shift_session(base, root / "shifted", None))


@pytest.fixture(scope="module")
def runs(sessions, tmp_path_factory):
    """RunResults of the unshifted and the offset session (full analyses), and of the shifted
    one without its offset (audit only)."""
    from mocap.workflows.run.pipeline import run_session
    from mocap.workflows.run.settings import RunSettings

    out = tmp_path_factory.mktemp("align_runs")
    full = RunSettings(bootstrap_samples=20, recording=False, jobs=1)
    base, offset, shifted = sessions
    return (run_session(base, out / "base", settings=full),
            run_session(offset, out / "offset", settings=full),
            run_session(shifted, out / "shifted",
                        settings=RunSettings(analyze=False, recording=False, jobs=1)))


def _commanded(session_dir: Path) -> list[str]:
    doc = tomllib.loads((session_dir / "session.toml").read_text())
    return [t["name"] for t in doc["takes"] if "commands" in t]


# --------------------------------------------------------------------------------------------
# The manifest field


def test_offset_is_read_validated_and_applied_once(sessions, tmp_path):
    base, offset, _ = sessions
    s0, s1 = load_session(base), load_session(offset)
    name = _commanded(base)[0]
    assert s1.take(name).commands_offset_s == -SHIFT_S and s0.take(name).commands_offset_s == 0.0
    raw = pd.read_csv(offset / "takes" / f"{name}_commands.csv")
    np.testing.assert_allclose(s1.read_command_log(name)["time_s"], raw["time_s"], rtol=0, atol=0)
    np.testing.assert_allclose(s1.read_commands(name)["time_s"],
                               pd.read_csv(base / "takes" / f"{name}_commands.csv")["time_s"],
                               atol=1e-12)
    n = s0.n_frames(name)
    assert (command_matrix(s1.read_commands(name), FPS, n, s1.du_ids)
            == command_matrix(s0.read_commands(name), FPS, n, s0.du_ids)).all()

    def broken(line: str, old: str = "commands_offset_s = -0.25") -> Path:
        d = tmp_path / f"s{len(list(tmp_path.iterdir()))}"
        shutil.copytree(offset, d)
        text = (d / "session.toml").read_text()
        (d / "session.toml").write_text(text.replace(old, line, 1))
        return d

    with pytest.raises(SessionError, match=r"commands_offset_s: expected a finite number"):
        load_session(broken('commands_offset_s = "0.25"'))
    with pytest.raises(SessionError, match="commands_offset_s: expected a finite number"):
        load_session(broken("commands_offset_s = nan"))
    # an offset on a take without a commands file says what to do
    d = broken("", "commands_offset_s = -0.25")
    text = (d / "session.toml").read_text()
    text = text.replace('kind = "rest"', 'kind = "rest"\ncommands_offset_s = 0.1', 1)
    (d / "session.toml").write_text(text)
    with pytest.raises(SessionError, match=r"'rest'.*commands_offset_s: the take has no "
                                           r"'commands' file"):
        load_session(d)


# --------------------------------------------------------------------------------------------
# Every stage honours it


def test_offset_restores_the_indices_and_without_it_the_audit_names_the_takes(runs, sessions):
    base, offset, shifted = runs
    a = pd.read_csv(base.out_dir / "properties.csv")
    b = pd.read_csv(offset.out_dir / "properties.csv")
    assert list(a.columns) == list(b.columns) and len(a) == len(b) > 0
    num = a.select_dtypes("number").columns
    np.testing.assert_allclose(b[num].to_numpy(float), a[num].to_numpy(float), rtol=1e-9,
                               atol=0, equal_nan=True)
    commanded = set(_commanded(sessions[0]))

    def flagged(res):
        return {f["item"] for f in res.audit["flagged"] if f["kind"] == "take"}

    assert flagged(shifted) == commanded
    assert flagged(base) == set() and flagged(offset) == set()
    why = [f["why"] for f in shifted.audit["flagged"] if f["kind"] == "take"][0]
    assert "misaligned" in why and "before its commands" in why and "commands_offset_s" in why
    lags = shifted.audit["command_alignment"]["lag_s"]
    assert all(abs(v + SHIFT_S) <= 1 / FPS for v in lags.values())


def test_offset_reaches_the_trials(runs):
    base, offset, shifted = runs
    assert len(base.trials.averages) == len(offset.trials.averages) == 2
    for a, b in zip(base.trials.averages, offset.trials.averages):
        assert a.du == b.du
        np.testing.assert_array_equal(a.command, b.command)
        np.testing.assert_allclose(b.mean, a.mean, rtol=0, atol=1e-12, equal_nan=True)
    # the motion (plan) take is evaluated on its aligned commands too
    assert [m.take for m in base.analysis.motions] == [m.take for m in offset.analysis.motions]


def test_offset_reaches_the_face_model_and_discrepancy_input(sessions):
    from mocap.workflows.discrepancy.inputs import load_measured

    base, offset, shifted = (load_measured(p) for p in sessions)
    for a, b, c in zip(base.takes, offset.takes, shifted.takes):
        assert a.name == b.name == c.name
        np.testing.assert_allclose(b.rows["time_s"], a.rows["time_s"], atol=1e-12)
        assert a.group == b.group  # trials of one schedule are grouped alike
        np.testing.assert_allclose(c.rows["time_s"], a.rows["time_s"] + SHIFT_S, atol=1e-12)


def test_offset_reaches_the_recording_timeline(runs, tmp_path, monkeypatch):
    pytest.importorskip("rerun")
    import mocap.outputs.recording as recording

    seen: dict[str, dict] = {}
    original = recording._series

    def spy(rec, rr, path, names, values, fps):
        if path.startswith("plots/commands/"):
            seen.setdefault(tag, {})[path] = np.asarray(values).copy()
        return original(rec, rr, path, names, values, fps)

    monkeypatch.setattr(recording, "_series", spy)
    for tag, res in zip(("base", "offset", "shifted"), runs):
        recording.write_recording(tmp_path / f"{tag}.rrd", res)
    assert seen["base"].keys() == seen["offset"].keys() and seen["base"]
    for path, v in seen["base"].items():
        np.testing.assert_array_equal(seen["offset"][path], v)
        assert not np.array_equal(seen["shifted"][path], v)  # without it the commands move


# --------------------------------------------------------------------------------------------
# mocap import --align-commands


def _write_c3d(path: Path, X: np.ndarray, names, fps: float, analogs: dict | None = None,
               analog_ratio: int = 10) -> Path:
    """A C3D written with ezc3d directly (not the project's writer)."""
    ezc3d = pytest.importorskip("ezc3d")
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [fps]
    c["parameters"]["POINT"]["LABELS"]["value"] = list(names)
    c.add_parameter("POINT", "UNITS", ["mm"])
    n, m, _ = X.shape
    pts = np.ones((4, m, n))
    pts[:3] = X.transpose(2, 1, 0)
    c["data"]["points"] = pts
    if analogs:
        labels = list(analogs)
        c["parameters"]["ANALOG"]["RATE"]["value"] = [fps * analog_ratio]
        c["parameters"]["ANALOG"]["LABELS"]["value"] = labels
        c["parameters"]["ANALOG"]["UNITS"]["value"] = ["V"] * len(labels)
        c["parameters"]["ANALOG"]["SCALE"]["value"] = [1.0] * len(labels)
        c["parameters"]["ANALOG"]["OFFSET"]["value"] = [0] * len(labels)
        c["parameters"]["ANALOG"]["GEN_SCALE"]["value"] = [1.0]
        c["data"]["analogs"] = np.stack([np.asarray(analogs[k], float) for k in labels])[None]
    c.write(str(path))
    return path


def _plan_take(base: Path):
    """The plan take of the simulated session: (X, marker names, its command file)."""
    from mocap.reconstruction.labeled_input import dense_from_3d, marker_names_3d

    s = load_session(base)
    name = next(t.name for t in s.takes if t.kind == "motion")
    df = s.read_take(name)
    names = marker_names_3d([df], s.marker_template)
    return name, dense_from_3d(df, names).X, list(names)


def _offsets(text: str) -> dict[str, tuple[float, float]]:
    return {m[0]: (float(m[1]), float(m[2]))
            for m in re.findall(r"^\s+(\S+): ([+-][0-9.]+) s \+- ([0-9.]+) s", text, re.MULTILINE)}


def test_align_commands_recovers_the_shift_from_the_motion_and_warns(sessions, tmp_path, capsys):
    from mocap.cli import main

    base, _, shifted = sessions
    name, X, names = _plan_take(base)
    c3d = _write_c3d(tmp_path / "smile.c3d", X, names, FPS)
    log = shifted / "takes" / f"{name}_commands.csv"
    out = tmp_path / "imported"
    assert main(["import", str(c3d), "--commands", str(log), "--fps", str(FPS), "--out", str(out),
                 "--align-commands"]) == 0
    text = capsys.readouterr().out
    (got, unc), = _offsets(text).values()
    assert abs(got + SHIFT_S) <= 1 / FPS and 0 < unc <= 0.05
    assert "dead time" in text and "cannot be separated" in text
    assert "not written" in text
    assert "commands_offset_s" not in (out / "session.toml").read_text()  # report only
    import json

    rep = json.loads((out / "import_report.json").read_text())["alignment"]
    assert rep["applied"] is False and rep["takes"]["smile"]["method"] == "motion"

    out2 = tmp_path / "applied"
    assert main(["import", str(c3d), "--commands", str(log), "--fps", str(FPS), "--out", str(out2),
                 "--align-commands", "apply"]) == 0
    written = load_session(out2).take("smile").commands_offset_s
    assert abs(written + SHIFT_S) <= 1 / FPS
    assert "written to session.toml" in capsys.readouterr().out


def test_align_session_reads_every_take_of_the_shifted_session(sessions):
    from mocap.interop.align import align_session

    rep = align_session(sessions[2])
    assert set(rep["takes"]) == set(_commanded(sessions[0]))
    for t in rep["takes"].values():
        assert abs(t["offset_s"] + SHIFT_S) <= 1 / FPS, t
        assert t["method"] == "motion"
    assert rep["disagree"] is False
    # an offset already in the manifest is the starting point: what is left is read as ~0
    rep = align_session(sessions[1])
    assert all(abs(t["offset_s"] + SHIFT_S) <= 1 / FPS for t in rep["takes"].values())


def test_takes_that_disagree_by_more_than_a_frame_are_flagged(sessions, tmp_path):
    from mocap.interop.align import align_session

    d = tmp_path / "mixed"
    shutil.copytree(sessions[0], d)
    name = next(t for t in _commanded(d) if "plan" in t)
    f = d / "takes" / f"{name}_commands.csv"
    rows = pd.read_csv(f)
    rows["time_s"] += 0.125  # not a whole number of its steps (0.05 s)
    rows.to_csv(f, index=False)
    rep = align_session(d)
    assert rep["disagree"] is True
    assert any("disagree" in w and name in w for w in rep["warnings"])


def test_sync_channel_gives_the_clock_offset(sessions, tmp_path, capsys):
    from mocap.cli import main

    base, _, shifted = sessions
    name, X, names = _plan_take(base)
    n = X.shape[0] * 10
    t = np.arange(n) / (FPS * 10)
    edge = 0.3
    sync = np.where(t >= edge, 5.0, 0.0)
    c3d = _write_c3d(tmp_path / "smile.c3d", X, names, FPS,
                     {"SYNC": sync, "EMG1": np.zeros(n)})
    log = shifted / "takes" / f"{name}_commands.csv"
    out = tmp_path / "synced"
    assert main(["import", str(c3d), "--commands", str(log), "--out", str(out),
                 "--align-commands", "apply", "--sync-channel", "sync"]) == 0
    text = capsys.readouterr().out
    (got, unc), = _offsets(text).values()
    # the edge lies between the samples at 0.3 - 1/1200 and 0.3 s: within a sample of 0.3
    assert abs(got - edge) <= 1 / (FPS * 10) and unc <= 1 / (FPS * 10)
    assert "sync channel" in text and "cannot be separated" not in text
    assert load_session(out).take("smile").commands_offset_s == pytest.approx(got, abs=1e-4)


def test_write_offsets_keeps_every_other_line(tmp_path):
    from mocap.interop.align import write_offsets

    text = ('# hand-written\nschema = "mocap-session/1"\nfps = 100.0\n\n[[takes]]\nname = "a"\n'
            'kind = "motion"\nfile = "a.csv"\ncommands = "a_c.csv"  # log\ncommands_offset_s = 9.0\n'
            '\n# next\n[[takes]]\nname = "b"\nkind = "rest"\nfile = "b.csv"\n')
    (tmp_path / "session.toml").write_text(text)
    write_offsets(tmp_path, {"a": -0.125})
    new = (tmp_path / "session.toml").read_text()
    doc = tomllib.loads(new)
    assert doc["takes"][0]["commands_offset_s"] == -0.125
    assert "commands_offset_s" not in doc["takes"][1]
    assert new.replace("commands_offset_s = -0.125", "commands_offset_s = 9.0") == text


def test_a_changed_offset_is_not_served_from_the_run_cache(sessions, tmp_path):
    """The offset is part of the stages' keys: editing it recomputes the trials and the audit,
    and reuses the reconstruction (the take files did not change)."""
    from mocap.workflows.run.pipeline import run_session
    from mocap.workflows.run.settings import RunSettings

    d = tmp_path / "s"
    shutil.copytree(sessions[1], d)
    settings = RunSettings(analyze=False, recording=False, jobs=1)
    first = run_session(d, tmp_path / "out", settings=settings)
    assert not [f for f in first.audit["flagged"] if f["kind"] == "take"]
    text = (d / "session.toml").read_text()
    (d / "session.toml").write_text(text.replace("commands_offset_s = -0.25",
                                                 "commands_offset_s = 0.0"))
    again = run_session(d, tmp_path / "out", settings=settings)
    assert "trials" in again.computed and "audit" in again.computed
    assert any(r.startswith("reconstruct") for r in again.reused)
    assert {f["item"] for f in again.audit["flagged"] if f["kind"] == "take"} \
        == set(_commanded(sessions[0]))


def test_trapezoids_alone_keep_the_manifest_lag_in_the_audit(sessions):
    """Response takes alone (uniform staircases) fit a delay of whole steps almost as well: the
    audit reads them near what the manifest says (0), so an aligned session of trapezoids is
    not flagged; a take that pins its lag (the plan take) is read as it is."""
    from mocap.reconstruction.align import motion_lags
    from mocap.reconstruction.labeled_input import dense_from_3d, marker_names_3d

    def takes(path, kinds):
        s = load_session(path)
        out = {}
        for t in s.takes:
            if t.kind in kinds and t.commands is not None:
                df = s.read_take(t.name)
                out[t.name] = (dense_from_3d(df, marker_names_3d([df], s.marker_template)).X,
                               s.read_commands(t.name))
        return out

    response = takes(sessions[0], ("response",))
    lags = motion_lags(response, FPS, max_lag_s=0.6, centre_s=0.0, refine=False, prior_s=0.0)
    assert all(abs(e.lag_s) <= 1 / FPS for e in lags.takes.values())
    assert all("no take of the session pins its lag" in e.note for e in lags.takes.values())
    plan = takes(sessions[2], ("motion",))
    lags = motion_lags(plan, FPS, max_lag_s=0.6, centre_s=0.0, refine=False, prior_s=0.0)
    (e,) = lags.takes.values()
    assert abs(e.lag_s + SHIFT_S) <= 1 / FPS and e.note == ""


def test_an_offset_read_from_the_motion_absorbs_a_dead_time(tmp_path):
    """On a face with a 0.06 s dead time and aligned logs, the motion reads a 0.06 s offset:
    what the report warns about (the clock offset and the dead time cannot be told apart)."""
    from mocap.interop.align import DEAD_TIME_WARNING, align_session
    from mocap.simulate import simulate
    from mocap.simulate.config import preset
    from mocap.simulate.effects import HiddenEffect

    delay = 0.06
    cfg = preset("small", seed=5, du_ids=(4, 7), n_markers=20, n_trials=2, battery=False,
                 motion_plans=("A",), motion_dus=(4, 7), labeled=True, ground=False,
                 effect=HiddenEffect("deadtime", delay))
    simulate(cfg, tmp_path)
    rep = align_session(tmp_path / "session")
    assert rep["takes"] and all(abs(t["offset_s"] - delay) <= 1 / FPS
                                for t in rep["takes"].values())
    assert DEAD_TIME_WARNING in rep["warnings"]
