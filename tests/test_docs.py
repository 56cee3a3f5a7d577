"""The project's own documentation: the API example runs, the CLI page is complete, links hold,
and nothing points outside the repository (issue #18)."""

from __future__ import annotations

import argparse
import re
from pathlib import Path



ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = ("index.md", "format.md", "outputs.md", "cli.md", "api.md", "architecture.md",
         "calibration.md", "indices.md", "simulator.md", "discrepancy.md", "design_loop.md")


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
