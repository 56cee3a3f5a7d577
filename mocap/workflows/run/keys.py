"""Every stage's cache key: what each stage of a run reads (:mod:`mocap.workflows.run.cache`).

A key holds the input files' fingerprints, the settings the stage reads and the keys of the
stages it builds on, so a change reaches every stage downstream of it and no other.
"""

from __future__ import annotations

from mocap.core.session import Session
from mocap.workflows.run.result import RunWriters
from mocap.workflows.run.settings import RunSettings
from mocap.workflows.run.stages import FACE_KINDS, _recorded, _rest_take


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
