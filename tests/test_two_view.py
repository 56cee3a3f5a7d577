"""Issue #17: a marker only two cameras see is reconstructed by default, and left to the audit.

With the default ``min_cameras`` (3) the shadowed nose bridge (``nose_bridge_cameras=2``) is in
the trajectories with ``n_cameras`` 2 and its residual; the analyses never see those samples
(one mask, ``mocap.reconstruction.camera_count``); the audit names the marker; the other markers are
labeled as well against the simulator's truth as by the 3+-view points alone (what the
reconstruction kept before 2-view points were accepted).
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pandas as pd
import pytest

from conftest import make_session
from mocap.workflows.run.pipeline import run_session
from mocap.workflows.run.settings import RunSettings
from mocap.reconstruction.camera_count import below_min_cameras, usable_positions
from mocap.reconstruction.correspondence import Points3D, reconstruct_points
from mocap.reconstruction.labeling import LabeledTake, TakeStats, label_take

TAKE = "du04_t01"


@pytest.fixture(scope="module")
def two_view(tmp_path_factory):
    root = make_session(tmp_path_factory.mktemp("two_view"), seed=41, du_ids=(4,), n_trials=3,
                        n_markers=24, motion_plans=(), battery=False, wand_duration_s=10.0,
                        nose_bridge_cameras=2)
    # a marker the analyses never see (too few cameras) is an expected NaN, not a numpy warning
    # printed at the user (trials, noise corrections, session analysis, audit)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        res = run_session(root / "session", root / "out",
                          settings=RunSettings(recording=False, jobs=1))
    truth = json.loads((root / "truth" / "truth.json").read_text())
    return root, res, truth


def _truth_dense(root, take, names):
    tr = pd.read_parquet(root / "truth" / "trajectories" / f"{take}.parquet")
    piv = tr.pivot(index="frame", columns="marker", values=["x", "y", "z"])
    return np.stack([piv[k][list(names)].to_numpy() for k in "xyz"], axis=-1)


def test_two_camera_marker_is_in_the_trajectories(two_view):
    root, res, truth = two_view
    nose = truth["nose_bridge_marker"]
    assert nose in res.reconstruction.markers.names
    assert nose not in res.reconstruction.markers.missing_from_template
    tr = pd.read_parquet(root / "out" / "trajectories" / f"{TAKE}.parquet")
    nb = tr[(tr.marker == nose) & tr.x.notna()]
    assert len(nb) > 0.8 * tr.frame.nunique()
    assert (nb.n_cameras == 2).all()  # the simulator lets exactly two cameras see it
    assert np.isfinite(nb.residual_px).all() and (nb.residual_px < 0.5).all()
    # where it is, it is the nose bridge (mm, against the simulator's truth)
    T = _truth_dense(root, TAKE, [nose])[nb.frame.to_numpy(), 0]
    err = np.linalg.norm(nb[["x", "y", "z"]].to_numpy() - T, axis=1)
    assert np.median(err) < 0.5, np.median(err)


def test_analyses_leave_out_exactly_the_samples_below_min_cameras(two_view):
    root, res, truth = two_view
    names = list(res.reconstruction.markers.names)
    nose = names.index(truth["nose_bridge_marker"])
    for take, lab in res.reconstruction.takes.items():
        tr = pd.read_parquet(root / "out" / "trajectories" / f"{take}.parquet")
        n_frames, M = lab.X.shape[:2]
        ncam = tr["n_cameras"].to_numpy().reshape(n_frames, M)
        X = tr[["x", "y", "z"]].to_numpy().reshape(n_frames, M, 3)
        written = np.isfinite(X[..., 0])
        np.testing.assert_array_equal(np.isfinite(lab.X[..., 0]), written)  # all samples kept
        kept = usable_positions(lab, 3)
        used = np.isfinite(kept[..., 0])
        # the analyses' samples are the written ones seen by 3 cameras or more, unchanged
        np.testing.assert_array_equal(used, written & (ncam >= 3))
        np.testing.assert_array_equal(kept[used], X[used])
        assert not used[:, nose].any()
    # so the trial averages never saw the nose bridge, and the rest of the markers fully
    for avg in res.trials.averages:
        assert (avg.n_trials[:, nose] == 0).all()
        others = np.delete(avg.n_trials, nose, axis=1)
        assert np.mean(others == len(avg.takes)) > 0.99


def test_audit_names_the_two_camera_marker(two_view):
    root, res, truth = two_view
    nose = truth["nose_bridge_marker"]
    a = json.loads((root / "out" / "audit.json").read_text())
    assert a["min_cameras"] == 3
    m = next(m for m in a["markers"] if m["marker"] == nose)
    assert m["cameras"] == 2 and m["verdicts"]["cameras"] == "fail"
    assert ("marker", nose) in {(f["kind"], f["item"]) for f in a["flagged"]}
    assert a["missing_markers"] == []
    flagged_markers = {f["item"] for f in a["flagged"] if f["kind"] == "marker"}
    assert flagged_markers == {nose}
    rej = pd.read_csv(root / "out" / "rejections.csv")
    assert nose in set(rej["marker"])  # left out of the analyses, with its reason
    assert set(rej.loc[rej["marker"] == nose, "reason"]) == {"gaps"}  # no usable sample at all
    assert np.isfinite(rej["value"]).all()


def test_masking_function_keeps_interpolated_and_3d_samples():
    n = np.array([[0, 1, 2, 3, 4]])
    np.testing.assert_array_equal(below_min_cameras(n, 3), [[False, True, True, False, False]])
    X = np.arange(15, dtype=float).reshape(1, 5, 3)
    lab = LabeledTake(X, n, np.zeros((1, 5)), np.zeros((1, 5), bool), TakeStats(points=4, labeled_points=4))
    out = usable_positions(lab, 3)
    assert np.isnan(out[0, 1:3]).all() and np.array_equal(out[0, [0, 3, 4]], X[0, [0, 3, 4]])
    assert usable_positions(lab, 1) is lab.X  # nothing to mask: no copy
    assert np.isfinite(lab.X).all()  # the input is untouched


def _subset(p: Points3D, keep: np.ndarray) -> Points3D:
    return Points3D(p.frame[keep], p.X[keep], p.n_cameras[keep], p.residual_px[keep], p.blob[keep])


def test_other_markers_labeled_as_with_three_view_points_only(two_view):
    """The points with 3+ views are exactly what the reconstruction kept before 2-view points were
    accepted (those come from a second pass over the blobs left); adding the 2-view points must
    not change the other markers' labels, and their error against the truth is no worse."""
    root, res, truth = two_view
    names = list(res.reconstruction.markers.names)
    nose = names.index(truth["nose_bridge_marker"])
    rig, quality = res.calibration.rig, res.calibration.quality
    for take in (TAKE, "rest"):
        blobs = pd.read_parquet(root / "session" / "takes" / f"{take}.parquet")
        n_frames = int(blobs["frame"].max()) + 1
        pts = reconstruct_points(blobs, rig, quality)
        assert (pts.n_cameras == 2).any() and (pts.n_cameras >= 3).any()
        both = label_take(pts, res.reconstruction.markers, n_frames)
        three = label_take(_subset(pts, pts.n_cameras >= 3), res.reconstruction.markers, n_frames)
        T = _truth_dense(root, take, names)
        others = np.ones(len(names), bool)
        others[nose] = False
        sel = (both.n_cameras >= 3)[:, others]
        Xb, Xt = both.X[:, others], three.X[:, others]
        np.testing.assert_array_equal(sel, np.isfinite(Xt[..., 0]))  # same samples labeled
        np.testing.assert_array_equal(Xb[sel], Xt[sel])  # at the same positions
        err_b = np.linalg.norm(Xb - T[:, others], axis=-1)
        err_t = np.linalg.norm(Xt - T[:, others], axis=-1)
        assert np.nanmax(err_b[sel]) < 1.0
        assert np.sqrt(np.mean(err_b[sel] ** 2)) <= np.sqrt(np.mean(err_t[sel] ** 2)) + 1e-12
        # 2-view samples of the other markers are few, and right where they are
        two = np.isfinite(Xb[..., 0]) & ~sel
        assert two.mean() < 0.02, two.mean()
        assert (err_b[two] < 1.0).all()
