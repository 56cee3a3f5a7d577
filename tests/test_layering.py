"""Imports go one way (docs/architecture.md): the layers are folders.

Every module of the package is parsed with ``ast`` and every import in it, including those inside
functions, is checked against the module's layer, which is its folder:

    core <- calib <- simulate (core and calib only)
    core <- calib <- reconstruction (and interop) <- analysis <- workflows <- outputs <- cli

A module may import its own layer and the layers below it. Only ``mocap.outputs`` imports
matplotlib and rerun, only ``mocap.workflows.batch`` dask. The package's entry points
(``mocap/__init__.py``, ``mocap/api.py``) sit above every layer.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = {"mocap": ROOT / "mocap", "mocap.calib": ROOT / "calib", "mocap.analysis": ROOT / "analysis"}

# what each layer may import (itself included); the entry points may import any layer, and any
# module may import the package's __init__ (it holds __version__)
ALLOWED = {
    "entry": {"core", "calib", "simulate", "reconstruction", "analysis", "workflows", "outputs",
              "cli", "entry"},
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

# the folder rules: a module's layer is that of the longest folder (package) holding it
ENTRY_POINTS = {"mocap", "mocap.api"}  # mocap/__init__.py and mocap/api.py: above every layer
FOLDER_LAYERS = {
    "mocap.core": "core",
    "mocap.calib": "calib",
    "mocap.simulate": "simulate",
    "mocap.reconstruction": "reconstruction",
    "mocap.interop": "reconstruction",
    "mocap.analysis": "analysis",
    "mocap.workflows": "workflows",
    "mocap.outputs": "outputs",
    "mocap.cli": "cli",
}

# third-party packages only some modules may import
RESTRICTED = {
    "rerun": {"mocap.outputs"},
    "matplotlib": {"mocap.outputs"},
    "dask": {"mocap.workflows.batch"},
}

# back-imports other branches are removing; each names who and why. Entries are allowed, not
# required: delete one when its import is gone (the graph test below says which are stale).
PENDING: dict[tuple[str, str], str] = {}


def _within(module: str, packages) -> bool:
    return any(module == p or module.startswith(p + ".") for p in packages)


def layer_of(module: str) -> str | None:
    if module in ENTRY_POINTS:
        return "entry"
    for prefix in sorted(FOLDER_LAYERS, key=len, reverse=True):
        if _within(module, [prefix]):
            return FOLDER_LAYERS[prefix]
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
            if top in RESTRICTED and not _within(module, RESTRICTED[top]):
                bad.append(f"{module}:{line} imports {target}: only {sorted(RESTRICTED[top])} may")
            if top != "mocap" or (module, target) in pending:
                continue
            theirs = layer(target)
            if mine is None or theirs is None:
                continue  # reported by test_every_module_has_a_layer
            if theirs not in ALLOWED[mine] and target != "mocap":
                bad.append(f"{module}:{line} ({mine}) imports {target} ({theirs})")
    return bad


def test_every_module_has_a_layer():
    unplaced = [m for m in package_modules() if layer_of(m) is None]
    assert not unplaced, f"move these modules into a layer's folder (FOLDER_LAYERS, docs/architecture.md): {unplaced}"


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
        raise AssertionError(f"mocap/__init__.py line {node.lineno}: only re-exports belong here")


def test_pending_back_imports_are_still_there():
    # an entry whose import is gone must leave PENDING, so the exception cannot outlive its cause
    edges = {(m, t) for m, imports in import_graph().items() for t, _ in imports}
    stale = [k for k in PENDING if k not in edges]
    assert not stale, f"remove from PENDING (the import is gone): {stale}"


# --------------------------------------------------------------------------------------------
# The check catches what issue #18 found (a synthetic graph, one back-import at a time)

BACK_IMPORTS = [
    ("mocap.reconstruction.trials", "mocap.analysis.paper.displacement"),  # reconstruction -> analysis
    ("mocap.simulate.face", "mocap.analysis.model.hysteresis"),  # simulate -> analysis
    ("mocap.simulate.session_writer", "mocap.reconstruction.trials"),  # simulate -> reconstruction
    ("mocap.workflows.audit", "mocap.outputs.figures"),  # workflows -> outputs
    ("mocap.workflows.run.pipeline", "mocap.outputs.recording"),  # workflows -> outputs
    ("mocap.calib.wand", "mocap.reconstruction.correspondence"),  # calib -> reconstruction
    ("mocap.core.session", "mocap.calib.camera"),  # core -> calib
    ("mocap.analysis.paper.properties", "mocap.workflows.run.pipeline"),  # analysis -> workflows
    ("mocap.outputs.recording", "mocap.cli"),  # outputs -> cli
    ("mocap.workflows.discrepancy.results", "mocap.outputs.figures"),  # workflows -> outputs
    ("mocap.workflows.batch", "mocap.outputs.run_writers"),  # workflows -> outputs (writers are passed in)
    ("mocap.outputs.run_writers", "mocap.api"),  # outputs -> the API entry point
]
FINE = [
    ("mocap.calib.calibration_file", "mocap.core.atomic"),  # calib -> core
    ("mocap.analysis.design.inverse_response", "mocap.core.schedules"),  # analysis -> core
    ("mocap.analysis.session_analysis", "mocap.reconstruction.trials"),  # analysis -> reconstruction
    ("mocap.cli.commands.design", "mocap.outputs.figures"),  # cli -> outputs
    ("mocap.workflows.design", "mocap.simulate.motion"),  # workflows -> simulate
    ("mocap.api", "mocap.outputs.run_writers"),  # the API entry point -> outputs
    ("mocap.outputs.run_writers", "mocap.workflows.run.pipeline"),  # outputs -> workflows
]


@pytest.mark.parametrize("edge", BACK_IMPORTS, ids=lambda e: f"{e[0]}->{e[1]}")
def test_each_back_import_is_caught(edge):
    graph = {edge[0]: [(edge[1], 1)]}
    assert len(violations(graph, pending={})) == 1


@pytest.mark.parametrize("edge", FINE, ids=lambda e: f"{e[0]}->{e[1]}")
def test_downward_imports_pass(edge):
    assert violations({edge[0]: [(edge[1], 1)]}, pending={}) == []


@pytest.mark.parametrize("module, target", [("mocap.workflows.audit", "rerun"),
                                            ("mocap.analysis.discrepancy.workflow", "matplotlib.pyplot"),
                                            ("mocap.workflows.run.pipeline", "dask.distributed")])
def test_restricted_packages_are_caught(module, target):
    assert len(violations({module: [(target, 3)]}, pending={})) == 1


def test_function_local_and_relative_imports_are_seen(tmp_path):
    f = tmp_path / "trials.py"
    f.write_text("import numpy\n\ndef g():\n    from mocap.analysis.paper import displacement\n"
                 "    from ..outputs.figures import x\n    from . import labeling\n")
    known = {"mocap.analysis.paper.displacement", "mocap.outputs.figures", "mocap.reconstruction.labeling"}
    got = imports_of("mocap.reconstruction.trials", f, known)
    assert ("mocap.analysis.paper.displacement", 4) in got
    assert ("mocap.outputs.figures", 5) in got  # ..analysis.figures from mocap.reconstruction
    assert ("mocap.reconstruction.labeling", 6) in got


def test_import_mocap_pulls_in_no_heavy_package():
    code = ("import sys, mocap, mocap.core.session, mocap.calib, mocap.analysis, mocap.reconstruction; "
            "print(sorted(m for m in ('rerun', 'matplotlib', 'dask') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
