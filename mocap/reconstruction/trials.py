"""Trials, noise floor and rejections (the paper, "Experiment").

Conventions: trajectories are dense arrays (n_frames, n_markers, 3) in mm with NaN where a
marker was not reconstructed; the first axis is time.

- Trial alignment: a DU's response takes are aligned on their command series (the frame of the
  first non-zero command), truncated to their common length; takes whose aligned command series
  differ are reported.
- Averaging: per frame and marker, the NaN-aware mean over trials; ``spread_mm`` is the
  across-trial standard deviation of the position as the RMS over the three axes of the per-axis
  sample standard deviation (what the paper calls the inter-trial standard deviation);
  ``n_trials`` counts the trials that saw the marker in that frame.
- Displacement: d_m(t) = v_m(t) - v_m(0), where v_m(0) is the mean position over the frames
  before the first command change (the take's rest lead-in), less noisy than frame 0 alone;
  ``delta`` = |d| / max_t |d| per (DU, marker), the maximum taken on the displacement smoothed
  over ``NORMALISE_S`` (see ``mocap.reconstruction.displacement``).
- Noise floor: per marker and axis, the standard deviation over the rest take's frames; the
  session's noise floor is their mean (the paper: 0.025 mm).
- Rejections (``rejections.csv``), each with a stable reason keyword, its value and threshold:
  ``small_displacement`` (per DU and marker: peak displacement under ``min_displacement_mm``;
  the peak is taken on the displacement vector averaged over a centred window of
  ``smooth_s`` (0.25 s by default, far shorter than the 3 s hold at full command), so that the
  noise's largest excursion over hundreds of frames does not pass for motion; with the paper's
  10 trials this matters little, with 3 it decides),
  ``abnormal_spread`` (per marker: mean across-trial spread above median + ``spread_k`` scaled
  MADs over the markers, and above ``spread_ratio`` times the median), ``gaps`` (per marker:
  fraction of response frames not reconstructed above ``max_gap_fraction``).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import pandas as pd

from mocap.reconstruction.displacement import normalized, normalized_along, peak_length, principal_direction
from mocap.core.schedules import ScheduleTiming, timing_from_series
from mocap.reconstruction.settings import RejectionSettings
from mocap.core.display import Summarised, Summary

NORMALISE_S = 0.25  # well within the 3 s hold at full command of the paper's schedule


@dataclass(frozen=True, repr=False)
class TrialAverage(Summarised):
    """One DU's averaged response.

    command : (n_frames,) the DU's command; mean : (n_frames, M, 3) mm; spread_mm : (n_frames,
    M); n_trials : (n_frames, M) int; rest_mm : (M, 3) v(0); displacement_mm : (n_frames, M);
    delta : (n_frames, M) the paper's |d| / max |d|; delta_along : the same along each marker's
    principal direction (noise-unbiased, ``mocap.reconstruction.displacement.normalized_along``); trials :
    (n_trials, n_frames, M, 3) the aligned trials; takes: names.
    """

    du: int
    fps: float
    command: np.ndarray
    mean: np.ndarray
    spread_mm: np.ndarray
    n_trials: np.ndarray
    rest_mm: np.ndarray
    displacement_mm: np.ndarray
    delta: np.ndarray
    trials: np.ndarray
    takes: tuple[str, ...]
    warnings: tuple[str, ...] = ()
    delta_along: np.ndarray | None = None  # (n_frames, M) along the principal direction
    along_mm: np.ndarray | None = None  # (n_frames, M) displacement along it, mm
    direction: np.ndarray | None = None  # (M, 3) each marker's unit principal direction

    def _summary(self) -> Summary:
        n_frames, n_markers = self.mean.shape[:2]
        return Summary(f"TrialAverage of DU {self.du}: {len(self.takes)} trials, {n_frames} "
                       f"frames x {n_markers} markers at {self.fps:g} fps",
                       (("takes", ", ".join(self.takes[:8]) + (" ..." if len(self.takes) > 8
                                                                 else "")),
                        ("peak", f"{np.nanmax(self.displacement_mm, initial=0):.3g} mm")),
                       more="attributes: .mean (n_frames, M, 3) mm .command .displacement_mm "
                            ".delta .trials")
    timing: ScheduleTiming | None = None  # the paper's time axis, from the first take's command rows


def _first_change(command: np.ndarray) -> int:
    nz = np.flatnonzero(command != command[0])
    return int(nz[0]) if nz.size else 0


def average_trials(du: int, trajectories: list[np.ndarray], commands: list[np.ndarray],
                   fps: float, takes: list[str], timing: ScheduleTiming | None = None) -> TrialAverage:
    """Align and average a DU's trials (see the module docstring).

    ``timing``: the paper's time axis of the first take (the one the others are aligned to),
    read from its command rows (``mocap.analysis.paper.indices.schedule_timing``); without it,
    read from the first take's per-frame command series (the step time then known to a frame).
    """
    starts = [_first_change(c) for c in commands]
    ref = starts[0]
    shifted_X, shifted_c = [], []
    for X, c, s in zip(trajectories, commands, starts):
        k = s - ref
        if k >= 0:
            shifted_X.append(X[k:])
            shifted_c.append(c[k:])
        else:  # pad the start with NaN / the initial command
            pad = np.full((-k,) + X.shape[1:], np.nan)
            shifted_X.append(np.concatenate([pad, X]))
            shifted_c.append(np.concatenate([np.full(-k, c[0]), c]))
    n = min(x.shape[0] for x in shifted_X)
    T = np.stack([x[:n] for x in shifted_X])
    C = np.stack([c[:n] for c in shifted_c])
    warnings = []
    differ = [takes[i] for i in range(len(takes)) if not np.array_equal(C[i], C[0])]
    if differ:
        warnings.append(f"DU {du}: the command series of {differ} differ from {takes[0]}'s after "
                        "alignment; averaged anyway")
    with np.errstate(invalid="ignore"):
        seen = np.isfinite(T[..., 0])
        n_tr = seen.sum(axis=0)
        mean = np.where(n_tr[..., None] > 0,
                        np.nansum(T, axis=0) / np.maximum(n_tr, 1)[..., None], np.nan)
        dev = np.where(seen[..., None], T - mean[None], 0.0)
        var = np.sum(dev**2, axis=0) / np.maximum(n_tr - 1, 1)[..., None]
        spread = np.where(n_tr >= 2, np.sqrt(var.mean(axis=-1)), np.nan)
    command = C[0]
    lead = max(_first_change(command), 1)
    with np.errstate(invalid="ignore"):
        import warnings as _w

        with _w.catch_warnings():
            _w.simplefilter("ignore", RuntimeWarning)
            rest = np.nanmean(mean[:lead], axis=0)
    window = max(1, int(round(NORMALISE_S * fps)))
    disp, delta = normalized(mean - rest[None], window)
    direction = principal_direction(mean - rest[None])
    along, delta_along = normalized_along(mean - rest[None], window, direction)
    if timing is None:
        timing = timing_from_series(commands[0], fps)
    return TrialAverage(du, fps, command, mean, spread, n_tr, rest, disp, delta, T,
                        tuple(takes), tuple(warnings), delta_along, along, direction, timing)


def responses_frame(avg: TrialAverage, names) -> pd.DataFrame:
    """Rows (du, frame, marker) per docs/outputs.md's responses.parquet."""
    n, M = avg.displacement_mm.shape
    return pd.DataFrame({
        "du": np.int64(avg.du),
        "frame": np.repeat(np.arange(n, dtype=np.int64), M),
        "time_s": np.repeat(np.arange(n) / avg.fps, M),
        "command": np.repeat(avg.command.astype(np.int64), M),
        "marker": np.tile(np.asarray(names, dtype=object), n),
        "x": avg.mean[..., 0].ravel(),
        "y": avg.mean[..., 1].ravel(),
        "z": avg.mean[..., 2].ravel(),
        "spread_mm": avg.spread_mm.ravel(),
        "n_trials": avg.n_trials.ravel().astype(np.int64),
        "displacement_mm": avg.displacement_mm.ravel(),
        "delta": avg.delta.ravel(),
        "delta_along": (avg.delta_along if avg.delta_along is not None else avg.delta).ravel(),
    })


def noise_floor(rest_X: np.ndarray) -> tuple[np.ndarray, float]:
    """Per marker and axis standard deviation (M, 3) mm over a still take, and their mean."""
    with np.errstate(invalid="ignore"):
        import warnings as _w

        with _w.catch_warnings():
            _w.simplefilter("ignore", RuntimeWarning)
            sd = np.nanstd(rest_X, axis=0, ddof=1)
    return sd, float(np.nanmean(sd))


def peak_displacement(avg: TrialAverage, smooth_s: float = 0.25) -> np.ndarray:
    """(M,) max over frames of |d| after a centred moving average of ``smooth_s`` seconds."""
    return peak_length(avg.mean - avg.rest_mm[None], max(1, int(round(smooth_s * avg.fps))))


def marker_spread(averages: list[TrialAverage]) -> np.ndarray:
    """(M,) mm each marker's inter-trial spread: the mean over the DUs of its mean over the
    take's frames; NaN for a marker no DU's takes saw (rejected for its gaps)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(np.stack([np.nanmean(a.spread_mm, axis=0) for a in averages]), axis=0)


def find_rejections(averages: list[TrialAverage], names, settings: RejectionSettings = RejectionSettings()
                    ) -> pd.DataFrame:
    """Rejections table (du, marker, reason, value, threshold); ``du`` is NA for all-DU rows."""
    rows = []
    names = np.asarray(names, dtype=object)
    for avg in averages:
        peak = peak_displacement(avg, settings.smooth_s)
        # a marker with no usable sample in this DU's takes has no displacement to judge: it is
        # rejected for its gaps below
        for m in np.flatnonzero(np.isfinite(peak) & (peak < settings.min_displacement_mm)):
            rows.append((avg.du, names[m], "small_displacement", float(peak[m]),
                         settings.min_displacement_mm))
    if averages:
        per_marker = marker_spread(averages)
        med = np.nanmedian(per_marker)
        mad = 1.4826 * np.nanmedian(np.abs(per_marker - med))
        threshold = max(med + settings.spread_k * mad, settings.spread_ratio * med)
        for m in np.flatnonzero(per_marker > threshold):
            rows.append((pd.NA, names[m], "abnormal_spread", float(per_marker[m]), float(threshold)))
        missing = np.stack([np.isnan(a.trials[..., 0]).mean(axis=(0, 1)) for a in averages]).mean(axis=0)
        for m in np.flatnonzero(missing > settings.max_gap_fraction):
            rows.append((pd.NA, names[m], "gaps", float(missing[m]), settings.max_gap_fraction))
    df = pd.DataFrame(rows, columns=["du", "marker", "reason", "value", "threshold"])
    df["du"] = df["du"].astype("Int64")
    return df
