"""The Rerun recording of a run: the only module that imports ``rerun``.

``write_recording(path, result)`` turns a :class:`mocap.workflows.run.result.RunResult` (read only) into a ``.rrd`` file
(written to a temporary name, then renamed). It uses an explicit ``RecordingStream`` and Rerun's
columnar ``send_columns`` for every series (no Python loop per frame). What it holds, on the
capture's own timelines ``frame`` (sequence) and ``time`` (seconds; each take starts at 0):

- ``world``: y-up view coordinates; an annotation context naming every marker (class id = marker
  index), so 3D points carry names without a string per point;
- ``world/cameras/<id>``: the camera's pose (world from camera) and, under ``image``, its pinhole
  (K, image size, OpenCV axes); ``image/blobs/<take>``: 2D blobs coloured by role (green: labeled
  marker, orange: in a 3D point left unlabeled, red: in no point, a ghost) for the wand take and a
  subset of takes (all on request); ``image/wand``: the wand sightings the calibration used
  (green) and rejected (red);
- ``world/calibration/wand``: the fitted wand per frame; ``world/calibration/ground``: the
  ground square's markers as measured; ``plots/calibration/residual_px``: each camera's worst
  marker residual per wand frame;
- ``world/rest``: the markers at rest; ``world/rejected``: rejected markers, labeled with why;
- ``world/takes/<take>/markers``: labeled 3D markers over time; ``.../paths``: each marker's
  trajectory as a line strip;
- ``plots/commands/<take>``: the DUs' commands as scalar series;
- ``plots/du<NN>/response``: measured mean normalised displacement along each marker's
  principal direction and the along-path estimator's forward and backward sigmoids (along the
  ramps' command lines; properties.csv's ``*_along_path`` columns);
- ``charts/property_chart``: sensitivity (x 1000) against hysteresis, coloured by dyssynchrony,
  all three the noise-corrected estimates (properties.csv's ``*_corrected`` columns);
- ``annotations/rejections`` and ``annotations/audit``: markdown tables;
- a default blueprint: the 3D view, a camera view, the plots and the property chart.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mocap.core.atomic import atomic_path

GREEN, ORANGE, RED, GREY = (60, 200, 90), (240, 160, 40), (230, 60, 60), (150, 150, 150)
ROLE_COLOURS = np.array([GREEN, ORANGE, RED], np.uint8)


def _times(rr, frames: np.ndarray, fps: float):
    return [rr.TimeColumn("frame", sequence=frames.astype(np.int64)),
            rr.TimeColumn("time", duration=frames / fps)]


def _points_over_time(rec, rr, path, frame, fps, positions, **columns):
    """Send points grouped by frame (rows sorted by frame) as one column batch."""
    if frame.size == 0:
        return
    if np.any(frame[1:] < frame[:-1]):  # most callers pass rows already in frame order
        order = np.argsort(frame, kind="stable")
        frame = frame[order]
        positions = positions[order]
        columns = {k: v[order] for k, v in columns.items()}
    # the frames' runs (no second sort, as np.unique would do)
    starts = np.r_[0, np.flatnonzero(frame[1:] != frame[:-1]) + 1]
    uniq, counts = frame[starts], np.diff(np.r_[starts, frame.size])
    kind = rr.Points3D if positions.shape[1] == 3 else rr.Points2D
    cols = kind.columns(positions=positions, **columns)
    rec.send_columns(path, indexes=_times(rr, uniq, fps), columns=cols.partition(lengths=counts))


def _series(rec, rr, path, names, values, fps):
    """values (n_frames, n_series): one scalar series per column, NaN where absent."""
    rec.log(path, rr.SeriesLines(names=list(names)), static=True)
    n, k = values.shape
    rec.send_columns(path, indexes=_times(rr, np.arange(n), fps),
                     columns=rr.Scalars.columns(scalars=values.ravel()).partition(lengths=[k] * n))


def blueprint(camera_ids):
    import rerun.blueprint as rrb

    cam_views = [rrb.Spatial2DView(origin=f"world/cameras/{c}/image", name=c) for c in camera_ids]
    right = [rrb.TimeSeriesView(origin="plots", name="plots"),
             rrb.Spatial2DView(origin="charts", name="property chart (noise-corrected estimates)")]
    if cam_views:
        right.insert(0, rrb.Tabs(*cam_views))
    return rrb.Blueprint(rrb.Horizontal(rrb.Spatial3DView(origin="world", name="face and rig"),
                                        rrb.Vertical(*right), column_shares=[3, 2]),
                         collapse_panels=True)


def write_recording(path: str | os.PathLike, result) -> Path:
    """Write the run's Rerun recording to ``path`` (atomically); return the path."""
    return RecordingWriter(path, result, background=False).finish(result)


class RecordingWriter:
    """A run's recording written in two parts, so that the larger part overlaps the run.

    ``RecordingWriter(path, result)`` opens the recording under a temporary name and logs what
    the reconstruction alone gives (the rig, the calibration, the rest positions and every
    take's markers, paths and commands: ~90 % of a paper run's recording) on a background
    thread; ``result`` needs ``session``, ``calibration`` and ``reconstruction`` only.
    :meth:`finish` adds the parts the trials, analyses and audit give, then renames the file
    onto ``path``; :meth:`abort` removes it. A failure on the thread is raised by
    :meth:`finish`. Rerun encodes and writes off Python's lock, so on a paper run the thread
    costs the trials and analyses little of their time (`benchmarks/profile.md`).
    """

    def __init__(self, path: str | os.PathLike, result, *, background: bool = True):
        import threading

        self.path = Path(path)
        self._paths = atomic_path(self.path)
        self._tmp = self._paths.__enter__()
        self._error: BaseException | None = None
        self._rec = None
        if background:
            self._thread = threading.Thread(target=self._first_part, args=(result,),
                                            name="facemocap-recording", daemon=True)
            self._thread.start()
        else:
            self._thread = None
            self._first_part(result)

    def _first_part(self, result) -> None:
        try:
            import rerun as rr

            session = result.session
            fps = float(session.fps)
            recon = result.reconstruction
            names = list(recon.markers.names)
            calib = result.calibration
            cam_ids = list(calib.rig.ids) if calib is not None else []
            rec = rr.RecordingStream("facemocap", recording_id=f"facemocap-{session.name}")
            self._rec = rec
            rec.save(str(self._tmp), default_blueprint=blueprint(cam_ids))
            rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
            rec.log("world", rr.AnnotationContext([(i, n) for i, n in enumerate(names)]),
                    static=True)
            _log_rig_and_calibration(rec, rr, result, fps)
            rest = recon.markers.rest_mm
            ok = np.all(np.isfinite(rest), axis=1)
            rec.log("world/rest", rr.Points3D(rest[ok], class_ids=np.flatnonzero(ok), radii=0.6),
                    static=True)
            _log_takes(rec, rr, result, fps, names)
        except BaseException as exc:  # noqa: BLE001  (raised again by finish)
            self._error = exc

    def _join(self) -> None:
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def finish(self, result) -> Path:
        """Add the trials', analyses' and audit's parts of ``result`` (a complete
        :class:`mocap.workflows.run.result.RunResult`), close the recording and commit it; return its path."""
        import rerun as rr

        self._join()
        try:
            if self._error is not None:
                raise self._error
            rec = self._rec
            fps = float(result.session.fps)
            _log_responses(rec, rr, result, fps)
            _log_annotations(rec, rr, result, list(result.reconstruction.markers.names))
            rec.flush()
            rec.disconnect()
            self._rec = None
        except BaseException as exc:
            self._close()
            self._paths.__exit__(type(exc), exc, exc.__traceback__)
            raise
        self._paths.__exit__(None, None, None)
        return self.path

    def abort(self) -> None:
        """Stop (after the thread's part) and remove the temporary file; nothing is written."""
        self._join()
        self._close()
        err = RuntimeError("recording aborted")
        self._paths.__exit__(RuntimeError, err, None)

    def _close(self) -> None:
        if self._rec is not None:
            try:
                self._rec.disconnect()
            finally:
                self._rec = None


def _log_rig_and_calibration(rec, rr, result, fps):
    calib = result.calibration
    if calib is None:
        return
    for cam in calib.rig:
        rec.log(f"world/cameras/{cam.id}", rr.Transform3D(translation=cam.center, mat3x3=cam.R.T),
                static=True)
        rec.log(f"world/cameras/{cam.id}/image",
                rr.Pinhole(image_from_camera=cam.K, resolution=[cam.width, cam.height],
                           camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=60.0),
                static=True)
    obs = calib.wand
    for ci, cid in enumerate(calib.rig.ids):
        sel = obs.camera == ci
        if not sel.any():
            continue
        n_w = obs.uv.shape[1]
        used = np.repeat(calib.used[sel], n_w)
        colours = np.where(used[:, None], np.array(GREEN, np.uint8), np.array(RED, np.uint8))
        _points_over_time(rec, rr, f"world/cameras/{cid}/image/wand", np.repeat(obs.frame[sel], n_w),
                          fps, obs.uv[sel].reshape(-1, 2), colors=colours)
    if calib.ground is not None:  # the ground square as measured, in the world frame it defines
        g = calib.ground
        pts = g.points_mm @ g.R.T + g.t
        rec.log("world/calibration/ground", rr.Points3D(pts, radii=1.5, colors=(80, 160, 255),
                                                        labels=[f"G{k + 1}" for k in range(len(pts))]),
                static=True)
    if calib.wand_points_mm is not None:
        F, n_w, _ = calib.wand_points_mm.shape
        _points_over_time(rec, rr, "world/calibration/wand", np.repeat(calib.wand_frames, n_w), fps,
                          calib.wand_points_mm.reshape(-1, 3),
                          colors=np.tile(np.array([[255, 220, 0]], np.uint8), (F * n_w, 1)))
        # worst marker residual per sighting, one series per camera (NaN where not seen)
        used_obs = calib.wand.select(calib.used)
        worst = np.linalg.norm(calib.residuals_px, axis=-1).max(axis=1)
        local = np.searchsorted(calib.wand_frames, used_obs.frame)
        table = np.full((F, len(calib.rig)), np.nan)
        table[local, used_obs.camera] = worst
        rec.log("plots/calibration/residual_px", rr.SeriesLines(names=list(calib.rig.ids)), static=True)
        rec.send_columns("plots/calibration/residual_px", indexes=_times(rr, calib.wand_frames, fps),
                         columns=rr.Scalars.columns(scalars=table.ravel()).partition(
                             lengths=[len(calib.rig)] * F))
    # raw blobs of the takes kept for the recording, coloured by role
    recon = result.reconstruction
    for take, b in recon.blob_roles.items():
        for ci, cid in enumerate(calib.rig.ids):
            sel = b.camera == ci
            _points_over_time(rec, rr, f"world/cameras/{cid}/image/blobs/{take}", b.frame[sel], fps,
                              np.column_stack([b.x[sel], b.y[sel]]), colors=ROLE_COLOURS[b.role[sel]])


def _log_takes(rec, rr, result, fps, names):
    session = result.session
    takes = result.reconstruction.takes
    for take in session.takes:
        if take.name not in takes:
            continue
        X = takes[take.name].X
        n_frames = X.shape[0]
        ok = np.isfinite(X[..., 0])
        f_idx, m_idx = np.nonzero(ok)
        _points_over_time(rec, rr, f"world/takes/{take.name}/markers", f_idx, fps, X[ok],
                          class_ids=m_idx.astype(np.uint16))
        drawn = np.flatnonzero(ok.sum(axis=0) >= 2)
        strips = [X[ok[:, m], m] for m in drawn]
        rec.log(f"world/takes/{take.name}/paths",
                rr.LineStrips3D(strips, radii=0.08, class_ids=drawn), static=True)
        if take.commands is not None:
            from mocap.core.session import command_matrix

            dus = list(session.du_ids)
            cmd = command_matrix(session.read_commands(take.name), fps, n_frames, dus)
            active = np.flatnonzero(cmd.any(axis=0))
            if active.size:
                _series(rec, rr, f"plots/commands/{take.name}", [f"DU {dus[i]}" for i in active],
                        cmd[:, active].astype(float), fps)


def _log_responses(rec, rr, result, fps):
    from mocap.analysis.paper.response import sigmoid

    res = result.analysis
    if res is None:
        return
    for avg in result.trials.averages:
        p = res.du.get(avg.du)
        if p is None:
            continue
        keep = res.fitted[avg.du]
        delta = avg.delta_along if avg.delta_along is not None else avg.delta
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(delta[:, keep], axis=1) if keep.any() else np.full(delta.shape[0], np.nan)
            sd = np.nanstd(delta[:, keep], axis=1) if keep.any() else mean
        n = delta.shape[0]
        t = np.arange(n) / fps
        cols = np.full((n, 5), np.nan)
        cols[:, 0] = mean
        cols[:, 1] = mean + sd
        cols[:, 2] = mean - sd
        for j, (ramp, par) in enumerate(((p.ramps[0], p.fwd), (p.ramps[1], p.bwd))):
            sl = slice(ramp.start, ramp.stop)
            cols[sl, 3 + j] = sigmoid(ramp.p0 + ramp.p1 * t[sl], par.alpha, par.beta)
        _series(rec, rr, f"plots/du{avg.du:02d}/response",
                ["measured mean", "mean + sd", "mean - sd", "fit forward", "fit backward"], cols, fps)


def _log_annotations(rec, rr, result, names):
    res = result.analysis
    if res is not None and len(res.properties):
        props = res.properties
        # one kind on every scale (docs/outputs.md's naming rule): the noise-corrected estimates,
        # as the property chart figure
        gamma = props["dyssynchrony_corrected"].to_numpy(float)
        g = (gamma - np.nanmin(gamma)) / max(np.nanmax(gamma) - np.nanmin(gamma), 1e-12)
        colours = np.column_stack([255 * g, 80 + 0 * g, 255 * (1 - g)]).astype(np.uint8)
        rec.log("charts/property_chart",
                rr.Points2D(np.column_stack([1000 * props["sensitivity_corrected"],
                                             props["hysteresis_corrected"]]),
                            labels=[f"DU {d}" for d in props["du"]], colors=colours, radii=1.5),
                static=True)
        rec.log("charts/about", rr.TextDocument(
            "Property chart, all three values noise-corrected estimates (properties.csv's "
            "`_corrected` columns): x = `sensitivity_corrected` (alpha) x 1000 (1/command unit), "
            "y = `hysteresis_corrected` (command units), colour = `dyssynchrony_corrected` (blue "
            "low, red high). The paper's computation literally is in the plain columns.",
            media_type=rr.MediaType.MARKDOWN), static=True)
    rej = result.trials.rejections
    if rej is not None and len(rej):
        lines = ["| DU | marker | reason | value | threshold |", "|---|---|---|---|---|"]
        import pandas as pd

        lines += [f"| {'all' if pd.isna(r.du) else int(r.du)} | {r.marker} | "
                  f"{r.reason} | {r.value:.4g} | {r.threshold:.4g} |" for r in rej.itertuples()]
        rec.log("annotations/rejections", rr.TextDocument("\n".join(lines),
                                                          media_type=rr.MediaType.MARKDOWN), static=True)
        rest = result.reconstruction.markers.rest_mm
        why: dict = {}
        for r in rej.itertuples():
            why.setdefault(r.marker, []).append(r.reason)
        idx = [names.index(m) for m in why if m in names]
        pts = rest[idx]
        ok = np.all(np.isfinite(pts), axis=1)
        rec.log("world/rejected", rr.Points3D(pts[ok], radii=1.2, colors=RED,
                                              labels=[f"{names[i]}: {', '.join(sorted(set(why[names[i]])))}"
                                                      for i, k in zip(idx, ok) if k]), static=True)
    audit = result.audit
    if audit:
        lines = [f"Audit verdict: **{audit['verdict']}**", ""]
        lines += [f"- {f['verdict']}: {f['kind']} {f['item']} ({f['why']})" for f in audit["flagged"]]
        rec.log("annotations/audit", rr.TextDocument("\n".join(lines),
                                                     media_type=rr.MediaType.MARKDOWN), static=True)


def write_discrepancy_recording(path: str | os.PathLike, res, data, session_name: str) -> Path:
    """The discrepancy workflow in Rerun: per stage, the held-out gap; for the takes where the
    base model disagreed most, the measured markers and each stage's held-out prediction in 3D
    (``discrepancy/<take>/measured``, ``.../model_<stage>``), the worst marker's displacement
    along its direction as series (``plots/discrepancy/<take>``), and the evidence as markdown."""
    import rerun as rr
    import rerun.blueprint as rrb

    from mocap.analysis.discrepancy.report import worst_marker

    fps = float(data.fps)
    names = list(data.marker_names)
    bp = rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial3DView(origin="discrepancy", name="measured and simulated"),
        rrb.Vertical(rrb.TimeSeriesView(origin="plots/discrepancy", name="worst markers"),
                     rrb.BarChartView(origin="charts/heldout_rms_mm", name="held-out RMS per stage"),
                     rrb.TextDocumentView(origin="annotations", name="evidence"))),
        collapse_panels=True)
    with atomic_path(path) as tmp:
        rec = rr.RecordingStream("facemocap", recording_id=f"facemocap-discrepancy-{session_name}")
        rec.save(str(tmp), default_blueprint=bp)
        rec.log("discrepancy", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
        rec.log("discrepancy", rr.AnnotationContext([(i, n) for i, n in enumerate(names)]), static=True)
        rec.log("charts/heldout_rms_mm",
                rr.BarChart(np.array([st["heldout_rms_mm"] for st in res.stages])), static=True)
        gaps = res.stages[0]["takes"]
        worst = sorted(gaps, key=lambda k: -(gaps[k]["rms_mm"] or 0))[:3]
        colours = [(230, 60, 60), (60, 130, 230), (60, 200, 90), (200, 160, 40), (150, 80, 200)]
        takes = [t.name for t in data.takes]
        for name in worst:
            k = takes.index(name)
            frames = data.samples(k)
            obs = data.observed(k) + data.rest_mm
            M = obs.shape[1]
            fr = np.repeat(frames, M)
            cid = np.tile(np.arange(M), frames.size)
            ok = np.isfinite(obs).all(-1).ravel()
            _points_over_time(rec, rr, f"discrepancy/{name}/measured", fr[ok], fps,
                              obs.reshape(-1, 3)[ok], class_ids=cid[ok],
                              radii=np.full(ok.sum(), 0.5, np.float32))
            m, u = worst_marker(res.heldout_residuals[0][k], data.used)
            series = [(obs[:, m] - data.rest_mm[m]) @ u]
            labels = ["measured"]
            for i, st in enumerate(res.stages):
                pred = obs - res.heldout_residuals[i][k]
                okp = np.isfinite(pred).all(-1).ravel()
                _points_over_time(rec, rr, f"discrepancy/{name}/model_{i}", fr[okp], fps,
                                  pred.reshape(-1, 3)[okp], class_ids=cid[okp],
                                  colors=np.tile(np.array(colours[i % len(colours)], np.uint8),
                                                 (okp.sum(), 1)),
                                  radii=np.full(okp.sum(), 0.35, np.float32))
                series.append((pred[:, m] - data.rest_mm[m]) @ u)
                labels.append(f"model {st['model']}")
            vals = np.full((int(frames.max()) + 1, len(series)), np.nan)
            vals[frames] = np.column_stack(series)
            _series(rec, rr, f"plots/discrepancy/{name}", labels, vals, fps)
        lines = ["| stage | model | held-out RMS (mm) | / noise |", "|---|---|---|---|"]
        for i, st in enumerate(res.stages):
            lines.append(f"| {i} | {st['model']} | {st['heldout_rms_mm']:.4f} | "
                         f"{st['heldout_rms_mm'] / res.noise_floor_mm:.2f} |")
        lines += ["", f"Named: {', '.join(res.named) or 'nothing (no missing effect found)'}."]
        for s in res.steps:
            lines.append(f"- {s.effect}: " + ", ".join(f"{k} = {v:.4g}" for k, v in s.parameters.items()))
        rec.log("annotations/discrepancy", rr.TextDocument("\n".join(lines), media_type="text/markdown"),
                static=True)
        rec.flush()
        rec.disconnect()
    return Path(path)
