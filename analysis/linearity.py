"""Spatial linearity (METHOD.md): the share of variance of the first principal component of all
positions of a marker over a take, all trials pooled. 1 for a straight path; noise and curved
paths lower it.

``spatial_linearity(P, noise)`` is the noise-corrected linearity, an estimate of the linearity of
the noise-free path: the noise covariance is subtracted from the positions' covariance, and the
first eigenvalue's share of the trace taken without flooring any eigenvalue (the corrected
covariance is unbiased; flooring the small eigenvalues at 0 would turn the noise of the noise
estimate into a bias towards lower linearity). It can leave [0, 1] by that noise where a marker
barely moves.

The noise covariance is best measured in the take itself (:func:`step_noise_covariance`): in a
static-response take the face is at rest within each command step, so each trial's positions
scatter about their own step mean by the noise alone, whatever the noise's size and shape in
that part of the face and capture volume. A separate rest take also measures it, but over a few
hundred frames and in one pose: its per-marker error (and any change of the noise as a marker
moves) left the corrected linearity 0.001-0.005 low on the paper preset.
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


def step_noise_covariance(trials: np.ndarray, command: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-marker noise covariance from the scatter within command steps.

    trials : (n_trials, n_frames, n_markers, 3) mm; command : (n_frames,). Each trial's positions
    in each run of constant command are taken about their own mean; the pooled sum of squares
    over the degrees of freedom left (samples less one per non-empty run and trial) is unbiased
    for white noise when the true position is constant within a step (the static response;
    motion within a step, e.g. a lag, would count as noise). Returns (cov (n_markers, 3, 3)
    mm^2, dof (n_markers,)).
    """
    X = np.asarray(trials, float)
    c = np.asarray(command)
    start = np.r_[0, np.flatnonzero(np.diff(c) != 0) + 1]
    length = np.diff(np.r_[start, c.size])
    ok = np.all(np.isfinite(X), axis=-1)  # (K, n, M)
    Z = np.where(ok[..., None], X, 0.0)
    sums = np.add.reduceat(Z, start, axis=1)
    counts = np.add.reduceat(ok.astype(float), start, axis=1)
    mean = sums / np.maximum(counts, 1)[..., None]
    R = np.where(ok[..., None], Z - np.repeat(mean, length, axis=1), 0.0)
    dof = ok.sum(axis=(0, 1)) - (counts > 0).sum(axis=(0, 1))
    cov = np.einsum("ktmi,ktmj->mij", R, R) / np.maximum(dof, 1)[:, None, None]
    return cov, dof


def spatial_linearity(P: np.ndarray, noise: np.ndarray | float | None = None) -> np.ndarray:
    """(n_markers,) first principal component's share of variance (NaN below 3 samples).

    In [0, 1] without ``noise``. ``noise`` makes it the noise-corrected linearity (module
    docstring): either a noise covariance per marker (n_markers, 3, 3) mm^2, subtracted from the
    position covariance before the eigen-decomposition (exact for anisotropic triangulation
    noise), or an isotropic variance (scalar or (n_markers,)) subtracted from every principal
    variance; NaN where the corrected total variance is not positive.
    """
    cov, n = position_covariance(P)
    noise_arr = None if noise is None else np.asarray(noise, float)
    if noise_arr is not None and noise_arr.ndim == 3:
        cov = cov - noise_arr
    lam = np.linalg.eigvalsh(cov)  # ascending
    if noise_arr is not None and noise_arr.ndim < 3:
        lam = lam - np.broadcast_to(noise_arr, n.shape)[:, None]
    total = lam.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        lin = lam[:, -1] / total
    return np.where((n >= 3) & (total > 0), lin, np.nan)
