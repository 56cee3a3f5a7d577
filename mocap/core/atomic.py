"""Atomic file writes: a temporary name beside the target, then ``os.replace``.

An interrupted run never leaves a half-written file under its final name (docs/outputs.md).
Files and folders are created with the user's umask, like any other program's (0644 and 0755
under umask 022), so that labmates can read the results.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from pathlib import Path
from typing import Iterator


def _new_temporary(folder: Path, name: str) -> Path:
    """A new empty file ``.<name>.<random>.tmp`` in ``folder``, created with mode 0666 less the
    umask (``tempfile.mkstemp`` would make it 0600, and the rename would keep that)."""
    for _ in range(100):
        tmp = folder / f".{name}.{secrets.token_hex(4)}.tmp"
        try:
            fd = os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
        except FileExistsError:
            continue
        os.close(fd)
        return tmp
    raise FileExistsError(f"{folder}: no free temporary name for {name}")  # pragma: no cover


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; rename it onto ``path`` on success.

    The folder is created when missing. On an exception the temporary file is removed and the
    target (if it existed) is left untouched. The file gets the user's umask (0644 under 022).
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp_path = _new_temporary(target.parent, target.name)
    try:
        yield tmp_path
        os.replace(tmp_path, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; return the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def write_parquet(df, path: str | os.PathLike) -> Path:
    """Write a pandas DataFrame to Parquet (zstd) atomically (no index); return the path.

    Only the columns that are not floating point are dictionary-encoded: measured coordinates
    rarely repeat, and trying a dictionary on them would be most of the write time (and the file
    larger). The data read back are the same.
    """
    with atomic_path(path) as tmp:
        df.to_parquet(tmp, index=False, compression="zstd", use_dictionary=dictionary_columns(df))
    return Path(path)


def dictionary_columns(df) -> list[str]:
    """The columns of a DataFrame worth a Parquet dictionary: those not floating point."""
    import pandas as pd

    return [str(c) for c in df.columns if not pd.api.types.is_float_dtype(df[c].dtype)]


def write_csv(df, path: str | os.PathLike, decimals: int | None = None) -> Path:
    """Write a pandas DataFrame to CSV atomically (no index, no quoting); return the path.

    Float columns are rounded to ``decimals`` when given and written in their shortest exact
    form; NaN is written as an empty cell ("not seen", docs/format.md). Uses pyarrow's CSV writer,
    about 20 x faster than pandas' for millions of rows.
    """
    import numpy as np
    import pandas as pd
    import pyarrow as pa
    import pyarrow.csv as pacsv

    if decimals is not None:
        df = df.copy()
        for col in df.columns:
            if pd.api.types.is_float_dtype(df[col].dtype):
                df[col] = np.round(df[col].to_numpy(), decimals)
    table = pa.Table.from_pandas(df, preserve_index=False)
    with atomic_path(path) as tmp:
        options = pacsv.WriteOptions(quoting_style="none", quoting_header="none")
        pacsv.write_csv(table, tmp, write_options=options)
    return Path(path)
