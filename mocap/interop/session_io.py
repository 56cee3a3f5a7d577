"""Vendor files to a labeled session (docs/format.md), and a run's (or a 3D session's) takes to C3D.

Import: each file becomes a 3D take (``takes/<name>.csv``) of a new session; markers keep their
labels (the union over files; a marker a file lacks is a gap there, noted); all files must share
one frame rate. What each file is (kind, DU, trial, plan, command log) comes from a take table, a
name pattern or the file's name (:mod:`mocap.interop.take_table`). Commands come from command
logs (CSV ``time_s,du,command``: named in the table, matched by name in a folder, or one given for
a single file) or else from C3D analog channels labeled ``DU<n>`` (as ``export`` writes them),
resampled to the point rate; they must be integers 0..255 (not rounded silently). DUs are named
from a DU table or numbered. Every guess and repair is listed in ``import_report.json`` beside
``session.toml``; when kinds or commands are missing the manifest says what to complete.
Nothing is overwritten: the output folder must not hold a session yet.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
from pathlib import Path

import numpy as np
import pandas as pd

from mocap.core.atomic import write_csv, write_text
from mocap.interop.c3d_file import read_c3d, write_c3d
from mocap.interop.marker_data import ImportError_, MarkerData, unique_names
from mocap.interop.take_table import DUEntry, Planning, check_response, plan_takes, read_du_table
from mocap.interop.vendor_text import sniff

DU_CHANNEL = re.compile(r"^\s*du\s*0*(\d+)\s*$", re.IGNORECASE)


def read_any(path: str | os.PathLike, fps: float | None = None) -> MarkerData:
    """Read a vendor file by its type (:func:`sniff`); ImportError_ naming the file and the place
    when it is malformed, or when it holds no frame or no marker."""
    reader = sniff(path)
    data = reader(path) if reader is read_c3d else reader(path, fps=fps)
    if data.X.shape[0] == 0 or data.X.shape[1] == 0:
        raise ImportError_(f"{path}: {data.X.shape[0]} frames of {data.X.shape[1]} markers: "
                           "nothing to import")
    return data


_CSV_UNSAFE = re.compile(r'[,"\r\n\x00-\x1f\x7f]')


def _csv_safe(names: list[str], where: str, notes: list[str]) -> list[str]:
    """Marker names a take file can hold (no comma, quote or control character), noted."""
    out = []
    for n in names:
        safe = _CSV_UNSAFE.sub("_", n).strip() or "unnamed"
        if safe != n:
            notes.append(f"{where}: marker name {n!r} written as {safe!r} (a take file cannot hold "
                         "commas, quotes or control characters in a name)")
        out.append(safe)
    return out


def _toml_string(text: str) -> str:
    """``text`` as a TOML basic string (quotes, backslashes and control characters escaped)."""
    def escape(m: re.Match) -> str:
        c = m.group(0)
        return {'"': '\\"', "\\": "\\\\"}.get(c, f"\\u{ord(c):04X}")

    return '"' + re.sub(r'["\\\x00-\x1f\x7f]', escape, text) + '"'


def _command_rows(values: np.ndarray, fps: float, du: int, where: str) -> pd.DataFrame:
    v = np.asarray(values, float)
    if not np.all(np.isfinite(v)) or np.any(np.abs(v - np.round(v)) > 1e-6) or v.min() < 0 or v.max() > 255:
        raise ImportError_(f"{where}: commands of DU {du} must be integers 0..255 "
                           f"(got {v.min():g}..{v.max():g}, non-integers present: "
                           f"{bool(np.any(np.abs(v - np.round(v)) > 1e-6))})")
    v = np.round(v).astype(np.int64)
    change = np.r_[0, np.flatnonzero(np.diff(v) != 0) + 1]
    return pd.DataFrame({"time_s": np.round(change / fps, 9), "du": du, "command": v[change]})


def _read_command_csv(path: Path) -> pd.DataFrame:
    """A command file given with ``--commands`` (time_s,du,command), checked row by row: time_s
    finite >= 0, du an integer, command an integer 0..255; errors name the file and line."""
    try:
        c = pd.read_csv(path, dtype=str, keep_default_na=False)
    except (OSError, ValueError, UnicodeDecodeError, pd.errors.ParserError) as e:
        raise ImportError_(f"{path}: not a readable CSV file ({e})") from None
    missing = [k for k in ("time_s", "du", "command") if k not in c.columns]
    if missing:
        raise ImportError_(f"{path} line 1: expected columns time_s,du,command; missing {missing}")
    out = {}
    for col, lo, hi, integer in (("time_s", 0.0, np.inf, False), ("du", -np.inf, np.inf, True),
                                 ("command", 0, 255, True)):
        values = pd.to_numeric(c[col].str.strip(), errors="coerce").to_numpy(float)
        bad = ~np.isfinite(values) | (values < lo) | (values > hi)
        if integer:
            bad |= values != np.round(values)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ImportError_(f"{path} line {i + 2}: {col} {c[col].iloc[i]!r} is not "
                               + ("an integer command 0..255" if col == "command" else
                                  "an integer DU id" if col == "du" else "a time in s >= 0"))
        out[col] = values.astype(np.int64) if integer else values
    return pd.DataFrame(out)


def _analog_commands(data: MarkerData) -> dict[int, np.ndarray]:
    out = {}
    n = data.X.shape[0]
    for label, (values, rate, _unit) in data.analogs.items():
        m = DU_CHANNEL.match(label)
        if not m:
            continue
        ratio = rate / data.fps
        if abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
            raise ImportError_(f"{data.source}: analog channel {label!r} at {rate} Hz is not a "
                               f"whole multiple of the point rate {data.fps} Hz")
        out[int(m.group(1))] = np.asarray(values)[:: int(round(ratio))][:n]
    return out


def _safe_name(stem: str, taken: set) -> str:
    name = re.sub(r"[^A-Za-z0-9_-]+", "_", stem).strip("_") or "take"
    base, k = name, 2
    while name in taken:
        name = f"{base}_{k}"
        k += 1
    taken.add(name)
    return name


def _plan(files: list[Path], commands, takes, patterns) -> Planning:
    """The takes to write (:mod:`mocap.interop.take_table`); ``commands`` a folder of logs
    matched by name, or one log for a single file."""
    single = None
    folder = None
    if commands is not None:
        c = Path(commands)
        folder, single = (c, None) if c.is_dir() else (None, c)
    if isinstance(patterns, str):
        patterns = [patterns]
    planning = plan_takes(files, table=takes, patterns=patterns or (), commands_dir=folder)
    if single is not None:
        if len(planning.takes) != 1:
            raise ImportError_(f"--commands {single}: one command log applies to a single imported "
                               "file; for several, give a folder of logs named like the takes "
                               "(--commands DIR) or name each in a take table (--takes)")
        planning = dataclasses.replace(planning, takes=(dataclasses.replace(
            planning.takes[0], commands=single),))
    return planning


def import_files(files, out_dir: str | os.PathLike, *, commands: str | os.PathLike | None = None,
                 fps: float | None = None, takes: str | os.PathLike | None = None,
                 patterns=(), dus: str | os.PathLike | None = None) -> dict:
    """Write a labeled session from vendor files; return the report (notes, guesses, what is
    missing).

    files : the takes' files (C3D, Motive CSV, QTM TSV, Vicon CSV; command logs among them are
    taken as logs); commands : a folder of command logs matched by name, or one log for a single
    file; takes : a take table (CSV) saying what each file is; patterns : name patterns
    (``"du{du}_t{trial}"``) used without a table; dus : a DU table (CSV ``du,name[,feedback]``).
    Without a table or a pattern, ``rest``, ``wand`` and ``ground`` takes are recognised by name
    and every other file is a ``motion`` take. ImportError_ names the file or line at fault.
    """
    files = [Path(f) for f in files]
    out = Path(out_dir)
    if (out / "session.toml").exists():
        raise ImportError_(f"{out}: already holds a session; choose a new folder")
    planning = _plan(files, commands, takes, patterns)
    guessed = list(planning.guessed)
    notes: list[str] = list(planning.notes)
    du_table = read_du_table(dus, notes) if dus is not None else None
    plans = list(planning.takes)
    datas = [read_any(t.source, fps) for t in plans]
    for k, (t, d) in enumerate(zip(plans, datas)):
        safe = _csv_safe(d.names, str(t.source), notes)
        if safe != d.names:
            datas[k] = dataclasses.replace(d, names=unique_names(safe, str(t.source), notes))
    rates = {d.fps for d in datas}
    if len(rates) > 1:
        by_rate = {}
        for t, d in zip(plans, datas):
            by_rate.setdefault(d.fps, t.source)
        raise ImportError_("frame rates differ between files ("
                           + ", ".join(f"{r:g} Hz: {f}" for r, f in sorted(by_rate.items()))
                           + "); a session has one")
    rate = rates.pop()
    names: list[str] = []
    for d in datas:
        names += [n for n in d.names if n not in names]
    notes = [n for d in datas for n in d.notes] + notes
    # every take's commands and checks first: an error leaves nothing written
    commands_of = []
    for k, (t, d) in enumerate(zip(plans, datas)):
        rows = None
        analog = _analog_commands(d)
        if t.commands is not None:
            rows = _read_command_csv(t.commands)
            if analog:
                notes.append(f"{t.source}: analog channels DU<n> ignored; commands from {t.commands}")
        elif analog:
            rows = pd.concat([_command_rows(v, rate, du, f"{t.source} analog DU{du}")
                              for du, v in analog.items()], ignore_index=True)
        driven = set() if rows is None else {int(u) for u in rows.loc[rows["command"] > 0, "du"]}
        plans[k], guess = check_response(t, driven)
        if guess:
            guessed.append(guess)
        commands_of.append(rows)
    taken: set = set()
    entries, dus_used = [], set()
    for t, d, rows in zip(plans, datas, commands_of):
        f = t.source
        stem = _safe_name(t.name, taken)
        missing = [n for n in names if n not in d.names]
        if missing:
            notes.append(f"{f}: markers {missing} absent from this file: gaps in take {t.name!r}")
        n_frames = d.X.shape[0]
        idx = {n: i for i, n in enumerate(d.names)}
        X = np.full((n_frames, len(names), 3), np.nan)
        for j, n in enumerate(names):
            if n in idx:
                X[:, j] = d.X[:, idx[n]]
        df = pd.DataFrame({"frame": np.repeat(np.arange(n_frames), len(names)),
                           "marker": np.tile(np.asarray(names, dtype=object), n_frames),
                           "x": X[..., 0].ravel(), "y": X[..., 1].ravel(), "z": X[..., 2].ravel()})
        write_csv(df, out / "takes" / f"{stem}.csv")
        entry = {"name": t.name, "kind": t.kind, "file": f"takes/{stem}.csv", "source": str(f)}
        entry.update({k: v for k, v in (("du", t.du), ("trial", t.trial), ("plan", t.plan),
                                        ("commands_offset_s", t.commands_offset_s)) if v is not None})
        if rows is not None:
            write_csv(rows, out / "takes" / f"{stem}_commands.csv",
                      decimals=None if t.commands is not None else 9)
            entry["commands"] = f"takes/{stem}_commands.csv"
            entry["commands_source"] = str(t.commands) if t.commands is not None else "analog DU<n>"
            dus_used |= {int(u) for u in rows["du"].unique()}
        if t.du is not None:
            dus_used.add(t.du)
        entries.append(entry)
    du_entries = _du_entries(dus_used, du_table, dus, guessed, notes)
    assumed = [e["name"] for e in entries if any(g.startswith(f"take {e['name']!r}: kind 'motion'")
                                                   for g in guessed)]
    todo = []
    if assumed:
        todo.append(f"set each take's kind: {len(assumed)} take(s) assumed 'motion' (rest, "
                    "response with du and trial, motion), or import again with --takes or "
                    "--pattern")
    if not dus_used:
        todo.append("no commands found: add command files (time_s,du,command) and [[dus]] tables, "
                    "or import again with --commands DIR")
    lines = ['# written by "mocap import"; what it guessed is listed in import_report.json']
    if todo:
        lines += ['# complete it before "mocap run":'] + [f"# - {x}" for x in todo]
    lines += ['schema = "mocap-session/1"', f"name = {_toml_string(out.name)}",
              f"fps = {float(rate)!r}", ""]
    for du in du_entries:
        lines += ["[[dus]]", f"id = {du.id}", f"name = {_toml_string(du.name)}",
                  f"feedback = {'true' if du.feedback else 'false'}", ""]
    for e in entries:
        lines += ["[[takes]]", f"name = {_toml_string(e['name'])}", f'kind = "{e["kind"]}"',
                  f'file = "{e["file"]}"']
        if "commands" in e:
            lines.append(f'commands = "{e["commands"]}"')
        for key in ("du", "trial"):
            if key in e:
                lines.append(f"{key} = {e[key]}")
        if "plan" in e:
            lines.append(f"plan = {_toml_string(e['plan'])}")
        if "commands_offset_s" in e:
            lines.append(f"commands_offset_s = {float(e['commands_offset_s'])!r}")
        lines.append("")
    write_text(out / "session.toml", "\n".join(lines))
    kinds: dict[str, int] = {}
    for e in entries:
        kinds[e["kind"]] = kinds.get(e["kind"], 0) + 1
    report = {"session": str(out), "fps": rate, "markers": names, "takes": entries,
              "kinds": kinds, "dus": sorted(dus_used), "guessed": guessed, "notes": notes,
              "to_complete": todo}
    write_text(out / "import_report.json", json.dumps(report, indent=2))
    return report


def _du_entries(used: set[int], table, table_path, guessed: list[str], notes: list[str]
                ) -> list[DUEntry]:
    """The manifest's DUs: those the commands and takes use, named from the DU table when given
    (else numbered, a guess); the table's other DUs are declared too (noted)."""
    table = table or {}
    unnamed = sorted(used - set(table))
    if unnamed:
        where = f"not in {table_path}" if table_path is not None else "no DU table (--dus)"
        guessed.append(f"DUs {unnamed}: {where}; named 'DU <n>', feedback false")
    extra = sorted(set(table) - used)
    if extra:
        notes.append(f"{table_path}: DUs {extra} drive no imported take; declared all the same")
    return [table.get(d, DUEntry(d, f"DU {d}")) for d in sorted(used | set(table))]


def export_c3d(source: str | os.PathLike, dest: str | os.PathLike, takes=None) -> list[Path]:
    """Write takes as C3D: ``source`` is a 'mocap run' output folder or a labeled 3D session.

    ``dest`` is a .c3d file (one take) or a folder (one file per take). The commands of every
    DU of the session become analog channels ``DU<nn>`` at the point rate (0 for idle DUs). A
    session with a single DU gets a single channel, which ezc3d stores as scalar parameters: the
    ``c3d`` package then cannot read its analog data (ezc3d and the vendors' tools can).
    """
    from mocap.core.session import command_matrix, load_session

    source = Path(source)
    if (source / "summary.json").is_file():
        summary = json.loads((source / "summary.json").read_text())
        session = load_session(summary["session"]["dir"])
        traj = {p.stem: p for p in sorted((source / "trajectories").glob("*.parquet"))}
    elif (source / "session.toml").is_file():
        session = load_session(source)
        if session.dimension != "3d":
            raise ImportError_(f"{source}: a raw session has no 3D trajectories yet: run "
                               f"'mocap run {source} --out OUT' and export OUT")
        traj = {t.name: None for t in session.takes}
    else:
        raise ImportError_(f"{source}: neither a 'mocap run' output (summary.json) nor a session")
    names = list(takes) if takes else list(traj)
    unknown = [t for t in names if t not in traj]
    if unknown:
        raise ImportError_(f"{source}: no trajectories for takes {unknown} (have {list(traj)})")
    dest = Path(dest)
    single = dest.suffix.lower() == ".c3d"
    if single and len(names) != 1:
        raise ImportError_(f"{dest}: one .c3d file holds one take; give a folder for {len(names)} takes")
    written = []
    for name in names:
        df = pd.read_parquet(traj[name]) if traj[name] is not None else session.read_take(name)
        markers = list(dict.fromkeys(df["marker"]))
        n_frames = int(df["frame"].max()) + 1
        X = np.full((n_frames, len(markers), 3), np.nan)
        m = pd.Categorical(df["marker"], categories=markers).codes
        X[df["frame"].to_numpy(), m] = df[["x", "y", "z"]].to_numpy(float)
        data = MarkerData(markers, X, session.fps)
        commands = None
        take = session.take(name)
        if take.commands is not None:
            rows = session.read_commands(name)
            # every DU of the session (idle ones hold 0): explicit, and never a single channel,
            # which ezc3d writes as a scalar parameter that the c3d package cannot read
            dus = sorted(set(session.du_ids) | set(int(d) for d in rows["du"]))
            mat = command_matrix(rows, session.fps, n_frames, dus)
            commands = {f"DU{d:02d}": mat[:, i].astype(float) for i, d in enumerate(dus)}
        path = dest if single else dest / f"{name}.c3d"
        written.append(write_c3d(path, data, commands))
    return written
