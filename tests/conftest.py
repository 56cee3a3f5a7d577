"""Shared fixtures: small simulated sessions with known truth (made once per test run)."""

from __future__ import annotations

import os

# before numpy is imported: one BLAS thread, as the command line runs (mocap.cli.single_threaded_blas)
for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import json  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from mocap.simulate import preset, simulate  # noqa: E402

TESTS = Path(__file__).resolve().parent

# Property-based tests draw the same examples on every run (hypothesis derandomize), so that the
# suite's verdict depends on the code only: a damage or an input found by chance would otherwise
# fail whichever change happened to be tested. The search for new ones is benchmarks/
# fuzz_inputs.py (thousands of random examples per target); MOCAP_FUZZ_RANDOM=1 draws fresh
# examples in the suite too.
try:
    from hypothesis import settings as _hypothesis_settings
except ImportError:  # the dev extra is not installed: the property-based tests cannot run anyway
    _hypothesis_settings = None
if _hypothesis_settings is not None and os.environ.get("MOCAP_FUZZ_RANDOM", "") in ("", "0"):
    _hypothesis_settings.register_profile("mocap-fixed", derandomize=True)
    _hypothesis_settings.load_profile("mocap-fixed")


# --- both cores by default (issue #20) ---------------------------------------------------------
# With pytest-xdist installed (the dev extra) and no -n given, the suite runs on as many workers
# as the machine has cores ("-n auto --dist loadgroup"); "-n 0" or "-p no:xdist" runs it in one
# process, as before. The default is set here rather than in addopts so that "-p no:xdist" (or a
# venv without xdist) still parses the command line. xdist's workers parse the command line
# again (with PYTEST_ADDOPTS), and only a worker that was told --dist loadgroup names its tests'
# groups: the option is passed on to them that way.


@pytest.hookimpl(tryfirst=True)
def pytest_cmdline_main(config):
    if not config.pluginmanager.hasplugin("xdist") or hasattr(config, "workerinput"):
        return
    opt = config.option
    if opt.numprocesses is None and not opt.usepdb and not opt.collectonly:
        opt.numprocesses = "auto"
    if opt.numprocesses and opt.dist == "no":
        opt.dist = "loadgroup"
        os.environ["PYTEST_ADDOPTS"] = f"{os.environ.get('PYTEST_ADDOPTS', '')} --dist loadgroup"


# Tests that share a session- or module-scoped fixture of this folder (a simulated session, a
# run of it, an identified face) go to one worker together (--dist loadgroup), so that each such
# fixture is still built once per test run; every other test is scheduled on its own.


def _shared_fixtures(item) -> list[str]:
    """The non-function-scoped fixtures of tests/ that ``item`` uses (directly or not)."""
    info = getattr(item, "_fixtureinfo", None)  # pytest's; without it, no grouping (slower only)
    if info is None:
        return []
    out = []
    for name in item.fixturenames:
        defs = info.name2fixturedefs.get(name)
        if not defs:
            continue
        fd = defs[-1]
        code = getattr(getattr(fd, "func", None), "__code__", None)
        if fd.scope != "function" and code is not None and Path(code.co_filename).parent == TESTS:
            out.append(f"{Path(code.co_filename).stem}.{name}")
    return out


@pytest.hookimpl(tryfirst=True)  # before xdist's worker reads the marks into node ids
def pytest_collection_modifyitems(config, items):
    if not config.pluginmanager.hasplugin("xdist"):
        return
    parent: dict[str, str] = {}

    def find(x: str) -> str:
        while parent.setdefault(x, x) != x:
            x = parent[x]
        return x

    uses = {}
    for item in items:
        shared = _shared_fixtures(item)
        if shared:
            uses[item] = shared
            for other in shared[1:]:
                a, b = find(shared[0]), find(other)
                if a != b:
                    parent[max(a, b)] = min(a, b)
    for item, shared in uses.items():
        item.add_marker(pytest.mark.xdist_group(find(shared[0])))


def make_session(root: Path, **overrides) -> Path:
    """Simulate a small session into ``root`` (session/ and truth/); return ``root``."""
    cfg = preset(overrides.pop("preset", "small"), **overrides)
    simulate(cfg, root)
    return root


@pytest.fixture(scope="session")
def small_sim(tmp_path_factory) -> Path:
    """A small raw session (4 DUs, 3 trials, 40 markers, no battery): root with session/, truth/."""
    return make_session(tmp_path_factory.mktemp("small_sim"), seed=11, battery=False)


@pytest.fixture(scope="session")
def small_truth(small_sim) -> dict:
    return json.loads((small_sim / "truth" / "truth.json").read_text())


@pytest.fixture(scope="session")
def small_run(small_sim, tmp_path_factory):
    """``mocap run``'s library call on the small raw session (figures and session.rrd
    included): the RunResult."""
    from mocap.workflows.run.pipeline import run_session
    from mocap.outputs.run_writers import WRITERS

    return run_session(small_sim / "session", tmp_path_factory.mktemp("small_run"),
                       writers=WRITERS)


@pytest.fixture(scope="session")
def sample_run(tmp_path_factory):
    """``mocap run`` on the committed sample session (what the README's main command does)."""
    from mocap.workflows.run.pipeline import run_session
    from mocap.outputs.run_writers import WRITERS

    root = Path(__file__).resolve().parents[1] / "sample_data" / "session"
    return run_session(root, tmp_path_factory.mktemp("sample_run"), writers=WRITERS)


TINY = dict(seed=5, du_ids=(4, 7), n_markers=20, n_trials=2, battery=False, motion_plans=("A",),
            motion_dus=(4, 7), wand_duration_s=12.0)


@pytest.fixture(scope="session")
def tiny_sim(tmp_path_factory) -> Path:
    """A tiny raw session (2 DUs, 2 trials, 20 markers, one plan take): root with session/, truth/."""
    return make_session(tmp_path_factory.mktemp("tiny_sim"), **TINY)


@pytest.fixture(scope="session")
def tiny_run(tiny_sim, tmp_path_factory) -> Path:
    """``mocap run --jobs 1 --no-recording`` on the tiny session, uninterrupted: its OUT_DIR."""
    from mocap.cli import main

    out = tmp_path_factory.mktemp("tiny_run") / "out"
    assert main(["run", str(tiny_sim / "session"), "--out", str(out), "--jobs", "1",
                 "--no-recording", "--quiet"]) == 0
    return out
