"""Everyday use (issue #49, item 4): outputs readable as the user's umask says, the API from a
script without a main guard, from ``python -c`` and from a notebook, results that print on one
screen, errors worded for where they are raised."""

from __future__ import annotations

import contextlib
import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from mocap.cli import main

ROOT = Path(__file__).resolve().parents[1]


@contextlib.contextmanager
def umask(mask: int):
    old = os.umask(mask)
    try:
        yield
    finally:
        os.umask(old)


def modes(folder: Path) -> dict[str, int]:
    """Every file and folder under ``folder`` (itself included) -> its permission bits."""
    out = {".": stat.S_IMODE(folder.stat().st_mode)}
    for p in sorted(folder.rglob("*")):
        out[str(p.relative_to(folder))] = stat.S_IMODE(p.stat().st_mode)
    return out


def wrong_modes(folder: Path, mask: int) -> dict[str, str]:
    """The entries whose mode is not 0666 (files) or 0777 (folders) less ``mask``."""
    bad = {}
    for name, mode in modes(folder).items():
        want = (0o777 if (folder / name).is_dir() else 0o666) & ~mask
        if mode != want:
            bad[name] = f"{mode:o} (expected {want:o})"
    return bad


@pytest.mark.parametrize("mask", [0o022, 0o027])
def test_atomic_writes_follow_the_umask(tmp_path, mask):
    import pandas as pd

    from mocap.core import atomic

    df = pd.DataFrame({"a": [1, 2], "b": [0.5, float("nan")]})
    with umask(mask):
        atomic.write_text(tmp_path / "new" / "a.txt", "x")
        atomic.write_csv(df, tmp_path / "new" / "deeper" / "b.csv")
        atomic.write_parquet(df, tmp_path / "new" / "c.parquet")
        with atomic.atomic_path(tmp_path / "new" / "d.bin") as tmp:
            tmp.write_bytes(b"\0")
        # an existing file rewritten takes the umask's mode too (a new inode replaces it)
        atomic.write_text(tmp_path / "new" / "a.txt", "y")
    assert sorted(modes(tmp_path / "new")) == [".", "a.txt", "c.parquet", "d.bin", "deeper",
                                               "deeper/b.csv"]
    assert wrong_modes(tmp_path / "new", mask) == {}


def test_a_failed_atomic_write_leaves_no_temporary_file(tmp_path):
    from mocap.core import atomic

    with pytest.raises(RuntimeError), atomic.atomic_path(tmp_path / "x.txt") as tmp:
        tmp.write_text("half")
        raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []


def test_no_module_makes_private_temporary_files():
    """Every output goes through mocap.core.atomic: no other module creates files with
    ``tempfile.mkstemp`` / ``NamedTemporaryFile`` (mode 0600, kept by the rename)."""
    offenders = []
    for folder in (ROOT / "mocap", ROOT / "calib", ROOT / "analysis"):
        for f in folder.rglob("*.py"):
            if f == ROOT / "mocap" / "core" / "atomic.py":
                continue
            text = f.read_text(encoding="utf-8")
            if "mkstemp" in text or "NamedTemporaryFile" in text:
                offenders.append(str(f.relative_to(ROOT)))
    assert offenders == []


@pytest.mark.parametrize("mask", [0o022, 0o027])
def test_every_command_writes_files_the_umask_allows(tiny_sim, tmp_path, mask, capsys):
    """`mocap run` (recording and figures included), `audit`, `calibrate`, `export`, `import`,
    `design` and `simulate` under umask 022 and 027: every file 0644 / 0640, every folder
    0755 / 0750."""
    session = str(tiny_sim / "session")
    out = tmp_path / "outputs"
    with umask(mask):
        assert main(["run", session, "--out", str(out / "run"), "--jobs", "1", "--quiet"]) == 0
        assert main(["audit", session, "--out", str(out / "audit")]) in (0, 1)
        assert main(["calibrate", session, "--out", str(out / "cal" / "calibration.toml")]) == 0
        assert main(["export", str(out / "run"), "--c3d", str(out / "c3d")]) == 0
        assert main(["import", *map(str, sorted((out / "c3d").glob("*.c3d"))),
                     "--out", str(out / "imported")]) == 0
        assert main(["design", str(out / "run"), "--plan", "A", "--dus", "4",
                     "--out", str(out / "design" / "commands.csv")]) == 0
        assert main(["simulate", str(out / "sim"), "--preset", "small", "--seed", "3",
                     "--labeled"]) == 0
    capsys.readouterr()
    for must in ("run/properties.csv", "run/session.rrd", "run/summary.json", "audit/audit.json",
                 "cal/calibration.toml", "imported/session.toml", "design/commands.csv",
                 "sim/session/session.toml"):
        assert (out / must).is_file(), must
    assert any((out / "run" / "figures").glob("*.png"))
    assert wrong_modes(out, mask) == {}


# Worker processes forced for a small session (they start only from 64 MB of takes and 16
# figures) and two of them whatever the machine's cores: the code a user writes after it.
FORCE_WORKERS = """\
import os
os.cpu_count = lambda: 2
import mocap.workflows.run.stages, mocap.outputs.run_writers
mocap.workflows.run.stages.PARALLEL_MIN_BYTES = 0
mocap.outputs.run_writers.PARALLEL_MIN_FIGURES = 1
"""

USER_CODE = """\
import sys
import mocap

session = mocap.load_session(sys.argv[1])
result = mocap.run(session, out_dir=sys.argv[2], recording=False)
print(result.properties.to_json())
"""


@pytest.mark.parametrize("how", ["script", "-c"])
def test_worker_processes_do_not_rerun_a_script_without_main_guard(tiny_sim, tmp_path, how):
    """A plain script (no ``if __name__ == "__main__":``) and ``python -c`` whose run uses
    worker processes for its takes and figures: the workers do not re-run the user's code
    (spawned processes did: RuntimeError in each worker, then BrokenProcessPool)."""
    import pandas as pd

    code = FORCE_WORKERS + USER_CODE
    out = tmp_path / "out"
    if how == "script":
        (tmp_path / "analyse.py").write_text(code, encoding="utf-8")
        cmd = [sys.executable, str(tmp_path / "analyse.py")]
    else:
        cmd = [sys.executable, "-c", code]
    proc = subprocess.run([*cmd, str(tiny_sim / "session"), str(out)], cwd=tmp_path,
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "bootstrapping" not in proc.stderr and "Traceback" not in proc.stderr
    got = pd.read_json(__import__("io").StringIO(proc.stdout.strip().splitlines()[-1]))
    written = pd.read_csv(out / "properties.csv")
    assert list(got["du"]) == list(written["du"]) == [4, 7]
    assert len(list((out / "figures").glob("*.png"))) >= 4


def test_the_crashing_reader_test_prints_no_fatal_error_dump():
    """The test that crashes the C3D reader's child on purpose passes without the child's
    "Fatal Python error: Segmentation fault" and module list in the output (pytest enables
    faulthandler, which the forked child inherited)."""
    # without the options the suite passes its xdist workers (PYTEST_ADDOPTS: --dist)
    env = {k: v for k, v in os.environ.items() if k != "PYTEST_ADDOPTS"}
    proc = subprocess.run([sys.executable, "-m", "pytest", "-p", "no:xdist", "-p", "no:cacheprovider",
                           "-q", "tests/test_import_errors.py", "-k", "crashing_c3d_reader"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300, env=env)
    output = proc.stdout + proc.stderr
    assert proc.returncode == 0 and "1 passed" in output, output[-3000:]
    assert "Fatal Python error" not in output and "Extension modules" not in output, output[-3000:]


@pytest.fixture(scope="module")
def tiny_result(tiny_sim):
    import mocap

    return mocap.run(mocap.load_session(tiny_sim / "session"), bootstrap_samples=0, jobs=1)


def test_results_print_on_one_screen(tiny_result):
    """Every public result type's repr is a short summary (the field-by-field dataclass repr
    of a 4-DU run was 486,000 characters) and a notebook gets an HTML table."""
    r = tiny_result
    shown = {"RunResult": r, "Session": r.session, "CalibrationResult": r.calibration,
             "CameraRig": r.calibration.rig, "Reconstruction": r.reconstruction,
             "LabeledTake": r.reconstruction.takes["rest"], "Trials": r.trials,
             "TrialAverage": r.trials.averages[0], "Analysis": r.analysis,
             "MotionEvaluation": r.analysis.motions[0].evaluation}
    for name, obj in shown.items():
        assert type(obj).__name__ == name
        text = repr(obj)
        assert len(text) < 2000 and len(text.splitlines()) <= 40, (name, len(text))
        assert text.startswith(name), text[:80]
        assert "array(" not in text and "DataFrame" not in text, name
        html = obj._repr_html_()
        assert html.startswith("<p><b>") and len(html) < 20000, name
    text = repr(r)
    assert f"{r.session.name!r}: 2D, 120 fps" in text
    for du in (4, 7):  # the properties' rows, one per DU
        assert any(line.split()[:1] == [str(du)] for line in text.splitlines()), text
    assert "properties" in text and ".trajectories" in text


def test_analyze_returns_the_type_a_run_holds(tiny_sim, tiny_result):
    """One Analysis type: mocap.analyze() gives what RunResult.analysis holds, with the same
    properties and the trials' rejections."""
    import numpy as np

    import mocap
    from mocap.analysis.session_analysis import Analysis

    r = tiny_result
    a = mocap.analyze(r.session, r.reconstruction, bootstrap_samples=0)
    assert type(a) is type(r.analysis) and type(a).__name__ == "Analysis"
    assert Analysis is type(a)
    np.testing.assert_array_equal(a.properties["sensitivity"].to_numpy(float),
                                  r.analysis.properties["sensitivity"].to_numpy(float))
    assert a.rejections.equals(r.rejections) and r.analysis.rejections.equals(r.rejections)
    assert [m.take for m in a.motions] == [m.take for m in r.analysis.motions]


def test_a_paper_sized_result_prints_on_one_screen(tiny_result):
    """16 DUs with the paper's long names (the paper preset's table), in an Analysis and in a
    RunResult holding it: under 2000 characters each."""
    import dataclasses

    import numpy as np
    import pandas as pd

    from mocap.analysis.session_analysis import Analysis
    from mocap.simulate.dus import DU_TABLE

    rng = np.random.default_rng(0)
    dus = list(DU_TABLE)[:16]
    props = pd.DataFrame({"du": [d.id for d in dus], "name": [d.name for d in dus],
                          **{c: rng.random(16) for c in ("alpha_fwd", "beta_fwd", "sensitivity",
                                                          "hysteresis", "dyssynchrony",
                                                          "linearity_mean")},
                          "n_markers": rng.integers(10, 116, 16)})
    a = Analysis(props, pd.DataFrame(), pd.DataFrame(), {}, {}, {}, {},
                 motions=tiny_result.analysis.motions * 5, trials=tiny_result.trials)
    r = dataclasses.replace(tiny_result, analysis=a)
    for obj in (a, r):
        text = repr(obj)
        assert len(text) < 2000, (type(obj).__name__, len(text))
        shown = [line.split()[0] for line in text.splitlines() if line[:4].strip().isdigit()]
        assert shown == [str(d.id) for d in dus], text  # every DU's row


# --- errors worded for where they are raised ----------------------------------------------------


def test_an_out_that_is_a_file_is_refused_before_anything_runs(tiny_sim, tmp_path, capsys):
    """`--out` naming an existing file: one line that says so, not "[Errno 17] File exists"
    followed by "what was finished is kept ... resumes from it"."""
    session = str(tiny_sim / "session")
    a_file = tmp_path / "notes.txt"
    a_file.write_text("mine\n")
    for argv in (["run", session, "--out", str(a_file), "--jobs", "1"],
                 ["audit", session, "--out", str(a_file)],
                 ["calibrate", session, "--out", str(a_file / "calibration.toml")],
                 ["calibrate", session, "--out", str(tmp_path)]):
        assert main(argv) == 1, argv
        err = capsys.readouterr().err
        assert err.startswith(f"error: --out {argv[-1] if argv[0] != 'run' else a_file}:"), err
        assert "Errno" not in err and "resumes" not in err and "Traceback" not in err, err
        assert len(err.strip().splitlines()) == 1, err
    assert a_file.read_text() == "mine\n"


def test_python_errors_name_the_python_argument(tiny_sim, tmp_path):
    """An output folder refused in mocap.run names ``out_dir`` (the argument the caller
    wrote), never the command line's ``--out``."""
    import mocap
    from mocap.core.paths import OutputPathError

    session = mocap.load_session(tiny_sim / "session")
    a_file = tmp_path / "notes.txt"
    a_file.write_text("")
    for out_dir, why in ((tiny_sim / "session" / "results", "inside the session folder"),
                         (a_file, "is a file, not a folder")):
        with pytest.raises(OutputPathError) as err:
            mocap.run(session, out_dir=out_dir)
        assert str(err.value).startswith(f"out_dir {out_dir}: ") and why in str(err.value)
        assert "--out" not in str(err.value)
    assert not (tiny_sim / "session" / "results").exists()


def test_dir_of_mocap_lists_the_api_not_its_helpers():
    code = "import mocap; print(' '.join(dir(mocap)))"
    names = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           check=True).stdout.split()
    assert {"load_session", "calibrate", "reconstruct", "analyze", "run", "RunSettings",
            "__version__"} <= set(names)
    assert "sys" not in names and not [n for n in names if n.startswith("_") and n != "__version__"]


def test_no_package_text_cites_a_file_users_do_not_have():
    """Help, messages and comments point at the project's docs/ pages, not at the contracts'
    file names (METHOD.md, FORMAT.md, OUTPUTS.md) that only the developers have."""
    import argparse

    from mocap.cli import COMMANDS, _module

    cited = []
    for folder in (ROOT / "mocap", ROOT / "calib", ROOT / "analysis"):
        for f in folder.rglob("*.py"):
            text = f.read_text(encoding="utf-8")
            cited += [f"{f.relative_to(ROOT)}: {name}" for name in
                      ("METHOD.md", "FORMAT.md", "OUTPUTS.md") if name in text]
    assert cited == []
    for name in COMMANDS:
        parser = argparse.ArgumentParser()
        _module(name).add_arguments(parser)
        for cited in ("METHOD.md", "FORMAT.md", "OUTPUTS.md"):
            assert cited not in parser.format_help(), (name, cited)
