"""What a refinement says about a played take and the next play: the take's tracking RMS read
from the take itself, whether the take is a play of the commands it is said to be, and the
tracking RMS of the next commands predicted consistently with what the take measured.

The model's own prediction of a refined design's play is not a guide to what the play will
measure: the refinement moves the reference the model tracks away from the plan by the model's
error (that is what it learns), so the model, scoring its own prediction against the plan,
predicts a worse take at every iteration while the played takes improve. What the model
predicts well is the change a change of commands makes. The prediction here is therefore

    delta_next_m(t) = delta_meas_m(t) + (pred_m(next, t) - pred_m(played, t))

with delta_meas the played take's normalised displacement read without the bias of noise
(:func:`mocap.analysis.design.model_based.debiased_delta`) and pred_m(rows, t) the model's
normalised displacement of a command file (:func:`mocap.analysis.design.model_based.predicted_delta`):
the model's error on the played commands is taken to repeat on the next ones, as iterative
learning control assumes. Its RMS against the plan is the evaluation's (markers' mean, forward
and backward), so it compares with the next play's measured RMS directly.

Shapes: X (n_frames, M, 3) mm; rows the command file (time_s s, du, command 0..255); RMS in the
evaluation's units (normalised displacement, 0 at rest, 1 at the full motion).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from mocap.analysis.design.evaluation import MotionEvaluation, evaluate_motion
from mocap.analysis.design.model_based import (
    SELECT_S,
    Reference,
    commands_matrix,
    debiased_delta,
    predicted_delta,
)
from mocap.analysis.model.face_model import FaceModel

MIN_MOTION_MM = 0.05  # markers that move less are left out of the evaluation (as evaluate_design)
# a take whose markers' mean departs further than this (RMS over the plan's rise and fall) from
# the model's prediction of the commands it is said to be a play of is another play: the model's
# own error on a face of another family is a few hundredths, plan A against plan E 0.4
MAX_TAKE_MISMATCH = 0.12
NOISE_FRAMES = 3  # frames the measured tracking error is averaged over before its RMS (_evaluate)


def _windows(ref: Reference, fps: float, n: int) -> tuple[slice, slice]:
    def window(a_b):
        return slice(int(round(a_b[0] * fps)), min(int(round(a_b[1] * fps)), n))

    return window(ref.rise), window(ref.fall)


def measured_delta(X: np.ndarray, rows: pd.DataFrame, fps: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The played take's normalised displacement (n_frames, M) without the bias of noise,
    whether each marker moves enough to be evaluated (M,) bool (plateau >= 0.05 mm), and each
    marker's noise in normalised units (M,): its noise per axis over its plateau, s_m / n_m
    (the noise of |d| along the displacement; 0 where nothing was measured)."""
    dus = sorted(int(d) for d in pd.unique(rows["du"]))
    delta, peak, noise = debiased_delta(X, commands_matrix(rows, dus, X.shape[0], fps),
                                        max_select_frames=max(6, int(round(SELECT_S * fps))))
    peak = np.nan_to_num(peak)
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.where(peak > 0, np.nan_to_num(noise) / np.where(peak > 0, peak, 1.0), 0.0)
    return delta, peak >= MIN_MOTION_MM, rel


def _evaluate(delta: np.ndarray, keep: np.ndarray, fps: float, ref: Reference,
              rel_noise: np.ndarray | None = None) -> MotionEvaluation:
    """The evaluation of ``delta`` against the plan; with ``rel_noise`` (M,) the forward and
    backward RMS without the variance the markers' noise adds to their mean: the mean's error
    averaged over :data:`NOISE_FRAMES` frames, whose RMS^2 is the noise-free one plus the
    averaged noise's variance, sum_m (s_m / n_m)^2 / K^2 over the K markers seen at a frame
    divided by NOISE_FRAMES, which is subtracted (clipped at 0)."""
    from dataclasses import replace

    n = delta.shape[0]
    t = np.arange(n) / fps
    ideal = np.interp(t, ref.t_s, ref.ideal)
    rise, fall = _windows(ref, fps, n)
    ev = evaluate_motion(delta, ideal, fps, rise, fall, keep)
    if rel_noise is None:
        return ev
    seen = np.isfinite(delta[:, keep])
    K = seen.sum(axis=1)
    var = np.where(K > 0, (seen * rel_noise[keep][None] ** 2).sum(axis=1) / np.maximum(K, 1) ** 2,
                   0.0)
    # the mean's error is smooth where the noise is white: averaged over NOISE_FRAMES frames the
    # noise's variance drops NOISE_FRAMES-fold, and so does the spread of its subtraction
    from scipy.ndimage import uniform_filter1d

    e = uniform_filter1d(np.nan_to_num(ev.mean - ev.ideal), NOISE_FRAMES, mode="nearest")
    var = uniform_filter1d(var, NOISE_FRAMES, mode="nearest") / NOISE_FRAMES

    def rms(sl):
        return float(np.sqrt(max(np.mean(e[sl] ** 2) - np.mean(var[sl]), 0.0)))

    return replace(ev, rms_forward=rms(rise), rms_backward=rms(fall))


def measured_tracking(X: np.ndarray, rows: pd.DataFrame, fps: float,
                      ref: Reference) -> MotionEvaluation:
    """The tracking of a played take against its plan, from the take alone: as
    :func:`mocap.analysis.design.model_based.evaluate_design` evaluates noise-free positions, on
    the normalised displacement read without the bias of measurement noise, and the forward and
    backward RMS without the variance the noise adds (:func:`_evaluate`)."""
    delta, keep, rel = measured_delta(X, rows, fps)
    return _evaluate(delta, keep, fps, ref, rel)


def _common(model: FaceModel, names) -> tuple[np.ndarray, np.ndarray]:
    """Indices (take, model) of the markers both have."""
    pos = {n: i for i, n in enumerate(model.marker_names)}
    pairs = [(i, pos[n]) for i, n in enumerate(names) if n in pos]
    if not pairs:
        raise ValueError("refine: the take has none of the model's markers "
                         f"(take: {', '.join(list(names)[:5])}...; model: "
                         f"{', '.join(model.marker_names[:5])}...)")
    a = np.array(pairs)
    return a[:, 0], a[:, 1]


def take_mismatch(model: FaceModel, rows: pd.DataFrame, X: np.ndarray, names,
                  ref: Reference, trial: int = 1) -> float:
    """RMS over the plan's rise and fall of the markers' mean normalised displacement of the take
    minus the model's prediction of ``rows`` (the markers both have and the take sees move): a
    play of ``rows`` differs by the model's error, a play of other commands by much more
    (:data:`MAX_TAKE_MISMATCH`)."""
    delta, keep, _ = measured_delta(X, rows, model.fps)
    ti, mi = _common(model, names)
    pred = predicted_delta(model, rows, X.shape[0], trial)
    k = keep[ti]
    if not k.any():
        return float("nan")
    with np.errstate(invalid="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            diff = np.nanmean(delta[:, ti[k]], axis=1) - np.nanmean(pred[:, mi[k]], axis=1)
    rise, fall = _windows(ref, model.fps, X.shape[0])
    sel = np.r_[diff[rise], diff[fall]]
    return float(np.sqrt(np.nanmean(sel ** 2)))


def calibrated_prediction(model: FaceModel, played_rows: pd.DataFrame, X: np.ndarray, names,
                          next_rows: pd.DataFrame, ref: Reference,
                          trial: int = 1) -> MotionEvaluation:
    """The evaluation the next play of ``next_rows`` is predicted to get (module docstring):
    the played take of ``played_rows`` (X (n_frames, M', 3) mm, markers ``names``) plus the
    model's predicted change from the played commands to the next, on the markers both have."""
    delta, keep, rel = measured_delta(X, played_rows, model.fps)
    ti, mi = _common(model, names)
    n = X.shape[0]
    change = predicted_delta(model, next_rows, n, trial) - predicted_delta(model, played_rows, n,
                                                                           trial)
    return _evaluate(delta[:, ti] + change[:, mi], keep[ti], model.fps, ref, rel[ti])


def model_prediction(model: FaceModel, rows: pd.DataFrame, ref: Reference, n_frames: int,
                     trial: int = 1) -> MotionEvaluation:
    """The evaluation of the model's own prediction of ``rows`` (no take), as
    :func:`mocap.analysis.design.model_based.design_plan` scores its hold levels."""
    from mocap.analysis.design.model_based import evaluate_design

    return evaluate_design(model.predict(rows, n_frames, trial), rows, model.fps, ref)
