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
from scipy.optimize import leastsq

from mocap.analysis.logistic_fit import fit_logistic, grouped_samples
# the paper's time axis is read from the command rows: core (reconstruction needs it too)
from mocap.schedules import TIME_TOL_S, ScheduleTiming, schedule_timing, timing_from_series  # noqa: F401


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
    start = fit_logistic(c, y[None])
    lo, hi = float(np.min(c)), float(np.max(c))
    # pooled pairs share their abscissae (a window's frames tiled once per marker): the least
    # squares on each abscissa's mean weighted by its count has the same gradient, Gauss-Newton
    # matrix and minimum (the cost less a constant), on M times fewer residuals
    c, Y, S, _ = grouped_samples(c, y[None], np.ones((1, c.size)))
    y, sw = Y[0], np.sqrt(S[0])

    last: list = [None, None]  # (alpha, beta), R there: the Jacobian comes at the point just fitted

    def response(p):
        if last[0] != (p[0], p[1]):
            z = -p[0] * (c - p[1])
            last[0], last[1] = (p[0], p[1]), 1.0 / (1.0 + np.exp(np.clip(z, -500, 500, out=z)))
        return last[1]

    def resid(p):
        return sw * (response(p) - y)

    def jac(p):
        r = response(p)
        dr = sw * r * (1 - r)
        J = np.empty((c.size, 2))
        np.multiply(dr, c - p[1], out=J[:, 0])
        np.multiply(-dr, p[0], out=J[:, 1])
        return J

    span = max(hi - lo, 1e-9)
    starts = [(float(start.a[0]), float(start.b[0]))]
    starts += [(k / span, lo + f * span) for k in (2.0, 8.0, 25.0) for f in (0.25, 0.5, 0.75)]
    # MINPACK's lmder through leastsq: the call least_squares(method="lm") makes with its default
    # scaling (scipy >= 1.16: diag from the Jacobian), bitwise the same fits, without the wrapper
    # that checks and copies every point and residual (a fifth of each fit's time)
    best, best_cost = None, np.inf
    for a0, b0 in starts:
        if not (np.isfinite(a0) and np.isfinite(b0)):
            continue
        with np.errstate(over="ignore", invalid="ignore"):  # leastsq's covariance, unused here
            x, _, info, _, _ = leastsq(resid, [a0, b0], Dfun=jac, full_output=True, xtol=1e-15,
                                       ftol=1e-15, gtol=1e-15, maxfev=2000)
        cost = 0.5 * float(np.dot(info["fvec"], info["fvec"]))
        if best is None or cost < best_cost:
            best, best_cost = x, cost
    return float(best[0]), float(best[1])


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
