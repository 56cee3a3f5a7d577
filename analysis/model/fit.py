"""Identification of the face model (:mod:`mocap.analysis.model.face_model`) from measured takes.

Per DU and marker the curve parameters (alpha, beta, r) are fitted by Levenberg-Marquardt,
vectorised over the DU's markers, with the linear ones (D and the path-basis vectors B)
eliminated by variable projection (closed form for given responses); the play widths r read the
take's play table (:mod:`mocap.analysis.model.play_kernel`), so no play loop runs inside the iterations.
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

from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
import pandas as pd
from scipy.optimize import minimize_scalar

from mocap.analysis.model.face_model import (
    DENSITY_FRACTIONS,
    EQUAL_DENSITY,
    OVERSAMPLE,
    PI_BRANCH,
    R_MAX,
    FaceModel,
    actuator_effects,
    n_bases,
    pair_features,
    take_tables,
)
from mocap.analysis.model.curve_fit_kernel import tangent_products
from mocap.analysis.model.effects import Effect
from mocap.analysis.model.play_kernel import H_STEP, pi_logistic_from_table

BETA_STARTS = (60.0, 128.0, 196.0)
# where a cold fit starts the branch parameters (mix, kappa): the PI form (mix = 1, where their
# first derivatives vanish until the density moves) and off it (0.75), so that a Gauss-Newton
# step can move them either way; the better training fit is kept (the fit is not convex in
# them: from one start alone a PI face can stay at a mix well below 1)
BRANCH_STARTS = (np.array([1.0, 0.0]), np.array([0.75, 0.0]))
BRANCH_START = BRANCH_STARTS[1]


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


# ----------------------------------------------------------------------------------------------
# curve fits (per DU, vectorised over its markers)


@dataclass
class _Block:
    """Stacked single-DU training samples of one DU: table P (S, H), bias shift (S,),
    transformed observations v (S, M_n, 3), weights wt (S, M_n), the PI density q (F,) and each
    sample's trial (S,)."""

    P: np.ndarray
    shift: np.ndarray
    v: np.ndarray
    wt: np.ndarray
    q: np.ndarray | None = None
    trial: np.ndarray | None = None
    branch: np.ndarray = field(default_factory=lambda: PI_BRANCH.copy())

    @cached_property
    def by_curve(self) -> np.ndarray:
        """v curve by curve (M_n, S, 3), contiguous (the variable projection's layout)."""
        return np.ascontiguousarray(self.v.transpose(1, 0, 2))

    def sub(self, cols) -> "_Block":
        return _Block(self.P, self.shift, self.v[:, cols], self.wt[:, cols], self.q, self.trial,
                      self.branch)


def _block(data: ModelData, du: int, takes, effects, markers: np.ndarray,
           take_shifts: dict | None = None) -> _Block | None:
    ks = [k for k in takes if data.takes[k].dus == (du,)]
    if not ks:
        return None
    outs = tuple((type(e).__qualname__, float(e.value)) for e in effects
                 if type(e).stage == "output")
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
    ts = take_shifts or {}
    shift = np.concatenate([np.full(data.observed(k).shape[0],
                                    float(np.asarray(sum((e.beta_shift(data.takes[k].trial)
                                                          for e in effects), 0.0)))
                                    + ts.get(data.takes[k].name, {}).get(du, 0.0))
                            for k in ks])
    trial = np.concatenate([np.full(data.observed(k).shape[0], data.takes[k].trial) for k in ks])
    return _Block(P, shift, v, wt, EQUAL_DENSITY, trial)


def _responses(blk: _Block, p: np.ndarray, hyst: bool, derivatives: bool = False):
    """y (S, M) and, with ``derivatives``, dy/d(alpha, beta[, r]) (S, M, P), analytically."""
    r = p[:, 2] if hyst else np.zeros(p.shape[0])
    mix, kappa = (blk.branch if hyst else PI_BRANCH)
    out = pi_logistic_from_table(blk.P, r, p[:, 0], p[:, 1], blk.shift, DENSITY_FRACTIONS,
                                 derivatives, weights=blk.q, mix=mix, kappa=kappa)
    if not derivatives:
        return out
    y, dy = out
    return y, (dy if hyst else dy[..., :2])


def _project(blk: _Block, y: np.ndarray, effects, v: np.ndarray, wt: np.ndarray):
    """Variable projection: coefficients (M, K+1, 3), residual (S, M, 3), cost (M,).

    Per curve m, with the basis A_m = [y, bases(y)] (S, K+1) and weights w: the normal
    equations (A^T W A + 1e-9 I) c = A^T W v, as batched matrix products over curves."""
    Am = _path_basis(y.T, effects)  # (M, S, k): curve by curve
    k = Am.shape[-1]
    wAm = Am * wt.T[..., None]
    G = np.matmul(wAm.transpose(0, 2, 1), Am) + 1e-9 * np.eye(k)  # (M, k, k)
    vm = blk.by_curve if v is blk.v else np.ascontiguousarray(v.transpose(1, 0, 2))  # (M, S, 3)
    coef = np.linalg.solve(G, np.matmul(wAm.transpose(0, 2, 1), vm))  # (M, k, 3)
    em = vm - np.matmul(Am, coef)  # (M, S, 3)
    cost = np.einsum("msx,ms->m", em * em, wt.T)
    return coef, em.transpose(1, 0, 2), cost


def _path_basis(y: np.ndarray, effects) -> np.ndarray:
    """The path's basis (S, M, K + 1) of responses y (S, M): [y, b_1(y), ...]."""
    return np.stack([y] + [b for e in effects for b in e.bases(y)], axis=-1)


def _dpred_dy(y: np.ndarray, coef: np.ndarray, effects) -> np.ndarray:
    """d pred / d y (S, M, 3) of the path d = y D + sum_k b_k(y) B_k: D + sum_k b_k'(y) B_k, for
    responses y (S, M) and coefficients coef (M, K + 1, 3) = [D, B_1, ...]."""
    g = np.broadcast_to(coef[None, :, 0, :], y.shape + (3,))
    db = _basis_derivatives(y, effects)
    for k in range(db.shape[-1]):
        g = g + db[..., k, None] * coef[None, :, k + 1, :]
    return g


def _basis_derivatives(y: np.ndarray, effects) -> np.ndarray:
    """d b_k / d y of the path's extra bases (S, M, K) at responses y (S, M) (K may be 0)."""
    db = [b for e in effects for b in e.bases_derivative(y)]
    return np.stack(db, axis=-1) if db else np.zeros(y.shape + (0,))


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
        ge, gg = tangent_products(_basis_derivatives(y, effects), coef, e, wt)
        J = np.ascontiguousarray(dy[..., :npar].transpose(1, 0, 2))  # (M, S, P)
        b = np.matmul(ge.T[:, None, :], J)[:, 0]  # (M, P)
        H = np.matmul((J * gg.T[..., None]).transpose(0, 2, 1), J)  # (M, P, P)
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
        if better.all():  # the usual case: every curve's step taken (no copies)
            p, y, dy, coef, e, cost = q, y_new, dy_new, coef_new, e_new, cost_new
        elif better.any():
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
    return FaceModel(branch=np.tile(BRANCH_START, (N, 1)), fps=data.fps,
                     marker_names=data.marker_names, rest_mm=data.rest_mm,
                     du_ids=data.du_ids, active=data.active.copy(),
                     alpha=np.full((N, M), 0.03), beta=np.full((N, M), 128.0),
                     r=np.where(any(type(e).frees_r for e in effects), 8.0, 0.0) * np.ones((N, M)),
                     D=np.zeros((N, M, 3)), B=np.zeros((N, M, n_bases(effects), 3)),
                     effects=tuple(effects))


def fit_curves(data: ModelData, effects, takes, warm: FaceModel | None = None,
               iters: int = 30, rounds: int | None = None) -> FaceModel:
    """Fit the model's per-DU and per-curve parts on ``takes`` (indices into data.takes).

    Curves (alpha, beta[, r], D, B) on the single-DU takes (:func:`_fit_all_curves`); with
    ``hysteresis``, each DU's PI density over :data:`DENSITY_FRACTIONS` (non-negative, summing to
    1) and branch parameters (mix, kappa) by projected Gauss-Newton steps, pulled towards the
    DUs' shared ones (:func:`_update_density`); with ``takeshift``, each take's bias shift per DU
    (:func:`conditional_shifts`, centred per DU into the biases); these alternate with the
    curves (three rounds from cold, two from a warm start with ``iters`` >= 30; one round, the
    density and shifts kept from ``warm``, inside profiles). A warm fit with ``iters`` >= 30 then
    polishes each DU's curves and branch parameters (and its density, where its takes hold minor
    loops) together, :data:`JOINT_ROUNDS` times (:func:`_joint_round`): the alternation alone
    creeps towards the optimum over tens of rounds. With a pairwise effect
    (``coupling``), the vectors C of every DU pair driven together in ``takes`` are fitted last
    by linear least squares on those takes.
    """
    effects = tuple(effects)
    hyst = any(type(e).frees_r for e in effects)
    shifting = any(type(e).name == "takeshift" for e in effects)
    density = None
    branch = None
    shifts: dict = {}
    if warm is not None:
        density = warm.density.copy()
        branch = warm.branch.copy()
        if shifting:
            shifts = dict(warm.take_shifts)
    if rounds is None:
        rounds = 1
        if hyst or shifting:
            rounds = 3 if warm is None else (2 if iters >= 30 else 1)

    def run(density, branch, shifts):
        model = None
        for rnd in range(rounds):
            model = _fit_all_curves(data, effects, takes, model if rnd else warm, iters, density,
                                    shifts, branch)
            if rnd == rounds - 1:
                break
            if hyst:
                density, branch = _update_density(data, model, takes)
                model.density, model.branch = density, branch
            if shifting:
                shifts = _update_shifts(data, model, takes)
                model.take_shifts = shifts
        return model

    if warm is None and hyst:  # the branch parameters from each start; the best training fit
        fits = [run(density, np.tile(b, (len(data.du_ids), 1)), shifts) for b in BRANCH_STARTS]
        model = fits[int(np.argmin([sse(data, m, takes)[0] for m in fits]))]
    else:
        model = run(density, branch, shifts)
        if hyst and warm is not None and rounds >= 2 and iters >= 30:
            # the alternation creeps (a curve step holds the density, a density step the
            # curves): polish both together, from where it stopped
            for _ in range(JOINT_ROUNDS):
                if shifting:
                    model.take_shifts = _update_shifts(data, model, takes)
                _joint_round(data, model, takes)
                model = _fit_all_curves(data, effects, takes, model, 0, model.density,
                                        model.take_shifts, model.branch)
    if any(type(e).pairwise for e in effects):
        model = _fit_pairs_and_shifts(data, model, takes, shifting)
    return model


def _fit_pairs_and_shifts(data: ModelData, model: FaceModel, takes, shifting: bool) -> FaceModel:
    """The pair vectors of ``model`` fitted on ``takes``, and with take shifts the multi-DU
    takes' shifts and the pair vectors identified in turn (:data:`PAIR_ROUNDS`), from two starts:
    the shifts as they stand, and the multi-DU takes' shifts at 0 (a take's shift is the face's
    trial-to-trial jitter, zero-mean). The shifts as they stand were identified without the pair
    terms and hold part of the coupling (a bias shift lowers a DU's response as a loss does),
    and the alternation only creeps away from there (a 3-DU smile's shifts can stay tens of
    command units off where the face draws a few). The start with the lower training SSE is
    kept."""
    if not shifting:
        _fit_pairs(data, model, takes)
        return model
    multi = multi_du_takes(data, takes)
    fits = []
    for zero in ((False, True) if multi else (False,)):
        m = replace(model, take_shifts=dict(model.take_shifts), info=dict(model.info))
        if zero:
            for k in multi:
                m.take_shifts[data.takes[k].name] = {int(d): 0.0 for d in data.takes[k].dus}
        _fit_pairs(data, m, takes, kappa=False)
        for _ in range(PAIR_ROUNDS):
            _refresh_shifts(data, m, multi)
            _fit_pairs(data, m, takes, kappa=False)
        fits.append(m)
    # the starts differ only on the multi-DU takes (their shifts; the pair terms act nowhere
    # else), so they are compared there; kappa is read once, for the one kept
    best = fits[0] if len(fits) == 1 else min(fits, key=lambda m: sse(data, m, multi)[0])
    best.info["coupling_kappa"] = coupling_kappa(data, best, takes)
    return best


PAIR_ROUNDS = 2  # shifts <-> pair vectors alternations after the pairs' first fit


def multi_du_takes(data: ModelData, takes) -> list[int]:
    """The takes among ``takes`` (indices) that drive several DUs at once."""
    return [k for k in takes if len(data.takes[k].dus) >= 2]


def _fit_all_curves(data: ModelData, effects, takes, warm: FaceModel | None, iters: int,
                    density: np.ndarray | None, shifts: dict,
                    branch: np.ndarray | None = None) -> FaceModel:
    """Every DU's curves, the density (N, F) given (None: equal plays) and the take shifts
    ({take name: {DU: shift}}) held; see :func:`fit_curves`."""
    model = empty_model(data, effects)
    model.take_shifts = dict(shifts)
    if density is not None:
        model.density = density.copy()
    if branch is not None:
        model.branch = branch.copy()
    hyst = model.hysteresis
    K = n_bases(effects)
    for n, du in enumerate(data.du_ids):
        act = np.flatnonzero(data.active[n])
        if act.size == 0:
            continue
        blk = _block(data, du, takes, effects, act, shifts)
        if blk is None:
            model.active[n] = False
            continue
        blk.q = model.density[n]
        blk.branch = model.branch[n]
        strong = data.strong[n, act]
        if not strong.any():
            strong = np.ones(act.size, bool)
        sb = blk.sub(strong)
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
            tiled = _Block(sb.P, sb.shift, np.tile(sb.v, (1, starts, 1)), np.tile(sb.wt, (1, starts)),
                           sb.q, sb.trial, sb.branch)
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
            wb = blk.sub(weak)
            y_weak = np.repeat(_responses(wb, p[weak][:1], hyst), int(weak.sum()), axis=1)  # one shape
            coef[weak] = _project(wb, y_weak, effects, wb.v, wb.wt)[0]
        model.alpha[n, act], model.beta[n, act] = p[:, 0], p[:, 1]
        model.r[n, act] = p[:, 2] if hyst else 0.0
        model.D[n, act] = coef[:, 0]
        if K:
            model.B[n, act] = coef[:, 1:]
    return model


def _du_parts(data: ModelData, model: FaceModel, takes, n: int, du: int):
    """A DU's strong curves' block, parameters (Ms, 3), coefficients and derivative factor:
    (blk, p, y, dy (S, Ms, 3), g = d pred / d y (S, Ms, 3), residual (S, Ms, 3)); None when the
    DU has no single-DU takes."""
    act = np.flatnonzero(model.active[n] & data.strong[n])
    if act.size == 0:
        act = np.flatnonzero(model.active[n])
    if act.size == 0:
        return None
    blk = _block(data, du, takes, model.effects, act, model.take_shifts)
    if blk is None:
        return None
    blk.q = model.density[n]
    blk.branch = model.branch[n]
    p = np.column_stack([model.alpha[n, act], model.beta[n, act], model.r[n, act]])
    y, dy = _responses(blk, p, True, derivatives=True)
    coef = np.concatenate([model.D[n, act][:, None], model.B[n, act]], axis=1)  # (Ms, K+1, 3)
    g = np.broadcast_to(coef[None, :, 0, :], blk.v.shape)
    pred = y[..., None] * coef[None, :, 0, :]
    kk = 1
    for ef in model.effects:
        for basis, db in zip(ef.bases(y), ef.bases_derivative(y)):
            g = g + db[..., None] * coef[None, :, kk, :]
            pred = pred + basis[..., None] * coef[None, :, kk, :]
            kk += 1
    return blk, p, act, y, dy, g, blk.v - pred


SHARED_PULL = 0.05  # a DU's density is pulled towards the DUs' shared one with this x its
#                    data's mean curvature (where its own takes say nothing, the shared one holds)


BRANCH_BOUNDS = ((0.0, 1.0), (-1.5, 1.5))  # (mix, kappa)


def _mix_terms(blk: _Block, p: np.ndarray, q: np.ndarray, branch: np.ndarray):
    """The response y (S, Ms) and its Jacobian J (S, F + 2, Ms) in the DU's density q (F,) and
    branch parameters (mix, kappa), the curves p (Ms, 3) held (numpy; the fitter's density step).

    y = sum_f q_f L(x_f; alpha, b_f), x_f = mix w + (1 - mix) P_f, w = sum_g q_g P_g,
    b_f = beta + s + kappa (f - fbar) r, fbar = sum_g q_g f_g."""
    fr = DENSITY_FRACTIONS
    H = blk.P.shape[1]
    r = p[:, 2]
    x = np.clip(fr[:, None] * r[None, :] / H_STEP, 0.0, H - 1 - 1e-9)  # (F, Ms)
    i0 = np.floor(x).astype(np.int64)
    lam = x - i0
    Q = blk.P[:, i0] * (1 - lam) + blk.P[:, np.minimum(i0 + 1, H - 1)] * lam  # (S, F, Ms)
    mix, kappa = float(branch[0]), float(branch[1])
    w = np.einsum("sfm,f->sm", Q, q)
    fbar = float(q @ fr)
    xf = mix * w[:, None] + (1.0 - mix) * Q
    off = kappa * (fr - fbar)  # (F,)
    al = p[None, None, :, 0]
    bb = p[None, None, :, 1] + blk.shift[:, None, None] + off[None, :, None] * r[None, None]
    sg = 1.0 / (1.0 + np.exp(np.clip(-al * (xf - bb), -700, 700)))
    lo = 1.0 / (1.0 + np.exp(np.clip(al * bb, -700, 700)))
    hi = 1.0 / (1.0 + np.exp(np.clip(-al * (255.0 - bb), -700, 700)))
    span = np.maximum(hi - lo, 1e-12)
    L = (sg - lo) / span
    dx = al * sg * (1.0 - sg) / span
    db = (-al * sg * (1 - sg) + al * lo * (1 - lo)) / span - L / span * (-al * hi * (1 - hi) + al * lo * (1 - lo))
    y = np.einsum("sfm,f->sm", L, q)
    Gx = np.einsum("sfm,f->sm", dx, q)
    Gb = np.einsum("sfm,f->sm", db, q)
    Jq = L + mix * Q * Gx[:, None] - kappa * fr[None, :, None] * r[None, None] * Gb[:, None]
    Jmix = np.einsum("sfm,f->sm", dx * (w[:, None] - Q), q)
    Jkap = np.einsum("sfm,f->sm", db * (fr - fbar)[None, :, None], q) * r[None]
    return y, np.concatenate([Jq, Jmix[:, None], Jkap[:, None]], axis=1)


def _density_problem(data: ModelData, model: FaceModel, takes, n: int, du: int):
    """A DU's Gauss-Newton model of the training cost in theta = (q (F,), mix, kappa):
    cost ~ theta^T A theta - 2 z^T theta + const; (A, z, (blk, p, act)) or None."""
    parts = _du_parts(data, model, takes, n, du)
    if parts is None:
        return None
    blk, p, act, y, dy, g, e = parts
    _, J = _mix_terms(blk, p, model.density[n], model.branch[n])
    gg = np.einsum("smx,smx->sm", g, g)
    ge = np.einsum("smx,smx->sm", g, e)
    A = np.einsum("sfm,sgm->fg", J * (blk.wt * gg)[:, None], J)
    b = np.einsum("sfm,sm->f", J, blk.wt * ge)
    theta = np.concatenate([model.density[n], model.branch[n]])
    return A, A @ theta + b, (blk, p, act)


def _theta_lsq(A: np.ndarray, z: np.ndarray) -> np.ndarray:
    """argmin theta^T A theta - 2 z^T theta over the density's simplex (q >= 0, sum 1) and the
    branch parameters' bounds (:data:`BRANCH_BOUNDS`)."""
    from scipy.optimize import lsq_linear

    F = DENSITY_FRACTIONS.size
    K = A.shape[0]
    scale = np.trace(A[:F, :F]) / F + 1e-300
    R = np.linalg.cholesky(A + 1e-8 * scale * np.eye(K))
    rhs = np.linalg.solve(R, z)  # min |R^T theta - rhs|^2 = theta^T A theta - 2 z^T theta + c
    big = 1e3 * np.sqrt(scale)
    row = np.concatenate([np.ones(F), np.zeros(K - F)])
    lo = np.concatenate([np.zeros(F), [b[0] for b in BRANCH_BOUNDS]])
    hi = np.concatenate([np.full(F, np.inf), [b[1] for b in BRANCH_BOUNDS]])
    sol = lsq_linear(np.vstack([R.T, big * row]), np.append(rhs, big), bounds=(lo, hi),
                     method="bvls")
    th = sol.x.copy()
    th[:F] = np.maximum(th[:F], 0.0)
    th[:F] /= max(th[:F].sum(), 1e-12)
    return th


def _turns_inside(data: ModelData, k: int) -> bool:
    """Whether take k's commands turn back inside the range (a minor loop), cached per take."""
    key = ("turns", k)
    if key not in data._tables:
        from mocap.analysis.model.effects import command_moves

        data._tables[key] = any(command_moves(g)[2] for _, g in data.takes[k].rows.groupby("du"))
    return data._tables[key]


def _has_minor_loops(data: ModelData, du: int, takes) -> bool:
    """Whether a single-DU take of ``du`` among ``takes`` turns back inside the range."""
    return any(data.takes[k].dus == (du,) and _turns_inside(data, k) for k in takes)


def _update_density(data: ModelData, model: FaceModel, takes):
    """One projected Gauss-Newton step of each DU's density q (F,) (q >= 0, sum 1) and branch
    parameters (mix, kappa), with a halving line search on the training cost; the curves held.

    Full sweeps say little of the density (they reverse where the sigmoid saturates): a DU
    without minor loops among its training takes borrows them from the DUs with some. The DUs
    share the skin's hysteresis in units of each curve's own width r: such a DU's density step
    is pulled towards the density of the DUs with minor loops (their Gauss-Newton problems
    summed, each normalised to its mean curvature) by SHARED_PULL x its own mean curvature; a
    DU with minor loops of its own keeps its own (without the pull, a DU's full sweeps spread its
    density to hold per-marker branch asymmetries, which predicts minor loops that are not flat
    after a reversal).

    Returns (density (N, F), branch (N, 2))."""
    F = DENSITY_FRACTIONS.size
    dens, br = model.density.copy(), model.branch.copy()
    probs = {}
    for n, du in enumerate(data.du_ids):
        pr = _density_problem(data, model, takes, n, du)
        if pr is not None:
            probs[n] = pr
    if not probs:
        return dens, br
    minor = {n: _has_minor_loops(data, data.du_ids[n], takes) for n in probs}
    teach = [n for n in probs if minor[n]] or list(probs)
    sc = {n: np.trace(A[:F, :F]) / F + 1e-300 for n, (A, _, _) in probs.items()}
    shared = _theta_lsq(sum(probs[n][0] / sc[n] for n in teach),
                        sum(probs[n][1] / sc[n] for n in teach))
    for n, (A, z, (blk, p, _)) in probs.items():
        # the density only: each DU keeps its own branch parameters (the shape of its forward
        # and backward branches, which its full sweeps do show); pulling them too read a
        # hidden coupling 20 % lower on a branch-play face
        mu = (0.0 if minor[n] else SHARED_PULL * sc[n]) * np.r_[np.ones(F), 0.0, 0.0]
        theta = np.concatenate([model.density[n], model.branch[n]])
        new = _theta_lsq(A + np.diag(mu), z + mu * shared)

        def cost(th, blk=blk, p=p, mu=mu):
            return _du_cost(blk, p, th, model.effects) + float(np.sum(mu * (th - shared) ** 2))

        c0 = cost(theta)
        for _ in range(5):
            if cost(new) < c0:
                dens[n], br[n] = new[:F], new[F:]
                break
            new = 0.5 * (theta + new)
    return dens, br


def _du_cost(blk: _Block, p: np.ndarray, theta: np.ndarray, effects) -> float:
    """A DU's training cost (mm^2) with its strong curves p (Ms, 3) and theta = (q (F,), mix,
    kappa), the path coefficients projected out."""
    F = DENSITY_FRACTIONS.size
    b = _Block(blk.P, blk.shift, blk.v, blk.wt, theta[:F], blk.trial, theta[F:])
    return float(np.sum(_project(b, _responses(b, p, True), effects, blk.v, blk.wt)[2]))



# ----------------------------------------------------------------------------------------------
# joint polish: Levenberg-Marquardt over a DU's curves and its branch parameters (and density)
# together, after the alternation

JOINT_ROUNDS = 2  # joint polish rounds of a warm fit with iters >= 30 and 2 rounds or more
JOINT_ITERS = 12  # joint steps per round at most
JOINT_TOL = 1e-6  # relative cost decrease of an accepted step below which a DU has converged


def _joint_normal(blk: _Block, p: np.ndarray, theta: np.ndarray, effects):
    """A DU's Gauss-Newton normal equations in its strong curves' (alpha, beta, r) and its
    (q (F,), mix, kappa), the linear path coefficients projected out (Kaufman's variable-projection
    Jacobian: each parameter's column taken off its curve's basis span).

    Returns (H (Ms, P, P), b (Ms, P)): per curve, the projected J^T W J and J^T W e over the
    columns (alpha, beta, r, q, mix, kappa); the DU's shared block is their sum over curves."""
    F = DENSITY_FRACTIONS.size
    blk_t = _Block(blk.P, blk.shift, blk.v, blk.wt, theta[:F], blk.trial, theta[F:])
    y, dy = _responses(blk_t, p, True, derivatives=True)
    _, Jt = _mix_terms(blk_t, p, theta[:F], theta[F:])  # (S, F + 2, Ms)
    coef, e, _ = _project(blk_t, y, effects, blk.v, blk.wt)
    A = _path_basis(y, effects)  # (S, Ms, k)
    g = _dpred_dy(y, coef, effects)
    Y = np.concatenate([dy, Jt.transpose(0, 2, 1)], axis=-1)  # (S, Ms, P): d y / d parameter
    w = blk.wt
    wg = g * w[..., None]  # (S, Ms, 3)
    UU = np.einsum("sm,smi,smj->mij", np.einsum("smx,smx->sm", g, wg), Y, Y, optimize=True)
    AU = np.einsum("smk,smx,smi->mxki", A, wg, Y, optimize=True)  # (Ms, 3, k, P)
    G = np.einsum("smk,sm,sml->mkl", A, w, A, optimize=True) + 1e-9 * np.eye(A.shape[-1])
    GiAU = np.linalg.solve(G[:, None], AU)
    H = UU - np.einsum("mxki,mxkj->mij", AU, GiAU, optimize=True)
    b = np.einsum("smi,sm->mi", Y, np.einsum("smx,smx->sm", wg, e), optimize=True)
    return H, b


def _joint_du(blk: _Block, p: np.ndarray, theta: np.ndarray, effects, free_density: bool,
              iters: int = JOINT_ITERS, tol: float = JOINT_TOL) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt over one DU's strong curves p (Ms, 3) and theta = (q (F,), mix, kappa)
    together (the density only with ``free_density``; on its simplex, the branch parameters in
    :data:`BRANCH_BOUNDS`). The normal equations are an arrowhead (a 3 x 3 block per curve, a
    dense border for theta): the curves are eliminated (Schur complement), theta's step solved
    under its constraints, the curves' steps substituted back. Returns (p, theta)."""
    F = DENSITY_FRACTIONS.size
    border = np.arange(3, 3 + F + 2) if free_density else np.arange(3 + F, 3 + F + 2)
    cost = _du_cost(blk, p, theta, effects)
    lam = 1e-3
    for _ in range(iters):
        H, b = _joint_normal(blk, p, theta, effects)
        Hpp, Hpt = H[:, :3, :3], H[:, :3][:, :, border]
        Htt = H[:, border][:, :, border].sum(axis=0)
        bp, bt = b[:, :3], b[:, border].sum(axis=0)
        step_taken = False
        while lam < 1e8:
            Hd = Hpp + lam * np.einsum("mii->mi", Hpp)[..., None] * np.eye(3) + 1e-12 * np.eye(3)
            Hinv = np.linalg.inv(Hd)
            W = np.einsum("mji,mjk->mik", Hpt, Hinv)  # (Ms, T, 3): Hpt^T Hpp^-1
            S = Htt + lam * np.diag(np.diag(Htt)) - np.einsum("mik,mkj->ij", W, Hpt)
            z = bt - np.einsum("mik,mk->i", W, bp)
            S = 0.5 * (S + S.T)
            new = theta.copy()
            if free_density:
                new = _theta_lsq(S, S @ theta + z)
            else:
                lo, hi = np.array(BRANCH_BOUNDS).T
                new[F:] = np.clip(theta[F:] + np.linalg.solve(S + 1e-12 * np.trace(S) * np.eye(2), z),
                                  lo, hi)
            dth = (new - theta)[border - 3]
            dp = np.einsum("mij,mj->mi", Hinv, bp - np.einsum("mij,j->mi", Hpt, dth))
            q = p + dp
            q[:, 0] = np.clip(q[:, 0], 1e-3, 0.5)
            q[:, 1] = np.clip(q[:, 1], -100.0, 355.0)
            q[:, 2] = np.clip(q[:, 2], 0.0, R_MAX)
            c_new = _du_cost(blk, q, new, effects)
            if c_new < cost:
                rel = (cost - c_new) / max(cost, 1e-300)
                p, theta, cost = q, new, c_new
                lam = max(lam / 4, 1e-9)
                step_taken = True
                break
            lam *= 6
        if not step_taken or rel < tol:
            break
    return p, theta


def _joint_round(data: ModelData, model: FaceModel, takes) -> None:
    """Every DU's strong curves and branch parameters by joint steps (:func:`_joint_du`), with
    its density too where its training takes hold minor loops (elsewhere the density stays as
    the alternation pulled it: full sweeps alone do not identify it); in place. The weak curves'
    shapes and every path coefficient are refitted after (by the caller)."""
    F = DENSITY_FRACTIONS.size
    for n, du in enumerate(data.du_ids):
        parts = _du_parts(data, model, takes, n, du)
        if parts is None:
            continue
        blk, p, act = parts[:3]
        theta = np.concatenate([model.density[n], model.branch[n]])
        p_new, th = _joint_du(blk, p, theta, model.effects, _has_minor_loops(data, du, takes))
        model.alpha[n, act], model.beta[n, act], model.r[n, act] = p_new.T
        model.density[n], model.branch[n] = th[:F], th[F:]


def _update_shifts(data: ModelData, model: FaceModel, takes) -> dict:
    """Each training take's bias shift per DU (:func:`conditional_shifts`), centred per DU over
    its single-DU takes with the centre moved into the DU's biases (the same predictions)."""
    out = {data.takes[k].name: conditional_shifts(data, model, k) for k in takes}
    for n, du in enumerate(data.du_ids):
        v = [out[data.takes[k].name][du] for k in takes if data.takes[k].dus == (du,)]
        if not v:
            continue
        c = float(np.median(v))
        model.beta[n] += c
        for sh in out.values():
            if du in sh:
                sh[du] -= c
    return out


def _refresh_shifts(data: ModelData, model: FaceModel, takes) -> None:
    """The bias shifts of ``takes`` (indices) identified again on ``model`` as it stands
    (:func:`conditional_shifts`, not centred), the other takes' kept; in place."""
    model.take_shifts = {**model.take_shifts,
                         **{data.takes[k].name: conditional_shifts(data, model, k) for k in takes}}


SHIFT_TOL = 1e-3  # command units: a take's shift converged


def conditional_shifts(data: ModelData, model: FaceModel, k: int, iters: int = 2,
                       step: float = 0.5, limit: float = 30.0) -> dict:
    """The bias shift per DU {DU: command units} that best fits take k's own measurement, the
    rest of the model held: Gauss-Newton from the model's stored shift (or 0), with the
    Jacobian from finite differences of ``step`` at the start (the chord method: later steps
    reuse it, so each costs one prediction instead of one per DU and more); bounded to
    +-``limit``. Takes of DUs the model does not know: {}."""
    t = data.takes[k]
    dus = [d for d in t.dus if d in model.du_ids]
    if not dus:
        return {}
    tables = data.tables(k, model.effects)
    obs = data.observed(k)
    ok = np.isfinite(obs).all(axis=-1) & data.used[None]
    s = np.array([model.take_shifts.get(t.name, {}).get(d, 0.0) if d in t.dus else 0.0
                  for d in t.dus], float)
    J = solve = None
    dus_ = list(t.dus)
    for _ in range(iters):
        y = model.response(tables, dus_, t.trial, s)
        pred = model.displacement_from_response(y, dus_)
        e = np.where(ok[..., None], obs - pred, 0.0)
        if J is None:
            J = []
            for j in range(len(t.dus)):
                sj = s.copy()
                sj[j] += step
                yj = y.copy()  # a DU's shift moves its own response only
                yj[:, j] = model.response(tables[j:j + 1], dus_[j:j + 1], t.trial, sj[j:j + 1])[:, 0]
                J.append(np.where(ok[..., None], model.displacement_from_response(yj, dus_)
                                  - pred, 0.0).ravel() / step)
            J = np.stack(J, axis=0)  # (n, S * M * 3); einsum: no BLAS threads for tiny products
            JtJ = np.einsum("ij,kj->ik", J, J)
            if not np.all(np.isfinite(JtJ)) or np.trace(JtJ) <= 0:
                break
            solve = JtJ + 1e-9 * np.trace(JtJ) * np.eye(len(s))
        ds = np.linalg.solve(solve, np.einsum("ij,j->i", J, e.ravel()))
        s = np.clip(s + ds, -limit, limit)
        if np.max(np.abs(ds)) < SHIFT_TOL:  # converged: a further step would not move it
            break
    return {int(d): float(v) for d, v in zip(t.dus, s)}


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


# ----------------------------------------------------------------------------------------------
# scoring


def take_residual(data: ModelData, model: FaceModel, k: int) -> np.ndarray:
    """Measured minus predicted displacement (S, M, 3) mm of take k (NaN where missing)."""
    t = data.takes[k]
    shift = None
    if model.shifts_takes:
        sh = conditional_shifts(data, model, k)
        shift = np.array([sh.get(d, 0.0) for d in t.dus])
    pred = model.predict_tables(data.tables(k, model.effects), list(t.dus), t.trial, shift)
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
