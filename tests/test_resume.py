"""Reusable, resumable, locked runs: a rerun reuses what did not change and says so; a killed run
resumes and ends with the results of an uninterrupted one; one run at a time per folder."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from conftest import make_session
from mocap.cli import main
from mocap.workflows.run.lock import OutputInUse, RunLock

ROOT = Path(__file__).resolve().parents[1]
TABLES = ("properties.csv", "linearity.csv", "marker_properties.csv", "rejections.csv")


def mocap_run(session: Path, out: Path, *flags: str) -> None:
    assert main(["run", str(session), "--out", str(out), "--jobs", "1", "--no-recording",
                 *flags]) == 0


def reused_line(stdout: str) -> str:
    return next((ln for ln in stdout.splitlines() if ln.startswith("reused from")), "")


def same_outputs(a: Path, b: Path, tables=TABLES) -> None:
    """Every trajectory file and table of ``a`` equals ``b``'s."""
    names = sorted(p.name for p in (b / "trajectories").glob("*.parquet"))
    assert sorted(p.name for p in (a / "trajectories").glob("*.parquet")) == names
    for name in names:
        pd.testing.assert_frame_equal(pd.read_parquet(a / "trajectories" / name),
                                      pd.read_parquet(b / "trajectories" / name))
    pd.testing.assert_frame_equal(pd.read_parquet(a / "responses.parquet"),
                                  pd.read_parquet(b / "responses.parquet"))
    for t in tables:
        pd.testing.assert_frame_equal(pd.read_csv(a / t), pd.read_csv(b / t))


def stamps(folder: Path) -> dict:
    return {p.name: p.stat().st_mtime_ns for p in sorted(folder.glob("*"))}


@pytest.fixture
def copy_of_run(tiny_run, tmp_path) -> Path:
    out = tmp_path / "out"
    shutil.copytree(tiny_run, out)  # modification times kept
    return out


def test_unchanged_rerun_reuses_everything(tiny_sim, tiny_run, copy_of_run, capsys):
    before = stamps(copy_of_run / "trajectories")
    mocap_run(tiny_sim / "session", copy_of_run)
    out = capsys.readouterr().out
    assert reused_line(out) == ("reused from the earlier run: calibrate, markers, reconstruct "
                                "(6 of 6 takes), trials, analyze, audit; computed: nothing")
    assert stamps(copy_of_run / "trajectories") == before  # not even rewritten
    same_outputs(copy_of_run, tiny_run)
    summary = json.loads((copy_of_run / "summary.json").read_text())
    assert summary["computed"] == [] and "audit" in summary["reused"]
    # the library call reads the reused results back, each take when asked for
    from mocap.workflows.run.pipeline import run_session
    from mocap.workflows.run.settings import RunSettings
    from mocap.reconstruction.takes import LazyTakes
    from mocap.outputs.run_writers import WRITERS

    res = run_session(tiny_sim / "session", copy_of_run, settings=RunSettings(jobs=1, recording=False),
                      writers=WRITERS)
    assert res.computed == () and isinstance(res.reconstruction.takes, LazyTakes)
    for take, X in res.arrays.items():
        ref = pd.read_parquet(tiny_run / "trajectories" / f"{take}.parquet")
        np.testing.assert_array_equal(X.reshape(-1, 3), ref[["x", "y", "z"]].to_numpy())
        lab = res.reconstruction.takes[take]
        np.testing.assert_array_equal(lab.n_cameras.ravel(), ref["n_cameras"].to_numpy())
        np.testing.assert_array_equal(lab.interpolated.ravel(), ref["interpolated"].to_numpy())
    pd.testing.assert_frame_equal(res.properties.reset_index(drop=True),
                                  pd.read_csv(tiny_run / "properties.csv"), check_dtype=False)


def test_a_rerun_that_adds_figures_does_not_reuse_stages_written_without(tiny_sim, copy_of_run):
    """The writers are part of the stage keys: a data-only library run recomputes the stages
    whose files differ (analyze, audit) and draws nothing; adding the writers back redraws."""
    from mocap.workflows.run.pipeline import run_session
    from mocap.workflows.run.settings import RunSettings
    from mocap.outputs.run_writers import WRITERS

    settings = RunSettings(jobs=1, recording=False)
    shutil.rmtree(copy_of_run / "figures")
    res = run_session(tiny_sim / "session", copy_of_run, settings=settings)  # no writers
    assert res.computed == ("analyze", "audit")
    assert res.reused == ("calibrate", "markers", "reconstruct (6 of 6 takes)", "trials")
    assert not (copy_of_run / "figures").exists()
    assert (copy_of_run / "properties.csv").is_file() and (copy_of_run / "audit.json").is_file()
    res = run_session(tiny_sim / "session", copy_of_run, settings=settings, writers=WRITERS)
    assert res.computed == ("analyze", "audit")
    figs = {p.name for p in (copy_of_run / "figures").glob("*.png")}
    assert {"linearity.png", "property_chart.png", "audit_noise.png"} <= figs
    res = run_session(tiny_sim / "session", copy_of_run, settings=settings, writers=WRITERS)
    assert res.computed == ()


def test_analysis_setting_change_reuses_the_reconstruction(tiny_sim, tiny_run, copy_of_run, capsys):
    before = stamps(copy_of_run / "trajectories")
    mocap_run(tiny_sim / "session", copy_of_run, "--bootstrap-samples", "20")
    cap = capsys.readouterr()
    assert "settings changed since the last run" in cap.err and "bootstrap_samples 200 -> 20" in cap.err
    line = reused_line(cap.out)
    assert line == ("reused from the earlier run: calibrate, markers, reconstruct (6 of 6 takes), "
                    "trials, audit; computed: analyze")
    assert stamps(copy_of_run / "trajectories") == before
    new, ref = (pd.read_csv(d / "properties.csv") for d in (copy_of_run, tiny_run))
    np.testing.assert_array_equal(new["sensitivity"], ref["sensitivity"])  # the fits themselves
    ci = [c for c in ref.columns if c.endswith("_ci_lo")]
    assert ci and not new[ci].equals(ref[ci])  # the bootstrap intervals changed
    assert json.loads((copy_of_run / "summary.json").read_text())["settings"]["bootstrap_samples"] == 20
    # a rejection setting: trials and what follows them, still no reconstruction
    mocap_run(tiny_sim / "session", copy_of_run, "--bootstrap-samples", "20",
              "--min-displacement-mm", "0.3")
    line = reused_line(capsys.readouterr().out)
    assert line == ("reused from the earlier run: calibrate, markers, reconstruct (6 of 6 takes); "
                    "computed: trials, analyze, audit")
    rej = pd.read_csv(copy_of_run / "rejections.csv")
    assert (rej.loc[rej["reason"] == "small_displacement", "threshold"] == 0.3).all()
    # and back to the defaults: the earlier results, identical
    mocap_run(tiny_sim / "session", copy_of_run)
    same_outputs(copy_of_run, tiny_run)


def test_changed_take_file_recomputes_that_take_only(tiny_sim, tiny_run, copy_of_run, tmp_path,
                                                     capsys):
    session = tmp_path / "session"
    shutil.copytree(tiny_sim / "session", session)
    take = session / "takes" / "du07_t02.parquet"
    blobs = pd.read_parquet(take)
    blobs[blobs["frame"] != 100].to_parquet(take, index=False)  # frame 100 edited out
    mocap_run(session, copy_of_run)
    line = reused_line(capsys.readouterr().out)
    assert line == ("reused from the earlier run: calibrate, markers, reconstruct (5 of 6 takes); "
                    "computed: reconstruct (1 of 6 takes), trials, analyze, audit")
    df = pd.read_parquet(copy_of_run / "trajectories" / "du07_t02.parquet")
    assert df.loc[df["frame"] == 100, "x"].isna().all()
    assert df.loc[df["frame"] == 101, "x"].notna().mean() > 0.9
    for name in ("du04_t01.parquet", "rest.parquet"):
        pd.testing.assert_frame_equal(pd.read_parquet(copy_of_run / "trajectories" / name),
                                      pd.read_parquet(tiny_run / "trajectories" / name))


def test_keys_follow_content_not_paths_or_times(tiny_sim, copy_of_run, tmp_path, capsys):
    session = tmp_path / "elsewhere" / "session"
    shutil.copytree(tiny_sim / "session", session)
    os.utime(session / "takes" / "du04_t01.parquet", (1e9, 1e9))  # touched, same bytes
    mocap_run(session, copy_of_run)
    assert reused_line(capsys.readouterr().out).endswith("computed: nothing")


def test_force_recomputes_everything(tmp_path, capsys):
    root = make_session(tmp_path / "lab", du_ids=(4,), n_trials=2, n_markers=12,
                        motion_plans=(), battery=False, labeled=True, seed=6)
    mocap_run(root / "session", tmp_path / "out", "--quiet")
    assert reused_line(capsys.readouterr().out) == ""  # a first run reuses nothing
    mocap_run(root / "session", tmp_path / "out", "--quiet")
    assert "reconstruct (3 of 3 takes)" in reused_line(capsys.readouterr().out)
    before = stamps(tmp_path / "out" / "trajectories")
    mocap_run(root / "session", tmp_path / "out", "--quiet", "--force")
    assert reused_line(capsys.readouterr().out) == ""
    after = stamps(tmp_path / "out" / "trajectories")
    assert all(after[k] > before[k] for k in before)  # every take written again


def test_killed_run_resumes_to_the_uninterrupted_results(tiny_sim, tiny_run, tmp_path, capsys):
    out = tmp_path / "out"
    faces = sorted(p.name for p in (tiny_run / "trajectories").glob("*.parquet"))
    proc = subprocess.Popen([sys.executable, "-m", "mocap.cli", "run", str(tiny_sim / "session"),
                             "--out", str(out), "--jobs", "1", "--no-recording", "--quiet"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 900
    while time.monotonic() < deadline and proc.poll() is None:
        if len(list((out / "trajectories").glob("*.parquet"))) >= 2:
            break
        time.sleep(0.005)
    assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
    os.kill(proc.pid, signal.SIGKILL)  # in the middle of the reconstruction
    proc.wait()
    proc.stderr.close()
    done = sorted(p.name for p in (out / "trajectories").glob("*.parquet"))
    finished = len(done)
    assert 2 <= finished < len(faces)
    assert not (out / "summary.json").exists() and (out / ".facemocap" / "lock").exists()

    mocap_run(tiny_sim / "session", out)
    cap = capsys.readouterr()
    assert "ended without finishing" in cap.err and f"pid {proc.pid}" in cap.err
    assert f"reusing {finished} of {len(faces)} reconstructed takes" in cap.err, (
        done, cap.err)  # the whole message: a failure under heavy load was not diagnosable
    assert (f"reconstruct ({finished} of {len(faces)} takes)" in reused_line(cap.out))
    same_outputs(out, tiny_run)
    # the same numbers to the optimiser's precision (resumed takes come back from Parquet in
    # another memory layout, so sums run in another order: differences of 1e-16 in, 1e-9 out)
    resumed = json.loads((out / "summary.json").read_text())["properties"]
    uninterrupted = json.loads((tiny_run / "summary.json").read_text())["properties"]
    assert [r["du"] for r in resumed] == [r["du"] for r in uninterrupted]
    for a, b in zip(resumed, uninterrupted):
        assert a == pytest.approx(b, rel=1e-6, abs=1e-12), (a, b)
    assert not list(out.rglob(".*.tmp"))  # no half-written file left behind
    assert not (out / ".facemocap" / "lock.owner").exists()  # released normally


# --- the lock --------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def lab_session(tmp_path_factory) -> Path:
    root = make_session(tmp_path_factory.mktemp("lab"), du_ids=(4,), n_trials=2, n_markers=12,
                        motion_plans=(), battery=False, labeled=True, seed=8)
    return root / "session"


def test_second_run_into_a_folder_in_use_is_refused(lab_session, tmp_path, capsys):
    out = tmp_path / "out"
    with RunLock(out):
        assert main(["run", str(lab_session), "--out", str(out), "--quiet"]) == 1
        err = capsys.readouterr().err
        assert f"{out} is in use by another run (pid {os.getpid()} on {socket.gethostname()}" in err
        assert sorted(p.name for p in out.iterdir()) == [".facemocap"]  # nothing written
    assert main(["run", str(lab_session), "--out", str(out), "--quiet"]) == 0  # free again


HOLD_LOCK = r"""
import sys, time
from mocap.workflows.run.lock import RunLock
with RunLock(sys.argv[1]):
    print("held", flush=True)
    time.sleep(60)
"""


def test_a_killed_run_leaves_no_lock_behind(tmp_path):
    # the operating system releases a killed process's lock: the next run goes ahead and says
    # that the previous one did not finish
    child = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, str(tmp_path)],
                             stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "held"
        with pytest.raises(OutputInUse, match=rf"pid {child.pid} on "):
            with RunLock(tmp_path):
                pass
        child.kill()
        child.wait()
    finally:
        child.kill()
        child.stdout.close()
    with RunLock(tmp_path) as held:
        assert held.note is not None and f"pid {child.pid}" in held.note
        assert "ended without finishing" in held.note
    with RunLock(tmp_path) as again:  # released normally this time: nothing to say
        assert again.note is None


TRY_LOCK = r"""
import sys, time
from mocap.workflows.run.lock import OutputInUse, RunLock
start = float(sys.argv[2])
while time.time() < start:
    time.sleep(0.001)
try:
    with RunLock(sys.argv[1]):
        time.sleep(5.0)
    print("got it")
except OutputInUse:
    print("refused")
"""


def test_one_of_many_simultaneous_runs_gets_the_lock(tmp_path):
    start = time.time() + 4.0
    procs = [subprocess.Popen([sys.executable, "-c", TRY_LOCK, str(tmp_path), str(start)],
                              stdout=subprocess.PIPE, text=True) for _ in range(6)]
    outcomes = sorted(p.communicate(timeout=120)[0].strip() for p in procs)
    assert outcomes == ["got it"] + ["refused"] * 5


def test_files_hashed_ahead_on_threads_match_one_by_one(tmp_path):
    """``Fingerprints.prefetch`` (the run hashes every input file at once, on its cores) gives
    each file the digest hashlib gives it alone, rehashes a file changed since, and leaves a
    missing file to the per-file call, which reports it."""
    import hashlib

    from mocap.workflows.run.cache import Fingerprints

    rng = np.random.default_rng(0)
    files = []
    for i in range(6):
        p = tmp_path / f"f{i}.bin"
        p.write_bytes(rng.bytes(int(rng.integers(1, 300_000))))
        files.append(p)
    fp = Fingerprints(tmp_path / "memo.json")
    fp.prefetch(files + [tmp_path / "missing.bin"], jobs=2)

    def plain(p):
        return hashlib.blake2b(p.read_bytes(), digest_size=20).hexdigest()

    assert {str(p.resolve()) for p in files} == set(fp.memo)
    for p in files:
        assert fp.memo[str(p.resolve())][2] == plain(p)
        assert fp(p) == plain(p)
    files[2].write_bytes(b"changed, and of another size")
    fp.prefetch(files, jobs=2)
    assert fp(files[2]) == plain(files[2])
    with pytest.raises(FileNotFoundError):
        fp(tmp_path / "missing.bin")


def test_takes_read_back_are_loaded_once_when_threads_ask_together():
    """A reused run's takes are read back on first access; the recording's thread and the
    trials may ask for the same take at once, and each take is still read once."""
    from collections import Counter
    from concurrent.futures import ThreadPoolExecutor

    from mocap.reconstruction.takes import LazyTakes

    calls: Counter = Counter()

    def loader(name):
        def load():
            calls[name] += 1
            time.sleep(0.02)  # a parquet read: long enough for the other threads to ask
            return object()
        return load

    takes = LazyTakes({n: loader(n) for n in "abc"})
    with ThreadPoolExecutor(6) as pool:
        got = list(pool.map(lambda n: (n, takes[n]), list("abc") * 6))
    assert calls == Counter({"a": 1, "b": 1, "c": 1})
    assert all(value is takes[n] for n, value in got)


def test_takes_read_back_in_two_threads_do_not_wait_on_each_other():
    """Two threads reading different takes load them side by side: take a's loader finishes only
    once take b's loader has started (one lock for all takes would hold b until a gave up)."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from mocap.reconstruction.takes import LazyTakes

    a_entered, b_started = threading.Event(), threading.Event()

    def load_a():
        a_entered.set()
        if not b_started.wait(timeout=5.0):
            raise TimeoutError("take b was not loaded while take a was loading")
        return "A"

    def load_b():
        b_started.set()
        return "B"

    takes = LazyTakes({"a": load_a, "b": load_b})
    with ThreadPoolExecutor(2) as pool:
        fa = pool.submit(lambda: takes["a"])
        assert a_entered.wait(timeout=5.0)  # a is loading (and holds whatever lock it takes)
        fb = pool.submit(lambda: takes["b"])
        assert (fa.result(timeout=10), fb.result(timeout=10)) == ("A", "B")
    with pytest.raises(KeyError):
        takes["missing"]
