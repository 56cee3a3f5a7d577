"""Evaluation of a designed motion against its plan (the paper, "Motion design").

The realized normalised displacement of marker m is |d_m(t)| / max_t |d_m(t)| over the take
(the maximum on the displacement smoothed over ``smooth_frames``), d_m(t) from the mean position
before the first command change. Against the ideal P(t) (rest, the
plan rising, a hold, the return 1 - P, rest): the RMS of the markers' mean minus the ideal over
the rising part (forward) and the returning part (backward), the mean over markers of each
marker's RMS, and the lag (s) that best aligns the mean with the ideal (cross-correlation of
their derivatives, searched within +-0.5 s).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocap.analysis.paper.displacement import normalized
from mocap.core.display import Summarised, Summary


@dataclass(frozen=True, repr=False)
class MotionEvaluation(Summarised):
    t: np.ndarray  # (n_frames,) s
    ideal: np.ndarray  # (n_frames,)
    mean: np.ndarray  # (n_frames,)
    std: np.ndarray  # (n_frames,)
    rms_forward: float
    rms_backward: float
    rms_markers_forward: float
    rms_markers_backward: float
    lag_s: float

    def _summary(self) -> Summary:
        return Summary(f"MotionEvaluation: {self.t.size} frames",
                       (("rms", f"forward {self.rms_forward:.3g}, backward "
                                f"{self.rms_backward:.3g}"),
                        ("rms markers", f"forward {self.rms_markers_forward:.3g}, backward "
                                        f"{self.rms_markers_backward:.3g}"),
                        ("lag", f"{self.lag_s:.3g} s")),
                       more="attributes: .t .ideal .mean .std (n_frames,)")


def realized_delta(X: np.ndarray, command: np.ndarray, smooth_frames: int = 6) -> np.ndarray:
    """(n_frames, M) normalised displacement of a take's markers (see module docstring)."""
    change = np.flatnonzero(np.any(np.diff(command, axis=0) != 0, axis=-1)) if command.ndim > 1 \
        else np.flatnonzero(np.diff(command) != 0)
    lead = int(change[0]) + 1 if change.size else 1
    with np.errstate(invalid="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            rest = np.nanmean(X[:lead], axis=0)
    return normalized(X - rest[None], smooth_frames)[1]


def evaluate_motion(delta: np.ndarray, ideal: np.ndarray, fps: float, rise: slice,
                    fall: slice, keep: np.ndarray | None = None) -> MotionEvaluation:
    """Compare realized delta (n_frames, M) with the ideal (n_frames,) on the rise and the fall."""
    if keep is not None:
        delta = delta[:, keep]
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(delta, axis=1)
        std = np.nanstd(delta, axis=1)
    n = min(mean.size, ideal.size)
    mean, std, ideal = mean[:n], std[:n], ideal[:n]

    def rms(a, b, sl):
        return float(np.sqrt(np.nanmean((a[sl] - b[sl]) ** 2)))

    per_marker_f = np.sqrt(np.nanmean((delta[:n][rise] - ideal[rise, None]) ** 2, axis=0))
    per_marker_b = np.sqrt(np.nanmean((delta[:n][fall] - ideal[fall, None]) ** 2, axis=0))
    dm = np.diff(np.nan_to_num(mean))
    di = np.diff(ideal)
    max_lag = int(0.5 * fps)
    lags = np.arange(-max_lag, max_lag + 1)
    score = [np.dot(np.roll(di, k), dm) for k in lags]
    lag = lags[int(np.argmax(score))] / fps
    return MotionEvaluation(np.arange(n) / fps, ideal, mean, std, rms(mean, ideal, rise),
                            rms(mean, ideal, fall), float(np.nanmean(per_marker_f)),
                            float(np.nanmean(per_marker_b)), float(lag))
