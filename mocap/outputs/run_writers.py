"""The run's figures and Rerun recording (outputs layer): the writers ``mocap run`` passes to
the composer (:class:`mocap.workflows.run.result.RunWriters`).

The composer (a workflow) computes and writes data files; drawing (matplotlib, in
:mod:`mocap.outputs.figures`) and recording (rerun, in :mod:`mocap.outputs.recording`) sit above it
and are handed down as plain functions, so the workflow never imports them::

    from mocap.workflows.run.pipeline import run_session
    from mocap.outputs.run_writers import WRITERS

    run_session("sample_data/session", "out/sample", writers=WRITERS)   # as `mocap run`

Module-level functions, so :data:`WRITERS` pickles by reference (``mocap batch`` sends it to
Dask workers).
"""

from __future__ import annotations

from pathlib import Path

from mocap.workflows.run.result import RunWriters, Trials
from mocap.workflows.run.stages import progress_bar
from mocap.reconstruction.takes import Reconstruction
from mocap.core.session import Session

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
    return _draw_all(analysis_figure_jobs(out, session, recon, trials, res), bars, jobs)


def analysis_figure_jobs(out: Path, session: Session, recon: Reconstruction, trials: Trials,
                         res) -> list[tuple]:
    """(path, draw, args) of each figure :func:`analysis_figures` draws, in its order:
    ``draw(*args)`` returns the figure. The property chart shows the noise-corrected estimates
    (``*_corrected``) on all three of its scales; the response curves are the paper's
    computation literally, with the corrected hysteresis and dyssynchrony in the title; the
    linearity bars both, each labelled (docs/outputs.md's naming rule)."""
    from mocap.outputs import figures as F

    du_names = {d.id: d.name for d in session.dus}
    feedback = {d.id: d.feedback for d in session.dus}
    fig = out / "figures"
    rest = recon.markers.rest_mm
    props = res.properties
    by_du = props.set_index("du")
    todo = []
    for avg in trials.averages:
        name = du_names.get(avg.du, "")
        todo.append((fig / f"du{avg.du:02d}_displacement_field.png", F.displacement_field,
                     (avg.du, name, rest, res.fields_mm[avg.du], res.keep[avg.du])))
        corrected = {k: float(by_du.loc[avg.du, k])
                     for k in ("hysteresis_corrected", "dyssynchrony_corrected")}
        todo.append((fig / f"du{avg.du:02d}_response.png", F.response_curves,
                     (avg.du, name, res.paper[avg.du], avg.fps, corrected)))
    todo.append((fig / "linearity.png", F.linearity_bars,
                 (props["du"], props["linearity_mean"], props["linearity_std"],
                  props["linearity_mean_corrected"])))
    todo.append((fig / "property_chart.png", F.property_chart,
                 (props["du"], props["sensitivity_corrected"], props["hysteresis_corrected"],
                  props["dyssynchrony_corrected"], [feedback.get(d, False) for d in props["du"]],
                  "corrected")))
    plans = {t.name: t.plan for t in session.takes}
    for take, _, ev in res.motions:
        todo.append((fig / f"motion_{take}.png", F.motion_result, (f"{take} (plan {plans[take]})", ev)))
    return todo


def _draw_all(todo: list, bars: bool | None, jobs: int) -> list[Path]:
    """Each (path, draw, args) of ``todo`` drawn and saved; the paths in ``todo``'s order."""
    from mocap.outputs.figures import draw_and_save

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
    """The audit's figures into ``out/figures`` (``mocap.outputs.figures.audit_figures``)."""
    from mocap.outputs import figures as F

    return F.audit_figures(out, audit, recon, calibration)


def start_recording(path: Path, result):
    """The run's Rerun recording, started on what the reconstruction gives (a ``RunResult``
    without trials, analysis or audit): a ``mocap.outputs.recording.RecordingWriter`` logging the takes
    on a thread; its ``finish(result)`` commits the file, ``abort()`` drops it."""
    from mocap.outputs.recording import RecordingWriter

    return RecordingWriter(path, result)


def write_recording(path: Path, result) -> Path:
    """The Rerun recording of a finished ``RunResult`` written in one go
    (``mocap.outputs.recording.write_recording``)."""
    from mocap.outputs.recording import write_recording as write

    return write(path, result)


WRITERS = RunWriters(analysis_figures=analysis_figures, audit_figures=audit_figures,
                     recording=start_recording)
