"""Outputs never go into a raw session (mocap.core.paths) and manifest paths stay inside it
(mocap.core.session): issue #19.

Every writing command is driven through the CLI with an output path that is the session folder,
lies inside it, contains it, or reaches it through a symbolic link; each must refuse with a
message naming the option, and leave the session folder byte for byte as it was.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import pytest
import session_builders as sb

from mocap.cli import main
from mocap.core.paths import OutputPathError, check_output_path, session_dir_of
from mocap.core.session import SessionError, load_session


def _fingerprint(root: Path) -> dict[str, str]:
    """Every file under ``root`` (relative path -> sha1 of its bytes)."""
    return {p.relative_to(root).as_posix(): hashlib.sha1(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture
def session(tmp_path) -> Path:
    return sb.session_3d("csv").write(tmp_path / "lab" / "session")


# --------------------------------------------------------------------------------------------
# The check itself


def test_outputs_beside_the_session_are_accepted(session):
    out = session.parent / "results"
    assert check_output_path(out, sessions=[session]) == out.resolve()
    assert check_output_path(session.parent / "commands.csv", sessions=[session])


@pytest.mark.parametrize("where, why", [
    (lambda s: s, "is the session folder"),
    (lambda s: s / "results", "is inside the session folder"),
    (lambda s: s / "takes" / "new" / "deep", "is inside the session folder"),
    (lambda s: s / "takes" / "x.csv", "is inside the session folder"),
    (lambda s: s.parent, "contains the session folder"),
    (lambda s: s.parent.parent, "contains the session folder"),
    (lambda s: s / ".." / "session" / "out", "is inside the session folder"),
])
def test_outputs_in_on_or_around_the_session_are_refused(session, where, why):
    with pytest.raises(OutputPathError, match=f"--out .*: {why}"):
        check_output_path(where(session), sessions=[session])


def test_a_link_does_not_smuggle_an_output_into_the_session(session, tmp_path):
    link = tmp_path / "innocent"
    link.symlink_to(session / "takes", target_is_directory=True)
    with pytest.raises(OutputPathError, match="is inside the session folder"):
        check_output_path(link / "out", sessions=[session])


def test_any_folder_holding_a_manifest_is_a_session(session):
    # the command reads no session (simulate, schedule) or another one: still refused
    with pytest.raises(OutputPathError, match=r"is inside the session folder .* session\.toml"):
        check_output_path(session / "sim", option="OUT_DIR")
    with pytest.raises(OutputPathError, match="OUT_DIR .*: is the session folder"):
        check_output_path(session, option="OUT_DIR")


def test_an_output_holding_an_input_file_is_refused(tmp_path):
    f = tmp_path / "data" / "trial.c3d"
    f.parent.mkdir()
    f.write_bytes(b"x")
    with pytest.raises(OutputPathError, match="contains the input file"):
        check_output_path(tmp_path / "data", inputs=[f])
    with pytest.raises(OutputPathError, match="is the input file"):
        check_output_path(f, inputs=[f])
    assert check_output_path(tmp_path / "data" / "session", inputs=[f])


def test_session_dir_of_a_run_output_is_the_recorded_session(session, tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "summary.json").write_text('{"session": {"dir": "%s"}}' % session.as_posix())
    assert session_dir_of(out) == session
    assert session_dir_of(session) == session
    assert session_dir_of(tmp_path) is None
    (out / "summary.json").write_text("{not json")
    assert session_dir_of(out) is None


# --------------------------------------------------------------------------------------------
# Every writing command refuses, and the session is left untouched


def _commands(session: Path, target: Path, tmp_path: Path) -> dict[str, list[str]]:
    c3d = tmp_path / "in" / "trial.csv"
    return {
        "run": ["run", str(session), "--out", str(target), "--no-rrd"],
        "audit": ["audit", str(session), "--out", str(target)],
        "calibrate": ["calibrate", str(session), "--out", str(target / "calibration.toml")],
        "discrepancy": ["discrepancy", str(session), "--out", str(target), "--quiet"],
        "design": ["design", str(session), "--plan", "A", "--dus", "4",
                   "--out", str(target / "commands.csv")],
        "export": ["export", str(session), "--c3d", str(target)],
        "simulate": ["simulate", str(target), "--preset", "small", "--force"],
        "schedule": ["schedule", "--dus", "4", "--out", str(target)],
        "batch": ["batch", str(session), "--out", str(target)],
        "import": ["import", str(c3d), "--out", str(target)],
    }


FOLDER_OUTPUTS = ["run", "audit", "discrepancy", "export", "simulate", "batch"]
# a file beside the session is fine, and schedule reads no session: no "parent" case for them
NO_PARENT = ["calibrate", "design", "schedule"]


@pytest.mark.parametrize("command, place", [(c, p) for c in FOLDER_OUTPUTS + NO_PARENT
                                            for p in ("session", "inside", "parent")
                                            if not (c in NO_PARENT and p == "parent")])
def test_every_writing_command_refuses_the_session(command, place, session, tmp_path, capsys):
    target = {"session": session, "inside": session / "results", "parent": session.parent}[place]
    before = _fingerprint(session.parent)
    argv = _commands(session, target, tmp_path)[command]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "error:" in err and "raw session" in err, err
    assert _fingerprint(session.parent) == before


def test_import_refuses_a_folder_holding_its_inputs(tmp_path, capsys):
    src = tmp_path / "in"
    src.mkdir()
    f = src / "trial.csv"
    f.write_text("Trajectories\n100\n")
    before = _fingerprint(src)
    assert main(["import", str(f), "--out", str(src)]) == 1
    assert "contains the input file" in capsys.readouterr().err
    assert _fingerprint(src) == before


def test_the_library_run_refuses_too(session):
    from mocap.workflows.run.pipeline import run_session

    before = _fingerprint(session.parent)
    with pytest.raises(SessionError, match="inside the session folder"):
        run_session(session, session / "out")
    assert _fingerprint(session.parent) == before


# --------------------------------------------------------------------------------------------
# Manifest paths: relative, and inside the session once links are resolved (FORMAT.md)


def _with_take_file(tmp_path, value: str, key: str = "file") -> Path:
    spec = sb.session_3d("csv")
    take = spec.manifest["takes"][0]
    take[key] = value
    return spec.write(tmp_path / "s")


@pytest.mark.parametrize("value, why", [
    ("../outside.csv", "leaves the session folder"),
    ("takes/../../outside.csv", "leaves the session folder"),
    ("/etc/passwd.csv", "is an absolute path"),
    (r"C:\data\take.csv", "is an absolute path"),
    (r"\\server\share\take.csv", "is an absolute path"),
])
def test_manifest_paths_outside_the_session_are_refused(tmp_path, value, why):
    (tmp_path / "outside.csv").write_text("frame,marker,x,y,z\n0,M001,1,2,3\n")
    root = _with_take_file(tmp_path, value)
    with pytest.raises(SessionError, match=rf"session\.toml: takes\[0\] \('\w+'\)\.file: .*{why}"):
        load_session(root)


def test_a_link_out_of_the_session_is_refused(tmp_path):
    outside = tmp_path / "elsewhere.csv"
    outside.write_text("frame,marker,x,y,z\n0,M001,1,2,3\n")
    root = _with_take_file(tmp_path, "takes/linked.csv")
    os.symlink(outside, root / "takes" / "linked.csv")
    with pytest.raises(SessionError, match=r'takes\[0\] .*\.file: "takes/linked\.csv" leaves the '
                                           r"session folder \(it resolves to .*elsewhere\.csv\)"):
        load_session(root)


def test_a_commands_path_outside_is_refused_naming_its_key(tmp_path):
    spec = sb.session_3d("csv")
    take = next(t for t in spec.manifest["takes"] if "commands" in t)
    take["commands"] = "../c.csv"
    root = spec.write(tmp_path / "s")
    with pytest.raises(SessionError, match=r'\.commands: "\.\./c\.csv" leaves the session folder'):
        load_session(root)


def test_a_link_inside_the_session_and_a_detour_through_dotdot_are_fine(tmp_path):
    spec = sb.session_3d("csv")
    first = spec.manifest["takes"][0]
    real = first["file"]
    first["file"] = "takes/../" + real
    root = spec.write(tmp_path / "s")
    assert load_session(root).takes[0].file.resolve() == (root / real).resolve()
    os.symlink(root / real, root / "alias.csv")
    first["file"] = "alias.csv"
    (root / "session.toml").write_text(sb.toml_dumps(spec.manifest))
    assert load_session(root).read_take(first["name"]).shape[0] > 0


def test_a_marker_template_linked_from_outside_is_refused(tmp_path):
    spec = sb.session_3d("csv")
    spec.markers = None
    root = spec.write(tmp_path / "s")
    outside = tmp_path / "template.csv"
    sb.marker_template().to_csv(outside, index=False)
    os.symlink(outside, root / "markers.csv")
    with pytest.raises(SessionError, match="markers.csv.*leaves the session folder"):
        load_session(root)


def test_simulate_replaces_only_a_simulated_session(tmp_path):
    from mocap.cli.commands.simulate import simulated

    real = sb.session_3d("csv")
    real.manifest["name"] = "robot-face-day1"
    real.write(tmp_path / "lab" / "session")
    assert not simulated(tmp_path / "lab")
    virtual = sb.session_3d("csv")
    virtual.manifest["name"] = "virtual-face-sample-seed1"  # as the committed sample_data
    virtual.write(tmp_path / "sample" / "session")
    assert simulated(tmp_path / "sample")
    (tmp_path / "lab" / "truth").mkdir()
    (tmp_path / "lab" / "truth" / "truth.json").write_text("{}")
    assert simulated(tmp_path / "lab")
