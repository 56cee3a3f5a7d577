"""Reuse and resume of ``mocap run`` (issue #19), timed end to end in fresh processes.

    python benchmarks/resume.py                     # the committed sample session
    python benchmarks/resume.py --session benchmarks/cache/paper/session   # the paper preset

Runs ``mocap run SESSION --out OUT`` four times into one folder: a first run, an unchanged
rerun (target: at most 1/10 of the first run's time), a rerun with one analysis setting changed
(``--bootstrap-samples 100``: the reconstruction is reused), and a run killed (SIGKILL) halfway
through the reconstruction of a fresh folder then resumed. Wall times of whole processes
(interpreter start and imports included). Results go to one page, ``benchmarks/resume.md``
(and ``resume.json``), one section per session (the sample session, the paper preset): a run
replaces its session's section and keeps the others.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
MOCAP = [sys.executable, "-m", "mocap.cli", "run"]


def timed(session: Path, out: Path, *flags: str) -> tuple[float, str]:
    t0 = time.perf_counter()
    proc = subprocess.run(MOCAP + [str(session), "--out", str(out), "--quiet", *flags],
                          capture_output=True, text=True, check=True)
    return time.perf_counter() - t0, proc.stdout.strip().splitlines()[-1]


def killed_then_resumed(session: Path, out: Path, n_takes: int) -> dict:
    t0 = time.perf_counter()
    proc = subprocess.Popen(MOCAP + [str(session), "--out", str(out), "--quiet"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    while proc.poll() is None and len(list((out / "trajectories").glob("*.parquet"))) < n_takes // 2:
        time.sleep(0.01)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    killed_at = time.perf_counter() - t0
    done = len(list((out / "trajectories").glob("*.parquet")))
    seconds, line = timed(session, out)
    return {"killed_after_s": round(killed_at, 1), "takes_done_when_killed": done,
            "resume_s": round(seconds, 1), "resume_says": line}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--session", type=Path, default=HERE.parent / "sample_data" / "session")
    ap.add_argument("--unchanged-only", action="store_true",
                    help="only the first run and the unchanged rerun")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="mocap-resume-"))
    try:
        out = work / "out"
        first, _ = timed(args.session, out)
        n_takes = len(list((out / "trajectories").glob("*.parquet")))
        unchanged, said = timed(args.session, out)
        analysis, said_analysis, resumed = 0.0, "", {}
        if not args.unchanged_only:
            analysis, said_analysis = timed(args.session, out, "--bootstrap-samples", "100")
            resumed = killed_then_resumed(args.session, work / "killed", n_takes)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    session = args.session.resolve()
    if session.is_relative_to(HERE.parent):
        session = session.relative_to(HERE.parent)
    res = {"session": str(session), "load_average_1min": round(os.getloadavg()[0], 1),
           "machine": f"{platform.node()} ({os.cpu_count()} cores)",
           "date": time.strftime("%Y-%m-%d %H:%M"), "face_takes": n_takes,
           "first_run_s": round(first, 1), "unchanged_rerun_s": round(unchanged, 1),
           "unchanged_ratio": round(unchanged / first, 3), "unchanged_says": said}
    if not args.unchanged_only:
        res.update({"analysis_setting_changed_s": round(analysis, 1),
                    "analysis_says": said_analysis, **resumed})
    name = "sample" if "sample_data" in str(args.session) else args.session.parent.name
    path = HERE / "resume.json"
    sections = json.loads(path.read_text()) if path.exists() else {}
    sections[name] = res
    path.write_text(json.dumps(sections, indent=2) + "\n")
    md = render(sections)
    (HERE / "resume.md").write_text(md)
    print(md)


def render(sections: dict) -> str:
    """The page: one table per session."""
    lines = ["# mocap run: reuse and resume", "",
             "`python benchmarks/resume.py` (the committed sample session) or "
             "`python benchmarks/resume.py --session benchmarks/cache/paper/session` (the paper "
             "preset, made by `benchmarks/run.py`; `--unchanged-only` runs only the first two). "
             "Wall times of whole `mocap run` processes, interpreter start and imports included. "
             "Target: an unchanged rerun at most 1/10 of the first run.", ""]
    for res in sections.values():
        session = Path(res["session"])
        if session.is_relative_to(HERE.parent):
            session = session.relative_to(HERE.parent)
        load = f", load {res['load_average_1min']}" if "load_average_1min" in res else ""
        lines += [f"## `{session}` ({res['face_takes']} face takes; {res['date']}, {res['machine']}"
                  f"{load})",
                  "", "| run | seconds | |", "|---|---|---|",
                  f"| first | {res['first_run_s']} | |",
                  f"| unchanged rerun | {res['unchanged_rerun_s']} | {res['unchanged_ratio']:.3f} x "
                  f"the first; {res['unchanged_says']} |"]
        if "analysis_setting_changed_s" in res:
            lines += [f"| --bootstrap-samples 100 | {res['analysis_setting_changed_s']} | "
                      f"{res['analysis_says']} |",
                      f"| killed at {res['killed_after_s']} s ({res['takes_done_when_killed']} takes "
                      f"done), resumed | {res['resume_s']} | {res['resume_says']} |"]
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
