"""The compiled correspondence and linking kernels against their NumPy references and the truth."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from mocap.reconstruction import correspondence_kernel as kern
from mocap.reconstruction.correspondence import (
    BlobIndex,
    BlobTable,
    ReconstructionSettings,
    reconstruct_points,
)
from mocap.reconstruction.labeling import LabelSettings, link_tracklets
from mocap.reconstruction.reference import (
    blob_table_reference,
    link_tracklets_reference,
    reconstruct_points_reference,
)

TAKES = ["rest", "du04_t01", "du12_t03", "smile_du01_07_12_planA"]


def read_take(root, take):
    return pd.read_parquet(root / "session" / "takes" / f"{take}.parquet")


def assert_same_points(new, ref):
    assert len(new) == len(ref) > 0
    np.testing.assert_array_equal(new.blob, ref.blob)  # the same correspondences, same order
    np.testing.assert_array_equal(new.frame, ref.frame)
    np.testing.assert_array_equal(new.n_cameras, ref.n_cameras)
    np.testing.assert_allclose(new.X, ref.X, rtol=0, atol=1e-9)  # mm
    np.testing.assert_allclose(new.residual_px, ref.residual_px, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("take", TAKES)
def test_compiled_correspondence_matches_numpy_reference(small_sim, small_run, take):
    rig, quality = small_run.calibration.rig, small_run.calibration.quality
    blobs = read_take(small_sim, take)
    assert_same_points(reconstruct_points(blobs, rig, quality),
                       reconstruct_points_reference(blobs, rig, quality))


def test_compiled_correspondence_matches_reference_with_two_cameras(small_sim, small_run):
    """Bare epipolar pairs, taken when unique after the 3+-view pass: the other acceptance rule
    (whatever ``min_cameras``, which only masks the analyses' samples)."""
    rig, quality = small_run.calibration.rig, small_run.calibration.quality
    blobs = read_take(small_sim, "du07_t02")
    # drop most of three cameras' blobs so that many markers are seen by two cameras only
    rng = np.random.default_rng(3)
    drop = blobs["camera"].isin(rig.ids[:3]).to_numpy() & (rng.random(len(blobs)) < 0.8)
    blobs = blobs[~drop].reset_index(drop=True)
    new = reconstruct_points(blobs, rig, quality)
    assert_same_points(new, reconstruct_points_reference(blobs, rig, quality))
    assert (new.n_cameras == 2).sum() > 100
    s = ReconstructionSettings(min_cameras=2)
    assert_same_points(reconstruct_points(blobs, rig, quality, s), new)


def test_compiled_correspondence_is_right_against_the_truth(small_sim, small_run):
    """Every point's blobs come from one true marker, and markers seen by 3 cameras are found."""
    rig, quality = small_run.calibration.rig, small_run.calibration.quality
    take = "du12_t02"
    blobs = read_take(small_sim, take)
    label = pd.read_parquet(small_sim / "truth" / "labels" / f"{take}.parquet")["label"].to_numpy()
    pts = reconstruct_points(blobs, rig, quality)
    lab = np.where(pts.blob >= 0, label[np.maximum(pts.blob, 0)], -2)
    seen = lab != -2
    first = lab[np.arange(len(pts)), np.argmax(seen, axis=1)]
    pure = np.all(~seen | (lab == first[:, None]), axis=1) & (first >= 0)
    assert pure.mean() >= 0.999, pure.mean()
    # (frame, marker) pairs whose marker left blobs in at least 3 cameras
    real = label >= 0
    key = pd.DataFrame({"f": blobs["frame"][real], "m": label[real], "c": blobs["camera"][real]})
    need = key.groupby(["f", "m"])["c"].nunique()
    need = set(need[need >= 3].index)
    found = set(zip(pts.frame[pure].tolist(), first[pure].tolist()))
    assert len(need & found) >= 0.995 * len(need), (len(need & found), len(need))


def test_blob_table_matches_camera_methods(small_sim, small_run):
    rig = small_run.calibration.rig
    blobs = read_take(small_sim, "du01_t01")
    new, ref = BlobTable.from_frame(blobs, rig), blob_table_reference(blobs, rig)
    np.testing.assert_array_equal(new.cam, ref.cam)
    np.testing.assert_allclose(new.xn, ref.xn, rtol=0, atol=1e-14)
    np.testing.assert_allclose(new.ray, ref.ray, rtol=0, atol=1e-14)


def test_nearest_blob_is_the_brute_force_nearest():
    rng = np.random.default_rng(0)
    n_frames, C = 4, 2
    n = 3000
    frame = rng.integers(0, n_frames, n)
    cam = rng.integers(0, C, n)
    uv = rng.uniform([0, 0], [1280, 1024], (n, 2))
    uv[:40, 0] = 300.0  # equal x in a bucket
    uv[40:60, 0] = rng.uniform(-50, -10, 20)  # off the image
    bt = BlobTable(frame, cam, uv, np.zeros((n, 2)), np.zeros((n, 3)))
    ix = BlobIndex.of(bt, C)
    q = rng.uniform([-60, -20], [1340, 1044], (4000, 2))
    q[:200] = uv[rng.integers(0, n, 200)] + rng.normal(0, 3, (200, 2))
    for gate in (0.5, 8.0, 40.0):
        for (u, v), f, c in zip(q, rng.integers(0, n_frames, q.shape[0]), rng.integers(0, C, q.shape[0])):
            j = kern._nearest_blob(ix.cells, ix.x0, ix.scale, ix.order_x, ix.uv_x,
                                   c * n_frames + f, u, v, gate)
            cand = np.flatnonzero((frame == f) & (cam == c))
            d = np.hypot(uv[cand, 0] - u, uv[cand, 1] - v)
            expect = cand[np.argmin(d)] if d.size and d.min() < gate else -1
            assert j == expect


def test_lex_order_is_numpy_lexsort():
    """The natural merge sort of candidate rows orders them as np.lexsort (stable), for rows
    presorted, shuffled, with duplicates and with -1 entries."""
    rng = np.random.default_rng(1)
    for trial in range(400):
        m, C = int(rng.integers(0, 120)), int(rng.integers(1, 7))
        views = rng.integers(-1, int(rng.integers(1, 6)), size=(m, C))
        if trial % 3 == 0 and m:  # mostly in order, as a pair's candidates come
            views = views[np.lexsort(views.T[::-1])]
            views[rng.integers(0, m, 3)] = rng.integers(-1, 3, C)
        np.testing.assert_array_equal(kern.lex_order(views), np.lexsort(views.T[::-1]))


def test_band_sort_and_lookup_are_sort_and_searchsorted():
    """The epipolar-angle keys' counting sort and band lookup against np.sort and
    np.searchsorted, with ties, a single key and a NaN key."""
    rng = np.random.default_rng(2)
    for n in (1, 2, 5, 17, 130):
        for trial in range(40):
            keys = np.round(rng.uniform(0, 12, n), int(rng.integers(0, 3)))
            if trial == 0 and n > 2:
                keys[1] = np.nan
            k, idx = keys.copy(), np.arange(n)
            start = np.empty(n + 1, np.int64)
            lo, scale = kern._band_sort(k, idx, n, np.empty(n), np.empty(n, np.int64), start)
            np.testing.assert_array_equal(k, np.sort(keys))
            np.testing.assert_array_equal(keys[idx], k)
            for x in np.concatenate([keys, keys + 1e-9, keys - 1e-9, [-3.0, 40.0, np.nan]]):
                assert kern._first_at_least(k, n, start, lo, scale, x) == np.searchsorted(k, x)


def test_frame_order_is_a_stable_argsort_of_the_kept_rows():
    rng = np.random.default_rng(3)
    for _ in range(200):
        m = int(rng.integers(0, 300))
        frame = rng.integers(0, int(rng.choice([3, 50, 10**6])), m) + int(rng.integers(-5, 1000))
        keep = rng.random(m) < rng.random()
        np.testing.assert_array_equal(kern.frame_order(frame, keep),
                                      np.flatnonzero(keep)[np.argsort(frame[keep], kind="stable")])


@pytest.mark.parametrize("take", ["rest", "du04_t01"])
def test_compiled_linking_matches_reference(small_sim, small_run, take):
    rig, quality = small_run.calibration.rig, small_run.calibration.quality
    pts = reconstruct_points(read_take(small_sim, take), rig, quality)
    perm = np.random.default_rng(1).permutation(len(pts))
    for s in (LabelSettings(), LabelSettings(link_gate_mm=0.2, max_gap_frames=2)):
        for order in (np.arange(len(pts)), perm):
            f, X = pts.frame[order] + 7, pts.X[order]
            np.testing.assert_array_equal(link_tracklets(f, X, s), link_tracklets_reference(f, X, s))


def test_empty_take():
    from mocap.calib.camera import Camera, CameraRig

    rig = CameraRig.of(Camera.look_at(f"c{i}", (300.0 * i, 0, -800), (0, 0, 0), width=640,
                                      height=480, focal_px=800.0) for i in range(3))
    blobs = pd.DataFrame({"frame": np.zeros(0, np.int64), "camera": np.zeros(0, str),
                          "x": np.zeros(0), "y": np.zeros(0)})
    pts = reconstruct_points(blobs, rig)
    assert len(pts) == 0 and pts.blob.shape == (0, 3)
    assert link_tracklets(pts.frame, pts.X).size == 0


@pytest.mark.parametrize("dtype", ["str", object, "category", "string[pyarrow]"])
def test_blob_camera_index_matches_camera_index(dtype):
    from mocap.calib.camera import camera_index
    from mocap.reconstruction.correspondence import blob_camera_index

    ids = ["cam1", "cam2", "cam3"]
    values = pd.Series(["cam2", "cam1", "camX", "cam3", "cam2", None], dtype=dtype)
    got = blob_camera_index(values, ids)
    np.testing.assert_array_equal(got, camera_index(values, ids))
    np.testing.assert_array_equal(got, [1, 0, -1, 2, 1, -1])
