"""C3D read and write with ezc3d.

Why ezc3d: a maintained C++ core with manylinux wheels (MIT), a plain dict-like API, and
residual handling the field relies on (a residual < 0 marks a gap: Vicon Nexus, Visual3D and
Mokka read it so). The pure-Python ``c3d`` package reads the same files identically and serves
as the cross-check in the tests.

Reading: POINT:LABELS (and LABELS2...), POINT:UNITS converted to mm, residual < 0 or NaN
coordinates are gaps, POINT entries that are model outputs (listed in POINT:ANGLES, FORCES,
MOMENTS, POWERS, SCALARS, REACTIONS) are left out with a note, duplicate labels renamed with a
note; ANALOG channels kept with their rate and unit.

Writing: points in mm with residual -1 at gaps (ezc3d writes NaN with residual 0 otherwise) and
0 elsewhere; commands as ANALOG channels at the point rate (``DU04``, unit ``command``), scale 1
and offset 0 (the c3d package's writer leaves them empty, which crashes ezc3d). ezc3d 1.7.2
writes files of more than 65,535 frames wrongly, so longer takes are refused with a clear error.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mocap.core.atomic import atomic_path
from mocap.interop.marker_data import ImportError_, MarkerData, unique_names, unit_scale

MODEL_OUTPUT_GROUPS = ("ANGLES", "FORCES", "MOMENTS", "POWERS", "SCALARS", "REACTIONS")
MAX_FRAMES = 65535


def _text(value, where: str, notes: list[str]) -> str:
    """A C3D string parameter as text: bytes that are not UTF-8 (ezc3d hands them over as
    surrogate escapes, which no writer accepts) are read as Latin-1, noted."""
    text = str(value).strip()
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        text = text.encode("utf-8", "surrogateescape").decode("latin-1")
        notes.append(f"{where}: {text!r} is not UTF-8; read as Latin-1")
    return text


def _labels(group: dict, where: str, notes: list[str], base: str = "LABELS") -> list[str]:
    out = list(np.atleast_1d(group.get(base, {}).get("value", [])))
    k = 2
    while f"{base}{k}" in group:
        out += list(np.atleast_1d(group[f"{base}{k}"]["value"]))
        k += 1
    return [_text(v, f"{where}:{base} entry {i + 1}", notes) for i, v in enumerate(out)]


def _first_number(group: dict, key: str, where: str) -> float:
    """The first value of a numeric parameter, finite, or an ImportError_ naming it."""
    try:
        value = float(np.atleast_1d(group[key]["value"])[0])
    except (KeyError, IndexError, TypeError, ValueError):
        raise ImportError_(f"{where}:{key}: missing or not a number") from None
    if not np.isfinite(value):
        raise ImportError_(f"{where}:{key}: expected a finite number, got {value}")
    return value


# The C3D reader's budget in its child process: memory beyond what the caller already maps, and
# time. A valid file needs a few times its size in memory and reads at tens of MB/s; a damaged
# header can make ezc3d allocate without bound (12 GB seen) or crash.
CHILD_MEMORY_BYTES = (1 << 30, 40)  # 1 GiB + 40 x the file's size
CHILD_SECONDS = (60.0, 2.0)  # 60 s + 2 s per MB of file


def read_c3d(path: str | os.PathLike) -> MarkerData:
    """Read a C3D file's labeled points (and analog channels) as :class:`MarkerData`.

    ezc3d can crash the interpreter (a segmentation fault) or allocate without bound on a
    corrupted file, so where the platform can fork the file is parsed in a child process with a
    memory limit and a time limit (``CHILD_MEMORY_BYTES``, ``CHILD_SECONDS``): a crash, an
    allocation failure or a timeout there becomes an ImportError_ naming the file instead of
    killing or stalling the caller.
    """
    import multiprocessing as mp

    path = Path(path)
    _check_extent(path)
    if "fork" not in mp.get_all_start_methods():  # pragma: no cover - Windows
        return _read_c3d(path)
    size = path.stat().st_size if path.is_file() else 0
    limit_s = CHILD_SECONDS[0] + CHILD_SECONDS[1] * size / 1e6
    ctx = mp.get_context("fork")
    receive, send = ctx.Pipe(duplex=False)
    child = ctx.Process(target=_read_c3d_child,
                        args=(path, send, CHILD_MEMORY_BYTES[0] + CHILD_MEMORY_BYTES[1] * size),
                        daemon=True)
    child.start()
    send.close()
    outcome, why = None, "crashed on it"
    try:
        if receive.poll(limit_s):
            outcome = receive.recv()
        else:
            why = f"took longer than {limit_s:.0f} s"
    except EOFError:  # the child died before answering
        pass
    finally:
        receive.close()
        if child.is_alive():
            child.kill()
        child.join()
    if outcome is None:
        raise ImportError_(f"{path}: not a readable C3D file (the C3D reader {why}, exit code "
                           f"{child.exitcode}: the file is corrupted)")
    ok, value = outcome
    if not ok:
        raise value
    return value


def _check_extent(path: Path) -> None:
    """Refuse at once a file that cannot hold its own C3D header and parameter section.

    The header's first byte is the parameter section's first 512-byte block (1-based) and its
    second the C3D key 0x50; the parameter section's third byte is its number of blocks, which
    every writer sets (the data follow it). A file cut inside that section made ezc3d loop
    until the child's time limit (60 s): the sizes alone tell, in the single bytes the format
    keeps whatever the processor type."""
    if not path.is_file():
        return  # the reader says "file not found"
    size = path.stat().st_size
    with path.open("rb") as fh:
        head = fh.read(512)
        if len(head) < 512:
            raise ImportError_(f"{path}: not a C3D file ({size} bytes: shorter than a C3D header, "
                               "512 bytes)")
        if head[1] != 0x50:
            raise ImportError_(f"{path}: not a C3D file (its second byte is 0x{head[1]:02x}; a "
                               "C3D header has 0x50 there)")
        start = head[0]
        if start < 2:
            raise ImportError_(f"{path}: not a readable C3D file (its header puts the parameter "
                               f"section at block {start}; it follows the header, block 2 or later)")
        fh.seek((start - 1) * 512)
        section = fh.read(4)
    if len(section) < 4:
        raise ImportError_(f"{path}: not a readable C3D file (it ends at byte {size}, before its "
                           f"parameter section at byte {(start - 1) * 512}: the file is cut)")
    end = (start - 1 + section[2]) * 512
    if size < end:
        raise ImportError_(f"{path}: not a readable C3D file (its parameter section, {section[2]} "
                           f"blocks from byte {(start - 1) * 512}, ends at byte {end}, but the "
                           f"file ends at byte {size}: the file is cut)")


def _limit_memory(extra_bytes: int) -> None:
    """Cap this process's address space at what it maps now plus ``extra_bytes`` (Linux)."""
    import resource

    try:
        with open("/proc/self/statm") as fh:
            mapped = int(fh.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
        resource.setrlimit(resource.RLIMIT_AS, (mapped + int(extra_bytes), resource.RLIM_INFINITY))
    except (OSError, ValueError):  # pragma: no cover - no /proc: no cap
        pass


def _read_c3d_child(path: Path, send, memory_bytes: int) -> None:
    import faulthandler

    # a crash here is reported by the parent as an error naming the file: the fault handler
    # inherited from a parent that enabled it (pytest, python -X faulthandler) would only add
    # a "Fatal Python error" dump and the list of loaded modules to the terminal
    faulthandler.disable()
    _limit_memory(memory_bytes)
    try:
        outcome = (True, _read_c3d(path))
    except MemoryError:
        outcome = (False, ImportError_(f"{path}: not a readable C3D file (reading it needs more "
                                       "memory than its size can justify: the file is corrupted)"))
    except BaseException as e:  # noqa: BLE001 - handed to the parent, which raises it
        outcome = (False, e)
    send.send(outcome)
    send.close()


def _read_c3d(path: Path) -> MarkerData:
    import ezc3d

    where = str(path)
    if not path.is_file():
        raise ImportError_(f"{where}: file not found")
    try:
        c = ezc3d.c3d(str(path), extract_forceplat_data=False)
    except Exception as e:  # ezc3d raises RuntimeError/IOError with C++ messages
        raise ImportError_(f"{where}: not a readable C3D file ({e})") from None
    params = c["parameters"]
    if "POINT" not in params:
        raise ImportError_(f"{where}: no POINT parameter group (not a C3D of marker data)")
    point = params["POINT"]
    notes: list[str] = []
    labels = _labels(point, f"{where} POINT", notes)
    pts = np.asarray(c["data"]["points"], float)  # (4, M, F)
    if len(labels) != pts.shape[1]:
        raise ImportError_(f"{where}: POINT:LABELS has {len(labels)} labels for {pts.shape[1]} points")
    model = set()
    for g in MODEL_OUTPUT_GROUPS:
        if g in point:
            model |= {_text(v, f"{where} POINT:{g}", notes) for v in np.atleast_1d(point[g]["value"])}
    keep = [i for i, lab in enumerate(labels) if lab not in model]
    if len(keep) < len(labels):
        notes.append(f"{where}: {len(labels) - len(keep)} POINT entries are model outputs "
                     f"({', '.join(g for g in MODEL_OUTPUT_GROUPS if g in point)}) and were left out")
    units = np.atleast_1d(point.get("UNITS", {}).get("value", ["mm"]))
    scale = unit_scale(_text(units[0], f"{where} POINT:UNITS", notes) if len(units) else "mm",
                       f"{where} POINT:UNITS")
    if scale != 1.0:
        notes.append(f"{where}: coordinates converted from {units[0]} to mm")
    res = np.asarray(c["data"]["meta_points"]["residuals"], float)[0]  # (M, F)
    X = pts[:3].transpose(2, 1, 0)[:, keep] * scale
    gap = (res.T[:, keep] < 0) | ~np.all(np.isfinite(X), axis=-1)
    X[gap] = np.nan
    names = unique_names([labels[i] for i in keep], where, notes)
    fps = _first_number(point, "RATE", f"{where} POINT")
    if fps <= 0:
        raise ImportError_(f"{where} POINT:RATE: expected a positive frame rate, got {fps:g}")
    first = 1
    if "TRIAL" in params and "ACTUAL_START_FIELD" in params["TRIAL"]:
        first = int(_first_number(params["TRIAL"], "ACTUAL_START_FIELD", f"{where} TRIAL"))
    analogs = {}
    an = np.asarray(c["data"]["analogs"], float)
    if an.size and "ANALOG" in params:
        alabels = unique_names(_labels(params["ANALOG"], f"{where} ANALOG", notes), f"{where} ANALOG",
                               notes)
        rate = _first_number(params["ANALOG"], "RATE", f"{where} ANALOG")
        aunits = list(np.atleast_1d(params["ANALOG"].get("UNITS", {}).get("value", [])))
        for k, lab in enumerate(alabels[: an.shape[1]]):
            unit = _text(aunits[k], f"{where} ANALOG:UNITS", notes) if k < len(aunits) else ""
            analogs[lab] = (an[0, k], rate, unit)
    return MarkerData(names, X, fps, first, analogs, notes, where)


def write_c3d(path: str | os.PathLike, data: MarkerData, commands: dict | None = None) -> Path:
    """Write markers (and DU commands, label -> (n_frames,) values) to a C3D file atomically."""
    import ezc3d

    n_frames, M, _ = data.X.shape
    if n_frames > MAX_FRAMES:
        raise ValueError(f"{path}: {n_frames} frames; ezc3d writes more than {MAX_FRAMES} frames "
                         "wrongly: export the take in parts")
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [float(data.fps)]
    c["parameters"]["POINT"]["LABELS"]["value"] = list(data.names)
    c.add_parameter("POINT", "UNITS", ["mm"])
    pts = np.ones((4, M, n_frames))
    pts[:3] = data.X.transpose(2, 1, 0)
    gap = ~np.all(np.isfinite(data.X), axis=-1).T  # (M, F)
    pts[:3, gap] = 0.0
    c["data"]["points"] = pts
    residuals = np.where(gap, -1.0, 0.0)[None]
    c["data"]["meta_points"]["residuals"] = residuals
    c["data"]["meta_points"]["camera_masks"] = np.zeros((7, M, n_frames), dtype=bool)
    if commands:
        labels = list(commands)
        c["parameters"]["ANALOG"]["RATE"]["value"] = [float(data.fps)]
        c["parameters"]["ANALOG"]["LABELS"]["value"] = labels
        c["parameters"]["ANALOG"]["UNITS"]["value"] = ["command"] * len(labels)
        c["parameters"]["ANALOG"]["SCALE"]["value"] = [1.0] * len(labels)
        c["parameters"]["ANALOG"]["OFFSET"]["value"] = [0] * len(labels)
        c["parameters"]["ANALOG"]["GEN_SCALE"]["value"] = [1.0]
        c["data"]["analogs"] = np.stack([np.asarray(commands[k], float) for k in labels])[None]
    with atomic_path(path) as tmp:
        c.write(str(tmp.with_suffix(".c3d")))
        os.replace(tmp.with_suffix(".c3d"), tmp)
    return Path(path)
