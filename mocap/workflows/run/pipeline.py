"""The composer: one run of a session through every stage, raw exports to results.

The stages (:mod:`mocap.workflows.run.stages`) are pure functions from one typed result to the
next:

    Session -> calibrate -> CalibrationResult (raw sessions)
            -> find_markers -> MarkerSet -> reconstruct -> Reconstruction (every face take)
            -> compute_trials -> Trials (averages, responses, rejections)
            -> analyze_session -> Analysis (the paper's analyses, motion evaluations)
            -> audit_capture -> the audit report

``run`` joins them and returns one frozen :class:`~mocap.workflows.run.result.RunResult`.
Without an output folder it writes nothing. With one it writes docs/outputs.md's files atomically, holds the folder's lock
(:mod:`mocap.workflows.run.lock`) and keys every stage's results by what it reads
(:mod:`mocap.workflows.run.cache`, the keys in :mod:`mocap.workflows.run.keys`): a rerun reuses
what is unchanged, recomputes the rest and says which; a killed run resumes from the takes it
finished (the data files: :mod:`mocap.workflows.run.writers`).

The composer is a workflow: it draws no figure and writes no recording itself. The output
writers (figures, the Rerun recording) live in the outputs layer (:mod:`mocap.outputs.run_writers`)
and are passed in as :class:`~mocap.workflows.run.result.RunWriters`; without them a run writes
its data files only.
"""

from __future__ import annotations

import json
import platform
import time
from dataclasses import asdict, replace
from pathlib import Path

from mocap import __version__
from mocap.core.atomic import write_csv, write_parquet, write_text
from mocap.core.paths import check_output_path
from mocap.core.session import Session, load_session
from mocap.reconstruction.takes import Reconstruction, TakeReconstruction
from mocap.workflows.run.keys import _Keys
from mocap.workflows.run.result import RunResult, RunWriters, Trials
from mocap.workflows.run.settings import RunSettings, to_dict
from mocap.workflows.run.stages import (
    FACE_KINDS,
    Say,
    _map_takes,
    _quiet,
    _recorded,
    analyze_session,
    assemble,
    calibrate,
    compute_trials,
    find_markers,
    progress_bar,
)
from mocap.workflows.run.writers import _stored_take, _write_take, write_analysis, write_audit_files

__all__ = ["run", "run_session"]

# the output layout's version (docs/outputs.md): raised when a file or column is renamed or dropped
OUTPUT_LAYOUT = 2


def _versions() -> dict:
    import numpy
    import pandas
    import scipy

    return {"outputs_layout": OUTPUT_LAYOUT, "facemocap": __version__,
            "python": platform.python_version(),
            "numpy": numpy.__version__, "scipy": scipy.__version__, "pandas": pandas.__version__}


# --- the composer ----------------------------------------------------------------------------

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
