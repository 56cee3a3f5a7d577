"""Telling the ends of a two-marker wand apart, across cameras, from the epipolar geometry.

A two-marker wand (a T-wand, an easyWand/Argus rod) shows two alike blobs in each camera; which
one is which end is only defined relative to the other cameras. For two cameras ``i, j`` whose
relative pose is known (essential matrix ``E_ij``), a frame's sightings ``(a0, a1)`` and
``(b0, b1)`` are matched straight (a0-b0, a1-b1) or swapped (a0-b1, a1-b0); the right assignment
has the smaller epipolar error, unless the wand lies in the pair's epipolar plane, where both
fit. The preference of every camera pair is

    d_ij = e(a0, b1) + e(a1, b0) - e(a0, b0) - e(a1, b1)    (px, symmetric epipolar distance)

(positive: straight). Each frame's sightings get signs ``s_i`` (+1 keep, -1 swap) maximising
``sum_ij s_i s_j d_ij`` (exhaustively up to ``EXHAUSTIVE_CAMERAS`` cameras, else the leading
eigenvector of ``d``): every pair votes, so a pair that cannot decide is outvoted by the others.
A sighting whose own support ``s_i sum_j s_j d_ij`` is under ``margin_px`` is left out (the
wand was in an epipolar plane of all its pairs, or the blobs are wrong), and so is one whose
epipolar error in its chosen order (median over the cameras it shares the frame with) exceeds
``max(outlier_factor x the median of all sightings', 1 px)``: a ghost or merged blob in place of
an end.

Epipolar errors use undistorted normalised coordinates scaled by the pair's mean focal length.
"""

from __future__ import annotations

import warnings

import numpy as np

from mocap.calib.camera import CameraRig
from mocap.calib.wand import WandObservations

EXHAUSTIVE_CAMERAS = 10


def _epipolar_px(E: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """Sampson distance (normalised units) of matches xa (..., 2) in a, xb (..., 2) in b."""
    ha = np.concatenate([xa, np.ones(xa.shape[:-1] + (1,))], axis=-1)
    hb = np.concatenate([xb, np.ones(xb.shape[:-1] + (1,))], axis=-1)
    Ea = ha @ E.T  # epipolar lines in b
    Eb = hb @ E  # epipolar lines in a
    num = np.einsum("...i,...i->...", hb, Ea)
    den = Ea[..., 0] ** 2 + Ea[..., 1] ** 2 + Eb[..., 0] ** 2 + Eb[..., 1] ** 2
    return np.abs(num) / np.sqrt(np.maximum(den, 1e-300))


def choose_pair_assignment(E: np.ndarray, xa: np.ndarray, xb: np.ndarray):
    """For sightings xa, xb (n, 2, 2) (normalised) of two cameras with essential matrix ``E``
    (b from a): ``swap`` (n,) bool, True where the swapped assignment fits better, and the
    preference ``d`` (n,) in normalised units (positive: straight)."""
    straight = _epipolar_px(E, xa, xb).sum(axis=-1)
    swapped = _epipolar_px(E, xa, xb[:, ::-1]).sum(axis=-1)
    d = swapped - straight
    return d < 0, d


def essential(rig: CameraRig, i: int, j: int) -> np.ndarray:
    """Essential matrix of camera j from camera i (normalised coordinates)."""
    ci, cj = rig[i], rig[j]
    R = cj.R @ ci.R.T
    t = cj.t - R @ ci.t
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return tx @ R


def _best_signs(D: np.ndarray) -> np.ndarray:
    """Signs (F, C) maximising s^T D s per frame; D (F, C, C) symmetric, zero diagonal."""
    F, C = D.shape[:2]
    if C <= EXHAUSTIVE_CAMERAS:
        k = np.arange(2 ** (C - 1))
        S = np.where((k[:, None] >> np.arange(C)[None]) & 1, -1.0, 1.0)  # camera 0 kept: +1
        best = np.empty((F, C))
        for lo in range(0, F, 2048):
            score = np.einsum("kc,fcd,kd->fk", S, D[lo:lo + 2048], S)
            best[lo:lo + 2048] = S[np.argmax(score, axis=1)]
        return best
    _, vec = np.linalg.eigh(D)
    return np.where(vec[..., -1] < 0, -1.0, 1.0)


def label_ends(obs: WandObservations, rig: CameraRig, *, margin_px: float = 0.5,
               outlier_factor: float = 6.0) -> tuple[WandObservations, np.ndarray]:
    """Order the ends of two-marker sightings consistently across the cameras of each frame.

    Parameters
    ----------
    obs : sightings with ``ordered=False`` (or ordered: they are checked again).
    rig : cameras whose relative poses are roughly known (the initial rig or a calibration).
    margin_px : least support a sighting's order needs (see the module docstring).

    Returns
    -------
    (ordered, kept): the sightings kept, each in a consistent end order (``ordered=True``), and
    the boolean mask (len(obs),) of the input's sightings kept.
    """
    C = len(rig)
    frames, local = np.unique(obs.frame, return_inverse=True)
    F = frames.size
    xn = np.empty(obs.uv.shape)
    for c in range(C):
        m = obs.camera == c
        xn[m] = rig[c].normalize(obs.uv[m])
    row = np.full((F, C), -1)
    row[local, obs.camera] = np.arange(len(obs))
    D = np.zeros((F, C, C))
    A = np.zeros((F, C, C))  # straight + swapped errors (px): the chosen one is (A -+ D) / 2
    for i in range(C):
        for j in range(i + 1, C):
            both = np.flatnonzero((row[:, i] >= 0) & (row[:, j] >= 0))
            if both.size == 0:
                continue
            f = 0.5 * (rig[i].focal_px + rig[j].focal_px)
            E = essential(rig, i, j)
            xa, xb = xn[row[both, i]], xn[row[both, j]]
            straight = _epipolar_px(E, xa, xb).sum(axis=-1)
            swapped = _epipolar_px(E, xa, xb[:, ::-1]).sum(axis=-1)
            D[both, i, j] = D[both, j, i] = f * (swapped - straight)
            A[both, i, j] = A[both, j, i] = f * (swapped + straight)
    signs = _best_signs(D)
    support = signs * np.einsum("fcd,fd->fc", D, signs)  # (F, C)
    s_obs = signs[local, obs.camera]
    # error of each pair in the chosen orders: straight when s_i s_j = +1
    chosen = 0.5 * (A - signs[:, :, None] * signs[:, None, :] * D)
    shared = A > 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # frames with one sighting: no pair
        err = np.nanmedian(np.where(shared, chosen, np.nan), axis=2)  # (F, C)
    e_obs = err[local, obs.camera]
    limit = max(outlier_factor * float(np.nanmedian(e_obs)), 1.0) if np.isfinite(e_obs).any() else 0
    kept = (support[local, obs.camera] > margin_px) & (e_obs <= limit)
    uv = np.where((s_obs < 0)[:, None, None], obs.uv[:, ::-1], obs.uv)
    out = WandObservations(obs.camera_ids, obs.camera[kept], obs.frame[kept], uv[kept], ordered=True)
    return out, kept
