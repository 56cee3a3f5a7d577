"""The run's result types: what a run produced and the output writers passed into it.

:class:`Trials` holds each DU's trial averages and the responses and rejections tables;
:class:`RunResult` holds every stage's result (trajectories in mm, NaN where a marker was not
seen); :class:`RunWriters` holds the outputs layer's figure and recording writers
(:mod:`mocap.outputs.run_writers`), which the composer (:mod:`mocap.workflows.run.pipeline`) calls.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping

import numpy as np
import pandas as pd

from mocap.analysis.session_analysis import SUMMARY_COLUMNS
from mocap.core.display import Summarised, Summary, table_of
from mocap.core.session import Session
from mocap.reconstruction.labeling import trajectories_frame
from mocap.reconstruction.takes import Reconstruction
from mocap.reconstruction.trials import TrialAverage
from mocap.workflows.run.settings import RunSettings

__all__ = ["Trials", "RunResult", "RunWriters"]


@dataclass(frozen=True, repr=False)
class Trials(Summarised):
    """Each DU's trials averaged, the responses table and the rejections.

    averages : one TrialAverage per DU (ascending); responses : responses.parquet's rows (plus
    ``rejected``); rejections : rejections.csv's rows (``du`` NA for every-DU rows).
    """

    averages: tuple[TrialAverage, ...]
    responses: pd.DataFrame
    rejections: pd.DataFrame

    def _summary(self) -> Summary:
        return Summary(
            f"Trials: {len(self.averages)} DUs averaged",
            tuple((f"DU {a.du}", f"{len(a.takes)} trials, {a.command.shape[0]} frames")
                  for a in self.averages[:16]) +
            (("rows", f"{len(self.responses)} responses, {len(self.rejections)} rejections"),),
            more="attributes: .averages .responses .rejections")


@dataclass(frozen=True, repr=False)
class RunResult(Summarised):
    """Everything a run produced.

    session, settings : what ran; calibration : ``CalibrationResult`` (raw sessions) or None;
    reconstruction : every face take's labeled trajectories; trials : averages, responses,
    rejections; analysis : :class:`Analysis`, what :func:`mocap.workflows.run.stages.analyze`
    returns (None for an audit-only run or without response takes); audit : the audit report
    (audit.json); summary : summary.json; out_dir : the output folder (None: nothing was
    written); reused, computed : the stages taken from an earlier run in ``out_dir`` and those
    computed (``reconstruct (k of n takes)`` for part of the takes).
    """

    session: Session
    settings: RunSettings
    calibration: object | None
    reconstruction: Reconstruction
    trials: Trials
    analysis: object | None
    audit: Mapping
    summary: Mapping
    out_dir: Path | None = None
    reused: tuple[str, ...] = ()
    computed: tuple[str, ...] = ()

    @property
    def averages(self) -> tuple[TrialAverage, ...]:
        return self.trials.averages

    @property
    def rejections(self) -> pd.DataFrame:
        return self.trials.rejections

    @property
    def responses(self) -> pd.DataFrame:
        return self.trials.responses

    @property
    def markers(self) -> tuple[str, ...]:
        return self.reconstruction.markers.names

    @property
    def properties(self) -> pd.DataFrame | None:
        """One row per DU, the paper's indices (properties.csv)."""
        return None if self.analysis is None else self.analysis.properties

    @property
    def linearity(self) -> pd.DataFrame | None:
        return None if self.analysis is None else self.analysis.linearity

    @property
    def arrays(self) -> dict[str, np.ndarray]:
        """Take name -> (n_frames, n_markers, 3) marker positions, mm (NaN: not seen); markers in
        ``markers`` order. Read-only views of the reconstruction."""
        def view(X: np.ndarray) -> np.ndarray:
            v = X.view()
            v.flags.writeable = False
            return v

        return {name: view(lab.X) for name, lab in self.reconstruction.takes.items()}

    @property
    def trajectories(self) -> pd.DataFrame:
        """Every face take's trajectories as one tidy table: take, frame, marker, x, y, z (mm),
        n_cameras, residual_px, interpolated (the rows of trajectories/<take>.parquet)."""
        names = self.markers
        parts = [trajectories_frame(lab, names).assign(take=name)
                 for name, lab in self.reconstruction.takes.items()]
        if not parts:
            return pd.DataFrame(columns=["take", "frame", "marker", "x", "y", "z"])
        df = pd.concat(parts, ignore_index=True)
        return df[["take"] + [c for c in df.columns if c != "take"]]

    def _summary(self) -> Summary:
        s = self.session
        where = f"written to {self.out_dir}" if self.out_dir is not None else "nothing written"
        lines = [("session", f"{s.name!r}: {s.dimension.upper()}, {s.fps:g} fps, "
                             f"{len(s.takes)} takes, {len(s.dus)} DUs")]
        if self.calibration is not None:
            q = self.calibration.quality
            lines.append(("calibration", f"{q.get('rating', '?')}: reprojection rms "
                                         f"{q.get('reprojection_rms_px_all', float('nan')):.3g} px, "
                                         f"{len(self.calibration.rig.ids)} cameras"))
        r = self.reconstruction
        lines.append(("reconstruction", f"{len(r.markers.names)} markers, {len(r.takes)} face "
                                        f"takes, {r.labeled_points:,} labeled points"))
        if self.trials is not None:
            lines.append(("trials", f"{len(self.trials.averages)} DUs averaged, "
                                    f"{len(self.trials.rejections)} rejections"))
        if self.analysis is not None:
            lines.append(("motions", f"{len(self.analysis.motions)} plan takes evaluated"))
        if self.audit:
            lines.append(("audit", str(self.audit.get("verdict", "?"))))
        if self.reused:
            lines.append(("reused", ", ".join(self.reused)))
        return Summary(f"RunResult ({where})", tuple(lines),
                       table_of(self.properties, SUMMARY_COLUMNS),
                       "properties (one row per DU; all columns: .properties)",
                       "attributes: .properties .linearity .rejections .trajectories .arrays "
                       ".audit .calibration .analysis .summary")


@dataclass(frozen=True)
class RunWriters:
    """The run's output writers, from the outputs layer (:data:`mocap.outputs.run_writers.WRITERS`);
    None: not written. Each returns the files it wrote.

    analysis_figures(out, session, reconstruction, trials, analysis, bars, jobs) -> list[Path]
        the analyses' figures into ``out/figures`` (``analysis``: :class:`Analysis`;
        ``bars``: as :func:`mocap.workflows.run.pipeline.run`'s; ``jobs``: processes it may
        use, ``RunSettings.jobs``)
    audit_figures(out, audit, reconstruction, calibration) -> list[Path]
        the audit's figures into ``out/figures`` (``calibration`` None for 3D sessions)
    recording(path, result) -> writer
        the Rerun recording (written when ``settings.recording``), started as soon as the takes
        are reconstructed: ``result`` is a :class:`RunResult` holding the session, settings,
        calibration and reconstruction (trials, analysis and audit None); the writer's
        ``finish(result) -> Path`` is given the complete result and commits the file, its
        ``abort()`` removes it (``mocap.outputs.recording.RecordingWriter``)
    """

    analysis_figures: Callable[..., list[Path]] | None = None
    audit_figures: Callable[..., list[Path]] | None = None
    recording: Callable[[Path, RunResult], object] | None = None
