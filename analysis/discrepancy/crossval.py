"""Cross-validated fits of the discrepancy workflow: two fold models, each fitted on its fold's
takes and scored on the other fold's (held-out SSE in mm^2 over the scored markers, residuals per
take (S, M, 3) in mm); a candidate effect fitted beside its null; its gain where it acts; and the
runner that spreads the fits over processes."""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from mocap.analysis.model.face_model import OVERSAMPLE, FaceModel, actuator_series
from mocap.analysis.model.effects import CATALOGUE, FORMS
from mocap.analysis.model.data import ModelData
from mocap.analysis.model.fit import fit_curves, sse, take_residual
from mocap.analysis.model.profiles import profile_effect


@dataclass
class CVFit:
    """Two fold models (each fitted on its fold, scored on the other) and held-out scores."""

    models: list[FaceModel]
    sse: float  # held-out sum of squares, mm^2 (used markers)
    n: int  # held-out residual scalars
    values: list[float] = field(default_factory=list)  # the effect's global parameter per fold
    cls: type | None = None  # a candidate's effect class (the form kept, :data:`FORMS`)
    local: dict = field(default_factory=dict)  # where the candidate acts (:func:`local_gain`)
    intervals: list = field(default_factory=list)  # per fold: the values that fit alike, or None
    residuals: list | None = field(default=None, repr=False)  # held-out residuals, if kept
    null: "CVFit | None" = field(default=None, repr=False)  # a candidate at its null value,
    #                                                          fitted along the candidate's path

    @property
    def rms_mm(self) -> float:
        """RMS of the 3D residual vectors (mm)."""
        return float(np.sqrt(3.0 * self.sse / max(self.n, 1)))


def fold_takes(data: ModelData, f: int) -> list[int]:
    return [k for k, t in enumerate(data.takes) if t.fold == f]


def heldout(data: ModelData, models: list[FaceModel]) -> tuple[float, int, list[np.ndarray]]:
    """Held-out SSE (mm^2), scalar count and residuals (per take, (S, M, 3)) of fold models."""
    res = [take_residual(data, models[1 - t.fold], k) for k, t in enumerate(data.takes)]
    sse_k, count_k = _take_sums(res, data.used)
    return float(sum(sse_k)), int(sum(count_k)), res


def fold_sse(data: ModelData, model: FaceModel, fold: int) -> float:
    """SSE (mm^2) of ``model`` on the takes of ``fold``."""
    return sse(data, model, fold_takes(data, fold))[0]


def _take_sums(residuals: list[np.ndarray], used: np.ndarray) -> tuple[list[float], list[int]]:
    """Each take's SSE (mm^2) over the scored markers' finite residuals and their count, from
    per-take residuals (S, M, 3)."""
    sse_k, count_k = [], []
    for e in residuals:
        u = e[:, used]
        ok = np.isfinite(u)
        sse_k.append(float(np.sum(u[ok] ** 2)))
        count_k.append(int(ok.sum()))
    return sse_k, count_k


def take_sse(residuals: list[np.ndarray], used: np.ndarray) -> np.ndarray:
    """(n_takes,) each take's SSE (mm^2) over the scored markers' finite residuals, from
    per-take residuals (S, M, 3) (:func:`heldout` sums them)."""
    return np.array(_take_sums(residuals, used)[0])


def effective_n(residuals: list[np.ndarray], used: np.ndarray) -> float:
    """Effective number of independent residual scalars: n (1 - rho) / (1 + rho), rho the lag-1
    autocorrelation of the residual series (per take, marker, axis), pooled."""
    num = den = 0.0
    n = 0
    for e in residuals:
        u = e[:, used]
        u = u - np.nanmean(u, axis=0, keepdims=True)
        a, b = u[1:], u[:-1]
        ok = np.isfinite(a) & np.isfinite(b)
        num += float(np.sum(np.where(ok, a * b, 0.0)))
        den += float(np.sum(np.where(np.isfinite(u), u * u, 0.0)))
        n += int(np.isfinite(u).sum())
    rho = float(np.clip(num / den, 0.0, 0.999)) if den > 0 else 0.0
    return max(n * (1.0 - rho) / (1.0 + rho), 1.0)


def n_parameters(model: FaceModel, effect_name: str) -> int:
    """Parameters an effect adds: 1 for a global value, else per active curve (the form the
    model holds: a coupling law is one value, its pair vectors 3 per pair and marker and order
    term, 1 or 3 terms)."""
    held = model.effect(effect_name)
    cls = type(held) if held is not None else CATALOGUE[effect_name]
    if cls.pairwise:  # a 3D vector per DU pair driven together and marker (+ a law's value)
        terms = 1 if model.C2 is None else 1 + model.C2.shape[1]
        return (3 * terms * max(len(model.pairs), 1) * int(model.active.any(axis=0).sum())
                + int(not cls.per_curve))
    if cls.name == "takeshift":
        return max(sum(len(v) for v in model.take_shifts.values()), 1)
    if not cls.per_curve:
        return 1
    per = (1 if cls.frees_r else 0) + 3 * cls.n_bases
    return int(model.active.sum()) * max(per, 1)


def fit_base(data: ModelData, effects, takes) -> FaceModel:
    """The base model on ``takes``: a cold fit polished by a warm one, as converged as a
    candidate's final fit (else a candidate at its null value would win by the polish alone)."""
    m = fit_curves(data, effects, takes)
    return fit_curves(data, m.effects, takes, warm=m)


def cv_fit(data: ModelData, models: list[FaceModel]) -> tuple[CVFit, list[np.ndarray]]:
    """Two fold models scored on the other fold: the CVFit and its held-out residuals."""
    s, n, res = heldout(data, models)
    return CVFit(models, s, n), res


def cv_base(data: ModelData, effects) -> CVFit:
    return cv_fit(data, [fit_base(data, effects, fold_takes(data, f)) for f in (0, 1)])[0]


def reported_value(prof, cls) -> float:
    """The parameter a profile of ``cls`` identified, as the effect reports it: per-curve
    effects and a coupling law with pair vectors read it from the fitted model (kappa from the
    whole fit: the law's own value can be ~0 where the pair vectors carry the coupling), the
    other global effects are the profiled value."""
    if cls.per_curve or cls.pairwise:
        return prof.model.parameters()[cls.parameter]
    return prof.best


def cv_candidate(data: ModelData, current: CVFit, name: str, cls=None,
                 floor: float | None = None) -> CVFit | None:
    """The candidate fitted on each fold and scored on the other, beside its null (the effect
    at 0 fitted along the same path, ``CVFit.null``: the reference its evidence is scored
    against, :func:`~mocap.analysis.discrepancy.rules.candidate_evidence`); None when the fit
    on fold 0 does not lower the held-out SSE of fold 1 below its null's (screened out: not
    fitted on fold 1).
    ``cls`` : the effect class (default: each of the candidate's forms, :data:`FORMS`, the one
    with the larger held-out gain on its null kept: a form's training fit can win by fitting
    noise, a play of 2 units read on one fold lowered its training SSE below the stick-slip
    band's and doubled its held-out excess).  ``floor`` : the noise floor (mm);
    given, the fit's gain where it acts is measured too (:func:`local_gain`; a stick-slip dead
    band's where it holds, :func:`hold_gain`)."""
    forms = (cls,) if cls is not None else FORMS.get(name, (CATALOGUE[name],))
    best = None
    for form in forms:
        models, nulls, values, intervals = [], [], [], []
        for f in (0, 1):
            prof = profile_effect(data, current.models[f], form(), fold_takes(data, f), null=True)
            models.append(prof.model)
            nulls.append(prof.null)
            intervals.append(prof.interval)
            values.append(reported_value(prof, form))
            if f == 0 and fold_sse(data, prof.model, 1) >= fold_sse(data, prof.null, 1):
                models = None
                break
        if models is not None:
            s, n, res = heldout(data, models)
            s0, n0, res0 = heldout(data, nulls)
            # the form that gains the most on its own null (forms share none of their path)
            gain = s / s0
            if best is None or gain < best[0]:
                best = (gain, s, n, res, form, models, values, intervals,
                        CVFit(nulls, s0, n0, residuals=res0))
    if best is None:
        return None
    _, s, n, res, form, models, values, intervals, null = best
    local = {}
    if floor is not None:
        local = (hold_gain(data, null.residuals, res, models, floor) if form.acts_where_held
                 else local_gain(null.residuals, res, data.used, floor))
    return CVFit(models, s, n, values, form, local, intervals, null=null)


LOCAL_CHANGE = 0.5  # x noise floor: a candidate acts where it moves the prediction this much
HOLD_CHANGE = 1.0  # command units: a dead band holds where it moves the actuator this much


NO_LOCAL = {"n": 0, "explained": 0.0, "rms_gain_vs_noise": 0.0}


def local_gain(before: list[np.ndarray], after: list[np.ndarray], used: np.ndarray,
               floor: float, change: float = LOCAL_CHANGE) -> dict:
    """A candidate's gain where it acts: over the held-out residual vectors (per take (S, M, 3),
    mm) that it moves by more than ``change`` x the noise floor, how many (``n``), the fraction
    of their excess over the noise floor it removes (``explained``) and the RMS it removes over
    the noise floor (``rms_gain_vs_noise``). An effect that acts in a few places (a dead band at
    reversals) is plain there and invisible in the whole session's RMS."""
    masks = [(np.linalg.norm(e1 - e0, axis=-1) > change * floor) & used[None]
             for e0, e1 in zip(before, after)]
    return _gain_over(before, after, masks, floor)


def hold_gain(data: ModelData, before: list[np.ndarray], after: list[np.ndarray],
              models: list[FaceModel], floor: float, change: float = HOLD_CHANGE) -> dict:
    """A stick-slip dead band's gain where it holds: :func:`local_gain`'s numbers over the
    held-out residual vectors (per take (S, M, 3), mm; ``before`` its null's, ``after`` the
    band's) of the samples where the band holds a DU's actuator (it differs from the actuator
    without the band by more than ``change`` command units, as the fold model that predicts the
    take has it) and of the markers that DU moves; ``"where": "held"``. The band acts there and
    nowhere else, which the commands and its width say before any fit; the vectors the fit
    moved (:func:`local_gain`) also count the density's refit everywhere, and on a Bouc-Wen
    skin, whose own misfit gathers at the same reversals, a 12-unit band explained 18 % of
    theirs and 58 % of the held rows' (a 4-DU session; docs/discrepancy.md, "Where it acts")."""
    masks = []
    every = slice(None, None, OVERSAMPLE * data.stride)  # the fine grid at the samples
    for t in data.takes:
        m = models[1 - t.fold]
        without = tuple(e for e in m.effects if type(e).name != "backlash")
        a = actuator_series(t.rows, t.dus, t.n_frames, data.fps, m.effects)[every]
        a_0 = actuator_series(t.rows, t.dus, t.n_frames, data.fps, without)[every]
        held = np.abs(a - a_0) > change  # (S, n_dus)
        moves = data.active[[data.du_ids.index(d) for d in t.dus]]  # (n_dus, M)
        masks.append((held[:, :, None] & moves[None]).any(axis=1) & data.used[None])  # (S, M)
    return {**_gain_over(before, after, masks, floor), "where": "held"}


def _gain_over(before: list[np.ndarray], after: list[np.ndarray], masks: list[np.ndarray],
               floor: float) -> dict:
    """n, explained and rms_gain_vs_noise (:func:`local_gain`) over the residual vectors
    selected by ``masks`` (per take (S, M) bool) where both residuals are finite."""
    a0 = a1 = 0.0
    n = 0
    for e0, e1, sel in zip(before, after, masks):
        u0, u1 = e0[sel], e1[sel]  # (V, 3)
        ok = np.isfinite(u0).all(axis=-1) & np.isfinite(u1).all(axis=-1)
        a0 += float(np.sum(u0[ok] ** 2))
        a1 += float(np.sum(u1[ok] ** 2))
        n += int(ok.sum())
    if n == 0:
        return dict(NO_LOCAL)
    mse0, mse1 = a0 / n, a1 / n
    excess = mse0 - floor ** 2
    return {"n": n, "explained": float((mse0 - mse1) / excess) if excess > 0 else 0.0,
            "rms_gain_vs_noise": float((np.sqrt(mse0) - np.sqrt(mse1)) / floor)}


# ----------------------------------------------------------------------------------------------
# the process runner


_WORKER_DATA: ModelData | None = None


def _init_worker(data: ModelData) -> None:
    global _WORKER_DATA
    _WORKER_DATA = data
    import numba

    numba.set_num_threads(1)  # one process per core: no nested numba threads


def _base_task(effects, takes) -> FaceModel:
    return fit_base(_WORKER_DATA, effects, takes)


def _candidate_task(current: CVFit, name: str, floor: float | None):
    t0 = time.perf_counter()
    return name, cv_candidate(_WORKER_DATA, current, name, floor=floor), time.perf_counter() - t0


class _Runner:
    """Runs the base and candidate fits in this process or in a pool of spawned processes."""

    def __init__(self, data: ModelData, jobs: int):
        self.data = data
        self.pool = None
        if jobs > 1:
            from loky import ProcessPoolExecutor  # never re-runs the caller's __main__

            self.pool = ProcessPoolExecutor(jobs, initializer=_init_worker, initargs=(data,))

    def base_fits(self, effects, takes_sets) -> list:
        """:func:`fit_base` on each set of takes: FaceModels, one after the other without a
        pool; with one, Futures of them, submitted in the order given (so the fits needed first
        should come first) and running while the caller goes on."""
        if self.pool is None:
            return [fit_base(self.data, effects, t) for t in takes_sets]
        return [self.pool.submit(_base_task, effects, t) for t in takes_sets]

    def map(self, current: CVFit, names: list[str], floor: float | None = None):
        if self.pool is None:
            for name in names:
                t0 = time.perf_counter()
                yield (name, cv_candidate(self.data, current, name, floor=floor),
                       time.perf_counter() - t0)
        else:
            # the slowest candidates first (they profile the actuator; backlash in two forms)
            slow = {"backlash": 0, "deadtime": 1, "lag": 2}
            order = sorted(names, key=lambda n: slow.get(n, 9))
            light = replace(current, residuals=None)  # the workers recompute them
            futures = {n: self.pool.submit(_candidate_task, light, n, floor) for n in order}
            for name in names:
                yield futures[name].result()

    def close(self):
        if self.pool is not None:
            self.pool.shutdown()

