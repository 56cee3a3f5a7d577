"""Which reconstructed samples the analyses use: those seen by at least ``min_cameras`` cameras.

The reconstruction keeps every point two or more cameras see (a marker only two cameras see is
still in the trajectories, with ``n_cameras`` 2 and its residual, so the audit can name it); the
analyses (trial averages, noise floor, responses, properties, linearity) take only the samples
with ``n_cameras >= min_cameras``. The run applies it where the analyses read a take
(``mocap.workflows.run.stages``: trial averages, the rest take's noise floor, motion takes); the
reconstruction, the trajectories, the audit and the recording keep every sample.

Samples with ``n_cameras`` 0 are left as they are: gap samples filled by interpolation, and
labeled 3D input (vendor exports carry no camera count).
"""

from __future__ import annotations

import numpy as np

from mocap.reconstruction.labeling import LabeledTake


def below_min_cameras(n_cameras: np.ndarray, min_cameras: int) -> np.ndarray:
    """Mask (same shape as n_cameras) of the reconstructed samples seen by 1 .. min_cameras - 1
    cameras."""
    n = np.asarray(n_cameras)
    return (n > 0) & (n < int(min_cameras))


def usable_positions(labeled: LabeledTake, min_cameras: int) -> np.ndarray:
    """(n_frames, n_markers, 3) mm: the take's positions, NaN where fewer than ``min_cameras``
    cameras saw the marker (a new array when anything is masked; the take is not modified)."""
    mask = below_min_cameras(labeled.n_cameras, min_cameras)
    if not mask.any():
        return labeled.X
    X = labeled.X.copy()
    X[mask] = np.nan
    return X
