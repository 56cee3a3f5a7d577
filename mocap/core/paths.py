"""Where a command may write: never into a raw session, never onto its own inputs.

Every command that writes (``run``, ``audit``, ``calibrate``, ``discrepancy``, ``design``,
``import``, ``export``, ``simulate``, ``schedule``, ``batch``) and the library's
``run_session`` pass their output path through :func:`check_output_path` before writing
anything. Paths are compared after resolving symbolic links, so a link cannot smuggle an output
into a session, and the output need not exist yet.

The rules, for an output path ``out`` (a folder or a file):

- ``out`` is not a session the command reads, does not lie inside one, and does not contain one
  (an output folder that holds the session would mix results with raw data, and a later
  ``--force`` or clean-up of the outputs would take the session with it);
- ``out`` is not, and does not contain, an input file the command reads (``import``'s vendor
  files, ``design``'s plan file);
- ``out`` is not, and does not lie inside, any folder that holds a ``session.toml``: another
  session is raw data too;
- with ``kind`` given, ``out`` is not an existing file where a folder is written (nor the
  reverse), and no part of its path is an existing file.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterable

from mocap.core.session import MANIFEST, SessionError


class OutputPathError(SessionError):
    """An output path that would write into a raw session or onto an input file; the message
    names the option, both paths and what to do."""


def _resolved(path: str | os.PathLike) -> Path:
    return Path(path).expanduser().resolve()


def _within(inner: Path, outer: Path) -> bool:
    """``inner`` is ``outer`` or lies below it (both resolved)."""
    return inner == outer or inner.is_relative_to(outer)


def check_output_path(out: str | os.PathLike, *, sessions: Iterable[str | os.PathLike] = (),
                      inputs: Iterable[str | os.PathLike] = (), option: str = "--out",
                      kind: str | None = None) -> Path:
    """Refuse an output path under a raw session or onto an input; return it resolved.

    Parameters
    ----------
    out : the folder or file the command will write (it need not exist).
    sessions : session folders the command reads.
    inputs : input files the command reads.
    option : how messages name ``out``: the command-line option or argument, or the Python
        argument (``out_dir``) when raised from the library.
    kind : "folder" or "file", what the command writes at ``out`` (None: not checked).

    Raises
    ------
    OutputPathError
        Naming ``option``, ``out`` and the session or input it collides with.
    """
    target = _resolved(out)
    if kind == "folder" and target.exists() and not target.is_dir():
        raise OutputPathError(f"{option} {out}: is a file, not a folder; give a folder (a new "
                              "one, or an earlier output folder to update)")
    if kind == "file" and target.is_dir():
        raise OutputPathError(f"{option} {out}: is a folder; give the name of the file to write")
    for parent in target.parents:
        if parent.exists():
            if not parent.is_dir():
                raise OutputPathError(f"{option} {out}: {parent} is a file, not a folder; "
                                      "choose a path whose folders are folders")
            break
    for s in sessions:
        session = _resolved(s)
        if target == session:
            why = "is the session folder"
        elif _within(target, session):
            why = f"is inside the session folder {session}"
        elif _within(session, target):
            why = f"contains the session folder {session}"
        else:
            continue
        raise OutputPathError(
            f"{option} {out}: {why}; outputs never go into a raw session: choose a folder "
            "outside it")
    for f in inputs:
        source = _resolved(f)
        if _within(source, target):
            why = "is" if source == target else "contains"
            raise OutputPathError(
                f"{option} {out}: {why} the input file {source}; choose an output path that "
                "holds none of the inputs")
    for folder in (target, *target.parents):
        if (folder / MANIFEST).is_file():
            raise OutputPathError(
                f"{option} {out}: {'is' if folder == target else 'is inside'} the session "
                f"folder {folder} (it holds {MANIFEST}); outputs never go into a raw session: "
                "choose a folder outside it")
    return target


def session_dir_of(source: str | os.PathLike) -> Path | None:
    """The session folder behind ``source``: itself when it holds ``session.toml``, the
    session a ``mocap run`` output folder records in ``summary.json``, else None."""
    source = Path(source)
    if (source / MANIFEST).is_file():
        return source
    summary = source / "summary.json"
    if summary.is_file():
        try:
            recorded = json.loads(summary.read_text(encoding="utf-8"))["session"]["dir"]
        except (OSError, ValueError, KeyError, TypeError):
            return None
        return Path(recorded) if isinstance(recorded, str) and recorded else None
    return None
