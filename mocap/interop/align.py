"""`mocap import --align-commands`: propose each imported take's ``commands_offset_s``.

A take's offset is the capture time of its command file's time 0 (a row acts at capture time
``commands_offset_s + time_s``). It is read, per take:

- from a sync channel, when the take's source file (a C3D) has an analog channel of the given
  name: the channel's first edge marks the command log's time 0
  (:func:`mocap.reconstruction.align.sync_edge`). This is the clock offset alone;
- otherwise from the motion against the commands (:func:`mocap.reconstruction.align.motion_lags`):
  the offset then absorbs the face's own dead time, which the discrepancy workflow can no longer
  find once the offset is applied. The report says so.

Takes of one session logged by one clock share an offset: offsets that differ by more than a
frame are flagged. The offsets are written into session.toml only when asked (``apply``);
otherwise they are reported. Nothing else in the session changes.
"""

from __future__ import annotations

import json
import math
import re
import tomllib
from pathlib import Path

import numpy as np

from mocap.core.atomic import write_text
from mocap.reconstruction.align import motion_lags, sync_edge

__all__ = ["DEAD_TIME_WARNING", "align_session", "alignment_lines", "update_import_report",
           "write_offsets"]

DEAD_TIME_WARNING = (
    "offsets read from the motion include the face's own dead time (the delay between a command "
    "and the motion it causes): the two cannot be separated from the motion alone, and once "
    "such an offset is applied 'mocap discrepancy' cannot find a dead time. A sync channel "
    "(--sync-channel) measures the clock offset alone.")


def _analog(source: Path, channel: str):
    """(values, rate) of ``channel`` (case-insensitive) in a C3D file, or None."""
    if source.suffix.lower() != ".c3d" or not source.is_file():
        return None
    from mocap.interop.c3d_file import read_c3d

    for label, (values, rate, _unit) in read_c3d(source).analogs.items():
        if label.strip().lower() == channel.strip().lower():
            return np.asarray(values, float), float(rate)
    return None


def align_session(session_dir, *, sources: dict | None = None, sync_channel: str | None = None,
                  max_lag_s: float = 2.0) -> dict:
    """Propose ``commands_offset_s`` for every take of a labeled session that has commands.

    Parameters
    ----------
    session_dir : the session folder (session.toml).
    sources : take name -> the vendor file it was imported from (for the sync channel).
    sync_channel : the analog channel whose first edge marks each command log's time 0.
    max_lag_s : offsets searched within this many seconds of the onsets' difference (s).

    Returns
    -------
    A JSON-ready dict: ``takes`` (name -> offset_s, uncertainty_s, method, current_offset_s,
    note), ``methods``, ``spread_s`` (largest minus smallest offset), ``disagree`` (spread over
    a frame), ``fps`` and ``warnings`` (the dead-time warning whenever an offset came from the
    motion; the disagreement).
    """
    from mocap.reconstruction.labeled_input import dense_from_3d, marker_names_3d
    from mocap.core.session import load_session

    session = load_session(session_dir)
    sources = {k: Path(v) for k, v in (sources or {}).items()}
    commanded = [t for t in session.takes if t.commands is not None]
    takes: dict[str, dict] = {}
    from_motion = {}
    notes = []
    for t in commanded:
        sync = _analog(sources[t.name], sync_channel) if (sync_channel and t.name in sources) else None
        if sync is not None:
            est = sync_edge(*sync)
            if math.isfinite(est.lag_s):
                takes[t.name] = {"offset_s": est.lag_s, "uncertainty_s": est.uncertainty_s,
                                 "method": f"sync channel {sync_channel!r}",
                                 "current_offset_s": t.commands_offset_s, "note": ""}
                continue
            notes.append(f"take {t.name!r}: sync channel {sync_channel!r}: {est.note}; read "
                         "from the motion instead")
        elif sync_channel:
            notes.append(f"take {t.name!r}: no channel {sync_channel!r} in its source file; read "
                         "from the motion instead")
        from_motion[t.name] = t
    if from_motion:
        frames = {}
        for name in from_motion:
            df = session.read_take(name)
            X = dense_from_3d(df, marker_names_3d([df], session.marker_template)).X
            frames[name] = (X, session.read_commands(name))  # capture time: current offset applied
        lags = motion_lags(frames, session.fps, max_lag_s=max_lag_s)
        for name, t in from_motion.items():
            e = lags.takes[name]
            takes[name] = {"offset_s": t.commands_offset_s + e.lag_s if math.isfinite(e.lag_s) else None,
                           "uncertainty_s": e.uncertainty_s if math.isfinite(e.uncertainty_s) else None,
                           "method": "motion", "current_offset_s": t.commands_offset_s,
                           "note": e.note}
    values = [v["offset_s"] for v in takes.values() if v["offset_s"] is not None]
    spread = float(max(values) - min(values)) if values else None
    frame = 1.0 / session.fps
    disagree = spread is not None and spread > frame + 1e-9
    warnings = list(notes)
    if disagree:
        lo = min(takes, key=lambda k: takes[k]["offset_s"] if takes[k]["offset_s"] is not None else np.inf)
        hi = max(takes, key=lambda k: takes[k]["offset_s"] if takes[k]["offset_s"] is not None else -np.inf)
        warnings.append(f"the takes' offsets disagree by {spread:.4f} s, more than a frame "
                        f"({frame:.4f} s): from {takes[lo]['offset_s']:+.4f} s ({lo}) to "
                        f"{takes[hi]['offset_s']:+.4f} s ({hi}). One logger on one clock gives "
                        "one offset: check for a restarted logger or drifting clocks before "
                        "applying them")
    if from_motion:
        warnings.append(DEAD_TIME_WARNING)
    return {"fps": session.fps, "sync_channel": sync_channel, "takes": takes,
            "spread_s": spread, "disagree": disagree, "warnings": warnings}


_TABLE = re.compile(r"^\s*\[")
_OFFSET = re.compile(r"^\s*commands_offset_s\s*=")


def write_offsets(session_dir, offsets: dict) -> Path:
    """Write ``commands_offset_s`` into session.toml for the takes named in ``offsets`` (name
    -> seconds), replacing any already there; every other line is kept as it is. The result is
    read back and checked before it replaces the file (atomically)."""
    path = Path(session_dir) / "session.toml"
    lines = path.read_text(encoding="utf-8").splitlines()
    blocks: list[tuple[int, int]] = []  # [[takes]] tables: (header line, end line)
    for i, line in enumerate(lines):
        if _TABLE.match(line):
            if blocks and blocks[-1][1] < 0:
                blocks[-1] = (blocks[-1][0], i)
            if line.strip() == "[[takes]]":
                blocks.append((i, -1))
    if blocks and blocks[-1][1] < 0:
        blocks[-1] = (blocks[-1][0], len(lines))
    doc = tomllib.loads("\n".join(lines))
    names = [t.get("name") for t in doc.get("takes", [])]
    if len(names) != len(blocks):
        raise ValueError(f"{path}: cannot place commands_offset_s (the [[takes]] tables are not "
                         "written one per header); add them by hand")
    for (start, end), name in reversed(list(zip(blocks, names))):
        if name not in offsets:
            continue
        kept = [line for line in lines[start + 1:end] if not _OFFSET.match(line)]
        filled = [j for j, line in enumerate(kept)
                  if line.strip() and not line.lstrip().startswith("#")]
        kept.insert(filled[-1] + 1 if filled else 0,
                    f"commands_offset_s = {float(offsets[name])!r}")
        lines[start + 1:end] = kept
    text = "\n".join(lines) + "\n"
    check = {t.get("name"): t.get("commands_offset_s") for t in tomllib.loads(text).get("takes", [])}
    for name, value in offsets.items():
        if check.get(name) != float(value):
            raise ValueError(f"{path}: commands_offset_s of take {name!r} did not read back")
    write_text(path, text)
    return path


def alignment_lines(report: dict, applied: bool) -> list[str]:
    """The report as lines to print."""
    out = ["command alignment (commands_offset_s: the capture time of each command file's "
           "time 0):"]
    for name, t in report["takes"].items():
        if t["offset_s"] is None:
            out.append(f"  {name}: not read ({t['note']})")
            continue
        out.append(f"  {name}: {t['offset_s']:+.4f} s +- {t['uncertainty_s']:.4f} s "
                   f"(from the {t['method']})" + (f"; {t['note']}" if t["note"] else ""))
    for w in report["warnings"]:
        out.append(f"  warning: {w}")
    out.append("  written to session.toml" if applied else
               "  not written: '--align-commands apply' writes them into session.toml")
    return out


def update_import_report(session_dir, report: dict, applied: bool) -> None:
    """Add the alignment to the session's import_report.json (when there is one)."""
    path = Path(session_dir) / "import_report.json"
    if not path.is_file():
        return
    doc = json.loads(path.read_text(encoding="utf-8"))
    doc["alignment"] = {**report, "applied": applied}
    write_text(path, json.dumps(doc, indent=2, default=float))
