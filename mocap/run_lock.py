"""One run at a time per output folder: a lock file created atomically.

``OUT_DIR/.facemocap/lock`` is created with ``O_CREAT | O_EXCL`` (atomic on local file systems)
and holds the owner's pid, host, process start time and start date as JSON. A second run into
the folder finds it and is refused with :class:`OutputInUse`, naming the owner. A lock whose
owner is gone (same host, the pid no longer runs, or runs a process started at another time: a
killed run) is stale: it is taken over, and the note says so. Takeovers are serialised by a
second O_EXCL file (``lock.takeover``) so two runs cannot both take over the same stale lock.
A lock from another host cannot be checked: it is refused, and the message says how to remove it.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import time
from pathlib import Path


class OutputInUse(RuntimeError):
    """Another run is writing into this output folder."""


def _start_time(pid: int) -> str | None:
    """The process's start time (clock ticks since boot, Linux), None where unknown."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat.rsplit(")", 1)[1].split()[19]


def _alive(pid: int, started: str | None) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # it runs, under another user
        return True
    now = _start_time(pid)
    return started is None or now is None or now == started  # a reused pid is another process


def _create(path: Path, owner: dict) -> bool:
    try:
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        return False
    with os.fdopen(fd, "w") as f:
        json.dump(owner, f)
    return True


def _read(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError):
        return {}  # being written, or damaged


class RunLock:
    """Context manager holding ``folder/.facemocap/lock``; ``note`` says if a stale lock was
    taken over."""

    def __init__(self, folder: str | os.PathLike):
        self.dir = Path(folder) / ".facemocap"
        self.path = self.dir / "lock"
        self.note: str | None = None
        self._owner = {"pid": os.getpid(), "host": socket.gethostname(),
                       "started": _start_time(os.getpid()),
                       "date": time.strftime("%Y-%m-%dT%H:%M:%S%z")}

    def __enter__(self) -> "RunLock":
        self.dir.mkdir(parents=True, exist_ok=True)
        if _create(self.path, self._owner):
            return self
        held = _read(self.path)
        if held is None and _create(self.path, self._owner):  # released meanwhile
            return self
        if not self._stale(held or {}):
            raise OutputInUse(self._refusal(held or {}))
        guard = self.path.with_name("lock.takeover")
        if not _create(guard, self._owner):
            raise OutputInUse(f"{self.path.parent.parent}: another run is taking over its stale "
                              f"lock; if none is, remove {guard}")
        try:
            again = _read(self.path)
            if again != held:  # changed under us: someone else's lock now
                raise OutputInUse(self._refusal(again or {}))
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()
            if not _create(self.path, self._owner):
                raise OutputInUse(self._refusal(_read(self.path) or {}))
        finally:
            guard.unlink()
        self.note = (f"took over a stale lock of {self.path.parent.parent} (pid {held.get('pid')} "
                     f"on {held.get('host')}, started {held.get('date')}, no longer runs)")
        return self

    def _stale(self, held: dict) -> bool:
        if held.get("host") != self._owner["host"] or not isinstance(held.get("pid"), int):
            return False
        return not _alive(held["pid"], held.get("started"))

    def _refusal(self, held: dict) -> str:
        who = (f"pid {held.get('pid')} on {held.get('host')} since {held.get('date')}"
               if held else "a run whose lock is being written")
        extra = ("" if held.get("host") in (None, self._owner["host"]) else
                 f"; it cannot be checked from here: if that run is gone, remove {self.path}")
        return (f"{self.path.parent.parent} is in use by another run ({who}){extra}. "
                "Wait for it, or choose another output folder.")

    def __exit__(self, *exc) -> None:
        if _read(self.path) == self._owner:
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()
