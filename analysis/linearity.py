"""Spatial linearity (METHOD.md): the share of variance of the first principal component of all
positions of a marker over a take, all trials pooled. 1 for a straight path; noise and curved
paths lower it. ``linearity_corrected`` also removes a known isotropic noise variance from every
principal variance first, estimating the linearity of the noise-free path.
"""

from __future__ import annotations

import numpy as np


def position_covariance(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """NaN-aware covariance per marker.

    P : (n_samples, n_markers, 3) positions, mm (trials and frames flattened into samples).
    Returns (cov (n_markers, 3, 3) mm^2, count (n_markers,)).
    """
    ok = np.all(np.isfinite(P), axis=-1)
    n = ok.sum(axis=0)
    Z = np.where(ok[..., None], P, 0.0)
    mean = Z.sum(axis=0) / np.maximum(n, 1)[:, None]
    D = np.where(ok[..., None], P - mean[None], 0.0)
    cov = np.einsum("smi,smj->mij", D, D) / np.maximum(n - 1, 1)[:, None, None]
    return cov, n


def spatial_linearity(P: np.ndarray, noise: np.ndarray | float | None = None) -> np.ndarray:
    """(n_markers,) first principal component's share of variance, in [0, 1] (NaN below 3 samples).

    ``noise`` makes it the noise-corrected linearity: either a noise covariance per marker
    (n_markers, 3, 3) mm^2 (e.g. of the rest take), subtracted from the position covariance
    before the eigen-decomposition (exact for anisotropic triangulation noise), or an isotropic
    variance (scalar or (n_markers,)) subtracted from every principal variance; negative
    variances are floored at 0.
    """
    cov, n = position_covariance(P)
    noise_arr = None if noise is None else np.asarray(noise, float)
    if noise_arr is not None and noise_arr.ndim == 3:
        cov = cov - noise_arr
    lam = np.linalg.eigvalsh(cov)  # ascending
    if noise_arr is not None and noise_arr.ndim < 3:
        lam = lam - np.broadcast_to(noise_arr, n.shape)[:, None]
    if noise_arr is not None:
        lam = np.clip(lam, 0, None)
    total = lam.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        lin = lam[:, -1] / total
    return np.where((n >= 3) & (total > 0), lin, np.nan)
