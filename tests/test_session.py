"""The session loader (mocap.core.session, manifest, session_files) against the input contract,
FORMAT.md.

Bad-input tests each break exactly one thing of a tiny valid session (session_builders) and
check the SessionError names the file and the row (CSV line, header = line 1) or manifest key.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import session_builders as sb

from mocap.core.session import (
    Session,
    SessionError,
    SessionWarning,
    command_matrix,
    load_session,
)


@pytest.fixture
def spec2d():
    return sb.session_2d("csv")


@pytest.fixture
def spec3d():
    return sb.session_3d("csv")


def write(spec, tmp_path):
    return spec.write(tmp_path / "session")


def load(spec, tmp_path) -> Session:
    return load_session(write(spec, tmp_path))


# --------------------------------------------------------------------------------------------
# Good sessions


def test_load_2d_csv(spec2d, tmp_path):
    session = load(spec2d, tmp_path)
    assert session.dimension == "2d"
    assert session.name == "tiny-2d"
    assert session.fps == sb.FPS
    assert [c.id for c in session.cameras] == ["cam1", "cam2"]
    assert session.cameras[0].focal_px == 1200.0
    assert session.cameras[1].focal_px is None
    assert session.cameras[0].width == 1280 and session.cameras[0].height == 1024
    np.testing.assert_array_equal(session.wand.marker_offsets_mm, [0.0, 45.0, 125.0])
    assert not session.wand.marker_offsets_mm.flags.writeable
    assert session.ground.markers_mm.shape == (3, 3)
    assert not session.ground.markers_mm.flags.writeable
    assert [(d.id, d.feedback) for d in session.dus] == [(1, True), (4, False)]
    assert [t.name for t in session.takes_of_kind("response")] == ["du04_t01"]
    take = session.take("du04_t01")
    assert (take.du, take.trial, take.plan) == (4, 1, None)
    assert take.file == session.root / "takes" / "du04_t01.csv"
    assert session.warnings == ()

    df = session.read_take("rest")
    assert list(df.columns) == ["frame", "camera", "x", "y"]
    assert df["frame"].dtype == np.int64
    assert df["x"].dtype == np.float64 and df["y"].dtype == np.float64
    assert pd.api.types.is_string_dtype(df["camera"])
    expected = spec2d.table("rest")
    np.testing.assert_array_equal(df["frame"], expected["frame"])
    assert df["camera"].tolist() == expected["camera"].tolist()
    np.testing.assert_allclose(df[["x", "y"]], expected[["x", "y"]])
    assert session.n_frames("rest") == sb.N_FRAMES

    commands = session.read_commands("du04_t01")
    assert commands.dtypes.to_dict() == {"time_s": np.float64, "du": np.int64, "command": np.int64}
    assert commands["command"].tolist() == [0, 13, 26]
    assert session.marker_template["name"].tolist() == list(sb.MARKERS)


def test_load_2d_parquet(tmp_path):
    spec = sb.session_2d("parquet")
    session = load(spec, tmp_path)
    assert session.take("wand").file.suffix == ".parquet"
    df = session.read_take("wand")
    assert df["frame"].dtype == np.int64 and df["x"].dtype == np.float64
    assert df["camera"].tolist() == spec.table("wand")["camera"].tolist()
    np.testing.assert_allclose(df[["x", "y"]], spec.table("wand")[["x", "y"]])


def test_load_3d_with_nan_gaps(spec3d, tmp_path):
    session = load(spec3d, tmp_path)
    assert session.dimension == "3d"
    assert session.cameras == () and session.wand is None and session.ground is None
    df = session.read_take("rest")
    assert list(df.columns) == ["frame", "marker", "x", "y", "z"]
    assert df["frame"].dtype == np.int64
    missing = df[["x", "y", "z"]].isna()
    assert (missing.all(axis=1) == missing.any(axis=1)).all()  # a marker is seen or not
    gaps = df.loc[missing.all(axis=1), ["frame", "marker"]]
    assert sorted(map(tuple, gaps.to_numpy().tolist())) == [(1, "M002"), (3, "M003")]
    np.testing.assert_allclose(df[["x", "y", "z"]], spec3d.table("rest")[["x", "y", "z"]])


def test_mixed_csv_and_parquet(tmp_path):
    spec = sb.session_2d("mixed")
    session = load(spec, tmp_path)
    suffixes = {t.file.suffix for t in session.takes}
    assert suffixes == {".csv", ".parquet"}
    for take in session.takes:
        df = session.read_take(take.name)
        assert len(df) == len(spec.table(take.name))
        assert df["frame"].dtype == np.int64


def test_load_is_lazy_about_take_bodies(spec2d, tmp_path):
    root = write(spec2d, tmp_path)
    sb.replace_line(root / "takes" / "rest.csv", 3, "not,a,valid,row")
    session = load_session(root)  # only the header is read
    assert session.take("rest").kind == "rest"
    with pytest.raises(SessionError, match=r"takes/rest\.csv line 3: frame 'not' is not a number"):
        session.read_take("rest")


def test_unknown_keys_are_warnings(spec2d, tmp_path):
    spec2d.manifest["operator"] = "kim"
    spec2d.manifest["cameras"][1]["gain"] = 2.0
    spec2d.take("rest")["notes"] = "eyes closed"
    with pytest.warns(SessionWarning) as record:
        session = load(spec2d, tmp_path)
    assert len(session.warnings) == 3
    text = "\n".join(session.warnings)
    assert "unknown key 'operator'" in text
    assert "cameras[1] ('cam2'): unknown key 'gain'" in text
    assert "takes[2] ('rest'): unknown key 'notes'" in text
    assert [str(w.message) for w in record] == list(session.warnings)


def test_csv_whitespace_and_blank_lines_tolerated(spec2d, tmp_path):
    root = write(spec2d, tmp_path)
    path = root / "takes" / "rest.csv"
    sb.replace_line(path, 2, "0, cam1 , 1.5 , 2.5\n")  # also leaves a blank line 3
    df = load_session(root).read_take("rest")
    assert (df.loc[0, "camera"], df.loc[0, "x"], df.loc[0, "y"]) == ("cam1", 1.5, 2.5)
    assert len(df) == len(spec2d.table("rest"))


def test_unknown_take_name(spec2d, tmp_path):
    with pytest.raises(SessionError, match=r"no take named 'nope' \(takes: wand, ground"):
        load(spec2d, tmp_path).take("nope")


def test_commands_read_once_per_session_each_call_a_copy(spec2d, tmp_path, monkeypatch):
    import pickle

    import mocap.core.session_files as files

    session = load(spec2d, tmp_path)
    reads = []
    real = files._read_commands
    monkeypatch.setattr(files, "_read_commands", lambda src, dus: reads.append(src) or real(src, dus))
    first = session.read_commands("du04_t01")
    first.loc[:, "command"] = -1  # a caller's changes stay with its copy
    second = session.read_commands("du04_t01")
    assert len(reads) == 1 and second["command"].between(0, 255).all()
    pd.testing.assert_frame_equal(second, real(reads[0], session.du_ids))
    # a session pickled to a worker (once per take) leaves the commands read so far behind
    assert pickle.loads(pickle.dumps(session))._commands == {}


def test_read_commands_of_take_without_commands(spec2d, tmp_path):
    with pytest.raises(SessionError, match=r"take 'rest' has no 'commands' file"):
        load(spec2d, tmp_path).read_commands("rest")


# --------------------------------------------------------------------------------------------
# Manifest violations


def test_missing_manifest(spec2d, tmp_path):
    root = write(spec2d, tmp_path)
    (root / "session.toml").unlink()
    with pytest.raises(SessionError, match=r"session\.toml: missing in .*session"):
        load_session(root)


def test_missing_schema(spec2d, tmp_path):
    del spec2d.manifest["schema"]
    with pytest.raises(
        SessionError, match=r"session\.toml: missing key 'schema' \(expected \"mocap-session/1\"\)"
    ):
        load(spec2d, tmp_path)


def test_wrong_schema(spec2d, tmp_path):
    spec2d.manifest["schema"] = "mocap-session/2"
    with pytest.raises(
        SessionError,
        match=r'session\.toml: schema: expected "mocap-session/1", got "mocap-session/2"',
    ):
        load(spec2d, tmp_path)


def test_fps_not_positive(spec2d, tmp_path):
    spec2d.manifest["fps"] = 0.0
    with pytest.raises(
        SessionError, match=r"session\.toml: fps: expected a positive number.*got 0"
    ):
        load(spec2d, tmp_path)


def test_fps_missing(spec2d, tmp_path):
    del spec2d.manifest["fps"]
    with pytest.raises(
        SessionError, match=r"session\.toml: missing key 'fps' \(expected a positive"
    ):
        load(spec2d, tmp_path)


def test_duplicate_camera_ids(spec2d, tmp_path):
    spec2d.manifest["cameras"][1]["id"] = "cam1"
    with pytest.raises(
        SessionError, match=r"session\.toml: cameras\[1\]\.id: duplicate camera id \"cam1\""
    ):
        load(spec2d, tmp_path)


def test_fewer_than_two_cameras_in_2d_session(spec2d, tmp_path):
    del spec2d.manifest["cameras"][1]
    with pytest.raises(
        SessionError, match=r"session\.toml: cameras: expected 2 or more \[\[cameras\]\].*got 1"
    ):
        load(spec2d, tmp_path)


def test_2d_session_without_cameras(spec2d, tmp_path):
    del spec2d.manifest["cameras"]
    with pytest.raises(SessionError, match=r"session\.toml: missing key 'cameras'"):
        load(spec2d, tmp_path)


def test_camera_width_not_positive(spec2d, tmp_path):
    spec2d.manifest["cameras"][0]["width"] = 0
    with pytest.raises(
        SessionError,
        match=r"session\.toml: cameras\[0\] \('cam1'\)\.width: expected a positive integer.*got 0",
    ):
        load(spec2d, tmp_path)


@pytest.mark.parametrize("where", ["dus", "cameras", "takes"])
def test_a_manifest_integer_beyond_2_to_the_53_is_refused_by_name(spec2d, tmp_path, where):
    """Found by the manifest fuzz test: a DU id of 2.0**63 passed the manifest and overflowed
    numpy's int64 when a commands file was checked against it."""
    key = {"dus": "id", "cameras": "width", "takes": "trial"}[where]
    table = spec2d.manifest[where][0]
    table[key] = 2.0**63
    with pytest.raises(
        SessionError,
        match=rf"session\.toml: {where}\[0\].*\.{key}: expected .* of at most 2\*\*53 "
        r"\(9007199254740992\) in size, got 9\.223372036854776e\+18",
    ):
        load(spec2d, tmp_path)
    table[key] = 2**53  # the largest accepted: the manifest loads or fails on something else
    try:
        load(spec2d, tmp_path)
    except SessionError as err:
        assert "2**53" not in str(err)


def test_camera_height_not_integer(spec2d, tmp_path):
    spec2d.manifest["cameras"][1]["height"] = 1024.5
    with pytest.raises(
        SessionError,
        match=r"cameras\[1\] \('cam2'\)\.height: expected a positive integer.*got 1024\.5",
    ):
        load(spec2d, tmp_path)


def test_focal_not_positive(spec2d, tmp_path):
    spec2d.manifest["cameras"][0]["focal_px"] = -1200.0
    with pytest.raises(
        SessionError,
        match=r"cameras\[0\] \('cam1'\)\.focal_px: expected a positive focal length.*got -1200",
    ):
        load(spec2d, tmp_path)


def test_wand_fewer_than_two_markers(spec2d, tmp_path):
    spec2d.manifest["wand"]["marker_offsets_mm"] = [45.0]
    with pytest.raises(
        SessionError, match=r"session\.toml: wand\.marker_offsets_mm: expected 2 or more.*got 1"
    ):
        load(spec2d, tmp_path)


def test_wand_equal_gaps(spec2d, tmp_path):
    spec2d.manifest["wand"]["marker_offsets_mm"] = [0.0, 40.0, 80.0, 125.0]
    with pytest.raises(
        SessionError,
        match=r"session\.toml: wand\.marker_offsets_mm: gaps must be distinct.*both 40 mm",
    ):
        load(spec2d, tmp_path)


def test_wand_take_without_wand_table(spec2d, tmp_path):
    del spec2d.manifest["wand"]
    with pytest.raises(SessionError, match=r"session\.toml: missing key 'wand' .*wand take 'wand'"):
        load(spec2d, tmp_path)


def test_ground_collinear(spec2d, tmp_path):
    spec2d.manifest["ground"]["markers_mm"] = [[0.0, 0, 0], [50.0, 0, 0], [120.0, 0, 0]]
    with pytest.raises(SessionError, match=r"session\.toml: ground\.markers_mm: .*collinear"):
        load(spec2d, tmp_path)


def test_ground_fewer_than_three_markers(spec2d, tmp_path):
    spec2d.manifest["ground"]["markers_mm"] = [[0.0, 0, 0], [120.0, 0, 0]]
    with pytest.raises(
        SessionError, match=r"session\.toml: ground\.markers_mm: expected 3 or more.*got 2"
    ):
        load(spec2d, tmp_path)


def test_ground_take_without_ground_table(spec2d, tmp_path):
    del spec2d.manifest["ground"]
    with pytest.raises(
        SessionError, match=r"session\.toml: missing key 'ground' .*ground take 'ground'"
    ):
        load(spec2d, tmp_path)


def test_unknown_take_kind(spec2d, tmp_path):
    spec2d.take("rest")["kind"] = "calib"
    with pytest.raises(
        SessionError,
        match=r"session\.toml: takes\[2\] \('rest'\)\.kind: unknown take kind \"calib\" "
        r"\(expected wand \| points \| ground \| rest \| response \| motion\)",
    ):
        load(spec2d, tmp_path)


def test_duplicate_take_names(spec2d, tmp_path):
    spec2d.manifest["takes"][1]["name"] = "wand"
    with pytest.raises(
        SessionError,
        match=r"session\.toml: takes\[1\]\.name: duplicate take name \"wand\" .*takes\[0\]",
    ):
        load(spec2d, tmp_path)


def test_response_take_without_du(spec2d, tmp_path):
    del spec2d.take("du04_t01")["du"]
    with pytest.raises(
        SessionError, match=r"session\.toml: takes\[3\] \('du04_t01'\): missing key 'du'"
    ):
        load(spec2d, tmp_path)


def test_response_take_without_commands(spec2d, tmp_path):
    del spec2d.take("du04_t01")["commands"]
    with pytest.raises(
        SessionError, match=r"session\.toml: takes\[3\] \('du04_t01'\): missing key 'commands'"
    ):
        load(spec2d, tmp_path)


def test_take_file_does_not_exist(spec2d, tmp_path):
    spec2d.take("rest")["file"] = "takes/nope.csv"
    with pytest.raises(
        SessionError,
        match=r"takes/nope\.csv: file not found \(session\.toml takes\[2\] \('rest'\)\.file\)",
    ):
        load(spec2d, tmp_path)


def test_commands_file_does_not_exist(spec2d, tmp_path):
    spec2d.take("du04_t01")["commands"] = "takes/gone.csv"
    with pytest.raises(
        SessionError, match=r"takes/gone\.csv: file not found .*takes\[3\] \('du04_t01'\)\.commands"
    ):
        load(spec2d, tmp_path)


# --------------------------------------------------------------------------------------------
# Take file violations (row numbers: data row i is CSV line i + 2)


def test_mixed_2d_and_3d_takes(spec2d, tmp_path):
    spec2d.files[spec2d.take_file("rest")] = sb.markers_3d()
    with pytest.raises(
        SessionError,
        match=r"takes/rest\.csv: holds labeled 3D markers \(3D\) but take 'wand' "
        r"\(takes/wand\.csv\) is 2D",
    ):
        load(spec2d, tmp_path)


def test_parquet_take_missing_column(tmp_path):
    spec = sb.session_2d("parquet")
    spec.files[spec.take_file("rest")] = spec.table("rest").drop(columns="y")
    with pytest.raises(
        SessionError,
        match=r"takes/rest\.parquet: missing column\(s\) 'y' \(expected 2D detections: "
        r"frame, camera, x, y; got frame, camera, x\)",
    ):
        load(spec, tmp_path)


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_empty_take(fmt, tmp_path):
    spec = sb.session_2d(fmt)
    spec.files[spec.take_file("rest")] = spec.table("rest").iloc[:0]
    with pytest.raises(SessionError, match=rf"takes/rest\.{fmt}: no data rows \(header only\)"):
        load(spec, tmp_path)


def test_csv_truncated_mid_row(spec2d, tmp_path):
    root = write(spec2d, tmp_path)
    n_lines = len(spec2d.table("rest")) + 1
    sb.append_text(root / "takes" / "rest.csv", "5,cam1,612.3")
    session = load_session(root)
    with pytest.raises(
        SessionError,
        match=rf"takes/rest\.csv line {n_lines + 1}: 3 field\(s\), expected 4 .*truncated",
    ):
        session.read_take("rest")


def test_camera_not_in_manifest(spec2d, tmp_path):
    spec2d.table("rest").loc[5, "camera"] = "cam9"
    with pytest.raises(
        SessionError,
        match=r"takes/rest\.csv line 7: camera 'cam9' is not in the manifest "
        r"\(cameras: cam1, cam2\)",
    ):
        load(spec2d, tmp_path).read_take("rest")


def test_non_numeric_x(spec2d, tmp_path):
    root = write(spec2d, tmp_path)
    sb.replace_line(root / "takes" / "rest.csv", 5, "1,cam1,12O.5,300.0")
    with pytest.raises(SessionError, match=r"takes/rest\.csv line 5: x '12O\.5' is not a number"):
        load_session(root).read_take("rest")


def test_nan_x_in_2d_take(spec2d, tmp_path):
    spec2d.table("rest").loc[2, "x"] = np.nan
    with pytest.raises(
        SessionError, match=r"takes/rest\.csv line 4: x is empty or NaN \(expected a finite"
    ):
        load(spec2d, tmp_path).read_take("rest")


def test_infinite_y_in_2d_take(spec2d, tmp_path):
    spec2d.table("rest").loc[8, "y"] = np.inf
    with pytest.raises(SessionError, match=r"takes/rest\.csv line 10: y inf is infinite"):
        load(spec2d, tmp_path).read_take("rest")


def test_infinite_z_in_3d_take(spec3d, tmp_path):
    spec3d.table("rest").loc[4, "z"] = -np.inf
    with pytest.raises(SessionError, match=r"takes/rest\.csv line 6: z -inf is infinite"):
        load(spec3d, tmp_path).read_take("rest")


def test_negative_frame(spec2d, tmp_path):
    spec2d.table("rest").loc[0, "frame"] = -1
    with pytest.raises(
        SessionError,
        match=r"takes/rest\.csv line 2: frame -1 is negative \(expected an integer frame >= 0\)",
    ):
        load(spec2d, tmp_path).read_take("rest")


@pytest.mark.parametrize("column", ["camera", "marker"])
def test_parquet_text_that_is_not_utf8_is_named_by_row(tmp_path, column):
    """Parquet readers do not check string bytes (found by the damaged-file fuzz test: a flipped
    byte in a camera name gave a UnicodeDecodeError / ArrowInvalid instead of an error that
    names the file and row)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    spec = sb.session_2d("parquet") if column == "camera" else sb.session_3d("parquet")
    root = write(spec, tmp_path)
    path = root / spec.take_file("rest")
    table = pq.read_table(path)
    raw = [v.encode() for v in table.column(column).to_pylist()]
    raw[5] = b"c\x80m"
    bad = pa.array(raw, pa.binary()).view(pa.string())
    pq.write_table(table.set_column(table.schema.get_field_index(column), column, bad), path)
    with pytest.raises(
        SessionError,
        match=rf"takes/rest\.parquet row 6: {column} b'c\\x80m' is not UTF-8 text",
    ):
        load_session(root).read_take("rest")


def test_non_integer_frame_parquet(tmp_path):
    spec = sb.session_2d("parquet")
    table = spec.table("rest")
    spec.files[spec.take_file("rest")] = table.assign(frame=table["frame"].astype(float))
    spec.table("rest").loc[3, "frame"] = 2.5
    with pytest.raises(
        SessionError, match=r"takes/rest\.parquet row 4: frame 2\.5 is not an integer"
    ):
        load(spec, tmp_path).read_take("rest")


# --------------------------------------------------------------------------------------------
# Commands file violations (commands of take du04_t01: rows at 0, 0.02, 0.03 s on DU 4)


def _commands(spec):
    return spec.files[spec.take("du04_t01")["commands"]]


def test_command_outside_range(spec2d, tmp_path):
    _commands(spec2d).loc[2, "command"] = 300
    with pytest.raises(
        SessionError,
        match=r"takes/du04_t01_commands\.csv line 4: command 300 is above 255 "
        r"\(expected an integer command 0\.\.255\)",
    ):
        load(spec2d, tmp_path).read_commands("du04_t01")


def test_command_not_integer(spec2d, tmp_path):
    commands = _commands(spec2d)
    spec2d.files[spec2d.take("du04_t01")["commands"]] = commands.assign(
        command=commands["command"].astype(float)
    )
    _commands(spec2d).loc[1, "command"] = 12.5
    with pytest.raises(
        SessionError,
        match=r"takes/du04_t01_commands\.csv line 3: command 12\.5 is not an integer",
    ):
        load(spec2d, tmp_path).read_commands("du04_t01")


def test_command_du_not_in_manifest(spec2d, tmp_path):
    _commands(spec2d).loc[1, "du"] = 7
    with pytest.raises(
        SessionError,
        match=r"takes/du04_t01_commands\.csv line 3: du 7 is not in the manifest's \[\[dus\]\] "
        r"\(ids: 1, 4\)",
    ):
        load(spec2d, tmp_path).read_commands("du04_t01")


def test_negative_time(spec2d, tmp_path):
    _commands(spec2d).loc[0, "time_s"] = -0.01
    with pytest.raises(
        SessionError, match=r"takes/du04_t01_commands\.csv line 2: time_s -0\.01 is negative"
    ):
        load(spec2d, tmp_path).read_commands("du04_t01")


# --------------------------------------------------------------------------------------------
# markers.csv violations


def test_markers_missing_column(spec3d, tmp_path):
    spec3d.markers = spec3d.markers.drop(columns="z")
    with pytest.raises(SessionError, match=r"markers\.csv: missing column\(s\) 'z'"):
        load(spec3d, tmp_path)


def test_markers_duplicate_name(spec3d, tmp_path):
    spec3d.markers.loc[2, "name"] = "M001"
    with pytest.raises(SessionError, match=r"markers\.csv line 4: duplicate marker name 'M001'"):
        load(spec3d, tmp_path)


def test_markers_non_numeric(spec3d, tmp_path):
    root = write(spec3d, tmp_path)
    sb.replace_line(root / "markers.csv", 3, "M002,20.0,five,8.0")
    with pytest.raises(SessionError, match=r"markers\.csv line 3: y 'five' is not a number"):
        load_session(root)


# --------------------------------------------------------------------------------------------
# command_matrix


def test_command_matrix_hand_worked():
    # fps 3: frames at 0, 1/3, 2/3, 1, 4/3, 5/3 s; columns DU 1, 2, 4.
    commands = pd.DataFrame(
        [
            (1.3333334, 1, 20),  # 6.7e-8 s after frame 4: drives frame 5 only
            (0.3333333333, 1, 10),  # 3e-11 s before frame 1: within tolerance, drives frame 1
            (1.0, 1, 10),  # a repeat: no change
            (0.0, 4, 3),
            (0.6666666667, 4, 9),  # 3e-11 s after frame 2: within tolerance, drives frame 2
            (1.0, 4, 4),
            (1.0, 4, 6),  # same time as the row above: the later row wins
            (5.0, 4, 99),  # after the take's end: ignored
            (0.0, 7, 255),  # DU 7 not asked for: ignored
        ],
        columns=["time_s", "du", "command"],
    )
    got = command_matrix(commands, 3.0, 6, [1, 2, 4])
    expected = np.array(
        [
            [0, 0, 3],
            [10, 0, 3],
            [10, 0, 9],
            [10, 0, 6],
            [10, 0, 6],
            [20, 0, 6],
        ]
    )
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, expected)


def test_command_matrix_beyond_tolerance():
    # 2e-9 s late misses frame 1 (1/10 s) and drives frame 2.
    commands = pd.DataFrame({"time_s": [0.1 + 2e-9], "du": [1], "command": [5]})
    np.testing.assert_array_equal(command_matrix(commands, 10.0, 3, [1])[:, 0], [0, 0, 5])


def test_command_matrix_no_frames_or_rows():
    empty = pd.DataFrame({"time_s": [], "du": [], "command": []})
    assert command_matrix(empty, 100.0, 4, [1, 4]).tolist() == [[0, 0]] * 4
    assert command_matrix(empty, 100.0, 0, [1, 4]).shape == (0, 2)


def test_2d_take_reads_alike_from_csv_and_every_parquet_string_encoding(tmp_path):
    """A take's blobs read the same from CSV, from Parquet with the camera column
    dictionary-encoded (pyarrow's default, read as a dictionary and checked per distinct id) or
    plain, and with ids padded by spaces: camera a categorical over the manifest's ids in its
    order, frame int64, x and y float64."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    expected = None
    for kind in ("csv", "parquet-dict", "parquet-plain", "parquet-padded"):
        spec = sb.session_2d("csv" if kind == "csv" else "parquet")
        root = write(spec, tmp_path / kind)
        if kind != "csv":
            path = root / spec.take_file("rest")
            table = pq.read_table(path)
            if kind == "parquet-padded":
                cams = [f"  {c} " for c in table.column("camera").to_pylist()]
                i = table.schema.get_field_index("camera")
                table = table.set_column(i, "camera", pa.array(cams, pa.string()))
            pq.write_table(table, path, use_dictionary=kind != "parquet-plain")
        session = load_session(root)
        df = session.read_take("rest")
        assert isinstance(df["camera"].dtype, pd.CategoricalDtype)
        assert list(df["camera"].cat.categories) == list(session.camera_ids)
        assert [str(t) for t in df.dtypes[["frame", "x", "y"]]] == ["int64", "float64", "float64"]
        plain = df.assign(camera=df["camera"].astype(str))
        if expected is None:
            expected = plain
            truth = spec.table("rest")
            assert list(plain["camera"]) == [c.strip() for c in truth["camera"]]
            np.testing.assert_array_equal(plain["x"], truth["x"].astype(float))
        else:
            pd.testing.assert_frame_equal(plain, expected, obj=kind)


@pytest.mark.parametrize("use_dictionary", [True, False])
def test_parquet_camera_not_in_manifest_and_negative_frame_named_by_row(tmp_path,
                                                                         use_dictionary):
    """The Parquet fast paths (a dictionary camera column, an integer frame column) name the
    row of a bad value as the general path does."""
    import pyarrow.parquet as pq

    spec = sb.session_2d("parquet")
    root = write(spec, tmp_path / "cam")
    path = root / spec.take_file("rest")
    df = pq.read_table(path).to_pandas()
    df.loc[5, "camera"] = "cam9"
    pq.write_table(pa_table(df), path, use_dictionary=use_dictionary)
    with pytest.raises(SessionError, match=r"takes/rest\.parquet row 6: camera 'cam9' is not "
                                           r"in the manifest \(cameras: cam1, cam2\)"):
        load_session(root).read_take("rest")
    df = pq.read_table(path).to_pandas()
    df.loc[5, "camera"] = df.loc[4, "camera"]
    df["frame"] = df["frame"].astype("int64")
    df.loc[7, "frame"] = -3
    pq.write_table(pa_table(df), path, use_dictionary=use_dictionary)
    with pytest.raises(SessionError, match=r"takes/rest\.parquet row 8: frame -3 is negative"):
        load_session(root).read_take("rest")


def pa_table(df):
    import pyarrow as pa

    return pa.Table.from_pandas(df, preserve_index=False)
