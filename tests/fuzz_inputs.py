"""Corrupted inputs for property-based tests (hypothesis) of the importers and the session loader.

Shared by ``tests/test_fuzz_inputs.py`` (bounded, in the default run) and
``benchmarks/fuzz_inputs.py`` (thousands of examples). Seeds are real vendor files
(``../shared/realdata``, read in place, never copied) and files generated here; a mutation is a
short list of the damage files really suffer: cut anywhere (a copy interrupted), bytes flipped
(a bad disk, a wrong editor encoding), a garbage line, a line deleted or repeated, emptied, cut
right after the header.

The properties:

- an importer either returns labeled data whose session then loads, or raises
  :class:`ImportError_` naming the file; nothing else (no traceback, no crash: a C3D reader that
  dies is reported as an error of the file);
- the session loader, and reading every take and command file of the loaded session, either
  succeed or raise :class:`SessionError` naming a file of the session.
"""

from __future__ import annotations

import os
import shutil
import warnings
from pathlib import Path

import numpy as np
from hypothesis import strategies as st

REALDATA = Path(os.environ.get("MOCAP_REALDATA",
                               Path(__file__).resolve().parents[2] / "shared" / "realdata"))
REAL_IMPORTS = ("vicon_nexus24_markers_emg.c3d", "qualisys_qtm217_forceplates.c3d",
                "ndi_optotrak_30hz.c3d", "vicon_nexus24_markers_export.csv")

MOTIVE = """Format Version,1.23,Take Name,face01,Take Notes,,Capture Frame Rate,120.000000,Export Frame Rate,120.000000,Capture Start Time,2026-11-22 10.00.00.000 AM,Total Frames in Take,4,Total Exported Frames,4,Rotation Type,Quaternion,Length Units,Meters,Coordinate Space,Global

,,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Marker,Marker,Marker,Marker,Marker,Marker,Unlabeled Marker,Unlabeled Marker,Unlabeled Marker
,,Head,Head,Head,Head,Head,Head,Head,Face:M001,Face:M001,Face:M001,Face:M002,Face:M002,Face:M002,Unlabeled 1000,Unlabeled 1000,Unlabeled 1000
,,1,1,1,1,1,1,1,A1,A1,A1,A2,A2,A2,U1,U1,U1
,,Rotation,Rotation,Rotation,Rotation,Position,Position,Position,Position,Position,Position,Position,Position,Position,Position,Position,Position
Frame,Time (Seconds),X,Y,Z,W,X,Y,Z,X,Y,Z,X,Y,Z,X,Y,Z
0,0.000000,0,0,0,1,0.1,0.2,0.3,0.010000,0.200000,0.030000,0.020000,0.210000,0.031000,0.5,0.5,0.5
1,0.008333,0,0,0,1,0.1,0.2,0.3,0.010100,0.200100,0.030100,,,,0.5,0.5,0.5
3,0.025000,0,0,0,1,0.1,0.2,0.3,0.010300,0.200300,0.030300,0.020300,0.210300,0.031300,,,
"""

QTM = ("FILE_VERSION\t2.0.0\nNO_OF_FRAMES\t3\nNO_OF_CAMERAS\t6\nNO_OF_MARKERS\t2\nFREQUENCY\t100\n"
       "NO_OF_ANALOG\t0\nANALOG_FREQUENCY\t0\nDESCRIPTION\t--\nTIME_STAMP\t2026-11-22, 10:00:00\n"
       "DATA_INCLUDED\t3D\nMARKER_NAMES\tM001\tM002\nTRAJECTORY_TYPES\tMeasured\tMeasured\n"
       "Frame\tTime\tM001 X\tM001 Y\tM001 Z\tM002 X\tM002 Y\tM002 Z\t\n"
       "1\t0.000\t1.000\t2.000\t3.000\t4.000\t5.000\t6.000\t\n"
       "2\t0.010\t1.100\t2.100\t3.100\t\t\t\t\n"
       "3\t0.020\t1.200\t2.200\t3.200\t0.000\t0.000\t0.000\t\n")

VICON = ("Trajectories\n100\n,,Sub:M1,,,Sub:M2,,\nFrame,Sub Frame,X,Y,Z,X,Y,Z\n,,mm,mm,mm,mm,mm,mm\n"
         "1,0,1.5,2.5,3.5,4.5,5.5,6.5\n2,0,1.6,2.6,3.6,,,\n3,0,1.7,2.7,3.7,4.7,5.7,6.7\n"
         "\nDevices\n1000\n,,EMG\nFrame,Sub Frame,V\n,,V\n1,0,0.1\n")


def generated_imports(folder: Path) -> dict[str, Path]:
    """Small valid files of every importer's format, written into ``folder``."""
    from mocap.interop.c3d_file import write_c3d
    from mocap.interop.marker_data import MarkerData

    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for name, text in (("motive.csv", MOTIVE), ("qtm.tsv", QTM), ("vicon.csv", VICON)):
        (folder / name).write_text(text, encoding="utf-8")
        out[name] = folder / name
    rng = np.random.default_rng(3)
    X = rng.normal(0.0, 30.0, (40, 4, 3))
    X[5:9, 2] = np.nan
    commands = {"DU04": np.r_[np.zeros(10), np.full(20, 26.0), np.zeros(10)],
                "DU07": np.zeros(40)}
    out["ours.c3d"] = write_c3d(folder / "ours.c3d", MarkerData(["M1", "M2", "M3", "M4"], X, 120.0),
                                commands)
    return out


def import_seeds(folder: Path) -> dict[str, bytes]:
    """Name -> bytes of every seed file: the generated ones and the real ones when present."""
    seeds = {k: p.read_bytes() for k, p in generated_imports(folder).items()}
    if REALDATA.is_dir():
        for name in REAL_IMPORTS:
            if (REALDATA / name).is_file():
                seeds[name] = (REALDATA / name).read_bytes()
    return seeds


# --------------------------------------------------------------------------------------------
# Mutations


def _line_starts(data: bytes) -> list[int]:
    return [0] + [i + 1 for i, b in enumerate(data) if b == 0x0A and i + 1 < len(data)]


@st.composite
def mutation(draw, data: bytes) -> tuple[str, bytes]:
    """One damage applied to ``data``: (description, damaged bytes)."""
    n = len(data)
    kind = draw(st.sampled_from(["cut", "flip", "flip_head", "garbage_line", "delete_line",
                                 "repeat_line", "empty", "after_header", "splice"]))
    if kind == "empty" or n == 0:
        return "emptied", b""
    if kind == "cut":
        k = draw(st.integers(0, n - 1))
        return f"cut at byte {k}", data[:k]
    if kind in ("flip", "flip_head"):
        hi = min(n, 4096) if kind == "flip_head" else n  # headers and C3D parameters live here
        out = bytearray(data)
        where = draw(st.lists(st.integers(0, hi - 1), min_size=1, max_size=4))
        for i in where:
            out[i] = draw(st.integers(0, 255))
        return f"bytes {where} changed", bytes(out)
    if kind == "splice":
        k = draw(st.integers(0, n))
        junk = draw(st.binary(min_size=1, max_size=40))
        return f"{len(junk)} bytes inserted at {k}", data[:k] + junk + data[k:]
    starts = _line_starts(data)
    i = draw(st.integers(0, len(starts) - 1))
    a = starts[i]
    b = starts[i + 1] if i + 1 < len(starts) else n
    if kind == "garbage_line":
        junk = draw(st.one_of(
            st.binary(min_size=0, max_size=60).filter(lambda s: b"\n" not in s),
            st.text(alphabet=",\t;. 0123456789-eEnaNX\"'xyz", max_size=60).map(str.encode),
        ))
        return f"garbage line before line {i + 1}", data[:a] + junk + b"\n" + data[a:]
    if kind == "delete_line":
        return f"line {i + 1} deleted", data[:a] + data[b:]
    if kind == "repeat_line":
        return f"line {i + 1} repeated", data[:b] + data[a:b] + data[b:]
    # after_header: keep the first few lines only (a file cut right after its header)
    k = draw(st.integers(1, min(len(starts), 12)))
    cut = starts[k] if k < len(starts) else n
    return f"cut after line {k}", data[:cut]


@st.composite
def damaged(draw, data: bytes, max_mutations: int = 3) -> tuple[str, bytes]:
    """``data`` with 1 to ``max_mutations`` damages: (description, bytes)."""
    what = []
    for _ in range(draw(st.integers(1, max_mutations))):
        desc, data = draw(mutation(data))
        what.append(desc)
    return "; ".join(what), data


TOML_VALUES = st.one_of(
    st.integers(-(2**63), 2**63 - 1), st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(), st.text(max_size=20), st.just(""), st.just("../outside.csv"),
    st.just("/etc/hosts"), st.lists(st.integers(-5, 300), max_size=4),
    st.lists(st.floats(allow_nan=True), max_size=4),
    st.lists(st.lists(st.floats(-1e3, 1e3), max_size=4), max_size=4),
    st.dictionaries(st.sampled_from(["id", "name", "x"]), st.integers(), max_size=2),
)


def _manifest_paths(doc, prefix=()):
    """Every key path of a manifest dict (keys and list indices)."""
    items = doc.items() if isinstance(doc, dict) else enumerate(doc)
    for k, v in items:
        yield (*prefix, k)
        if isinstance(v, (dict, list)):
            yield from _manifest_paths(v, (*prefix, k))


def mutate_manifest(draw, manifest: dict) -> bool:
    """Delete one key of ``manifest`` (a session_builders manifest dict) or give it a value of
    any TOML type, in place; False when the value is one the tests' TOML writer cannot write."""
    from session_builders import toml_dumps

    path = draw(st.sampled_from(sorted(_manifest_paths(manifest), key=repr)))
    parent = manifest
    for k in path[:-1]:
        parent = parent[k]
    if isinstance(parent, dict) and draw(st.booleans()):
        del parent[path[-1]]
    else:
        parent[path[-1]] = draw(TOML_VALUES)
    try:
        toml_dumps(manifest)
    except TypeError:
        return False
    return True


# --------------------------------------------------------------------------------------------
# Properties


def check_import(path: Path, out: Path) -> str:
    """Import ``path`` into the new session ``out``: "ok" (and the session loads, every take and
    command file reads) or "error" (an ImportError_ naming the file). Anything else raises."""
    from mocap.interop.marker_data import ImportError_
    from mocap.interop.session_io import import_files

    if out.exists():
        shutil.rmtree(out)
    try:
        import_files([path], out, fps=None)
    except ImportError_ as e:
        assert path.name in str(e), f"the error does not name the file: {e}"
        return "error"
    check_session(out, must_load=True)
    return "ok"


def check_session(root: Path, must_load: bool = False) -> str:
    """Load ``root`` and read every take and commands file: "ok", or "error" (a SessionError
    naming a file of the session); with ``must_load`` an error fails the check."""
    from mocap.core.session import SessionError, SessionWarning, load_session

    names = {"session.toml", "markers.csv"} | {p.name for p in root.rglob("*") if p.is_file()}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SessionWarning)
            s = load_session(root)
            for take in s.takes:
                s.read_take(take.name)
                if take.commands is not None:
                    s.read_commands(take.name)
    except SessionError as e:
        assert not must_load, f"an imported session does not load: {e}"
        assert any(n in str(e) for n in names), f"the error names no file of the session: {e}"
        return "error"
    return "ok"
