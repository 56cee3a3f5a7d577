"""The project's own documentation: the API example runs, the CLI page is complete, links hold,
and nothing points outside the repository (issue #18)."""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = ("index.md", "format.md", "import.md", "outputs.md", "cli.md", "api.md", "design.md",
         "design_loop.md", "architecture.md", "calibration.md", "indices.md", "simulator.md",
         "discrepancy.md")


def python_blocks(text: str) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def test_the_api_example_runs(tmp_path, monkeypatch):
    blocks = python_blocks((DOCS / "api.md").read_text(encoding="utf-8"))
    assert len(blocks) >= 3
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "docs_api"}
    for i, code in enumerate(blocks):
        exec(compile(code, f"docs/api.md block {i + 1}", "exec"), namespace)  # noqa: S102
    assert (tmp_path / "results" / "properties.csv").is_file()
    assert not any((tmp_path / "virtual" / "session").rglob("properties.csv"))


def test_the_import_page_matches_the_importer(tmp_path):
    """docs/import.md's take table and DU table have the importer's columns, its column table
    lists each once, and its example table plans as the page says."""
    from mocap.interop.take_table import DU_TABLE_COLUMNS, TABLE_COLUMNS, plan_takes

    text = (DOCS / "import.md").read_text(encoding="utf-8")
    tables = re.findall(r"^```csv\n(.*?)^```", text, flags=re.S | re.M)
    assert tables[0].splitlines()[0].split(",") == list(TABLE_COLUMNS)
    assert tables[1].splitlines()[0].split(",") == list(DU_TABLE_COLUMNS)
    assert re.findall(r"^\| `(\w+)` \|", text, flags=re.M) == list(TABLE_COLUMNS)
    (tmp_path / "takes.csv").write_text(tables[0])
    (tmp_path / "commands").mkdir()
    for row in tables[0].splitlines()[1:]:
        (tmp_path / row.split(",")[0]).write_bytes(b"")
        log = row.split(",")[6]
        if log:
            (tmp_path / log).write_text("time_s,du,command\n0.0,1,0\n")
    plan = plan_takes([], table=tmp_path / "takes.csv")
    assert [(t.name, t.kind, t.du, t.trial, t.plan) for t in plan.takes] == [
        ("rest", "rest", None, None, None), ("du1_t1", "response", 1, 1, None),
        ("du1_t2", "response", 1, 2, None), ("smile_A", "motion", None, None, "A")]
    assert plan.takes[1].commands == tmp_path / "commands" / "smile_DU1_trial1_commands.csv"
def readme_python() -> str:
    """The README's "From Python" example: the indented block under that heading."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = re.search(r"^## From Python.*?\n\n((?:    .*\n|\n)+)", text, flags=re.M)
    assert section, "README.md: no indented code block under '## From Python'"
    return "\n".join(line[4:] for line in section.group(1).splitlines()).strip() + "\n"


def test_the_readme_python_block_is_found():
    code = readme_python()
    assert code.startswith("import mocap\n") and "mocap.run(session" in code
    compile(code, "README.md", "exec")


def _readme_folder(tmp_path: Path, sim: Path) -> Path:
    """A working folder where the README's ``sample_data/session`` is a small simulated
    session (the README's code is run unchanged, on less data than the sample's)."""
    cwd = tmp_path / "cwd"
    (cwd / "sample_data").mkdir(parents=True)
    (cwd / "sample_data" / "session").symlink_to(sim / "session", target_is_directory=True)
    return cwd


def test_the_readme_python_example_runs_as_a_plain_script(tiny_sim, tmp_path):
    """The README's lines pasted into ``analyse.py`` (no main guard) and run with ``python
    analyse.py``: exit 0, the outputs written."""
    cwd = _readme_folder(tmp_path, tiny_sim)
    (cwd / "analyse.py").write_text(readme_python(), encoding="utf-8")
    proc = subprocess.run([sys.executable, "analyse.py"], cwd=cwd, capture_output=True,
                          text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    props = (cwd / "out" / "sample" / "properties.csv").read_text().splitlines()
    assert props[0].startswith("du,") and len(props) == 3  # DUs 4 and 7


# A notebook's way of running code, for where Jupyter is not installed: a fresh interpreter
# whose __main__ is a module without a file (as ipykernel's), each statement a cell compiled
# under an ipykernel-like file name, and each expression's value displayed as a notebook
# does (its _repr_html_ when it has one, else its repr).
NOTEBOOK = r"""
import ast, json, sys, types
main = types.ModuleType("__main__")
main.__dict__["__builtins__"] = __builtins__
sys.modules["__main__"] = main
shown = []
tree = ast.parse(sys.stdin.read())
for i, node in enumerate(tree.body):
    if isinstance(node, ast.Expr):
        value = eval(compile(ast.Expression(node.value), f"/tmp/ipykernel_0/{i}.py", "eval"),
                     main.__dict__)
        html = getattr(value, "_repr_html_", None)
        shown.append({"line": node.lineno, "type": type(value).__name__,
                      "repr": len(repr(value)), "html": len(html() or "") if html else None})
    else:
        exec(compile(ast.Module([node], []), f"/tmp/ipykernel_0/{i}.py", "exec"), main.__dict__)
json.dump(shown, sys.stdout)
"""


def test_the_readme_python_example_runs_in_a_notebook(tiny_sim, tmp_path):
    """The same lines run as notebook cells (no jupyter needed: see NOTEBOOK): each displayed
    value fits on a screen."""
    cwd = _readme_folder(tmp_path, tiny_sim)
    proc = subprocess.run([sys.executable, "-c", NOTEBOOK], input=readme_python(), cwd=cwd,
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    shown = json.loads(proc.stdout)
    assert [s["type"] for s in shown] == ["DataFrame", "DataFrame", "ndarray", "RunResult"]
    assert (cwd / "out" / "sample" / "properties.csv").is_file()
    result = shown[-1]
    assert result["repr"] < 2000 and result["html"] is not None and result["html"] < 20000


def test_python_blocks_are_found():
    text = "a\n```python\nx = 1\n```\n```sh\nls\n```\n```python\ny = 2\n```\n"
    assert python_blocks(text) == ["x = 1\n", "y = 2\n"]


def test_every_page_exists_and_the_index_links_them():
    index = (DOCS / "index.md").read_text(encoding="utf-8")
    for page in PAGES:
        if page != "index.md":
            assert f"({page})" in index, f"docs/index.md does not link {page}"
    for page in PAGES:
        assert (DOCS / page).is_file(), page


def _links(path: Path) -> list[str]:
    text = path.read_text(encoding="utf-8")
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)  # not inside code blocks
    return re.findall(r"\]\(([^)\s]+)\)", text)


def test_relative_links_resolve_and_stay_in_the_repository():
    for page in [ROOT / "README.md", *sorted(DOCS.glob("*.md"))]:
        for link in _links(page):
            if re.match(r"^[a-z]+://", link) or link.startswith("#"):
                continue
            target = (page.parent / link.split("#")[0]).resolve()
            assert target.is_relative_to(ROOT), f"{page.name}: {link} leaves the repository"
            assert target.exists(), f"{page.name}: {link} does not exist"


def test_readme_links_the_docs_and_names_no_outside_path():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    for page in ("docs/index.md", "docs/format.md", "docs/outputs.md", "docs/cli.md",
                 "docs/api.md"):
        assert f"({page})" in readme, f"README does not link {page}"
    assert "../" not in readme and "shared/" not in readme
    for page in DOCS.glob("*.md"):
        text = page.read_text(encoding="utf-8")
        assert "../shared" not in text and "shared/FORMAT" not in text, page.name


def test_the_cli_page_covers_every_command_and_option():
    from mocap.cli import COMMANDS, _module

    text = (DOCS / "cli.md").read_text(encoding="utf-8")
    sections = dict(re.findall(r"^## mocap (\S+)\n(.*?)(?=^## |\Z)", text, flags=re.S | re.M))
    missing = [c for c in COMMANDS if c not in sections]
    assert not missing, f"docs/cli.md lacks {missing}: run python docs/make_cli.py > docs/cli.md"
    for name in COMMANDS:
        parser = argparse.ArgumentParser()
        _module(name).add_arguments(parser)
        options = [o for a in parser._actions for o in a.option_strings
                   if o.startswith("--") and o != "--help"]
        absent = [o for o in options if f"`{o}" not in sections[name] and f", {o}" not in sections[name]]
        assert not absent, (f"docs/cli.md, mocap {name}: options {absent} undocumented; run "
                            "python docs/make_cli.py > docs/cli.md")


def test_the_design_loop_commands_parse_and_name_real_options():
    """docs/design_loop.md's commands are what 'mocap design' accepts: each shell block's
    command parses with the command line's own parser, and the options the page names in its
    text exist."""
    import shlex

    from mocap.cli import build_parser

    text = (DOCS / "design_loop.md").read_text(encoding="utf-8")
    blocks = re.findall(r"^```sh\n(.*?)^```", text, flags=re.S | re.M)
    assert len(blocks) >= 2
    parser = build_parser()
    for block in blocks:
        argv = shlex.split(block.replace("\\\n", " "))
        assert argv[0] == "mocap", block
        args = parser.parse_args(argv[1:])
        assert args.command == "design" and args.method == "model", block
    sub = next(a for a in build_parser("design")._actions
               if isinstance(a, argparse._SubParsersAction)).choices["design"]
    options = {o for a in sub._actions for o in a.option_strings}
    named = set(re.findall(r"`(--[a-z-]+)", text))
    assert named and named <= options, named - options
