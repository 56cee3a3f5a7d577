"""Labeled marker data as vendor files hold it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


class ImportError_(ValueError):  # noqa: N801 - 'ImportError' is Python's own
    """A vendor file that cannot be read as labeled marker data; the message names the file and
    the place (line, column or parameter) and what was expected."""


@dataclass
class MarkerData:
    """Labeled 3D markers of one recording.

    names : marker labels (unique); X : (n_frames, n_markers, 3) mm, NaN where not seen;
    fps : point rate (Hz); first_frame : the vendor's number of the first frame;
    analogs : channel label -> (values (n_samples,), rate Hz, unit); notes : repairs made.
    """

    names: list[str]
    X: np.ndarray
    fps: float
    first_frame: int = 0
    analogs: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    source: str = ""

    def __post_init__(self) -> None:
        if self.X.ndim != 3 or self.X.shape[1:] != (len(self.names), 3):
            raise ValueError(f"marker data: expected X of shape (n_frames, {len(self.names)}, 3), "
                             f"got {self.X.shape}")
        if not np.isfinite(self.fps) or self.fps <= 0:
            raise ValueError(f"marker data: expected a positive frame rate, got {self.fps}")


UNIT_SCALE = {"mm": 1.0, "millimeters": 1.0, "millimetres": 1.0, "cm": 10.0, "centimeters": 10.0,
              "centimetres": 10.0, "m": 1000.0, "meters": 1000.0, "metres": 1000.0}


def unit_scale(unit: str, where: str) -> float:
    """mm per unit for a length unit name; ImportError_ naming ``where`` for an unknown unit."""
    key = str(unit).strip().lower()
    if key not in UNIT_SCALE:
        raise ImportError_(f"{where}: unknown length unit {unit!r} (expected mm, cm or m)")
    return UNIT_SCALE[key]


def unique_names(names: list[str], where: str, notes: list[str]) -> list[str]:
    """Make labels unique (``label~2``...), noting every rename."""
    seen: dict[str, int] = {}
    out = []
    for n in names:
        n = str(n).strip() or "unnamed"
        if n in seen:
            seen[n] += 1
            new = f"{n}~{seen[n]}"
            notes.append(f"{where}: duplicate label {n!r} renamed {new!r}")
            out.append(new)
        else:
            seen[n] = 1
            out.append(n)
    return out
