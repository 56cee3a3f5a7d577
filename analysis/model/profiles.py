"""Profiles of the face model's global effect parameters.

A global effect parameter is identified by a profile: for each value on the effect's grid every
curve is refitted (warm start) and the training sum of squares (all training takes, mm^2) is
recorded; the best grid value is refined by a bounded scalar search between its neighbours.
Its uncertainty is the profile's curvature with the residuals' effective sample size (for a
time shift, never below the fine time grid's resolution: the sampled likelihood of a dead time
is piecewise constant at that scale).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import minimize_scalar

from mocap.analysis.model.coupling import _fit_pairs, coupling_kappa
from mocap.analysis.model.data import ModelData, multi_du_takes
from mocap.analysis.model.effects import Effect
from mocap.analysis.model.face_model import OVERSAMPLE, FaceModel
from mocap.analysis.model.fit import _refresh_shifts, fit_curves, sse


@dataclass
class Profile:
    """A global parameter's profile: values tried and training SSE (mm^2) at each."""

    values: list[float]
    sse: list[float]
    best: float
    model: FaceModel
    n: int
    resolution: float = 0.0  # grid step of a grid-refined parameter (0: continuous)
    interval: tuple[float, float] | None = None  # the values that fit equally well (a plateau)
    null: FaceModel | None = None  # the effect at its null value, fitted along the same path


def profile_effect(data: ModelData, base: FaceModel, effect: Effect, takes,
                   refine: bool = True, null: bool = False) -> Profile:
    """Identify ``effect``'s global parameter on ``takes`` (indices), every curve refitted.

    ``base`` supplies the other effects (values fixed) and the warm start. ``null``: also fit
    the effect at its null value (0) along the same path (the same warm starts, iterations and
    polishes; ``Profile.null``). The base fit is not converged to the last digit: each further
    polish moves its held-out SSE by a few per cent, either way, so a candidate is compared
    with itself at 0 carried along its own path, not with the base (on a face with nothing
    hidden, a lag of 0 s fitted by the profile scored -5446 against the base and explained 31 %
    of its held-out excess).
    """
    cls = type(effect)
    others = tuple(e for e in base.effects if type(e).name != cls.name)
    cache: dict[float, tuple[float, FaceModel]] = {}
    count = [0]

    # an actuator effect moves what the hysteresis density absorbed while it was missing (a lag
    # widens the loops): each profile point updates the density once, else the profile keeps
    # the base's lag-shaped density and turns bimodal (a second-order lag on Bouc-Wen loops read
    # 0.03 s for 0.08 s on a fold without slow ramps; 0.06 s with the update)
    inner_rounds = 2 if (cls.stage == "actuator" and base.hysteresis) else None
    fixed = None if cls.affects_curves else fit_curves(data, others + (cls(0.0),), takes, warm=base,
                                                          iters=8)
    # an interaction with the curves held: each multi-DU take's bias shift was identified
    # without it and holds part of it (a coupling law read on stale shifts comes out short)
    refresh = (multi_du_takes(data, takes)
               if fixed is not None and fixed.shifts_takes and cls.stage == "interact" else [])
    # a rough profile (a dead time: each value re-times every ramp; from the base, which absorbed
    # the missing delay in its density and biases, five iterations stop short, and the profile
    # from the base has local minima far from the delay that a step-by-step approach finds):
    # each value warm-starts from the nearest value tried, the grid ascending
    cont = fixed is None and cls.continuation

    def point(v: float, warm: FaceModel, rounds: int | None = inner_rounds) -> FaceModel:
        # one profile point: the curves refitted at ``v`` from ``warm``, a few iterations
        return fit_curves(data, others + (cls(v),), takes, warm=warm, iters=5, rounds=rounds)

    def warm_for(key: float) -> FaceModel:
        if not cont or not cache:
            return base
        return cache[min(cache, key=lambda k: (abs(k - key), k))][1]

    def evaluate(v: float) -> float:
        v = float(np.clip(v, *cls.bounds))
        key = round(v, 9)
        if key not in cache:
            effs = others + (cls(v),)
            if fixed is None:
                m = point(v, warm_for(key))
            else:
                m = replace(fixed, effects=effs, info=dict(fixed.info))
                if refresh:  # the shifts of the takes the value moves, identified again
                    _refresh_shifts(data, m, refresh)
                if cls.pairwise:  # the pair vectors on top of the value's law (kappa read
                    #                 once, for the chosen value)
                    _fit_pairs(data, m, takes, kappa=False)
            s, count[0] = sse(data, m, takes)
            cache[key] = (s, m)
        return cache[key][0]

    if cls.per_curve:
        m = fit_curves(data, others + (cls(),), takes, warm=base, iters=30)
        s, n = sse(data, m, takes)
        m0 = fit_curves(data, others, takes, warm=base, iters=30) if null else None
        return Profile([0.0], [s], 0.0, m, n, null=m0)
    grid = list(cls.grid)
    vals = [evaluate(v) for v in grid]
    i = int(np.argmin(vals))
    if refine:
        lo = grid[max(i - 1, 0)]
        hi = grid[min(i + 1, len(grid) - 1)]
        if hi > lo:
            minimize_scalar(evaluate, bounds=(lo, hi), method="bounded",
                            options={"xatol": (hi - lo) * 0.01, "maxiter": 8 if cls.fine_grid else 6})
    best_key = min(cache, key=lambda k: cache[k][0])
    s_best, m_best = cache[best_key]
    null_key = round(float(np.clip(0.0, *cls.bounds)), 9)
    if null:
        evaluate(null_key)
    m_null = cache[null_key][1] if null else None
    if null and cont and best_key != null_key:
        # the null carried along the same continuation: down the grid from the best value (the
        # better of the two nulls by training SSE, so the continuation's extra iterations are
        # never read as the effect)
        m = cache[best_key][1]
        down = sorted((round(float(v), 9) for v in grid if v < best_key), reverse=True)
        for v in down + ([null_key] if not down or down[-1] != null_key else []):
            m = point(v, m)
        if sse(data, m, takes)[0] < cache[null_key][0]:
            m_null = m
    if cls.pairwise and fixed is not None:
        m_best.info["coupling_kappa"] = coupling_kappa(data, m_best, takes)
    if null and cls.pairwise:  # a law with pair vectors: its null is no coupling at all, as
        #                        the pair vectors' own null (forms are compared by their gain)
        m_null = replace(fixed.with_effects(others), pairs=(), C=None, C2=None, info={})
    if fixed is None:  # final polish of the curves at the chosen value
        same = best_key == null_key
        m_best = fit_curves(data, m_best.effects, takes, warm=m_best, iters=30)
        if null:
            m_null = m_best if same else fit_curves(data, m_null.effects, takes, warm=m_null,
                                                   iters=30)
    stage2 = False
    if fixed is None and refine and cls.stage == "actuator" and m_best.hysteresis:
        # the hysteresis density was fitted without this effect and absorbed part of it (a lag
        # widens the loops): profile again around the best value from the polished model
        span = 0.5 * (grid[min(i + 1, len(grid) - 1)] - grid[max(i - 1, 0)])
        warm2 = m_best
        cache2: dict[float, tuple[float, FaceModel]] = {}

        def evaluate2(v: float) -> float:
            v = float(np.clip(v, *cls.bounds))
            key = round(v, 9)
            if key not in cache2:
                m = point(v, warm2, rounds=None)
                cache2[key] = (sse(data, m, takes)[0], m)
            return cache2[key][0]

        stage2 = span > 0
        if span > 0:
            evaluate2(best_key)
            minimize_scalar(evaluate2, bounds=(max(best_key - span, cls.bounds[0]),
                                               min(best_key + span, cls.bounds[1])),
                            method="bounded", options={"xatol": span * 0.02, "maxiter": 6})
            key2 = min(cache2, key=lambda k: cache2[k][0])
            if key2 != round(best_key, 9):
                best_key = key2
                m_best = fit_curves(data, cache2[key2][1].effects, takes, warm=cache2[key2][1],
                                    iters=30)
                if null:  # the same two steps at the null value
                    if key2 == null_key:
                        m_null = m_best
                    else:
                        m5 = fit_curves(data, m_null.effects, takes, warm=m_null, iters=5)
                        m_null = fit_curves(data, m5.effects, takes, warm=m5, iters=30)
    keys = sorted(cache)
    # sampled data: a delay is resolved to the fine time grid at best, a dead band's half-width
    # to half a command step (the band of 2 b releases at a command row)
    resolution = (1.0 / (data.fps * OVERSAMPLE) if cls.fine_grid else
                  0.5 * data.command_step if cls.command_grid else 0.0)
    interval = None
    if cls.command_grid and fixed is None:
        # a dead band that releases at command rows fits the same for every width between two
        # rows' thresholds: report that plateau and its centre, not whichever value was tried.
        # "The same" to within the fits' own reproducibility: the best value fitted again, as
        # the profile fitted it, from the models of the nearest values tried on either side
        # (the profile's fits stop after a few iterations, so each carries its warm start's
        # path). After a coupling the rows a 3-DU smile adds differ by 0.01-0.03 mm^2 of 361
        # while the best value refitted from its neighbours' models moves by 0.07-0.08: the
        # exact-equality plateau read 7.0 for a band of 12, and the width fitted from the
        # best's own model at 12 scored 0.06 below it.
        ev, tried = (evaluate2, cache2) if stage2 else (evaluate, cache)
        tol = _reproducibility(data, takes, tried, best_key,
                               lambda v, w: point(v, w, None if stage2 else inner_rounds))
        interval = _plateau(ev, tried, best_key, cls.bounds, probes=keys if stage2 else (),
                            tol=tol)
        if interval is not None:
            centre = 0.5 * (interval[0] + interval[1])
            best_key = round(centre, 9)
            m_best = m_best.with_effects(tuple(cls(centre) if type(e) is cls else e
                                               for e in m_best.effects))
            resolution = max(resolution, interval[1] - interval[0])
    return Profile(keys, [cache[k][0] for k in keys], float(best_key), m_best, count[0], resolution,
                   interval, m_null)


def _reproducibility(data: ModelData, takes, cache: dict, best: float, fit) -> float:
    """How far a profile's SSE at ``best`` depends on the fit's path (mm^2): the value fitted
    again (``fit(value, warm model)``) from the models of the nearest other values in ``cache``
    ({value: (SSE, model)}) below and above it, the larger departure from the SSE the profile
    holds for it (one refit alone read 0.013 where the other side's read 0.076 on a Preisach
    face after its coupling). 0 with nothing else tried."""
    key = round(best, 9)
    below = [k for k in cache if k < key]
    above = [k for k in cache if k > key]
    near = ([max(below)] if below else []) + ([min(above)] if above else [])
    return max((abs(sse(data, fit(best, cache[k][1]), takes)[0] - cache[key][0]) for k in near),
               default=0.0)


def _plateau(evaluate, cache: dict, best: float, bounds: tuple[float, float], steps: int = 5,
             rel: float = 1e-9, probes=(), tol: float = 0.0) -> tuple[float, float] | None:
    """The interval around ``best`` over which the profiled SSE stays at its minimum (to
    ``rel`` of it, or ``tol`` mm^2 where that is more: the fits' reproducibility,
    :func:`_reproducibility`), its edges located by bisection between the tried values
    (``steps`` each) and, where no tried value on a side is off the minimum, the ``probes``
    (evaluated as needed); None when no other tried value is on the minimum (a smooth profile:
    no plateau)."""
    smin = cache[round(best, 9)][0]
    level = smin + max(smin * rel, tol)

    def flat(v: float) -> bool:
        return evaluate(v) <= level

    if sum(cache[k][0] <= level for k in cache) < 2:
        return None
    keys = sorted(set(cache) | {round(float(v), 9) for v in probes})
    edges = []
    for side in (-1, 1):
        inner, outer = best, None
        for k in (sorted((k for k in keys if k < best), reverse=True) if side < 0 else
                  sorted(k for k in keys if k > best)):
            if flat(k):
                inner = k
            else:
                outer = k
                break
        if outer is None:
            edges.append(bounds[0] if side < 0 else bounds[1])
            continue
        for _ in range(steps):
            mid = 0.5 * (inner + outer)
            if flat(mid):
                inner = mid
            else:
                outer = mid
        edges.append(0.5 * (inner + outer))
    return float(edges[0]), float(edges[1])


def profile_uncertainty(profile: Profile, n_eff: float) -> float:
    """Standard error of the profiled parameter: a parabola through the minimum and its grid
    neighbours, Delta(-2 log L) = n_eff Delta(SSE) / SSE_min = 1."""
    v = np.asarray(profile.values)
    s = np.asarray(profile.sse)
    if v.size < 3:
        return float("nan")
    i = int(np.argmin(s))
    idx = np.argsort(np.abs(v - v[i]))[:5]
    if np.unique(v[idx]).size < 3:
        return float("nan")
    a, _, _ = np.polyfit(v[idx] - v[i], s[idx], 2)
    floor = profile.resolution / np.sqrt(12.0)  # a grid-refined value is known to its step
    if a <= 0:
        return float("nan") if floor == 0 else float(floor)
    return float(max(np.sqrt(s[i] / (max(n_eff, 1.0) * a)), floor))
