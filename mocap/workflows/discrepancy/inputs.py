"""Read what the discrepancy workflow needs from a session or from a `mocap run` output folder.

A labeled (3D) session is read directly; a raw (2D) session is reconstructed first by the
pipeline (calibration, correspondence, labeling) into ``work_dir``; an OUT_DIR of `mocap run`
gives its trajectories/<take>.parquet and, through summary.json, the session's commands.
"""

from __future__ import annotations

import json
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from mocap.analysis.model.data import TakeData
from mocap.reconstruction.labeled_input import dense_from_3d, marker_names_3d
from mocap.core.session import Session, SessionError, load_session


@dataclass
class MeasuredSession:
    """Measured takes of a session (positions mm, world frame).

    session : the loaded session.  marker_names : (M,).  rest_mm : (M, 3) mean rest positions.
    rest_X : (n_frames, M, 3) the rest take (None without one).  takes : every commanded take.
    source : where the trajectories came from.
    """

    session: Session
    marker_names: tuple[str, ...]
    rest_mm: np.ndarray
    rest_X: np.ndarray | None
    takes: list[TakeData]
    source: str


def _schedule_key(rows: pd.DataFrame) -> str:
    r = rows.sort_values(["du", "time_s"], kind="stable")
    blob = np.column_stack([r["time_s"].to_numpy(float).round(6), r["du"].to_numpy(float),
                            r["command"].to_numpy(float)]).tobytes()
    return f"{zlib.crc32(blob):08x}"


def _trajectories_from_out(out: Path) -> dict[str, Path]:
    files = {p.stem: p for p in (out / "trajectories").glob("*.parquet")}
    if not files:
        raise SessionError(f"{out / 'trajectories'}: no <take>.parquet files (is this a mocap run output?)")
    return files


def load_measured(path: str | Path, work_dir: str | Path | None = None,
                  progress=None) -> MeasuredSession:
    """Measured takes from a session directory or a `mocap run` output directory.

    Raises SessionError naming the file when something needed is missing.
    """
    say = progress or (lambda m: None)
    path = Path(path)
    if (path / "summary.json").exists() and (path / "trajectories").is_dir():
        summary = json.loads((path / "summary.json").read_text())
        sdir = Path(summary.get("session", {}).get("dir", ""))
        if not (sdir / "session.toml").exists():
            raise SessionError(f"{path / 'summary.json'}: session.dir {str(sdir)!r} has no session.toml "
                               "(the commands are read from the session)")
        session = load_session(sdir)
        files = _trajectories_from_out(path)
        source = f"trajectories of {path}"
    elif (path / "session.toml").exists():
        session = load_session(path)
        if session.dimension == "3d":
            files = None
            source = f"labeled takes of {path}"
        else:
            from mocap.workflows.run.pipeline import run_session
            from mocap.workflows.run.settings import RunSettings

            if work_dir is None:
                raise ValueError("a raw (2D) session needs a work_dir for its reconstruction")
            run_dir = Path(work_dir)
            say(f"raw session: reconstructing into {run_dir}")
            run_session(path, run_dir, progress=say,
                        settings=RunSettings(analyze=False, recording=False))
            files = _trajectories_from_out(run_dir)
            source = f"reconstruction of {path} in {run_dir}"
    else:
        raise SessionError(f"{path}: neither a session (session.toml) nor a mocap run output "
                           "(summary.json and trajectories/)")

    def read(name: str) -> pd.DataFrame:
        if files is None:
            return session.read_take(name)
        if name not in files:
            raise SessionError(f"{path / 'trajectories'}: no trajectories for take {name!r}")
        return pd.read_parquet(files[name], columns=["frame", "marker", "x", "y", "z"])

    wanted = [t for t in session.takes if t.kind in ("rest", "response", "motion")]
    frames = {t.name: read(t.name) for t in wanted}
    template = session.marker_template
    names = marker_names_3d(list(frames.values()), template)
    dense = {k: dense_from_3d(df, names).X for k, df in frames.items()}

    rest_takes = [t.name for t in wanted if t.kind == "rest"]
    takes: list[TakeData] = []
    for t in wanted:
        if t.kind == "rest" or t.commands is None:
            continue
        rows = session.read_commands(t.name)
        dus = tuple(sorted(int(d) for d, g in rows.groupby("du") if (g["command"] > 0).any()))
        if not dus:
            continue
        takes.append(TakeData(name=t.name, kind=t.kind, trial=int(t.trial or 1), dus=dus,
                              rows=rows, X=dense[t.name], group=_schedule_key(rows)))
    if not takes:
        raise SessionError(f"{session.root / 'session.toml'}: no response or motion take with "
                           "nonzero commands: nothing to model")
    if rest_takes:
        rest_X = np.concatenate([dense[n] for n in rest_takes])
    else:
        rest_X = None
    if rest_X is not None and np.isfinite(rest_X).any():
        with np.errstate(all="ignore"):
            rest = np.nanmean(rest_X, axis=0)
    else:  # no rest take: the frames before each take's first command
        before = []
        for td in takes:
            first = float(td.rows.loc[td.rows["command"] > 0, "time_s"].min())
            nf = max(1, int(first * session.fps))
            before.append(td.X[:nf])
        with np.errstate(all="ignore"):
            rest = np.nanmedian(np.concatenate(before), axis=0)
    return MeasuredSession(session=session, marker_names=tuple(names), rest_mm=rest,
                           rest_X=rest_X, takes=takes, source=source)
