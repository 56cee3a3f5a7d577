"""Displacement vectors and their normalisation (METHOD.md, "Spatial properties"); used by trial
averaging (here) and the analyses (re-exported by ``mocap.analysis.displacement``).

d_m(t) = v_m(t) - v_m(0); delta_m(t) = |d_m(t)| / max_t |d_m(t)| (``normalized``), and the
noise-unbiased variant along each marker's principal direction (``normalized_along``).

The maximum is estimated as the mean displacement over the marker's plateau: the frames where
its displacement, smoothed over ``frames``, is within ``PLATEAU`` of its smoothed maximum. For a
flat plateau (a held command) that is max_t |d| exactly, without the noise's largest excursion
setting the scale: an unsmoothed maximum over hundreds of noisy frames sits a few noise sigmas
above the plateau, and even a smoothed one varies from marker to marker by its noise, which
would show as spread between the markers' normalised curves (dyssynchrony).
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.ndimage import convolve1d

PLATEAU = 0.95  # frames within 5 % of the smoothed maximum form the plateau


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


def plateau_mask(x: np.ndarray, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(on (n_frames, M) bool, top (M,)): each column's plateau frames (see the module docstring)
    and its smoothed maximum. The mask is the same for x and any positive multiple of it (a
    normalised curve has its displacement's plateau)."""
    s = smoothed(x, frames)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        top = np.nanmax(np.where(np.isfinite(s), s, -np.inf), axis=0)
        on = np.isfinite(x) & (s >= PLATEAU * top[None]) & (top[None] > 0)
    return on, top


def plateau_level(x: np.ndarray, frames: int) -> np.ndarray:
    """(M,) mean of x (n_frames, M) over each column's plateau (see the module docstring)."""
    on, top = plateau_mask(x, frames)
    level = np.where(on, x, 0.0).sum(axis=0) / np.maximum(on.sum(axis=0), 1)
    return np.where(on.any(axis=0), level, top)


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


def normalized_along(d: np.ndarray, frames: int, direction: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Signed displacement along each marker's principal direction and its normalisation.

    For a straight path this equals |d| without the bias |noise| adds near rest (|d| of pure noise
    is positive on average; the projection's noise has zero mean), so fits and spreads computed
    from it are not pulled by measurement noise. Returns (along (n_frames, M) mm, delta_along).
    """
    u = principal_direction(d) if direction is None else direction
    along = np.einsum("fmk,mk->fm", d, u)
    peak = plateau_level(along, frames)
    with np.errstate(invalid="ignore", divide="ignore"):
        return along, along / np.where(peak > 0, peak, np.nan)[None]


def normalized(d: np.ndarray, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(|d| (n_frames, M), delta (n_frames, M)) with delta = |d| / peak_length(d)."""
    length = np.linalg.norm(d, axis=-1)
    peak = plateau_level(length, frames)
    with np.errstate(invalid="ignore", divide="ignore"):
        return length, length / np.where(peak > 0, peak, np.nan)[None]
