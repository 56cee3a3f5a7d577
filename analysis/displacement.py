"""Displacement vectors and their normalisation (METHOD.md, "Spatial properties").

The functions live in :mod:`mocap.reconstruct.displacement`: trial averaging (reconstruction)
normalises displacements too, and imports go one way (reconstruction <- analysis). They are
re-exported here for the analyses.
"""

from mocap.reconstruct.displacement import (
    PLATEAU,
    normalized,
    normalized_along,
    peak_length,
    plateau_level,
    plateau_mask,
    principal_direction,
    smoothed,
)

__all__ = ["PLATEAU", "normalized", "normalized_along", "peak_length", "plateau_level",
           "plateau_mask", "principal_direction", "smoothed"]
