"""All of METHOD.md's analyses for one session, from the trial-averaged responses.

Pure computation: takes the reconstruction's results, returns tables and fitted models; the
pipeline writes them (properties.csv, linearity.csv, marker_properties.csv, figures).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, NamedTuple

import numpy as np
import pandas as pd

from mocap.analysis.design import PlanTiming
from mocap.analysis.evaluation import MotionEvaluation, evaluate_motion, realized_delta
from mocap.analysis.displacement import plateau_mask
from mocap.analysis.linearity import spatial_linearity, step_noise_covariance
from mocap.analysis.plans import PLAN_NAMES
from mocap.analysis.properties import du_properties

MIN_STEP_DOF = 30  # in-take noise covariance needs this many degrees of freedom per marker
MIN_SNR = 20.0  # a marker enters the response fits when its peak is 20 x its trial mean's noise

PROPERTY_COLUMNS = ["du", "name", "alpha_fwd", "beta_fwd", "alpha_bwd", "beta_bwd", "sensitivity",
                    "hysteresis", "dyssynchrony", "linearity_mean", "linearity_std",
                    "max_displacement_mm", "n_markers"]


class MotionResult(NamedTuple):
    """A motion take played from a plan, evaluated against the plan's ideal."""

    take: str
    plan: str
    evaluation: MotionEvaluation


@dataclass(frozen=True)
class SessionAnalysis:
    """The paper's analyses of a session.

    properties : one row per DU (properties.csv); linearity : per (DU, marker) (linearity.csv);
    marker_properties : per (DU, marker) fits; du : DU -> its DUProperties; keep : DU -> (M,)
    bool, markers not rejected; fitted : DU -> (M,) bool, markers in the response fits;
    fields_mm : DU -> (M, 3) mean displacement at full command (mm); motions : the motion takes
    evaluated against their plans (``evaluate_plan_take``), added by the composer.
    """

    properties: pd.DataFrame
    linearity: pd.DataFrame
    marker_properties: pd.DataFrame
    du: Mapping
    keep: Mapping[int, np.ndarray]
    fitted: Mapping[int, np.ndarray]
    fields_mm: Mapping[int, np.ndarray]
    motions: tuple[MotionResult, ...] = ()


def delta_noise_variance(delta: np.ndarray, command: np.ndarray) -> np.ndarray:
    """(M,) white-noise variance per frame of each marker's normalised curve, measured on the
    curve itself.

    Where the command is held at its lowest or highest value the true response is flat, so half
    the mean squared frame-to-frame difference there is the variance of the curve's white noise
    (trial-mean measurement noise and skin jitter alike, in delta units, whatever the noise's
    direction). How it reaches each step mean (through the rest reference and the plateau too)
    is ``mocap.analysis.properties.step_noise_factor``'s business. Flat holds rather than every step:
    a response still moving inside a step would count as noise there.
    """
    c = np.asarray(command)
    flat = (c == c.min()) | (c == c.max())
    pair = flat[1:] & flat[:-1] & (c[1:] == c[:-1])
    diff = np.diff(delta, axis=0)[pair]
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return 0.5 * np.nanmean(diff**2, axis=0)


def take_noise_covariance(avg, noise_mm: np.ndarray | None = None,
                          noise_cov_mm2: np.ndarray | None = None) -> np.ndarray:
    """(M, 3, 3) mm^2 noise covariance of each marker's positions in a response take, for the
    noise-corrected linearity: measured within the take's command steps
    (``mocap.analysis.linearity.step_noise_covariance``); where a marker has fewer than
    ``MIN_STEP_DOF`` degrees of freedom there, the rest take's covariance (``noise_cov_mm2``) or
    isotropic ``noise_mm`` ** 2 when given."""
    cov, dof = step_noise_covariance(avg.trials, avg.command)
    few = dof < MIN_STEP_DOF
    if few.any():
        if noise_cov_mm2 is not None:
            cov[few] = np.asarray(noise_cov_mm2)[few]
        elif noise_mm is not None:
            cov[few] = (np.asarray(noise_mm)[few] ** 2)[:, None, None] * np.eye(3)
    return cov


def kept_markers(rejections: pd.DataFrame, names, du: int | None) -> np.ndarray:
    """(M,) True for markers not rejected for ``du`` (nor for every DU)."""
    names = list(names)
    bad = rejections[rejections["du"].isna() | ((rejections["du"] == du) if du is not None else False)]
    out = np.ones(len(names), bool)
    for m in bad["marker"]:
        if m in names:
            out[names.index(m)] = False
    return out


def analyze_responses(averages, names, rejections: pd.DataFrame, du_names: dict,
                      *, n_boot: int = 200, noise_mm: np.ndarray | None = None,
                      noise_cov_mm2: np.ndarray | None = None) -> SessionAnalysis:
    """Linearity, fitted responses and indices for every DU's averaged response.

    noise_mm : optional (M,) per-marker measurement noise sd (mm, per axis; the rest take's
        noise floor); the trial mean's noise is noise_mm / sqrt(n_trials). With it, the response
        fits and indices use only markers whose peak displacement is at least ``MIN_SNR`` times
        that noise (below it a normalised curve is mostly noise: its "peak" is a noise maximum),
        and the dyssynchrony is corrected for the remaining noise (``mocap.analysis.properties``).
    noise_cov_mm2 : optional (M, 3, 3) per-marker noise covariance at rest: the noise-corrected
        linearity's fallback for markers with too few samples within the response takes' steps
        (its noise covariance is measured there, ``take_noise_covariance``).
    """
    prop_rows, lin_rows, marker_rows = [], [], []
    du_props, keeps, fitted, fields = {}, {}, {}, {}
    for avg in averages:
        keep = kept_markers(rejections, names, avg.du)
        pooled = avg.trials.reshape(-1, *avg.trials.shape[2:])
        lin = spatial_linearity(pooled)
        lin_c = spatial_linearity(pooled, take_noise_covariance(avg, noise_mm, noise_cov_mm2))
        delta = avg.delta_along if avg.delta_along is not None else avg.delta
        noise_var, plateau = None, None
        n_tr = np.maximum(np.max(avg.n_trials, axis=0), 1)  # trials that saw each marker
        if noise_mm is not None:
            noise_var = delta_noise_variance(delta, avg.command)
            from mocap.reconstruct.trials import NORMALISE_S

            plateau = plateau_mask(delta, max(1, int(round(NORMALISE_S * avg.fps))))[0]
        fit_keep = keep
        if noise_mm is not None:
            se = np.asarray(noise_mm) / np.sqrt(n_tr)
            peak = np.nanmax(np.where(np.isfinite(avg.displacement_mm), avg.displacement_mm,
                                      -np.inf), axis=0)
            fit_keep = keep & (peak >= MIN_SNR * se)
        props = du_properties(avg.du, delta, avg.command, avg.fps, fit_keep, n_boot=n_boot,
                              noise_var=noise_var, plateau=plateau)
        hold = avg.command == avg.command.max()
        field_mm = np.nanmean(avg.mean[hold] - avg.rest_mm[None], axis=0)
        peak = np.nanmax(np.where(np.isfinite(avg.displacement_mm), avg.displacement_mm, -np.inf), axis=0)
        du_props[avg.du] = props
        keeps[avg.du] = keep
        fitted[avg.du] = fit_keep
        fields[avg.du] = field_mm
        row = {"du": avg.du, "name": du_names.get(avg.du, f"DU{avg.du}"),
               "alpha_fwd": props.fwd.alpha, "beta_fwd": props.fwd.beta,
               "alpha_bwd": props.bwd.alpha, "beta_bwd": props.bwd.beta,
               "sensitivity": props.sensitivity, "hysteresis": props.hysteresis,
               "dyssynchrony": props.dyssynchrony,
               "linearity_mean": float(np.nanmean(lin[keep])), "linearity_std": float(np.nanstd(lin[keep])),
               "max_displacement_mm": float(np.nanmax(peak[keep])) if keep.any() else np.nan,
               "n_markers": int(props.n_markers),
               # over the markers in the fits: noise correction is only as good as the noise
               # estimate, so it is reported where the motion is well above the noise
               "linearity_corrected_mean": float(np.nanmean(lin_c[fit_keep])),
               "dyssynchrony_raw": props.dyssynchrony_raw}
        for k, (lo, hi) in props.ci.items():
            row[f"{k}_ci_lo"] = lo
            row[f"{k}_ci_hi"] = hi
        prop_rows.append(row)
        for m, name in enumerate(names):
            lin_rows.append({"du": avg.du, "marker": name, "linearity": lin[m],
                             "linearity_corrected": lin_c[m],
                             "max_displacement_mm": peak[m], "kept": bool(keep[m])})
            pm = props.per_marker
            marker_rows.append({"du": avg.du, "marker": name, "alpha_fwd": pm["alpha_fwd"][m],
                                "beta_fwd": pm["beta_fwd"][m], "alpha_bwd": pm["alpha_bwd"][m],
                                "beta_bwd": pm["beta_bwd"][m],
                                "sensitivity": 0.5 * (pm["alpha_fwd"][m] + pm["alpha_bwd"][m]),
                                "hysteresis": pm["beta_fwd"][m] - pm["beta_bwd"][m],
                                "max_displacement_mm": peak[m], "kept": bool(keep[m]),
                                "fitted": bool(fit_keep[m])})
    properties = pd.DataFrame(prop_rows, columns=PROPERTY_COLUMNS + [
        c for c in (prop_rows[0].keys() if prop_rows else []) if c not in PROPERTY_COLUMNS])
    linearity = pd.DataFrame(lin_rows, columns=["du", "marker", "linearity", "max_displacement_mm",
                                                "linearity_corrected", "kept"])
    return SessionAnalysis(properties, linearity, pd.DataFrame(marker_rows), du_props, keeps,
                           fitted, fields)


def plan_timing_from_rows(rows: pd.DataFrame, base: PlanTiming = PlanTiming()) -> PlanTiming:
    """The paper's plan timing, starting at the command file's first row after 0 s (a designed
    file has a row at every command step, even where the value repeats)."""
    later = rows["time_s"][rows["time_s"] > 1e-9]
    start = float(later.min()) if len(later) else base.start_s
    return PlanTiming(start_s=start, n_steps=base.n_steps, step_s=base.step_s,
                      hold_s=base.hold_s, tail_s=base.tail_s)


def evaluate_plan_take(X: np.ndarray, command: np.ndarray, rows: pd.DataFrame, fps: float,
                       plan: str, keep: np.ndarray) -> MotionEvaluation:
    """Evaluate a motion take played from plan A-E (paper timing) against its ideal."""
    timing = plan_timing_from_rows(rows)
    n = X.shape[0]
    t = np.arange(n) / fps
    ideal = timing.ideal(t, plan)
    delta = realized_delta(X, command)
    f0 = int(round(timing.start_s * fps))
    f1 = int(round((timing.start_s + timing.duration_s) * fps))
    b0 = int(round((timing.start_s + timing.duration_s + timing.hold_s) * fps))
    b1 = int(round((timing.start_s + 2 * timing.duration_s + timing.hold_s) * fps))
    peak = np.nanmax(np.linalg.norm(X - np.nanmean(X[: max(f0, 1)], axis=0)[None], axis=-1), axis=0)
    keep = keep & (peak >= 0.05)
    return evaluate_motion(delta, ideal, fps, slice(f0, min(f1, n)), slice(b0, min(b1, n)), keep)


def is_plan(label: str | None) -> bool:
    return label is not None and label.upper() in PLAN_NAMES
