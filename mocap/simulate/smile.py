"""The paper's smile design as the simulated motion takes play it (the simulator's own copy).

The analysis has its own design code; the simulator does not import it (its truth is made
separately). Plans P(s), s = t / T in [0, 1] (METHOD.md, plans A-E)::

    A  1 - e^{-18 s} (1 + 18 s)      B  1 - e^{-7 s} (1 + 7 s)      C  s
    D  e^{-7 u} (1 + 7 u)            E  e^{-18 u} (1 + 18 u),  u = 1 - s

Rise step k = 1..n_steps commands c = beta_fwd - ln((1 - P) / P) / alpha_fwd at P = P(k / n);
the return step k commands the backward sigmoid's inverse at 1 - P(k / n) (the paper's inverse
sigmoid, P clipped to [1e-6, 1 - 1e-6]); commands rounded half up and clipped to 0..255.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from mocap.schedules import round_half_up
from mocap.simulate.dus import DU_BY_ID

PLAN_NAMES = ("A", "B", "C", "D", "E")


def plan(name: str, t, T) -> np.ndarray:
    """P(t) in [0, 1] of plan ``name`` for 0 <= t <= T (clipped outside)."""
    s = np.clip(np.asarray(t, float) / float(T), 0.0, 1.0)
    key = name.upper()
    if key in ("A", "B"):
        a = 18.0 if key == "A" else 7.0
        return 1.0 - np.exp(-a * s) * (1.0 + a * s)
    if key == "C":
        return s
    if key in ("D", "E"):
        a = 7.0 if key == "D" else 18.0
        u = 1.0 - s
        return np.exp(-a * u) * (1.0 + a * u)
    raise ValueError(f"motion plan: expected one of {', '.join(PLAN_NAMES)}, got {name!r}")


def inverse_sigmoid(p, alpha, beta, eps: float = 1e-6) -> np.ndarray:
    """c = beta - ln((1 - P) / P) / alpha, P clipped to [eps, 1 - eps]; command units."""
    d = np.clip(np.asarray(p, float), eps, 1.0 - eps)
    return np.asarray(beta, float) - np.log((1.0 - d) / d) / np.asarray(alpha, float)


@dataclass(frozen=True)
class Branches:
    """A DU's forward and backward full-sweep sigmoids (1/command unit, command units)."""

    alpha_fwd: float
    beta_fwd: float
    alpha_bwd: float
    beta_bwd: float


@dataclass(frozen=True)
class SmileTiming:
    """When a designed motion happens (s): rest, the plan, a hold, the return, rest (the paper's
    130 command steps of 16 ms each way)."""

    start_s: float = 0.25
    n_steps: int = 130
    step_s: float = 0.016
    hold_s: float = 1.0
    tail_s: float = 0.25

    @property
    def duration_s(self) -> float:
        return self.n_steps * self.step_s

    @property
    def total_s(self) -> float:
        return self.start_s + 2 * self.duration_s + self.hold_s + self.tail_s


def nominal_branches(du_ids) -> dict[int, Branches]:
    """The DUs' nominal full-sweep sigmoids (bias +- half the loop width): the design basis of
    the simulated motion takes (a perfectly identified paper model of the nominal face)."""
    out = {}
    for du in du_ids:
        s = DU_BY_ID[du]
        out[du] = Branches(s.alpha, s.beta + s.hysteresis / 2, s.alpha, s.beta - s.hysteresis / 2)
    return out


def smile_commands(plan_name: str, branches: dict[int, Branches],
                   timing: SmileTiming = SmileTiming()) -> pd.DataFrame:
    """Command rows (time_s, du, command) of plan ``plan_name`` on every DU of ``branches``."""
    k = np.arange(1, timing.n_steps + 1)
    p = plan(plan_name, k, timing.n_steps)
    t_up = timing.start_s + (k - 1) * timing.step_s
    t_down = timing.start_s + timing.duration_s + timing.hold_s + (k - 1) * timing.step_s
    frames = []
    for du in sorted(branches):
        r = branches[du]
        c_up = inverse_sigmoid(p, r.alpha_fwd, r.beta_fwd)
        c_down = inverse_sigmoid(1.0 - p, r.alpha_bwd, r.beta_bwd)
        t = np.concatenate([[0.0], t_up, t_down])
        c = np.concatenate([[0.0], c_up, c_down])
        frames.append(pd.DataFrame({"time_s": np.round(t, 9), "du": int(du),
                                    "command": np.clip(round_half_up(c), 0, 255)}))
    return pd.concat(frames, ignore_index=True)
