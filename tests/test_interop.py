"""C3D, Motive CSV, QTM TSV and Vicon CSV in and out, on our data and on real vendor files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from fuzz_inputs import MOTIVE, QTM  # the sample exports the fuzz tests damage
from mocap.cli import main
from mocap.interop.c3d_file import read_c3d, write_c3d
from mocap.interop.marker_data import ImportError_, MarkerData
from mocap.interop.session_io import export_c3d, import_files
from mocap.interop.vendor_text import read_motive_csv, read_qtm_tsv, read_vicon_csv

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
needs_realdata = pytest.mark.skipif(not REALDATA.is_dir(), reason="../shared/realdata is absent")


def test_round_trip_ours_to_c3d_and_back(small_run, tmp_path):
    out = small_run.out_dir
    files = export_c3d(out, tmp_path / "c3d", ["du04_t01", "smile_du01_07_12_planB"])
    assert len(files) == 2
    for f, take in zip(files, ["du04_t01", "smile_du01_07_12_planB"]):
        ours = pd.read_parquet(out / "trajectories" / f"{take}.parquet")
        names = list(dict.fromkeys(ours["marker"]))
        X = ours[["x", "y", "z"]].to_numpy().reshape(-1, len(names), 3)
        back = read_c3d(f)
        assert back.names == names and back.fps == small_run.session.fps
        assert np.array_equal(np.isnan(back.X), np.isnan(X))
        np.testing.assert_allclose(back.X, X, rtol=0, atol=1e-4)  # float32 in the file
        assert np.array_equal(back.X, X.astype(np.float32).astype(np.float64), equal_nan=True)
        # the commands ride along as analog channels
        rows = small_run.session.read_commands(take)
        for du in sorted(set(rows["du"])):
            values, rate, unit = back.analogs[f"DU{du:02d}"]
            assert rate == small_run.session.fps and unit == "command"
            assert values.max() == rows.loc[rows["du"] == du, "command"].max()
        # the other maintained reader sees the same file
        import c3d

        with open(f, "rb") as fh:
            reader = c3d.Reader(fh)
            labels = [s.strip() for s in reader.point_labels]
            frames = [pts for _, pts, _ in reader.read_frames()]
        assert labels == names and len(frames) == X.shape[0]
        P = np.stack([p[:, :3] for p in frames])
        seen = np.isfinite(X[..., 0])
        np.testing.assert_allclose(P[seen], X[seen], atol=1e-4)
        assert np.all(np.stack([p[:, 3] for p in frames])[~seen] < 0)  # gaps marked invalid


def test_labeled_session_from_c3d_runs(small_run, tmp_path):
    export_c3d(small_run.out_dir, tmp_path / "c3d", ["rest", "du04_t01"])
    rep = import_files(sorted((tmp_path / "c3d").glob("*.c3d")), tmp_path / "sess")
    assert rep["dus"] == [1, 4, 7, 12] and len(rep["takes"]) == 2
    rows = pd.read_csv(tmp_path / "sess" / "takes" / "du04_t01_commands.csv")
    rows = rows[rows["du"] == 4]
    orig = small_run.session.read_commands("du04_t01")
    # one row per change, same schedule as the original (which also holds repeats)
    from mocap.core.session import command_matrix

    n = 606
    assert np.array_equal(command_matrix(rows, 120.0, n, [4]), command_matrix(orig, 120.0, n, [4]))
    assert main(["validate", str(tmp_path / "sess")]) == 0




def test_motive_csv(tmp_path):
    p = tmp_path / "take.csv"
    p.write_text(MOTIVE)
    d = read_motive_csv(p)
    assert d.names == ["M001", "M002"] and d.fps == 120.0
    assert d.X.shape == (4, 2, 3)  # frame 2 was missing: inserted as a gap
    np.testing.assert_allclose(d.X[0, 0], [10.0, 200.0, 30.0])  # metres to mm
    assert np.isnan(d.X[1, 1]).all() and np.isnan(d.X[2]).all()
    text = " ".join(d.notes)
    assert "Rigid Body" in text and "Unlabeled Marker" in text and "Meters" in text
    assert "missing frame" in text


def test_motive_csv_truncated(tmp_path):
    p = tmp_path / "cut.csv"
    p.write_text(MOTIVE.rstrip("\n")[:-12])
    with pytest.raises(ImportError_, match=r"cut.csv line 10: truncated row"):
        read_motive_csv(p)



def test_qtm_tsv_with_and_without_file_version(tmp_path):
    p = tmp_path / "t.tsv"
    p.write_text(QTM)
    d = read_qtm_tsv(p)
    assert d.names == ["M001", "M002"] and d.fps == 100.0 and d.first_frame == 1
    np.testing.assert_allclose(d.X[2, 0], [1.2, 2.2, 3.2])
    assert np.isnan(d.X[1, 1]).all() and np.isnan(d.X[2, 1]).all()  # empty and 0.000 triplets
    assert any("0.000" in n for n in d.notes)
    old = tmp_path / "old.tsv"
    old.write_text(QTM.replace("FILE_VERSION\t2.0.0\n", ""))
    d2 = read_qtm_tsv(old)
    assert any("FILE_VERSION" in n for n in d2.notes)
    np.testing.assert_array_equal(np.isnan(d.X), np.isnan(d2.X))
    bare = tmp_path / "bare.tsv"
    bare.write_text("1.0\t2.0\t3.0\t4.0\t5.0\t6.0\n1.1\t2.1\t3.1\t4.1\t5.1\t6.1\n")
    with pytest.raises(ImportError_, match="frame rate"):
        read_qtm_tsv(bare)
    d3 = read_qtm_tsv(bare, fps=60)
    assert d3.names == ["M001", "M002"] and d3.X.shape == (2, 2, 3)
    bad = tmp_path / "bad.tsv"
    bad.write_text(QTM.replace("1.100", "x1.1"))
    with pytest.raises(ImportError_, match=r"bad.tsv line 15, column 3: expected a number"):
        read_qtm_tsv(bad)


def test_import_cli_reports_what_to_complete(tmp_path, capsys):
    p = tmp_path / "t.tsv"
    p.write_text(QTM)
    assert main(["import", str(p), "--out", str(tmp_path / "s")]) == 0
    out = capsys.readouterr().out
    assert "set each take's kind" in out and "note:" in out
    assert main(["import", str(p), "--out", str(tmp_path / "s")]) == 1  # never overwrites
    assert "is the session folder" in capsys.readouterr().err


@needs_realdata
@pytest.mark.parametrize("name", ["vicon_nexus24_markers_emg.c3d", "qualisys_qtm217_forceplates.c3d",
                                  "ndi_optotrak_30hz.c3d"])
def test_real_c3d_files_import_audit_and_reexport(tmp_path, name):
    from mocap.workflows.run.pipeline import run_session
    from mocap.workflows.run.settings import RunSettings

    src = REALDATA / name
    orig = read_c3d(src)
    rep = import_files([src], tmp_path / "s")
    assert rep["markers"] == orig.names
    res = run_session(tmp_path / "s", tmp_path / "out", settings=RunSettings(recording=False))
    audit = json.loads((tmp_path / "out" / "audit.json").read_text())
    gaps = {m["marker"]: m["gaps"] for m in audit["markers"]}
    with_gaps = {n for n, g in zip(orig.names, np.isnan(orig.X[..., 0]).any(axis=0)) if g}
    assert {n for n, g in gaps.items() if g > 0} == with_gaps  # the file's gaps show in the audit
    assert res.summary["audit"]["verdict"] in ("pass", "warn")
    back = export_c3d(tmp_path / "s", tmp_path / "back.c3d")[0]
    again = read_c3d(back)
    assert again.names == orig.names and again.fps == orig.fps
    assert np.array_equal(again.X, orig.X, equal_nan=True)  # identical values and gap mask


@needs_realdata
def test_vicon_csv_matches_its_c3d():
    csv = read_vicon_csv(REALDATA / "vicon_nexus24_markers_export.csv")
    c3d_ = read_c3d(REALDATA / "vicon_nexus24_markers_emg.c3d")
    assert csv.names == c3d_.names and csv.fps == c3d_.fps
    assert np.array_equal(np.isnan(csv.X), np.isnan(c3d_.X))
    assert np.nanmax(np.abs(csv.X - c3d_.X)) < 0.005 + 1e-9


def test_c3d_writer_refuses_what_it_would_write_wrongly(tmp_path):
    d = MarkerData(["a"], np.zeros((70000, 1, 3)), 120.0)
    with pytest.raises(ValueError, match="65535"):
        write_c3d(tmp_path / "long.c3d", d)


def test_duplicate_labels_and_unknown_units_are_reported(tmp_path):
    dup = MOTIVE.replace("Face:M002,Face:M002,Face:M002", "Face:M001,Face:M001,Face:M001")
    p = tmp_path / "dup.csv"
    p.write_text(dup)
    d = read_motive_csv(p)
    assert d.names == ["M001", "M001~2"]  # the second set is a second marker, not an overwrite
    np.testing.assert_allclose(d.X[0, 1], [20.0, 210.0, 31.0])
    assert any("duplicate label" in n for n in d.notes)
    p2 = tmp_path / "units.csv"
    p2.write_text(MOTIVE.replace("Length Units,Meters", "Length Units,Furlongs"))
    with pytest.raises(ImportError_, match=r"units.csv line 1 'Length Units': unknown length unit 'Furlongs'"):
        read_motive_csv(p2)
    q = tmp_path / "dup.tsv"
    q.write_text(QTM.replace("MARKER_NAMES\tM001\tM002", "MARKER_NAMES\tM001\tM001")
                 .replace("M002 X\tM002 Y\tM002 Z", "M001 X\tM001 Y\tM001 Z"))
    d2 = read_qtm_tsv(q)
    assert d2.names == ["M001", "M001~2"]
    np.testing.assert_allclose(d2.X[0], [[1, 2, 3], [4, 5, 6]])
    assert any("duplicate label 'M001' renamed 'M001~2'" in n for n in d2.notes)
