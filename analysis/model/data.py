"""The data the face model is identified on: measured takes and the session around them.

:class:`TakeData` holds one commanded take (positions (n_frames, M, 3) mm, NaN where missing, its
command rows); :class:`ModelData` holds the session's takes with its markers, DUs and the caches
of the takes' play tables, observed displacements and stacked training blocks.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import pandas as pd

from mocap.analysis.model.face_model import actuator_effects, take_tables


@dataclass
class TakeData:
    """A commanded take's measurement.

    name, kind : as in the session.  trial : the trial number (1 when the session gives none).
    dus : the DUs the take drives (a nonzero command).  rows : its commands (time_s, du, command).
    X : (n_frames, M, 3) measured positions, mm, NaN where missing.
    group : the schedule (takes with the same group are repetitions of one command series).
    fold : cross-validation fold (0 or 1).
    """

    name: str
    kind: str
    trial: int
    dus: tuple[int, ...]
    rows: pd.DataFrame
    X: np.ndarray
    group: str
    fold: int = 0

    @property
    def n_frames(self) -> int:
        return self.X.shape[0]


@dataclass
class ModelData:
    """Everything the identification reads, with the play-table cache.

    fps : frames/s.  marker_names : (M,).  rest_mm : (M, 3).  takes : commanded takes.
    used : (M,) bool, the markers that are scored (markers with abnormal noise are left out).
    active : (N, M) bool per DU id in ``du_ids``: the markers the model moves with the DU.
    strong : (N, M) bool: the curves fitted with their own sigmoid (the others take the DU's
        median shape).  stride : frames between samples used.
    """

    fps: float
    marker_names: tuple[str, ...]
    rest_mm: np.ndarray
    takes: list[TakeData]
    du_ids: tuple[int, ...]
    used: np.ndarray
    active: np.ndarray
    strong: np.ndarray | None = None
    stride: int = 2
    _tables: dict = field(default_factory=dict, repr=False)
    _obs: dict = field(default_factory=dict, repr=False)
    _blocks: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if self.strong is None:
            self.strong = self.active.copy()

    @cached_property
    def command_step(self) -> float:
        """The median nonzero change of a DU's command from one command row to the next
        (command units): what a dead band's width is resolved to at best."""
        steps = [np.abs(np.diff(g.sort_values("time_s", kind="stable")["command"].to_numpy(float)))
                 for t in self.takes for _, g in t.rows.groupby("du")]
        steps = np.concatenate(steps) if steps else np.zeros(0)
        steps = steps[steps > 0]
        return float(np.median(steps)) if steps.size else 0.0

    def samples(self, k: int) -> np.ndarray:
        return np.arange(0, self.takes[k].n_frames, self.stride)

    def observed(self, k: int) -> np.ndarray:
        """Measured displacements (S, M, 3) mm of take k at its samples (NaN where missing)."""
        if k not in self._obs:
            X = self.takes[k].X[self.samples(k)]
            self._obs[k] = X - self.rest_mm
        return self._obs[k]

    def tables(self, k: int, effects) -> list[np.ndarray]:
        # keyed by the effect's class: two forms of one effect (a first- and a second-order lag)
        # with the same value make different tables
        sig = tuple((type(e).__qualname__, float(e.value)) for e in actuator_effects(effects))
        key = (k, sig)
        if key not in self._tables:
            if len(self._tables) > 4 * len(self.takes):  # keep the cache to a few signatures
                base = [kk for kk in self._tables if kk[1] != ()]
                for kk in base[: len(base) // 2]:
                    del self._tables[kk]
            t = self.takes[k]
            self._tables[key] = take_tables(t.rows, t.dus, t.n_frames, self.fps, effects, self.stride)
        return self._tables[key]


def multi_du_takes(data: ModelData, takes) -> list[int]:
    """The takes among ``takes`` (indices) that drive several DUs at once."""
    return [k for k in takes if len(data.takes[k].dus) >= 2]
