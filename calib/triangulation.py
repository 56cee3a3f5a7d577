"""Batched multi-view triangulation: a linear (DLT) solution refined by Gauss-Newton.

Observations are given per camera as ``uv`` (n_cameras, n_points, 2) distorted pixels with NaN
where a camera has no observation. :func:`triangulate` runs the fused compiled kernel
(``triangulation_kernel``); the NumPy functions here are its reference. Each point is solved from all its observing cameras at once
(no pairwise fusion, no dropped views): the linear solution minimises the algebraic error in
undistorted normalised coordinates, then ``iterations`` Gauss-Newton steps minimise the
reprojection error, each camera's normalised residual weighted by its focal length (so the
objective is in pixels up to the lens distortion's local scale, a few per cent at most). One
step from the linear solution already reaches the Cramer-Rao bound at these noise levels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocap.calib.camera import CameraRig


@dataclass(frozen=True)
class Triangulated:
    """Triangulated points.

    Attributes
    ----------
    X : (n_points, 3) world mm; NaN where fewer than ``min_cameras`` observed the point.
    n_cameras : (n_points,) int, cameras that observed the point.
    residual_px : (n_points,) RMS over its cameras of the reprojection error norm, px (NaN when
        not triangulated).
    """

    X: np.ndarray
    n_cameras: np.ndarray
    residual_px: np.ndarray


def normalized_observations(rig: CameraRig, uv: np.ndarray) -> np.ndarray:
    """(n_cameras, n_points, 2) px -> undistorted normalised coordinates (NaN kept)."""
    return np.stack([cam.normalize(uv[i]) for i, cam in enumerate(rig)])


def linear_triangulation(Rt: np.ndarray, xn: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares DLT in inhomogeneous form.

    Parameters
    ----------
    Rt : (n_cameras, 3, 4) ``[R | t]`` of each camera.
    xn : (n_cameras, n_points, 2) undistorted normalised coordinates, NaN = not observed.
    weights : optional (n_cameras,) weights (e.g. focal lengths).

    Returns
    -------
    (n_points, 3); NaN where fewer than 2 cameras observed the point.
    """
    seen = np.all(np.isfinite(xn), axis=-1)  # (C, N)
    x = np.where(seen[..., None], xn, 0.0)
    w = np.ones(Rt.shape[0]) if weights is None else np.asarray(weights, float)
    ww = (seen * (w**2)[:, None])[..., None]  # (C, N, 1)
    # rows r1 = x P3 - P1, r2 = y P3 - P2, each (C, N, 4)
    r1 = x[..., 0:1] * Rt[:, None, 2, :] - Rt[:, None, 0, :]
    r2 = x[..., 1:2] * Rt[:, None, 2, :] - Rt[:, None, 1, :]
    A = np.einsum("cni,cnj->nij", r1 * ww, r1) + np.einsum("cni,cnj->nij", r2 * ww, r2)
    M = A[:, :3, :3]
    b = -A[:, :3, 3]
    count = seen.sum(axis=0)
    X = np.full((xn.shape[1], 3), np.nan)
    ok = count >= 2
    if np.any(ok):
        X[ok] = np.linalg.solve(M[ok], b[ok][..., None])[..., 0]
    return X


def gauss_newton(Rt: np.ndarray, xn: np.ndarray, X: np.ndarray, weights: np.ndarray,
                 iterations: int = 1) -> np.ndarray:
    """Refine points X (n_points, 3) by Gauss-Newton on weighted normalised reprojection error."""
    seen = np.all(np.isfinite(xn), axis=-1)
    x = np.where(seen[..., None], xn, 0.0)
    w2 = (seen * (np.asarray(weights, float) ** 2)[:, None])  # (C, N)
    R = Rt[:, :, :3]
    t = Rt[:, :, 3]
    X = X.copy()
    good = np.all(np.isfinite(X), axis=1)
    for _ in range(iterations):
        Xc = np.einsum("cij,nj->cni", R, np.where(good[:, None], X, 0.0)) + t[:, None, :]
        z = Xc[..., 2]
        z = np.where(np.abs(z) > 1e-9, z, 1e-9)
        proj = Xc[..., :2] / z[..., None]
        r = x - proj  # (C, N, 2)
        # d proj / d Xc
        J = np.zeros(Xc.shape[:2] + (2, 3))
        J[..., 0, 0] = 1.0 / z
        J[..., 1, 1] = 1.0 / z
        J[..., 0, 2] = -Xc[..., 0] / z**2
        J[..., 1, 2] = -Xc[..., 1] / z**2
        J = np.einsum("cnij,cjk->cnik", J, R)  # d proj / d X
        H = np.einsum("cn,cnik,cnil->nkl", w2, J, J)
        g = np.einsum("cn,cnik,cni->nk", w2, J, r)
        ok = good & (np.linalg.det(H) > 1e-18)
        if not np.any(ok):
            break
        X[ok] += np.linalg.solve(H[ok], g[ok][..., None])[..., 0]
    return X


def triangulate(rig: CameraRig, uv: np.ndarray, *, min_cameras: int = 2,
                iterations: int = 1) -> Triangulated:
    """Triangulate points seen by several cameras.

    Undistortion, triangulation and reprojection residuals run fused in one compiled pass over
    blocks of points (:func:`mocap.calib.triangulation_kernel.triangulate_pixels`);
    :func:`triangulate_reference` is the same in NumPy, and both give the same numbers to
    rounding (a test checks 1e-9 mm and px under strong distortion).

    Parameters
    ----------
    rig : the calibrated cameras (n_cameras).
    uv : (n_cameras, n_points, 2) distorted pixel observations, NaN where unobserved.
    min_cameras : fewest cameras for a point to be triangulated (>= 2).
    iterations : Gauss-Newton steps after the linear solution.
    """
    if uv.ndim != 3 or uv.shape[0] != len(rig) or uv.shape[2] != 2:
        raise ValueError(f"triangulate: expected uv of shape ({len(rig)}, n_points, 2), got {uv.shape}")
    from mocap.calib.triangulation_kernel import triangulate_pixels

    X, n_cam, residual = triangulate_pixels(rig, uv, min_cameras=max(int(min_cameras), 2),
                                            iterations=iterations)
    return Triangulated(X=X, n_cameras=n_cam, residual_px=residual)


def triangulate_reference(rig: CameraRig, uv: np.ndarray, *, min_cameras: int = 2,
                          iterations: int = 1) -> Triangulated:
    """:func:`triangulate` step by step in NumPy (the reference the compiled path is tested
    against): undistortion per camera, linear solution, Gauss-Newton, reprojection residuals."""
    min_cameras = max(int(min_cameras), 2)
    xn = normalized_observations(rig, uv)
    Rt = np.stack([np.hstack([c.R, c.t[:, None]]) for c in rig])
    f = np.array([c.focal_px for c in rig])
    X = gauss_newton(Rt, xn, linear_triangulation(Rt, xn, f), f, iterations)
    seen = np.all(np.isfinite(uv), axis=-1)
    n_cam = seen.sum(axis=0)
    X[n_cam < min_cameras] = np.nan
    residual = reprojection_rms(rig, X, uv)
    return Triangulated(X=X, n_cameras=n_cam, residual_px=residual)


def reprojection_errors(rig: CameraRig, X: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(n_cameras, n_points) reprojection error norm, px (NaN where unobserved)."""
    proj = rig.project(X)  # (C, N, 2)
    return np.linalg.norm(proj - uv, axis=-1)


def reprojection_rms(rig: CameraRig, X: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(n_points,) RMS over observing cameras of the reprojection error norm, px."""
    e2 = reprojection_errors(rig, X, uv) ** 2
    seen = np.isfinite(e2)
    count = seen.sum(axis=0)
    total = np.where(seen, e2, 0.0).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, np.sqrt(total / count), np.nan)
