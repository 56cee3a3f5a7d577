"""The refinement loop of ``mocap design --method model`` as a lab runs it: what a design was
made from (its record, ``X.design.json`` beside the command file ``X.csv``), the identities
that record compares (the source session's, the face model's, files'), the played take read
from the file the lab recorded (C3D, Motive CSV, QTM TSV, or a take file of the session format),
and the checks that refuse a refinement whose inputs do not belong together.

A record holds: the plan (its name, or the plan file and its SHA-256), the DUs, the timing
(s), the tracked markers, the model's identity (:func:`model_identity`) and effects, the source
session's identity (:func:`session_identity`), the iteration (0: a first design; k + 1: refined
from a play of iteration k), the SHA-256 of the command file and of the reference written with
it, and the tracking RMS the design expects of its play (the model's own, and the one calibrated
on the previous play, :func:`mocap.analysis.design.refinement.calibrated_prediction`).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from mocap.analysis.model.face_model import FaceModel

DESIGN_FILE_FORMAT = "facemocap design 1"
CHUNK = 1 << 20  # bytes of a session file's start and end hashed into the session's identity
TAKE_SUFFIXES = (".c3d", ".csv", ".tsv", ".parquet")


# ----------------------------------------------------------------------------------------------
# identities


def file_sha256(path) -> str:
    """SHA-256 (hex) of a file's bytes."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _session_dir(source) -> Path:
    """The session folder of ``source`` (a session, or a 'mocap run' output: its summary.json's
    session.dir)."""
    p = Path(source)
    if (p / "session.toml").is_file():
        return p
    summary = p / "summary.json"
    if summary.is_file():
        sdir = json.loads(summary.read_text()).get("session", {}).get("dir", "")
        if sdir and (Path(sdir) / "session.toml").is_file():
            return Path(sdir)
    return p


def session_identity(source) -> str:
    """A session's identity (hex): SHA-256 over its manifest, its marker template and every take
    and command file the manifest lists: each one's path in the session, size, and first and
    last MiB. Two recordings of the same lab set-up differ in their takes, so they differ here;
    a session copied elsewhere keeps its identity, and files the manifest does not list do not
    count. ``source``: a session or a 'mocap run' output."""
    from mocap.core.session import MANIFEST, MARKERS_FILE, load_session

    root = _session_dir(source).resolve()
    files = {root / MANIFEST, root / MARKERS_FILE}
    for t in load_session(root).takes:
        files.update(f for f in (t.file, t.commands) if f is not None)
    h = hashlib.sha256()
    for f in sorted(p for p in files if p.is_file()):
        try:
            rel = f.resolve().relative_to(root).as_posix()
        except ValueError:
            rel = f.name
        size = f.stat().st_size
        h.update(f"{rel}\0{size}\0".encode())
        with open(f, "rb") as fh:
            h.update(fh.read(CHUNK))
            if size > 2 * CHUNK:
                fh.seek(size - CHUNK)
                h.update(fh.read(CHUNK))
    return h.hexdigest()


def model_identity(model: FaceModel) -> str:
    """A face model's identity (hex): SHA-256 over its frame rate, names, DU ids, effects and
    parameters, and every array that predicts (a model saved and read back keeps it)."""
    h = hashlib.sha256()
    h.update(repr((float(model.fps), tuple(model.marker_names), tuple(int(d) for d in model.du_ids),
                   tuple(model.effect_names),
                   sorted((k, round(float(v), 12)) for k, v in model.parameters().items()))
                  ).encode())
    for name in ("rest_mm", "active", "alpha", "beta", "r", "D", "B", "density", "branch", "C",
                 "C2"):
        a = getattr(model, name, None)
        if a is not None:
            h.update(name.encode())
            h.update(np.ascontiguousarray(np.asarray(a, float)).tobytes())
    return h.hexdigest()


# ----------------------------------------------------------------------------------------------
# the design record


@dataclass(frozen=True)
class DesignRecord:
    """What a design was made from (module docstring). Times in s; RMS in the evaluation's units
    (normalised displacement); ``expected_rms`` None on a first design (nothing measured yet)."""

    plan: str
    plan_sha256: str | None
    dus: tuple[int, ...]
    timing: dict
    markers: tuple[str, ...]
    model_sha256: str
    model_effects: tuple[str, ...]
    source: str
    source_sha256: str
    iteration: int
    commands_sha256: str
    reference_sha256: str
    predicted_rms: float
    expected_rms: float | None = None
    measured_rms: float | None = None  # the play this design was refined from (None: first)


def record_path(commands_path) -> Path:
    """Where a design's record is written beside its command file (``X.csv`` -> ``X.design.json``)."""
    p = Path(commands_path)
    return p.with_name(p.stem + ".design.json")


def write_record(path, record: DesignRecord) -> Path:
    """Write ``record`` as JSON (atomically)."""
    from mocap.core.atomic import write_text

    doc = {"format": DESIGN_FILE_FORMAT, **asdict(record)}
    write_text(path, json.dumps(doc, indent=1) + "\n")
    return Path(path)


def read_record(path) -> DesignRecord:
    """The record :func:`write_record` wrote; ValueError naming the file and the key."""
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not a readable design record ({e})") from None
    if not isinstance(doc, dict) or doc.get("format") != DESIGN_FILE_FORMAT:
        raise ValueError(f"{path}: expected a design record ({DESIGN_FILE_FORMAT!r}) written by "
                         "'mocap design --method model'")
    fields = DesignRecord.__dataclass_fields__
    missing = [k for k, f in fields.items() if k not in doc and f.default is not None]
    if missing:
        raise ValueError(f"{path}: key {missing[0]!r} is missing (a design record holds "
                         f"{', '.join(fields)})")
    vals = {k: doc.get(k) for k in fields}
    vals["dus"] = tuple(int(d) for d in vals["dus"])
    vals["markers"] = tuple(vals["markers"])
    vals["model_effects"] = tuple(vals["model_effects"])
    return DesignRecord(**vals)


def check_refinement(record: DesignRecord, where, *, plan: str, plan_sha256: str | None, dus,
                     timing: dict, model: FaceModel, source_sha256: str, reference_path,
                     commands_sha256: str) -> None:
    """Refuse a refinement whose inputs are not those the played design was made from.

    ``where``: the record's file (named in the message). Raises ValueError listing each
    mismatch (the plan, the DUs, the timing, the commands, the reference, the model, the source
    session) with what to pass instead.
    """
    bad = []
    if record.plan != plan or (plan_sha256 is not None and record.plan_sha256 != plan_sha256):
        bad.append(f"the plan: the played design was made for plan {record.plan}, --plan is "
                   f"{plan} (refine it with --plan {record.plan}, or design plan {plan} anew)")
    if tuple(record.dus) != tuple(int(d) for d in dus):
        bad.append(f"the DUs: the played design drives {list(record.dus)}, --dus is {list(dus)}")
    diff = [k for k in record.timing if not np.isclose(record.timing[k], timing.get(k, np.nan))]
    if diff:
        bad.append("the timing: " + ", ".join(f"{k} {record.timing[k]} (given {timing.get(k)})"
                                              for k in diff))
    if record.commands_sha256 != commands_sha256:
        bad.append("the commands: the played commands are not the command file this record "
                   "was written with (was the file edited, or is it another design's?)")
    if reference_path is not None and Path(reference_path).is_file() \
            and file_sha256(reference_path) != record.reference_sha256:
        other = _record_beside_reference(reference_path)
        whose = f" (it is the reference of a plan {other.plan} design)" if other else ""
        bad.append(f"the reference: {reference_path} is not the one the played design was made "
                   f"for{whose}; leave --reference out to use that design's own")
    if model_identity(model) != record.model_sha256:
        bad.append(f"the model: not the face model the played design was made with (effects "
                   f"{', '.join(record.model_effects) or 'none'}); pass that design's --model "
                   "FILE (--save-model writes one)")
    if source_sha256 != record.source_sha256:
        bad.append(f"the source session: the played design was made from {record.source}, "
                   "not this SOURCE; refine with that session")
    if bad:
        raise ValueError(f"--refine: the inputs do not match {where}: " + "; ".join(bad))


def _record_beside_reference(reference_path) -> DesignRecord | None:
    p = Path(reference_path)
    if not p.name.endswith(".reference.csv"):
        return None
    rec = p.with_name(p.name[: -len(".reference.csv")] + ".design.json")
    try:
        return read_record(rec) if rec.is_file() else None
    except ValueError:
        return None


def commands_beside_reference(reference_path) -> Path | None:
    """The command file a design wrote with the reference ``X.reference.csv`` (``X.csv``), if there."""
    p = Path(reference_path)
    if not p.name.endswith(".reference.csv"):
        return None
    c = p.with_name(p.name[: -len(".reference.csv")] + ".csv")
    return c if c.is_file() else None


def check_take(take, model: FaceModel, ref, markers_w, say) -> None:
    """Refuse a played take that cannot be a play of its commands on this design: its frame
    rate (the model's), its length (at least to the end of the plan's return ``ref.fall``), its
    markers (at least half of those with a weight in ``markers_w`` (M,)), and its motion (its
    markers' mean within :data:`mocap.analysis.design.refinement.MAX_TAKE_MISMATCH` of the
    model's prediction of its commands). ValueError naming the take; ``say`` gets notes."""
    from mocap.analysis.design.refinement import MAX_TAKE_MISMATCH, take_mismatch

    if abs(take.fps - model.fps) > 1e-6:
        raise ValueError(f"--refine: the take {take.name} is at {take.fps} fps, the model at "
                         f"{model.fps}")
    n = take.X.shape[0]
    need = ref.fall[1]
    if n / take.fps < need - 1e-9:
        raise ValueError(f"--refine: the take {take.name} is {n} frames ({n / take.fps:.2f} s at "
                         f"{take.fps:g} fps); the design's return ends at {need:.2f} s: the take "
                         "is too short for it (another design's take, or a recording stopped early?)")
    tracked = [m for m, w in zip(model.marker_names, markers_w) if w > 0]
    missing = sorted(set(tracked) - set(take.marker_names))
    if len(missing) * 2 > len(tracked):
        raise ValueError(f"--refine: the take {take.name} lacks {len(missing)} of the "
                         f"{len(tracked)} markers the design tracks ({', '.join(missing[:6])}"
                         f"{'...' if len(missing) > 6 else ''}): another face or labeling?")
    if missing:
        say(f"note: the take lacks {len(missing)} tracked markers ({', '.join(missing[:6])}); "
            "the others teach the refinement")
    off = take_mismatch(model, take.rows, take.X, take.marker_names, ref)
    if not off <= MAX_TAKE_MISMATCH:
        raise ValueError(f"--refine: the take {take.name} does not move as a play of its "
                         f"commands on plan {ref.label}: its markers' mean departs from the "
                         f"model's prediction of them by RMS {off:.3f} over the rise and return "
                         f"(a play departs by the model's error, under {MAX_TAKE_MISMATCH}); was "
                         "it recorded playing another command file?")


# ----------------------------------------------------------------------------------------------
# the played take, as the lab recorded it


def read_command_file(path, du_ids) -> pd.DataFrame:
    """A command file (time_s, du, command) checked by the session format's own reader; the DUs
    must be among ``du_ids``. SessionError naming the file and line."""
    from mocap.core.session_files import _read_commands, _Source

    p = Path(path)
    return _read_commands(_Source(p, str(p)), tuple(int(d) for d in du_ids))


def commands_sha256(rows: pd.DataFrame) -> str:
    """SHA-256 of command rows as values (time_s to 1 ns, du, command), whatever file held them."""
    r = rows.sort_values(["du", "time_s"], kind="stable")
    blob = np.column_stack([np.round(r["time_s"].to_numpy(float), 9), r["du"].to_numpy(float),
                            r["command"].to_numpy(float)])
    return hashlib.sha256(np.ascontiguousarray(blob).tobytes()).hexdigest()


def is_take_file(value) -> bool:
    """Whether ``--refine``'s value names a take file (an existing file with a take's suffix)
    rather than a take of a session."""
    p = Path(str(value))
    return p.suffix.lower() in TAKE_SUFFIXES and p.is_file()


def read_take_file(path, rows: pd.DataFrame, session_fps: float):
    """The played take in a file as the lab recorded it: a vendor's export ('mocap import'
    reads C3D, Motive CSV, QTM TSV) or a take file of the session format (frame, marker, x, y, z;
    CSV or Parquet; at the session's frame rate ``session_fps``), played with ``rows``. Frame 0
    is the commands' time 0. Returns a :class:`mocap.workflows.design.PlayedTake`; ImportError_
    or SessionError naming the file and place."""
    from mocap.workflows.design import PlayedTake

    p = Path(path)
    if p.suffix.lower() == ".parquet" or (p.suffix.lower() == ".csv" and _session_take_csv(p)):
        from mocap.core.session_files import _read_take_3d, _Source
        from mocap.reconstruction.labeled_input import dense_from_3d, marker_names_3d

        df = _read_take_3d(_Source(p, str(p)))
        names = marker_names_3d([df], None)
        return PlayedTake(p.name, rows, dense_from_3d(df, names).X, tuple(names),
                          float(session_fps))
    from mocap.interop.session_io import _analog_commands, read_any

    data = read_any(p)
    _check_analog_commands(p, _analog_commands(data), rows, float(data.fps))
    return PlayedTake(p.name, rows, data.X, tuple(data.names), float(data.fps))


def _check_analog_commands(path, channels: dict, rows: pd.DataFrame, fps: float) -> None:
    """A take whose file records the commands (C3D analog channels ``DU<n>``, as 'mocap export'
    writes them) must record the played ones: ValueError naming the DU and the first frame that
    differs."""
    from mocap.core.schedules import sample_commands

    for du, values in sorted(channels.items()):
        if du not in set(int(d) for d in rows["du"]):
            continue
        played = sample_commands(rows, [du], np.arange(len(values)) / fps)[:, 0]
        bad = np.flatnonzero(np.abs(np.asarray(values, float) - played) > 0.5)
        if bad.size:
            f = int(bad[0])
            raise ValueError(f"--refine: {path} records DU {du}'s command {values[f]:g} at frame "
                             f"{f} ({f / fps:.3f} s) where the played commands have "
                             f"{played[f]:g}: the take played another command file than "
                             "--played-commands")


def _session_take_csv(path: Path) -> bool:
    with open(path, encoding="utf-8", errors="replace") as f:
        head = f.readline().strip().lstrip("\ufeff")
    return [c.strip() for c in head.split(",")][:2] == ["frame", "marker"]
