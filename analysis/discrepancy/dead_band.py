"""The widest actuator dead band the takes allow: a backlash the base's hysteresis has absorbed.

A play of half-width h before the skin's hysteresis is, for a Preisach-type skin, the same kind
of operator with every relay widened by h (a play before a play is one play of the summed width:
docs/discrepancy.md), so the base model's play density can hold a backlash and the candidate
search sees no held-out gain: on a face with a play of 12 command units, the base with a play
forced to any width from 0 to 12 fits the takes alike while the density moves its weight from the
quarter-width plays to the zero-width one.

What the density cannot do is take away a dead band the face has not got: a play forced wider
than the face's band stops motion the takes show, and the fit degrades fast. On faces without a backlash it degrades from 2 to 4 command
units on, on every base family (Bouc-Wen, PI, Preisach and branch play: a DU whose skin moves at
once after a reversal rules out a shared band). So the profile of a forced play, from 0 upwards,
is flat to an edge and rises beyond it, and the edge is a measurement: the narrowest band every
DU's response shows after its reversals, in command units. Where it is at least one command step
of the takes wide, the step names a backlash of that half-width (the elastic skin moves at once
after a reversal, so the band is the actuator's), and reports the alternative (a skin whose
hysteresis holds that band itself) beside it.

The edge is the onset of the profile's rise: a least-squares fit of S0 + A max(0, h - h0)^3 to
the profile's points (S0, A >= 0 and h0 free; A and S0 carry the session's size, so the reading
does not depend on how many takes it has), h0 the edge. The cube is the rise's shape near its
onset: beyond the band the forced play takes away travel in proportion to h - h0 at every
reversal, and the density gives part of it back at first, so the rise starts softer than the
square of the lost travel (a free exponent reads 2.25-4.25 on the four families' profiles). With
commands in steps of 12.75 units it reads a band of 12 as 12.3 (Bouc-Wen), 12.9 (Preisach), 13.3
(PI) on 4-DU sessions and 11.1 on a 2-DU one. A threshold on the slope relative to the flat
level reads later where fewer reversals carry the band, and a likelihood-ratio bound takes the
fit's own convergence wobble (a few tenths of a mm^2 over about 2.5e5 effective residuals) for
evidence. The interval is the onset fitted
with the exponents 4 and 2: how far the reading moves with the shape.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocap.analysis.model.face_model import FaceModel
from mocap.analysis.model.effects import Backlash
from mocap.analysis.model.data import ModelData
from mocap.analysis.model.fit import fit_curves, sse

EDGE_POWER = 3.0  # the rise's shape near its onset (the interval: 4 and 2)
EDGE_STEP = 2.0  # command units between the forced plays of the profile (1.0 moved the onset by
#                 at most 0.4 on eight faces' profiles, at twice the cost)
WALK_STEP = 4.0  # command units between the forced plays of a walk to a given play
EDGE_MAX = 48.0  # the widest play tried, command units
PAST_EDGE = 0.25  # the profile stops once its SSE is this fraction above its flat level
SCREEN_RISE = 0.10  # a screening play that costs more than this fraction of the fit: no band
WALK_ITERS = 5  # curve iterations per profile point (each warm from the point before)


@dataclass(frozen=True)
class DeadBandEdge:
    """A forced play's profile and its edge.

    halfwidth : the edge, command units (nan when the profile never rose: the takes do not
        bound a band).
    interval : (lo, hi) command units, the edge fitted with the exponents 4 and 2.
    flat_sse : mm^2, the profile's lowest training SSE.
    profile : ((h command units, training SSE mm^2), ...) in the order tried.
    model : the model fitted with the play at the edge (None when unbounded).
    screened : True when a play of the screen's width already cost the fit more than
        :data:`SCREEN_RISE` (the onset is below it; halfwidth nan, profile the two plays).
    """

    halfwidth: float
    interval: tuple[float, float]
    flat_sse: float
    profile: tuple[tuple[float, float], ...]
    model: FaceModel | None
    screened: bool = False

    @property
    def bounded(self) -> bool:
        return bool(np.isfinite(self.halfwidth))


def walk(data: ModelData, effects, takes, warm: FaceModel, target: float,
         step: float = WALK_STEP, iters: int = WALK_ITERS) -> FaceModel:
    """The model with a play of ``target`` (command units), reached from ``warm`` by forced plays
    ``step`` apart (a jump straight to a wide play leaves the density where the narrow one had
    it), then polished."""
    m = warm
    for h in np.arange(step, target, step):
        m = fit_curves(data, tuple(effects) + (Backlash(float(h)),), takes, warm=m, iters=iters,
                       rounds=2)
    return fit_curves(data, tuple(effects) + (Backlash(float(target)),), takes, warm=m, iters=30)


def onset(points, power: float = EDGE_POWER, resolution: float = 0.05) -> float:
    """The onset h0 of a profile's rise: least squares of S0 + A max(0, h - h0)^power over
    ``points`` ((h, SSE), ...), h0 on a grid of ``resolution`` (S0 and A in closed form for each,
    A > 0). nan when the profile does not rise (no h0 with A > 0)."""
    h = np.array([p[0] for p in points], float)
    v = np.array([p[1] for p in points], float)
    if h.size < 3:
        return float("nan")
    h0 = np.arange(h.min(), h.max(), resolution)  # (G,)
    x = np.clip(h[None, :] - h0[:, None], 0.0, None) ** power  # (G, P)
    xm, vm = x.mean(axis=1, keepdims=True), v.mean()
    sxx = np.sum((x - xm) ** 2, axis=1)
    sxv = np.sum((x - xm) * (v - vm), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(sxx > 0, sxv / sxx, 0.0)
    sse_fit = np.sum((v - vm) ** 2) - np.where(sxx > 0, a * sxv, 0.0)
    ok = a > 0
    if not ok.any():
        return float("nan")
    return float(h0[ok][np.argmin(sse_fit[ok])])


def dead_band_edge(data: ModelData, model: FaceModel, takes,
                   screen: float | None = None) -> DeadBandEdge:
    """The profile of a play forced before ``model``'s hysteresis (its other effects kept),
    fitted on ``takes`` from 0 up in steps of :data:`EDGE_STEP`, each point warm from the one
    before, and its edge (module docstring).

    ``screen`` (command units): first the play at 0 and at ``screen`` (reached in one jump);
    where the latter costs more than :data:`SCREEN_RISE` of the fit, the onset is below it and
    the profile stops there (``DeadBandEdge.screened``; two fits instead of the profile's
    four or five on a face without a band: on five faces of four families a play of 6 cost
    20-54 % (a stick-slip face 20 %, a dead-time face 23 %), within a band of 12 at most
    0.5 %; on a 2-DU session without a band 1.4 %, where fewer reversals carry the rise: the
    screen is a saving where it triggers, never the reading)."""
    others = tuple(e for e in model.effects if type(e).name != "backlash")
    points: list[tuple[float, float]] = []
    models: list[FaceModel] = []
    m = model
    if screen is not None and screen > 0:
        m0 = fit_curves(data, others + (Backlash(0.0),), takes, warm=model, iters=WALK_ITERS,
                        rounds=2)
        m1 = fit_curves(data, others + (Backlash(float(screen)),), takes, warm=m0,
                        iters=WALK_ITERS, rounds=2)
        pts = ((0.0, sse(data, m0, takes)[0]), (float(screen), sse(data, m1, takes)[0]))
        if pts[1][1] > (1.0 + SCREEN_RISE) * pts[0][1]:
            return DeadBandEdge(float("nan"), (float("nan"), float("nan")), pts[0][1], pts, None,
                                screened=True)
    for h in np.arange(0.0, EDGE_MAX + 1e-9, EDGE_STEP):
        m = fit_curves(data, others + (Backlash(float(h)),), takes, warm=m, iters=WALK_ITERS,
                       rounds=2)
        points.append((float(h), sse(data, m, takes)[0]))
        models.append(m)
        if points[-1][1] > (1.0 + PAST_EDGE) * min(v for _, v in points):
            break
    flat = min(v for _, v in points)
    rose = points[-1][1] > (1.0 + PAST_EDGE) * flat
    edge = onset(points) if rose else float("nan")
    if not np.isfinite(edge):
        return DeadBandEdge(float("nan"), (float("nan"), float("nan")), flat, tuple(points), None)
    lo, hi = onset(points, EDGE_POWER + 1.0), onset(points, EDGE_POWER - 1.0)
    below = max(i for i, (h, _) in enumerate(points) if h <= edge)
    at = fit_curves(data, others + (Backlash(edge),), takes, warm=models[below], iters=30)
    return DeadBandEdge(edge, (min(lo, edge), max(hi, edge)), flat, tuple(points), at)
