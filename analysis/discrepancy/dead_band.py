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

:func:`dead_band_step` is the workflow's step (:mod:`mocap.analysis.discrepancy.workflow`): the
edge read on all takes, the model with the play at the edge scored on the held-out folds, and
the backlash named with its alternative, a dead band in the skin's hysteresis.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from mocap.analysis.discrepancy.crossval import CVFit, fold_takes, heldout, local_gain, take_sse
from mocap.analysis.discrepancy.result import Step
from mocap.analysis.model.face_model import FaceModel
from mocap.analysis.model.effects import CATALOGUE, Backlash
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


# ----------------------------------------------------------------------------------------------
# the workflow's dead-band step


def dead_band_alternative(halfwidth: float, model: FaceModel, form: str = "play") -> dict:
    """What a named backlash could also be: a dead band in the skin's own hysteresis. A play
    in the actuator followed by the skin's plays is one operator with wider plays, so the takes
    cannot say where the band sits; the base's loops hold what a density can, and the band is
    what they could not. Reported beside the naming, never instead of it."""
    width = model.loop_width()
    loops = {int(d): round(float(np.median(width[n][model.active[n]])), 2)
             for n, d in enumerate(model.du_ids) if model.active[n].any()}
    return {"effects": ["backlash", "hysteresis dead band"],
            "evidence": {"halfwidth": round(float(halfwidth), 3), "form": form,
                         "loop_width": loops},
            "reason": (f"after every reversal the face holds for about {2 * halfwidth:.1f} command "
                       "units: a dead band in the actuator (named: backlash) or in the skin's "
                       "own hysteresis (a branch play, relays that all need a push to switch) "
                       "fit alike; a take that moves the actuator without the skin (or a "
                       "position sensor on it) would tell them apart")}


DEAD_BAND_READING = ("the widest play before the skin's hysteresis that the takes allow: a play "
                     "forced wider than the face's dead band stops motion the takes show, and the "
                     "fit degrades at once (the edge of its profile); narrower, the skin's play "
                     "density holds the rest of the band")


def dead_band_step(data: ModelData, model: FaceModel, current: CVFit, floor: float, say):
    """A backlash the base's hysteresis absorbed, read as the edge of a forced play's profile
    (:func:`dead_band_edge`) on all takes, before ``model`` (the final model, fitted on
    all takes; ``current`` its two fold fits). Named when the edge is at least
    ``Backlash.min_plausible`` and half the takes' command step (a band narrower than one step
    still moves the response at the first step after a reversal), and the model with the play
    at the edge, walked up to it on each fold from the fold's model, predicts the held-out fold
    no worse (within :data:`EDGE_HELDOUT_SLACK`) than the fold's model polished at 0 (its final
    polish only: the walk's extra iterations at the narrower plays are not repeated at 0), in
    total or on the median take. The total alone is one take's verdict when a fold has not seen
    a DU's minor loop: both fold models extrapolate that loop poorly, and whichever does worse
    outweighs every other take; the median take's ratio is not swayed by it. A play the face
    has not got stops motion after every reversal, in every take.
    Returns (Step or None, its CVFit, the alternative, the model with the play, the evidence
    item or None where the step did not apply)."""
    cls = CATALOGUE["backlash"]
    if not model.hysteresis or any(type(e).name == "backlash" for e in model.effects):
        return None, None, None, None, None
    t0 = time.perf_counter()
    all_takes = list(range(len(data.takes)))
    step_c = data.command_step
    threshold = max(cls.min_plausible, 0.5 * step_c)
    edge = dead_band_edge(data, model, all_takes, screen=threshold)
    item = {"effect": "backlash", "testable": True, "dead_band_edge": True,
            "halfwidth": round(edge.halfwidth, 4) if edge.bounded else None,
            "interval": [round(v, 4) for v in edge.interval] if edge.bounded else None,
            "threshold": round(threshold, 4), "command_step": round(step_c, 4),
            "profile": [[round(h, 3), round(v, 4)] for h, v in edge.profile],
            "heldout_rms_mm": current.rms_mm, "score": 0.0, "explained": 0.0}
    say(f"  backlash edge {'screened out' if edge.screened else f'{edge.halfwidth:.2f}'} "
        f"(threshold {threshold:.2f} command units; {len(edge.profile)} forced plays, "
        f"{time.perf_counter() - t0:.1f} s)")
    if edge.screened:
        (_, s0), (_, s1) = edge.profile
        item["reason"] = (f"a play of {threshold:.3g} command units costs {100 * (s1 / s0 - 1):.0f} % "
                          "of the fit: some DU moves within a command step of a reversal, no "
                          f"dead band of a command step ({step_c:.3g})")
        return None, None, None, None, item
    if not edge.bounded or edge.halfwidth < threshold:
        item["reason"] = ("the takes do not bound a forced play" if not edge.bounded else
                          f"every DU moves within {2 * edge.halfwidth:.1f} command units of a "
                          f"reversal: no dead band of a command step ({step_c:.3g})")
        return None, None, None, None, item
    others = tuple(e for e in model.effects if type(e).name != "backlash")
    models, nulls = [], []
    for f in (0, 1):
        tk = fold_takes(data, f)
        models.append(walk(data, others, tk, current.models[f], edge.halfwidth))
        nulls.append(walk(data, others, tk, current.models[f], 0.0))
    s, n, res = heldout(data, models)
    s0, n0, res0 = heldout(data, nulls)
    cv = CVFit(models, s, n, [edge.halfwidth] * 2, cls, local_gain(res0, res, data.used, floor),
               [list(edge.interval)] * 2, residuals=res, null=CVFit(nulls, s0, n0, residuals=res0))
    with_play, without = take_sse(res, data.used), take_sse(res0, data.used)
    ratio = with_play / without
    median_ratio = float(np.nanmedian(ratio))
    k = int(np.argmax(with_play - without))
    item.update(heldout_rms_mm=cv.rms_mm, null_heldout_rms_mm=cv.null.rms_mm,
                explained=float((s0 - s) / s0), takes_median_ratio=round(median_ratio, 4),
                takes_worse=int(np.sum(ratio > 1.0 + EDGE_HELDOUT_SLACK)),
                takes_better=int(np.sum(ratio < 1.0 - EDGE_HELDOUT_SLACK)),
                most_worse_take={"take": data.takes[k].name,
                                 "sse_mm2": [round(float(without[k]), 3),
                                             round(float(with_play[k]), 3)]})
    if s > s0 * (1.0 + EDGE_HELDOUT_SLACK) and median_ratio > 1.0 + EDGE_HELDOUT_SLACK:
        item["reason"] = (f"the model with a play of {edge.halfwidth:.2f} predicts the held-out "
                          f"takes worse ({cv.rms_mm:.4f} mm against {cv.null.rms_mm:.4f} mm; "
                          f"the median take's SSE x {median_ratio:.3f})")
        return None, None, None, None, item
    h = edge.halfwidth
    lo, hi = edge.interval
    # each DU's own band: the onset on its single-DU takes (a robot's actuators may differ),
    # where they determine it to half a command step (on the PI face with a band of 12, DUs 1
    # and 12 read 12.75 in 10.4-15.05 and 14.0 in 13.55-14.45; DU 4, whose wide loops let the
    # density give back much of a wider band, rose softly from 12 to 29 and read 6.25 in 0.2-12)
    per_du = {}
    for du in data.du_ids:
        own = [k for k, t in enumerate(data.takes) if t.dus == (du,)]
        if own:
            e_du = dead_band_edge(data, model, own)
            if e_du.bounded and e_du.interval[1] - e_du.interval[0] <= 0.5 * step_c:
                per_du[int(du)] = e_du.halfwidth
    step = Step("backlash", {cls.parameter: h}, {cls.parameter: 0.5 * (hi - lo)},
                current.rms_mm, cv.rms_mm, [item], 0.0, per_du, form=cls.form,
                meaning=cls.meaning, reading=DEAD_BAND_READING,
                interval={cls.parameter: [float(lo), float(hi)]})
    alt = dead_band_alternative(h, edge.model, cls.form)
    alt["reason"] = (f"every DU holds for about {2 * h:.1f} command units after its reversals "
                     f"(a play forced wider degrades the fit at once; profile in the evidence): "
                     "a dead band in the actuators (named: backlash) or in the skin's own "
                     "hysteresis (relays that all need a push of that much to switch) fit alike, "
                     "and the base held it in its play density; the step names the actuator "
                     "because an elastic skin moves at once after a reversal. A take that moves "
                     "the actuator without the skin (or a position sensor on it) would tell them "
                     "apart")
    return step, cv, alt, edge.model, item


EDGE_HELDOUT_SLACK = 0.01  # the held-out SSE with the play may exceed its null's by this fraction (at
#                            the edge the training fit has begun to lose: 0.5 % per command unit)
