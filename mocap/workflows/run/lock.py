"""One run at a time per output folder.

``OUT_DIR/.facemocap/lock`` is held with an operating-system file lock (``filelock``: ``flock``
on POSIX), so the lock is released by the operating system when its run ends in any way,
killed runs included: there are no stale locks to detect. Beside it, ``lock.owner`` names the
holder (pid, host, start date) for the refusal message; it is removed when the run ends
normally, so one found on entry means the previous run into the folder was killed (``note``
says so; its finished stages are kept, see :mod:`mocap.workflows.run.cache`).

Network file systems may not honour ``flock`` across machines; run into a local folder when
several machines share one.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import time
from pathlib import Path

import filelock

from mocap.core.atomic import write_text


class OutputInUse(RuntimeError):
    """Another run is writing into this output folder."""


def _read(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}  # none, being written, or damaged


class RunLock:
    """Context manager holding ``folder/.facemocap/lock``; ``note`` says if the previous run into
    the folder was killed before it released the lock."""

    def __init__(self, folder: str | os.PathLike):
        self.dir = Path(folder) / ".facemocap"
        self.path = self.dir / "lock"
        self.owner_path = self.dir / "lock.owner"
        self.note: str | None = None
        self._lock = filelock.FileLock(self.path, timeout=0)
        self._owner = {"pid": os.getpid(), "host": socket.gethostname(),
                       "date": time.strftime("%Y-%m-%dT%H:%M:%S%z")}

    def __enter__(self) -> "RunLock":
        self.dir.mkdir(parents=True, exist_ok=True)
        try:
            self._lock.acquire()
        except filelock.Timeout:
            raise OutputInUse(self._refusal(_read(self.owner_path))) from None
        left = _read(self.owner_path)
        if left:
            self.note = (f"the previous run into {self.dir.parent} (pid {left.get('pid')} on "
                         f"{left.get('host')}, started {left.get('date')}) ended without "
                         "finishing; what it had finished is kept")
        write_text(self.owner_path, json.dumps(self._owner))
        return self

    def _refusal(self, held: dict) -> str:
        who = (f"pid {held.get('pid')} on {held.get('host')} since {held.get('date')}"
               if held else "a run that is starting")
        return (f"{self.dir.parent} is in use by another run ({who}). "
                "Wait for it, or choose another output folder.")

    def __exit__(self, *exc) -> None:
        with contextlib.suppress(FileNotFoundError):
            self.owner_path.unlink()
        self._lock.release()
