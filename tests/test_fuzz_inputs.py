"""Property-based tests: corrupted inputs get clear errors, never a traceback (issue #19).

Every importer (C3D, Motive CSV, QTM TSV, Vicon CSV) on damaged copies of real vendor files
(``../shared/realdata``, read in place; those seeds skip where it is absent) and of files made
here, and the session loader on damaged copies of small valid sessions. Bounded here (100
examples per property, 40 for the two large real C3D files: a few seconds each; the same examples
on every run); ``benchmarks/fuzz_inputs.py`` runs thousands of random ones.
The properties and the damages are in ``fuzz_inputs.py``.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import session_builders as sb
from fuzz_inputs import (
    REAL_IMPORTS,
    REALDATA,
    check_import,
    check_session,
    damaged,
    generated_imports,
    mutate_manifest,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

_HEALTH = [HealthCheck.function_scoped_fixture, HealthCheck.too_slow, HealthCheck.data_too_large]
# (the same examples on every run unless MOCAP_FUZZ_RANDOM=1: the profile set in conftest.py)
BOUNDED = settings(max_examples=100, deadline=None, database=None, suppress_health_check=_HEALTH)
# the two real C3D files with analog data take about 0.1 s per example on a quiet machine
BOUNDED_HEAVY = settings(max_examples=40, deadline=None, database=None,
                         suppress_health_check=_HEALTH)
HEAVY = ("vicon_nexus24_markers_emg.c3d", "qualisys_qtm217_forceplates.c3d")

GENERATED = ("motive.csv", "qtm.tsv", "vicon.csv", "ours.c3d")


@pytest.fixture
def short_c3d_time_limit(monkeypatch):
    """Some damaged C3D files make ezc3d hang (one cut inside its parameter section loops for
    ever): the importer's child process turns that into a clear error at its time limit, 60 s
    (+ 2 s per MB) for real files on slow disks. These seeds are at most 2.3 MB and read in well
    under a second; a 10 s limit takes the same path (the timeout, the ImportError_ naming the
    file) without a minute's wait each time Hypothesis draws such a cut."""
    from mocap.interop import c3d_file

    monkeypatch.setattr(c3d_file, "CHILD_SECONDS", (10.0, 2.0))


@pytest.fixture(scope="module")
def seeds(tmp_path_factory) -> dict[str, Path]:
    return generated_imports(tmp_path_factory.mktemp("seeds"))


def _fuzz_import(src: bytes, name: str, folder: Path, data) -> None:
    what, bad = data.draw(damaged(src), label="damage")
    path = folder / name
    path.write_bytes(bad)
    check_import(path, folder / "session")


@pytest.mark.usefixtures("short_c3d_time_limit")
@pytest.mark.parametrize("name", GENERATED)
@BOUNDED
@given(data=st.data())
def test_a_damaged_generated_file_imports_or_gets_a_clear_error(name, seeds, tmp_path_factory, data):
    folder = tmp_path_factory.mktemp("fuzz")
    _fuzz_import(seeds[name].read_bytes(), name, folder, data)


@pytest.mark.usefixtures("short_c3d_time_limit")
@pytest.mark.skipif(not REALDATA.is_dir(), reason="../shared/realdata is absent")
@pytest.mark.parametrize("name", [n for n in REAL_IMPORTS if n not in HEAVY])
@BOUNDED
@given(data=st.data())
def test_a_damaged_real_file_imports_or_gets_a_clear_error(name, tmp_path_factory, data):
    folder = tmp_path_factory.mktemp("fuzz")
    _fuzz_import((REALDATA / name).read_bytes(), name, folder, data)


@pytest.mark.usefixtures("short_c3d_time_limit")
@pytest.mark.skipif(not REALDATA.is_dir(), reason="../shared/realdata is absent")
@pytest.mark.parametrize("name", HEAVY)
@BOUNDED_HEAVY
@given(data=st.data())
def test_a_damaged_real_c3d_with_analogs_imports_or_gets_a_clear_error(name, tmp_path_factory,
                                                                       data):
    folder = tmp_path_factory.mktemp("fuzz")
    _fuzz_import((REALDATA / name).read_bytes(), name, folder, data)


def test_the_seeds_themselves_import(seeds, tmp_path):
    # the property is not vacuous: undamaged, every seed imports and its session loads
    for name, path in seeds.items():
        assert check_import(path, tmp_path / name) == "ok"
    if REALDATA.is_dir():
        for name in REAL_IMPORTS:
            assert check_import(REALDATA / name, tmp_path / f"real_{name}") == "ok"


SESSIONS = {"2d_csv": lambda: sb.session_2d("csv"), "2d_mixed": lambda: sb.session_2d("mixed"),
            "3d_csv": lambda: sb.session_3d("csv")}


@pytest.mark.parametrize("kind", sorted(SESSIONS))
@BOUNDED
@given(data=st.data())
def test_a_damaged_session_loads_or_gets_a_clear_error(kind, tmp_path_factory, data):
    root = SESSIONS[kind]().write(tmp_path_factory.mktemp("session") / "s")
    files = sorted(p for p in root.rglob("*") if p.is_file())
    target = data.draw(st.sampled_from(files), label="file")
    what, bad = data.draw(damaged(target.read_bytes()), label="damage")
    target.write_bytes(bad)
    check_session(root)


@pytest.mark.parametrize("kind", sorted(SESSIONS))
def test_the_undamaged_sessions_load(kind, tmp_path):
    assert check_session(SESSIONS[kind]().write(tmp_path / "s"), must_load=True) == "ok"



@pytest.mark.parametrize("kind", sorted(SESSIONS))
@BOUNDED
@given(data=st.data())
def test_a_manifest_value_of_any_type_gets_a_clear_error(kind, tmp_path_factory, data):
    spec = SESSIONS[kind]()
    if mutate_manifest(data.draw, spec.manifest):
        root = tmp_path_factory.mktemp("manifest") / "s"
        spec.write(root)
        check_session(root)
