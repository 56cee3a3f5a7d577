"""The coupling of DUs driven together: pair vectors and the coupling's kappa.

The pair vectors C (P, M, 3) mm (and their second order C2 (P, 2, M, 3) mm) are fitted by linear
least squares on the multi-DU takes (:func:`_fit_pairs`). The coupling's kappa (the fraction of
its travel a DU loses while another DU is at full command) is read from each DU's measured
:class:`TravelPath` where the multi-DU takes hold their DUs at full command
(:func:`coupling_kappa`), or from a scalar law in the model's drive (:func:`law_kappa`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mocap.analysis.model.data import ModelData, multi_du_takes
from mocap.analysis.model.face_model import FaceModel, pair_features


PAIR_ORDER = 2  # the pair terms' order in the drives (face_model.pair_features)


def _fit_pairs(data: ModelData, model: FaceModel, takes, kappa: bool = True,
               order: int | None = None) -> None:
    """Fit the pair vectors C (P, M, 3), and for ``order`` 2 their second order C2 (P, 2, M,
    3), of ``model`` in place on the multi-DU takes among ``takes``: per marker, linear least
    squares of the residual (after any coupling law the model holds) on the pair features
    (:func:`mocap.analysis.model.face_model.pair_features`). ``kappa``: also read the coupling's kappa
    (:func:`coupling_kappa`, into ``model.info``)."""
    order = PAIR_ORDER if order is None else order
    K = 1 if order == 1 else 3
    multi = multi_du_takes(data, takes)
    pairs = sorted({(a, b) for k in multi for i, a in enumerate(data.takes[k].dus)
                    for b in data.takes[k].dus[i + 1:] if a in data.du_ids and b in data.du_ids})
    M = len(data.marker_names)
    model.pairs = tuple(pairs)
    model.C = np.zeros((len(pairs), M, 3))
    model.C2 = None if order == 1 else np.zeros((len(pairs), 2, M, 3))
    if not pairs:
        return
    P = len(pairs) * K
    G = np.zeros((M, P, P))
    bvec = np.zeros((M, P, 3))
    plain = replace(model, pairs=(), C=None, C2=None)  # the prediction without the pair terms
    for k in multi:
        t = data.takes[k]
        sh = model.take_shifts.get(t.name, {})
        y = model.response(data.tables(k, model.effects), list(t.dus), t.trial,
                           np.array([sh.get(d, 0.0) for d in t.dus]))
        idx, F = pair_features(y, list(t.dus), model.pairs, order)
        if not idx:
            continue
        F = F.reshape(F.shape[0], -1, F.shape[-1])  # (S, P_take K, M), pair-major
        e = data.observed(k) - plain.displacement_from_response(y, list(t.dus))
        ok = np.isfinite(e).all(axis=-1)  # (S, M)
        e = np.where(ok[..., None], e, 0.0)
        Fw = F * ok[:, None, :]
        ii = (np.array(idx)[:, None] * K + np.arange(K)[None]).ravel()
        G[:, ii[:, None], ii[None, :]] += np.einsum("spm,sqm->mpq", Fw, F)
        bvec[:, ii] += np.einsum("spm,smx->mpx", Fw, e)
    # the second-order features are nearly collinear with the first where the DUs of a take
    # move together (a smile's plans): a small ridge keeps their vectors bounded there
    ridge = (1e-9 if K == 1 else 1e-6) * np.maximum(np.einsum("mpp->m", G), 1e-12)[:, None, None] * np.eye(P)
    seen = np.einsum("mpp->mp", G) > 0
    C = np.linalg.solve(G + ridge + np.eye(P) * (~seen)[:, :, None], bvec)  # (M, P, 3)
    C = np.where(seen[..., None], C, 0.0) * model.active.any(axis=0)[:, None, None]
    C = np.transpose(C.reshape(M, len(pairs), K, 3), (1, 2, 0, 3))  # (pairs, K, M, 3)
    model.C = np.ascontiguousarray(C[:, 0])
    if K > 1:
        model.C2 = np.ascontiguousarray(C[:, 1:])
    if kappa:
        model.info["coupling_kappa"] = coupling_kappa(data, model, takes)


def without_coupling(model: FaceModel) -> FaceModel:
    """``model`` without its coupling (no coupling effect, no pair vectors)."""
    return replace(model, effects=tuple(e for e in model.effects if type(e).name != "coupling"),
                   pairs=(), C=None, C2=None, info={})


FULL_HOLD_S = 0.5  # a DU is at full command, settled, once its command has been at its highest
#                    this long (a lag of 0.1 s settles to 1 %; the paper's hold is 3 s)


def top_commands(data: ModelData) -> dict[int, float]:
    """{DU id: the highest command it gets in any of the session's takes}."""
    top: dict[int, float] = {}
    for t in data.takes:
        for d, c in t.rows.groupby("du")["command"].max().items():
            top[int(d)] = max(top.get(int(d), -np.inf), float(c))
    return top


def full_command(data: ModelData, k: int, top: dict[int, float]) -> np.ndarray:
    """(S,) bool: the samples of take k where every DU of the take has held its highest command
    (``top``, :func:`top_commands`) for :data:`FULL_HOLD_S` or more."""
    from mocap.analysis.noise.corrected import still_frames
    from mocap.core.schedules import sample_commands

    t = data.takes[k]
    rate = data.fps / data.stride  # samples per second
    c = sample_commands(t.rows, list(t.dus), data.samples(k) / data.fps)  # (S, n)
    return np.all([(c[:, j] >= top[int(d)] - 1e-9)
                   & still_frames(c[:, j], rate, min_run_s=FULL_HOLD_S, settle_s=FULL_HOLD_S)
                   for j, d in enumerate(t.dus)], axis=0)


@dataclass(frozen=True)
class TravelPath:
    """One DU's marker paths as measured in its single-DU takes, parametrised by travel.

    chord (M, 3) mm the mean displacement where the DU is at full command; coef (M, 2, 3) mm the
    path's departure from its chord, d(s) = s chord + s (1 - s) (coef_0 + s coef_1), s the
    travel (the displacement's projection on the chord over |chord|^2: 0 at rest, 1 at full
    command). The travel does not depend on how a model parametrises its drive."""

    chord: np.ndarray
    coef: np.ndarray

    def at(self, s: np.ndarray) -> np.ndarray:
        """Displacements (..., M, 3) mm at travels s (..., M)."""
        s = np.asarray(s, float)[..., None]
        return s * self.chord + s * (1.0 - s) * (self.coef[:, 0] + s * self.coef[:, 1])


def travel_path(obs: np.ndarray, full: np.ndarray, used: np.ndarray) -> TravelPath | None:
    """A DU's :class:`TravelPath` from its single-DU takes' displacements ``obs`` (S, M, 3) mm,
    ``full`` (S,) bool where the DU is at full command, settled (:func:`full_command`); None
    without a sample at full command. The departure from the chord is fitted by linear least
    squares per marker on the samples with travel in [-0.1, 1.1]."""
    fin = np.isfinite(obs).all(axis=-1) & used[None]
    full = fin & np.asarray(full, bool)[:, None]
    n_full = full.sum(axis=0)
    if not n_full.any():
        return None
    x = np.where(fin[..., None], obs, 0.0)
    chord = np.einsum("sm,smk->mk", full, x) / np.maximum(n_full, 1)[:, None]
    c2 = np.sum(chord**2, axis=-1)
    s = np.einsum("smk,mk->sm", x, chord) / np.maximum(c2, 1e-12)
    w = fin & (s > -0.1) & (s < 1.1)
    F = np.stack([s * (1 - s), s * s * (1 - s)], axis=-1) * w[..., None]  # (S, M, 2)
    r = np.where(w[..., None], x - s[..., None] * chord[None], 0.0)
    G = np.einsum("smi,smj->mij", F, F)
    G = G + (1e-9 * np.maximum(np.trace(G, axis1=1, axis2=2), 1e-12))[:, None, None] * np.eye(2)
    coef = np.linalg.solve(G, np.einsum("smi,smk->mik", F, r))  # (M, 2, 3)
    coef = np.where((n_full > 0)[:, None, None], coef, 0.0)
    return TravelPath(chord, coef)


def travel_paths(data: ModelData, takes, dus, top: dict[int, float]) -> dict[int, TravelPath]:
    """{DU id: :class:`TravelPath`} of ``dus`` from their single-DU takes among ``takes`` (at
    full command: :func:`full_command`). DUs without such takes are left out."""
    out = {}
    for du in dus:
        single = [k for k in takes if tuple(data.takes[k].dus) == (du,)]
        if not single:
            continue
        path = travel_path(np.concatenate([data.observed(k) for k in single]),
                           np.concatenate([full_command(data, k, top) for k in single]),
                           data.used)
        if path is not None:
            out[int(du)] = path
    return out


def coupling_kappa(data: ModelData, model: FaceModel, takes) -> float:
    """The coupling's kappa: the fraction of its travel a DU loses while another DU is at full
    command (at the markers most in the other DU's field for the pull-weighted law), read where
    the multi-DU takes among ``takes`` hold all their DUs at full command (:func:`full_command`:
    each DU's command at its highest for :data:`FULL_HOLD_S`).

    Each DU's paths are measured in its single-DU takes as functions of the travel along the
    chord (:func:`travel_path`); where a take holds its DUs at full command, the law puts each
    DU at travel 1 - kappa sum_other o_n'm (o the other DU's relative pull, |chord_n'm| /
    max_m |chord_n'm|, or 1 at every marker) and the marker at the sum of the DUs' paths there.
    kappa is fitted to the takes' mean displacements there by least squares (a grid, then a
    parabola), with the weighting that fits better (``model.info["coupling_law"]``). Neither the
    pair vectors nor the model's drive enter: the model's y is the face's drive only up to a
    reparametrisation its paths absorb on single-DU takes, and a loss in y is a loss in travel
    only where the two agree (accuracy of both readings: benchmarks/coupling_reading.md). Where no multi-DU
    take holds its DUs at full command: :func:`law_kappa`."""
    multi = multi_du_takes(data, takes)
    top = top_commands(data)
    holds = []
    for k in multi:
        obs = data.observed(k)
        ok = full_command(data, k, top)[:, None] & np.isfinite(obs).all(axis=-1) & data.used[None]
        cnt = ok.sum(axis=0)
        if cnt.any():
            total = np.einsum("sm,smk->mk", ok, np.where(ok[..., None], obs, 0.0))
            holds.append((list(data.takes[k].dus), total / np.maximum(cnt, 1)[:, None], cnt))
    paths = travel_paths(data, takes, sorted({d for dus, _, _ in holds for d in dus}), top)
    holds = [h for h in holds if all(d in paths for d in h[0])]
    if not holds:
        model.info["coupling_law"] = "drive"
        return law_kappa(data, model, multi)
    grid = np.round(np.arange(-0.3, 1.2001, 0.01), 6)
    best = (np.inf, 0.0, "")
    for law in ("pull-weighted", "uniform"):
        cost = np.zeros(grid.size)
        for dus, mean, cnt in holds:
            mag = np.stack([np.linalg.norm(paths[d].chord, axis=-1) for d in dus])  # (n, M)
            o = (np.ones_like(mag) if law == "uniform"
                 else mag / np.maximum(mag.max(axis=1, keepdims=True), 1e-12))
            others = o.sum(axis=0, keepdims=True) - o
            pred = sum(paths[d].at(1.0 - grid[:, None] * others[i][None])
                       for i, d in enumerate(dus))
            cost += np.einsum("m,gmk->g", cnt, (mean[None] - pred) ** 2)
        v = parabola_min(grid, cost)
        if cost.min() < best[0]:
            best = (float(cost.min()), v, law)
    model.info["coupling_law"] = best[2]
    return best[1]


def parabola_min(grid: np.ndarray, cost: np.ndarray) -> float:
    """The minimum of ``cost`` over ``grid``, refined by a parabola through the lowest point and
    its neighbours (kept within them; the grid point where the parabola opens downwards)."""
    i = int(np.clip(np.argmin(cost), 1, grid.size - 2))
    a, b, _ = np.polyfit(grid[i - 1:i + 2], cost[i - 1:i + 2], 2)
    return float(np.clip(-b / (2 * a), grid[i - 1], grid[i + 1])) if a > 0 else float(grid[i])


def law_kappa(data: ModelData, model: FaceModel, multi) -> float:
    """kappa in the model's drive: the multi-DU takes ``multi`` refitted with a scalar law
    instead of the pair vectors, y_n -> y_n (1 - kappa sum_other y_n' o_n'm), with o the other
    DU's relative pull (|D_n'm| / max_m |D_n'm|) or o = 1 (the same loss at every marker); the
    law that fits better gives kappa. Grid then parabola. The fallback of :func:`coupling_kappa`
    where no multi-DU take holds its DUs at full command: the model's y is the face's drive only
    up to a reparametrisation its paths absorb, and the reading follows it (up to about 40 % off
    the kappa in travel: benchmarks/coupling_reading.md)."""
    from mocap.analysis.model.effects import Coupling

    plain = without_coupling(model)
    pre = []
    for k in multi:
        t = data.takes[k]
        sh = model.take_shifts.get(t.name, {})
        shift = np.array([sh.get(d, 0.0) for d in t.dus])
        y = plain.response(data.tables(k, plain.effects), list(t.dus), t.trial, shift)
        obs = data.observed(k)
        ok = np.isfinite(obs).all(axis=-1) & data.used[None]
        pre.append((y, list(t.dus), np.where(ok[..., None], obs, 0.0), ok))
    if not pre:
        return 0.0
    grid = np.round(np.arange(-0.3, 1.2001, 0.05), 6)
    best = (np.inf, 0.0)

    def cost(v: float, uniform: bool) -> float:
        law = replace(plain, effects=plain.effects + (Coupling(float(v), uniform),))
        return sum(float(np.sum(np.where(ok[..., None], obs - law.displacement_from_response(y, dus),
                                         0.0) ** 2)) for y, dus, obs, ok in pre)

    for uniform in (False, True):
        v = parabola_min(grid, np.array([cost(v, uniform) for v in grid]))
        cv = cost(v, uniform)
        if cv < best[0]:
            best = (cv, v)
    return best[1]
