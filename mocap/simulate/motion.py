"""True 3D marker positions of a take on the virtual face (see ``face``, ``families``, ``effects``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from mocap.core.schedules import sample_commands
from mocap.simulate.effects import HiddenEffect
from mocap.simulate.face import (
    SKIN_JITTER_MM,
    TRIAL_AMPLITUDE_SD,
    TRIAL_BETA_SD,
    VirtualFace,
)

OVERSAMPLE = 4  # fine time grid per frame for the actuator dynamics and hysteresis


def take_dus(face: VirtualFace, rows: pd.DataFrame | None) -> list[int]:
    if rows is None or len(rows) == 0:
        return []
    dus = sorted(int(d) for d in pd.unique(rows["du"]))
    unknown = [d for d in dus if d not in face.du_ids]
    if unknown:
        raise ValueError(f"command rows name DUs {unknown} that the virtual face lacks {face.du_ids}")
    return dus


def normalized_response(face: VirtualFace, effect: HiddenEffect, rows: pd.DataFrame | None,
                        n_frames: int, fps: float, trial: int,
                        beta_jitter: np.ndarray | None = None) -> tuple[list[int], np.ndarray]:
    """The take's DUs and their normalised responses y (n_frames, n_take_dus, n_markers)."""
    dus = take_dus(face, rows)
    if not dus:
        return dus, np.zeros((n_frames, 0, face.n_markers))
    rows_idx = np.array([face.du_index(d) for d in dus])
    t = np.arange(n_frames * OVERSAMPLE) / (fps * OVERSAMPLE)

    def sampler(times):
        return sample_commands(rows, dus, times)

    a = effect.command(sampler(t), t, sampler)
    shift = effect.beta_shift(trial, face.n_markers)
    if beta_jitter is not None:
        shift = shift + beta_jitter[:, None]
    return dus, face.response(a, rows_idx, beta_shift=shift, step=OVERSAMPLE)


@dataclass(frozen=True)
class TrueTake:
    """A take's true marker positions and the trial variation drawn for it.

    positions : (n_frames, n_markers, 3) mm. dus : the take's DUs. bias_shift : (n_dus,) the
    common bias shift of each DU in this take, command units (the base face's trial jitter plus
    the family's trial shift; zeros without ``rng``). family_shift : (n_dus,) the family's part.
    """

    positions: np.ndarray
    dus: tuple[int, ...]
    bias_shift: np.ndarray
    family_shift: np.ndarray


def true_take(face: VirtualFace, effect: HiddenEffect, rows: pd.DataFrame | None,
              n_frames: int, fps: float, trial: int,
              rng: np.random.Generator | None, skin_jitter: bool = True) -> TrueTake:
    """True marker positions of a take, with the trial variation drawn for it.

    With ``rng`` the trial-to-trial variation and the skin's jitter are drawn (a real take;
    ``skin_jitter=False`` draws the same numbers but leaves the jitter out: the take's response
    without its frame-to-frame noise); with ``rng=None`` the noise-free mean response.
    """
    dus = take_dus(face, rows)
    n_sel = len(dus)
    beta_jitter = rng.normal(0.0, TRIAL_BETA_SD, n_sel) if (rng is not None and n_sel) else None
    family_shift = np.zeros(n_sel)
    if beta_jitter is not None and face.family.trial_shift_sd > 0:
        family_shift = rng.normal(0.0, face.family.trial_shift_sd, n_sel)
        beta_jitter = beta_jitter + family_shift
    dus, y = normalized_response(face, effect, rows, n_frames, fps, trial, beta_jitter)
    pos = np.broadcast_to(face.rest_mm, (n_frames, face.n_markers, 3)).copy()
    if dus:
        rows_idx = np.array([face.du_index(d) for d in dus])
        D = face.D_mm[rows_idx]
        if rng is not None:
            D = D * (1.0 + rng.normal(0.0, TRIAL_AMPLITUDE_SD, D.shape[:2]))[..., None]
        paths = None
        if face.family.path != "straight":
            paths = lambda y_eff: face.displacement(y_eff, D, rows_idx)
        pos += effect.displacement(y, D, face.normals, paths=paths)
    if rng is not None:
        jitter = rng.normal(0.0, SKIN_JITTER_MM, pos.shape)
        if skin_jitter:
            pos += jitter
    shift = np.zeros(n_sel) if beta_jitter is None else beta_jitter
    return TrueTake(pos, tuple(dus), shift, family_shift)


def true_positions(face: VirtualFace, effect: HiddenEffect, rows: pd.DataFrame | None,
                   n_frames: int, fps: float, trial: int,
                   rng: np.random.Generator | None, skin_jitter: bool = True) -> np.ndarray:
    """True marker positions (n_frames, n_markers, 3) mm of a take (see :func:`true_take`)."""
    return true_take(face, effect, rows, n_frames, fps, trial, rng, skin_jitter).positions
