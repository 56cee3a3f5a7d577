"""Compiled (numba) triangulation: linear solution plus Gauss-Newton, on blocks of points.

Same mathematics as :func:`mocap.calib.triangulation.linear_triangulation` followed by
:func:`mocap.calib.triangulation.gauss_newton` (the NumPy reference the tests compare against).
Points are solved a block at a time as structure-of-arrays loops (``solve_block``), so every
loop over points vectorises; blocks run in parallel for large calls on more than one thread and
on the calling thread otherwise (``PARALLEL_MIN_POINTS``; the same block function either way, so
the same bits). ``triangulate_pixels_kernel`` fuses the
undistortion of distorted pixels (:mod:`mocap.calib.distortion_kernel`), the solution and the
reprojection residuals in one pass: what :func:`mocap.calib.triangulation.triangulate` runs.
Kernels are compiled on first use and cached on disk (``cache=True``); ``error_model="numpy"``
(a division by zero gives inf or NaN, as in NumPy, instead of raising) is what lets LLVM
vectorise loops that divide. Camera weights must be positive.

The parallel kernels run on numba's OpenMP threads, which by default spin-wait between parallel
regions: on a machine whose cores are busy (other jobs, our own worker processes) a kernel called
on a take's few thousand points then waits for the spinning threads' time slices, 15.8 ms a call
instead of 0.23 ms (measured on a loaded 2-core machine). Importing this module sets
``OMP_WAIT_POLICY=PASSIVE`` unless the user set it (libgomp reads it when numba first loads it):
the idle threads sleep instead, at no cost on a quiet machine.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
from numba import get_num_threads, njit, prange  # noqa: E402

from mocap.calib.distortion_kernel import (  # noqa: E402
    BLOCK,
    undistort_buffers,
    undistort_rounds,
)


@njit(cache=True, error_model="numpy")
def _solve3_block(a00, a01, a02, a11, a12, a22, b0, b1, b2, m, x0, x1, x2):
    """Solve the symmetric 3x3 systems [[a00, a01, a02], [., a11, a12], [., ., a22]] x = b of the
    first ``m`` entries of (B,) arrays by Cramer's rule, into x0, x1, x2 (B,); NaN where
    singular (|det| < 1e-300)."""
    for p in range(m):
        c00 = a11[p] * a22[p] - a12[p] * a12[p]
        c01 = a02[p] * a12[p] - a01[p] * a22[p]
        c02 = a01[p] * a12[p] - a02[p] * a11[p]
        det = a00[p] * c00 + a01[p] * c01 + a02[p] * c02
        c11 = a00[p] * a22[p] - a02[p] * a02[p]
        c12 = a01[p] * a02[p] - a00[p] * a12[p]
        c22 = a00[p] * a11[p] - a01[p] * a01[p]
        s0 = (c00 * b0[p] + c01 * b1[p] + c02 * b2[p]) / det
        s1 = (c01 * b0[p] + c11 * b1[p] + c12 * b2[p]) / det
        s2 = (c02 * b0[p] + c12 * b1[p] + c22 * b2[p]) / det
        singular = abs(det) < 1e-300
        x0[p] = np.nan if singular else s0
        x1[p] = np.nan if singular else s1
        x2[p] = np.nan if singular else s2


@njit(cache=True, error_model="numpy")
def solve_block(Rt, xb, yb, wb, m, iterations, X0, X1, X2):
    """Triangulate the first ``m`` points of a block: the weighted linear solution (DLT normal
    equations), then ``iterations`` Gauss-Newton steps on the weighted normalised residuals.

    Rt (C, 3, 4); xb, yb (C, B) undistorted normalised coordinates (any finite value where
    unobserved); wb (C, B) the camera's squared weight where observed, 0 where not. Writes
    X0, X1, X2 (B,) mm: NaN below two views or for a singular system. The mathematics of the
    NumPy reference (:func:`mocap.calib.triangulation.linear_triangulation`,
    :func:`~mocap.calib.triangulation.gauss_newton`) per point; laid out over the block's points
    (structure of arrays, unobserved views masked by their zero weight instead of a branch) so
    every loop over points vectorises.
    """
    C = Rt.shape[0]
    B = X0.shape[0]
    # linear solution: the normal equations of the DLT rows, accumulated camera by camera
    a00 = np.zeros(B)
    a01 = np.zeros(B)
    a02 = np.zeros(B)
    a11 = np.zeros(B)
    a12 = np.zeros(B)
    a22 = np.zeros(B)
    b0 = np.zeros(B)
    b1 = np.zeros(B)
    b2 = np.zeros(B)
    used = np.zeros(B, np.int64)
    for c in range(C):
        for p in range(m):
            used[p] += wb[c, p] != 0.0
        for row in range(2):
            q0, q1, q2, q3 = Rt[c, 2, 0], Rt[c, 2, 1], Rt[c, 2, 2], Rt[c, 2, 3]
            s0, s1, s2, s3 = Rt[c, row, 0], Rt[c, row, 1], Rt[c, row, 2], Rt[c, row, 3]
            for p in range(m):
                u = xb[c, p] if row == 0 else yb[c, p]
                w2 = wb[c, p]
                r0 = u * q0 - s0
                r1 = u * q1 - s1
                r2 = u * q2 - s2
                r3 = u * q3 - s3
                a00[p] += w2 * r0 * r0
                a01[p] += w2 * r0 * r1
                a02[p] += w2 * r0 * r2
                a11[p] += w2 * r1 * r1
                a12[p] += w2 * r1 * r2
                a22[p] += w2 * r2 * r2
                b0[p] -= w2 * r0 * r3
                b1[p] -= w2 * r1 * r3
                b2[p] -= w2 * r2 * r3
    _solve3_block(a00, a01, a02, a11, a12, a22, b0, b1, b2, m, X0, X1, X2)
    for p in range(m):
        few = used[p] < 2
        X0[p] = np.nan if few else X0[p]
        X1[p] = np.nan if few else X1[p]
        X2[p] = np.nan if few else X2[p]
    d0 = np.empty(B)
    d1 = np.empty(B)
    d2 = np.empty(B)
    for _ in range(iterations):  # Gauss-Newton on the focal-weighted normalised residuals
        a00[:] = 0.0
        a01[:] = 0.0
        a02[:] = 0.0
        a11[:] = 0.0
        a12[:] = 0.0
        a22[:] = 0.0
        b0[:] = 0.0
        b1[:] = 0.0
        b2[:] = 0.0
        for c in range(C):
            r00, r01, r02, r03 = Rt[c, 0, 0], Rt[c, 0, 1], Rt[c, 0, 2], Rt[c, 0, 3]
            r10, r11, r12, r13 = Rt[c, 1, 0], Rt[c, 1, 1], Rt[c, 1, 2], Rt[c, 1, 3]
            r20, r21, r22, r23 = Rt[c, 2, 0], Rt[c, 2, 1], Rt[c, 2, 2], Rt[c, 2, 3]
            for p in range(m):
                xc = r00 * X0[p] + r01 * X1[p] + r02 * X2[p] + r03
                yc = r10 * X0[p] + r11 * X1[p] + r12 * X2[p] + r13
                zc = r20 * X0[p] + r21 * X1[p] + r22 * X2[p] + r23
                near = abs(zc) < 1e-9  # (False for NaN: a NaN point stays NaN)
                w2 = 0.0 if near else wb[c, p]
                iz = 0.0 if near else 1.0 / zc
                ex = xb[c, p] - xc * iz
                ey = yb[c, p] - yc * iz
                j00 = iz * r00 - xc * iz * iz * r20
                j01 = iz * r01 - xc * iz * iz * r21
                j02 = iz * r02 - xc * iz * iz * r22
                j10 = iz * r10 - yc * iz * iz * r20
                j11 = iz * r11 - yc * iz * iz * r21
                j12 = iz * r12 - yc * iz * iz * r22
                a00[p] += w2 * (j00 * j00 + j10 * j10)
                a01[p] += w2 * (j00 * j01 + j10 * j11)
                a02[p] += w2 * (j00 * j02 + j10 * j12)
                a11[p] += w2 * (j01 * j01 + j11 * j11)
                a12[p] += w2 * (j01 * j02 + j11 * j12)
                a22[p] += w2 * (j02 * j02 + j12 * j12)
                b0[p] += w2 * (j00 * ex + j10 * ey)
                b1[p] += w2 * (j01 * ex + j11 * ey)
                b2[p] += w2 * (j02 * ex + j12 * ey)
        _solve3_block(a00, a01, a02, a11, a12, a22, b0, b1, b2, m, d0, d1, d2)
        for p in range(m):
            step = d0[p] == d0[p]
            X0[p] = X0[p] + d0[p] if step else X0[p]
            X1[p] = X1[p] + d1[p] if step else X1[p]
            X2[p] = X2[p] + d2[p] if step else X2[p]


@njit(cache=True, error_model="numpy")
def _normalized_block(Rt, weights, xn, iterations, out, blk):
    """Block ``blk`` of :func:`triangulate_kernel` (points blk * BLOCK onwards)."""
    C = xn.shape[0]
    N = xn.shape[1]
    B = BLOCK
    s = blk * B
    m = min(B, N - s)
    xb = np.empty((C, B))
    yb = np.empty((C, B))
    wb = np.empty((C, B))
    for c in range(C):
        w2 = weights[c] * weights[c]
        for p in range(m):
            x = xn[c, s + p, 0]
            y = xn[c, s + p, 1]
            seen = x == x and y == y
            xb[c, p] = x if seen else 0.0
            yb[c, p] = y if seen else 0.0
            wb[c, p] = w2 if seen else 0.0
    X0 = np.empty(B)
    X1 = np.empty(B)
    X2 = np.empty(B)
    solve_block(Rt, xb, yb, wb, m, iterations, X0, X1, X2)
    for p in range(m):
        out[s + p, 0] = X0[p]
        out[s + p, 1] = X1[p]
        out[s + p, 2] = X2[p]


@njit(cache=True, parallel=True, fastmath=False, error_model="numpy")
def triangulate_kernel(Rt, weights, xn, iterations, out):
    """Rt (C, 3, 4); weights (C,); xn (C, N, 2) undistorted normalised, NaN = unobserved;
    out (N, 3) mm written (NaN below two views). Blocks of points run in parallel."""
    n_blocks = (xn.shape[1] + BLOCK - 1) // BLOCK
    for blk in prange(n_blocks):
        _normalized_block(Rt, weights, xn, iterations, out, blk)


@njit(cache=True, error_model="numpy")
def triangulate_kernel_serial(Rt, weights, xn, iterations, out):
    """:func:`triangulate_kernel` on the calling thread (no parallel region to compile or
    enter)."""
    n_blocks = (xn.shape[1] + BLOCK - 1) // BLOCK
    for blk in range(n_blocks):
        _normalized_block(Rt, weights, xn, iterations, out, blk)


@njit(cache=True, error_model="numpy")
def _pixels_block(K, dist, R, t, Rt, weights, uv, iterations, undistort_iterations, min_cameras,
                  X, n_cam, resid, blk):
    """Block ``blk`` of :func:`triangulate_pixels_kernel` (points blk * BLOCK onwards)."""
    C = uv.shape[0]
    N = uv.shape[1]
    B = BLOCK
    s = blk * B
    m = min(B, N - s)
    xb = np.empty((C, B))  # undistorted normalised, 0 where unobserved
    yb = np.empty((C, B))
    wb = np.empty((C, B))  # the camera's squared weight where observed, else 0
    ub = np.empty((C, B))  # the pixels, 0 where unobserved
    vb = np.empty((C, B))
    x0, y0, x, y, k1, k2, p1, p2, k3 = undistort_buffers(B)
    views = np.zeros(B, np.int64)
    for c in range(C):
        k1[:] = dist[c, 0]
        k2[:] = dist[c, 1]
        p1[:] = dist[c, 2]
        p2[:] = dist[c, 3]
        k3[:] = dist[c, 4]
        for p in range(m):
            u = uv[c, s + p, 0]
            v = uv[c, s + p, 1]
            seen = np.isfinite(u) and np.isfinite(v)
            views[p] += seen
            ub[c, p] = u if seen else 0.0
            vb[c, p] = v if seen else 0.0
            # a neutral value keeps the block's loops free of NaN
            u = u if seen else K[c, 0, 2]
            v = v if seen else K[c, 1, 2]
            y0[p] = (v - K[c, 1, 2]) / K[c, 1, 1]
            x0[p] = (u - K[c, 0, 2] - K[c, 0, 1] * y0[p]) / K[c, 0, 0]
            x[p] = x0[p]
            y[p] = y0[p]
            wb[c, p] = weights[c] * weights[c] if seen else 0.0
        undistort_rounds(x0, y0, x, y, k1, k2, p1, p2, k3, m, undistort_iterations)
        for p in range(m):
            ok = wb[c, p] != 0.0 and np.isfinite(x[p]) and np.isfinite(y[p])
            xb[c, p] = x[p] if ok else 0.0
            yb[c, p] = y[p] if ok else 0.0
            wb[c, p] = wb[c, p] if ok else 0.0
    X0 = np.empty(B)
    X1 = np.empty(B)
    X2 = np.empty(B)
    solve_block(Rt, xb, yb, wb, m, iterations, X0, X1, X2)
    for p in range(m):
        few = views[p] < min_cameras
        X0[p] = np.nan if few else X0[p]
        X1[p] = np.nan if few else X1[p]
        X2[p] = np.nan if few else X2[p]
    # reprojection residuals: project_pixel's operations, per camera over the block
    total = np.zeros(B)
    count = np.zeros(B, np.int64)
    for c in range(C):
        r00, r01, r02, r03 = R[c, 0, 0], R[c, 0, 1], R[c, 0, 2], t[c, 0]
        r10, r11, r12, r13 = R[c, 1, 0], R[c, 1, 1], R[c, 1, 2], t[c, 1]
        r20, r21, r22, r23 = R[c, 2, 0], R[c, 2, 1], R[c, 2, 2], t[c, 2]
        c1, c2, c3, c4, c5 = dist[c, 0], dist[c, 1], dist[c, 2], dist[c, 3], dist[c, 4]
        fx, sk, cx, fy, cy = K[c, 0, 0], K[c, 0, 1], K[c, 0, 2], K[c, 1, 1], K[c, 1, 2]
        for p in range(m):
            xc = X0[p] * r00 + X1[p] * r01 + X2[p] * r02 + r03
            yc = X0[p] * r10 + X1[p] * r11 + X2[p] * r12 + r13
            zc = X0[p] * r20 + X1[p] * r21 + X2[p] * r22 + r23
            xx = xc / zc
            yy = yc / zc
            r2 = xx * xx + yy * yy
            radial = 1.0 + r2 * (c1 + r2 * (c2 + r2 * c5))
            xd = xx * radial + 2.0 * c3 * xx * yy + c4 * (r2 + 2.0 * xx * xx)
            yd = yy * radial + c3 * (r2 + 2.0 * yy * yy) + 2.0 * c4 * xx * yy
            du = fx * xd + sk * yd + cx - ub[c, p]
            dv = fy * yd + cy - vb[c, p]
            e2 = du * du + dv * dv
            # behind the camera (z <= 0, or NaN) or unobserved: not counted
            ok = zc > 0 and wb[c, p] != 0.0 and np.isfinite(e2)
            total[p] += e2 if ok else 0.0
            count[p] += ok
    for p in range(m):
        n = s + p
        X[n, 0] = X0[p]
        X[n, 1] = X1[p]
        X[n, 2] = X2[p]
        n_cam[n] = views[p]
        resid[n] = np.sqrt(total[p] / count[p]) if count[p] > 0 else np.nan


@njit(cache=True, parallel=True, fastmath=False, error_model="numpy")
def triangulate_pixels_kernel(K, dist, R, t, Rt, weights, uv, iterations, undistort_iterations,
                              min_cameras, X, n_cam, resid):
    """Undistortion, triangulation and reprojection residuals fused, per block of points.

    K (C, 3, 3) px, dist (C, 5), R (C, 3, 3), t (C, 3) mm, Rt (C, 3, 4), weights (C,);
    uv (C, N, 2) distorted px, non-finite = unobserved. Writes X (N, 3) mm (NaN below
    ``min_cameras`` views), n_cam (N,) the views with finite pixels, resid (N,) px the RMS over
    the views of the distance between pixel and reprojection (views behind the camera left out;
    NaN when none is left or X is NaN).

    The arithmetic per point is :func:`solve_block`'s and
    :func:`mocap.calib.distortion_kernel.project_pixel`'s, operation for operation, laid out over
    the block's points so every loop over points vectorises. Blocks run in parallel.
    """
    n_blocks = (uv.shape[1] + BLOCK - 1) // BLOCK
    for blk in prange(n_blocks):
        _pixels_block(K, dist, R, t, Rt, weights, uv, iterations, undistort_iterations,
                      min_cameras, X, n_cam, resid, blk)


@njit(cache=True, error_model="numpy")
def triangulate_pixels_kernel_serial(K, dist, R, t, Rt, weights, uv, iterations,
                                     undistort_iterations, min_cameras, X, n_cam, resid):
    """:func:`triangulate_pixels_kernel` on the calling thread (no parallel region to compile or
    enter)."""
    n_blocks = (uv.shape[1] + BLOCK - 1) // BLOCK
    for blk in range(n_blocks):
        _pixels_block(K, dist, R, t, Rt, weights, uv, iterations, undistort_iterations,
                      min_cameras, X, n_cam, resid, blk)


# Below this many points a call runs on the calling thread: the parallel kernels' gain there is
# a few milliseconds, and a run that never calls them above it (the sample session; every
# reconstruction worker, which runs one thread) never compiles them (about 3-4 CPU-s each,
# cold). The results do not depend on the choice: both run the same block function per point.
PARALLEL_MIN_POINTS = 65_536


def _parallel(n_points: int) -> bool:
    return n_points >= PARALLEL_MIN_POINTS and get_num_threads() > 1


def triangulate_normalized(Rt: np.ndarray, weights: np.ndarray, xn: np.ndarray,
                           iterations: int = 1) -> np.ndarray:
    """(C, N, 2) undistorted normalised observations -> (N, 3); NaN below two views."""
    out = np.empty((xn.shape[1], 3))
    kernel = triangulate_kernel if _parallel(xn.shape[1]) else triangulate_kernel_serial
    kernel(np.ascontiguousarray(Rt, dtype=np.float64),
           np.ascontiguousarray(weights, dtype=np.float64),
           np.ascontiguousarray(xn, dtype=np.float64), int(iterations), out)
    return out


UNDISTORT_ITERATIONS = 20  # as mocap.calib.camera.undistort_normalized


def triangulate_pixels(rig, uv: np.ndarray, *, min_cameras: int = 2, iterations: int = 1,
                       undistort_iterations: int = UNDISTORT_ITERATIONS):
    """Distorted pixels (C, N, 2) of the cameras of ``rig`` (NaN = unobserved) -> X (N, 3) mm,
    n_cameras (N,) int, residual_px (N,) px: :func:`mocap.calib.triangulation.triangulate`'s
    arrays, from one fused compiled pass (see ``triangulate_pixels_kernel``)."""
    uv = np.ascontiguousarray(uv, dtype=np.float64)
    C, N = uv.shape[0], uv.shape[1]
    K = np.ascontiguousarray(np.stack([c.K for c in rig]), dtype=np.float64)
    dist = np.ascontiguousarray(np.stack([c.dist for c in rig]), dtype=np.float64)
    if dist.shape != (C, 5):
        raise ValueError(f"triangulate_pixels: expected [k1, k2, p1, p2, k3] per camera, got "
                         f"distortion of shape {dist.shape}")
    R = np.ascontiguousarray(np.stack([c.R for c in rig]), dtype=np.float64)
    t = np.ascontiguousarray(np.stack([c.t for c in rig]), dtype=np.float64)
    Rt = np.ascontiguousarray(np.concatenate([R, t[:, :, None]], axis=2))
    f = np.array([c.focal_px for c in rig], np.float64)
    X = np.empty((N, 3))
    n_cam = np.empty(N, np.int64)
    resid = np.empty(N)
    if N:
        kernel = triangulate_pixels_kernel if _parallel(N) else triangulate_pixels_kernel_serial
        kernel(K, dist, R, t, Rt, f, uv, int(iterations), int(undistort_iterations),
               max(int(min_cameras), 2), X, n_cam, resid)
    return X, n_cam, resid
