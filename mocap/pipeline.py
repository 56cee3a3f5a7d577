"""The composer: one run of a session through every stage, raw to result.

``run_session`` is the only place that joins the stages; each stage is a pure function of the
previous stages' results, and the returned ``RunResult`` holds every intermediate. Files are
written atomically under ``OUT_DIR`` per OUTPUTS.md.

Stages (as they land): validate -> calibrate (raw sessions) -> reconstruct -> trials, noise,
rejections -> analyses and figures -> audit -> Rerun recording.
"""

from __future__ import annotations

import json
import os
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from mocap import __version__
from mocap.analysis.paper_indices import schedule_timing
from mocap.atomic import write_csv, write_parquet, write_text
from mocap.paths import check_output_path
from mocap.reconstruct.camera_count import usable_samples
from mocap.reconstruct.correspondence import (
    ReconstructionSettings,
    blob_camera_index,
    reconstruct_points,
)
from mocap.reconstruct.labeled_input import dense_from_3d, marker_names_3d
from mocap.reconstruct.labeling import (
    LabelSettings,
    MarkerSet,
    identify_markers,
    label_take,
    trajectories_frame,
)
from mocap.reconstruct.trials import (
    RejectionSettings,
    TrialAverage,
    average_trials,
    find_rejections,
    noise_floor,
    responses_frame,
)
from mocap.session import Session, SessionError, command_matrix, load_session


def _versions() -> dict:
    import numpy
    import pandas
    import scipy

    return {"facemocap": __version__, "python": platform.python_version(),
            "numpy": numpy.__version__, "scipy": scipy.__version__, "pandas": pandas.__version__}


@dataclass(frozen=True)
class RunSettings:
    """Settings of a run; defaults follow the paper."""

    reconstruction: ReconstructionSettings = ReconstructionSettings()
    labels: LabelSettings = LabelSettings()
    rejections: RejectionSettings = RejectionSettings()
    fill_gaps_frames: int = 0  # interpolate gaps up to this many frames (always flagged)
    analyze: bool = True  # the paper's analyses and figures (off for an audit-only run)
    jobs: int = field(default_factory=lambda: os.cpu_count() or 1)  # processes over takes
    recording: bool = True  # write session.rrd (Rerun)
    record_blobs: str = "subset"  # 2D blobs in the recording: "subset" (wand, rest, first
    #                               response take), "all" face takes, or "none"


@dataclass
class Reconstruction:
    """Labeled trajectories kept for the later stages (response takes), plus statistics."""

    markers: MarkerSet
    dense: dict  # take name -> LabeledTake, for response takes and the rest take
    stats: dict
    noise_floor_mm: float | None
    noise_per_marker_mm: np.ndarray | None
    capture: dict = field(default_factory=dict)  # per camera / marker counts for the audit
    blob_roles: dict = field(default_factory=dict)  # take -> (frame, camera, x, y, role) arrays;
    #   role 0 labeled marker, 1 in an unlabeled point, 2 in no point (ghost)


@dataclass
class RunResult:
    """Everything a run produced; ``summary`` is what summary.json holds."""

    session: Session
    out_dir: Path
    summary: dict = field(default_factory=dict)
    calibration: object | None = None  # calib.wand_calibration.CalibrationResult (raw sessions)
    reconstruction: Reconstruction | None = None
    averages: list = field(default_factory=list)
    rejections: pd.DataFrame | None = None
    analysis: object | None = None  # mocap.analysis.session_analysis.SessionAnalysis
    audit: dict | None = None


def _take_frame_count(df: pd.DataFrame) -> int:
    return int(df["frame"].max()) + 1


def reconstruct_all(session: Session, out: Path, calibration, settings: "RunSettings",
                    say: Callable[[str], None]) -> Reconstruction:
    """Every take to labeled trajectories, written as trajectories/<take>.parquet."""
    keep_kinds = {"rest", "response"}
    dense: dict = {}
    blob_roles: dict = {}
    stats: dict = {"takes": {}}
    face_takes = [t for t in session.takes if t.kind in ("rest", "response", "motion")]
    if session.dimension == "2d":
        rig, quality = calibration.rig, calibration.quality
        rest = session.takes_of_kind("rest")
        if not rest:
            raise SessionError(f"{session.root}/session.toml: a raw session needs a 'rest' take "
                               "to find its markers")
        blobs = session.read_take(rest[0].name)
        pts = reconstruct_points(blobs, rig, quality, settings.reconstruction)
        markers = identify_markers(pts, _take_frame_count(blobs), session.marker_template,
                                   settings.labels)
        say(f"{len(markers.names)} markers found on the rest take '{rest[0].name}'")
        responses = session.takes_of_kind("response")
        subset = {rest[0].name} | ({responses[0].name} if responses else set())
        M = len(markers.names)
        capture = {"camera_blobs": np.zeros(len(rig), np.int64),
                   "camera_labeled_blobs": np.zeros(len(rig), np.int64),
                   "views": np.zeros((len(rig), M), np.int64),
                   "marker_frames": np.zeros(M, np.int64), "frames": 0,
                   "gaps": np.zeros(M, np.int64), "longest_gap": np.zeros(M, np.int64)}
        tasks = [(take.name, take.kind in keep_kinds,
                  settings.record_blobs == "all"
                  or (settings.record_blobs == "subset" and take.name in subset))
                 for take in face_takes]
        for name, res in _map_takes(session, out, rig, quality, markers, settings, tasks):
            lab, acc = res["labeled"], res["capture"]
            for k in ("camera_blobs", "camera_labeled_blobs", "views", "marker_frames", "gaps"):
                capture[k] += acc[k]
            capture["frames"] += acc["frames"]
            capture["longest_gap"] = np.maximum(capture["longest_gap"], acc["longest_gap"])
            stats["takes"][name] = res["stats"]
            if lab is not None:
                dense[name] = lab
            if res["roles"] is not None:
                blob_roles[name] = res["roles"]
            say(f"  {name}: {res['stats']['labeled_points']} labeled points, "
                f"{res['stats']['missing_marker_frames']} marker-frames missing")
    else:
        frames = {t.name: session.read_take(t.name) for t in face_takes}
        names = marker_names_3d(list(frames.values()), session.marker_template)
        rest_take = session.takes_of_kind("rest")
        rest_pos = (np.nanmedian(dense_from_3d(frames[rest_take[0].name], names).X, axis=0)
                    if rest_take else np.full((len(names), 3), np.nan))
        markers = MarkerSet(tuple(names), rest_pos)
        M = len(names)
        capture = {"marker_frames": np.zeros(M, np.int64), "frames": 0,
                   "gaps": np.zeros(M, np.int64), "longest_gap": np.zeros(M, np.int64)}
        for take in face_takes:
            lab = dense_from_3d(frames[take.name], names)
            missing = np.isnan(lab.X[..., 0])
            capture["marker_frames"] += (~missing).sum(axis=0)
            capture["frames"] += missing.shape[0]
            capture["gaps"] += _gap_counts(missing)
            capture["longest_gap"] = np.maximum(capture["longest_gap"], _longest_gaps(missing))
            write_parquet(trajectories_frame(lab, names), out / "trajectories" / f"{take.name}.parquet")
            stats["takes"][take.name] = lab.stats
            if take.kind in keep_kinds:
                dense[take.name] = lab
    noise, noise_mean = None, None
    rest = session.takes_of_kind("rest")
    if rest and rest[0].name in dense:
        noise, noise_mean = noise_floor(dense[rest[0].name].X)
    total = sum(s.get("labeled_points", s.get("points", 0)) for s in stats["takes"].values())
    stats["labeled_points"] = int(total)
    return Reconstruction(markers, dense, stats, noise_mean, noise, capture, blob_roles)


def reconstruct_take(session: Session, out: Path, rig, quality, markers: MarkerSet,
                     settings: "RunSettings", name: str, keep: bool, record: bool) -> dict:
    """One raw take to labeled trajectories (written as trajectories/<take>.parquet).

    Returns the take's statistics, its per-camera/marker capture counts, the LabeledTake when
    ``keep`` and the blobs' roles when ``record``. Independent of every other take once the rig
    is calibrated and the markers are known, so takes run in parallel (``RunSettings.jobs``).
    """
    blobs = session.read_take(name)
    n_frames = _take_frame_count(blobs)
    pts = reconstruct_points(blobs, rig, quality, settings.reconstruction)
    lab = label_take(pts, markers, n_frames, settings.labels, settings.fill_gaps_frames,
                     n_blobs=len(blobs))
    lab.stats["blobs"] = int(len(blobs))
    lab.stats["matched_blobs"] = int((pts.blob >= 0).sum())
    cam_idx = blob_camera_index(blobs["camera"], rig.ids)
    missing = np.isnan(lab.X[..., 0])
    capture = {
        "camera_blobs": np.bincount(cam_idx, minlength=len(rig)),
        "camera_labeled_blobs": np.bincount(cam_idx[lab.blob_marker >= 0], minlength=len(rig)),
        "views": lab.views, "marker_frames": (~missing).sum(axis=0), "frames": n_frames,
        "gaps": _gap_counts(missing), "longest_gap": _longest_gaps(missing),
    }
    write_parquet(trajectories_frame(lab, markers.names), out / "trajectories" / f"{name}.parquet")
    roles = None
    if record:
        role = np.full(len(blobs), 2, np.int8)  # in no 3D point: a ghost
        role[pts.blob[pts.blob >= 0]] = 1  # in a point that got no marker
        role[lab.blob_marker >= 0] = 0  # labeled
        roles = (blobs["frame"].to_numpy(), cam_idx, blobs["x"].to_numpy(), blobs["y"].to_numpy(), role)
    kept = usable_samples(lab, settings.reconstruction.min_cameras) if keep else None  # analyses' samples
    return {"stats": lab.stats, "capture": capture, "labeled": kept, "roles": roles}


def _worker_init() -> None:
    try:  # one process per core: no nested numba threads
        import numba

        numba.set_num_threads(1)
    except Exception:  # pragma: no cover - numba is a dependency
        pass


def _map_takes(session, out, rig, quality, markers, settings, tasks):
    """Yield (take name, result) for every task, in parallel over ``settings.jobs`` processes."""
    jobs = max(1, min(int(settings.jobs), len(tasks)))
    if jobs == 1:
        for name, keep, record in tasks:
            yield name, reconstruct_take(session, out, rig, quality, markers, settings, name, keep, record)
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn"),
                             initializer=_worker_init) as pool:
        futures = [pool.submit(reconstruct_take, session, out, rig, quality, markers, settings,
                               name, keep, record) for name, keep, record in tasks]
        for (name, _, _), fut in zip(tasks, futures):
            yield name, fut.result()


def _gap_counts(missing: np.ndarray) -> np.ndarray:
    """(M,) number of interior runs of missing frames per marker; missing (n_frames, M)."""
    starts = missing[1:] & ~missing[:-1]
    return starts.sum(axis=0) + missing[0]


def _longest_gaps(missing: np.ndarray) -> np.ndarray:
    """(M,) longest run of missing frames per marker (vectorised run lengths)."""
    n = missing.shape[0]
    # the run length at a missing frame is its distance to the last frame that was seen
    idx = np.where(~missing, np.arange(n)[:, None], -1)
    run_len = np.arange(n)[:, None] - np.maximum.accumulate(idx, axis=0)
    return np.where(missing, run_len, 0).max(axis=0)


def average_responses(session: Session, recon: Reconstruction) -> list[TrialAverage]:
    """Per DU, its response takes averaged over trials."""
    out = []
    by_du: dict[int, list] = {}
    for take in session.takes_of_kind("response"):
        by_du.setdefault(int(take.du), []).append(take)
    for du, takes in sorted(by_du.items()):
        takes = sorted(takes, key=lambda t: (t.trial or 0, t.name))
        X = [recon.dense[t.name].X for t in takes]
        rows = [session.read_commands(t.name) for t in takes]
        cmds = [command_matrix(r, session.fps, x.shape[0], [du])[:, 0] for r, x in zip(rows, X)]
        first = rows[0][rows[0]["du"] == du]
        timing = schedule_timing(first["time_s"].to_numpy(float), first["command"].to_numpy(float),
                                 source=f"take {takes[0].name}: its command file")
        out.append(average_trials(du, X, cmds, session.fps, [t.name for t in takes], timing))
    return out


def run_analyses(session: Session, recon: Reconstruction, averages, rejections, out: Path,
                 say: Callable[[str], None]):
    """The paper's analyses, their tables and figures; motion takes evaluated against plans."""
    from mocap.analysis import figures
    from mocap.analysis.session_analysis import analyze_responses, evaluate_plan_take, is_plan, kept_markers

    names = list(recon.markers.names)
    du_names = {d.id: d.name for d in session.dus}
    feedback = {d.id: d.feedback for d in session.dus}
    noise, noise_cov = None, None
    if recon.noise_per_marker_mm is not None:
        noise = np.sqrt(np.nanmean(recon.noise_per_marker_mm**2, axis=1))
        rest = session.takes_of_kind("rest")
        if rest and rest[0].name in recon.dense:
            from mocap.analysis.linearity import position_covariance

            noise_cov = position_covariance(recon.dense[rest[0].name].X)[0]
    res = analyze_responses(averages, names, rejections, du_names, noise_mm=noise,
                            noise_cov_mm2=noise_cov)
    write_csv(res.properties, out / "properties.csv")
    write_csv(res.linearity, out / "linearity.csv")
    write_csv(res.marker_properties, out / "marker_properties.csv")
    fig = out / "figures"
    rest = recon.markers.rest_mm
    for avg in averages:
        figures.displacement_field(fig / f"du{avg.du:02d}_displacement_field.png", avg.du,
                                   du_names.get(avg.du, ""), rest, res.fields_mm[avg.du],
                                   res.keep[avg.du])
        figures.response_curves(fig / f"du{avg.du:02d}_response.png", avg.du,
                                du_names.get(avg.du, ""), res.paper[avg.du], avg.fps)
    props = res.properties
    figures.linearity_bars(fig / "linearity.png", props["du"], props["linearity_mean"],
                           props["linearity_std"])
    figures.property_chart(fig / "property_chart.png", props["du"], props["sensitivity"],
                           props["hysteresis"], props["dyssynchrony"],
                           [feedback.get(d, False) for d in props["du"]])
    keep_all = kept_markers(rejections[rejections["du"].isna()], names, None)
    for take in session.takes_of_kind("motion"):
        if not is_plan(take.plan) or take.commands is None:
            continue
        path = out / "trajectories" / f"{take.name}.parquet"
        df = pd.read_parquet(path, columns=["frame", "marker", "x", "y", "z"])
        n_frames = int(df["frame"].max()) + 1
        X = df[["x", "y", "z"]].to_numpy().reshape(n_frames, len(names), 3)
        rows = session.read_commands(take.name)
        cmd = command_matrix(rows, session.fps, n_frames, list(session.du_ids))
        # evaluated over the markers its DUs move well (those in their response fits)
        keep = keep_all.copy()
        fitted = [res.fitted[d] for d in sorted(set(rows["du"])) if d in res.fitted]
        if fitted:
            keep &= np.any(fitted, axis=0)
        ev = evaluate_plan_take(X, cmd, rows, session.fps, take.plan, keep)
        res.motions.append((take.name, take.plan.upper(), ev))
        figures.motion_result(fig / f"motion_{take.name}.png", f"{take.name} (plan {take.plan})", ev)
    say(f"analyses: {len(averages)} DUs, {len(res.motions)} motion takes evaluated; figures in {fig}")
    return res


def run_session(session_dir: str | Path, out_dir: str | Path,
                progress: Callable[[str], None] | None = None,
                settings: RunSettings = RunSettings()) -> RunResult:
    """Run every available stage on ``session_dir`` and write results into ``out_dir``."""
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    session = load_session(session_dir)
    out = Path(out_dir)
    check_output_path(out, sessions=[session.root])
    out.mkdir(parents=True, exist_ok=True)
    say(f"session {session.name}: {len(session.takes)} takes, {session.dimension}")

    # the manifest, the take headers and every command file are checked here; each take's rows
    # are validated by the stage that reads them (read once: 95 M blob rows in the paper study)
    counts = {"takes": {}, "rows": 0}
    t = time.perf_counter()
    for take in session.takes:
        counts["takes"][take.kind] = counts["takes"].get(take.kind, 0) + 1
        if take.commands is not None:
            session.read_commands(take.name)
    timings["validate_s"] = time.perf_counter() - t
    say(f"session checked: {len(session.takes)} takes, command files valid")
    stages = ["validate"]
    warnings_list = list(session.warnings)

    calibration = None
    if session.dimension == "2d":
        from mocap.calib.calibration_file import write_calibration
        from mocap.calib.wand_calibration import calibrate_session

        t = time.perf_counter()
        calibration = calibrate_session(session, progress=say)
        write_calibration(out / "calibration.toml", calibration.rig, calibration.quality)
        timings["calibrate_s"] = time.perf_counter() - t
        stages.append("calibrate")
        say(f"calibration {calibration.quality['rating']} in {timings['calibrate_s']:.1f} s")

    # --- reconstruction (raw) or labeled input (3D) -> trajectories/<take>.parquet ----------
    t = time.perf_counter()
    recon = reconstruct_all(session, out, calibration, settings, say)
    timings["reconstruct_s"] = time.perf_counter() - t
    stages.append("reconstruct" if session.dimension == "2d" else "load_labeled")
    counts["rows"] = int(sum(s.get("blobs", s.get("points", 0)) for s in recon.stats["takes"].values()))

    # --- trials, noise floor, rejections -> responses.parquet, rejections.csv -----------------
    t = time.perf_counter()
    averages = average_responses(session, recon)
    names = list(recon.markers.names)
    if averages:
        responses = pd.concat([responses_frame(a, names) for a in averages], ignore_index=True)
    else:
        responses = pd.DataFrame(columns=["du", "frame", "time_s", "command", "marker", "x", "y",
                                          "z", "spread_mm", "n_trials", "displacement_mm", "delta"])
    rejections = find_rejections(averages, names, settings.rejections)
    rejected = set(zip(rejections["du"].astype("float").fillna(-1).astype(int), rejections["marker"]))
    all_du = {m for d, m in rejected if d == -1}
    responses["rejected"] = [(m in all_du) or ((d, m) in rejected)
                             for d, m in zip(responses["du"], responses["marker"])] if len(responses) else []
    write_parquet(responses, out / "responses.parquet")
    write_csv(rejections, out / "rejections.csv")
    timings["trials_s"] = time.perf_counter() - t
    stages.append("trials")
    for a in averages:
        warnings_list.extend(a.warnings)

    # --- analyses and figures -> properties.csv, linearity.csv, figures/ ---------------------
    analysis_result = None
    if averages and settings.analyze:
        t = time.perf_counter()
        analysis_result = run_analyses(session, recon, averages, rejections, out, say)
        timings["analyze_s"] = time.perf_counter() - t
        stages.append("analyze")

    # --- capture-quality audit -> audit.json, audit.md --------------------------------------
    t = time.perf_counter()
    from mocap.audit import write_audit

    partial = RunResult(session=session, out_dir=out, calibration=calibration,
                        reconstruction=recon, averages=averages, rejections=rejections)
    audit = write_audit(partial, out, min_cameras=settings.reconstruction.min_cameras)
    from mocap.analysis.figures import audit_figures  # the audit's figures (outputs layer)
    audit_figures(partial, audit, out)
    timings["audit_s"] = time.perf_counter() - t
    stages.append("audit")

    # --- Rerun recording -> session.rrd ---------------------------------------------------
    if settings.recording:
        from mocap.recording import write_recording

        t = time.perf_counter()
        partial.analysis = analysis_result
        partial.audit = audit
        write_recording(out / "session.rrd", partial)
        timings["recording_s"] = time.perf_counter() - t
        stages.append("recording")
        say(f"Rerun recording written: {out / 'session.rrd'} "
            f"({(out / 'session.rrd').stat().st_size / 1e6:.1f} MB)")

    summary = {
        "session": {"name": session.name, "dir": str(Path(session_dir).resolve()),
                    "dimension": session.dimension, "fps": session.fps,
                    "cameras": list(session.camera_ids), "dus": list(session.du_ids)},
        "stages": stages,
        "versions": _versions(),
        "timings_s": timings,
        "counts": counts,
        "warnings": warnings_list,
        "markers": {"count": len(names), "names": names,
                    "missing_from_template": list(recon.markers.missing_from_template)},
        "reconstruction": recon.stats,
        "noise_floor_mm": recon.noise_floor_mm,
        "rejections": {str(k): int(v) for k, v in rejections["reason"].value_counts().items()},
        "audit": {"verdict": audit["verdict"], "flagged": audit["flagged"]},
    }
    if analysis_result is not None:
        summary["properties"] = analysis_result.properties[
            ["du", "sensitivity", "hysteresis", "dyssynchrony", "linearity_mean"]].to_dict("records")
        summary["motion_evaluations"] = [
            {"take": take, "plan": plan, "rms_forward": ev.rms_forward,
             "rms_backward": ev.rms_backward, "lag_s": ev.lag_s}
            for take, plan, ev in analysis_result.motions]
    if calibration is not None:
        q = calibration.quality
        summary["calibration"] = {k: q[k] for k in (
            "rating", "reprojection_rms_px_all", "wand_length_error_mean_mm",
            "wand_length_error_sd_mm", "point_error_mm") if k in q}
    timings["total_s"] = time.perf_counter() - t0
    write_text(out / "summary.json", json.dumps(summary, indent=2))
    return RunResult(session=session, out_dir=out, summary=summary, calibration=calibration,
                     reconstruction=recon, averages=averages, rejections=rejections,
                     analysis=analysis_result, audit=audit)
