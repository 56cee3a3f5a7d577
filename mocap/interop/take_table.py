"""What each imported file is: a take table, a name pattern, or the file's own name.

A lab exports one file per take (C3D, Motive CSV, QTM TSV, Vicon CSV) and logs commands per take.
This module decides, before any motion data is read, each file's take: its name, kind, DU, trial,
plan, command log and command offset (:class:`TakePlan`), and lists what it had to guess.

Three routes, in this order of precedence:

- a take table (CSV; columns ``file, name, kind, du, trial, plan, commands, commands_offset_s``,
  every one but ``file`` optional): one row per file, matched to the files given by path or
  by file name;
- name patterns (``du{du}_t{trial}``): a file whose stem matches is a ``response`` take of that
  DU and trial (``{plan}`` makes a ``motion`` take of that plan);
- the file's name alone: ``rest``, ``wand`` and ``ground`` are recognised as words of the stem;
  without a table or a pattern every other file is a ``motion`` take (a guess, listed).

Command logs (``time_s,du,command`` CSV files) come from the table's ``commands`` column, or are
matched by name in a folder (``--commands DIR``): a log whose stem, less a ``_commands``-like
suffix, equals the take's name or its file's stem (case ignored). Files given for import that
are command logs join that pool instead of becoming takes.

Errors (:class:`ImportError_`) name the file or the table's line: a file no row or pattern
accounts for, a row naming a file not given, two takes of one name, an unknown kind, a response
take without its DU.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from pathlib import Path

import pandas as pd

from mocap.interop.marker_data import ImportError_
from mocap.core.session import TAKE_KINDS

TABLE_COLUMNS = ("file", "name", "kind", "du", "trial", "plan", "commands", "commands_offset_s")
DU_TABLE_COLUMNS = ("du", "name", "feedback")
NAMED_KINDS = ("rest", "wand", "ground")
_NAMED = re.compile(r"(?:^|[^a-z])(rest|wand|ground)(?=[^a-z]|$)")
_LOG_SUFFIX = re.compile(r"[_\-. ]+(commands?|cmds?|log)$", re.IGNORECASE)
_FIELD = re.compile(r"\{(\w*)\}|\*")
_FIELDS = {"du": r"(?P<du>\d+)", "trial": r"(?P<trial>\d+)", "plan": r"(?P<plan>[A-Za-z0-9]+)"}


@dataclass(frozen=True)
class TakePlan:
    """One file's take, as the session will declare it.

    source : the vendor file; name : the take's name (unique); kind : one of the session
    format's take kinds; du, trial, plan : as the manifest's keys (None: absent);
    commands : a command log (CSV ``time_s,du,command``) to copy, or None (C3D analog channels
    ``DU<n>`` are used when the file has them); commands_offset_s : capture time (s) of the
    log's time 0, or None; where : the place that described it ("takes.csv line 4", or the
    file), for messages.
    """

    source: Path
    name: str
    kind: str
    du: int | None = None
    trial: int | None = None
    plan: str | None = None
    commands: Path | None = None
    commands_offset_s: float | None = None
    where: str = ""


@dataclass(frozen=True)
class Planning:
    """The takes of an import, in the order of the files given, and what was guessed.

    takes : one :class:`TakePlan` per motion file; guessed : one line per guess (what and why);
    notes : what else the planning found (unused command logs, files taken as command logs).
    """

    takes: tuple[TakePlan, ...]
    guessed: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class DUEntry:
    """A DU as the manifest's ``[[dus]]`` declares it: id, name, feedback (closed loop)."""

    id: int
    name: str
    feedback: bool = False


# --- reading small CSV tables ---------------------------------------------------------------

def _read_table(path: Path, columns: tuple[str, ...], required: tuple[str, ...], what: str,
                notes: list[str]) -> list[tuple[int, dict[str, str]]]:
    """The rows of a small CSV table as (line number, {column: stripped text}); blank lines
    skipped, columns it does not know noted and ignored."""
    try:
        t = pd.read_csv(path, dtype=str, keep_default_na=False, skip_blank_lines=False)
    except FileNotFoundError:
        raise ImportError_(f"{path}: no such {what}") from None
    except (OSError, ValueError, UnicodeDecodeError, pd.errors.ParserError) as e:
        raise ImportError_(f"{path}: not a readable CSV {what} ({e})") from None
    t.columns = [str(c).strip().lower() for c in t.columns]
    unknown = [c for c in t.columns if c not in columns]
    if unknown:
        notes.append(f"{path}: column(s) {unknown} ignored (a {what} has the columns "
                     f"{', '.join(columns)})")
    missing = [c for c in required if c not in t.columns]
    if missing:
        raise ImportError_(f"{path} line 1: missing column(s) {missing} (a {what} needs "
                           f"{', '.join(required)})")
    rows = [(i + 2, {c: "" if pd.isna(v) else str(v).strip() for c, v in r.items() if c in columns})
            for i, r in enumerate(t.to_dict("records"))]
    rows = [(n, r) for n, r in rows if any(r.values())]
    if not rows:
        raise ImportError_(f"{path}: no rows below the header")
    return rows


def _int_cell(value: str, where: str, col: str, minimum: int) -> int | None:
    if value == "":
        return None
    try:
        f = float(value)
    except ValueError:
        f = math.nan
    if not math.isfinite(f) or f != round(f) or f < minimum:
        raise ImportError_(f"{where}: {col} {value!r} is not an integer >= {minimum}")
    return int(f)


def read_du_table(path: str | Path, notes: list[str] | None = None) -> dict[int, DUEntry]:
    """A DU table (CSV ``du,name[,feedback]``): DU id -> :class:`DUEntry`; ``feedback`` true/false,
    1/0 or yes/no, false when absent. Errors name the line; ignored columns are noted."""
    path = Path(path)
    rows = _read_table(path, DU_TABLE_COLUMNS, ("du", "name"), "DU table",
                       notes if notes is not None else [])
    out: dict[int, DUEntry] = {}
    for line, row in rows:
        where = f"{path} line {line}"
        du = _int_cell(row["du"], where, "du", 0)
        if du is None:
            raise ImportError_(f"{where}: empty du; expected an integer DU id")
        if du in out:
            raise ImportError_(f"{where}: DU {du} listed twice")
        fb = row.get("feedback", "").lower()
        if fb not in ("", "true", "false", "1", "0", "yes", "no"):
            raise ImportError_(f"{where}: feedback {row['feedback']!r}; expected true or false")
        out[du] = DUEntry(du, row["name"] or f"DU {du}", fb in ("true", "1", "yes"))
    return out


# --- command logs -----------------------------------------------------------------------------

def is_command_log(path: Path) -> bool:
    """True for a CSV file whose header holds ``time_s``, ``du`` and ``command``."""
    if path.suffix.lower() != ".csv" or not path.is_file():
        return False
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as fh:
            head = fh.readline()
    except OSError:
        return False
    cols = {c.strip().strip('"').lower() for c in head.split(",")}
    return {"time_s", "du", "command"} <= cols


def _log_key(path: Path) -> str:
    stem = path.stem
    bare = _LOG_SUFFIX.sub("", stem)
    return (bare or stem).lower()


def command_logs(folder: Path) -> list[Path]:
    """The command logs in ``folder`` (not its subfolders), sorted by name."""
    if not folder.is_dir():
        raise ImportError_(f"{folder}: no such folder of command logs")
    return sorted(p for p in folder.iterdir() if is_command_log(p))


def _match_logs(takes: list[TakePlan], logs: list[Path], guessed: list[str], notes: list[str]
                ) -> list[TakePlan]:
    """Each take without a command log gets the one named like it (ambiguity is an error)."""
    by_key: dict[str, list[Path]] = {}
    for p in logs:
        by_key.setdefault(_log_key(p), []).append(p)
    used: set[Path] = set()
    out = []
    for t in takes:
        if t.commands is None:
            keys = dict.fromkeys([t.name.lower(), t.source.stem.lower()])
            found = sorted({p for k in keys for p in by_key.get(k, [])})
            if len(found) > 1:
                raise ImportError_(f"{t.where}: take {t.name!r} matches several command logs "
                                   f"({', '.join(str(p) for p in found)}); name one in a take "
                                   "table's 'commands' column")
            if found:
                t = replace(t, commands=found[0])
                guessed.append(f"take {t.name!r}: commands from {found[0]} (matched by name)")
        if t.commands is not None:
            used.add(t.commands.resolve())
        out.append(t)
    unused = [str(p) for p in logs if p.resolve() not in used]
    if unused:
        notes.append(f"command logs matching no take, not imported: {', '.join(unused)}")
    return out


# --- kinds from names and patterns ------------------------------------------------------------

def kind_from_name(stem: str, where: str | None = None) -> str | None:
    """``rest``, ``wand`` or ``ground`` when the stem holds that word (``smile_rest``,
    ``Wand-02``), else None; a stem naming two of them is an error naming ``where`` (the
    file)."""
    found = set(_NAMED.findall(stem.lower()))
    if len(found) > 1:
        raise ImportError_(f"{where or stem}: the name holds {' and '.join(sorted(found))}; say "
                           "which kind the take is in a take table (--takes)")
    return found.pop() if found else None


def compile_pattern(pattern: str) -> re.Pattern:
    """A name pattern as a regular expression matched against whole stems, case ignored:
    ``{du}`` and ``{trial}`` match integers, ``{plan}`` a word of letters and digits, ``*``
    anything; the rest literally."""
    parts, pos, seen = [], 0, set()
    for m in _FIELD.finditer(pattern):
        parts.append(re.escape(pattern[pos:m.start()]))
        if m.group(0) == "*":
            parts.append(".*?")
        else:
            f = m.group(1)
            if f not in _FIELDS:
                raise ImportError_(f"--pattern {pattern!r}: unknown field {{{f}}}; expected "
                                   "{du}, {trial}, {plan} or *")
            if f in seen:
                raise ImportError_(f"--pattern {pattern!r}: {{{f}}} appears twice")
            seen.add(f)
            parts.append(_FIELDS[f])
        pos = m.end()
    parts.append(re.escape(pattern[pos:]))
    if not seen:
        raise ImportError_(f"--pattern {pattern!r}: holds no field; expected {{du}}, {{trial}} "
                           "or {plan} (e.g. 'du{du}_t{trial}')")
    return re.compile("".join(parts), re.IGNORECASE)


def _take_name(stem: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", stem).strip("_") or "take"


def _unique(takes: list[TakePlan], guessed: list[str]) -> list[TakePlan]:
    """Names from file stems made unique (``rest_2``), each rename listed."""
    taken: set[str] = set()
    out = []
    for t in takes:
        name, k = t.name, 2
        while name.lower() in taken:
            name = f"{t.name}_{k}"
            k += 1
        if name != t.name:
            guessed.append(f"{t.source}: named {name!r} ({t.name!r} was taken by another file)")
        taken.add(name.lower())
        out.append(replace(t, name=name))
    return out


def _by_name(files: list[Path], patterns: list[str], guessed: list[str]) -> list[TakePlan]:
    compiled = [compile_pattern(p) for p in patterns]
    takes = []
    for f in files:
        where, name = str(f), _take_name(f.stem)
        for rx in compiled:
            m = rx.fullmatch(f.stem)
            if m:
                g = m.groupdict()
                du = int(g["du"]) if g.get("du") else None
                trial = int(g["trial"]) if g.get("trial") else None
                kind = "response" if du is not None else "motion"
                takes.append(TakePlan(f, name, kind, du, trial, g.get("plan"), where=where))
                break
        else:
            kind = kind_from_name(f.stem, str(f))
            if kind is not None:
                guessed.append(f"take {name!r}: kind {kind!r}, from its file name {f.name!r}")
            elif patterns:
                raise ImportError_(
                    f"{f}: its name {f.stem!r} matches no --pattern ({', '.join(patterns)}) and "
                    f"names none of {', '.join(NAMED_KINDS)}: rename it, leave it out, or describe "
                    "the files in a take table (--takes)")
            else:
                kind = "motion"
                guessed.append(f"take {name!r}: kind 'motion' (no take table or pattern says "
                               "otherwise)")
            takes.append(TakePlan(f, name, kind, where=where))
    return _unique(takes, guessed)


# --- the take table -----------------------------------------------------------------------------

def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve()
    except OSError:
        return False


def _table_file(value: str, table: Path, files: list[Path], where: str) -> Path:
    """The file (among ``files``, or all files when none are given) a row's ``file`` names."""
    if value == "":
        raise ImportError_(f"{where}: empty 'file'; every row names the file of its take")
    given = Path(value)
    candidates = [given] if given.is_absolute() else [table.parent / given, given]
    if not files:
        for c in candidates:
            if c.is_file():
                return c
        raise ImportError_(f"{where}: file {value!r} not found (looked in "
                           f"{', '.join(str(c.parent) for c in candidates)})")
    hit = [f for f in files if any(_same_file(f, c) for c in candidates)]
    if not hit:
        hit = [f for f in files if f.name == given.name] if given.name == value else []
    if len(hit) > 1:
        raise ImportError_(f"{where}: file {value!r} matches several files given "
                           f"({', '.join(map(str, hit))}); write its path instead")
    if not hit:
        exists = any(c.is_file() for c in candidates)
        raise ImportError_(f"{where}: file {value!r} is not among the files given"
                           + (" (it exists: add it to the command line, or drop the row)" if exists
                              else " and does not exist"))
    return hit[0]


def _from_table(files: list[Path], table: Path, guessed: list[str], notes: list[str]
                ) -> list[TakePlan]:
    rows = _read_table(table, TABLE_COLUMNS, ("file",), "take table", notes)
    takes: list[TakePlan] = []
    names: dict[str, str] = {}
    sources: dict[Path, str] = {}
    for line, row in rows:
        where = f"{table} line {line}"
        src = _table_file(row["file"], table, files, where)
        key = src.resolve()
        if key in sources:
            raise ImportError_(f"{where}: file {row['file']!r} already described on {sources[key]}")
        sources[key] = f"line {line}"
        name = row.get("name", "") or _take_name(src.stem)
        if name.lower() in names:
            raise ImportError_(f"{where}: take name {name!r} already used on {names[name.lower()]}; "
                               "take names must be unique")
        names[name.lower()] = f"line {line}"
        du = _int_cell(row.get("du", ""), where, "du", 0)
        trial = _int_cell(row.get("trial", ""), where, "trial", 1)
        kind = row.get("kind", "").lower()
        if kind and kind not in TAKE_KINDS:
            raise ImportError_(f"{where}: kind {row['kind']!r}; expected one of "
                               f"{', '.join(TAKE_KINDS)}")
        if not kind:
            kind = ("response" if du is not None else kind_from_name(src.stem, where) or "motion")
            why = ("it names a DU" if du is not None else "from its file name"
                   if kind in NAMED_KINDS else "no kind given")
            guessed.append(f"{where}: take {name!r} kind {kind!r} ({why})")
        offset = None
        if row.get("commands_offset_s", ""):
            try:
                offset = float(row["commands_offset_s"])
            except ValueError:
                offset = math.nan
            if not math.isfinite(offset):
                raise ImportError_(f"{where}: commands_offset_s {row['commands_offset_s']!r} is "
                                   "not a number of seconds")
        commands = None
        if row.get("commands", ""):
            c = Path(row["commands"])
            c = c if c.is_absolute() or not (table.parent / c).is_file() else table.parent / c
            if not c.is_file():
                raise ImportError_(f"{where}: command log {row['commands']!r} not found (relative "
                                   f"paths are read from {table.parent})")
            commands = c
        takes.append(TakePlan(src, name, kind, du, trial, row.get("plan", "") or None, commands,
                              offset, where))
    missed = [f for f in files if f.resolve() not in sources]
    if missed:
        raise ImportError_(f"{missed[0]}: no row of {table} names it"
                           + (f" (nor {len(missed) - 1} other file(s))" if len(missed) > 1 else "")
                           + ": add a row for it, or leave it out of the files given")
    return takes


# --- the whole planning -------------------------------------------------------------------------

def plan_takes(files, *, table: str | Path | None = None, patterns=(),
               commands_dir: str | Path | None = None) -> Planning:
    """Each file's take (:class:`Planning`), by ``table``, else ``patterns``, else names.

    files : the files given for import (motion files; command logs among them join the pool of
    logs); table : a take table's path; patterns : name patterns (tried in order);
    commands_dir : a folder of command logs matched by name. ImportError_ names the file or
    line at fault.
    """
    files = [Path(f) for f in files]
    guessed: list[str] = []
    notes: list[str] = []
    logs = [f for f in files if is_command_log(f)]
    if logs:
        notes.append(f"{len(logs)} file(s) given are command logs (time_s,du,command), taken as "
                     f"such: {', '.join(str(p) for p in logs)}")
    motion = [f for f in files if f not in logs]
    seen: dict[Path, Path] = {}
    for f in motion:
        if f.resolve() in seen:
            raise ImportError_(f"{f}: given twice (also as {seen[f.resolve()]})")
        seen[f.resolve()] = f
    if table is not None:
        takes = _from_table(motion, Path(table), guessed, notes)
    else:
        if not motion:
            raise ImportError_("no files to import: give the takes' files (or a take table)")
        takes = _by_name(motion, list(patterns), guessed)
    if commands_dir is not None:
        pool = command_logs(Path(commands_dir))
        logs += [p for p in pool if not any(_same_file(p, q) for q in logs)]
    if logs:
        takes = _match_logs(takes, logs, guessed, notes)
    return Planning(tuple(takes), tuple(guessed), tuple(notes))


def check_response(take: TakePlan, command_dus: set[int]) -> tuple[TakePlan, str | None]:
    """A response take checked against the DUs its command log drives: the DU guessed when the
    log drives one only (the guess returned), ImportError_ when it has no log, no DU or a DU the
    log does not drive."""
    if take.kind != "response":
        return take, None
    if not command_dus:
        raise ImportError_(f"{take.where}: response take {take.name!r} has no command log: give "
                           "one (the table's 'commands' column, --commands DIR with a log named "
                           "like the take, or C3D analog channels DU<n>)")
    if take.du is None:
        if len(command_dus) != 1:
            raise ImportError_(f"{take.where}: response take {take.name!r} names no DU and its "
                               f"commands drive DUs {sorted(command_dus)}: give its du")
        du = next(iter(command_dus))
        return replace(take, du=du), (f"take {take.name!r}: DU {du}, the only DU its command log "
                                      "drives")
    if take.du not in command_dus:
        raise ImportError_(f"{take.where}: response take {take.name!r} drives DU {take.du} but its "
                           f"command log has no rows for DU {take.du} (it drives "
                           f"{sorted(command_dus)}): a DU without commands")
    return take, None


__all__ = ["TABLE_COLUMNS", "TakePlan", "Planning", "DUEntry", "plan_takes", "read_du_table",
           "compile_pattern", "kind_from_name", "is_command_log", "command_logs",
           "check_response"]
