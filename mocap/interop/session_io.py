"""Vendor files to a labeled FORMAT.md session, and a run's (or a 3D session's) takes to C3D.

Import: each file becomes a 3D take (``takes/<stem>.csv``) of a new session; markers keep their
labels (the union over files; a marker a file lacks is a gap there, noted); all files must share
one frame rate. Commands come from C3D analog channels labeled ``DU<n>`` (as ``export`` writes
them), resampled to the point rate, or from a command CSV given for a single file; they must be
integers 0..255 (not rounded silently). The manifest is written for the user to complete: every
take is a ``motion`` take until its kind is set, DUs are named ``DU <n>``; the report says what is
missing. Nothing is overwritten: the output folder must not hold a session yet.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
from pathlib import Path

import numpy as np
import pandas as pd

from mocap.atomic import write_csv, write_text
from mocap.interop.c3d_file import read_c3d, write_c3d
from mocap.interop.marker_data import ImportError_, MarkerData, unique_names
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


def import_files(files, out_dir: str | os.PathLike, *, commands: str | os.PathLike | None = None,
                 fps: float | None = None) -> dict:
    """Write a labeled session from vendor files; return the report (notes, what is missing)."""
    files = [Path(f) for f in files]
    out = Path(out_dir)
    if (out / "session.toml").exists():
        raise ImportError_(f"{out}: already holds a session; choose a new folder")
    if commands is not None and len(files) != 1:
        raise ImportError_("--commands applies to a single imported file; import files one by one")
    command_table = None if commands is None else _read_command_csv(Path(commands))
    datas = [read_any(f, fps) for f in files]
    notes: list[str] = []
    for k, (f, d) in enumerate(zip(files, datas)):
        safe = _csv_safe(d.names, str(f), notes)
        if safe != d.names:
            datas[k] = dataclasses.replace(d, names=unique_names(safe, str(f), notes))
    rates = {d.fps for d in datas}
    if len(rates) > 1:
        raise ImportError_(f"frame rates differ between files ({sorted(rates)} Hz); a session has one")
    rate = rates.pop()
    names: list[str] = []
    for d in datas:
        names += [n for n in d.names if n not in names]
    notes = [n for d in datas for n in d.notes] + notes
    taken: set = set()
    takes, dus = [], set()
    for f, d in zip(files, datas):
        name = _safe_name(f.stem, taken)
        missing = [n for n in names if n not in d.names]
        if missing:
            notes.append(f"{f}: markers {missing} absent from this file: gaps in take {name!r}")
        n_frames = d.X.shape[0]
        idx = {n: i for i, n in enumerate(d.names)}
        X = np.full((n_frames, len(names), 3), np.nan)
        for j, n in enumerate(names):
            if n in idx:
                X[:, j] = d.X[:, idx[n]]
        df = pd.DataFrame({"frame": np.repeat(np.arange(n_frames), len(names)),
                           "marker": np.tile(np.asarray(names, dtype=object), n_frames),
                           "x": X[..., 0].ravel(), "y": X[..., 1].ravel(), "z": X[..., 2].ravel()})
        write_csv(df, out / "takes" / f"{name}.csv")
        entry = {"name": name, "file": f"takes/{name}.csv", "source": str(f)}
        cmd = {}
        if commands is not None:
            c = command_table
            write_csv(c, out / "takes" / f"{name}_commands.csv")
            cmd = {int(du): None for du in c["du"].unique()}
        else:
            for du, values in _analog_commands(d).items():
                cmd[du] = _command_rows(values, rate, du, f"{f} analog DU{du}")
            if cmd:
                write_csv(pd.concat(cmd.values(), ignore_index=True), out / "takes" / f"{name}_commands.csv",
                          decimals=9)
        if cmd:
            entry["commands"] = f"takes/{name}_commands.csv"
            dus |= set(cmd)
        takes.append(entry)
    lines = ['# written by "mocap import": complete it before "mocap run"',
             "# - set each take's kind: rest (the face still), response (one DU's trapezoid: add du",
             "#   and trial), motion (anything else); a session needs a rest take to find markers",
             "# - name your DUs below and say which have position feedback",
             'schema = "mocap-session/1"', f"name = {_toml_string(out.name)}", f"fps = {float(rate)!r}", ""]
    for du in sorted(dus):
        lines += ["[[dus]]", f"id = {du}", f'name = "DU {du}"', "feedback = false", ""]
    for t in takes:
        lines += ["[[takes]]", f'name = "{t["name"]}"', 'kind = "motion"', f'file = "{t["file"]}"']
        if "commands" in t:
            lines.append(f'commands = "{t["commands"]}"')
        lines.append("")
    write_text(out / "session.toml", "\n".join(lines))
    todo = ["set each take's kind (all are 'motion' now)"]
    if not dus:
        todo.append("no commands found: add command files (time_s,du,command) and [[dus]] tables")
    else:
        todo.append(f"name DUs {sorted(dus)} and set their feedback")
    report = {"session": str(out), "fps": rate, "markers": names, "takes": takes,
              "dus": sorted(dus), "notes": notes, "to_complete": todo}
    write_text(out / "import_report.json", json.dumps(report, indent=2))
    return report


def export_c3d(source: str | os.PathLike, dest: str | os.PathLike, takes=None) -> list[Path]:
    """Write takes as C3D: ``source`` is a 'mocap run' output folder or a labeled 3D session.

    ``dest`` is a .c3d file (one take) or a folder (one file per take). The commands of every
    DU of the session become analog channels ``DU<nn>`` at the point rate (0 for idle DUs). A
    session with a single DU gets a single channel, which ezc3d stores as scalar parameters: the
    ``c3d`` package then cannot read its analog data (ezc3d and the vendors' tools can).
    """
    from mocap.session import command_matrix, load_session

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
