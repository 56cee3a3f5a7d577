"""Real rigs (issue #17): two-marker wands, no ground square, other labs' files and formats.

Truth comes from the simulator's cameras (another model of the world than the calibration's
estimate) and, for the real recording, from the recording tool's own choice of wand blobs.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.optimize import least_squares

from conftest import make_session
from mocap.calib.bundle import IntrinsicsModel
from mocap.calib.calibration_file import read_calibration
from mocap.calib.camera import rodrigues_from_rotation, rotation_from_rodrigues
from mocap.calib.interchange import (
    camera_from_dlt,
    dlt_coefficients,
    dlt_project,
    read_anipose,
    read_dlt_csv,
    write_anipose,
    write_dlt_csv,
)
from mocap.calib.wand_calibration import CalibrationError, calibrate_session
from mocap.calib.world_frame import umeyama
from mocap.core.session import load_session
from mocap.simulate.rig import VOLUME_CENTER, VOLUME_HALF_MM

REAL = Path(__file__).resolve().parents[2] / "shared" / "realdata" / "pyopenlpt_wand_4cam_blobs.csv"
if not REAL.is_file():
    REAL = Path("/work/shared/realdata/pyopenlpt_wand_4cam_blobs.csv")
MINIMAL = dict(du_ids=(4,), n_trials=1, motion_plans=(), battery=False)


@pytest.fixture(scope="module")
def rod_sim(tmp_path_factory):
    """A 200 mm two-marker rod waved for 10 s, no ground square."""
    return make_session(tmp_path_factory.mktemp("rod"), seed=31, wand_offsets_mm=(0.0, 200.0),
                        ground=False, wand_duration_s=10.0, **MINIMAL)


@pytest.fixture(scope="module")
def rod_result(rod_sim):
    return calibrate_session(load_session(rod_sim / "session"))


def true_rig(root):
    return read_calibration(root / "truth" / "cameras.toml")[0]


def volume_points(n=3000, seed=0):
    rng = np.random.default_rng(seed)
    return VOLUME_CENTER + rng.uniform(-1, 1, (n, 3)) * VOLUME_HALF_MM


def image_space_rms(est, truth):
    """RMS (px, per axis) between the estimated and the true cameras' images of points filling
    the capture volume, after the similarity (the gauge) that best aligns the two."""
    X = volume_points()
    uv_t = truth.project(X)
    vis = np.stack([c.in_image(u) for c, u in zip(truth, uv_t)])
    C = np.array([c.center for c in est])
    T = np.array([c.center for c in truth])
    R, t, s = umeyama(T, C, with_scale=True)

    def res(p):
        Xe = np.exp(p[6]) * X @ rotation_from_rodrigues(p[:3]).T + p[3:6]
        return np.where(vis[..., None], est.project(Xe) - uv_t, 0.0).ravel()

    r = least_squares(res, np.r_[rodrigues_from_rotation(R), t, np.log(s)])
    return float(np.sqrt(np.sum(r.fun**2) / (2 * vis.sum())))


def test_two_marker_wand_without_ground_matches_truth(rod_sim, rod_result):
    est, truth = rod_result.rig, true_rig(rod_sim)
    C = np.array([c.center for c in est])
    T = np.array([c.center for c in truth])
    R, t, s = umeyama(C, T, with_scale=True)
    centre_err = np.linalg.norm(s * C @ R.T + t - T, axis=1)
    assert centre_err.max() < 0.15, centre_err
    assert abs(s - 1.0) < 1e-3  # the wand alone sets the scale
    assert image_space_rms(est, truth) <= 0.02
    # the world frame is the first camera's, and the report says so
    np.testing.assert_allclose(est[0].R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(est[0].t, 0.0, atol=1e-9)
    q = rod_result.quality
    assert "first camera (cam1)" in q["world_frame"] and "no ground" in q["world_frame"]
    assert q["wand_markers"] == 2 and q["rating"] == "excellent"


def test_two_marker_ends_ordered_like_truth(rod_sim, rod_result):
    """Every kept sighting's ends are in one order per frame across cameras, the true one up to
    a per-frame swap."""
    truth = true_rig(rod_sim)
    P = pd.read_parquet(rod_sim / "truth" / "trajectories" / "wand.parquet")
    P = P[["x", "y", "z"]].to_numpy().reshape(-1, 2, 3)
    obs = rod_result.wand.select(rod_result.used)
    proj = np.stack([truth[int(c)].project(P[f]) for c, f in zip(obs.camera, obs.frame)])
    straight = np.abs(obs.uv - proj).max(axis=(1, 2)) < 1.0
    swapped = np.abs(obs.uv[:, ::-1] - proj).max(axis=(1, 2)) < 1.0
    assert np.mean(straight | swapped) > 0.999
    per_frame = pd.DataFrame({"f": obs.frame, "s": straight}).groupby("f")["s"].nunique()
    assert (per_frame == 1).mean() > 0.999


def test_principal_point_fixed_and_unsupported_models(rod_sim, tmp_path):
    session = load_session(rod_sim / "session")
    r = calibrate_session(session, intrinsics=IntrinsicsModel("fixed", "k1"), max_frames=400)
    for c in r.rig:
        assert c.K[0, 2] == (c.width - 1) / 2 and c.K[1, 2] == (c.height - 1) / 2
        assert c.dist[1] == c.dist[2] == c.dist[3] == 0.0 and c.dist[0] != 0.0
    assert r.quality["intrinsics"] == {"principal_point": "fixed", "distortion": "k1"}
    # 30 frames of wand: too few for a full model
    short = make_session(tmp_path / "short", seed=32, wand_offsets_mm=(0.0, 200.0), ground=False,
                         wand_duration_s=0.25, **MINIMAL)
    with pytest.raises(CalibrationError, match=r"too few frames.*--principal-point fixed"):
        calibrate_session(load_session(short / "session"),
                          intrinsics=IntrinsicsModel("free", "k1k2p1p2"))


def capture_points(result, n=500):
    """Points of the capture volume in the calibration's own frame (the fitted wand's markers)."""
    X = result.wand_points_mm.reshape(-1, 3)
    return X[np.linspace(0, len(X) - 1, n).astype(int)]


def test_anipose_round_trip(rod_result, tmp_path):
    rig = rod_result.rig
    X = capture_points(rod_result)
    for units in ("mm", "m"):
        write_anipose(tmp_path / f"{units}.toml", rig, units=units)
        back = read_anipose(tmp_path / f"{units}.toml", units=units)
        assert back.ids == rig.ids
        uv = rig.project(X)
        seen = np.stack([c.in_image(u) for c, u in zip(rig, uv)])  # (far outside the image the
        assert seen.mean() > 0.5  # distortion polynomial explodes and compares nothing)
        assert np.abs(back.project(X) - uv)[seen].max() < 1e-6
    text = (tmp_path / "mm.toml").read_text()
    assert "[cam_0]" in text and 'name = "cam1"' in text and "size = [1280, 1024]" in text


def test_dlt_export_reproduces_undistorted_projections(rod_result, tmp_path):
    rig = rod_result.rig
    X = capture_points(rod_result)
    write_dlt_csv(tmp_path / "dlt.csv", rig)
    L = np.loadtxt(tmp_path / "dlt.csv", delimiter=",")
    assert L.shape == (11, len(rig))
    for i, c in enumerate(rig):
        undistorted = replace(c, dist=np.zeros(5)).project(X)
        assert np.isfinite(undistorted).all()
        uv = dlt_project(L[:, i], X)  # MATLAB pixels: bottom-left origin, 1-based
        ours = np.stack([uv[:, 0] - 1.0, c.height - uv[:, 1]], axis=-1)
        assert np.abs(ours - undistorted).max() < 1e-6
        top = dlt_project(dlt_coefficients(c, origin="top-left"), X)
        assert np.abs(top - undistorted).max() < 1e-6
    back = read_dlt_csv(tmp_path / "dlt.csv", [(c.id, c.width, c.height) for c in rig])
    for c, b in zip(rig, back):
        assert np.abs(b.project(X) - replace(c, dist=np.zeros(5)).project(X)).max() < 1e-6
        np.testing.assert_allclose(b.center, c.center, atol=1e-6)
    with pytest.raises(ValueError, match="origin"):
        camera_from_dlt(L[:, 0], camera_id="a", width=10, height=10, origin="centre")


def test_xypts_and_profile_import(rod_sim, tmp_path):
    """A DLTdv/easyWand digitisation (bottom-left origin, NaN when unseen) of the true wand,
    with a camera profile, becomes a session whose blobs are the true image points."""
    from mocap.interop.wand_points import read_camera_profile, read_xypts, write_wand_session

    truth = true_rig(rod_sim)
    P = pd.read_parquet(rod_sim / "truth" / "trajectories" / "wand.parquet")
    P = P[["x", "y", "z"]].to_numpy().reshape(-1, 2, 3)[::20]
    cols = {}
    for k in range(2):
        for i, c in enumerate(truth):
            uv = c.project(P[:, k])
            uv[~c.in_image(uv)] = np.nan
            cols[f"pt{k + 1}_cam{i + 1}_X"] = uv[:, 0] + 1.0
            cols[f"pt{k + 1}_cam{i + 1}_Y"] = c.height - uv[:, 1]
    pd.DataFrame(cols).to_csv(tmp_path / "wand_xypts.csv", index=False, na_rep="NaN")
    (tmp_path / "profile.txt").write_text("".join(
        f"{i + 1} {c.focal_px:.2f} {c.width} {c.height} {c.K[0, 2] + 1:.2f} "
        f"{c.height - c.K[1, 2]:.2f} 1 0 0 0 0 0\n" for i, c in enumerate(truth)))
    profile = read_camera_profile(tmp_path / "profile.txt")
    assert [p.id for p in profile] == truth.ids and profile[0].width == 1280
    blobs = read_xypts(tmp_path / "wand_xypts.csv", {p.id: p.height for p in profile})
    for cid, g in blobs.groupby("camera"):
        c = truth[cid]
        uv = g[["x", "y"]].to_numpy()
        proj = np.stack([c.project(P[f]) for f in g.frame])  # (n, 2, 2)
        d = np.min(np.linalg.norm(proj - uv[:, None], axis=-1), axis=1)
        assert d.max() < 1e-6
    root = write_wand_session(tmp_path / "session", blobs, profile, [0.0, 200.0], fps=120.0)
    s = load_session(root)
    assert s.ground is None and len(s.wand.marker_offsets_mm) == 2
    assert abs(s.cameras[0].focal_px - truth[0].focal_px) < 0.01


@pytest.mark.skipif(not REAL.is_file(), reason="real data folder absent")
def test_blob_table_import_takes_the_raw_rows(tmp_path):
    from mocap.interop.wand_points import is_blob_table, is_xypts, read_blob_table

    assert is_blob_table(REAL) and not is_xypts(REAL)
    b = read_blob_table(REAL)
    raw = pd.read_csv(REAL)
    raw = raw[raw.Status == "Raw"]
    assert len(b) == len(raw) and set(b.camera) == {"cam0", "cam1", "cam2", "cam3"}
    np.testing.assert_allclose(np.sort(b.x.to_numpy()), np.sort(raw.X.to_numpy()))


@pytest.mark.slow
@pytest.mark.skipif(not REAL.is_file(), reason="real data folder absent")
def test_real_two_marker_recording_calibrates_from_nothing(tmp_path):
    """pyOpenLPT's real 4-camera recording, Raw blobs only, no focal length, no ground: the
    calibration converges, its sightings are the tool's own wand blobs, and its end order
    matches the tool's small/large labels (which it never saw)."""
    from mocap.interop.wand_points import CameraProfile, read_blob_table, write_wand_session

    b = read_blob_table(REAL)
    root = write_wand_session(tmp_path / "s", b, [CameraProfile(c, 1280, 800)
                                                  for c in sorted(b.camera.unique())], [0.0, 1000.0])
    r = calibrate_session(load_session(root), max_frames=1200)
    q = r.quality
    assert max(q["reprojection_rms_px"].values()) < 1.5
    from mocap.calib.quality import wand_lengths

    _, lengths = wand_lengths(r.rig, r.wand.select(r.used))
    lengths = lengths[np.isfinite(lengths)]
    assert np.std(lengths) / np.mean(lengths) < 0.02
    d = pd.read_csv(REAL)
    small = d[d.Status == "Filtered_Small"].set_index(["Frame", "Camera"])[["X", "Y"]]
    large = d[d.Status == "Filtered_Large"].set_index(["Frame", "Camera"])[["X", "Y"]]
    obs = r.wand  # every sighting chosen and ordered (not only the adjustment's subsample)
    same, end0_small = [], {}
    for c, f, uv in zip(obs.camera, obs.frame, obs.uv):
        if (f, c) not in small.index:
            continue
        s, lg = small.loc[(f, c)].to_numpy(), large.loc[(f, c)].to_numpy()
        st = np.abs(uv - [s, lg]).max() < 1e-3
        sw = np.abs(uv - [lg, s]).max() < 1e-3
        same.append(st or sw)
        if st or sw:
            end0_small.setdefault(f, set()).add(bool(st))
    assert len(same) > 5000 and np.mean(same) > 0.98
    assert np.mean([len(v) == 1 for v in end0_small.values()]) > 0.99


@pytest.mark.skipif(not REAL.is_file(), reason="real data folder absent")
def test_import_cli_wand_recording(tmp_path, capsys):
    from mocap.cli import main

    assert main(["import", str(REAL), "--out", str(tmp_path / "s")]) == 1
    assert "--wand-offsets" in capsys.readouterr().err
    assert main(["import", str(REAL), "--wand-offsets", "0,660", "--image-size", "1280x800",
                 "--out", str(tmp_path / "s")]) == 0
    s = load_session(tmp_path / "s")
    assert [c.id for c in s.cameras] == ["cam0", "cam1", "cam2", "cam3"]
    assert s.ground is None and list(s.wand.marker_offsets_mm) == [0.0, 660.0]
    assert len(s.read_take("wand")) == int((pd.read_csv(REAL).Status == "Raw").sum())


def test_calibrate_cli_writes_other_formats(rod_sim, rod_result, tmp_path, capsys):
    from mocap.cli import main

    out = tmp_path / "c.toml"
    assert main(["calibrate", str(rod_sim / "session"), "--out", str(out), "--max-frames", "400",
                 "--principal-point", "fixed", "--distortion", "k1k2",
                 "--anipose", str(tmp_path / "a.toml"), "--dlt", str(tmp_path / "d.csv")]) == 0
    rig, q = read_calibration(out)
    a = read_anipose(tmp_path / "a.toml")
    X = capture_points(rod_result, 200)
    uv = rig.project(X)
    seen = np.stack([c.in_image(u) for c, u in zip(rig, uv)])
    assert np.abs(a.project(X) - uv)[seen].max() < 1e-6
    assert np.loadtxt(tmp_path / "d.csv", delimiter=",").shape == (11, 6)
    printed = capsys.readouterr().out
    assert "world frame: first camera (cam1)" in printed and "distortion k1k2" in printed
    assert q["intrinsics"] == {"principal_point": "fixed", "distortion": "k1k2"}


def test_short_hand_digitised_recording(tmp_path):
    """50 frames spread over a 30 s take (as a hand digitisation picks them), 3 cameras, a
    300 mm rod, no ground: the default model converges close to the truth."""
    root = make_session(tmp_path / "s", seed=33, wand_offsets_mm=(0.0, 300.0), ground=False,
                        wand_duration_s=30.0, n_cameras=3, **MINIMAL)
    path = root / "session" / "takes" / "wand.parquet"
    b = pd.read_parquet(path)
    b = b[b.frame % 72 == 0].assign(frame=lambda d: d.frame // 72)
    b.to_parquet(path, index=False)
    assert b.frame.nunique() == 50
    r = calibrate_session(load_session(root / "session"))
    est, truth = r.rig, true_rig(root)
    C = np.array([c.center for c in est])
    T = np.array([c.center for c in truth])
    R, t, s = umeyama(C, T, with_scale=True)
    assert np.linalg.norm(s * C @ R.T + t - T, axis=1).max() < 0.3
    assert image_space_rms(est, truth) < 0.1
