"""Displacement vectors and their normalisation (METHOD.md, "Spatial properties").

d_m(t) = v_m(t) - v_m(0); delta_m(t) = |d_m(t)| / max_t |d_m(t)| (``normalized``), and the
noise-unbiased variant along each marker's principal direction (``normalized_along``). The maximum is taken on the
displacement averaged over a centred window (``smooth_frames``) so that the noise's largest
excursion does not set the scale (an unsmoothed maximum over hundreds of noisy frames sits a few
noise sigmas above the true plateau, which would pull the whole normalised curve down).
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.ndimage import convolve1d


def smoothed(d: np.ndarray, frames: int) -> np.ndarray:
    """NaN-aware centred moving average along axis 0 of d (n_frames, ...)."""
    if frames <= 1:
        return d
    ok = np.isfinite(d)
    k = np.ones(int(frames))
    num = convolve1d(np.where(ok, d, 0.0), k, axis=0, mode="nearest")
    den = convolve1d(ok.astype(float), k, axis=0, mode="nearest")
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / den, np.nan)


def peak_length(d: np.ndarray, frames: int) -> np.ndarray:
    """(M,) max over frames of |smoothed d| for displacement vectors d (n_frames, M, 3)."""
    s = np.linalg.norm(smoothed(d, frames), axis=-1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmax(np.where(np.isfinite(s), s, -np.inf), axis=0)


def principal_direction(d: np.ndarray) -> np.ndarray:
    """(M, 3) unit first principal axis of each marker's displacements d (n_frames, M, 3), signed
    so that the largest displacement projects positively (the direction the DU pushes)."""
    ok = np.isfinite(d[..., 0])
    Z = np.where(ok[..., None], d, 0.0)
    cov = np.einsum("fmi,fmj->mij", Z, Z) / np.maximum(ok.sum(axis=0), 1)[:, None, None]
    _, vec = np.linalg.eigh(cov)
    u = vec[..., -1]
    far = np.argmax(np.where(ok, np.linalg.norm(Z, axis=-1), -1.0), axis=0)
    sign = np.sign(np.einsum("mk,mk->m", Z[far, np.arange(d.shape[1])], u))
    return u * np.where(sign == 0, 1.0, sign)[:, None]


def normalized_along(d: np.ndarray, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Signed displacement along each marker's principal direction and its normalisation.

    For a straight path this equals |d| without the bias |noise| adds near rest (|d| of pure noise
    is positive on average; the projection's noise has zero mean), so fits and spreads computed
    from it are not pulled by measurement noise. Returns (along (n_frames, M) mm, delta_along).
    """
    u = principal_direction(d)
    along = np.einsum("fmk,mk->fm", d, u)
    peak = np.nanmax(np.where(np.isfinite(along), smoothed(along, frames), -np.inf), axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return along, along / np.where(peak > 0, peak, np.nan)[None]


def normalized(d: np.ndarray, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(|d| (n_frames, M), delta (n_frames, M)) with delta = |d| / peak_length(d)."""
    length = np.linalg.norm(d, axis=-1)
    peak = peak_length(d, frames)
    with np.errstate(invalid="ignore", divide="ignore"):
        return length, length / np.where(peak > 0, peak, np.nan)[None]
