"""Malformed vendor files: the cases issue #19 found, and the C3D reader's isolation.

A damaged C3D can crash ezc3d (a segmentation fault) or make it allocate without bound; the
reader runs it in a child process with a memory and a time limit, so each of those becomes an
ImportError_ naming the file. The crash, the allocation and the stall are provoked directly
(the child runs a replaced parser), and the real crash on a real file where it is present.
"""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest
from fuzz_inputs import REALDATA, VICON, check_import

from mocap.interop import c3d_file
from mocap.interop.c3d_file import read_c3d, write_c3d
from mocap.interop.marker_data import ImportError_, MarkerData
from mocap.interop.session_io import import_files
from mocap.interop.vendor_text import read_vicon_csv
from mocap.core.session import load_session


def _c3d(tmp_path, names=("Knee", "Heel", "Toe")):
    X = np.random.default_rng(0).normal(0, 20, (12, len(names), 3))
    return write_c3d(tmp_path / "t.c3d", MarkerData(list(names), X, 100.0))


def test_c3d_labels_that_are_not_utf8_are_read_as_latin1(tmp_path):
    path = _c3d(tmp_path)
    data = path.read_bytes()
    assert data.count(b"Knee") == 1
    path.write_bytes(data.replace(b"Knee", b"Kn\xe9e"))  # Latin-1 e-acute: invalid UTF-8
    d = read_c3d(path)
    assert d.names[0] == "Kn\u00e9e"
    assert any("not UTF-8" in n and "POINT:LABELS entry 1" in n for n in d.notes)
    # before: pyarrow refused the surrogate escapes when the take was written
    assert check_import(path, tmp_path / "s") == "ok"
    assert load_session(tmp_path / "s").read_take("t")["marker"].iloc[0] == "Kn\u00e9e"


@pytest.mark.parametrize("lines", [1, 2, 3, 4])
def test_a_vicon_csv_cut_inside_its_header_names_file_and_line(tmp_path, lines):
    path = tmp_path / "cut.csv"
    path.write_text("\n".join(VICON.splitlines()[:lines]) + "\n")
    with pytest.raises(ImportError_, match=r"cut\.csv line \d+: the Trajectories header ends"):
        read_vicon_csv(path)


def test_vicon_rates_and_frames_that_are_not_numbers(tmp_path):
    path = tmp_path / "v.csv"
    path.write_text(VICON.replace("Trajectories\n100\n", "Trajectories\nfast\n"))
    with pytest.raises(ImportError_, match=r"v\.csv line 2: frame rate 'fast' is not a number"):
        read_vicon_csv(path)
    path.write_text(VICON.replace("\n2,0,1.6", "\n2.5,0,1.6"))
    with pytest.raises(ImportError_, match=r"v\.csv line 7: frame number 2\.5 is not an integer"):
        read_vicon_csv(path)
    path.write_text(VICON.replace("\n3,0,1.7", "\n300000000,0,1.7"))
    with pytest.raises(ImportError_, match=r"v\.csv line 8: frame numbers jump from 2 to 300000000"):
        read_vicon_csv(path)
    path.write_text(VICON.replace("4.5,5.5", "inf,5.5"))
    with pytest.raises(ImportError_, match=r"v\.csv line 6, column 6: expected a finite number"):
        read_vicon_csv(path)


def test_import_writes_marker_names_a_take_file_can_hold(tmp_path):
    path = tmp_path / "v.csv"
    path.write_text(VICON.replace("Sub:M1", 'Sub:M"1'))
    rep = import_files([path], tmp_path / "s")
    assert rep["markers"] == ["M_1", "M2"] and any("written as 'M_1'" in n for n in rep["notes"])
    assert set(load_session(tmp_path / "s").read_take("v")["marker"]) == {"M_1", "M2"}


def _crash(path):
    os.kill(os.getpid(), signal.SIGSEGV)


def _allocate(path):
    return np.ones((1 << 40) // 8)  # 1 TiB


def _stall(path):
    time.sleep(60)


def test_a_crashing_c3d_reader_becomes_an_error_of_the_file(tmp_path, monkeypatch):
    path = _c3d(tmp_path)
    monkeypatch.setattr(c3d_file, "_read_c3d", _crash)
    with pytest.raises(ImportError_, match=r"t\.c3d: not a readable C3D file \(the C3D reader "
                                           r"crashed on it, exit code -11"):
        read_c3d(path)


def test_an_allocating_c3d_reader_is_stopped(tmp_path, monkeypatch):
    path = _c3d(tmp_path)
    monkeypatch.setattr(c3d_file, "_read_c3d", _allocate)
    with pytest.raises(ImportError_, match=r"t\.c3d: .*more memory than its size can justify"):
        read_c3d(path)


def test_a_stalled_c3d_reader_is_stopped(tmp_path, monkeypatch):
    path = _c3d(tmp_path)
    monkeypatch.setattr(c3d_file, "_read_c3d", _stall)
    monkeypatch.setattr(c3d_file, "CHILD_SECONDS", (0.5, 0.0))
    t0 = time.perf_counter()
    with pytest.raises(ImportError_, match=r"t\.c3d: .*took longer than 0 s"):
        read_c3d(path)
    assert time.perf_counter() - t0 < 30


def test_a_c3d_cut_before_the_end_of_its_parameter_section_is_refused_before_parsing(
        tmp_path, monkeypatch):
    """Cut inside its header or parameter section, a C3D made ezc3d crash (a cut at byte 520 of
    a 2-block parameter section) or loop until the child's 60 s limit (byte 820): the sizes in
    the header tell it, and the file is refused before any parser runs (the parser is replaced
    by one that accepts everything); a cut in the data section still goes to the parser."""
    path = _c3d(tmp_path)
    data = path.read_bytes()
    end = (data[0] - 1 + data[(data[0] - 1) * 512 + 2]) * 512  # the parameter section's end
    monkeypatch.setattr(c3d_file, "_read_c3d", lambda p: "parsed")
    for cut in (0, 100, 511, 512, 515, 520, 820, end - 1):
        bad = tmp_path / f"cut{cut}.c3d"
        bad.write_bytes(data[:cut])
        with pytest.raises(ImportError_, match=str(bad)) as e:
            read_c3d(bad)
        assert "C3D" in str(e.value) and ("cut" in str(e.value) or "header" in str(e.value))
    bad = tmp_path / "wrongkey.c3d"
    bad.write_bytes(data[:1] + b"\x51" + data[2:])
    with pytest.raises(ImportError_, match="0x50"):
        read_c3d(bad)
    cut = tmp_path / "data_cut.c3d"
    cut.write_bytes(data[:end + 10])
    assert read_c3d(cut) == "parsed"


def test_errors_raised_in_the_child_keep_their_type(tmp_path):
    with pytest.raises(ImportError_, match="file not found"):
        read_c3d(tmp_path / "none.c3d")
    bad = tmp_path / "junk.c3d"
    bad.write_bytes(b"\x00" * 100)
    with pytest.raises(ImportError_, match=r"junk\.c3d: not a C3D file"):  # refused by its size
        read_c3d(bad)
    # a header and a parameter section of the right sizes, all zeros: the parser's own error
    bad = tmp_path / "zeros.c3d"
    bad.write_bytes(bytes([2, 0x50]) + bytes(510) + bytes([0, 0, 1, 84]) + bytes(1532))
    with pytest.raises(ImportError_, match=r"zeros\.c3d"):
        read_c3d(bad)


@pytest.mark.skipif(not (REALDATA / "ndi_optotrak_30hz.c3d").is_file(),
                    reason="../shared/realdata is absent")
def test_the_real_file_that_crashed_ezc3d(tmp_path):
    data = bytearray((REALDATA / "ndi_optotrak_30hz.c3d").read_bytes())
    data[2796] = 236  # one parameter byte: ezc3d 1.7 dies of a segmentation fault on it
    path = tmp_path / "optotrak.c3d"
    path.write_bytes(bytes(data))
    with pytest.raises(ImportError_, match=r"optotrak\.c3d: not a readable C3D file"):
        read_c3d(path)


def test_a_bad_commands_file_is_refused_before_anything_is_written(tmp_path):
    take = tmp_path / "v.csv"
    take.write_text(VICON)
    cmd = tmp_path / "c.csv"
    cmd.write_text("time_s,du,command\n0,4,0\n0.5,4,12.5\n")
    with pytest.raises(ImportError_, match=r"c\.csv line 3: command '12\.5' is not an integer"):
        import_files([take], tmp_path / "s", commands=cmd)
    assert not (tmp_path / "s").exists()
    cmd.write_text("time_s,du,command\n0,4,0\n0.5,4,12\n")
    rep = import_files([take], tmp_path / "s", commands=cmd)
    assert rep["dus"] == [4]
    assert load_session(tmp_path / "s").read_commands("v")["command"].tolist() == [0, 12]
