"""Motion design by inverse response (METHOD.md, "Motion design").

A motion plan P(t) in [0, 1] becomes, per DU, a command plan c(t) = R^-1(P(t)) through the DU's
forward response while rising and its backward response while falling, sampled at the rig's
command step and written as FORMAT.md command rows.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from mocap.analysis.plans import plan as plan_function
from mocap.analysis.response import inverse_sigmoid
from mocap.schedules import round_half_up


@dataclass(frozen=True)
class SigmoidPair:
    """A DU's forward and backward response functions (the paper's R_fwd, R_bwd)."""

    alpha_fwd: float
    beta_fwd: float
    alpha_bwd: float
    beta_bwd: float


@dataclass(frozen=True)
class PlanTiming:
    """When a designed motion happens (s): rest, the plan, a hold, the return 1 - P, rest.

    Defaults follow the paper: 130 command steps of 16 ms (2.08 s) each way.
    """

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

    def ideal(self, t_s, plan_name: str) -> np.ndarray:
        """The ideal normalised displacement at times t_s (s): 0, P rising, 1, 1 - P, 0."""
        t = np.asarray(t_s, float)
        T = self.duration_s
        up = plan_function(plan_name, t - self.start_s, T)
        t_back = t - (self.start_s + T + self.hold_s)
        down = 1.0 - plan_function(plan_name, t_back, T)
        return np.where(t < self.start_s, 0.0, np.where(t_back < 0, up, down))


def paper_design(plan_name: str, responses: Mapping[int, SigmoidPair],
                 timing: PlanTiming = PlanTiming(), dus: Sequence[int] | None = None) -> pd.DataFrame:
    """Command rows for plan ``plan_name`` on ``dus`` by the paper's inverse sigmoids.

    Step k = 1..n_steps of the rise commands R_fwd^-1(P(k / n_steps)); step k of the return
    commands R_bwd^-1(1 - P(k / n_steps)); commands rounded half up and clipped to 0..255.
    """
    dus = sorted(responses) if dus is None else list(dus)
    k = np.arange(1, timing.n_steps + 1)
    p = plan_function(plan_name, k, timing.n_steps)
    t_up = timing.start_s + (k - 1) * timing.step_s
    t_down = timing.start_s + timing.duration_s + timing.hold_s + (k - 1) * timing.step_s
    frames = []
    for du in dus:
        r = responses[du]
        c_up = inverse_sigmoid(p, r.alpha_fwd, r.beta_fwd)
        c_down = inverse_sigmoid(1.0 - p, r.alpha_bwd, r.beta_bwd)
        t = np.concatenate([[0.0], t_up, t_down])
        c = np.concatenate([[0.0], c_up, c_down])
        frames.append(pd.DataFrame({
            "time_s": np.round(t, 9),
            "du": int(du),
            "command": np.clip(round_half_up(c), 0, 255),
        }))
    return pd.concat(frames, ignore_index=True)


def paper_design_series(t_s, P, responses: Mapping[int, SigmoidPair], *, start_s: float,
                        step_s: float, dus: Sequence[int] | None = None) -> pd.DataFrame:
    """The paper's rule on any plan P(t) (t_s from the plan's start, s): at every command step
    c = R_fwd^-1(P) while P rises and R_bwd^-1(P) while it falls (the branch of the last change
    where P is flat). A reversal inside the range jumps from one branch to the other: the
    full-sweep sigmoids know no minor loops, which is where this rule fails.
    """
    t_s = np.asarray(t_s, float)
    P = np.asarray(P, float)
    dus = sorted(responses) if dus is None else list(dus)
    n = int(np.floor((t_s[-1] - t_s[0]) / step_s + 1e-9))
    k = np.arange(1, n + 1)
    p = np.interp(t_s[0] + k * step_s, t_s, P)
    dp = np.diff(np.concatenate([[0.0], p]))
    sign = np.sign(dp)
    last = np.maximum.accumulate(np.where(sign != 0, np.arange(sign.size), 0))
    rising = sign[last] >= 0
    t = np.concatenate([[0.0], start_s + (k - 1) * step_s])
    frames = []
    for du in dus:
        r = responses[du]
        pc = np.clip(p, 1e-6, 1 - 1e-6)
        c = np.where(rising, inverse_sigmoid(pc, r.alpha_fwd, r.beta_fwd),
                     inverse_sigmoid(pc, r.alpha_bwd, r.beta_bwd))
        c = np.where(p <= 0, 0.0, np.where(p >= 1, 255.0, c))
        frames.append(pd.DataFrame({"time_s": np.round(t, 9), "du": int(du),
                                    "command": np.clip(round_half_up(np.concatenate([[0.0], c])), 0, 255)}))
    return pd.concat(frames, ignore_index=True)
