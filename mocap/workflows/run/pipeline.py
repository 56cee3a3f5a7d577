"""The composer: one run of a session through every stage, raw exports to results.

Stages are pure functions from one typed result to the next:

    Session -> calibrate -> CalibrationResult (raw sessions)
            -> find_markers -> MarkerSet -> reconstruct -> Reconstruction (every face take)
            -> compute_trials -> Trials (averages, responses, rejections)
            -> analyze_session -> Analysis (the paper's analyses, motion evaluations)
            -> audit_capture -> the audit report

``run`` joins them and returns one frozen :class:`RunResult`. Without an output folder it
writes nothing. With one it writes docs/outputs.md's files atomically, holds the folder's lock
(:mod:`mocap.workflows.run.lock`) and keys every stage's results by what it reads
(:mod:`mocap.workflows.run.cache`): a rerun reuses what is unchanged, recomputes the rest and says which;
a killed run resumes from the takes it finished.

The composer is a workflow: it draws no figure and writes no recording itself. The output
writers (figures, the Rerun recording) live in the outputs layer (:mod:`mocap.outputs.run_writers`) and
are passed in as :class:`RunWriters`; without them a run writes its data files only.
"""

from __future__ import annotations

import json
import platform
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable, Iterator, Mapping

import numpy as np
import pandas as pd

from mocap import __version__
from mocap.analysis.session_analysis import SUMMARY_COLUMNS, Analysis
from mocap.core.atomic import write_csv, write_parquet, write_text
from mocap.calib.camera import CameraRig
from mocap.core.display import Summarised, Summary, table_of
from mocap.core.paths import check_output_path
from mocap.reconstruction.camera_count import usable_positions
from mocap.reconstruction.labeled_input import dense_from_3d, marker_names_3d
from mocap.reconstruction.labeling import (
    MarkerSet,
    identify_markers,
    trajectories_frame,
    trajectories_table,
)
from mocap.reconstruction.takes import (
    BlobRoles,
    CaptureCounts,
    LazyTakes,
    Reconstruction,
    TakeReconstruction,
    labeled_take,
    labeled_take_from_table,
    reconstruct_take,
    take_frame_count,
)
from mocap.reconstruction.trials import (
    TrialAverage,
    average_trials,
    find_rejections,
    noise_floor,
    responses_frame,
)
from mocap.workflows.run.settings import RunSettings, to_dict
from mocap.core.schedules import schedule_timing
from mocap.core.session import Session, SessionError, command_matrix, load_session

__all__ = ["RunSettings", "RunResult", "RunWriters", "Trials", "Analysis", "calibrate",
           "find_markers",
                      "reconstruct", "compute_trials", "analyze_session", "analyze", "run", "run_session"]

FACE_KINDS = ("rest", "response", "motion")
RESPONSE_COLUMNS = ["du", "frame", "time_s", "command", "marker", "x", "y", "z", "spread_mm",
                    "n_trials", "displacement_mm", "delta"]
Say = Callable[[str], None]


def _quiet(msg: str) -> None:
    pass


# the output layout's version (docs/outputs.md): raised when a file or column is renamed or dropped
OUTPUT_LAYOUT = 2


def _versions() -> dict:
    import numpy
    import pandas
    import scipy

    return {"outputs_layout": OUTPUT_LAYOUT, "facemocap": __version__,
            "python": platform.python_version(),
            "numpy": numpy.__version__, "scipy": scipy.__version__, "pandas": pandas.__version__}


def progress_bar(iterable, total: int, desc: str, bars: bool | None):
    """A tqdm progress bar on stderr: shown when ``bars`` is True, or when None and stderr is a
    terminal."""
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=desc, unit="take" if "take" in desc else "it",
                disable=(None if bars is None else not bars), file=sys.stderr, leave=False,
                dynamic_ncols=True)


# --- results ---------------------------------------------------------------------------------

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
    rejections; analysis : :class:`Analysis`, what :func:`analyze` returns (None for an
    audit-only run or without response takes); audit : the audit report (audit.json); summary : summary.json; out_dir : the output
    folder (None: nothing was written); reused, computed : the stages taken from an earlier run
    in ``out_dir`` and those computed (``reconstruct (k of n takes)`` for part of the takes).
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
        ``bars``: as :func:`run`'s; ``jobs``: processes it may use, ``RunSettings.jobs``)
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


# --- stages ----------------------------------------------------------------------------------

def calibrate(session: Session, *, progress: Say | None = None):
    """The rig's wand calibration (raw sessions): ``CalibrationResult``."""
    from mocap.calib.wand_calibration import calibrate_session

    if session.dimension != "2d":
        raise SessionError(f"{session.root}: a labeled 3D session has no cameras to calibrate")
    return calibrate_session(session, progress=progress)


def _rest_take(session: Session):
    rest = session.takes_of_kind("rest")
    return rest[0] if rest else None


def find_markers(session: Session, calibration=None, settings: RunSettings = RunSettings()
                 ) -> MarkerSet:
    """The session's markers: found on the rest take (raw sessions), or the labeled takes'
    names (3D sessions, rest positions from the rest take when there is one)."""
    face = [t for t in session.takes if t.kind in FACE_KINDS]
    rest = _rest_take(session)
    if session.dimension == "2d":
        if calibration is None:
            raise ValueError("a raw session's markers need its calibration: calibrate(session)")
        if rest is None:
            raise SessionError(f"{session.root}/session.toml: a raw session needs a 'rest' take "
                               "to find its markers")
        from mocap.reconstruction.correspondence import reconstruct_points

        blobs = session.read_take(rest.name)
        pts = reconstruct_points(blobs, calibration.rig, calibration.quality, settings.reconstruction)
        return identify_markers(pts, take_frame_count(blobs), session.marker_template,
                                settings.labels)
    frames = [session.read_take(t.name) for t in face]
    names = marker_names_3d(frames, session.marker_template)
    if rest is not None:
        rest_pos = np.nanmedian(dense_from_3d(session.read_take(rest.name), names).X, axis=0)
    else:
        rest_pos = np.full((len(names), 3), np.nan)
    return MarkerSet(tuple(names), rest_pos)


def _recorded(session: Session, settings: RunSettings) -> set[str]:
    """The takes whose blobs the recording shows."""
    if settings.record_blobs == "all":
        return {t.name for t in session.takes if t.kind in FACE_KINDS}
    if settings.record_blobs == "none":
        return set()
    rest, responses = _rest_take(session), session.takes_of_kind("response")
    return ({rest.name} if rest else set()) | ({responses[0].name} if responses else set())


def _one_take(session: Session, name: str, calibration, markers: MarkerSet,
              settings: RunSettings, record: bool) -> TakeReconstruction:
    """One face take, read and reconstructed (run in worker processes)."""
    if session.dimension == "2d":
        return reconstruct_take(name, session.read_take(name), calibration.rig, calibration.quality,
                                markers, reconstruction=settings.reconstruction,
                                labels=settings.labels, fill_gaps_frames=settings.fill_gaps_frames,
                                record=record)
    return labeled_take(name, dense_from_3d(session.read_take(name), list(markers.names)))


def _worker_init() -> None:
    try:  # one process per core: no nested numba threads
        import numba

        numba.set_num_threads(1)
    except Exception:  # pragma: no cover - numba is a dependency
        pass


# Below this many bytes of take files, the takes are reconstructed in this process whatever
# ``jobs`` says: a spawned worker imports numpy, pandas, scipy and numba (1-3 s) and receives the
# calibration, more than it saves on a few seconds of work (reconstruction runs at about 9 MB of
# Parquet per CPU-second; the sample session's 19 MB took 1.2-2.1 s in-process and 9.1 s with
# two workers on a loaded 2-core machine).
PARALLEL_MIN_BYTES = 64 * 2**20


def _take_bytes(session, names: list[str]) -> int:
    by_name = {t.name: t for t in session.takes}
    total = 0
    for name in names:
        try:
            total += Path(by_name[name].file).stat().st_size
        except (KeyError, OSError):  # missing files are reported when the take is read
            pass
    return total


@dataclass(frozen=True)
class _RigOnly:
    """What a take's reconstruction reads of a calibration (``_one_take``)."""

    rig: CameraRig
    quality: dict


def _map_takes(session, names: list[str], calibration, markers, settings: RunSettings,
               recorded: set[str]) -> Iterator[TakeReconstruction]:
    """Every take of ``names`` reconstructed, yielded as each finishes (in parallel over
    ``settings.jobs`` processes for raw sessions of at least ``PARALLEL_MIN_BYTES``)."""
    jobs = max(1, min(int(settings.jobs), len(names)))
    if (jobs == 1 or session.dimension != "2d"
            or _take_bytes(session, names) < PARALLEL_MIN_BYTES):
        for name in names:
            yield _one_take(session, name, calibration, markers, settings, name in recorded)
        return
    from concurrent.futures import as_completed

    from loky import ProcessPoolExecutor  # workers that never re-run the caller's __main__

    # a take reads the rig and its quality only: the wand's observations and residuals (2.5 MB
    # on the paper preset, pickled again for every take) stay here
    slim = _RigOnly(calibration.rig, calibration.quality)
    with ProcessPoolExecutor(max_workers=jobs, initializer=_worker_init) as pool:
        futures = [pool.submit(_one_take, session, name, slim, markers, settings,
                               name in recorded) for name in names]
        try:
            for fut in as_completed(futures):
                yield fut.result()
        finally:  # a take that fails stops the run now: the takes not started are dropped
            for fut in futures:  # (leaving the pool would otherwise run every one of them)
                fut.cancel()


def assemble(session: Session, markers: MarkerSet, takes: Mapping[str, TakeReconstruction],
             stored: Mapping[str, tuple] | None = None) -> Reconstruction:
    """The session's Reconstruction from its takes' (in session order); the noise floor from
    the rest take. ``stored``: takes of an earlier run, name -> (loader of its LabeledTake,
    stats, capture, roles), read only when asked for."""
    stored = stored or {}
    order = [t.name for t in session.takes if t.name in takes or t.name in stored]
    part = {n: (lambda tr=takes[n]: tr.labeled, takes[n].labeled.stats, takes[n].capture,
                takes[n].roles) if n in takes else stored[n] for n in order}
    caps = [part[n][2] for n in order]
    M = len(markers.names)
    capture = sum(caps[1:], caps[0]) if caps else CaptureCounts.of_take(np.zeros((0, M), bool))
    labeled = LazyTakes({n: part[n][0] for n in order}) if stored else \
        {n: takes[n].labeled for n in order}
    rest = _rest_take(session)
    noise, noise_mean = None, None
    if rest is not None and rest.name in labeled:
        noise, noise_mean = noise_floor(labeled[rest.name].X)
    roles: dict[str, BlobRoles] = {n: part[n][3] for n in order if part[n][3] is not None}
    return Reconstruction(markers, labeled, {n: part[n][1] for n in order}, capture, noise_mean,
                          noise, roles)


def reconstruct(session: Session, calibration=None, settings: RunSettings = RunSettings(), *,
                progress: Say | None = None, bars: bool | None = False) -> Reconstruction:
    """Every face take (rest, response, motion) to labeled trajectories; nothing is written.

    calibration : ``calibrate(session)``'s result (raw sessions; None for labeled 3D ones).
    """
    say = progress or _quiet
    markers = find_markers(session, calibration, settings)
    say(f"{len(markers.names)} markers")
    names = [t.name for t in session.takes if t.kind in FACE_KINDS]
    done = {}
    for tr in progress_bar(_map_takes(session, names, calibration, markers, settings,
                              _recorded(session, settings)), len(names), "reconstructing takes", bars):
        done[tr.name] = tr
    return assemble(session, markers, done)


def average_responses(session: Session, recon: Reconstruction,
                      min_cameras: int = 3) -> list[TrialAverage]:
    """Per DU, its response takes averaged over trials, from the samples at least
    ``min_cameras`` cameras saw (``mocap.reconstruction.camera_count``)."""
    out = []
    by_du: dict[int, list] = {}
    for take in session.takes_of_kind("response"):
        by_du.setdefault(int(take.du), []).append(take)
    for du, takes in sorted(by_du.items()):
        takes = sorted(takes, key=lambda t: (t.trial or 0, t.name))
        X = [usable_positions(recon.takes[t.name], min_cameras) for t in takes]
        rows = [session.read_commands(t.name) for t in takes]
        cmds = [command_matrix(r, session.fps, x.shape[0], [du])[:, 0] for r, x in zip(rows, X)]
        first = rows[0][rows[0]["du"] == du]
        timing = schedule_timing(first["time_s"].to_numpy(float), first["command"].to_numpy(float),
                                 source=f"take {takes[0].name}: its command file")
        out.append(average_trials(du, X, cmds, session.fps, [t.name for t in takes], timing))
    return out


def compute_trials(session: Session, recon: Reconstruction, settings: RunSettings = RunSettings()
                   ) -> Trials:
    """Trials averaged per DU, the responses table and the rejections."""
    averages = average_responses(session, recon, settings.reconstruction.min_cameras)
    names = list(recon.markers.names)
    if averages:
        responses = pd.concat([responses_frame(a, names) for a in averages], ignore_index=True)
    else:
        responses = pd.DataFrame(columns=RESPONSE_COLUMNS)
    rejections = find_rejections(averages, names, settings.rejections)
    # a row is rejected when its marker is rejected for every DU (du empty) or for its DU:
    # vectorised (the paper preset has millions of response rows)
    every = rejections["du"].isna()
    per_du = pd.MultiIndex.from_arrays([rejections["du"][~every].astype(int),
                                        rejections["marker"][~every]])
    rows = pd.MultiIndex.from_arrays([responses["du"].astype(int), responses["marker"]])
    flags = responses["marker"].isin(rejections["marker"][every]).to_numpy() | rows.isin(per_du)
    responses = responses.assign(rejected=np.asarray(flags, bool))
    return Trials(tuple(averages), responses, rejections)


def analyze_session(session: Session, recon: Reconstruction, trials: Trials,
                    settings: RunSettings = RunSettings()):
    """The paper's analyses of the averaged responses, and every plan take (A-E) evaluated
    against its plan: :class:`Analysis` (``trials`` set)."""
    from mocap.analysis.paper.linearity import position_covariance
    from mocap.analysis.session_analysis import (
        MotionResult,
        analyze_responses,
        evaluate_plan_take,
        is_plan,
        kept_markers,
    )

    min_cameras = settings.reconstruction.min_cameras

    names = list(recon.markers.names)
    du_names = {d.id: d.name for d in session.dus}
    noise, noise_cov = None, None
    rest = _rest_take(session)
    if recon.noise_per_marker_mm is not None:
        noise = np.sqrt(np.nanmean(recon.noise_per_marker_mm**2, axis=1))
        if rest is not None and rest.name in recon.takes:
            noise_cov = position_covariance(usable_positions(recon.takes[rest.name], min_cameras))[0]
    res = analyze_responses(list(trials.averages), names, trials.rejections, du_names,
                            n_boot=settings.bootstrap_samples, noise_mm=noise,
                            noise_cov_mm2=noise_cov, jobs=settings.jobs)
    rejections = trials.rejections
    keep_all = kept_markers(rejections[rejections["du"].isna()], names, None)
    motions = []
    for take in session.takes_of_kind("motion"):
        if not is_plan(take.plan) or take.commands is None or take.name not in recon.takes:
            continue
        X = usable_positions(recon.takes[take.name], min_cameras)
        rows = session.read_commands(take.name)
        cmd = command_matrix(rows, session.fps, X.shape[0], list(session.du_ids))
        # evaluated over the markers its DUs move well (those in their response fits)
        keep = keep_all.copy()
        fitted = [res.fitted[d] for d in sorted(set(rows["du"])) if d in res.fitted]
        if fitted:
            keep &= np.any(fitted, axis=0)
        ev = evaluate_plan_take(X, cmd, rows, session.fps, take.plan, keep)
        motions.append(MotionResult(take.name, take.plan.upper(), ev))
    return replace(res, motions=tuple(motions), trials=trials)


def analyze(session: Session, reconstruction: Reconstruction, settings: RunSettings | None = None,
            **overrides) -> Analysis:
    """Trials, rejections and the paper's analyses of a reconstruction (:class:`Analysis`, the
    type :attr:`RunResult.analysis` holds; empty tables without response takes); nothing is
    written.

    ``overrides``: settings by name (``bootstrap_samples=0``, ``min_displacement_mm=0.1``...).
    """
    from mocap.workflows.run.settings import with_values

    settings = with_values(settings or RunSettings(), overrides, "analyze()")
    trials = compute_trials(session, reconstruction, settings)
    return analyze_session(session, reconstruction, trials, settings)


# --- outputs ---------------------------------------------------------------------------------

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


# --- the composer ----------------------------------------------------------------------------

class _Keys:
    """Every stage's key (``mocap.workflows.run.cache``): what each stage reads."""

    def __init__(self, session: Session, settings: RunSettings, fp,
                 writers: RunWriters = RunWriters()):
        from mocap.workflows.audit import nothing_to_analyse
        from mocap.workflows.run.cache import make_key

        face = [t for t in session.takes if t.kind in FACE_KINDS]
        template = (None if session.marker_template is None
                    else session.marker_template.to_csv(index=False))
        recon = {"reconstruction": settings.reconstruction, "labels": settings.labels}
        rest = _rest_take(session)
        if session.dimension == "2d":
            by_kind = {k: [fp(t.file) for t in session.takes_of_kind(k)] for k in ("wand", "ground")}
            self.calibrate = make_key("calibrate", cameras=session.cameras, wand=session.wand,
                                      ground=session.ground, takes=by_kind)
            self.markers = make_key("markers", calibrate=self.calibrate, template=template,
                                    rest=fp(rest.file) if rest else None, **recon)
        else:
            self.calibrate = None
            self.markers = make_key("markers3d", template=template,
                                    takes=[(t.name, fp(t.file)) for t in face],
                                    rest=rest.name if rest else None)
        recorded = _recorded(session, settings)
        self.takes = {t.name: make_key("take", markers=self.markers, file=fp(t.file),
                                       fill_gaps_frames=settings.fill_gaps_frames,
                                       record=t.name in recorded, **recon)
                      for t in face}
        # a command file's key holds its take's offset (the same file read on another clock)
        commands = {t.name: fp(t.commands) if not t.commands_offset_s
                    else (fp(t.commands), t.commands_offset_s)
                    for t in session.takes if t.commands is not None}
        responses = [(t.name, t.du, t.trial, self.takes[t.name], commands.get(t.name))
                     for t in session.takes_of_kind("response")]
        rest_key = self.takes.get(rest.name) if rest else None
        self.trials = make_key("trials", responses=responses, rest=rest_key, fps=session.fps,
                               rejections=settings.rejections)
        motions = [(t.name, t.plan, self.takes[t.name], commands.get(t.name))
                   for t in session.takes_of_kind("motion")]
        self.analyze = make_key("analyze", trials=self.trials, motions=motions, dus=session.dus,
                                du_ids=session.du_ids, bootstrap=settings.bootstrap_samples,
                                figures=writers.analysis_figures is not None)
        self.audit = make_key("audit", trials=self.trials, calibrate=self.calibrate,
                              takes=self.takes, min_cameras=settings.reconstruction.min_cameras,
                              session=session.name, unanalysable=nothing_to_analyse(session),
                              commands=commands,
                              figures=writers.audit_figures is not None)
        self.recording = make_key("recording", analyze=self.analyze if settings.analyze else None,
                                  audit=self.audit, commands=commands, du_ids=session.du_ids,
                                  record_blobs=settings.record_blobs,
                                  writer=writers.recording is not None)


class _Composer:
    """One run's stages with their cache (``store`` None: compute all, write nothing)."""

    def __init__(self, session: Session, out: Path | None, settings: RunSettings, say: Say,
                 bars: bool | None, store, writers: RunWriters = RunWriters()):
        self.session, self.out, self.settings = session, out, settings
        self.say, self.bars, self.store, self.writers = say, bars, store, writers
        if store is not None:  # every input file hashed at once, on the run's cores
            store.fingerprints.prefetch([p for t in session.takes for p in (t.file, t.commands)],
                                        settings.jobs)
        self.keys = (_Keys(session, settings, store.fingerprints, writers) if store is not None
                     else None)
        self.timings: dict[str, float] = {}
        self.reused: list[str] = []
        self.computed: list[str] = []

    def _saved(self, name: str) -> tuple[bool, object]:
        """(True, (value, files)) when the stage's saved result has its key and files."""
        if self.store is None:
            return False, None
        hit, saved = self.store.load(name, getattr(self.keys, name))
        return (True, saved) if hit and all(Path(self.out / f).exists() for f in saved[1]) \
            else (False, None)

    def stage(self, name: str, compute, write=None):
        """The stage's result: reused when its key and files match, else computed and
        written (``write(value) -> files``) then saved."""
        t = time.perf_counter()
        key = getattr(self.keys, name) if self.keys is not None else None
        hit, saved = self._saved(name)
        if hit:
            self.reused.append(name)
            self.timings[f"{name}_s"] = time.perf_counter() - t
            return saved[0]
        value = compute()
        files = write(value) if (write is not None and self.out is not None) else []
        if self.store is not None:
            rel = [str(Path(f).relative_to(self.out)) for f in files or []]
            self.store.save(name, key, (value, rel))
        self.computed.append(name)
        self.timings[f"{name}_s"] = time.perf_counter() - t
        return value

    def reconstruction(self, calibration) -> Reconstruction:
        session, settings, out, store = self.session, self.settings, self.out, self.store
        t = time.perf_counter()
        markers = self.stage("markers", lambda: find_markers(session, calibration, settings))
        names = list(markers.names)
        self.say(f"{len(names)} markers" + (" found on the rest take" if session.dimension == "2d" else ""))
        face = [t.name for t in session.takes if t.kind in FACE_KINDS]
        done: dict[str, TakeReconstruction] = {}
        stored: dict[str, tuple] = {}
        if store is not None:
            for name in face:
                st = _stored_take(out, store, self.keys.takes[name], name, names)
                if st is not None:
                    stored[name] = st
        todo = [n for n in face if n not in stored]
        if stored:
            self.say(f"reusing {len(stored)} of {len(face)} reconstructed takes"
                     + (f"; reconstructing {len(todo)}" if todo else ""))
        for tr in progress_bar(_map_takes(session, todo, calibration, markers, settings,
                                  _recorded(session, settings)), len(todo),
                       "reconstructing takes", self.bars):
            if out is not None:
                _write_take(out, store, self.keys.takes[tr.name] if store else "", tr, names)
            done[tr.name] = tr
            s = tr.labeled.stats
            self.say(f"  {tr.name}: {s.labeled_points} labeled points, "
                     f"{s.missing_marker_frames} marker-frames missing")
        n_reused = len(face) - len(todo)
        if n_reused:
            self.reused.append(f"reconstruct ({n_reused} of {len(face)} takes)")
        if todo:
            self.computed.append(f"reconstruct ({len(todo)} of {len(face)} takes)")
        self.timings["reconstruct_s"] = time.perf_counter() - t
        return assemble(session, markers, done, stored)

    def run(self) -> RunResult:
        session, settings, out, say = self.session, self.settings, self.out, self.say
        t0 = time.perf_counter()
        say(f"session {session.name}: {len(session.takes)} takes, {session.dimension}")
        changed = self.changed_settings()
        if changed:
            say(f"settings changed since the last run in {out}: {changed}")
        # the manifest, the take headers and every command file are checked here; each take's
        # rows are validated by the stage that reads them (read once)
        t = time.perf_counter()
        for take in session.takes:
            if take.commands is not None:
                session.read_commands(take.name)
        self.timings["validate_s"] = time.perf_counter() - t
        stages = ["validate"]

        calibration = None
        if session.dimension == "2d":
            from mocap.calib.calibration_file import write_calibration

            calibration = self.stage(
                "calibrate", lambda: calibrate(session, progress=say),
                lambda c: [write_calibration(out / "calibration.toml", c.rig, c.quality)])
            stages.append("calibrate")
            say(f"calibration {calibration.quality['rating']}")

        recon = self.reconstruction(calibration)
        stages.append("reconstruct" if session.dimension == "2d" else "load_labeled")
        # the recording's larger part (rig, calibration, takes) is written beside the stages
        # that follow; its analyses' part and the commit come last
        recording = settings.recording and out is not None and self.writers.recording is not None
        recorder = None
        if recording and not self._saved("recording")[0]:
            recorder = self.writers.recording(
                out / "session.rrd", RunResult(session, settings, calibration, recon, None, None,
                                               None, {}, out, ()))
        try:
            result = self._after_reconstruction(calibration, recon, stages)
        except BaseException:
            if recorder is not None:
                recorder.abort()
            raise
        if recording:  # reused when it was not started (else started now, should it be gone)
            self.stage("recording", lambda: None, lambda _: [
                (recorder or self.writers.recording(out / "session.rrd", result)).finish(result)])
            stages.append("recording")
            say(f"Rerun recording: {out / 'session.rrd'} "
                f"({(out / 'session.rrd').stat().st_size / 1e6:.1f} MB)")
        if self.reused:
            say(f"reused from the earlier run in {out}: {', '.join(self.reused)}")
            say(f"computed: {', '.join(self.computed) or 'nothing'}")
        self.timings["total_s"] = time.perf_counter() - t0
        summary = self.summary(stages, recon, result.trials, result.analysis, calibration,
                               result.audit)
        if out is not None:
            write_text(out / "summary.json", json.dumps(summary, indent=2))
            if self.store is not None:
                self.store.fingerprints.save()
        return replace(result, summary=summary, reused=tuple(self.reused),
                       computed=tuple(self.computed))

    def _after_reconstruction(self, calibration, recon: Reconstruction,
                              stages: list[str]) -> RunResult:
        """The trials, analyses and audit of a reconstruction (a RunResult without summary)."""
        session, settings, out, say = self.session, self.settings, self.out, self.say

        def write_trials(tr: Trials):
            return [write_parquet(tr.responses, out / "responses.parquet"),
                    write_csv(tr.rejections, out / "rejections.csv")]

        trials = self.stage("trials", lambda: compute_trials(session, recon, settings), write_trials)
        stages.append("trials")

        analysis = None
        if trials.averages and settings.analyze:
            analysis = self.stage(  # stored without its trials (the trials stage has them)
                "analyze", lambda: replace(analyze_session(session, recon, trials, settings),
                                           trials=None),
                lambda res: write_analysis(out, session, recon, trials, res, self.bars,
                                           self.writers.analysis_figures, settings.jobs))
            analysis = replace(analysis, trials=trials)
            stages.append("analyze")
            say(f"analyses: {len(trials.averages)} DUs, {len(analysis.motions)} motion takes evaluated")

        from mocap.workflows.audit import audit_capture, command_alignment, nothing_to_analyse

        min_cam = settings.reconstruction.min_cameras
        audit = self.stage(
            "audit", lambda: audit_capture(session.name, calibration, recon, trials.averages,
                                           trials.rejections, min_cameras=min_cam,
                                           unanalysable=nothing_to_analyse(session),
                                           alignment=command_alignment(session, recon, min_cam)),
            lambda a: write_audit_files(out, a, recon, calibration,
                                        self.writers.audit_figures))
        stages.append("audit")

        return RunResult(session, settings, calibration, recon, trials, analysis, audit, {},
                         out, ())

    def changed_settings(self) -> str:
        """The settings that differ from the last run's summary.json, as text ('' if none)."""
        if self.out is None or not (self.out / "summary.json").is_file():
            return ""
        try:
            before = json.loads((self.out / "summary.json").read_text()).get("settings") or {}
        except ValueError:
            return ""

        def flat(d, prefix=""):
            for k, v in d.items():
                if isinstance(v, dict):
                    yield from flat(v, f"{prefix}{k}.")
                else:
                    yield f"{prefix}{k}", v

        old, new = dict(flat(before)), dict(flat(to_dict(self.settings)))
        return ", ".join(f"{k} {old[k]!r} -> {v!r}" for k, v in new.items()
                         if k in old and old[k] != v and k != "jobs")

    def summary(self, stages, recon, trials, analysis, calibration, audit) -> dict:
        session = self.session
        counts = {"takes": {}, "rows": 0}
        for take in session.takes:
            counts["takes"][take.kind] = counts["takes"].get(take.kind, 0) + 1
        stats = recon.stats
        counts["rows"] = int(sum(s.blobs or s.points for s in stats.values()))
        names = list(recon.markers.names)
        warnings_list = list(session.warnings) + [w for a in trials.averages for w in a.warnings]
        if audit.get("nothing_to_analyse"):
            warnings_list.append(audit["nothing_to_analyse"])
        summary = {
            "session": {"name": session.name, "dir": str(Path(session.root).resolve()),
                        "dimension": session.dimension, "fps": session.fps,
                        "cameras": list(session.camera_ids), "dus": list(session.du_ids)},
            "stages": stages,
            "versions": _versions(),
            "settings": to_dict(self.settings),
            "reused": self.reused,
            "computed": self.computed,
            "timings_s": self.timings,
            "counts": counts,
            "warnings": warnings_list,
            "markers": {"count": len(names), "names": names,
                        "missing_from_template": list(recon.markers.missing_from_template)},
            "reconstruction": {"takes": {n: asdict(s) for n, s in stats.items()},
                               "labeled_points": recon.labeled_points},
            "noise_floor_mm": recon.noise_floor_mm,
            "rejections": {str(k): int(v) for k, v in
                           trials.rejections["reason"].value_counts().items()},
            "audit": {"verdict": audit["verdict"], "flagged": audit["flagged"]},
        }
        if analysis is not None:
            summary["properties"] = analysis.properties[  # literal, then corrected (docs/outputs.md)
                ["du", "sensitivity", "hysteresis", "dyssynchrony", "linearity_mean",
                 "sensitivity_corrected", "hysteresis_corrected", "dyssynchrony_corrected",
                 "linearity_mean_corrected"]].to_dict("records")
            summary["motion_evaluations"] = [
                {"take": take, "plan": plan, "rms_forward": ev.rms_forward,
                 "rms_backward": ev.rms_backward, "lag_s": ev.lag_s}
                for take, plan, ev in analysis.motions]
        if calibration is not None:
            q = calibration.quality
            summary["calibration"] = {k: q[k] for k in (
                "rating", "reprojection_rms_px_all", "wand_length_error_mean_mm",
                "wand_length_error_sd_mm", "point_error_mm") if k in q}
        return summary


def run(session: Session, out_dir: str | Path | None = None,
        settings: RunSettings = RunSettings(), *, progress: Say | None = None,
        bars: bool | None = False, force: bool = False, writers: RunWriters = RunWriters()
        ) -> RunResult:
    """Every stage on ``session``; the results, and (with ``out_dir``) docs/outputs.md's files.

    out_dir : None writes nothing at all. Otherwise the folder is locked for the run (a second
        run into it is refused: ``mocap.workflows.run.lock.OutputInUse``), results of an earlier run with
        the same keys are reused (``force``: recompute everything), and takes are written as
        they finish, so a killed run resumes from them.
    progress : called with a line of text per step; bars : tqdm progress bars on stderr (None:
        when stderr is a terminal).
    writers : the figures and the recording (``mocap.outputs.run_writers.WRITERS``, as ``mocap run``
        writes them); the default writes the data files only (no figures/, no session.rrd).
    """
    say = progress or _quiet
    if out_dir is None:
        return _Composer(session, None, settings, say, bars, None, writers).run()
    from mocap.workflows.run.cache import RunStore
    from mocap.workflows.run.lock import RunLock

    out = Path(out_dir)
    check_output_path(out, sessions=[session.root], option="out_dir", kind="folder")
    out.mkdir(parents=True, exist_ok=True)
    with RunLock(out) as lock:
        if lock.note:
            say(lock.note)
        return _Composer(session, out, settings, say, bars, RunStore(out, force), writers).run()


def run_session(session_dir: str | Path, out_dir: str | Path | None,
                progress: Say | None = None, settings: RunSettings = RunSettings(), *,
                bars: bool | None = False, force: bool = False,
                writers: RunWriters = RunWriters()) -> RunResult:
    """:func:`run` on the session folder ``session_dir`` (loaded and checked first)."""
    return run(load_session(session_dir), out_dir, settings, progress=progress, bars=bars,
               force=force, writers=writers)
