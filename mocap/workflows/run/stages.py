"""The run's stages: pure functions from one typed result to the next, nothing written.

    Session -> calibrate -> CalibrationResult (raw sessions)
            -> find_markers -> MarkerSet -> reconstruct -> Reconstruction (every face take)
            -> compute_trials -> Trials (averages, responses, rejections)
            -> analyze_session -> Analysis (the paper's analyses, motion evaluations)

Positions in mm (NaN: not seen), times in s. Face takes are reconstructed in worker processes
for large raw sessions (``PARALLEL_MIN_BYTES``). The composer
(:mod:`mocap.workflows.run.pipeline`) joins these stages with their cache and files.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Iterator, Mapping

import numpy as np
import pandas as pd

from mocap.analysis.session_analysis import Analysis
from mocap.calib.camera import CameraRig
from mocap.core.schedules import schedule_timing
from mocap.core.session import Session, SessionError, command_matrix
from mocap.reconstruction.camera_count import usable_positions
from mocap.reconstruction.labeled_input import dense_from_3d, marker_names_3d
from mocap.reconstruction.labeling import MarkerSet, identify_markers
from mocap.reconstruction.takes import (
    BlobRoles,
    CaptureCounts,
    LazyTakes,
    Reconstruction,
    TakeReconstruction,
    labeled_take,
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
from mocap.workflows.run.result import Trials
from mocap.workflows.run.settings import RunSettings

__all__ = ["calibrate", "find_markers", "reconstruct", "compute_trials", "analyze_session",
           "analyze"]

FACE_KINDS = ("rest", "response", "motion")
RESPONSE_COLUMNS = ["du", "frame", "time_s", "command", "marker", "x", "y", "z", "spread_mm",
                    "n_trials", "displacement_mm", "delta"]
Say = Callable[[str], None]


def _quiet(msg: str) -> None:
    pass


def progress_bar(iterable, total: int, desc: str, bars: bool | None):
    """A tqdm progress bar on stderr: shown when ``bars`` is True, or when None and stderr is a
    terminal."""
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=desc, unit="take" if "take" in desc else "it",
                disable=(None if bars is None else not bars), file=sys.stderr, leave=False,
                dynamic_ncols=True)


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
