"""The Python API: typed, frozen results; a run without an output folder writes nothing;
``import mocap`` stays light; figures draw into a notebook's axes; settings from one dataclass."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import mocap
from conftest import make_session
from mocap.workflows.run.settings import RunSettings, describe, from_toml, settings_table, with_values

ROOT = Path(__file__).resolve().parents[1]


def snapshot(folder: Path) -> dict:
    """Every file under ``folder`` with its size and modification time."""
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*"))}


def out_dense(out: Path, take: str, names) -> np.ndarray:
    df = pd.read_parquet(out / "trajectories" / f"{take}.parquet")
    piv = df.pivot(index="frame", columns="marker", values=["x", "y", "z"])
    return np.stack([piv[k][list(names)].to_numpy() for k in "xyz"], axis=-1)


RUN_IN_A_CLEAN_PROCESS = r"""
import json, sys
import mocap
heavy = ("rerun", "matplotlib", "dask")
after_import = [m for m in heavy if m in sys.modules]
result = mocap.run(mocap.load_session(sys.argv[1]), jobs=1)
after_run = sorted({m.split(".")[0] for m in sys.modules} & set(heavy))
np_arrays = {k: v.tolist() for k, v in result.arrays.items() if k == "du04_t01"}
json.dump({"after_import": after_import, "after_run": after_run,
           "properties": result.properties.to_dict("list"),
           "markers": list(result.markers),
           "n_rows": len(result.trajectories),
           "takes": sorted(result.trajectories["take"].unique()),
           "du04_t01": np_arrays["du04_t01"],
           "audit": result.audit["verdict"], "out_dir": str(result.out_dir)}, sys.stdout)
"""


def test_run_without_out_dir_writes_nothing_and_imports_no_heavy_package(tiny_sim, tiny_run,
                                                                          tmp_path):
    cwd, tmp = tmp_path / "cwd", tmp_path / "tmp"
    cwd.mkdir()
    tmp.mkdir()
    session = tiny_sim / "session"
    before = snapshot(session)
    env = {"PATH": "/usr/bin:/bin", "TMPDIR": str(tmp), "HOME": str(tmp_path / "home"),
           "PYTHONPATH": str(ROOT / "tests")}
    proc = subprocess.run([sys.executable, "-c", RUN_IN_A_CLEAN_PROCESS, str(session)], cwd=cwd,
                          env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    r = json.loads(proc.stdout)
    # nothing written: not in the working folder, not in the temporary folder, not in the session
    assert list(cwd.iterdir()) == [] and list(tmp.iterdir()) == []
    assert not (tmp_path / "home").exists()
    assert snapshot(session) == before
    assert r["out_dir"] == "None"
    assert r["after_import"] == [] and r["after_run"] == []
    # the same results as `mocap run` into a folder
    props = pd.read_csv(tiny_run / "properties.csv")
    got = pd.DataFrame(r["properties"])
    assert list(got["du"]) == [4, 7]
    # equal to the optimiser's precision: this clean process runs BLAS with its default threads
    # (the test process and the CLI use one), which changes the order of the calibration's and
    # the fits' sums
    for col in ("sensitivity", "beta_fwd", "beta_bwd", "hysteresis", "dyssynchrony",
                "linearity_mean"):
        np.testing.assert_allclose(got[col].to_numpy(float), props[col].to_numpy(float),
                                   rtol=1e-7, err_msg=col)
    X = np.array(r["du04_t01"], dtype=float)
    np.testing.assert_allclose(X, out_dense(tiny_run, "du04_t01", r["markers"]), rtol=0,
                               atol=1e-9)  # mm; the calibration's sums differ in the last bits
    faces = sorted(p.stem for p in (tiny_run / "trajectories").glob("*.parquet"))
    assert r["takes"] == faces
    assert r["n_rows"] == sum(len(pd.read_parquet(p)) for p in (tiny_run / "trajectories").glob("*.parquet"))
    assert r["audit"] == json.loads((tiny_run / "audit.json").read_text())["verdict"]


def test_stage_by_stage_api_gives_the_run_results(tiny_sim, tiny_run):
    session = mocap.load_session(tiny_sim / "session")
    calibration = mocap.calibrate(session)
    assert calibration.quality["rating"] in ("excellent", "good")
    recon = mocap.reconstruct(session, calibration, jobs=1)
    names = list(recon.markers.names)
    for take, lab in recon.takes.items():
        np.testing.assert_array_equal(lab.X, out_dense(tiny_run, take, names))
    analysis = mocap.analyze(session, recon)
    props = pd.read_csv(tiny_run / "properties.csv")
    np.testing.assert_array_equal(analysis.properties["sensitivity"].to_numpy(float),
                                  props["sensitivity"].to_numpy(float))
    rej = pd.read_csv(tiny_run / "rejections.csv")
    assert list(analysis.rejections["marker"]) == list(rej["marker"])
    assert [m.take for m in analysis.motions] == ["smile_du04_07_planA"]
    # an analysis setting by name changes the analysis, not the reconstruction
    stricter = mocap.analyze(session, recon, min_displacement_mm=0.5)
    assert len(stricter.rejections) > len(analysis.rejections)


def test_results_are_frozen(tiny_sim):
    root = make_session(tiny_sim.parent / "lab3d", du_ids=(4,), n_trials=2, n_markers=12,
                        motion_plans=(), battery=False, labeled=True, seed=2)
    session = mocap.load_session(root / "session")
    result = mocap.run(session, bootstrap_samples=0)
    assert result.out_dir is None and result.calibration is None
    with pytest.raises(dataclasses.FrozenInstanceError):
        result.analysis = None
    for obj, attr in ((result.reconstruction, "takes"), (result.trials, "averages"),
                      (result.analysis, "motions"), (result.reconstruction.takes["rest"], "X"),
                      (result.reconstruction.takes["rest"].stats, "points"),
                      (result.reconstruction.capture, "frames"), (result.settings, "jobs")):
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(obj, attr, None)
    with pytest.raises(ValueError):  # counts are read-only arrays
        result.reconstruction.capture.marker_frames[0] = 0
    with pytest.raises(ValueError):
        result.arrays["rest"][0, 0, 0] = 0.0
    # tidy trajectories and arrays agree
    traj = result.trajectories
    assert list(traj.columns[:6]) == ["take", "frame", "marker", "x", "y", "z"]
    rest = traj[traj["take"] == "rest"]
    X = result.arrays["rest"]
    assert X.shape == (rest["frame"].max() + 1, len(result.markers), 3)
    np.testing.assert_array_equal(rest["x"].to_numpy().reshape(X.shape[:2]), X[..., 0])
    with pytest.raises(Exception, match="labeled 3D session has no cameras"):
        mocap.calibrate(session)
    with pytest.raises(KeyError, match="no_such_setting"):
        mocap.run(session, no_such_setting=1)
    with pytest.raises(TypeError, match="min_cameras"):
        mocap.run(session, min_cameras="three")


def test_figures_draw_into_given_axes_without_pyplot():
    code = r"""
import sys
import numpy as np
from matplotlib.figure import Figure
from mocap.outputs import figures as F
fig = Figure()
ax = fig.subplots()
got = F.linearity_bars([1, 4], [0.9, 0.8], [0.05, 0.1], ax=ax)
assert got is fig and ax.get_ylabel().startswith("spatial linearity"), ax.get_ylabel()
new = F.property_chart([1, 4], [0.02, 0.05], [10, 60], [0.1, 0.3], [True, False], "literal")
assert isinstance(new, Figure) and new is not fig and len(new.axes) == 2  # the chart and its colorbar
assert "matplotlib.pyplot" not in sys.modules
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_no_library_module_picks_a_matplotlib_backend():
    picks = ("matplotlib.use(", "import matplotlib.pyplot", "from matplotlib import pyplot")
    offenders = [str(p.relative_to(ROOT)) for folder in ("mocap", "calib", "analysis")
                 for p in (ROOT / folder).rglob("*.py")
                 if any(k in p.read_text() for k in picks)]
    assert offenders == []
    assert 'os.environ.setdefault("MPLBACKEND", "Agg")' in (ROOT / "mocap" / "cli" / "__init__.py").read_text()


# --- settings --------------------------------------------------------------------------------

def test_every_setting_has_a_flag_and_a_meaning(capsys):
    from mocap.cli import main

    with pytest.raises(SystemExit):
        main(["run", "--help"])
    help_text = capsys.readouterr().out
    table = settings_table()
    leaves = [f.name for f in dataclasses.fields(RunSettings)
              if not dataclasses.is_dataclass(f.default)]
    for section in ("reconstruction", "labels", "rejections"):
        leaves += [f"{section}.{g.name}" for g in
                   dataclasses.fields(getattr(RunSettings(), section))]
    assert [s.key for s in table] == leaves or sorted(s.key for s in table) == sorted(leaves)
    for s in table:
        assert s.flag in help_text, s.flag
        assert len(s.help) > 10, s.key
    printed = describe()
    for s in table:
        assert f"{s.key.rsplit('.', 1)[-1]} = " in printed and s.help in printed


def test_print_config_is_a_valid_config_of_the_defaults(capsys, tmp_path):
    from mocap.cli import main

    assert main(["run", "--print-config"]) == 0
    text = capsys.readouterr().out
    doc = tomllib.loads(text)
    assert doc["reconstruction"]["min_cameras"] == 3 and doc["bootstrap_samples"] == 200
    (tmp_path / "run.toml").write_text(text)
    assert dataclasses.replace(from_toml(tmp_path / "run.toml"), jobs=1) == \
        dataclasses.replace(RunSettings(), jobs=1)


def test_config_file_then_flags_and_effective_settings_in_summary(tmp_path, capsys):
    from mocap.cli import main

    root = make_session(tmp_path / "lab", du_ids=(4,), n_trials=2, n_markers=12,
                        motion_plans=(), battery=False, labeled=True, seed=3)
    cfg = tmp_path / "run.toml"
    cfg.write_text("bootstrap_samples = 7\nrecording = false\n[rejections]\n"
                   "min_displacement_mm = 0.08\nspread_k = 4\n")
    assert main(["run", str(root / "session"), "--out", str(tmp_path / "out"), "--quiet",
                 "--config", str(cfg), "--spread-k", "6.5", "--min-cameras", "2"]) == 0
    s = json.loads((tmp_path / "out" / "summary.json").read_text())["settings"]
    assert s["bootstrap_samples"] == 7 and s["recording"] is False  # the file
    assert s["rejections"]["min_displacement_mm"] == 0.08
    assert s["rejections"]["spread_k"] == 6.5  # the flag wins over the file
    assert s["reconstruction"]["min_cameras"] == 2
    assert s["labels"] == dataclasses.asdict(RunSettings().labels)  # defaults elsewhere
    assert not (tmp_path / "out" / "session.rrd").exists()
    assert json.loads((tmp_path / "out" / "audit.json").read_text())["min_cameras"] == 2
    rej = pd.read_csv(tmp_path / "out" / "rejections.csv")
    assert (rej.loc[rej["reason"] == "small_displacement", "threshold"] == 0.08).all()
    # errors name the key and the file
    cfg.write_text("[rejections]\nmin_displacment_mm = 0.1\n")
    assert main(["run", str(root / "session"), "--out", str(tmp_path / "o2"), "--config", str(cfg)]) == 1
    err = capsys.readouterr().err
    assert "rejections.min_displacment_mm" in err and str(cfg) in err
    cfg.write_text('jobs = "many"\n')
    assert main(["run", str(root / "session"), "--out", str(tmp_path / "o2"), "--config", str(cfg)]) == 1
    assert "jobs" in capsys.readouterr().err


def test_settings_by_bare_name_section_or_dotted_key():
    a = with_values(RunSettings(), {"min_cameras": 2})
    b = with_values(RunSettings(), {"reconstruction.min_cameras": 2})
    c = with_values(RunSettings(), {"reconstruction": {"min_cameras": 2}})
    assert a == b == c and a.reconstruction.min_cameras == 2
    with pytest.raises(ValueError, match="min_cameras"):
        with_values(RunSettings(), {"min_cameras": 1})
    with pytest.raises(ValueError, match="record_blobs"):
        RunSettings(record_blobs="some")


def test_progress_bars_when_asked_or_on_a_terminal_and_quiet_is_silent(tmp_path, capsys):
    from mocap.cli import main

    root = make_session(tmp_path / "lab", du_ids=(4,), n_trials=2, n_markers=12,
                        motion_plans=(), battery=False, labeled=True, seed=9)
    session = mocap.load_session(root / "session")
    mocap.run(session, bars=True, bootstrap_samples=0)
    err = capsys.readouterr().err
    assert "reconstructing takes" in err and "0/3 [" in err
    mocap.run(session, bars=None, bootstrap_samples=0)  # stderr is not a terminal here
    assert "reconstructing takes" not in capsys.readouterr().err
    assert main(["run", str(root / "session"), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    cap = capsys.readouterr()
    assert cap.err == "" and "results in" in cap.out
    assert main(["run", str(root / "session"), "--out", str(tmp_path / "out2")]) == 0
    err = capsys.readouterr().err
    assert "reconstructing takes" not in err and "markers" in err  # messages, no bar
