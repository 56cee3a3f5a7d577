"""The paper's static-response indices computed literally (METHOD.md, "Static response").

This module is the paper's recipe and nothing else: no noise handling, no smoothing. Its numbers
are what properties.csv reports as ``alpha_fwd, beta_fwd, alpha_bwd, beta_bwd, sensitivity,
hysteresis, dyssynchrony_raw, linearity_mean`` (OUTPUTS.md). The estimates of what this recipe
gives on noise-free positions are in ``mocap.analysis.noise_corrected``.

Time axis (the schedule's, read from the take's command rows, :func:`schedule_timing`):
t = 0 at step s = 0 (one step before the first rising step), T_fwd the duration of the rising ramp
(t = 0 to the first step at the top command), t_end the start of the step that returns the
command to 0 and T_bwd = t_end - (start of the last step at the top, one step before the first
falling step). Repeated rows (a row per step during the hold) and rows that only restate the
command are ignored. For the paper's trapezoid
(100 steps of 50 ms): T_fwd = T_bwd = 20 steps = 1 s, t_end = 100 steps = 5 s.

Recipe, on the trial-averaged positions v_m(t) (n_frames, n_markers, 3) mm:

- d_m(t) = v_m(t) - v_m(0), v_m(0) the frame at t = 0;
- delta_m(t) = |d_m(t)| / max_t |d_m(t)|, the maximum over the schedule's frames
  (0 <= t < t_end + one step);
- forward: frames 0 <= t <= T_fwd, abscissa c = c_top t / T_fwd; backward: frames
  t_end - T_bwd <= t <= t_end, abscissa c = c_top (t_end - t) / T_bwd (c_top = 255 for the paper);
- one least-squares fit of R(c) = 1 / (1 + exp(-alpha (c - beta))) per branch over the pooled
  (c, delta_m) pairs of the kept markers (NaN pairs left out);
- sensitivity (alpha_fwd + alpha_bwd) / 2, hysteresis beta_fwd - beta_bwd;
- dyssynchrony_raw = mean over the schedule's frames of the sample standard deviation (ddof 1) of
  delta_m(t) over the kept markers (the paper's (1 / T_e) sum_t u_t on frames);
- linearity l_m: the first principal component's share of the variance of all positions of
  marker m over the schedule's frames, all trials pooled; linearity_mean / _std over the kept
  markers (std with ddof 0).

Markers kept: those the session's rejection rules keep (``rejections.csv``: the paper's two
rules, small displacement and abnormal inter-trial spread, and markers the reconstruction lost
too often).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from mocap.analysis.logistic_fit import fit_logistic

TIME_TOL_S = 1e-9  # frames within this of a window's edge are inside it (FORMAT.md's tolerance)


@dataclass(frozen=True)
class ScheduleTiming:
    """The paper's time axis of one take, in the take's own seconds (frame f at f / fps).

    t0_s: t = 0 (step s = 0); step_s: one command step; fwd_s: T_fwd; t_end_s: absolute time of
    t_end; bwd_s: T_bwd; top: the top command (255 for the paper).
    """

    t0_s: float
    step_s: float
    fwd_s: float
    t_end_s: float
    bwd_s: float
    top: float

    def frame_times(self, n_frames: int, fps: float) -> np.ndarray:
        """(n_frames,) t of each frame on the paper's axis (s; negative before step 0)."""
        return np.arange(n_frames) / float(fps) - self.t0_s

    def forward(self, n_frames: int, fps: float) -> tuple[np.ndarray, np.ndarray]:
        """(frames, c): the forward window's frame indices and their abscissa c = top t / T_fwd."""
        t = self.frame_times(n_frames, fps)
        f = np.flatnonzero((t >= -TIME_TOL_S) & (t <= self.fwd_s + TIME_TOL_S))
        return f, self.top * t[f] / self.fwd_s

    def backward(self, n_frames: int, fps: float) -> tuple[np.ndarray, np.ndarray]:
        """(frames, c): the backward window, c = top (t_end - t) / T_bwd."""
        t = self.frame_times(n_frames, fps)
        end = self.t_end_s - self.t0_s
        f = np.flatnonzero((t >= end - self.bwd_s - TIME_TOL_S) & (t <= end + TIME_TOL_S))
        return f, self.top * (end - t[f]) / self.bwd_s

    def schedule(self, n_frames: int, fps: float) -> np.ndarray:
        """(frames,) the schedule's frames, 0 <= t < t_end + one step (duration T_e)."""
        t = self.frame_times(n_frames, fps)
        end = self.t_end_s - self.t0_s + self.step_s
        return np.flatnonzero((t >= -TIME_TOL_S) & (t < end - TIME_TOL_S))

    def origin_frame(self, fps: float) -> int:
        """The frame at t = 0 (the first frame at or after step 0's start)."""
        return max(int(np.ceil(self.t0_s * float(fps) - 1e-6)), 0)


def schedule_timing(time_s, command, *, source: str = "command rows") -> ScheduleTiming:
    """The paper's time axis from one DU's command rows (a trapezoid: rise, hold, fall to 0).

    time_s, command : (n_rows,) the rows of one DU (any order; for equal times the later row
    wins, as FORMAT.md says). Raises ValueError naming ``source`` when the rows are not a
    rising ramp of several steps, a hold at the top, and a falling ramp back to 0.
    """
    t = np.asarray(time_s, float)
    c = np.asarray(command, float)
    if t.shape != c.shape or t.ndim != 1:
        raise ValueError(f"{source}: expected matching 1-D time_s and command, got {t.shape}, {c.shape}")
    order = np.argsort(t, kind="stable")
    t, c = t[order], c[order]
    last = np.r_[np.diff(t) > TIME_TOL_S, True]  # the last row of each time wins
    t, c = t[last], c[last]
    change = np.r_[True, np.diff(c) != 0]  # rows that change the command (repeats add nothing)
    t, c = t[change], c[change]
    if c.size == 0 or c[0] != 0:
        c = np.r_[0.0, c]  # the command is 0 before a DU's first row (FORMAT.md)
        t = np.r_[-np.inf, t]
    top = float(c.max())
    i_top = int(np.argmax(c == top))
    i_fall = i_top + int(np.argmax(c[i_top:] < top)) if np.any(c[i_top:] < top) else -1
    if top <= 0 or i_top < 2 or i_fall < 0:
        raise ValueError(f"{source}: expected a trapezoid (a rising ramp of several steps to the "
                         f"top command, a hold, a fall back to 0), got commands {c.tolist()[:12]}...")
    i_zero = i_fall + int(np.argmax(c[i_fall:] == 0)) if np.any(c[i_fall:] == 0) else -1
    rise = slice(1, i_top + 1)
    if i_zero < 0 or np.any(np.diff(c[rise]) <= 0) or np.any(np.diff(c[i_fall - 1: i_zero + 1]) >= 0):
        raise ValueError(f"{source}: expected a monotone rise to {top:g} and a monotone fall back "
                         "to 0 (the paper's trapezoid)")
    steps = np.diff(t[rise])
    step = float(np.median(steps))
    if not np.isfinite(step) or step <= 0:
        raise ValueError(f"{source}: cannot read the step time from the rising ramp's rows")
    t0 = float(t[1] - step)  # step 1 starts one step after t = 0
    fall0 = float(t[i_fall] - step)  # the last step at the top starts one step before the fall
    return ScheduleTiming(t0_s=t0, step_s=step, fwd_s=float(t[i_top] - t0),
                          t_end_s=float(t[i_zero]), bwd_s=float(t[i_zero] - fall0), top=top)


def timing_from_series(command: np.ndarray, fps: float) -> ScheduleTiming:
    """:func:`schedule_timing` from a per-frame command series (n_frames,): each change is a row
    at its frame's time. The step time is then known to a frame; prefer the command file."""
    c = np.asarray(command, float)
    f = np.r_[0, np.flatnonzero(np.diff(c) != 0) + 1]
    return schedule_timing(f / float(fps), c[f], source="command series")


@dataclass(frozen=True)
class PaperIndices:
    """One DU's indices by the paper's recipe (module docstring).

    alpha_* 1/command unit, beta_* command units; dyssynchrony_raw, linearity 1. ``delta``
    (n_frames, n_markers): |d| / max |d| at every frame of the take (the maximum over the
    schedule's frames; frames recorded after the schedule keep their values); ``linearity``
    (n_markers,); ``keep`` (n_markers,) the markers used; ``ci``: name -> (2.5 %, 97.5 %) from a
    bootstrap over the kept markers (the fits redone with the markers resampled).
    """

    alpha_fwd: float
    beta_fwd: float
    alpha_bwd: float
    beta_bwd: float
    dyssynchrony_raw: float
    linearity: np.ndarray
    delta: np.ndarray
    keep: np.ndarray
    timing: ScheduleTiming
    ci: dict

    @property
    def sensitivity(self) -> float:
        return 0.5 * (self.alpha_fwd + self.alpha_bwd)

    @property
    def hysteresis(self) -> float:
        return self.beta_fwd - self.beta_bwd

    @property
    def linearity_mean(self) -> float:
        return _nan_stat(np.nanmean, self.linearity[self.keep])

    @property
    def linearity_std(self) -> float:
        return _nan_stat(np.nanstd, self.linearity[self.keep])


def _nan_stat(f, x) -> float:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return float(f(x)) if np.size(x) else float("nan")


def paper_delta(mean: np.ndarray, timing: ScheduleTiming, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """(|d| (n_frames, M) mm, delta (n_frames, M)) of trial-mean positions ``mean`` (n_frames, M, 3):
    d = v(t) - v(0) with v(0) the frame at t = 0, delta = |d| / max over the schedule's frames."""
    v = np.asarray(mean, float)
    f0 = timing.origin_frame(fps)
    if f0 >= v.shape[0]:
        raise ValueError(f"take of {v.shape[0]} frames ends before the schedule's t = 0 "
                         f"({timing.t0_s:.3f} s)")
    length = np.linalg.norm(v - v[f0][None], axis=-1)
    sched = timing.schedule(v.shape[0], fps)
    with warnings.catch_warnings(), np.errstate(invalid="ignore", divide="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        peak = np.nanmax(length[sched], axis=0)
        return length, length / np.where(peak > 0, peak, np.nan)[None]


def pca_share(P: np.ndarray) -> np.ndarray:
    """(M,) first principal component's share of the variance of positions P (n_samples, M, 3)
    (NaN samples of a marker left out; NaN below 3 samples or with no variance)."""
    ok = np.all(np.isfinite(P), axis=-1)
    n = ok.sum(axis=0)
    Z = np.where(ok[..., None], P, 0.0)
    mean = Z.sum(axis=0) / np.maximum(n, 1)[:, None]
    D = np.where(ok[..., None], P - mean[None], 0.0)
    cov = np.einsum("smi,smj->mij", D, D)
    lam = np.linalg.eigvalsh(cov)
    total = lam.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where((n >= 3) & (total > 0), lam[:, -1] / total, np.nan)


def _pairs(delta_w: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pooled (c, delta, marker index) pairs of a window (n_w, M_kept), NaN pairs left out."""
    x = np.repeat(c[:, None], delta_w.shape[1], axis=1)
    m = np.broadcast_to(np.arange(delta_w.shape[1])[None], delta_w.shape)
    ok = np.isfinite(delta_w)
    return x[ok], delta_w[ok], m[ok]


def fit_sigmoid(c: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Least-squares (alpha, beta) of R(c) = 1 / (1 + exp(-alpha (c - beta))) to pairs (c, y),
    solved to the optimum: scipy's Levenberg-Marquardt from the batched fit's start and from a
    grid of starts over the command range, the lowest cost kept (noisy data have a flat valley
    towards alpha -> 0 that a single start can slide into)."""
    c = np.asarray(c, float)
    y = np.asarray(y, float)
    if c.size < 3:
        return float("nan"), float("nan")

    def resid(p):
        z = np.clip(-p[0] * (c - p[1]), -500, 500)
        return 1.0 / (1.0 + np.exp(z)) - y

    def jac(p):
        z = np.clip(-p[0] * (c - p[1]), -500, 500)
        r = 1.0 / (1.0 + np.exp(z))
        dr = r * (1 - r)
        return np.stack([dr * (c - p[1]), -dr * p[0]], axis=1)

    start = fit_logistic(c, y[None])
    lo, hi = float(np.min(c)), float(np.max(c))
    span = max(hi - lo, 1e-9)
    starts = [(float(start.a[0]), float(start.b[0]))]
    starts += [(k / span, lo + f * span) for k in (2.0, 8.0, 25.0) for f in (0.25, 0.5, 0.75)]
    best = None
    for a0, b0 in starts:
        if not (np.isfinite(a0) and np.isfinite(b0)):
            continue
        sol = least_squares(resid, [a0, b0], jac=jac, method="lm", xtol=1e-15, ftol=1e-15,
                            gtol=1e-15, max_nfev=2000)
        if best is None or sol.cost < best.cost:
            best = sol
    return float(best.x[0]), float(best.x[1])


def paper_indices(mean: np.ndarray, trials: np.ndarray, keep: np.ndarray, timing: ScheduleTiming,
                  fps: float, *, n_boot: int = 200, seed: int = 0) -> PaperIndices:
    """One DU's indices by the paper's recipe (module docstring).

    mean : (n_frames, M, 3) mm trial-averaged positions; trials : (n_trials, n_frames, M, 3) mm
    the aligned trials (for the linearity); keep : (M,) bool markers kept; timing : the take's
    :class:`ScheduleTiming`; n_boot : bootstrap replicates over the kept markers for the
    intervals (0: none).
    """
    mean = np.asarray(mean, float)
    n = mean.shape[0]
    _, delta = paper_delta(mean, timing, fps)
    keep = np.asarray(keep, bool) & np.any(np.isfinite(delta), axis=0)
    idx = np.flatnonzero(keep)
    sched = timing.schedule(n, fps)
    fits, boots = {}, {}
    rng = np.random.default_rng(seed)
    counts = (rng.multinomial(idx.size, np.full(idx.size, 1.0 / idx.size), size=n_boot).astype(float)
              if (n_boot and idx.size) else None)
    for name, (frames, c) in (("fwd", timing.forward(n, fps)), ("bwd", timing.backward(n, fps))):
        x, y, m = _pairs(delta[frames][:, idx], c)
        fits[name] = fit_sigmoid(x, y)
        if counts is not None and x.size >= 3:
            b = fit_logistic(x, np.broadcast_to(y, (n_boot, y.size)), counts[:, m],
                             a0=np.full(n_boot, fits[name][0]), b0=np.full(n_boot, fits[name][1]))
            boots[f"alpha_{name}"], boots[f"beta_{name}"] = b.a, b.b
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        u = np.nanstd(delta[sched][:, idx], axis=1, ddof=1) if idx.size >= 2 else np.full(sched.size, np.nan)
        dys = float(np.nanmean(u)) if np.isfinite(u).any() else float("nan")
    T = np.asarray(trials, float)[:, sched]
    lin = pca_share(T.reshape(-1, *T.shape[2:]))
    ci = {}
    if boots:
        boots["sensitivity"] = 0.5 * (boots["alpha_fwd"] + boots["alpha_bwd"])
        boots["hysteresis"] = boots["beta_fwd"] - boots["beta_bwd"]
        for k, v in boots.items():
            ci[k] = (float(np.nanpercentile(v, 2.5)), float(np.nanpercentile(v, 97.5)))
    return PaperIndices(fits["fwd"][0], fits["fwd"][1], fits["bwd"][0], fits["bwd"][1], dys, lin,
                        delta, keep, timing, ci)
