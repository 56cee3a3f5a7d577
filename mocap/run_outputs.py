"""The run's figures and Rerun recording (outputs layer): the writers ``mocap run`` passes to
the composer (:class:`mocap.pipeline.RunWriters`).

The composer (a workflow) computes and writes data files; drawing (matplotlib, in
:mod:`mocap.analysis.figures`) and recording (rerun, in :mod:`mocap.recording`) sit above it
and are handed down as plain functions, so the workflow never imports them::

    from mocap.pipeline import run_session
    from mocap.run_outputs import WRITERS

    run_session("sample_data/session", "out/sample", writers=WRITERS)   # as `mocap run`

Module-level functions, so :data:`WRITERS` pickles by reference (``mocap batch`` sends it to
Dask workers).
"""

from __future__ import annotations

from pathlib import Path

from mocap.pipeline import RunWriters, Trials, progress_bar
from mocap.reconstruct.takes import Reconstruction
from mocap.session import Session

__all__ = ["analysis_figures", "audit_figures", "start_recording", "write_recording", "WRITERS"]


# Below this many figures they are drawn in this process whatever ``jobs`` says: a spawned
# worker imports numpy, pandas and matplotlib (about 1.5 s), and a figure takes 0.2-0.5 s.
PARALLEL_MIN_FIGURES = 16


def analysis_figures(out: Path, session: Session, recon: Reconstruction, trials: Trials, res,
                     bars: bool | None = False, jobs: int = 1) -> list[Path]:
    """The analyses' figures into ``out/figures`` (docs/outputs.md): per DU its displacement
    field and response curves, the linearity bars, the property chart and one figure per
    evaluated motion take. ``res``: the run's ``Analysis``. Drawn on up to ``jobs``
    processes when there are at least :data:`PARALLEL_MIN_FIGURES` (the paper preset's 39:
    12.6-13.5 s in one process, 9.2-10.2 s on two). Returns the files, in the order above."""
    from mocap.analysis import figures as F

    du_names = {d.id: d.name for d in session.dus}
    feedback = {d.id: d.feedback for d in session.dus}
    fig = out / "figures"
    rest = recon.markers.rest_mm
    props = res.properties
    todo = []
    for avg in trials.averages:
        name = du_names.get(avg.du, "")
        todo.append((fig / f"du{avg.du:02d}_displacement_field.png", F.displacement_field,
                     (avg.du, name, rest, res.fields_mm[avg.du], res.keep[avg.du])))
        todo.append((fig / f"du{avg.du:02d}_response.png", F.response_curves,
                     (avg.du, name, res.paper[avg.du], avg.fps)))
    todo.append((fig / "linearity.png", F.linearity_bars,
                 (props["du"], props["linearity_mean"], props["linearity_std"])))
    todo.append((fig / "property_chart.png", F.property_chart,
                 (props["du"], props["sensitivity"], props["hysteresis"], props["dyssynchrony"],
                  [feedback.get(d, False) for d in props["du"]])))
    plans = {t.name: t.plan for t in session.takes}
    for take, _, ev in res.motions:
        todo.append((fig / f"motion_{take}.png", F.motion_result, (f"{take} (plan {plans[take]})", ev)))
    return _draw_all(todo, bars, jobs)


def _draw_all(todo: list, bars: bool | None, jobs: int) -> list[Path]:
    """Each (path, draw, args) of ``todo`` drawn and saved; the paths in ``todo``'s order."""
    from mocap.analysis.figures import draw_and_save

    jobs = max(1, min(int(jobs), len(todo)))
    if jobs == 1 or len(todo) < PARALLEL_MIN_FIGURES:
        return [draw_and_save(*job) for job in progress_bar(todo, len(todo), "figures", bars)]
    from concurrent.futures import as_completed

    from loky import ProcessPoolExecutor  # workers that never re-run the caller's __main__

    with ProcessPoolExecutor(max_workers=jobs) as pool:
        futures = [pool.submit(draw_and_save, *job) for job in todo]
        for fut in progress_bar(as_completed(futures), len(futures), "figures", bars):
            fut.result()  # a figure that fails stops the run here, with its error
    return [fut.result() for fut in futures]


def audit_figures(out: Path, audit: dict, recon: Reconstruction, calibration) -> list[Path]:
    """The audit's figures into ``out/figures`` (``mocap.analysis.figures.audit_figures``)."""
    from mocap.analysis import figures as F

    return F.audit_figures(out, audit, recon, calibration)


def start_recording(path: Path, result):
    """The run's Rerun recording, started on what the reconstruction gives (a ``RunResult``
    without trials, analysis or audit): a ``mocap.recording.RecordingWriter`` logging the takes
    on a thread; its ``finish(result)`` commits the file, ``abort()`` drops it."""
    from mocap.recording import RecordingWriter

    return RecordingWriter(path, result)


def write_recording(path: Path, result) -> Path:
    """The Rerun recording of a finished ``RunResult`` written in one go
    (``mocap.recording.write_recording``)."""
    from mocap.recording import write_recording as write

    return write(path, result)


WRITERS = RunWriters(analysis_figures=analysis_figures, audit_figures=audit_figures,
                     recording=start_recording)
