"""Which reconstructed samples the analyses use: those seen by at least ``min_cameras`` cameras.

The reconstruction keeps every point two or more cameras see (a marker only two cameras see is
still in the trajectories, with ``n_cameras`` 2 and its residual, so the audit can name it); the
analyses (trial averages, noise floor, responses, properties, linearity) take only the samples
with ``n_cameras >= min_cameras``. This is the one place that mask is applied: on the labeled
takes kept for the later stages, before trials are built.

Samples with ``n_cameras`` 0 are left as they are: gap samples filled by interpolation, and
labeled 3D input (vendor exports carry no camera count).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from mocap.reconstruct.labeling import LabeledTake


def below_min_cameras(n_cameras: np.ndarray, min_cameras: int) -> np.ndarray:
    """Mask (same shape as n_cameras) of the reconstructed samples seen by 1 .. min_cameras - 1
    cameras."""
    n = np.asarray(n_cameras)
    return (n > 0) & (n < int(min_cameras))


def usable_samples(labeled: LabeledTake, min_cameras: int) -> LabeledTake:
    """The take with positions (n_frames, n_markers, 3) mm set to NaN where fewer than
    ``min_cameras`` cameras saw the marker; ``n_cameras`` and ``residual_px`` are kept (they
    describe the reconstruction), and ``stats['below_min_cameras']`` counts the masked samples.
    The input is not modified."""
    mask = below_min_cameras(labeled.n_cameras, min_cameras)
    if not mask.any():
        return replace(labeled, stats={**labeled.stats, "below_min_cameras": 0})
    X = labeled.X.copy()
    X[mask] = np.nan
    return replace(labeled, X=X, stats={**labeled.stats, "below_min_cameras": int(mask.sum())})
