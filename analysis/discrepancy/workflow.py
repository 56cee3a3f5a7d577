"""The model-discrepancy workflow: find where the face model and the measurement disagree,
name the missing effect, add it, show the gap shrink.

1. Fit the base model (:data:`mocap.analysis.model.effects.BASE`: a PI hysteresis density +
   logistic, each marker's own path, a bias shift per take and DU; what every face has,
   :mod:`mocap.analysis.model.fit`) on identification takes.
2. Predict every take and compare with the measurement; residuals per take, DU, marker and
   phase of the command (:func:`~mocap.analysis.discrepancy.prepare.phases`).
3. Localise the disagreement against the measurement's own noise floor
   (:func:`~mocap.analysis.discrepancy.prepare.trial_noise`, from repeated trials).
4. For each candidate effect (:data:`mocap.analysis.model.effects.CATALOGUE`) fit the extended model
   and score it on held-out takes: two-fold cross-validation over takes (repetitions and
   schedules alternate between folds, :func:`~mocap.analysis.discrepancy.prepare.assign_folds`),
   scored by a held-out BIC,
   ``n_eff ln(SSE_cand / SSE_cur) + dk ln(n_eff)`` with ``n_eff`` the residuals' effective
   sample size (their lag-1 autocorrelation discounts the samples).
   A candidate is scored against its null: the effect at 0 fitted along the same path (the
   same warm start, iterations and polish), so a fit's extra polish is not read as the effect.
5. Name the best candidate when its score beats its null by ``margin`` (10), it
   explains at least ``min_explained`` (20 %) of the held-out excess over the noise floor and
   removes at least ``min_rms_gain`` (3 %) of a noise floor from the held-out RMS (or, with
   ``local``, on by default, does as much where it acts,
   :func:`~mocap.analysis.discrepancy.crossval.local_gain`; a stick-slip dead band where it
   holds, :func:`~mocap.analysis.discrepancy.crossval.hold_gain`), its
   parameter is physically plausible in both folds, and the
   session's takes can test it; else "no missing effect found". A candidate with several forms
   (:data:`mocap.analysis.model.effects.FORMS`: backlash as a play or a stick-slip dead band) is
   fitted in each and keeps the one that gains the most on its own null in held-out takes.
6. Add it and repeat (forward stepwise; a named effect's parameter is re-identified on all
   takes, with its uncertainty from the profile). Then a backlash the base's hysteresis
   absorbed (no held-out gain: a play before the skin's plays is one operator with wider plays):
   the widest play the takes allow before the final model, the edge of its profile
   (:func:`~mocap.analysis.discrepancy.dead_band.dead_band_step`), named when it is at least half a
   command step of the takes and the model with it predicts the held-out takes no worse. Drift
   last, from the final model: the trend
   over trials of the takes' bias shifts (:func:`~mocap.analysis.discrepancy.drift.drift_step`),
   named when it stands out of the takes' random scatter, reported as an alternative when it
   only half does.
7. Report held-out residuals before and after each step, per DU and marker, in mm and relative
   to the noise floor.

Pure computations on :class:`mocap.analysis.model.data.ModelData`; I/O is in :mod:`mocap.workflows.discrepancy.results`.
"""

from __future__ import annotations

import time
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Callable

import numpy as np

from mocap.analysis.discrepancy.crossval import (
    CVFit,
    _Runner,
    cv_fit,
    effective_n,
    fold_takes,
    heldout,
    reported_value,
)
from mocap.analysis.discrepancy.dead_band import dead_band_alternative, dead_band_step
from mocap.analysis.discrepancy.drift import drift_step, with_drift
from mocap.analysis.discrepancy.prepare import PHASES, Prepared
from mocap.analysis.discrepancy.report import base_report, parameter_reading, per_du_values
from mocap.analysis.discrepancy.result import DiscrepancyResult, Step
from mocap.analysis.discrepancy.rules import (
    candidate_evidence,
    fold_hull,
    lag_order_alternative,
    passes,
    reaches_null,
)
from mocap.analysis.discrepancy.settings import DiscrepancySettings
from mocap.analysis.model.face_model import FaceModel, make_effects
from mocap.analysis.model.effects import CATALOGUE
from mocap.analysis.model.data import ModelData
from mocap.analysis.model.profiles import profile_effect, profile_uncertainty


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
        stage = _stage(data, current, res, floor, "+".join(settings.base) or "static",
                       prep.phase_labels)
        say(f"base model ({stage['model']}): held-out RMS {current.rms_mm:.4f} mm, "
            f"noise floor {floor:.4f} mm ({prep.noise_source})")
        untestable = {}
        for name in settings.candidates:
            why = CATALOGUE[name]().untestable(prep.schedules)
            if why:
                untestable[name] = why
        return _steps(_Search(prep, settings, runner, say), current, res, stage, whole,
                      untestable)
    finally:
        runner.close()


def _settle(model):
    """A model that may still be fitting in the runner's pool (a Future), waited for."""
    return model.result() if isinstance(model, Future) else model


def _on(jobs: int, tasks: int) -> str:
    n = max(1, min(int(jobs), tasks))
    return "in this process" if n == 1 else f"on {n} processes"


@dataclass(frozen=True)
class _Search:
    """What the stepwise search reads and never changes: the prepared session, the settings,
    the runner of the fits and the progress callback (a message -> None)."""

    prep: Prepared
    settings: DiscrepancySettings
    runner: _Runner
    say: Callable[[str], None]


def _steps(search: _Search, current: CVFit, res: list[np.ndarray], base_stage: dict, base_model,
           untestable: dict[str, str]) -> DiscrepancyResult:
    """Forward stepwise search from the base, then the dead-band and drift steps. ``current``:
    the base's fold fits, ``res`` their held-out residuals (per take (S, M, 3), mm),
    ``base_stage`` its held-out diagnostics (:func:`_stage`), ``base_model`` its fit on all takes
    (a FaceModel, or a Future of one while it runs in the pool); ``untestable`` (effect ->
    reason) gains drift when the takes cannot test it."""
    prep, settings, runner, say = search.prep, search.settings, search.runner, search.say
    data = prep.data
    floor = prep.noise_floor_mm
    stages, residual_sets, stage_models = [base_stage], [res], [base_model]
    steps: list[Step] = []
    named: list[str] = []
    evidence: list[dict] = []
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
