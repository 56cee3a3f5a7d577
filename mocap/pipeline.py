"""The composer: one run of a session through every stage, raw to result.

``run_session`` is the only place that joins the stages; each stage is a pure function of the
previous stages' results, and the returned ``RunResult`` holds every intermediate. Files are
written atomically under ``OUT_DIR`` per OUTPUTS.md.

Stages (as they land): validate -> calibrate (raw sessions) -> reconstruct -> trials, noise,
rejections -> analyses and figures -> audit -> Rerun recording.
"""

from __future__ import annotations

import json
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from mocap import __version__
from mocap.atomic import write_text
from mocap.session import Session, load_session


@dataclass
class RunResult:
    """Everything a run produced; ``summary`` is what summary.json holds."""

    session: Session
    out_dir: Path
    summary: dict = field(default_factory=dict)
    calibration: object | None = None  # calib.wand_calibration.CalibrationResult (raw sessions)


def _versions() -> dict:
    import numpy
    import pandas
    import scipy

    return {"facemocap": __version__, "python": platform.python_version(),
            "numpy": numpy.__version__, "scipy": scipy.__version__, "pandas": pandas.__version__}


def run_session(session_dir: str | Path, out_dir: str | Path,
                progress: Callable[[str], None] | None = None) -> RunResult:
    """Run every available stage on ``session_dir`` and write results into ``out_dir``."""
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    session = load_session(session_dir)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    say(f"session {session.name}: {len(session.takes)} takes, {session.dimension}")

    counts = {"takes": {}, "rows": 0, "frames": 0}
    t = time.perf_counter()
    for take in session.takes:
        df = session.read_take(take.name)
        counts["takes"][take.kind] = counts["takes"].get(take.kind, 0) + 1
        counts["rows"] += len(df)
        counts["frames"] += int(df["frame"].max()) + 1
        if take.commands is not None:
            session.read_commands(take.name)
    timings["validate_s"] = time.perf_counter() - t
    say(f"validated {counts['rows']} rows in {timings['validate_s']:.1f} s")
    stages = ["validate"]

    calibration = None
    if session.dimension == "2d":
        from calib.calibration_file import write_calibration
        from calib.wand_calibration import calibrate_session

        t = time.perf_counter()
        calibration = calibrate_session(session, progress=say)
        write_calibration(out / "calibration.toml", calibration.rig, calibration.quality)
        timings["calibrate_s"] = time.perf_counter() - t
        stages.append("calibrate")
        say(f"calibration {calibration.quality['rating']} in {timings['calibrate_s']:.1f} s")

    summary = {
        "session": {"name": session.name, "dir": str(Path(session_dir).resolve()),
                    "dimension": session.dimension, "fps": session.fps,
                    "cameras": list(session.camera_ids), "dus": list(session.du_ids)},
        "stages": stages,
        "versions": _versions(),
        "timings_s": timings,
        "counts": counts,
        "warnings": list(session.warnings),
    }
    if calibration is not None:
        q = calibration.quality
        summary["calibration"] = {k: q[k] for k in (
            "rating", "reprojection_rms_px_all", "wand_length_error_mean_mm",
            "wand_length_error_sd_mm", "point_error_mm") if k in q}
    timings["total_s"] = time.perf_counter() - t0
    write_text(out / "summary.json", json.dumps(summary, indent=2))
    return RunResult(session=session, out_dir=out, summary=summary, calibration=calibration)
