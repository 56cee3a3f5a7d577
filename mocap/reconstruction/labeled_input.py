"""Labeled 3D takes (vendor exports, other pipelines) as dense trajectories."""

from __future__ import annotations

import numpy as np
import pandas as pd

from mocap.reconstruction.labeling import LabeledTake, TakeStats


def marker_names_3d(takes: list[pd.DataFrame], template: pd.DataFrame | None) -> list[str]:
    """Marker order: the template's where given (then any extra markers sorted), else sorted."""
    seen = sorted(set().union(*(set(t["marker"].unique()) for t in takes))) if takes else []
    if template is None:
        return seen
    tnames = [str(n) for n in template["name"]]
    return [n for n in tnames if n in set(seen)] + [n for n in seen if n not in set(tnames)]


def dense_from_3d(df: pd.DataFrame, names: list[str]) -> LabeledTake:
    """(frame, marker, x, y, z) rows -> LabeledTake (n_cameras 0, residual NaN)."""
    n_frames = int(df["frame"].max()) + 1
    idx = {n: i for i, n in enumerate(names)}
    m = df["marker"].map(idx).to_numpy()
    f = df["frame"].to_numpy(np.int64)
    X = np.full((n_frames, len(names), 3), np.nan)
    X[f, m.astype(np.int64)] = df[["x", "y", "z"]].to_numpy(float)
    shape = (n_frames, len(names))
    seen = int(np.isfinite(X[..., 0]).sum())
    stats = TakeStats(points=seen, labeled_points=seen,
                      missing_marker_frames=int(np.isnan(X[..., 0]).sum()))
    return LabeledTake(X, np.zeros(shape, np.int64), np.full(shape, np.nan), np.zeros(shape, bool),
                       stats)
