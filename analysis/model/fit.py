"""Identification of the face model (:mod:`mocap.analysis.model.face_model`) from measured takes.

Per DU and marker the curve parameters (alpha, beta, r) are fitted by Levenberg-Marquardt,
vectorised over the DU's markers, with the linear ones (D and the path-basis vectors B)
eliminated by variable projection (closed form for given responses); the play widths r read the
take's play table (:mod:`mocap.analysis.model.play_kernel`), so no play loop runs inside the iterations.
Curves are fitted on single-DU takes only; takes with several DUs inform the global parameters of
interaction effects (``coupling``) and are predicted like any other.

The curves alternate with each DU's PI density and branch parameters
(:mod:`mocap.analysis.model.density`) and each take's bias shifts (here); the pair vectors of a
coupling are fitted last (:mod:`mocap.analysis.model.coupling`). The containers are in
:mod:`mocap.analysis.model.data`, the curves' Levenberg-Marquardt in
:mod:`mocap.analysis.model.curves`, the profiles of global parameters in
:mod:`mocap.analysis.model.profiles`. Scores are sums of squared residuals in mm^2.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from mocap.analysis.model.coupling import _fit_pairs, coupling_kappa
from mocap.analysis.model.curves import _block, _Block, _lm_curves, _project, _responses
from mocap.analysis.model.data import ModelData, multi_du_takes
from mocap.analysis.model.density import JOINT_ROUNDS, _joint_round, _update_density
from mocap.analysis.model.face_model import FaceModel, n_bases

BETA_STARTS = (60.0, 128.0, 196.0)
# where a cold fit starts the branch parameters (mix, kappa): the PI form (mix = 1, where their
# first derivatives vanish until the density moves) and off it (0.75), so that a Gauss-Newton
# step can move them either way; the better training fit is kept (the fit is not convex in
# them: from one start alone a PI face can stay at a mix well below 1)
BRANCH_STARTS = (np.array([1.0, 0.0]), np.array([0.75, 0.0]))
BRANCH_START = BRANCH_STARTS[1]


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


# ----------------------------------------------------------------------------------------------
# take shifts


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
