"""The run's data files for the analyses, the audit and each finished take.

The analyses' tables (properties.csv, linearity.csv, marker_properties.csv), the audit
(audit.json, audit.md) and a take's trajectories (trajectories/<take>.parquet, keyed for the
cache of :mod:`mocap.workflows.run.cache`), written atomically; figures only through the writers
passed in (:class:`mocap.workflows.run.result.RunWriters`). Layout: docs/outputs.md.
"""

from __future__ import annotations

from pathlib import Path

from mocap.core.atomic import write_csv
from mocap.core.session import Session
from mocap.reconstruction.labeling import trajectories_table
from mocap.reconstruction.takes import Reconstruction, TakeReconstruction, labeled_take_from_table
from mocap.workflows.run.result import Trials

__all__ = ["write_analysis", "write_audit_files"]


def write_analysis(out: Path, session: Session, recon: Reconstruction, trials: Trials, res,
                   bars: bool | None = False, figures=None, jobs: int = 1) -> list[Path]:
    """properties.csv, linearity.csv, marker_properties.csv and (``figures``: a
    :attr:`RunWriters.analysis_figures`, drawn on up to ``jobs`` processes) the figures; the
    files."""
    files = [write_csv(res.properties, out / "properties.csv"),
             write_csv(res.linearity, out / "linearity.csv"),
             write_csv(res.marker_properties, out / "marker_properties.csv")]
    if figures is not None:
        files += list(figures(out, session, recon, trials, res, bars, jobs))
    return files


def write_audit_files(out: Path, audit: dict, recon: Reconstruction, calibration,
                      figures=None) -> list[Path]:
    """audit.json, audit.md and (``figures``: a :attr:`RunWriters.audit_figures`) the audit's
    figures; the files."""
    from mocap.workflows.audit import write_audit

    files = write_audit(out, audit)
    if figures is not None:
        files += list(figures(out, audit, recon, calibration))
    return files


def _write_take(out: Path, store, key: str, tr: TakeReconstruction, names) -> None:
    """A finished take: its counts (state), then its trajectories, which commit it."""
    from mocap.workflows.run.cache import write_keyed_parquet

    path = out / "trajectories" / f"{tr.name}.parquet"
    if store is not None:
        store.save_take(tr.name, key, (tr.labeled.stats, tr.capture, tr.roles))
    write_keyed_parquet(trajectories_table(tr.labeled, names), path, key if store else "")


def _stored_take(out: Path, store, key: str, name: str, names) -> tuple | None:
    """A take finished by an earlier run with ``key``: (loader of its LabeledTake, stats,
    capture, roles), or None."""
    path = out / "trajectories" / f"{name}.parquet"
    hit, saved = store.load_take(name, key, path)
    if not hit:
        return None
    stats, capture, roles = saved

    def load():
        import pyarrow.parquet as pq

        return labeled_take_from_table(pq.read_table(path, read_dictionary=["marker"]), names,
                                       stats, capture.views)

    return load, stats, capture, roles
