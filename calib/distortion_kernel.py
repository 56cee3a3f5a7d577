"""Compiled (numba) Brown-Conrady distortion: projection to pixels and its inverse on blocks.

The operations are those of :func:`mocap.calib.camera.distort_normalized`,
:func:`mocap.calib.camera.undistort_normalized` and :meth:`mocap.calib.camera.Camera.project`, in
the same order (no fast-math, no fused multiply-add), so both give the same numbers; the tests
compare them. Used by the fused triangulation (:mod:`mocap.calib.triangulation_kernel`) and by the
correspondence search (:mod:`mocap.reconstruction.correspondence_kernel`).

Undistortion runs on blocks of points held in small contiguous buffers: the fixed-point round
is then a loop without branches over the block, which LLVM vectorises (4 to 8 points per
instruction), and a round that leaves the whole block unchanged ends the iteration early (every
further round would compute the same numbers again). Kernels are compiled on first use and
cached on disk (``cache=True``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

BLOCK = 256  # points undistorted together (buffers of a few kB: they stay in L1)


@njit(cache=True, error_model="numpy")
def undistort_buffers(B):
    """The nine (B,) work arrays of :func:`undistort_rounds`, uninitialised: x0, y0, x, y, k1,
    k2, p1, p2, k3."""
    return (np.empty(B), np.empty(B), np.empty(B), np.empty(B), np.empty(B), np.empty(B),
            np.empty(B), np.empty(B), np.empty(B))


@njit(cache=True, error_model="numpy")
def undistort_rounds(x0, y0, x, y, k1, k2, p1, p2, k3, m, iterations):
    """Fixed-point undistortion of the block's first ``m`` points, in place.

    x0, y0 (B,) distorted normalised coordinates; x, y (B,) the iterate (start: x0, y0),
    overwritten by the undistorted coordinates; k1 .. k3 (B,) each point's ``[k1, k2, p1, p2,
    k3]``. At most ``iterations`` rounds of :func:`mocap.calib.camera.undistort_normalized`'s
    update, stopping after a round that changes no point (inputs must be finite; a NaN would
    never compare equal and only costs the remaining rounds).
    """
    for _ in range(iterations):
        moved = 0
        for p in range(m):
            xp = x[p]
            yp = y[p]
            r2 = xp * xp + yp * yp
            radial = 1.0 + r2 * (k1[p] + r2 * (k2[p] + r2 * k3[p]))
            dx = 2.0 * p1[p] * xp * yp + p2[p] * (r2 + 2.0 * xp * xp)
            dy = p1[p] * (r2 + 2.0 * yp * yp) + 2.0 * p2[p] * xp * yp
            x_new = (x0[p] - dx) / radial
            y_new = (y0[p] - dy) / radial
            moved += (x_new != xp) | (y_new != yp)
            x[p] = x_new
            y[p] = y_new
        if moved == 0:
            break


@njit(cache=True, error_model="numpy")
def project_pixel(K, dist, R, t, c, X0, X1, X2):
    """World point (mm) -> distorted pixel (px) in camera c; NaN behind the camera (z <= 0).

    K (C, 3, 3) px, dist (C, 5), R (C, 3, 3), t (C, 3) mm. Same operations as
    :meth:`mocap.calib.camera.Camera.project`.
    """
    xc = X0 * R[c, 0, 0] + X1 * R[c, 0, 1] + X2 * R[c, 0, 2] + t[c, 0]
    yc = X0 * R[c, 1, 0] + X1 * R[c, 1, 1] + X2 * R[c, 1, 2] + t[c, 1]
    zc = X0 * R[c, 2, 0] + X1 * R[c, 2, 1] + X2 * R[c, 2, 2] + t[c, 2]
    if not zc > 0:
        return np.nan, np.nan
    x = xc / zc
    y = yc / zc
    k1, k2, p1, p2, k3 = dist[c, 0], dist[c, 1], dist[c, 2], dist[c, 3], dist[c, 4]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return K[c, 0, 0] * xd + K[c, 0, 1] * yd + K[c, 0, 2], K[c, 1, 1] * yd + K[c, 1, 2]


@njit(cache=True, error_model="numpy")
def undistort_pixels(uv, K, dist, iterations):
    """(N, 2) distorted pixels of one camera -> (N, 2) undistorted normalised coordinates.

    K (3, 3) px; dist (5,). Rows with a non-finite coordinate give NaN (as the NumPy reference:
    NaN in, NaN out). Same numbers as :meth:`mocap.calib.camera.Camera.normalize`.
    """
    n = uv.shape[0]
    out = np.empty((n, 2))
    B = BLOCK
    x0, y0, x, y, k1, k2, p1, p2, k3 = undistort_buffers(B)
    k1[:] = dist[0]
    k2[:] = dist[1]
    p1[:] = dist[2]
    p2[:] = dist[3]
    k3[:] = dist[4]
    bad = np.zeros(B, np.bool_)
    for s in range(0, n, B):
        m = min(B, n - s)
        for p in range(m):
            u = uv[s + p, 0]
            v = uv[s + p, 1]
            bad[p] = not (np.isfinite(u) and np.isfinite(v))
            if bad[p]:
                u = K[0, 2]
                v = K[1, 2]
            y0[p] = (v - K[1, 2]) / K[1, 1]
            x0[p] = (u - K[0, 2] - K[0, 1] * y0[p]) / K[0, 0]
            x[p] = x0[p]
            y[p] = y0[p]
        undistort_rounds(x0, y0, x, y, k1, k2, p1, p2, k3, m, iterations)
        for p in range(m):
            out[s + p, 0] = np.nan if bad[p] else x[p]
            out[s + p, 1] = np.nan if bad[p] else y[p]
    return out
