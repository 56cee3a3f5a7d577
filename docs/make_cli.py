"""Write docs/cli.md from the command parsers: ``python docs/make_cli.py > docs/cli.md``.

tests/test_docs.py checks that docs/cli.md has a section for every command and names every
option; rerun this after adding a command or an option (then edit the prose if needed).
"""

from __future__ import annotations

import argparse
import re

from mocap.cli import COMMANDS, _module

INTRO = """\
# Command line

`mocap COMMAND --help` prints a command's options and examples; `mocap --version` prints the
version. Exit status: 0 on success, 1 on an error (printed as `error: ...` on stderr, naming
the file, line or key at fault), 2 on a usage error. Progress goes to stderr, results to
stdout. The session format is in [format](format.md), what each command writes in
[outputs](outputs.md). Commands that write refuse an output path that is, lies inside or
contains the session they read ([where outputs may go](outputs.md#where-outputs-may-go)).
"""


def _plain(text: str) -> str:
    return text.replace("FORMAT.md", "docs/format.md").replace("OUTPUTS.md", "docs/outputs.md")


def _flag(a: argparse.Action) -> str:
    if not a.option_strings:
        return (a.metavar or a.dest.upper()) + (" ..." if a.nargs in ("+", "*") else "")
    flag = ", ".join(a.option_strings)
    if a.nargs != 0:
        choices = "{" + ",".join(map(str, a.choices)) + "}" if a.choices else a.dest.upper()
        flag += " " + (a.metavar or choices)
    return flag


def command_section(name: str) -> list[str]:
    module = _module(name)
    parser = argparse.ArgumentParser(prog=f"mocap {name}")
    module.add_arguments(parser)
    out = [f"## mocap {name}", ""]
    prose, *examples = re.split(r"\n(?=examples?:\n)", _plain(module.DESCRIPTION.strip()))
    for paragraph in prose.split("\n\n"):
        out += [paragraph.strip(), ""]
    if examples:
        body = examples[0].split("\n", 1)[1]
        out += ["```sh", *(ln[2:] if ln.startswith("  ") else ln for ln in body.splitlines()),
                "```", ""]
    out += ["| argument | meaning |", "|---|---|"]
    for a in parser._actions:
        if isinstance(a, argparse._HelpAction):
            continue
        meaning = _plain(a.help or "").replace("|", "\\|")
        if a.required and a.option_strings:
            meaning += " (required)"
        if a.option_strings and a.default not in (None, False, [], argparse.SUPPRESS) \
                and "default" not in meaning:
            meaning += f" (default {a.default})"
        out.append(f"| `{_flag(a)}` | {meaning} |")
    return out + [""]


def main() -> None:
    lines = [INTRO, "| command | what it does |", "|---|---|"]
    lines += [f"| [`{n}`](#mocap-{n}) | {h} |" for n, h in COMMANDS.items()]
    lines.append("")
    for name in COMMANDS:
        lines += command_section(name)
    print("\n".join(lines).rstrip("\n"))


if __name__ == "__main__":
    main()
