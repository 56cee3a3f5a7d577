"""Identification of the face model (:mod:`mocap.analysis.face_model`) from measured takes.

Per DU and marker the curve parameters (alpha, beta, r) are fitted by Levenberg-Marquardt,
vectorised over the DU's markers, with the linear ones (D and the path-basis vectors B)
eliminated by variable projection (closed form for given responses); the play widths r read the
take's play table (:mod:`mocap.analysis.play_kernel`), so no play loop runs inside the iterations.
Curves are fitted on single-DU takes only; takes with several DUs inform the global parameters of
interaction effects (``coupling``) and are predicted like any other.

A global effect parameter is identified by a profile: for each value on the effect's grid every
curve is refitted (warm start) and the training sum of squares (all training takes, mm^2) is
recorded; the best grid value is refined by a bounded scalar search between its neighbours.
Its uncertainty is the profile's curvature with the residuals' effective sample size (for a
time shift, never below the fine time grid's resolution: the sampled likelihood of a dead time
is piecewise constant at that scale).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.optimize import minimize_scalar

from mocap.analysis.face_model import (
    OVERSAMPLE,
    PLAY_FRACTIONS,
    R_MAX,
    FaceModel,
    actuator_effects,
    n_bases,
    take_tables,
)
from mocap.analysis.model_effects import Effect
from mocap.analysis.play_kernel import pi_logistic_from_table

BETA_STARTS = (60.0, 128.0, 196.0)


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

    def samples(self, k: int) -> np.ndarray:
        return np.arange(0, self.takes[k].n_frames, self.stride)

    def observed(self, k: int) -> np.ndarray:
        """Measured displacements (S, M, 3) mm of take k at its samples (NaN where missing)."""
        if k not in self._obs:
            X = self.takes[k].X[self.samples(k)]
            self._obs[k] = X - self.rest_mm
        return self._obs[k]

    def tables(self, k: int, effects) -> list[np.ndarray]:
        sig = tuple((type(e).name, float(e.value)) for e in actuator_effects(effects))
        key = (k, sig)
        if key not in self._tables:
            if len(self._tables) > 4 * len(self.takes):  # keep the cache to a few signatures
                base = [kk for kk in self._tables if kk[1] != ()]
                for kk in base[: len(base) // 2]:
                    del self._tables[kk]
            t = self.takes[k]
            self._tables[key] = take_tables(t.rows, t.dus, t.n_frames, self.fps, effects, self.stride)
        return self._tables[key]


# ----------------------------------------------------------------------------------------------
# curve fits (per DU, vectorised over its markers)


@dataclass
class _Block:
    """Stacked single-DU training samples of one DU: table P (S, H), bias shift (S,),
    transformed observations v (S, M_n, 3), weights wt (S, M_n)."""

    P: np.ndarray
    shift: np.ndarray
    v: np.ndarray
    wt: np.ndarray


def _block(data: ModelData, du: int, takes, effects, markers: np.ndarray) -> _Block | None:
    ks = [k for k in takes if data.takes[k].dus == (du,)]
    if not ks:
        return None
    outs = tuple((type(e).name, float(e.value)) for e in effects if type(e).stage == "output")
    key = (du, tuple(ks), outs, markers.tobytes())
    if key not in data._blocks:
        V, W = [], []
        for k in ks:
            d = data.observed(k)[:, markers]
            ok = np.isfinite(d).all(axis=-1)
            d = np.where(ok[..., None], d, 0.0)
            wt = ok.astype(float)
            for e in effects:
                d, w_e = e.output_inverse(d)
                if w_e is not None:
                    wt = wt * w_e
            V.append(d)
            W.append(wt)
        if len(data._blocks) > 8 * len(data.du_ids):  # a few output-effect values at a time
            data._blocks.clear()
        data._blocks[key] = (np.concatenate(V), np.concatenate(W))
    v, wt = data._blocks[key]
    P = np.concatenate([data.tables(k, effects)[0] for k in ks])
    shift = np.concatenate([np.full(data.observed(k).shape[0],
                                    float(np.asarray(sum((e.beta_shift(data.takes[k].trial)
                                                          for e in effects), 0.0))))
                            for k in ks])
    return _Block(P, shift, v, wt)


def _responses(blk: _Block, p: np.ndarray, hyst: bool, derivatives: bool = False):
    """y (S, M) and, with ``derivatives``, dy/d(alpha, beta[, r]) (S, M, P), analytically."""
    r = p[:, 2] if hyst else np.zeros(p.shape[0])
    out = pi_logistic_from_table(blk.P, r, p[:, 0], p[:, 1], blk.shift, PLAY_FRACTIONS, derivatives)
    if not derivatives:
        return out
    y, dy = out
    return y, (dy if hyst else dy[..., :2])


def _project(blk: _Block, y: np.ndarray, effects, v: np.ndarray, wt: np.ndarray):
    """Variable projection: coefficients (M, K+1, 3), residual (S, M, 3), cost (M,)."""
    Phi = [y] + [b for e in effects for b in e.bases(y)]
    k = len(Phi)
    wPhi = [ph * wt for ph in Phi]
    G = np.empty((y.shape[1], k, k))
    for i in range(k):
        for j in range(i, k):
            G[:, i, j] = G[:, j, i] = np.einsum("sm,sm->m", wPhi[i], Phi[j])
    G = G + 1e-9 * np.eye(k)
    Bm = np.stack([np.einsum("sm,smx->mx", wp, v) for wp in wPhi], axis=1)  # (M, k, 3)
    coef = np.linalg.solve(G, Bm)
    e = v - sum(Phi[i][..., None] * coef[None, :, i, :] for i in range(k))
    cost = np.einsum("smx,smx->m", e * e, np.broadcast_to(wt[..., None], e.shape))
    return coef, e, cost


def _lm_curves(blk: _Block, p0: np.ndarray, effects, hyst: bool, iters: int = 30,
               tol: float = 1e-6):
    """Levenberg-Marquardt over (alpha, beta[, r]) per curve; returns (p, coef, cost)."""
    v, wt = blk.v, blk.wt
    p = p0.copy()
    npar = 3 if hyst else 2
    y, dy = _responses(blk, p, hyst, derivatives=True)
    coef, e, cost = _project(blk, y, effects, v, wt)
    lam = np.full(p.shape[0], 1e-3)
    for _ in range(iters):
        # d pred / dp_j = dy/dp_j * g,  g = coef_0 + sum_k basis_k'(y) coef_k   (Kaufman)
        g = np.broadcast_to(coef[None, :, 0, :], e.shape)
        kk = 1
        for ef in effects:
            for db in ef.bases_derivative(y):
                g = g + db[..., None] * coef[None, :, kk, :]
                kk += 1
        ge = np.einsum("smx,smx->sm", g, e) * wt
        gg = np.einsum("smx,smx->sm", g, g) * wt
        H = np.empty((p.shape[0], npar, npar))
        b = np.empty((p.shape[0], npar))
        for i in range(npar):
            b[:, i] = np.einsum("sm,sm->m", dy[..., i], ge)
            dgi = dy[..., i] * gg
            for j in range(i, npar):
                H[:, i, j] = H[:, j, i] = np.einsum("sm,sm->m", dgi, dy[..., j])
        Hd = H + lam[:, None, None] * (np.einsum("mii->mi", H)[..., None] * np.eye(npar)) + 1e-12 * np.eye(npar)
        step = np.linalg.solve(Hd, b[..., None])[..., 0]
        q = p.copy()
        q[:, :npar] += step
        q[:, 0] = np.clip(q[:, 0], 1e-3, 0.5)
        q[:, 1] = np.clip(q[:, 1], -100.0, 355.0)
        if hyst:
            q[:, 2] = np.clip(q[:, 2], 0.0, R_MAX)
        y_new, dy_new = _responses(blk, q, hyst, derivatives=True)
        coef_new, e_new, cost_new = _project(blk, y_new, effects, v, wt)
        better = cost_new < cost
        rel = np.where(better, (cost - cost_new) / np.maximum(cost, 1e-300), 0.0)
        p = np.where(better[:, None], q, p)
        y = np.where(better[None], y_new, y)
        dy = np.where(better[None, :, None], dy_new, dy)
        coef = np.where(better[:, None, None], coef_new, coef)
        e = np.where(better[None, :, None], e_new, e)
        cost = np.where(better, cost_new, cost)
        lam = np.where(better, np.maximum(lam / 4, 1e-9), lam * 6)
        if np.all((better & (rel < tol)) | (lam > 1e7)):
            break
    return p, coef, cost


def empty_model(data: ModelData, effects) -> FaceModel:
    N, M = len(data.du_ids), len(data.marker_names)
    return FaceModel(fps=data.fps, marker_names=data.marker_names, rest_mm=data.rest_mm,
                     du_ids=data.du_ids, active=data.active.copy(),
                     alpha=np.full((N, M), 0.03), beta=np.full((N, M), 128.0),
                     r=np.where(any(type(e).frees_r for e in effects), 8.0, 0.0) * np.ones((N, M)),
                     D=np.zeros((N, M, 3)), B=np.zeros((N, M, n_bases(effects), 3)),
                     effects=tuple(effects))


def fit_curves(data: ModelData, effects, takes, warm: FaceModel | None = None,
               iters: int = 30) -> FaceModel:
    """Fit every DU's curves on the single-DU takes among ``takes`` (indices into data.takes).

    Strong curves (``data.strong``) get their own sigmoid by Levenberg-Marquardt: without
    ``warm`` from three biases (:data:`BETA_STARTS`), keeping the best; with it, from the warm
    model's curves. A marker a DU barely moves does not determine a sigmoid (its fit can trade a
    tiny response for a huge D): it takes the median shape (alpha, beta, r) of the DU's strong
    curves and only its displacement vectors are fitted (linear, well conditioned).
    """
    effects = tuple(effects)
    model = empty_model(data, effects)
    hyst = model.hysteresis
    K = n_bases(effects)
    for n, du in enumerate(data.du_ids):
        act = np.flatnonzero(data.active[n])
        if act.size == 0:
            continue
        blk = _block(data, du, takes, effects, act)
        if blk is None:
            model.active[n] = False
            continue
        strong = data.strong[n, act]
        if not strong.any():
            strong = np.ones(act.size, bool)
        sb = _Block(blk.P, blk.shift, blk.v[:, strong], blk.wt[:, strong])
        ns = int(strong.sum())
        if warm is not None:
            sa = act[strong]
            p0 = np.column_stack([warm.alpha[n, sa], warm.beta[n, sa],
                                  warm.r[n, sa] if hyst else np.zeros(ns)])
            if hyst and not warm.hysteresis:
                p0[:, 2] = 8.0
            ps, cs, _ = _lm_curves(sb, p0, effects, hyst, iters)
        else:
            starts = len(BETA_STARTS)
            p0 = np.column_stack([np.full(ns * starts, 0.03), np.repeat(BETA_STARTS, ns),
                                  np.full(ns * starts, 8.0 if hyst else 0.0)])
            tiled = _Block(sb.P, sb.shift, np.tile(sb.v, (1, starts, 1)), np.tile(sb.wt, (1, starts)))
            p_all, coef_all, cost_all = _lm_curves(tiled, p0, effects, hyst, iters)
            best = np.argmin(cost_all.reshape(starts, ns), axis=0)
            pick = best * ns + np.arange(ns)
            ps, cs = p_all[pick], coef_all[pick]
        p = np.empty((act.size, 3))
        coef = np.empty((act.size, K + 1, 3))
        p[strong], coef[strong] = ps, cs
        weak = ~strong
        if weak.any():
            p[weak] = np.median(ps, axis=0)
            wb = _Block(blk.P, blk.shift, blk.v[:, weak], blk.wt[:, weak])
            coef[weak] = _project(wb, _responses(wb, p[weak], hyst), effects, wb.v, wb.wt)[0]
        model.alpha[n, act], model.beta[n, act] = p[:, 0], p[:, 1]
        model.r[n, act] = p[:, 2] if hyst else 0.0
        model.D[n, act] = coef[:, 0]
        if K:
            model.B[n, act] = coef[:, 1:]
    return model


# ----------------------------------------------------------------------------------------------
# scoring


def take_residual(data: ModelData, model: FaceModel, k: int) -> np.ndarray:
    """Measured minus predicted displacement (S, M, 3) mm of take k (NaN where missing)."""
    t = data.takes[k]
    pred = model.predict_tables(data.tables(k, model.effects), list(t.dus), t.trial)
    return data.observed(k) - pred


def sse(data: ModelData, model: FaceModel, takes) -> tuple[float, int]:
    """Sum of squared residuals (mm^2) over the used markers of ``takes``, and their count."""
    total, count = 0.0, 0
    for k in takes:
        e = take_residual(data, model, k)[:, data.used]
        ok = np.isfinite(e)
        total += float(np.sum(e[ok] ** 2))
        count += int(ok.sum())
    return total, count


@dataclass
class Profile:
    """A global parameter's profile: values tried and training SSE (mm^2) at each."""

    values: list[float]
    sse: list[float]
    best: float
    model: FaceModel
    n: int
    resolution: float = 0.0  # grid step of a grid-refined parameter (0: continuous)


def profile_effect(data: ModelData, base: FaceModel, effect: Effect, takes,
                   refine: bool = True) -> Profile:
    """Identify ``effect``'s global parameter on ``takes`` (indices), every curve refitted.

    ``base`` supplies the other effects (values fixed) and the warm start.
    """
    cls = type(effect)
    others = tuple(e for e in base.effects if type(e).name != cls.name)
    cache: dict[float, tuple[float, FaceModel]] = {}
    count = [0]

    fixed = None if cls.affects_curves else fit_curves(data, others + (cls(0.0),), takes, warm=base,
                                                          iters=8)

    def evaluate(v: float) -> float:
        v = float(np.clip(v, *cls.bounds))
        key = round(v, 9)
        if key not in cache:
            effs = others + (cls(v),)
            if fixed is None:
                m = fit_curves(data, effs, takes, warm=base, iters=5)
            else:
                m = fixed.with_effects(effs)
            s, count[0] = sse(data, m, takes)
            cache[key] = (s, m)
        return cache[key][0]

    if cls.per_curve:
        m = fit_curves(data, others + (cls(),), takes, warm=base, iters=30)
        s, n = sse(data, m, takes)
        return Profile([0.0], [s], 0.0, m, n)
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
    if fixed is None:  # final polish of the curves at the chosen value
        m_best = fit_curves(data, m_best.effects, takes, warm=m_best, iters=30)
    keys = sorted(cache)
    # sampled data: a delay is resolved to the fine time grid at best
    resolution = 1.0 / (data.fps * OVERSAMPLE) if cls.fine_grid else 0.0
    return Profile(keys, [cache[k][0] for k in keys], float(best_key), m_best, count[0], resolution)


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
