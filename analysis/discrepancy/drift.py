"""Drift in the discrepancy workflow: the trend over trials of the takes' bias shifts (command
units per trial, one intercept per DU), read from the final model and named when it stands out of
the takes' random scatter."""

from __future__ import annotations

import numpy as np

from mocap.analysis.discrepancy.result import Step
from mocap.analysis.model.face_model import FaceModel
from mocap.analysis.model.data import ModelData


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
