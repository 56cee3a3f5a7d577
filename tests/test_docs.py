"""The project's own documentation: the API example runs, the CLI page is complete, links hold,
and nothing points outside the repository (issue #18)."""

from __future__ import annotations

import argparse
import re
from pathlib import Path



ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = ("index.md", "format.md", "import.md", "outputs.md", "cli.md", "api.md", "design.md",
         "architecture.md", "calibration.md", "indices.md", "simulator.md", "discrepancy.md")


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
