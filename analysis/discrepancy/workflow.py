"""The model-discrepancy workflow: find where the face model and the measurement disagree,
name the missing effect, add it, show the gap shrink.

1. Fit the base model (:data:`mocap.analysis.model.effects.BASE`: a PI hysteresis density +
   logistic, each marker's own path, a bias shift per take and DU; what every face has,
   :mod:`mocap.analysis.model.fit`) on identification takes.
2. Predict every take and compare with the measurement; residuals per take, DU, marker and
   phase of the command (:func:`phases`).
3. Localise the disagreement against the measurement's own noise floor (:func:`noise_floor`,
   from repeated trials).
4. For each candidate effect (:data:`mocap.analysis.model.effects.CATALOGUE`) fit the extended model
   and score it on held-out takes: two-fold cross-validation over takes (repetitions and
   schedules alternate between folds, :func:`assign_folds`), scored by a held-out BIC,
   ``n_eff ln(SSE_cand / SSE_cur) + dk ln(n_eff)`` with ``n_eff`` the residuals' effective
   sample size (their lag-1 autocorrelation discounts the samples).
   A candidate is scored against its null: the effect at 0 fitted along the same path (the
   same warm start, iterations and polish), so a fit's extra polish is not read as the effect.
5. Name the best candidate when its score beats its null by ``margin`` (10), it
   explains at least ``min_explained`` (20 %) of the held-out excess over the noise floor and
   removes at least ``min_rms_gain`` (3 %) of a noise floor from the held-out RMS (or, with
   ``local``, on by default, does as much where it acts, :func:`local_gain`; a stick-slip dead
   band where it holds, :func:`hold_gain`), its
   parameter is physically plausible in both folds, and the
   session's takes can test it; else "no missing effect found". A candidate with several forms
   (:data:`mocap.analysis.model.effects.FORMS`: backlash as a play or a stick-slip dead band) is
   fitted in each and keeps the one that gains the most on its own null in held-out takes.
6. Add it and repeat (forward stepwise; a named effect's parameter is re-identified on all
   takes, with its uncertainty from the profile). Then a backlash the base's hysteresis
   absorbed (no held-out gain: a play before the skin's plays is one operator with wider plays):
   the widest play the takes allow before the final model, the edge of its profile
   (:func:`dead_band_step`, :mod:`mocap.analysis.discrepancy.dead_band`), named when it is at least half a
   command step of the takes and the model with it predicts the held-out takes no worse. Drift
   last, from the final model: the trend
   over trials of the takes' bias shifts (:func:`drift_step`), named when it stands out of the
   takes' random scatter, reported as an alternative when it only half does.
7. Report held-out residuals before and after each step, per DU and marker, in mm and relative
   to the noise floor.

Pure computations on :class:`mocap.analysis.model.data.ModelData`; I/O is in :mod:`mocap.workflows.discrepancy.results`.
"""

from __future__ import annotations

import time
from concurrent.futures import Future
from dataclasses import dataclass, field, replace

import numpy as np

from mocap.analysis.discrepancy.dead_band import dead_band_edge, walk
from mocap.analysis.model.face_model import OVERSAMPLE, FaceModel, actuator_series, make_effects
from mocap.analysis.model.effects import (
    BASE,
    CANDIDATES,
    CATALOGUE,
    FORMS,
    ScheduleSummary,
    command_moves,
    summarize_schedules,
)
from mocap.analysis.model.data import ModelData, TakeData
from mocap.analysis.model.fit import fit_curves, sse, take_residual
from mocap.analysis.model.profiles import profile_effect, profile_uncertainty

PHASES = ("rest", "hold", "rise-fast", "rise", "rise-slow", "fall-fast", "fall", "fall-slow",
          "reversal")


@dataclass(frozen=True)
class DiscrepancySettings:
    """Settings of the workflow (defaults as documented in the module docstring).

    base : the starting model's effects: by default what every face has (a PI hysteresis density,
        each marker's own path, per-trial bias shifts); ``("hysteresis",)`` is the paper's model
        with straight paths, ``()`` a static model without hysteresis.
    candidates : effect names to try (default: the missing effects of the catalogue; base
        effects are never candidates).
    margin : held-out BIC units a candidate must gain.  min_explained : fraction of the held-out
        excess over the noise floor it must explain.  min_rms_gain : the held-out RMS it must
        remove, as a fraction of the noise floor (a gain nobody could see in the data is not an
        effect, however significant statistically).  beyond_noise : ratio to the noise floor above
        which a residual is reported as a disagreement.
    active_mm : a DU moves a marker when the marker's 95th-percentile displacement in that DU's
        single-DU takes exceeds this (0: every scored marker is modelled for every DU; leaving
        out markers that move a little leaves their motion in the residual).
    stride : frames between the samples used (3 = 40 Hz at 120 fps), at least; coarser when a
        DU's single-DU takes hold more than ``max_samples_per_du`` samples.
    strong_fraction : a curve gets its own sigmoid when the marker's 95th-percentile
        displacement reaches this fraction of the DU's largest; the others take the DU's median
        shape and only their displacement vectors are fitted.
    local, local_explained, local_gain, local_min_n : with ``local`` (on by default), another
        way to pass the explained and RMS-gain tests: where the candidate acts (the held-out
        residual vectors it moves by more than half the noise floor, at least ``local_min_n`` of
        them), it removes at least ``local_explained`` of the excess over the noise floor and
        ``local_gain`` x the noise floor from the RMS (a stick-slip dead band: on the rows where
        it holds a DU's actuator, :func:`hold_gain`). An effect that acts in a few places (a dead
        band at reversals) is plain there and lost in the session's RMS. It is safe only
        against the candidate's own null (:func:`cv_candidate`): against the base, a
        candidate's extra polish of the curves is local too. The numbers are reported in every
        candidate's evidence either way.
    max_steps : effects to add at most.
    jobs : processes over the base fits (each fold, all takes) and the candidates (spawned;
        1 runs in this process). The results do not depend on it.
    """

    base: tuple[str, ...] = BASE
    candidates: tuple[str, ...] = CANDIDATES
    margin: float = 10.0
    min_explained: float = 0.2
    min_rms_gain: float = 0.03
    beyond_noise: float = 1.5
    active_mm: float = 0.0
    stride: int = 3
    max_samples_per_du: int = 1600
    strong_fraction: float = 0.15
    local: bool = True
    local_explained: float = 0.35
    local_gain: float = 0.25
    local_min_n: int = 100
    max_steps: int = 4
    jobs: int = 1


# ----------------------------------------------------------------------------------------------
# data preparation


def schedule_class(t: TakeData) -> tuple[int, bool]:
    """What a take's schedule can reveal, as a sortable key: the median ramp rate of its moving
    command rows in octaves (log2 of command units/s, rounded) and whether it turns back inside
    the range (a minor loop)."""
    rates, inner = [], False
    for _du, g in t.rows.groupby("du"):
        step_rate, _, turns_inside = command_moves(g)
        if step_rate.size:
            rates.append(step_rate)
            inner |= turns_inside
    octave = int(np.round(np.log2(np.median(np.concatenate(rates))))) if rates else 0
    return octave, inner


def assign_folds(takes: list[TakeData]) -> None:
    """Two folds that each see every DU set at as many ramp rates as the session has.

    Within each DU set, the takes fall in three strata by :func:`schedule_class`: ramps at
    another rate than the set's most common one, schedules with minor loops, and the rest (the
    reference schedule and its repetitions, multi-DU takes). Ordered by DU set, rate, schedule
    and trial, each stratum alternates between the folds with its own running count over all
    DU sets (minor loops starting in the other fold). So each fold holds some trials of every
    repeated schedule; a DU's fast and slow ramps land in different folds instead of both in
    one (a fold that sees a DU at one rate cannot tell a lag from a wider hysteresis, and its
    fit then misleads the other fold's score); and the minor loops of successive DUs alternate,
    so both folds can test what only reversals inside the range reveal."""
    by_set: dict[tuple, list[int]] = {}
    for i, t in enumerate(takes):
        by_set.setdefault(t.dus, []).append(i)
    seen = {"rate": 0, "minor": 1, "reference": 0}
    for _, idx in sorted(by_set.items()):
        cls = {i: schedule_class(takes[i]) for i in idx}
        octaves, counts = np.unique([cls[i][0] for i in idx], return_counts=True)
        modal = octaves[np.argmax(counts)]
        order = sorted(idx, key=lambda i: (takes[i].kind != "motion", cls[i], takes[i].group,
                                           takes[i].trial, takes[i].name))
        for i in order:
            k = "rate" if cls[i][0] != modal else ("minor" if cls[i][1] else "reference")
            takes[i].fold = seen[k] % 2
            seen[k] += 1


def trial_noise(takes: list[TakeData], markers: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """Noise floor from repeated trials: what no deterministic model can predict.

    For every schedule played in n >= 2 trials, each trial's deviation from the trials' fit
    (the mean for 2 trials, a straight line over the trial number from 3, so that a drift across
    trials is not counted as noise), scaled to unbiased (sqrt(n / (n - p))), per marker.

    Returns (floor_mm, per_marker_mm (M,)): the RMS 3D deviation over all markers (or
    ``markers``) and per marker; NaN when no schedule was repeated.
    """
    groups: dict[str, list[TakeData]] = {}
    for t in takes:
        groups.setdefault(t.group, []).append(t)
    M = takes[0].X.shape[1]
    ss = np.zeros(M)
    cnt = np.zeros(M)
    for g in groups.values():
        n = len(g)
        if n < 2 or len({t.n_frames for t in g}) != 1:
            continue
        X = np.stack([t.X for t in g])  # (n, F, M, 3)
        tr = np.array([t.trial for t in g], float)
        if n >= 3 and np.unique(tr).size == n:
            A = np.column_stack([np.ones(n), tr - tr.mean()])
            p = 2
        else:
            A = np.ones((n, 1))
            p = 1
        ok = np.isfinite(X).all(axis=(0, 3))  # (F, M) frames seen in every trial
        Xf = np.where(ok[None, ..., None], X, 0.0)
        coef, *_ = np.linalg.lstsq(A, Xf.reshape(n, -1), rcond=None)
        fit = (A @ coef).reshape(X.shape)
        dev = np.sum((Xf - fit) ** 2, axis=-1) * n / (n - p)  # (n, F, M)
        ss += np.sum(np.where(ok[None], dev, 0.0), axis=(0, 1))
        cnt += n * ok.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        per = np.sqrt(ss / cnt)
    sel = np.ones(M, bool) if markers is None else markers
    sel = sel & (cnt > 0)
    floor = float(np.sqrt(ss[sel].sum() / cnt[sel].sum())) if sel.any() else float("nan")
    return floor, per


def rest_noise(rest_X: np.ndarray | None) -> tuple[float, np.ndarray]:
    """Noise floor from the rest take: RMS 3D deviation from each marker's mean (mm)."""
    if rest_X is None or not np.isfinite(rest_X).any():
        return float("nan"), np.full(0, np.nan)
    with np.errstate(invalid="ignore"):
        dev = np.sum((rest_X - np.nanmean(rest_X, axis=0)) ** 2, axis=-1)
        per = np.sqrt(np.nanmean(dev, axis=0))
    return float(np.sqrt(np.nanmean(dev))), per


@dataclass
class Prepared:
    """A session ready for the workflow: the model data, the noise floor and what can be tested."""

    data: ModelData
    noise_floor_mm: float
    noise_source: str
    per_marker_noise_mm: np.ndarray
    excluded: list[str]
    schedules: ScheduleSummary
    phase_labels: list[np.ndarray]  # per take, the phase (index into PHASES) of each sample


def prepare(fps: float, marker_names, rest_mm: np.ndarray, takes: list[TakeData],
            rest_X: np.ndarray | None = None,
            settings: DiscrepancySettings = DiscrepancySettings()) -> Prepared:
    """Folds, noise floor, moving markers per DU and the markers scored.

    Markers whose trial noise is over 3 x the median marker's (a badly seen marker) are left out
    of the scores and named in ``excluded``.
    """
    assign_folds(takes)
    floor, per = trial_noise(takes)
    source = "repeated trials"
    if not np.isfinite(floor):
        floor, per = rest_noise(rest_X)
        source = "rest take"
    if not np.isfinite(floor) or floor <= 0:
        raise ValueError("discrepancy: the noise floor cannot be measured: no command schedule was "
                         "played in two or more trials and there is no rest take")
    M = len(marker_names)
    used = np.ones(M, bool)
    if per.size == M and np.isfinite(per).any():
        med = np.nanmedian(per)
        used = ~(per > 3.0 * med)
        floor_used, _ = trial_noise(takes, used) if source == "repeated trials" else (floor, per)
        if np.isfinite(floor_used):
            floor = floor_used
    du_ids = tuple(sorted({d for t in takes for d in t.dus}))
    active = np.zeros((len(du_ids), M), bool)
    strong = np.zeros((len(du_ids), M), bool)
    n_frames = 0
    for n, du in enumerate(du_ids):
        ds = [np.linalg.norm(t.X - rest_mm, axis=-1) for t in takes if t.dus == (du,)]
        if not ds:
            continue
        n_frames = max(n_frames, sum(d.shape[0] for d in ds))
        with np.errstate(invalid="ignore"):
            p95 = np.nanpercentile(np.concatenate(ds), 95, axis=0)
        active[n] = (p95 > settings.active_mm) & used
        peak = np.nanmax(np.where(active[n], p95, np.nan)) if active[n].any() else 0.0
        strong[n] = active[n] & (p95 >= settings.strong_fraction * peak)
    # samples per DU bounded: a long study is read at a coarser stride
    stride = max(settings.stride, int(np.ceil(n_frames / settings.max_samples_per_du)))
    data = ModelData(fps=fps, marker_names=tuple(marker_names), rest_mm=rest_mm, takes=takes,
                     du_ids=du_ids, used=used, active=active, strong=strong, stride=stride)
    summary = summarize_schedules([(t.rows, t.trial, t.group) for t in takes], fps)
    excluded = [str(marker_names[i]) for i in np.flatnonzero(~used)]
    labels = [phases(t, data.samples(k), fps) for k, t in enumerate(takes)]
    return Prepared(data, floor, source, per, excluded, summary, labels)


# ----------------------------------------------------------------------------------------------
# phases of the command


def phases(t: TakeData, frames: np.ndarray, fps: float, reversal_s: float = 0.3) -> np.ndarray:
    """Phase label index (into :data:`PHASES`) of each frame of a take, from its commands.

    Each command row's rate is its change over the time since the row before (command units/s);
    a frame takes the rate of the row in force for each DU and the DU changing fastest decides:
    rise / fall, fast above 400 units/s, slow below 150 (the paper's ramp is 255 per second);
    ``hold`` when the row in force changed nothing, ``rest`` when every command is 0;
    ``reversal`` for ``reversal_s`` after a DU's command turns back inside its range.
    """
    from mocap.core.schedules import TIME_TOL_S

    times = frames / fps
    n = len(times)
    best_rate = np.zeros(n)
    best_sign = np.zeros(n)
    level = np.zeros(n)
    out = np.full(n, PHASES.index("hold"))
    for du in t.dus:
        g = t.rows[t.rows["du"] == du].sort_values("time_s", kind="stable")
        cc = g["command"].to_numpy(float)
        tt = g["time_s"].to_numpy(float)
        if cc.size == 0:
            continue
        dc = np.diff(cc, prepend=0.0)
        dt = np.diff(tt, prepend=tt[0] - 1.0)
        rate = np.abs(dc) / np.maximum(dt, 1e-6)
        idx = np.searchsorted(tt, times + TIME_TOL_S, side="right") - 1
        i = np.maximum(idx, 0)
        # a row's change is in force for one step (its own duration), then the command holds
        ok = (idx >= 0) & (times - tt[i] < np.maximum(dt[i], 1e-6))
        r = np.where(ok, rate[i], 0.0)
        sg = np.where(ok, np.sign(dc[i]), 0.0)
        c_now = np.where(idx >= 0, cc[i], 0.0)
        take = r > best_rate
        best_rate = np.where(take, r, best_rate)
        best_sign = np.where(take, sg, best_sign)
        level = np.maximum(level, c_now)
        # reversals inside the range
        mv = np.flatnonzero(np.diff(cc) != 0)
        if mv.size >= 2:
            s = np.sign(np.diff(cc)[mv])
            for k in mv[1:][s[1:] != s[:-1]]:
                if 0.05 * 255 < cc[k] < 0.95 * 255:
                    t0 = tt[k]
                    out[(times >= t0) & (times < t0 + reversal_s)] = -1
    rev = out == -1
    out[:] = PHASES.index("hold")
    out[(level == 0) & (best_rate == 0)] = PHASES.index("rest")
    for sign, name in ((1, "rise"), (-1, "fall")):
        m = best_sign == sign
        out[m & (best_rate > 400)] = PHASES.index(f"{name}-fast")
        out[m & (best_rate <= 400) & (best_rate >= 150)] = PHASES.index(name)
        out[m & (best_rate < 150)] = PHASES.index(f"{name}-slow")
    out[rev] = PHASES.index("reversal")
    return out


# ----------------------------------------------------------------------------------------------
# cross-validated fits


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
    against, :func:`candidate_evidence`); None when the fit on fold 0 does not lower the
    held-out SSE of fold 1 below its null's (screened out: not fitted on fold 1).
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


# ----------------------------------------------------------------------------------------------
# the workflow


@dataclass
class Step:
    """One named effect: parameters (all takes), uncertainty, held-out gap before/after."""

    effect: str
    parameters: dict
    uncertainty: dict
    heldout_rms_before_mm: float
    heldout_rms_after_mm: float
    evidence: list[dict]
    explained: float
    per_du: dict = field(default_factory=dict)  # DU id -> the parameter from its own takes
    named: bool = True  # False: kept in the model, but an alternative explains it as well
    form: str | None = None  # the effect's form, where it has several (backlash: play, stick-slip)
    interval: dict = field(default_factory=dict)  # parameter -> [lo, hi] that fit equally well
    interval_note: str = ""  # what the interval is, where not the values that fit alike
    meaning: str = ""  # what the effect is, in the form it was named in
    reading: str = ""  # how the parameter was read from the data, where not from the fit


@dataclass
class DiscrepancyResult:
    """What the workflow found (see :func:`run_discrepancy`)."""

    named: list[str]
    steps: list[Step]
    noise_floor_mm: float
    noise_source: str
    base_effects: tuple[str, ...]
    untestable: dict[str, str]
    stages: list[dict]  # per stage (base, then after each step): held-out diagnostics
    final_model: FaceModel
    final_evidence: list[dict]
    excluded_markers: list[str]
    heldout_residuals: list[list[np.ndarray]]  # per stage, per take (S, M, 3)
    models_by_stage: list[FaceModel]
    base_report: dict = field(default_factory=dict)  # what the base model holds (path, loop, shifts)
    alternatives: list[dict] = field(default_factory=list)  # explanations the data cannot tell apart

    @property
    def final_heldout_rms_mm(self) -> float:
        return self.stages[-1]["heldout_rms_mm"]


def _gap_tables(data: ModelData, residuals: list[np.ndarray], floor: float,
                phase_labels: list[np.ndarray]) -> dict:
    """Held-out residual RMS (mm and / noise floor) per take, DU set, marker, phase, and per
    take and phase (``take_phases``: take -> phase -> ratio to the noise floor)."""
    per_take, per_set, per_phase, take_phases = {}, {}, {}, {}
    M = len(data.marker_names)
    m_ss = np.zeros(M)
    m_n = np.zeros(M)
    set_acc: dict[str, list[float]] = {}
    ph_acc = np.zeros((len(PHASES), 2))
    for k, (t, e) in enumerate(zip(data.takes, residuals)):
        sq = np.sum(e ** 2, axis=-1)  # (S, M)
        sq = np.where(data.used[None], sq, np.nan)
        ok = np.isfinite(sq)
        per_take[t.name] = float(np.sqrt(np.nanmean(sq))) if ok.any() else float("nan")
        key = "+".join(str(d) for d in t.dus)
        acc = set_acc.setdefault(key, [0.0, 0.0])
        acc[0] += float(np.nansum(sq))
        acc[1] += int(ok.sum())
        m_ss += np.nansum(sq, axis=0)
        m_n += ok.sum(axis=0)
        ph = phase_labels[k]
        take_phases[t.name] = {}
        for p in np.unique(ph):
            sel = ok & (ph == p)[:, None]
            ss_p, n_p = float(np.sum(np.where(sel, sq, 0.0))), int(sel.sum())
            ph_acc[p, 0] += ss_p
            ph_acc[p, 1] += n_p
            if n_p and floor > 0:
                take_phases[t.name][PHASES[p]] = round(float(np.sqrt(ss_p / n_p) / floor), 3)
    for key, (s, n) in set_acc.items():
        per_set[key] = float(np.sqrt(s / max(n, 1)))
    for p, name in enumerate(PHASES):
        if ph_acc[p, 1] > 0:
            per_phase[name] = float(np.sqrt(ph_acc[p, 0] / ph_acc[p, 1]))
    with np.errstate(invalid="ignore", divide="ignore"):
        per_marker = np.sqrt(m_ss / m_n)

    def ratio(d):
        return {k: {"rms_mm": round(v, 5), "ratio": round(v / floor, 3) if floor > 0 else None}
                for k, v in d.items()}

    return {"takes": ratio(per_take), "dus": ratio(per_set), "phases": ratio(per_phase),
            "take_phases": take_phases,
            "markers": {str(data.marker_names[m]): {"rms_mm": round(float(per_marker[m]), 5),
                                                    "ratio": round(float(per_marker[m] / floor), 3)}
                        for m in range(M) if data.used[m] and np.isfinite(per_marker[m])}}


def _stage(data, cv: CVFit, residuals, floor, label, phase_labels) -> dict:
    tables = _gap_tables(data, residuals, floor, phase_labels)
    return {"model": label, "heldout_rms_mm": cv.rms_mm,
            "ratio_to_noise": cv.rms_mm / floor if floor > 0 else None, **tables}


def run_discrepancy(prep: Prepared, settings: DiscrepancySettings = DiscrepancySettings(),
                    progress=None) -> DiscrepancyResult:
    """The whole workflow on a prepared session (see the module docstring)."""
    say = progress or (lambda m: None)
    data = prep.data
    floor = prep.noise_floor_mm
    effects = make_effects(settings.base)
    runner = _Runner(data, settings.jobs)
    try:
        # the base on each fold (cv_base) and on all takes, side by side with jobs > 1: the
        # folds first, which the candidates' screens need; the fit on all takes, needed only
        # once a candidate is judged, runs beside the first screens
        say(f"fitting the base model ({'+'.join(settings.base) or 'static'}) on all "
            f"{len(data.takes)} takes and on each fold ({_on(settings.jobs, 3)})")
        *folds, whole = runner.base_fits(effects, [fold_takes(data, 0), fold_takes(data, 1),
                                                   list(range(len(data.takes)))])
        current, res = cv_fit(data, [_settle(f) for f in folds])
        stages = [_stage(data, current, res, floor, "+".join(settings.base) or "static",
                         prep.phase_labels)]
        residual_sets = [res]
        stage_models = [whole]
        say(f"base model ({stages[0]['model']}): held-out RMS {current.rms_mm:.4f} mm, "
            f"noise floor {floor:.4f} mm ({prep.noise_source})")
        untestable = {}
        for name in settings.candidates:
            why = CATALOGUE[name]().untestable(prep.schedules)
            if why:
                untestable[name] = why
        steps: list[Step] = []
        named: list[str] = []
        evidence: list[dict] = []
        return _steps(data, prep, settings, current, res, stages, residual_sets, stage_models,
                      untestable, steps, named, evidence, runner, say)
    finally:
        runner.close()


def _settle(model):
    """A model that may still be fitting in the runner's pool (a Future), waited for."""
    return model.result() if isinstance(model, Future) else model


def _on(jobs: int, tasks: int) -> str:
    n = max(1, min(int(jobs), tasks))
    return "in this process" if n == 1 else f"on {n} processes"


def _steps(data, prep, settings, current, res, stages, residual_sets, stage_models, untestable,
           steps, named, evidence, runner, say) -> DiscrepancyResult:
    floor = prep.noise_floor_mm
    alternatives: list[dict] = []
    for _ in range(settings.max_steps):
        have = {type(e).name for e in current.models[0].effects}
        if current.models[0].shifts_takes:
            have.add("drift")  # decided from the takes' bias shifts above
        n_eff = effective_n(res, data.used)
        evidence = []
        fits: dict[str, CVFit] = {}
        todo = []
        for name in settings.candidates:
            if name in have:
                continue
            if name in untestable:
                evidence.append({"effect": name, "testable": False, "reason": untestable[name]})
                continue
            todo.append(name)
        current.residuals = res
        if todo:
            say(f"trying {', '.join(todo)} ({_on(settings.jobs, len(todo))})")
        for name, cv, t_c in runner.map(current, todo, floor):
            if cv is None:
                evidence.append({"effect": name, "testable": True, "screened_out": True,
                                 "score": 0.0, "heldout_rms_mm": current.rms_mm, "explained": 0.0,
                                 "plausible": False,
                                 "reason": "fitted on fold 0, no gain on held-out fold 1"})
                say(f"  {name:<10} no held-out gain on the first fold ({t_c:.1f} s)")
                continue
            fits[name] = cv
            item = candidate_evidence(name, cv, current, floor, n_eff)
            evidence.append(item)
            say(f"  {name:<10} held-out RMS {cv.rms_mm:.4f} mm, score {item['score']:9.1f}, "
                f"explains {item['explained']:5.2f} of the excess, {item['local']['explained']:5.2f} "
                f"where it acts ({item['local']['n']} residuals) ({t_c:.1f} s)")
        ok = [e for e in evidence if e.get("testable") and not e.get("screened_out")
              and passes(e, settings)]
        # the best candidate whose parameter, identified again on all takes, is still plausible
        # (the folds can each find a value the whole session does not support: a dead time
        # after a second-order lag that reads 0 s on all takes; a stick-slip band whose widths
        # that fit all takes alike reach 0, which would keep the dead-band step from reading a
        # play)
        t_c = time.perf_counter()
        all_takes = list(range(len(data.takes)))
        stage_models[0] = _settle(stage_models[0])
        full = stage_models[-1]
        best = prof = None
        for item in sorted(ok, key=lambda e: e["score"]):
            cls = fits[item["effect"]].cls or CATALOGUE[item["effect"]]
            prof = profile_effect(data, full, cls(), all_takes)
            value = reported_value(prof, cls)
            supported = not reaches_null(prof, cls)
            if cls.per_curve or (cls(value).plausible() and supported):
                best = item
                break
            item["plausible"] = False
            shown = cls(value).describe()
            item["reason"] = (f"on all takes its {cls.parameter} is {shown['value']:.4g} "
                              f"{shown['unit']}, " + (
                                  "not a plausible value" if supported else
                                  f"and every value from {prof.interval[0]:.4g} to "
                                  f"{prof.interval[1]:.4g} fits alike") +
                              ": the folds' gain does not hold on the whole session")
            say(f"  {item['effect']} not named: {item['reason']}")
        if best is None:
            break
        name = best["effect"]
        cls = fits[name].cls or CATALOGUE[name]
        prof = fold_hull(prof, cls, fits[name].intervals)
        model = prof.model
        params, unc = {}, {}
        if cls.per_curve:
            params = {cls.parameter: model.parameters()[cls.parameter]}
            unc = {cls.parameter: _per_curve_spread(model, name)}
        else:
            eff = model.effect(name)
            v = reported_value(prof, cls) if cls.pairwise else eff.describe()["value"]
            fv = fits[name].values
            # the profile's curvature is the law's, not kappa's: a law with pair vectors takes
            # the spread of its kappa readings (the folds', and all takes' from their mean)
            se = (abs(v - 0.5 * (fv[0] + fv[1])) if cls.pairwise
                  else profile_uncertainty(prof, n_eff))
            # two half-samples: |v0 - v1| / 2 estimates the full-sample standard error
            se = float(np.nanmax([se, abs(fv[0] - fv[1]) / 2]))
            if name == "saturation" and np.isfinite(se) and prof.best > 0:
                se = se / prof.best ** 2  # 1/L -> L
            params = {cls.parameter: float(v)}
            unc = {cls.parameter: float(se)}
        per_du = per_du_values(data, model, name) if cls.affects_curves and not cls.per_curve else {}
        say(f"  {name} on all takes: {time.perf_counter() - t_c:.1f} s")
        alt = (lag_order_alternative(data, current, best, n_eff, settings.margin)
               if name == "deadtime" and "lag" in have else None)
        if alt:
            alternatives.append(alt)
            say(f"  {name} kept in the model but not named: {alt['reason']}")
        if name == "backlash":
            alternatives.append(dead_band_alternative(params[cls.parameter], model, cls.form))
        before = current.rms_mm
        current = fits[name]
        s, n, res = heldout(data, current.models)
        residual_sets.append(res)
        stage_models.append(model)
        if not alt:
            named.append(name)
        model_label = "+".join(settings.base + tuple(s_.effect for s_ in steps) + (name,))
        stages.append(_stage(data, current, res, floor, model_label, prep.phase_labels))
        steps.append(Step(name, params, unc, before, current.rms_mm, evidence, best["explained"],
                          per_du, named=not alt, form=getattr(cls, "form", None),
                          meaning=cls.meaning, reading=parameter_reading(name, model),
                          interval=({cls.parameter: [float(v) for v in prof.interval]}
                                    if prof.interval else {})))
        say(f"{'kept' if alt else 'named'} {name} {params}: held-out RMS {before:.4f} -> "
            f"{current.rms_mm:.4f} mm")
    stage_models[0] = _settle(stage_models[0])
    # a backlash the base's density absorbed: the edge of a forced play's profile
    if "backlash" in settings.candidates and "backlash" not in untestable:
        step, cv, alt, model, item = dead_band_step(data, stage_models[-1], current, floor, say)
        if item is not None and step is None:  # the reading beside the last round's evidence
            evidence = [*evidence, item]
        if step is not None:
            alternatives.append(alt)
            named.append("backlash")
            steps.append(step)
            current = cv
            res = cv.residuals  # the held-out residuals the step scored
            residual_sets.append(res)
            stage_models.append(model)
            model_label = "+".join(settings.base + tuple(s_.effect for s_ in steps))
            stages.append(_stage(data, current, res, floor, model_label, prep.phase_labels))
            say(f"named backlash {step.parameters}: the edge of a forced play's profile")
    # drift last: the trend of the takes' bias shifts, read from the final model (an effect still
    # missing, such as a lag, would bias the shifts)
    last = stage_models[-1]
    if "drift" in settings.candidates and last.shifts_takes:
        step, alt = drift_step(data, last, current.rms_mm, untestable)
        if alt:
            alternatives.append(alt)
        if step is not None:
            named.append("drift")
            steps.append(step)
            stage_models.append(with_drift(last, step.parameters["beta_per_trial"]))
            residual_sets.append(residual_sets[-1])
            stages.append({**stages[-1], "model": stages[-1]["model"] + "+drift"})
            say(f"named drift {step.parameters}: a trend of the takes' bias shifts")
    return DiscrepancyResult(named=named, steps=steps, noise_floor_mm=floor,
                             noise_source=prep.noise_source, base_effects=tuple(settings.base),
                             untestable=untestable, stages=stages, final_model=stage_models[-1],
                             final_evidence=evidence, excluded_markers=prep.excluded,
                             heldout_residuals=residual_sets, models_by_stage=stage_models,
                             base_report=base_report(stage_models[0]), alternatives=alternatives)


def reaches_null(prof, cls) -> bool:
    """Whether a profile's plateau (the values that fit alike, ``prof.interval``) reaches the
    effect's null, the lower bound of its parameter (a dead band of 0): then the takes fit as
    well without the effect as with the value read, whatever the folds gained."""
    return prof.interval is not None and prof.interval[0] <= cls.bounds[0]


def fold_hull(prof, cls, fold_intervals: list):
    """A dead band read on command rows (``cls.command_grid``) whose profile on all takes has a
    single minimum while the folds' own profiles are flat over intervals
    (:attr:`CVFit.intervals`): the whole session's minimum then wins by less than the folds
    disagree, and the widths the data allow are the hull of the folds' intervals and that
    minimum. Returns ``prof`` with that interval, its centre as the value (the model's band set
    to it, as :func:`mocap.analysis.model.profiles.profile_effect` does for a plateau) and the
    interval's width as its resolution; ``prof`` unchanged otherwise. Example: a Preisach face
    with straight paths, a coupling and a stick-slip band of 12, after the coupling: all takes
    prefer 7.0 by less than the fits' reproducibility, the folds are flat over 6.56-12.51 and
    6.50-9.49, and the band is reported as 9.5 in 6.50-12.51."""
    ivs = [iv for iv in fold_intervals if iv is not None]
    if not cls.command_grid or prof.interval is not None or not ivs:
        return prof
    lo = min([prof.best] + [iv[0] for iv in ivs])
    hi = max([prof.best] + [iv[1] for iv in ivs])
    centre = 0.5 * (lo + hi)
    model = prof.model.with_effects(tuple(cls(centre) if type(e) is cls else e
                                          for e in prof.model.effects))
    return replace(prof, best=centre, model=model, interval=(float(lo), float(hi)),
                   resolution=max(prof.resolution, hi - lo))


def candidate_evidence(name: str, cv: CVFit, current: CVFit, floor: float, n_eff: float) -> dict:
    """A fitted candidate's evidence against its null (``cv.null``: the candidate at 0 fitted
    along its own path; the current model when it has none): its held-out BIC score, the
    fraction of the held-out excess over the noise floor it explains and the RMS it removes (in
    the whole session and where it acts, :func:`local_gain`), its fold values and whether they
    are plausible, and the form it was fitted in."""
    current = cv.null if cv.null is not None else current
    score = n_eff * np.log(cv.sse / current.sse) + n_parameters(cv.models[0], name) * np.log(n_eff)
    mse_cur = 3.0 * current.sse / max(current.n, 1)
    mse = 3.0 * cv.sse / max(cv.n, 1)
    excess = mse_cur - floor ** 2
    # with take shifts the base can fit under the trial noise floor: then any gain counts
    explained = (mse_cur - mse) / excess if excess > 0 else 1.0
    plausible = all(CATALOGUE[name](v).plausible() for v in (cv.values or [0.0]))
    return {"effect": name, "testable": True, "score": float(score),
            "heldout_rms_mm": cv.rms_mm, "explained": float(explained),
            "rms_gain_vs_noise": float((current.rms_mm - cv.rms_mm) / floor),
            "null_heldout_rms_mm": current.rms_mm,
            "fold_values": [float(v) for v in cv.values], "plausible": bool(plausible),
            "form": getattr(cv.cls, "form", None) if cv.cls is not None else None,
            "local": dict(cv.local or NO_LOCAL)}


def passes(e: dict, settings: DiscrepancySettings) -> bool:
    """Whether a candidate's evidence (:func:`candidate_evidence`) names it: testable, its score
    beyond the margin, its values plausible, and it explains enough of the held-out excess, in
    the whole session or where it acts."""
    if not e.get("testable") or e.get("screened_out"):
        return False
    loc = e.get("local") or NO_LOCAL
    overall = (e["explained"] >= settings.min_explained
               and e["rms_gain_vs_noise"] >= settings.min_rms_gain)
    local = (settings.local and loc["n"] >= settings.local_min_n
             and loc["explained"] >= settings.local_explained
             and loc["rms_gain_vs_noise"] >= settings.local_gain)
    return e["score"] < -settings.margin and e["plausible"] and (overall or local)


def lag_order_alternative(data: ModelData, current: CVFit, best: dict, n_eff: float,
                          margin: float) -> dict | None:
    """A dead time about to be named after a lag, weighed against a second-order lag of the
    same mean delay in place of the first-order one (one parameter fewer than lag + dead time).
    Both delay a ramp by their mean delay and differ only just after a step, so when the
    second-order lag's held-out score is within ``margin`` of the dead time's, the data cannot
    tell them apart: returns the alternative to report (and the dead time is not named), else
    None."""
    from mocap.analysis.model.effects import SecondOrderLag

    swap = cv_candidate(data, current, "lag", cls=SecondOrderLag)
    if swap is None:
        return None
    score = n_eff * np.log(swap.sse / current.sse)  # no parameter added: the lag is replaced
    if score > best["score"] + margin:
        return None
    return {"effects": ["deadtime", "second-order lag"],
            "evidence": {"deadtime_score": round(float(best["score"]), 1),
                         "second_order_lag_score": round(float(score), 1),
                         "second_order_lag_heldout_rms_mm": round(swap.rms_mm, 5),
                         "deadtime_heldout_rms_mm": round(float(best["heldout_rms_mm"]), 5),
                         "second_order_tau_s": [round(float(v), 5) for v in swap.values]},
            "reason": (f"after the lag, a dead time (fold values {best['fold_values']} s) "
                       f"scores {best['score']:.1f} held-out BIC units; the lag made second "
                       f"order instead (the same mean delay, one parameter fewer) scores "
                       f"{score:.1f}, no worse by more than the margin ({margin:g}): a "
                       "higher-order actuator and a lag plus a small dead time fit these takes "
                       "alike (the model keeps lag + dead time for its predictions); steps "
                       "sampled finely against the lag would tell them apart")}


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
    (:mod:`mocap.analysis.discrepancy.dead_band`) on all takes, before ``model`` (the final model, fitted on
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


def shift_trend(points: list[tuple[int, int, float]]) -> dict:
    """Least-squares trend of the takes' bias shifts over the trial number, one intercept per DU:
    s = a_DU + k trial. points : (trial, DU, shift command units) per take and DU.

    Returns the slope k (command units per trial), its standard error from the scatter about the
    fit (the takes' random shifts), the t ratio, the scatter's SD, the residual degrees of
    freedom and the counts; with fewer than 3 distinct trials, only the counts."""
    tr = np.array([p[0] for p in points], float)
    du = np.array([p[1] for p in points])
    v = np.array([p[2] for p in points], float)
    out = {"trials": int(np.unique(tr).size), "points": int(v.size)}
    if out["trials"] < 3:
        return out
    ids = np.unique(du)
    A = np.column_stack([tr] + [(du == d).astype(float) for d in ids])
    coef, *_ = np.linalg.lstsq(A, v, rcond=None)
    res = v - A @ coef
    dof = max(v.size - A.shape[1], 1)
    s2 = float(res @ res) / dof
    cov = s2 * np.linalg.pinv(A.T @ A)
    se = float(np.sqrt(max(cov[0, 0], 1e-30)))
    return {**out, "slope": float(coef[0]), "slope_se": se, "t": float(coef[0] / se),
            "scatter_sd": float(np.sqrt(s2)), "dof": int(dof)}


DRIFT_CONFIDENCE = 0.95  # the drift's interval: this confidence from the t distribution


def trend_interval(tr: dict, confidence: float = DRIFT_CONFIDENCE) -> list[float]:
    """[lo, hi] of a :func:`shift_trend`'s slope: slope -+ t(confidence, dof) x its standard
    error (the takes' shifts scattered about the trend, independently, with a common SD)."""
    from scipy.stats import t as student

    half = float(student.ppf(0.5 + 0.5 * confidence, max(int(tr["dof"]), 1))) * tr["slope_se"]
    return [tr["slope"] - half, tr["slope"] + half]


DRIFT_MIN_RATE = 0.5  # command units per trial: a smaller trend is no drift worth naming
DRIFT_T = 4.0  # slope / its standard error to name a drift
DRIFT_T_AMBIGUOUS = 2.0  # above this (and under DRIFT_T): reported as an alternative


def take_shift_points(data: ModelData, model: FaceModel, takes=None) -> list[tuple[int, int, float]]:
    ks = range(len(data.takes)) if takes is None else takes
    return [(data.takes[k].trial, du, v) for k in ks
            for du, v in model.take_shifts.get(data.takes[k].name, {}).items()]


def drift_step(data: ModelData, model: FaceModel, rms: float, untestable: dict):
    """Decide drift from the base model's bias shift per take and DU (fitted on all takes).

    A drift is a trend over the trial number; a take's random shift is not. Named when the
    trend's slope is at least :data:`DRIFT_MIN_RATE` per trial and :data:`DRIFT_T` standard
    errors (from the takes' scatter about the trend); between :data:`DRIFT_T_AMBIGUOUS` and
    :data:`DRIFT_T` both explanations are reported as an alternative and nothing is named; with
    fewer than 3 trials a trend cannot be told from a random shift (untestable). Returns
    (Step or None, alternative dict or None). The held-out RMS does not change: the base
    already holds each take's shift; the step says what they are.
    """
    tr = shift_trend(take_shift_points(data, model))
    if tr["trials"] < 3:
        if "drift" not in untestable:
            untestable["drift"] = "fewer than 3 trials: a trend cannot be told from a random shift"
        return None, None
    ev = {"effect": "drift", "testable": True, "shifts": True,
          **{k: round(float(v), 5) for k, v in tr.items()}}
    big = abs(tr["slope"]) >= DRIFT_MIN_RATE
    if big and abs(tr["t"]) >= DRIFT_T:
        per_du = {}
        for du in data.du_ids:
            pts = [p for p in take_shift_points(data, model) if p[1] == du]
            one = shift_trend(pts)
            if "slope" in one:
                per_du[int(du)] = round(one["slope"], 4)
        step = Step("drift", {"beta_per_trial": tr["slope"]}, {"beta_per_trial": tr["slope_se"]},
                    rms, rms, [ev], 0.0, per_du,
                    interval={"beta_per_trial": trend_interval(tr)},
                    interval_note=(f"{100 * DRIFT_CONFIDENCE:.0f} % confidence from the takes' "
                                   "scatter about the trend"))
        return step, None
    if big and abs(tr["t"]) >= DRIFT_T_AMBIGUOUS:
        return None, {"effects": ["drift", "takeshift"], "evidence": ev,
                      "reason": (f"the takes' bias shifts move {tr['slope']:.2f} command units per "
                                 f"trial, {abs(tr['t']):.1f} standard errors of their scatter: a drift "
                                 "and random take-to-take shifts explain them about equally; the "
                                 "reference trapezoid repeated in more trials would tell")}
    return None, None


def with_drift(model: FaceModel, k: float) -> FaceModel:
    """The model with a ``drift`` of k per trial (its takes' shifts are re-identified per take,
    so held-out predictions do not change; a new schedule's prediction gets the trend)."""
    from mocap.analysis.model.effects import Drift

    return model.with_effects(model.effects + (Drift(k),))


def base_report(model: FaceModel) -> dict:
    """What the base model holds, per DU: the path bow (|B_1| / |D|, median), the loop width
    (median, command units), the PI density and branch parameters (mix, kappa), and the SD of the
    takes' bias shifts."""
    from mocap.analysis.model.face_model import DENSITY_FRACTIONS, bow_ratio

    out: dict = {}
    if model.effect("curvature") is not None:
        out["path_bow"] = round(bow_ratio(model), 4)
    if model.hysteresis:
        lw = model.loop_width()
        out["loop_width"] = {int(d): round(float(np.median(lw[n][model.active[n]])), 3)
                             for n, d in enumerate(model.du_ids) if model.active[n].any()}
        out["density_fractions"] = [float(f) for f in DENSITY_FRACTIONS]
        out["density"] = {int(d): [round(float(q), 4) for q in model.density[n]]
                          for n, d in enumerate(model.du_ids)}
        out["branch_mix_kappa"] = {int(d): [round(float(v), 4) for v in model.branch[n]]
                                   for n, d in enumerate(model.du_ids)}
    if model.shifts_takes and model.take_shifts:
        v = np.array([x for sh in model.take_shifts.values() for x in sh.values()], float)
        out["take_shift_sd"] = round(float(np.std(v)), 4)
    return out


READINGS = {
    "pull-weighted": "in travel along the measured paths where the multi-DU takes hold their DUs "
                     "at full command; the loss follows the other DU's pull at each marker "
                     "(skin shared where both DUs pull)",
    "uniform": "in travel along the measured paths where the multi-DU takes hold their DUs at "
               "full command; the same loss at every marker (a drive shared before the skin)",
    "drive": "in the model's drive, by the scalar law refitted on the multi-DU takes (no take "
             "holds its DUs at full command: a take driving them together to full command and "
             "holding there reads it in travel)",
}


def parameter_reading(name: str, model: FaceModel) -> str:
    """How the step's parameter was read where the data, not the fit, give it: the coupling's
    kappa (:func:`mocap.analysis.model.coupling.coupling_kappa`, its weighting in
    ``model.info["coupling_law"]``); "" otherwise."""
    if name != "coupling":
        return ""
    return READINGS.get(model.info.get("coupling_law", ""), "")


def per_du_values(data: ModelData, model: FaceModel, name: str) -> dict[int, float]:
    """A named global effect's parameter identified again from each DU's own single-DU takes
    (the model shares one value; a robot's actuators may differ): DU id -> value, in the
    effect's reported unit."""
    cls = CATALOGUE[name]
    out = {}
    for du in data.du_ids:
        takes = [k for k, t in enumerate(data.takes) if t.dus == (du,)]
        if not takes:
            continue
        prof = profile_effect(data, model, cls(), takes)
        out[int(du)] = float(prof.model.effect(name).describe()["value"])
    return out


def worst_marker(residual: np.ndarray, used: np.ndarray) -> tuple[int, np.ndarray]:
    """The marker with the largest residual (S, M, 3) among ``used``, and the unit direction
    (3,) in which its residual is largest (first principal axis)."""
    e = np.where(used[None, :, None], residual, np.nan)
    m = int(np.nanargmax(np.nansum(e ** 2, axis=(0, 2))))
    r = residual[:, m]
    r = r[np.isfinite(r).all(axis=1)]
    if len(r) < 3:
        return m, np.array([1.0, 0.0, 0.0])
    _, _, vt = np.linalg.svd(r - r.mean(axis=0), full_matrices=False)
    return m, vt[0]


def _per_curve_spread(model: FaceModel, name: str) -> float:
    """Uncertainty of a per-curve effect's summary: the median's standard error over curves
    (1.25 x the standard deviation / sqrt(n))."""
    if name == "hysteresis":
        v = 2.0 * model.r[model.active]
    else:
        magD = np.linalg.norm(model.D, axis=-1)
        big = model.active & (magD >= 0.5 * magD.max(axis=1, keepdims=True))
        v = (np.linalg.norm(model.B[:, :, 0], axis=-1) / np.maximum(magD, 1e-12))[big]
    return float(1.25 * np.std(v) / np.sqrt(max(v.size, 1))) if v.size else float("nan")
