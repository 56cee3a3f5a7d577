"""The Rerun recording, read back with the Rerun SDK's own reader."""

from __future__ import annotations

import subprocess
import sys
from collections import Counter

import numpy as np
import pandas as pd
import pytest


@pytest.fixture(scope="module")
def chunks(small_run):
    from rerun.chunk import RrdReader

    path = small_run.out_dir / "session.rrd"
    assert path.is_file()
    reader = RrdReader(path)
    rows, timelines = Counter(), {}
    for ch in reader.stream():
        rows[ch.entity_path] += ch.num_rows
        timelines.setdefault(ch.entity_path, set()).update(ch.timeline_names)
    return reader, rows, timelines


def test_recording_holds_rig_markers_and_plots(small_run, chunks):
    reader, rows, timelines = chunks
    session = small_run.session
    cams = list(small_run.calibration.rig.ids)
    for c in cams:
        assert rows[f"/world/cameras/{c}"] >= 1 and rows[f"/world/cameras/{c}/image"] >= 1
        assert rows[f"/world/cameras/{c}/image/wand"] > 100
        assert rows[f"/world/cameras/{c}/image/blobs/rest"] > 0
    assert rows["/world/calibration/wand"] == len(small_run.calibration.wand_frames)
    assert rows["/world/calibration/ground"] == 1
    for take in session.takes:
        if take.kind not in ("rest", "response", "motion"):
            continue
        df = pd.read_parquet(small_run.out_dir / "trajectories" / f"{take.name}.parquet")
        frames_with_points = df.loc[df["x"].notna(), "frame"].nunique()
        assert rows[f"/world/takes/{take.name}/markers"] == frames_with_points, take.name
        assert {"frame", "time"} <= timelines[f"/world/takes/{take.name}/markers"]
        assert rows[f"/world/takes/{take.name}/paths"] == 1
        if take.commands is not None:
            n_frames = df["frame"].max() + 1
            assert rows[f"/plots/commands/{take.name}"] == n_frames + 1  # + the static styling
    for du in (1, 4, 7, 12):
        assert rows[f"/plots/du{du:02d}/response"] > 600
    for path in ("/charts/property_chart", "/annotations/rejections", "/world/rejected",
                 "/world/rest", "/annotations/audit"):
        assert rows[path] >= 1, path
    assert len(list(reader.blueprints())) >= 1


def test_recording_blob_colours_reflect_roles(small_run):
    role = small_run.reconstruction.blob_roles["rest"].role
    labels = pd.read_parquet(small_run.session.root.parent / "truth" / "labels" / "rest.parquet")["label"].to_numpy()
    # blobs labeled as markers are real markers; ghosts rarely are
    assert np.mean(labels[role == 0] >= 0) > 0.999
    assert np.mean(role[labels == -1] != 0) > 0.95


def test_core_packages_do_not_import_rerun():
    code = ("import sys, mocap.workflows.run.pipeline, mocap.workflows.audit, calib.wand_calibration, analysis.session_analysis;"
            "sys.exit(1 if 'rerun' in sys.modules else 0)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_replay_without_display(small_run, capsys, monkeypatch):
    from mocap.cli import main

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert main(["replay", str(small_run.out_dir)]) == 0
    assert "rerun session.rrd" in capsys.readouterr().out
    assert main(["replay", str(small_run.out_dir / "nothing")]) == 1


def test_sample_data_recording_loads_back(sample_run):
    from rerun.chunk import RrdReader

    rows = Counter()
    for ch in RrdReader(sample_run.out_dir / "session.rrd").stream():
        rows[ch.entity_path] += ch.num_rows
    prefixes = ["/world/cameras/cam1/image/wand", "/world/cameras/cam1/image/blobs/rest",
                "/world/calibration/wand", "/plots/calibration/residual_px", "/world/rest",
                "/world/takes/rest/markers", "/world/takes/du04_t01/paths",
                "/plots/commands/du04_t01", "/plots/du04/response", "/charts/property_chart",
                "/annotations/rejections", "/annotations/audit"]
    for p in prefixes:
        assert rows[p] > 0, p


def _chunk_contents(path) -> dict:
    """(entity, column) -> the sorted contents of its chunks, row ids and the recording's start
    time left out: what a viewer shows, whatever order the chunks were written in."""
    from rerun.chunk import RrdReader

    out: dict = {}
    for ch in RrdReader(path).stream():
        rb = ch.to_record_batch()
        for name in rb.schema.names:
            if "rowid" in name.lower().replace("_", "") or name.endswith("start_time"):
                continue
            out.setdefault((ch.entity_path, name), []).append(repr(rb.column(name).to_pylist()))
    return {k: sorted(v) for k, v in out.items()}


def test_recording_written_beside_the_run_equals_one_written_after_it(small_run, tmp_path):
    """The run starts its recording when the takes are reconstructed and logs them on a thread
    while the trials and analyses go on; the file equals one written from the finished result
    in one go."""
    from mocap.outputs.recording import write_recording

    after = write_recording(tmp_path / "after.rrd", small_run)
    beside = _chunk_contents(small_run.out_dir / "session.rrd")
    assert beside == _chunk_contents(after)
    assert any(entity.startswith("/world/takes/") for entity, _ in beside)


def _no_recording_left(out) -> None:
    assert not (out / "session.rrd").exists()
    assert not list(out.glob(".session.rrd*")), "a temporary recording was left behind"


def test_run_failing_after_the_reconstruction_leaves_no_recording(tiny_sim, tmp_path,
                                                                   monkeypatch):
    import mocap.workflows.run.pipeline as pipeline
    from mocap.outputs.run_writers import WRITERS
    from mocap.workflows.run.settings import RunSettings

    def fail(*args, **kwargs):
        raise RuntimeError("analysis failed on purpose")

    monkeypatch.setattr(pipeline, "analyze_session", fail)
    out = tmp_path / "out"
    with pytest.raises(RuntimeError, match="on purpose"):
        pipeline.run_session(tiny_sim / "session", out,
                             settings=RunSettings(jobs=1), writers=WRITERS)
    _no_recording_left(out)
    assert len(list((out / "trajectories").glob("*.parquet"))) > 0  # the takes are kept


def test_failure_while_recording_the_takes_is_raised_and_a_rerun_only_records(
        tiny_sim, tmp_path, monkeypatch, capsys):
    import mocap.outputs.recording as recording
    from mocap.cli import main

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device (on purpose)")

    out = tmp_path / "out"
    with monkeypatch.context() as m:
        m.setattr(recording, "_log_takes", full_disk)
        assert main(["run", str(tiny_sim / "session"), "--out", str(out), "--jobs", "1",
                     "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "error: [Errno 28] No space left on device (on purpose)" in err
    assert "Traceback" not in err
    _no_recording_left(out)
    for table in ("properties.csv", "audit.json", "responses.parquet"):
        assert (out / table).is_file(), table  # the stages before the recording are kept
    assert main(["run", str(tiny_sim / "session"), "--out", str(out), "--jobs", "1"]) == 0
    stdout = capsys.readouterr().out
    assert "computed: recording" in stdout, stdout
    assert (out / "session.rrd").is_file()
    assert not list(out.glob(".session.rrd*"))
