"""One import namespace: `mocap`, with `mocap.calib` and `mocap.analysis` mapped from the
repository's top-level calib/ and analysis/ folders. Checked from a folder outside the repository,
where the working directory cannot put the repository's folders on the import path."""
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(code: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True,
                          timeout=120)


def test_generic_top_level_names_are_not_installed(tmp_path):
    for name in ("calib", "analysis"):
        r = _run(f"import {name}", tmp_path)
        assert r.returncode != 0 and "ModuleNotFoundError" in r.stderr, (name, r.stderr)


def test_subpackages_import_under_mocap(tmp_path):
    r = _run("import mocap.calib.camera as c, mocap.analysis.model.face_model as f; "
             "print(c.__file__); print(f.__file__)", tmp_path)
    assert r.returncode == 0, r.stderr
    cam, face = r.stdout.split()
    assert Path(cam).parent.name == "calib" and Path(face).parent.parent.name == "analysis"


def test_every_package_folder_is_installed():
    """pyproject.toml lists the packages explicitly (package-dir maps two of them): a new
    subpackage missing from the list would be absent from a wheel."""
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    dirs = cfg["package-dir"]
    listed = set(cfg["packages"])
    found = set()
    for top, folder in (("mocap", "mocap"), ("mocap.calib", "calib"), ("mocap.analysis", "analysis")):
        assert dirs[top] == folder
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder).parts
            found.add(".".join((top, *rel)))
    # calib/ and analysis/ are reached through mocap.calib / mocap.analysis, not as mocap/calib
    assert found == listed, (found - listed, listed - found)
