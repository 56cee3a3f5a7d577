"""True 3D marker positions of a take on the virtual face (see ``face`` and ``effects``)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from mocap.schedules import sample_commands
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
    w = face.hysteresis_state(a, rows_idx)[::OVERSAMPLE]
    shift = effect.beta_shift(trial)
    if beta_jitter is not None:
        shift = shift + beta_jitter[:, None]
    return dus, face.static_map(w, rows_idx, beta_shift=shift)


def true_positions(face: VirtualFace, effect: HiddenEffect, rows: pd.DataFrame | None,
                   n_frames: int, fps: float, trial: int,
                   rng: np.random.Generator | None, skin_jitter: bool = True) -> np.ndarray:
    """True marker positions (n_frames, n_markers, 3) mm of a take.

    With ``rng`` the trial-to-trial variation and the skin's jitter are drawn (a real take;
    ``skin_jitter=False`` draws the same numbers but leaves the jitter out: the take's response
    without its frame-to-frame noise); with ``rng=None`` the noise-free mean response.
    """
    dus = take_dus(face, rows)
    n_sel = len(dus)
    beta_jitter = rng.normal(0.0, TRIAL_BETA_SD, n_sel) if (rng is not None and n_sel) else None
    dus, y = normalized_response(face, effect, rows, n_frames, fps, trial, beta_jitter)
    pos = np.broadcast_to(face.rest_mm, (n_frames, face.n_markers, 3)).copy()
    if dus:
        rows_idx = np.array([face.du_index(d) for d in dus])
        D = face.D_mm[rows_idx]
        if rng is not None:
            D = D * (1.0 + rng.normal(0.0, TRIAL_AMPLITUDE_SD, D.shape[:2]))[..., None]
        pos += effect.displacement(y, D, face.normals)
    if rng is not None:
        jitter = rng.normal(0.0, SKIN_JITTER_MM, pos.shape)
        if skin_jitter:
            pos += jitter
    return pos
