"""Everyday use (issue #49, item 4): outputs readable as the user's umask says, the API from a
script without a main guard, from ``python -c`` and from a notebook, results that print on one
screen, errors worded for where they are raised."""

from __future__ import annotations

import ast
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

    from mocap import atomic

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
    from mocap import atomic

    with pytest.raises(ZeroDivisionError), atomic.atomic_path(tmp_path / "x.txt") as tmp:
        tmp.write_text("half")
        1 / 0
    assert list(tmp_path.iterdir()) == []


def test_no_module_makes_private_temporary_files():
    """Every output goes through mocap.atomic: no other module creates files with
    ``tempfile.mkstemp`` / ``NamedTemporaryFile`` (mode 0600, kept by the rename)."""
    offenders = []
    for folder in (ROOT / "mocap", ROOT / "calib", ROOT / "analysis"):
        for f in folder.rglob("*.py"):
            if f == ROOT / "mocap" / "atomic.py":
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
import mocap.pipeline, mocap.run_outputs
mocap.pipeline.PARALLEL_MIN_BYTES = 0
mocap.run_outputs.PARALLEL_MIN_FIGURES = 1
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
    proc = subprocess.run([sys.executable, "-m", "pytest", "-p", "no:xdist", "-p", "no:cacheprovider",
                           "-q", "tests/test_import_errors.py", "-k", "crashing_c3d_reader"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    output = proc.stdout + proc.stderr
    assert proc.returncode == 0 and "1 passed" in output, output[-3000:]
    assert "Fatal Python error" not in output and "Extension modules" not in output, output[-3000:]
