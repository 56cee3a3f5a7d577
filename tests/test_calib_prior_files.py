"""Prior intrinsics from the files labs have (issue #50): hand-typed easyWand/Argus profiles,
aniposelib calibration.toml, OpenCV YAML and session manifests; static background points from a
DLTdv xypts file; the import and calibrate commands end to end."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from mocap.calib.priors import PriorFileError, read_priors
from mocap.core.session import SessionError, load_session

PROFILE = "1 450 640 512 320.5 256.5 1 -0.3 0.09 -0.001 -0.002 0.01\n"  # bottom-left, 1-based
ANIPOSE = """\
[cam_0]
name = "cam1"
size = [640, 512]
matrix = [[450.0, 0.0, 319.5], [0.0, 450.0, 255.5], [0.0, 0.0, 1.0]]
distortion = [-0.3, 0.09, 0.001, -0.002, 0.01]
rotation = [0.0, 0.0, 0.0]
translation = [0.0, 0.0, 0.0]

[metadata]
adjusted = false
error = 0.0
"""
OPENCV = """\
%YAML:1.0
---
camera_id: cam1
image_width: 640
image_height: 512
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 450., 0., 319.5, 0., 450., 255.5, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ -0.3, 0.09, 0.001, -0.002, 0.01 ]
"""


def test_three_formats_give_the_same_priors(tmp_path):
    (tmp_path / "profile.txt").write_text("# camera f w h cx cy ar k1 k2 t1 t2 k3\n" + PROFILE)
    (tmp_path / "calibration.toml").write_text(ANIPOSE)
    (tmp_path / "cam1.yml").write_text(OPENCV)
    got = [read_priors(tmp_path / n)["cam1"]
           for n in ("profile.txt", "calibration.toml", "cam1.yml")]
    for p in got:
        assert p.camera_id == "cam1" and p.size == (640, 512) and p.mode == "refine"
        assert p.focal_px == pytest.approx(450.0)
        assert p.principal_px == pytest.approx((319.5, 255.5))
        assert p.distortion == pytest.approx((-0.3, 0.09, 0.001, -0.002, 0.01))
    assert read_priors(tmp_path / "cam1.yml", mode="fixed")["cam1"].mode == "fixed"


@pytest.mark.parametrize("text, match", [
    ("1 450 640 512 320.5 256.5 1.2 -0.3 0.09 0 0 0\n", "aspect ratio"),
    ("1 450 640 512 320.5 256.5 1 -0.3\n", "12 columns"),
    ("1 450 640 512 x 256.5\n", "line 1: expected numbers"),
    ("1 450 640 512 320.5 256.5\n1 450 640 512 320.5 256.5\n", "line 2: camera 1 given twice"),
])
def test_bad_profiles_name_the_line(tmp_path, text, match):
    (tmp_path / "p.txt").write_text(text)
    with pytest.raises(PriorFileError, match=match):
        read_priors(tmp_path / "p.txt")


def test_bad_anipose_and_opencv_files(tmp_path):
    (tmp_path / "a.toml").write_text(ANIPOSE.replace("matrix = ", "matrx = "))
    with pytest.raises(PriorFileError, match=r"\[cam_0\]: missing key 'matrix'"):
        read_priors(tmp_path / "a.toml")
    (tmp_path / "b.toml").write_text(ANIPOSE.replace("[0.0, 450.0, 255.5]", "[0.0, 500.0, 255.5]"))
    with pytest.raises(PriorFileError, match="non-square"):
        read_priors(tmp_path / "b.toml")
    (tmp_path / "c.yml").write_text(OPENCV.replace("camera_matrix", "cam_matrix"))
    with pytest.raises(PriorFileError, match="missing key 'camera_matrix'"):
        read_priors(tmp_path / "c.yml")
    with pytest.raises(PriorFileError, match="not found"):
        read_priors(tmp_path / "none.txt")


MANIFEST = """\
schema = "mocap-session/1"
name = "priors"
fps = 100.0

[[cameras]]
id = "cam1"
width = 640
height = 512
focal_px = 450.0
principal_px = [319.5, 255.5]
distortion = [-0.3, 0.09, 0.0, 0.0]
{mode}
[[cameras]]
id = "cam2"
width = 640
height = 512

[wand]
marker_offsets_mm = [0.0, 300.0]

[[takes]]
name = "wand"
kind = "wand"
file = "takes/wand.csv"

[[takes]]
name = "bkgd"
kind = "points"
file = "takes/bkgd.csv"
"""


def write_manifest(root, text):
    (root / "takes").mkdir(parents=True, exist_ok=True)
    (root / "takes" / "wand.csv").write_text("frame,camera,x,y\n0,cam1,1.0,2.0\n")
    (root / "takes" / "bkgd.csv").write_text("frame,camera,x,y\n0,cam1,1.0,2.0\n0,cam2,3.0,4.0\n")
    (root / "session.toml").write_text(text)
    return root


def test_manifest_priors(tmp_path):
    s = load_session(write_manifest(tmp_path / "a", MANIFEST.format(mode='intrinsics = "fixed"')))
    c1, c2 = s.cameras
    assert c1.principal_px == (319.5, 255.5) and c1.distortion == (-0.3, 0.09, 0.0, 0.0, 0.0)
    assert c1.intrinsics == "fixed" and c1.has_prior
    assert c2.intrinsics is None and not c2.has_prior
    assert [t.name for t in s.takes_of_kind("points")] == ["bkgd"]
    s = load_session(write_manifest(tmp_path / "b", MANIFEST.format(mode="")))
    assert s.cameras[0].intrinsics == "refine"  # the default when a prior is given
    for bad, match in [('intrinsics = "free"', "intrinsics: expected"),
                       ("", "distortion: expected")]:
        text = MANIFEST.format(mode=bad)
        if not bad:
            text = text.replace("[-0.3, 0.09, 0.0, 0.0]", "[-0.3, 0.09]")
        with pytest.raises(SessionError, match=match):
            load_session(write_manifest(tmp_path / "c", text))
    text = MANIFEST.format(mode="").replace("focal_px = 450.0\n", "")
    with pytest.raises(SessionError, match="prior intrinsics need focal_px"):
        load_session(write_manifest(tmp_path / "d", text))


def xypts(path, truth, P):
    """DLTdv columns (bottom-left origin, 1-based, NaN unseen) of points P (rows, k, 3)."""
    cols = {}
    for k in range(P.shape[1]):
        for i, c in enumerate(truth):
            uv = c.project(P[:, k])
            uv[~c.in_image(uv)] = np.nan
            cols[f"pt{k + 1}_cam{i + 1}_X"] = uv[:, 0] + 1.0
            cols[f"pt{k + 1}_cam{i + 1}_Y"] = c.height - uv[:, 1]
    pd.DataFrame(cols).to_csv(path, index=False, na_rep="NaN")


def test_import_and_calibrate_with_profile_and_background_points(tmp_path, capsys):
    """A lab's files: the wand digitised in DLTdv, 40 background points digitised in every view
    (one row, 40 points), a lens profile per camera. Imported and calibrated by the commands:
    the priors are used as given, the static points join the adjustment and cover more of the
    image, and every point reprojects near its noise-free position."""
    from test_calib_priors import thin_rig, wand_recording

    from mocap.calib.calibration_file import read_calibration
    from mocap.cli import main

    truth = thin_rig()
    rng = np.random.default_rng(3)
    P, _ = wand_recording(truth)
    xypts(tmp_path / "wand_xypts.csv", truth, P)
    # background points spread wider than the wand went
    Q = (P.reshape(-1, 3).mean(axis=0) + rng.uniform(-1, 1, (40, 3)) * [350, 280, 120])[None]
    xypts(tmp_path / "bkgd_xypts.csv", truth, Q)
    (tmp_path / "profile.txt").write_text("".join(
        " ".join(repr(float(v)) for v in (
            i + 1, c.focal_px, c.width, c.height, c.K[0, 2] + 1, c.height - c.K[1, 2], 1,
            c.dist[0], c.dist[1], -c.dist[2], c.dist[3], c.dist[4])) + "\n"
        for i, c in enumerate(truth)))
    s = tmp_path / "s"
    assert main(["import", str(tmp_path / "wand_xypts.csv"), "--profile",
                 str(tmp_path / "profile.txt"), "--intrinsics-mode", "fixed", "--points",
                 str(tmp_path / "bkgd_xypts.csv"), "--wand-offsets", "0,300", "--out", str(s)]) == 0
    session = load_session(s)
    for c, t in zip(session.cameras, truth):
        assert c.intrinsics == "fixed"
        np.testing.assert_allclose(c.principal_px, t.K[:2, 2], atol=1e-9)
        np.testing.assert_allclose(c.distortion, t.dist, atol=1e-12)
    pts = session.read_take("points")
    assert pts.frame.nunique() == int(np.sum(np.sum([c.in_image(c.project(Q[0]))
                                                     for c in truth], axis=0) >= 1))
    assert main(["calibrate", str(s), "--out", str(tmp_path / "c.toml")]) == 0
    out = capsys.readouterr().out
    assert "intrinsics from the prior fixed" in out and "image covered" in out
    rig, q = read_calibration(tmp_path / "c.toml")
    for c, t in zip(rig, truth):
        np.testing.assert_allclose(c.K, t.K, atol=1e-9)
    assert q["points"]["points"] >= 20
    assert max(q["points"]["reprojection_rms_px"].values()) < 1e-3  # noise-free digitisation
    for _cid, cov in q["coverage"].items():
        assert cov["both"] > cov["wand"]
    assert sum(q["sightings_dropped"].values()) == 0
    # the same profile read by --intrinsics overrides a manifest without priors
    s2 = tmp_path / "s2"
    assert main(["import", str(tmp_path / "wand_xypts.csv"), "--image-size", "640x512",
                 "--wand-offsets", "0,300", "--out", str(s2)]) == 0
    assert not any(c.has_prior for c in load_session(s2).cameras)
    assert main(["calibrate", str(s2), "--out", str(tmp_path / "c2.toml"), "--intrinsics",
                 str(tmp_path / "profile.txt"), "--intrinsics-mode", "fixed"]) == 0
    rig2, _ = read_calibration(tmp_path / "c2.toml")
    for c, t in zip(rig2, truth):
        np.testing.assert_allclose(c.dist, t.dist, atol=1e-12)
    assert main(["calibrate", str(s2), "--out", str(tmp_path / "c3.toml"), "--intrinsics",
                 str(tmp_path / "nothing.txt")]) == 1
    assert "nothing.txt: file not found" in capsys.readouterr().err
