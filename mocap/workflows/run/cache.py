"""Reusable, resumable runs: every stage's results keyed by a hash of what it reads.

A key is a BLAKE2b hash of the stage's inputs: the fingerprints of the session files it reads
(their content hash), the settings it uses, the keys of the stages it builds on, and the code
version (the package version and a hash of its source files, so that a changed algorithm never
reuses an old result). ``mocap run`` into a folder holding results with the same keys reuses them
and recomputes only the stages whose key changed.

State lives in ``OUT_DIR/.facemocap/``:

- ``fingerprints.json``: content hash of each input file by (path, size, mtime): a file whose
  size and modification time are unchanged is not read again (as git's index);
- ``stages/<stage>.pkl``: (key, result) of each stage, written atomically after its outputs;
- ``takes/<take>.pkl``: (key, counts) of each reconstructed take; its trajectories are the
  output file ``trajectories/<take>.parquet``, whose metadata holds the same key. Both are
  written atomically as each take finishes, so a killed run resumes from the takes it finished.

The stage files are Python pickles of the package's own result types: like the rest of an
output folder they are trusted; never run into a folder from an untrusted source (``--force``
ignores the state, and the lock and these files are all that ``.facemocap`` holds).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pickle
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq

from mocap.core.atomic import atomic_path, write_text

STATE_DIR = ".facemocap"
KEY_METADATA = b"facemocap_key"
_FORMAT = 1  # of the state files


def _source_hash() -> str:
    h = hashlib.blake2b(digest_size=16)
    import mocap
    import mocap.analysis
    import mocap.calib

    roots = [Path(p) for m in (mocap, mocap.calib, mocap.analysis) for p in m.__path__]
    for root in roots:
        for path in sorted(root.rglob("*.py")):
            if ".venv" in path.parts:
                continue
            h.update(str(path.relative_to(root)).encode())
            h.update(path.read_bytes())
    return h.hexdigest()


_CODE: str | None = None


def code_version() -> str:
    """The package version and a hash of its source files."""
    global _CODE
    if _CODE is None:
        from mocap import __version__

        _CODE = f"{__version__}+{_source_hash()}"
    return _CODE


def _plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.integer, np.floating, np.bool_)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value


def make_key(stage: str, **parts: Any) -> str:
    """The key of ``stage`` from its inputs (JSON-able values, dataclasses, arrays)."""
    doc = json.dumps({"stage": stage, "code": code_version(), "format": _FORMAT,
                      "parts": _plain(parts)}, sort_keys=True, default=str)
    return hashlib.blake2b(doc.encode(), digest_size=20).hexdigest()


def file_hash(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, lambda: hashlib.blake2b(digest_size=20)).hexdigest()


class Fingerprints:
    """Content hashes of input files, remembered by (path, size, mtime) in ``memo_path``."""

    def __init__(self, memo_path: Path | None):
        self.memo_path = memo_path
        self.memo: dict = {}
        if memo_path is not None and memo_path.is_file():
            try:
                self.memo = json.loads(memo_path.read_text())
            except ValueError:
                self.memo = {}
        self._dirty = False

    def __call__(self, path: Path | None) -> str | None:
        if path is None:
            return None
        path = Path(path).resolve()
        stamp, known = self._lookup(path)
        return known if known is not None else self._remember(path, stamp, file_hash(path))

    def _lookup(self, path: Path) -> tuple[list, str | None]:
        """(the file's [size, mtime_ns], its remembered hash or None when unknown or stale);
        OSError when it cannot be stat'ed."""
        st = path.stat()
        stamp = [st.st_size, st.st_mtime_ns]
        entry = self.memo.get(str(path))
        return stamp, (entry[2] if entry is not None and entry[:2] == stamp else None)

    def _remember(self, path: Path, stamp: list, digest: str) -> str:
        self.memo[str(path)] = stamp + [digest]
        self._dirty = True
        return digest

    def prefetch(self, paths, jobs: int = 1) -> None:
        """Hash the files of ``paths`` that are not remembered yet, on up to ``jobs`` threads
        (hashlib lets go of the GIL while it hashes: a paper session's 461 files, 648 MB, took
        1.3 s on one thread before anything else could start). Files that cannot be read are
        left to :meth:`__call__`, which reports them."""
        todo = []
        for path in {Path(p).resolve() for p in paths if p is not None}:
            try:
                stamp, known = self._lookup(path)
            except OSError:
                continue
            if known is None:
                todo.append((path, stamp))
        if not todo:
            return

        def digest(item):
            try:
                return file_hash(item[0])
            except OSError:
                return None

        if jobs > 1 and len(todo) > 1:
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(min(int(jobs), len(todo))) as pool:
                digests = list(pool.map(digest, todo))
        else:
            digests = [digest(item) for item in todo]
        for (path, stamp), value in zip(todo, digests):
            if value is not None:
                self._remember(path, stamp, value)

    def save(self) -> None:
        if self._dirty and self.memo_path is not None:
            write_text(self.memo_path, json.dumps(self.memo))
            self._dirty = False


class RunStore:
    """The state of an output folder (see the module docstring); ``force`` ignores it."""

    def __init__(self, out_dir: Path, force: bool = False):
        self.root = Path(out_dir) / STATE_DIR
        self.force = force
        self.fingerprints = Fingerprints(self.root / "fingerprints.json")
        self.removed = remove_partial_files(Path(out_dir))

    # --- whole stages --------------------------------------------------------------------
    def load(self, stage: str, key: str, outputs=()) -> tuple[bool, Any]:
        """(True, result) when ``stage`` was saved with ``key`` and its ``outputs`` exist."""
        if self.force or not all(Path(p).exists() for p in outputs):
            return False, None
        return _load_pickle(self.root / "stages" / f"{stage}.pkl", key)

    def save(self, stage: str, key: str, value: Any) -> None:
        _save_pickle(self.root / "stages" / f"{stage}.pkl", key, value)

    # --- takes ---------------------------------------------------------------------------
    def load_take(self, name: str, key: str, parquet: Path) -> tuple[bool, Any]:
        """(True, counts) when take ``name`` was finished with ``key``: its trajectories file
        carries the key and so does its counts file."""
        if self.force or not parquet.is_file():
            return False, None
        try:
            meta = pq.read_schema(parquet).metadata or {}
        except Exception:  # unreadable: recompute  # noqa: BLE001
            return False, None
        if meta.get(KEY_METADATA, b"").decode() != key:
            return False, None
        return _load_pickle(self.root / "takes" / f"{name}.pkl", key)

    def save_take(self, name: str, key: str, value: Any) -> None:
        """The take's counts; written before its trajectories file (which commits the take)."""
        _save_pickle(self.root / "takes" / f"{name}.pkl", key, value)


def remove_partial_files(out_dir: Path) -> int:
    """Remove the temporary files a killed run left (``mocap.core.atomic``'s ``.<name>.*.tmp``);
    call only while holding the folder's lock. Returns how many."""
    n = 0
    for sub in ("", "trajectories", "figures", STATE_DIR, f"{STATE_DIR}/stages", f"{STATE_DIR}/takes"):
        for path in (out_dir / sub).glob(".*.tmp"):
            if path.is_file():
                path.unlink(missing_ok=True)
                n += 1
    return n


def _load_pickle(path: Path, key: str) -> tuple[bool, Any]:
    try:
        with open(path, "rb") as f:
            saved_key = pickle.load(f)
            if saved_key != key:
                return False, None
            return True, pickle.load(f)
    except (OSError, EOFError, pickle.UnpicklingError, AttributeError, ImportError, TypeError,
            ValueError):  # missing, damaged or written by other code: recompute
        return False, None


def _save_pickle(path: Path, key: str, value: Any) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            pickle.dump(key, f, protocol=pickle.HIGHEST_PROTOCOL)
            pickle.dump(value, f, protocol=pickle.HIGHEST_PROTOCOL)


def write_keyed_parquet(df, path: Path, key: str) -> Path:
    """``df`` (a DataFrame or an Arrow table) as Parquet (zstd) written atomically, its schema
    metadata holding ``key`` (none for an empty key); only the columns that are not floating
    point dictionary-encoded, as :func:`mocap.core.atomic.write_parquet` writes (a dictionary
    tried on the coordinates, which rarely repeat, would cost most of the write time)."""
    import pyarrow as pa

    table = df if isinstance(df, pa.Table) else pa.Table.from_pandas(df, preserve_index=False)
    if key:
        table = table.replace_schema_metadata({**(table.schema.metadata or {}),
                                               KEY_METADATA: key.encode()})
    dictionary = [f.name for f in table.schema if not pa.types.is_floating(f.type)]
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp, compression="zstd", use_dictionary=dictionary)
    return Path(path)
