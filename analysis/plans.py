"""Motion plans P(t) of the paper (METHOD.md, plans A-E): neutral (0) to smile (1).

``t`` and ``T`` share any time unit (frames or seconds); P is clipped to [0, 1] outside.
"""

from __future__ import annotations

import numpy as np

PLAN_NAMES = ("A", "B", "C", "D", "E")


def plan(name: str, t, T) -> np.ndarray:
    """P(t) for plan ``name`` (A fastest ... E slowest start), ``0 <= t <= T``."""
    s = np.clip(np.asarray(t, float) / float(T), 0.0, 1.0)
    key = name.upper()
    if key == "A":
        return 1.0 - np.exp(-18.0 * s) * (1.0 + 18.0 * s)
    if key == "B":
        return 1.0 - np.exp(-7.0 * s) * (1.0 + 7.0 * s)
    if key == "C":
        return s
    if key == "D":
        u = 1.0 - s
        return np.exp(-7.0 * u) * (1.0 + 7.0 * u)
    if key == "E":
        u = 1.0 - s
        return np.exp(-18.0 * u) * (1.0 + 18.0 * u)
    raise ValueError(f"motion plan: expected one of {', '.join(PLAN_NAMES)}, got {name!r}")
