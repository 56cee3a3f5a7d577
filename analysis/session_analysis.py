"""All of the paper's analyses (docs/indices.md) for one session, from the trial-averaged responses.

Pure computation: takes the reconstruction's results, returns tables and fitted models; the
pipeline writes them (properties.csv, linearity.csv, marker_properties.csv, figures).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Mapping, NamedTuple

import numpy as np
import pandas as pd

from mocap.analysis.design.inverse_response import PlanTiming
from mocap.analysis.design.evaluation import MotionEvaluation, evaluate_motion, realized_delta
from mocap.analysis.paper.displacement import plateau_mask
from mocap.analysis.paper.linearity import share_mean, spatial_linearity, step_noise_covariance
from mocap.analysis.noise.corrected import (
    capture_noise_covariance,
    corrected_dyssynchrony,
    corrected_fits,
    corrected_linearity,
    rest_sums,
)
from mocap.analysis.paper.indices import paper_indices, timing_from_series
from mocap.analysis.design.plans import PLAN_NAMES
from mocap.analysis.paper.properties import du_properties
from mocap.core.display import Summarised, Summary

MIN_STEP_DOF = 30  # in-take noise covariance needs this many degrees of freedom per marker
MIN_SNR = 20.0  # a marker enters the response fits when its peak is 20 x its trial mean's noise

# properties.csv's columns in the layout's order (docs/outputs.md): a plain name is the paper's
# computation literally, the same name with ``_corrected`` its noise-free estimate
LITERAL_COLUMNS = ("alpha_fwd", "beta_fwd", "alpha_bwd", "beta_bwd", "sensitivity", "hysteresis",
                   "dyssynchrony", "linearity_mean")
PROPERTY_COLUMNS = ["du", "name", *LITERAL_COLUMNS, *(f"{k}_corrected" for k in LITERAL_COLUMNS),
                    "linearity_std", "max_displacement_mm", "n_markers"]
# further columns, named for what they are (docs/indices.md): the literal fits' bootstrap
# intervals (``*_ci_lo``, ``*_ci_hi``); the along-path estimator: the fits on the displacement
# along each marker's principal direction normalised by its plateau, over the ramps' command
# lines one step beyond each ramp, markers with a peak 20 x their noise (``*_along_path``), its
# dyssynchrony on command-step means with their noise removed and its linearity with the
# in-take noise covariance removed
ALONG_PATH = ("alpha_fwd", "beta_fwd", "alpha_bwd", "beta_bwd", "sensitivity", "hysteresis")


class MotionResult(NamedTuple):
    """A motion take played from a plan, evaluated against the plan's ideal."""

    take: str
    plan: str
    evaluation: MotionEvaluation


# the columns a printed result shows (all of them are in .properties)
SUMMARY_COLUMNS = ("du", "name", "sensitivity", "hysteresis", "dyssynchrony", "linearity_mean")


@dataclass(frozen=True, repr=False)
class Analysis(Summarised):
    """The paper's analyses of a session: what ``mocap.analyze`` returns and
    ``RunResult.analysis`` holds.

    properties : one row per DU (properties.csv); linearity : per (DU, marker) (linearity.csv);
    marker_properties : per (DU, marker) along-path fits; du : DU -> its DUProperties (the
    along-path estimator); keep : DU -> (M,) bool, markers not rejected; fitted : DU -> (M,)
    bool, markers in the along-path fits;
    fields_mm : DU -> (M, 3) mean displacement at full command (mm); motions : the motion takes
    evaluated against their plans (``evaluate_plan_take``), added by the composer; paper : DU ->
    its PaperIndices (the paper's recipe, ``mocap.analysis.paper.indices``); trials : the
    trials analysed (``mocap.workflows.run.result.Trials``: averages, responses, rejections), set by the
    composer.
    """

    properties: pd.DataFrame
    linearity: pd.DataFrame
    marker_properties: pd.DataFrame
    du: Mapping  # du -> DUProperties (the along-path estimator)
    keep: Mapping[int, np.ndarray]
    fitted: Mapping[int, np.ndarray]
    fields_mm: Mapping[int, np.ndarray]
    motions: tuple[MotionResult, ...] = ()
    paper: Mapping | None = None  # du -> PaperIndices (the paper's recipe, mocap.analysis.paper.indices)
    trials: object | None = None  # mocap.workflows.run.result.Trials

    @property
    def rejections(self) -> pd.DataFrame | None:
        """rejections.csv's rows (the trials'; None when ``trials`` is not set)."""
        return None if self.trials is None else self.trials.rejections

    def _summary(self) -> Summary:
        shown = [m.take + f" (plan {m.plan})" for m in self.motions[:6]]
        lines = [("DUs", ", ".join(str(d) for d in self.properties["du"]) or "none"),
                 ("motions", ", ".join(shown) + (" ..." if len(self.motions) > 6 else "")
                  if shown else "none evaluated")]
        if self.trials is not None:
            lines.append(("rejections", str(len(self.trials.rejections))))
        return Summary(f"Analysis: {len(self.properties)} DUs, {len(self.motions)} motion takes",
                       tuple(lines), self.properties[[c for c in SUMMARY_COLUMNS
                                                      if c in self.properties.columns]],
                       "properties (one row per DU; all columns: .properties)",
                       "attributes: .properties .linearity .marker_properties .rejections "
                       ".motions .paper .du .trials")


def delta_noise_variance(delta: np.ndarray, command: np.ndarray) -> np.ndarray:
    """(M,) white-noise variance per frame of each marker's normalised curve, measured on the
    curve itself.

    Where the command is held at its lowest or highest value the true response is flat, so half
    the mean squared frame-to-frame difference there is the variance of the curve's white noise
    (trial-mean measurement noise and skin jitter alike, in delta units, whatever the noise's
    direction). How it reaches each step mean (through the rest reference and the plateau too)
    is ``mocap.analysis.paper.properties.step_noise_factor``'s business. Flat holds rather than every step:
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
    (``mocap.analysis.paper.linearity.step_noise_covariance``); where a marker has fewer than
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
                      noise_cov_mm2: np.ndarray | None = None, jobs: int = 1) -> Analysis:
    """Linearity, fitted responses and indices for every DU's averaged response.

    One naming rule (docs/outputs.md): the plain columns (``alpha_fwd`` ... ``hysteresis``,
    ``dyssynchrony``, ``linearity_mean``) are the paper's recipe literally on the measured data
    (``mocap.analysis.paper.indices``) over the markers the rejections keep; the same names
    ending ``_corrected`` estimate what that recipe gives on noise-free positions of the same
    trials, over the same markers (``mocap.analysis.noise.corrected``; the capture noise
    measured on each take's still frames): the fits on the noise-corrected chords
    (``corrected_fits``), ``dyssynchrony_corrected`` (``corrected_dyssynchrony``) and
    ``linearity_mean_corrected``, the mean of the markers' corrected shares clipped to [0, 1]
    (``mocap.analysis.paper.linearity.share_mean``). Columns ending ``_along_path``,
    ``dyssynchrony_step_means`` and ``linearity_step_noise_mean`` are the along-path estimator
    (docs/indices.md says when to prefer which); ``*_ci_lo``, ``*_ci_hi`` the literal fits'
    bootstrap intervals. marker_properties.csv holds the along-path fits per marker
    (``*_along_path``); linearity.csv each marker's ``linearity`` (literal) and
    ``linearity_corrected`` (clipped to [0, 1]).

    noise_mm : optional (M,) per-marker measurement noise sd (mm, per axis; the rest take's
        noise floor); the trial mean's noise is noise_mm / sqrt(n_trials). With it, the
        along-path fits use only markers whose peak displacement is at least ``MIN_SNR`` times
        that noise, and its step-mean dyssynchrony is corrected for the remaining noise
        (``mocap.analysis.paper.properties``); it is also the capture noise's fallback for markers
        with too few still frames.
    noise_cov_mm2 : optional (M, 3, 3) per-marker noise covariance at rest: the fallback
        preferred over ``noise_mm``.
    jobs : DUs analysed at once, on threads (the same results in any order).
    """
    prop_rows, lin_rows, marker_rows = [], [], []
    du_props, papers, keeps, fitted, fields = {}, {}, {}, {}, {}
    timings = [a.timing if a.timing is not None else timing_from_series(a.command, a.fps)
               for a in averages]
    # the face at rest before every response take: each DU's rest reference is pooled with the
    # other DUs' rest frames where they agree (``mocap.analysis.noise.corrected.pooled_rest``)
    sums = [rest_sums(a.trials, tm, a.fps) for a, tm in zip(averages, timings)]
    total = (sum(x[0] for x in sums), sum(x[1] for x in sums)) if sums else None

    def one_du(i: int):
        avg = averages[i]
        keep = kept_markers(rejections, names, avg.du)
        timing = timings[i]
        others_n = total[1] - sums[i][1]
        with np.errstate(invalid="ignore", divide="ignore"):
            prior = ((total[0] - sums[i][0]) / others_n[:, None], others_n)
        paper = paper_indices(avg.mean, avg.trials, keep, timing, avg.fps, n_boot=n_boot)
        fallback = noise_cov_mm2
        if fallback is None and noise_mm is not None:
            fallback = (np.asarray(noise_mm, float) ** 2)[:, None, None] * np.eye(3)
        noise = capture_noise_covariance(avg.trials, avg.command, avg.fps, fallback=fallback)
        dys_c, chord = corrected_dyssynchrony(avg.mean, avg.n_trials, paper.keep, timing,
                                              avg.fps, noise.cov, rest_prior=prior)
        fits_c = corrected_fits(chord, paper.keep, timing, avg.fps)
        lin_c = corrected_linearity(avg.trials, timing, avg.fps, noise.cov)
        # the along-path estimator (today's, kept in its own columns)
        pooled = avg.trials.reshape(-1, *avg.trials.shape[2:])
        lin_step = spatial_linearity(pooled, take_noise_covariance(avg, noise_mm, noise_cov_mm2))
        delta = avg.delta_along if avg.delta_along is not None else avg.delta
        noise_var, plateau = None, None
        n_tr = np.maximum(np.max(avg.n_trials, axis=0), 1)  # trials that saw each marker
        if noise_mm is not None:
            noise_var = delta_noise_variance(delta, avg.command)
            from mocap.reconstruction.trials import NORMALISE_S

            plateau = plateau_mask(delta, max(1, int(round(NORMALISE_S * avg.fps))))[0]
        fit_keep = keep
        if noise_mm is not None:
            se = np.asarray(noise_mm) / np.sqrt(n_tr)
            peak = np.nanmax(np.where(np.isfinite(avg.displacement_mm), avg.displacement_mm,
                                      -np.inf), axis=0)
            fit_keep = keep & (peak >= MIN_SNR * se)
        props = du_properties(avg.du, delta, avg.command, avg.fps, fit_keep, n_boot=0,
                              noise_var=noise_var, plateau=plateau)
        hold = avg.command == avg.command.max()
        with warnings.catch_warnings():  # a marker never seen on the hold: NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            field_mm = np.nanmean(avg.mean[hold] - avg.rest_mm[None], axis=0)
        peak = np.nanmax(np.where(np.isfinite(avg.displacement_mm), avg.displacement_mm, -np.inf), axis=0)
        kept = paper.keep
        row = {"du": avg.du, "name": du_names.get(avg.du, f"DU{avg.du}"),
               "alpha_fwd": paper.alpha_fwd, "beta_fwd": paper.beta_fwd,
               "alpha_bwd": paper.alpha_bwd, "beta_bwd": paper.beta_bwd,
               "sensitivity": paper.sensitivity, "hysteresis": paper.hysteresis,
               "dyssynchrony": paper.dyssynchrony, "linearity_mean": paper.linearity_mean}
        row.update({f"{k}_corrected": v for k, v in fits_c.items()})
        row["dyssynchrony_corrected"] = dys_c
        row["linearity_mean_corrected"] = share_mean(lin_c, kept)
        row.update({"linearity_std": paper.linearity_std,
                    "max_displacement_mm": float(np.nanmax(peak[keep])) if keep.any() else np.nan,
                    "n_markers": int(kept.sum())})
        for k, (lo, hi) in paper.ci.items():
            row[f"{k}_ci_lo"] = lo
            row[f"{k}_ci_hi"] = hi
        along = {"alpha_fwd": props.fwd.alpha, "beta_fwd": props.fwd.beta,
                 "alpha_bwd": props.bwd.alpha, "beta_bwd": props.bwd.beta,
                 "sensitivity": props.sensitivity, "hysteresis": props.hysteresis}
        for k in ALONG_PATH:
            row[f"{k}_along_path"] = along[k]
        row["n_markers_along_path"] = int(props.n_markers)
        row["dyssynchrony_step_means"] = props.dyssynchrony
        row["linearity_step_noise_mean"] = share_mean(lin_step, fit_keep)
        lin = paper.linearity
        lin_du, marker_du = [], []
        pm = props.per_marker
        for m, name in enumerate(names):
            lin_du.append({"du": avg.du, "marker": name, "linearity": lin[m],
                           "linearity_corrected": float(np.clip(lin_c[m], 0.0, 1.0)),
                           "max_displacement_mm": peak[m], "kept": bool(keep[m])})
            marker_du.append({"du": avg.du, "marker": name,
                              "alpha_fwd_along_path": pm["alpha_fwd"][m],
                              "beta_fwd_along_path": pm["beta_fwd"][m],
                              "alpha_bwd_along_path": pm["alpha_bwd"][m],
                              "beta_bwd_along_path": pm["beta_bwd"][m],
                              "sensitivity_along_path": 0.5 * (pm["alpha_fwd"][m] + pm["alpha_bwd"][m]),
                              "hysteresis_along_path": pm["beta_fwd"][m] - pm["beta_bwd"][m],
                              "max_displacement_mm": peak[m], "kept": bool(keep[m]),
                              "fitted": bool(fit_keep[m])})
        return props, paper, keep, fit_keep, field_mm, row, lin_du, marker_du

    # DU by DU on threads (numpy's heavy loops run outside the GIL; the results do not depend on
    # the order: each DU's bootstraps draw from their own seeded generator)
    if jobs > 1 and len(averages) > 1:
        from concurrent.futures import ThreadPoolExecutor

        # the warnings filters are the process's (catch_warnings is not thread-safe before
        # Python 3.14): the DUs' own expected-NaN silencing would race, so the threads run with
        # RuntimeWarnings held off as a whole and the filters restored after
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            with ThreadPoolExecutor(max_workers=min(jobs, len(averages))) as pool:
                results = list(pool.map(one_du, range(len(averages))))
    else:
        results = [one_du(i) for i in range(len(averages))]
    for avg, (props, paper, keep, fit_keep, field_mm, row, lin_du, marker_du) in zip(averages,
                                                                                    results):
        du_props[avg.du], papers[avg.du], keeps[avg.du] = props, paper, keep
        fitted[avg.du], fields[avg.du] = fit_keep, field_mm
        prop_rows.append(row)
        lin_rows += lin_du
        marker_rows += marker_du
    properties = pd.DataFrame(prop_rows, columns=PROPERTY_COLUMNS + [
        c for c in (prop_rows[0].keys() if prop_rows else []) if c not in PROPERTY_COLUMNS])
    linearity = pd.DataFrame(lin_rows, columns=["du", "marker", "linearity", "max_displacement_mm",
                                                "linearity_corrected", "kept"])
    return Analysis(properties, linearity, pd.DataFrame(marker_rows), du_props, keeps,
                           fitted, fields, paper=papers)


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
