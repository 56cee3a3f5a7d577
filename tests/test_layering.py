"""Imports go one way (issue #18; docs/architecture.md).

Every module of the package is parsed with ``ast`` and every import in it, including those inside
functions, is checked against the module's layer:

    core <- calib <- simulate (core and calib only)
    core <- calib <- reconstruction <- analysis <- workflows <- outputs <- cli

A module may import its own layer and the layers below it. Layers are assigned per module, not per
folder (``analysis/figures.py`` is an outputs module living in analysis/). Only
``mocap.recording`` imports rerun, only the figure modules matplotlib, only ``mocap.batch`` dask.
A module the map does not place fails the test: decide its layer in ``LAYER_OF`` and in
docs/architecture.md.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = {"mocap": ROOT / "mocap", "mocap.calib": ROOT / "calib", "mocap.analysis": ROOT / "analysis"}

# what each layer may import (itself included); the package's __init__ ("facade") only
# re-exports, from any layer, and any module may import it (it holds __version__)
ALLOWED = {
    "facade": {"core", "calib", "simulate", "reconstruction", "analysis", "workflows", "outputs",
               "cli", "facade"},
    "core": {"core"},
    "calib": {"core", "calib"},
    "simulate": {"core", "calib", "simulate"},
    "reconstruction": {"core", "calib", "reconstruction"},
    "analysis": {"core", "calib", "reconstruction", "analysis"},
    "workflows": {"core", "calib", "simulate", "reconstruction", "analysis", "workflows"},
    "outputs": {"core", "calib", "simulate", "reconstruction", "analysis", "workflows", "outputs"},
    "cli": {"core", "calib", "simulate", "reconstruction", "analysis", "workflows", "outputs",
            "cli"},
}

# modules placed one by one (mocap's top level), then packages by prefix (longest first)
LAYER_OF = {
    "mocap": "facade",  # mocap/__init__.py only re-exports (test_the_package_init_only_reexports)
    "mocap._facade": "facade",  # the package object that makes mocap.reconstruct callable
    "mocap.session": "core",
    "mocap.schedules": "core",
    "mocap.atomic": "core",
    "mocap.paths": "core",
    "mocap.errors": "core",
    "mocap.display": "core",  # one-screen summaries (repr, notebook HTML) of result objects
    "mocap.pipeline": "workflows",
    "mocap.audit": "workflows",
    "mocap.batch": "workflows",
    "mocap.discrepancy_input": "workflows",
    "mocap.discrepancy_io": "workflows",
    "mocap.design_io": "workflows",
    "mocap.truth_properties": "workflows",  # the simulator's truth through the analyses' estimators
    "mocap.api": "cli",  # an entry point beside the CLI: its run() writes figures and session.rrd
    "mocap.run_settings": "workflows",  # the run's settings (sections from reconstruct.settings)
    "mocap.run_cache": "workflows",  # stage keys and stored results of a run's output folder
    "mocap.run_lock": "workflows",  # one run per output folder
    "mocap.recording": "outputs",
    "mocap.run_outputs": "outputs",  # the run's figure and recording writers (RunWriters)
    "mocap.discrepancy_outputs": "outputs",  # the discrepancy workflow's figures and recording
    "mocap.analysis.figures": "outputs",
    "mocap.cli": "cli",
}
PACKAGES = {
    "mocap.calib": "calib",
    "mocap.simulate": "simulate",
    "mocap.reconstruct": "reconstruction",
    "mocap.interop": "reconstruction",
    "mocap.analysis": "analysis",
    "mocap.commands": "cli",
}

# third-party packages only some modules may import
RESTRICTED = {
    "rerun": {"mocap.recording"},
    "matplotlib": {"mocap.analysis.figures"},
    "dask": {"mocap.batch"},
}

# back-imports other branches are removing; each names who and why. Entries are allowed, not
# required: delete one when its import is gone (the graph test below says which are stale).
PENDING: dict[tuple[str, str], str] = {}


def layer_of(module: str) -> str | None:
    if module in LAYER_OF:
        return LAYER_OF[module]
    for prefix in sorted(PACKAGES, key=len, reverse=True):
        if module == prefix or module.startswith(prefix + "."):
            return PACKAGES[prefix]
    return None


def package_modules() -> dict[str, Path]:
    """Every module of the package: dotted name -> file."""
    out = {}
    for base, folder in FOLDERS.items():
        for f in sorted(folder.rglob("*.py")):
            parts = list(f.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join([base, *parts])] = f
    return out


def imports_of(module: str, path: Path, known: set[str]) -> list[tuple[str, int]]:
    """Every module ``module`` imports, anywhere in the file (function-local included), with its
    line: package modules resolved to the most specific known module, others by their top name."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    is_pkg = path.name == "__init__.py"
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = module.split(".") if is_pkg else module.split(".")[:-1]
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            for a in node.names:
                sub = f"{base}.{a.name}"
                out.append((sub if sub in known else base, node.lineno))
    return out


def import_graph() -> dict[str, list[tuple[str, int]]]:
    modules = package_modules()
    known = set(modules)
    return {m: imports_of(m, f, known) for m, f in modules.items()}


def violations(graph: dict[str, list[tuple[str, int]]], layer=layer_of,
               pending=PENDING) -> list[str]:
    """Every import that goes against the layers or the third-party rules, as messages."""
    bad = []
    for module, imports in graph.items():
        mine = layer(module)
        for target, line in imports:
            top = target.split(".")[0]
            if top in RESTRICTED and module not in RESTRICTED[top]:
                bad.append(f"{module}:{line} imports {target}: only {sorted(RESTRICTED[top])} may")
            if top != "mocap" or (module, target) in pending:
                continue
            theirs = layer(target)
            if mine is None or theirs is None:
                continue  # reported by test_every_module_has_a_layer
            if theirs != "facade" and theirs not in ALLOWED[mine]:
                bad.append(f"{module}:{line} ({mine}) imports {target} ({theirs})")
    return bad


def test_every_module_has_a_layer():
    unplaced = [m for m in package_modules() if layer_of(m) is None]
    assert not unplaced, f"place these modules in a layer (LAYER_OF, docs/architecture.md): {unplaced}"


def test_imports_go_one_way():
    assert violations(import_graph()) == []


def test_the_package_init_only_reexports():
    # mocap/__init__.py: a docstring, imports, dunder assignments (__version__, __all__) and a
    # lazy __getattr__/__dir__; no logic of its own
    tree = ast.parse((ROOT / "mocap" / "__init__.py").read_text(encoding="utf-8"))
    for node in tree.body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            continue
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant):
            continue
        if isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if all(isinstance(t, ast.Name) and t.id.startswith("__") for t in targets):
                continue
        if isinstance(node, ast.FunctionDef) and node.name in ("__getattr__", "__dir__"):
            continue
        if (isinstance(node, ast.Assign) and len(node.targets) == 1
                and ast.unparse(node.targets[0]) == "sys.modules[__name__].__class__"):
            continue  # the package object (mocap._facade): mocap.reconstruct is also callable
        raise AssertionError(f"mocap/__init__.py line {node.lineno}: only re-exports belong here")


def test_pending_back_imports_are_still_there():
    # an entry whose import is gone must leave PENDING, so the exception cannot outlive its cause
    edges = {(m, t) for m, imports in import_graph().items() for t, _ in imports}
    stale = [k for k in PENDING if k not in edges]
    assert not stale, f"remove from PENDING (the import is gone): {stale}"


# --------------------------------------------------------------------------------------------
# The check catches what issue #18 found (a synthetic graph, one back-import at a time)

BACK_IMPORTS = [
    ("mocap.reconstruct.trials", "mocap.analysis.displacement"),  # reconstruction -> analysis
    ("mocap.simulate.face", "mocap.analysis.hysteresis"),  # simulate -> analysis
    ("mocap.simulate.session_writer", "mocap.reconstruct.trials"),  # simulate -> reconstruction
    ("mocap.audit", "mocap.analysis.figures"),  # workflows -> outputs
    ("mocap.pipeline", "mocap.recording"),  # workflows -> outputs
    ("mocap.calib.wand", "mocap.reconstruct.correspondence"),  # calib -> reconstruction
    ("mocap.session", "mocap.calib.camera"),  # core -> calib
    ("mocap.analysis.properties", "mocap.pipeline"),  # analysis -> workflows
    ("mocap.recording", "mocap.cli"),  # outputs -> cli
    ("mocap.discrepancy_io", "mocap.analysis.figures"),  # workflows -> outputs
    ("mocap.batch", "mocap.run_outputs"),  # workflows -> outputs (writers are passed in)
    ("mocap.run_outputs", "mocap.api"),  # outputs -> the API entry point
]
FINE = [
    ("mocap.calib.calibration_file", "mocap.atomic"),  # calib -> core
    ("mocap.analysis.design", "mocap.schedules"),  # analysis -> core
    ("mocap.analysis.session_analysis", "mocap.reconstruct.trials"),  # analysis -> reconstruction
    ("mocap.commands.design", "mocap.analysis.figures"),  # cli -> outputs
    ("mocap.design_io", "mocap.simulate.motion"),  # workflows -> simulate
    ("mocap.api", "mocap.run_outputs"),  # the API entry point -> outputs
    ("mocap.run_outputs", "mocap.pipeline"),  # outputs -> workflows
]


@pytest.mark.parametrize("edge", BACK_IMPORTS, ids=lambda e: f"{e[0]}->{e[1]}")
def test_each_back_import_is_caught(edge):
    graph = {edge[0]: [(edge[1], 1)]}
    assert len(violations(graph, pending={})) == 1


@pytest.mark.parametrize("edge", FINE, ids=lambda e: f"{e[0]}->{e[1]}")
def test_downward_imports_pass(edge):
    assert violations({edge[0]: [(edge[1], 1)]}, pending={}) == []


@pytest.mark.parametrize("module, target", [("mocap.audit", "rerun"),
                                            ("mocap.analysis.discrepancy", "matplotlib.pyplot"),
                                            ("mocap.pipeline", "dask.distributed")])
def test_restricted_packages_are_caught(module, target):
    assert len(violations({module: [(target, 3)]}, pending={})) == 1


def test_function_local_and_relative_imports_are_seen(tmp_path):
    f = tmp_path / "trials.py"
    f.write_text("import numpy\n\ndef g():\n    from mocap.analysis import displacement\n"
                 "    from ..analysis.figures import x\n    from . import labeling\n")
    known = {"mocap.analysis.displacement", "mocap.analysis.figures", "mocap.reconstruct.labeling"}
    got = imports_of("mocap.reconstruct.trials", f, known)
    assert ("mocap.analysis.displacement", 4) in got
    assert ("mocap.analysis.figures", 5) in got  # ..analysis.figures from mocap.reconstruct
    assert ("mocap.reconstruct.labeling", 6) in got


def test_import_mocap_pulls_in_no_heavy_package():
    code = ("import sys, mocap, mocap.session, mocap.calib, mocap.analysis, mocap.reconstruct; "
            "print(sorted(m for m in ('rerun', 'matplotlib', 'dask') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
