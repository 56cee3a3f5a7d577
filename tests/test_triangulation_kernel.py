"""The compiled undistortion and the fused triangulation against their NumPy references and
against OpenCV, under strong lens distortion (all five Brown-Conrady terms)."""

import cv2
import numpy as np
import pytest

from mocap.calib.camera import Camera, CameraRig
from mocap.calib.distortion_kernel import BLOCK, undistort_pixels
from mocap.calib.triangulation import triangulate, triangulate_reference

STRONG = [(-0.30, 0.12, 0.0015, -0.0010, -0.020), (-0.22, 0.08, -0.0020, 0.0012, 0.010),
          (0.15, -0.05, 0.0008, 0.0016, 0.004), (-0.26, 0.10, 0.0, 0.0, 0.0),
          (0.05, 0.02, -0.0025, -0.0018, -0.008), (-0.18, 0.03, 0.0011, -0.0007, 0.015)]


def strong_rig(seed: int = 0) -> CameraRig:
    """Six cameras around the origin, 0.7 m away, each with strong distortion."""
    rng = np.random.default_rng(seed)
    cams = []
    for i, dist in enumerate(STRONG):
        ang = -0.9 + 0.36 * i
        centre = (700 * np.sin(ang), 120 * rng.normal(), -700 * np.cos(ang))
        cams.append(Camera.look_at(f"c{i}", centre, (0, 0, 0), width=1280, height=1024,
                                   focal_px=1150 + 40 * i, principal=(640 + 5 * i, 510 - 3 * i),
                                   dist=dist))
    return CameraRig.of(cams)


def observations(rig: CameraRig, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) points and their noisy pixels (C, n, 2) with missing and broken views."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(-70, 70, (n, 3))
    uv = rig.project(X) + rng.normal(0, 0.1, (len(rig), n, 2))
    uv[rng.random((len(rig), n)) < 0.35] = np.nan  # unobserved views
    k = min(n, 12)
    uv[0, :k:3, 0] = np.inf  # a broken coordinate
    uv[1, 1:k:3, 1] = np.nan  # half a coordinate missing
    uv[2, 2:k:3] = -np.inf
    return X, uv


def assert_same(a, b, tol):
    assert np.array_equal(np.isnan(a), np.isnan(b))
    assert np.nanmax(np.abs(a - b), initial=0.0) <= tol


@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")  # the NumPy
# reference on the broken (infinite) coordinates of observations(); the kernels do not warn
@pytest.mark.parametrize("n", [0, 1, BLOCK - 1, BLOCK + 1, 3 * BLOCK + 17])
@pytest.mark.parametrize("min_cameras", [2, 3])
def test_fused_triangulation_equals_numpy_reference(n, min_cameras):
    rig = strong_rig(n)
    X, uv = observations(rig, n, seed=n + min_cameras)
    fast = triangulate(rig, uv, min_cameras=min_cameras)
    ref = triangulate_reference(rig, uv, min_cameras=min_cameras)
    np.testing.assert_array_equal(fast.n_cameras, ref.n_cameras)
    assert_same(fast.X, ref.X, 1e-9)  # mm
    assert_same(fast.residual_px, ref.residual_px, 1e-9)  # px
    if n > BLOCK:  # and it is a triangulation: the points come back within the noise
        ok = np.isfinite(fast.X[:, 0])
        assert ok.mean() > 0.5
        assert np.sqrt(np.mean(np.sum((fast.X[ok] - X[ok]) ** 2, axis=1))) < 0.3
        assert 0.02 < np.nanmedian(fast.residual_px) < 0.2


def test_gauss_newton_steps_and_points_behind_a_camera():
    from mocap.calib.camera import distort_normalized

    front = strong_rig(1)
    # a seventh camera behind the scene, looking away from it: its views of the scene are only
    # algebraic (x / z, y / z with z < 0); they enter the triangulation but not the residual
    back = Camera.look_at("back", (0, 0, 900), (0, 0, 2000), width=1280, height=1024,
                          focal_px=1200, dist=STRONG[0])
    rig = CameraRig.of([*front, back])
    rng = np.random.default_rng(5)
    X = rng.uniform(-70, 70, (700, 3))
    uv = rig.project(X)
    xc = back.world_to_camera(X)
    assert np.all(xc[:, 2] < 0) and np.all(np.isnan(uv[6]))
    xd = distort_normalized(xc[:, :2] / xc[:, 2:], back.dist)
    uv[6] = np.column_stack([back.K[0, 0] * xd[:, 0] + back.K[0, 2], back.K[1, 1] * xd[:, 1] + back.K[1, 2]])
    uv[:6][rng.random((6, 700)) < 0.5] = np.nan
    for iterations in (0, 1, 3):
        fast = triangulate(rig, uv, iterations=iterations)
        ref = triangulate_reference(rig, uv, iterations=iterations)
        np.testing.assert_array_equal(fast.n_cameras, ref.n_cameras)
        assert_same(fast.X, ref.X, 1e-9)
        assert_same(fast.residual_px, ref.residual_px, 1e-9)
    ok = fast.n_cameras >= 2
    assert np.max(np.abs(fast.X[ok] - X[ok])) < 1e-6  # noise-free views: exact
    # the back camera left out of the residual: the front views are exact, so it is ~0; with no
    # front view left there is no residual at all
    front_views = np.sum(np.isfinite(uv[:6, :, 0]), axis=0)
    assert np.nanmax(fast.residual_px[ok]) < 1e-6
    assert np.array_equal(np.isnan(fast.residual_px), ~ok | (front_views == 0))


def test_compiled_undistortion_matches_numpy_and_opencv():
    rig = strong_rig(2)
    rng = np.random.default_rng(7)
    for cam in rig:
        uv = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], (3 * BLOCK + 5, 2))
        uv[::97] = np.nan
        fast = undistort_pixels(uv, np.asarray(cam.K), np.asarray(cam.dist), 20)
        ref = cam.normalize(uv)
        assert_same(fast * cam.focal_px, ref * cam.focal_px, 1e-9)  # px
        ok = np.isfinite(uv[:, 0])
        # OpenCV's own iteration, run to convergence: an implementation independent of ours
        cv = cv2.undistortPoints(uv[ok].reshape(-1, 1, 2), np.asarray(cam.K), np.asarray(cam.dist),
                                 criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200,
                                           1e-15)).reshape(-1, 2)
        assert np.max(np.abs(fast[ok] - cv)) * cam.focal_px < 1e-9
        # and it is the inverse: distorting the result gives back the pixels
        X = np.column_stack([fast[ok], np.ones(ok.sum())]) @ cam.R + cam.center
        np.testing.assert_allclose(cam.project(X), uv[ok], atol=1e-9)


def test_distortion_of_another_shape_is_refused():
    from mocap.calib.triangulation_kernel import triangulate_pixels

    class Eight:
        def __init__(self, cam):
            self.K, self.R, self.t, self.focal_px = cam.K, cam.R, cam.t, cam.focal_px
            self.dist = np.r_[cam.dist, 0.0, 0.0, 0.0]

    rig = strong_rig(3)
    with pytest.raises(ValueError, match="k1, k2, p1, p2, k3"):
        triangulate_pixels([Eight(c) for c in rig], np.zeros((len(rig), 4, 2)))


def test_importing_the_kernels_lets_idle_threads_sleep_unless_the_user_chose():
    """The parallel kernels' OpenMP threads must not spin on busy cores (module docstring)."""
    import subprocess
    import sys

    code = ("import os; import mocap.calib.triangulation_kernel; "
            "print(os.environ['OMP_WAIT_POLICY'])")
    env = {k: v for k, v in __import__("os").environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "PASSIVE"
    env["OMP_WAIT_POLICY"] = "ACTIVE"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "ACTIVE"


@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")  # the NumPy
# reference on the broken (infinite) coordinates of observations(); the kernels do not warn
@pytest.mark.parametrize("parallel_from", [0, 10**9])
def test_parallel_and_serial_kernels_give_the_same_bits(monkeypatch, parallel_from):
    """Large calls run the blocks in parallel, small ones on the calling thread: both run the same
    block function, so the results do not depend on the choice (and both equal the reference)."""
    import numba

    from mocap.calib import triangulation_kernel as tk

    rig = strong_rig(4)
    X, uv = observations(rig, 5 * BLOCK + 3, seed=11)
    monkeypatch.setattr(tk, "PARALLEL_MIN_POINTS", parallel_from)
    previous = numba.get_num_threads()
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    try:
        fast = triangulate(rig, uv, min_cameras=2)
        xn = np.stack([c.normalize(uv[i]) for i, c in enumerate(rig)])
        Rt = np.stack([np.hstack([c.R, c.t[:, None]]) for c in rig])
        f = np.array([c.focal_px for c in rig])
        norm = tk.triangulate_normalized(Rt, f, xn, 1)
    finally:
        numba.set_num_threads(previous)
    ref = triangulate_reference(rig, uv, min_cameras=2)
    assert_same(fast.X, ref.X, 1e-9)
    assert_same(fast.residual_px, ref.residual_px, 1e-9)
    # the other kernel, called directly, gives the same bits
    args = [np.ascontiguousarray(a, dtype=np.float64) for a in (
        np.stack([c.K for c in rig]), np.stack([c.dist for c in rig]), np.stack([c.R for c in rig]),
        np.stack([c.t for c in rig]), Rt, f, uv)]
    N = uv.shape[1]
    other = tk.triangulate_pixels_kernel_serial if parallel_from == 0 else tk.triangulate_pixels_kernel
    Xo, no, ro = np.empty((N, 3)), np.empty(N, np.int64), np.empty(N)
    other(*args, 1, tk.UNDISTORT_ITERATIONS, 2, Xo, no, ro)
    np.testing.assert_array_equal(Xo, fast.X)
    np.testing.assert_array_equal(ro, fast.residual_px)
    np.testing.assert_array_equal(no, fast.n_cameras)
    other_n = tk.triangulate_kernel_serial if parallel_from == 0 else tk.triangulate_kernel
    out = np.empty((N, 3))
    other_n(Rt, f, np.ascontiguousarray(xn), 1, out)
    np.testing.assert_array_equal(out, norm)
