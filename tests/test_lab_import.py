"""A lab's files to a runnable session in one command (issue 49, items 1 and 2).

The lab's layout is the paper's: per DU, trials of the trapezoidal command schedule, one motion
file per take (C3D written here with ezc3d directly, or Motive CSV text typed here) and one
command log per take, named as a lab names them (``smile_DU1_trial2.c3d``,
``smile_DU1_trial2_commands.csv``), plus a rest take. The truth each import is held to is the
run of the same numbers given as a session written by hand in the documented format.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from mocap.cli import main
from mocap.interop.take_table import compile_pattern, kind_from_name

FPS = 100.0
DUS = {1: "brow raiser", 2: "lip corner puller"}
TRIALS = (1, 2, 3)
MARKERS = [f"M{i:02d}" for i in range(1, 11)]
RUN_FLAGS = ["--jobs", "1", "--no-recording", "--quiet", "--bootstrap-samples", "20"]


# --- the lab's numbers (numpy-made motion) -----------------------------------------------------

def _schedule(du: int) -> pd.DataFrame:
    """The paper's trapezoid typed out: 100 steps of 50 ms, 255 s / 20 rounded half up."""
    levels = [int(np.floor(255 * s / 20 + 0.5)) for s in range(21)] + [255] * 59 \
        + [int(np.floor(255 * (100 - s) / 20 + 0.5)) for s in range(81, 101)]
    return pd.DataFrame({"time_s": [round(0.05 * k, 9) for k in range(len(levels))],
                         "du": du, "command": levels})


def _motion(du: int, trial: int, rows: pd.DataFrame) -> np.ndarray:
    """(n_frames, n_markers, 3) mm: rest positions plus a lagged, curved response to the DU's
    command along each marker's own direction, plus 0.02 mm noise; a 3-frame gap on M03."""
    rng = np.random.default_rng(7)
    rest = np.c_[rng.uniform(-40, 40, (len(MARKERS), 2)), rng.uniform(80, 95, len(MARKERS))]
    direction = rng.normal(size=(len(DUS), len(MARKERS), 3))
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    gain = rng.uniform(0.5, 4.0, (len(DUS), len(MARKERS)))
    n = 560
    t = np.arange(n) / FPS
    idx = np.searchsorted(rows["time_s"].to_numpy() - 1e-9, t, side="right") - 1
    c = np.where(idx >= 0, rows["command"].to_numpy()[np.maximum(idx, 0)], 0) / 255.0
    lagged = np.zeros(n)
    for k in range(1, n):  # first-order lag: a hysteresis loop in command space
        lagged[k] = lagged[k - 1] + (c[k] - lagged[k - 1]) * 0.15
    shape = lagged ** 1.3
    noise = np.random.default_rng(100 * du + trial).normal(0.0, 0.02, (n, len(MARKERS), 3))
    X = rest + shape[:, None, None] * gain[du - 1][None, :, None] * direction[du - 1][None] + noise
    X[200:203, 2] = np.nan
    return X


def _rest() -> np.ndarray:
    rng = np.random.default_rng(7)
    rest = np.c_[rng.uniform(-40, 40, (len(MARKERS), 2)), rng.uniform(80, 95, len(MARKERS))]
    return rest + np.random.default_rng(3).normal(0.0, 0.02, (300, len(MARKERS), 3))


@pytest.fixture(scope="module")
def lab_numbers():
    """Per lab stem: (X float64, its float32 rounding as C3D holds it, command rows or None)."""
    out = {"smile_rest": (_rest(), None)}
    for du in DUS:
        for trial in TRIALS:
            rows = _schedule(du)
            out[f"smile_DU{du}_trial{trial}"] = (_motion(du, trial, rows), rows)
    return out


# --- the lab's files -----------------------------------------------------------------------------

def write_c3d_ezc3d(path: Path, X: np.ndarray) -> None:
    """A C3D file as a vendor writes it, with ezc3d directly: float32 points in mm, a gap as
    zeros with residual -1."""
    import ezc3d

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [FPS]
    c["parameters"]["POINT"]["LABELS"]["value"] = MARKERS
    c.add_parameter("POINT", "UNITS", ["mm"])
    pts = np.ones((4, len(MARKERS), X.shape[0]))
    gap = ~np.isfinite(X[..., 0]).T
    pts[:3] = np.nan_to_num(X.transpose(2, 1, 0), nan=0.0)
    c["data"]["points"] = pts
    c["data"]["meta_points"]["residuals"] = np.where(gap, -1.0, 0.0)[None]
    c["data"]["meta_points"]["camera_masks"] = np.zeros((7, len(MARKERS), X.shape[0]), dtype=bool)
    c.write(str(path))


def _num(v: float) -> str:
    return "" if not np.isfinite(v) else repr(float(v))


def write_motive_csv(path: Path, X: np.ndarray, take: str) -> None:
    """An OptiTrack Motive 'CSV export' (format 1.23), millimetres, one rigid body besides the
    markers, typed here line by line."""
    n = X.shape[0]
    head = (f"Format Version,1.23,Take Name,{take},Take Notes,,Capture Frame Rate,{FPS:.6f},"
            f"Export Frame Rate,{FPS:.6f},Capture Start Time,2026-11-22 10.00.00.000 AM,"
            f"Total Frames in Take,{n},Total Exported Frames,{n},Rotation Type,Quaternion,"
            "Length Units,Millimeters,Coordinate Space,Global")
    rb = ["Rigid Body"] * 7
    lines = [head, "",
             ",," + ",".join(rb + ["Marker"] * 3 * len(MARKERS)),
             ",," + ",".join(["Head"] * 7 + [f"Face:{m}" for m in MARKERS for _ in range(3)]),
             ",," + ",".join(["1"] * 7 + [f"A{i}" for i in range(len(MARKERS)) for _ in range(3)]),
             ",," + ",".join(["Rotation"] * 4 + ["Position"] * 3 + ["Position"] * 3 * len(MARKERS)),
             "Frame,Time (Seconds)," + ",".join(list("XYZW") + list("XYZ") + list("XYZ") * len(MARKERS))]
    for f in range(n):
        cells = [str(f), f"{f / FPS:.6f}", "0", "0", "0", "1", "1.0", "2.0", "3.0"]
        cells += [_num(v) for v in X[f].ravel()]
        lines.append(",".join(cells))
    path.write_text("\n".join(lines) + "\n")


def _take_name(stem: str) -> str:
    return "rest" if stem == "smile_rest" else stem.replace("smile_DU", "du").replace("_trial", "_t")


def write_hand_session(root: Path, numbers: dict, names=_take_name) -> Path:
    """The same numbers as a labeled session written by hand: session.toml typed out, one
    frame,marker,x,y,z CSV per take and the command logs as they are."""
    (root / "takes").mkdir(parents=True)
    toml = ['schema = "mocap-session/1"', 'name = "smile"', f"fps = {FPS}", ""]
    for du, name in DUS.items():
        toml += ["[[dus]]", f"id = {du}", f'name = "{name}"', "feedback = false", ""]
    for stem, (X, rows) in numbers.items():
        name = names(stem)
        n = X.shape[0]
        pd.DataFrame({"frame": np.repeat(np.arange(n), len(MARKERS)),
                      "marker": MARKERS * n, "x": X[..., 0].ravel(), "y": X[..., 1].ravel(),
                      "z": X[..., 2].ravel()}).to_csv(root / "takes" / f"{name}.csv", index=False)
        toml += ["[[takes]]", f'name = "{name}"', f'file = "takes/{name}.csv"']
        if rows is None:
            toml += ['kind = "rest"', ""]
            continue
        rows.to_csv(root / "takes" / f"{name}_commands.csv", index=False)
        du, trial = (int(v) for v in _take_name(stem)[2:].split("_t"))
        toml += ['kind = "response"', f'commands = "takes/{name}_commands.csv"', f"du = {du}",
                 f"trial = {trial}", ""]
    (root / "session.toml").write_text("\n".join(toml))
    return root


def _lab(tmp: Path, numbers: dict, fmt: str, commands_in: str = "commands") -> Path:
    """The lab's folder: motion files, and command logs in ``lab/<commands_in>``."""
    lab = tmp / "lab"
    (lab / commands_in).mkdir(parents=True, exist_ok=True)
    for stem, (X, rows) in numbers.items():
        if fmt == "c3d":
            write_c3d_ezc3d(lab / f"{stem}.c3d", X)
        else:
            write_motive_csv(lab / f"{stem}.csv", X, stem)
        if rows is not None:
            rows.to_csv(lab / commands_in / f"{stem}_commands.csv", index=False)
    (lab / "dus.csv").write_text("du,name\n" + "".join(f"{d},{n}\n" for d, n in DUS.items()))
    return lab


def _as_c3d_holds(numbers: dict) -> dict:
    return {k: (X.astype(np.float32).astype(np.float64), rows) for k, (X, rows) in numbers.items()}


def _run(session: Path, out: Path) -> pd.DataFrame:
    assert main(["validate", str(session)]) == 0
    assert main(["run", str(session), "--out", str(out), *RUN_FLAGS]) == 0
    return pd.read_csv(out / "properties.csv")


@pytest.fixture(scope="module")
def hand_run_c3d(lab_numbers, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("hand_c3d")
    return _run(write_hand_session(tmp / "session", _as_c3d_holds(lab_numbers)), tmp / "out")


def _same_properties(got: pd.DataFrame, want: pd.DataFrame) -> None:
    assert len(want) == len(DUS) and want["sensitivity"].notna().all()
    pd.testing.assert_frame_equal(got, want, check_exact=False, rtol=1e-9, atol=0)


def _table(lab: Path, ext: str, commands_column: bool) -> Path:
    lines = ["file,name,kind,du,trial" + (",commands" if commands_column else "")]
    lines.append(f"smile_rest.{ext},rest,rest,," + ("," if commands_column else ""))
    for du in DUS:
        for t in TRIALS:
            stem = f"smile_DU{du}_trial{t}"
            lines.append(f"{stem}.{ext},du{du}_t{t},response,{du},{t}"
                         + (f",commands/{stem}_commands.csv" if commands_column else ""))
    (lab / "takes.csv").write_text("\n".join(lines) + "\n")
    return lab / "takes.csv"


# --- the import, against the hand-written session -------------------------------------------------

def test_c3d_takes_and_a_take_table_run_as_the_hand_written_session(lab_numbers, hand_run_c3d,
                                                                    tmp_path, capsys):
    lab = _lab(tmp_path, lab_numbers, "c3d")
    table = _table(lab, "c3d", commands_column=False)
    files = sorted(str(p) for p in lab.glob("*.c3d"))
    assert main(["import", *files, "--takes", str(table), "--commands", str(lab / "commands"),
                 "--dus", str(lab / "dus.csv"), "--out", str(tmp_path / "S")]) == 0
    printed = capsys.readouterr().out
    assert "ready: mocap run" in printed and "to complete" not in printed
    report = json.loads((tmp_path / "S" / "import_report.json").read_text())
    # the command logs were matched by name: a guess, listed and printed
    assert sum("matched by name" in g for g in report["guessed"]) == len(DUS) * len(TRIALS)
    assert "smile_DU2_trial3_commands.csv (matched by name)" in printed
    assert report["kinds"] == {"rest": 1, "response": 6}
    _same_properties(_run(tmp_path / "S", tmp_path / "out"), hand_run_c3d)
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert not any("nothing to analyse" in w for w in summary["warnings"])


def test_motive_csv_takes_with_commands_in_the_table(lab_numbers, tmp_path):
    lab = _lab(tmp_path, lab_numbers, "motive")
    table = _table(lab, "csv", commands_column=True)
    # the motion files by glob; the table names their command logs
    files = sorted(str(p) for p in lab.glob("smile_*.csv"))
    assert main(["import", *files, "--takes", str(table), "--dus", str(lab / "dus.csv"),
                 "--out", str(tmp_path / "S")]) == 0
    want = _run(write_hand_session(tmp_path / "hand", lab_numbers), tmp_path / "hand_out")
    _same_properties(_run(tmp_path / "S", tmp_path / "out"), want)


def test_the_pattern_route_without_a_table(lab_numbers, hand_run_c3d, tmp_path, capsys):
    lab = _lab(tmp_path, lab_numbers, "c3d", commands_in=".")  # logs beside the C3D files
    files = sorted(str(p) for p in lab.glob("smile_*"))  # C3D files and command logs together
    assert main(["import", *files, "--pattern", "smile_DU{du}_trial{trial}",
                 "--dus", str(lab / "dus.csv"), "--out", str(tmp_path / "S")]) == 0
    printed = capsys.readouterr().out
    assert "kind 'rest', from its file name 'smile_rest.c3d'" in printed
    _same_properties(_run(tmp_path / "S", tmp_path / "out"), hand_run_c3d)
    assert main(["validate", str(tmp_path / "S")]) == 0


def test_dus_left_numbered_are_a_listed_guess(lab_numbers, tmp_path, capsys):
    small = {k: v for k, v in lab_numbers.items() if k in ("smile_rest", "smile_DU1_trial1")}
    lab = _lab(tmp_path, small, "c3d")
    assert main(["import", *map(str, sorted(lab.glob("*.c3d"))), "--pattern", "*DU{du}_trial{trial}",
                 "--commands", str(lab / "commands"), "--out", str(tmp_path / "S")]) == 0
    assert "DUs [1]: no DU table (--dus); named 'DU <n>'" in capsys.readouterr().out
    assert 'name = "DU 1"' in (tmp_path / "S" / "session.toml").read_text()


# --- clear errors ---------------------------------------------------------------------------------

@pytest.fixture
def small_lab(lab_numbers, tmp_path):
    keep = ("smile_rest", "smile_DU1_trial1", "smile_DU2_trial1")
    return _lab(tmp_path, {k: lab_numbers[k] for k in keep}, "c3d")


def _import_error(capsys, *argv) -> str:
    assert main(["import", *map(str, argv)]) == 1
    return capsys.readouterr().err


def test_errors_name_the_file_or_the_row(small_lab, tmp_path, capsys):
    lab = small_lab
    c3ds = sorted(lab.glob("*.c3d"))
    out = tmp_path / "S"
    # a file no pattern accounts for
    (lab / "calibration_check.c3d").write_bytes((lab / "smile_rest.c3d").read_bytes())
    err = _import_error(capsys, *c3ds, lab / "calibration_check.c3d", "--pattern",
                        "smile_DU{du}_trial{trial}", "--out", out)
    assert "calibration_check.c3d: its name 'calibration_check' matches no --pattern" in err
    # a file no table row names
    table = lab / "t1.csv"
    table.write_text("file,kind\nsmile_rest.c3d,rest\nsmile_DU1_trial1.c3d,response\n")
    err = _import_error(capsys, *c3ds, "--takes", table, "--out", out)
    assert "smile_DU2_trial1.c3d: no row of" in err and "t1.csv" in err
    # a table row naming a missing file
    table.write_text("file,kind\nsmile_rest.c3d,rest\nsmile_DU9_trial1.c3d,motion\n")
    err = _import_error(capsys, lab / "smile_rest.c3d", "--takes", table, "--out", out)
    assert "t1.csv line 3: file 'smile_DU9_trial1.c3d' is not among the files given" in err
    # a duplicate take name (a blank line and a column of the lab's own counted and ignored)
    table.write_text("file,name,notes\nsmile_rest.c3d,a,x\n\nsmile_DU1_trial1.c3d,b,\n"
                     "smile_DU2_trial1.c3d,A,y\n")
    err = _import_error(capsys, *c3ds, "--takes", table, "--out", out)
    assert "t1.csv line 5: take name 'A' already used on line 2" in err
    # an unknown kind
    table.write_text("file,kind\nsmile_rest.c3d,resting\n")
    err = _import_error(capsys, lab / "smile_rest.c3d", "--takes", table, "--out", out)
    assert "t1.csv line 2: kind 'resting'; expected one of" in err
    # a response take whose DU its command log does not drive: a DU without commands
    table.write_text("file,kind,du,trial,commands\nsmile_rest.c3d,rest,,,\n"
                     "smile_DU1_trial1.c3d,response,2,1,commands/smile_DU1_trial1_commands.csv\n")
    err = _import_error(capsys, lab / "smile_rest.c3d", lab / "smile_DU1_trial1.c3d",
                        "--takes", table, "--dus", lab / "dus.csv", "--out", out)
    assert "t1.csv line 3: response take 'smile_DU1_trial1' drives DU 2 but its command log " \
           "has no rows for DU 2" in err
    # a response take without any command log
    err = _import_error(capsys, *c3ds, "--pattern", "smile_DU{du}_trial{trial}", "--out", out)
    assert "smile_DU1_trial1.c3d: response take 'smile_DU1_trial1' has no command log" in err
    assert not out.exists()  # nothing written on any error


def test_single_file_commands_still_work(small_lab, tmp_path):
    f = small_lab / "smile_DU1_trial1.c3d"
    log = small_lab / "commands" / "smile_DU1_trial1_commands.csv"
    assert main(["import", str(f), "--commands", str(log), "--out", str(tmp_path / "S")]) == 0
    text = (tmp_path / "S" / "session.toml").read_text()
    assert 'kind = "motion"' in text and 'commands = "takes/smile_DU1_trial1_commands.csv"' in text
    assert (pd.read_csv(tmp_path / "S" / "takes" / "smile_DU1_trial1_commands.csv")
            .equals(pd.read_csv(log)))


# --- names and patterns -----------------------------------------------------------------------------

@pytest.mark.parametrize("stem,kind", [("smile_rest", "rest"), ("Rest01", "rest"),
                                       ("wand-2", "wand"), ("GROUND", "ground"),
                                       ("forest_walk", None), ("restart", None), ("du1_t1", None)])
def test_kind_from_name(stem, kind):
    assert kind_from_name(stem) == kind


def test_a_name_with_two_kinds_is_an_error_naming_the_file(tmp_path):
    from mocap.interop.marker_data import ImportError_
    from mocap.interop.take_table import plan_takes

    f = tmp_path / "wand_rest.c3d"
    f.write_bytes(b"")
    with pytest.raises(ImportError_, match=r"wand_rest.c3d: the name holds rest and wand"):
        plan_takes([f])


def test_patterns():
    rx = compile_pattern("du{du}_t{trial}")
    assert rx.fullmatch("DU04_t3").groupdict() == {"du": "04", "trial": "3"}
    assert rx.fullmatch("du4_t3_extra") is None
    assert compile_pattern("*_DU{du}_trial{trial}").fullmatch("smile_DU1_trial2")
    assert compile_pattern("smile_{plan}").fullmatch("smile_planB")["plan"] == "planB"
    from mocap.interop.marker_data import ImportError_

    for bad, why in (("du{dof}", "unknown field {dof}"), ("du{du}_{du}", "{du} appears twice"),
                     ("smile", "holds no field")):
        with pytest.raises(ImportError_, match=re.escape(why)):
            compile_pattern(bad)


# --- a session with nothing to analyse says so --------------------------------------------------------

def test_an_unanalysable_session_warns_on_stderr_in_the_summary_and_the_audit(lab_numbers, tmp_path,
                                                                              capsys):
    small = {k: lab_numbers[k] for k in ("smile_rest", "smile_DU1_trial1", "smile_DU2_trial1")}
    lab = _lab(tmp_path, small, "c3d")
    shutil.rmtree(lab / "commands")
    # the unedited import: motion takes, no commands
    assert main(["import", *map(str, sorted(lab.glob("*.c3d"))), "--out", str(tmp_path / "S")]) == 0
    assert "set each take's kind: 2 take(s) assumed 'motion'" in capsys.readouterr().out
    assert main(["run", str(tmp_path / "S"), "--out", str(tmp_path / "out"), *RUN_FLAGS]) == 0
    cap = capsys.readouterr()
    warning = [ln for ln in cap.err.splitlines() if ln.startswith("warning: nothing to analyse")]
    assert len(warning) == 1
    assert "no response takes, no command files, no DU" in warning[0]
    assert "audit verdict: warn (nothing to analyse)" in cap.out
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert any(w.startswith("nothing to analyse: no response takes") for w in summary["warnings"])
    assert summary["audit"]["verdict"] == "warn"
    audit = json.loads((tmp_path / "out" / "audit.json").read_text())
    assert audit["nothing_to_analyse"] and audit["verdict"] == "warn"
    assert {"kind": "session", "item": "analyses"}.items() <= audit["flagged"][-1].items()
    md = (tmp_path / "out" / "audit.md").read_text()
    assert "Overall verdict: **warn** (nothing to analyse: no response takes" in md
    assert not (tmp_path / "out" / "properties.csv").exists()
    # 'mocap audit' says the same
    assert main(["audit", str(tmp_path / "S"), "--out", str(tmp_path / "audit")]) == 0
    assert "warning: nothing to analyse" in capsys.readouterr().err


def test_a_table_alone_names_the_files(small_lab, tmp_path):
    table = small_lab / "takes.csv"
    table.write_text("file,name,du,trial,commands_offset_s\nsmile_rest.c3d,rest,,,\n"
                     "smile_DU1_trial1.c3d,du1_t1,1,1,0.25\nsmile_DU2_trial1.c3d,du2_t1,2,1,\n")
    assert main(["import", "--takes", str(table), "--commands", str(small_lab / "commands"),
                 "--out", str(tmp_path / "S")]) == 0
    report = json.loads((tmp_path / "S" / "import_report.json").read_text())
    assert [(t["name"], t["kind"], t.get("du")) for t in report["takes"]] == [
        ("rest", "rest", None), ("du1_t1", "response", 1), ("du2_t1", "response", 2)]
    # kinds the table left empty are guesses, listed with the line that left them
    assert any("takes.csv line 3: take 'du1_t1' kind 'response' (it names a DU)" in g
               for g in report["guessed"])
    # the offset is the manifest's, copied for the take that has one
    manifest = (tmp_path / "S" / "session.toml").read_text()
    assert manifest.count("commands_offset_s = 0.25") == 1
    assert main(["validate", str(tmp_path / "S")]) == 0
    table.write_text("file,commands_offset_s\nsmile_rest.c3d,soon\n")
    assert main(["import", "--takes", str(table), "--out", str(tmp_path / "S2")]) == 1


@pytest.mark.parametrize("log", ["smile_DU1_trial1_commands.csv", "SMILE_DU1_TRIAL1-cmd.csv",
                                 "smile_DU1_trial1.csv", "du1_t1 log.csv"])
def test_command_logs_are_matched_in_the_spellings_labs_use(tmp_path, log):
    from mocap.interop.take_table import plan_takes

    (tmp_path / "smile_DU1_trial1.c3d").write_bytes(b"")
    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / log).write_text("time_s,du,command\n0.0,1,0\n")
    (tmp_path / "logs" / "catalog.csv").write_text("time_s,du,command\n0.0,1,0\n")
    (tmp_path / "t.csv").write_text("file,name\nsmile_DU1_trial1.c3d,du1_t1\n")
    plan = plan_takes([tmp_path / "smile_DU1_trial1.c3d"], table=tmp_path / "t.csv",
                      commands_dir=tmp_path / "logs")
    assert plan.takes[0].commands == tmp_path / "logs" / log
    assert any("catalog.csv" in n for n in plan.notes)  # matches no take: noted, not imported


def write_qtm_tsv(path: Path, X: np.ndarray) -> None:
    """A Qualisys QTM 3D TSV export (file version 2.0.0), gaps as empty cells, typed here."""
    n = X.shape[0]
    head = [("FILE_VERSION", "2.0.0"), ("NO_OF_FRAMES", str(n)), ("NO_OF_CAMERAS", "8"),
            ("NO_OF_MARKERS", str(len(MARKERS))), ("FREQUENCY", f"{FPS:g}"), ("NO_OF_ANALOG", "0"),
            ("ANALOG_FREQUENCY", "0"), ("DESCRIPTION", "--"), ("TIME_STAMP", "2026-11-22, 10:00:00"),
            ("DATA_INCLUDED", "3D"), ("MARKER_NAMES", "\t".join(MARKERS)),
            ("TRAJECTORY_TYPES", "\t".join(["Measured"] * len(MARKERS)))]
    lines = [f"{k}\t{v}" for k, v in head]
    lines.append("Frame\tTime\t" + "\t".join(f"{m} {a}" for m in MARKERS for a in "XYZ") + "\t")
    for f in range(n):
        lines.append(f"{f + 1}\t{f / FPS:.3f}\t" + "\t".join(_num(v) for v in X[f].ravel()) + "\t")
    path.write_text("\n".join(lines) + "\n")


def test_qtm_tsv_takes_by_pattern_hold_the_numbers_as_written(lab_numbers, tmp_path):
    from mocap.core.session import load_session

    keep = {k: lab_numbers[k] for k in ("smile_rest", "smile_DU2_trial3")}
    lab = tmp_path / "lab"
    lab.mkdir()
    for stem, (X, rows) in keep.items():
        write_qtm_tsv(lab / f"{stem}.tsv", X)
        if rows is not None:
            rows.to_csv(lab / f"{stem}_commands.csv", index=False)
    assert main(["import", *map(str, sorted(lab.iterdir())), "--pattern", "smile_DU{du}_trial{trial}",
                 "--out", str(tmp_path / "S")]) == 0
    hand = load_session(write_hand_session(tmp_path / "hand", keep, names=lambda s: s))
    got = load_session(tmp_path / "S")
    assert [(t.name, t.kind, t.du, t.trial) for t in got.takes] == [
        ("smile_DU2_trial3", "response", 2, 3), ("smile_rest", "rest", None, None)]
    for name in ("smile_rest", "smile_DU2_trial3"):
        pd.testing.assert_frame_equal(got.read_take(name), hand.read_take(name))
    pd.testing.assert_frame_equal(got.read_commands("smile_DU2_trial3"),
                                  hand.read_commands("smile_DU2_trial3"))
