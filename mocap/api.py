"""The Python API: a session in, typed results out, for notebooks and scripts.

    import mocap

    session = mocap.load_session("sample_data/session")
    result = mocap.run(session)                  # nothing is written
    result.properties                            # one row per DU: the paper's indices
    result.trajectories                          # tidy table: take, frame, marker, x, y, z, ...
    result.arrays["du04_t01"]                    # (n_frames, n_markers, 3) mm, NaN: not seen

or stage by stage::

    calibration = mocap.calibrate(session)       # raw sessions
    recon = mocap.reconstruct(session, calibration)
    analysis = mocap.analyze(session, recon)     # .properties, .linearity, .rejections, .motions

Settings are :class:`mocap.workflows.run.settings.RunSettings` fields, passed by name
(``mocap.run(session, min_cameras=2, bootstrap_samples=0)``); ``mocap run --print-config``
lists them with their defaults and meanings. Units: mm, px, s, command units.
"""

from __future__ import annotations

from pathlib import Path

from mocap.analysis.session_analysis import Analysis
from mocap.workflows.run.pipeline import run as _run
from mocap.workflows.run.result import RunResult
from mocap.workflows.run.stages import analyze as _analyze
from mocap.workflows.run.stages import calibrate as _calibrate
from mocap.workflows.run.stages import reconstruct as _reconstruct
from mocap.reconstruction.takes import Reconstruction
from mocap.outputs.run_writers import WRITERS
from mocap.workflows.run.settings import RunSettings, with_values
from mocap.core.session import Session
from mocap.core.session import load_session as _load_session

__all__ = ["load_session", "calibrate", "reconstruct", "analyze", "run"]


def _session(session: Session | str | Path) -> Session:
    if isinstance(session, Session):
        return session
    if isinstance(session, (str, Path)):
        return _load_session(session)
    raise TypeError(f"expected a Session (mocap.load_session) or a session folder, got {session!r}")


def _settings(settings: RunSettings | None, overrides: dict, where: str) -> RunSettings:
    if settings is not None and not isinstance(settings, RunSettings):
        raise TypeError(f"{where}: expected settings=RunSettings(...), got {settings!r}")
    return with_values(settings or RunSettings(), overrides, where)


def load_session(path: str | Path) -> Session:
    """The session folder ``path`` (holding session.toml), checked against the input contract;
    a ``mocap.core.session.SessionError`` names the file, row or key of any violation."""
    return _load_session(path)


def calibrate(session: Session | str | Path, *, progress=None):
    """The wand calibration of a raw session's camera rig (``CalibrationResult``: ``.rig``,
    ``.quality``)."""
    return _calibrate(_session(session), progress=progress)


def reconstruct(session: Session | str | Path, calibration=None, *,
                settings: RunSettings | None = None, progress=None, bars: bool | None = False,
                **overrides) -> Reconstruction:
    """Every face take to labeled 3D trajectories (``Reconstruction``: ``.markers``,
    ``.takes[name].X`` (n_frames, n_markers, 3) mm); ``calibration`` is required for raw
    sessions, None for labeled 3D ones. Nothing is written."""
    s = _settings(settings, overrides, "reconstruct()")
    return _reconstruct(_session(session), calibration, s, progress=progress, bars=bars)


def analyze(session: Session | str | Path, reconstruction: Reconstruction, *,
            settings: RunSettings | None = None, **overrides) -> Analysis:
    """Trials, rejections and the paper's analyses (``Analysis``: ``.properties``,
    ``.linearity``, ``.rejections``, ``.motions``, ``.trials``). Nothing is written."""
    return _analyze(_session(session), reconstruction,
                    _settings(settings, overrides, "analyze()"))


def run(session: Session | str | Path, out_dir: str | Path | None = None, *,
        settings: RunSettings | None = None, progress=None, bars: bool | None = False,
        force: bool = False, **overrides) -> RunResult:
    """The whole run: calibration, reconstruction, trials, analyses, audit.

    out_dir : None (default) writes nothing anywhere; a folder receives every file ``mocap run``
        writes (figures and session.rrd included), and a rerun into it reuses the results whose
        inputs did not change (``force=True`` recomputes everything).
    overrides : settings by name, e.g. ``min_cameras=2``, ``bootstrap_samples=0``.

    Returns a ``RunResult``: ``.properties``, ``.linearity``, ``.rejections``, ``.audit``,
    ``.calibration``, ``.trajectories`` (tidy DataFrame), ``.arrays`` (take -> (n_frames,
    n_markers, 3) mm), ``.markers``, ``.summary``.
    """
    s = _settings(settings, overrides, "run()")
    if out_dir is None and s.recording:
        s = with_values(s, {"recording": False})  # nothing to write it to
    return _run(_session(session), out_dir, s, progress=progress, bars=bars, force=force,
                writers=WRITERS)
