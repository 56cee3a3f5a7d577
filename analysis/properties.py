"""The paper's static response properties per DU (METHOD.md, "Static response").

Segmentation: the forward (rising) and backward (falling) ramps are found from the command
series: their step changes are fitted by a straight line ``c(t) = p0 + p1 t`` (for the paper's
trapezoid ``c = 255 t / T_s`` forward), and the fit window runs from one step before the ramp's
first change to one step after its last (so both end plateaus are included).

Fits: the normalised displacement delta_m(t) of the markers kept (not rejected) in a window is
fitted against time by a logistic ``1 / (1 + exp(-a (t - b)))`` pooled over the markers (and per
marker), then converted to command with the ramp's line: ``alpha = a / p1``, ``beta = p0 +
p1 b`` (METHOD.md's t = T_s c / 255 for the paper's schedule).

Indices: sensitivity alpha_n = (alpha_fwd + alpha_bwd) / 2; hysteresis beta_fwd - beta_bwd
(command units; positive when the backward curve stays high); dyssynchrony gamma = the mean over
the take's frames of the sample standard deviation of delta_m(t) over the markers
(``dyssynchrony_raw``, the paper's formula). Measurement noise inflates that spread: a marker
moving 0.1 mm with 0.01 mm of noise on its trial mean has 0.1 of noise in its delta.
``dyssynchrony`` estimates the noise-free index: the same formula on command-step means, with
each marker's noise variance on its step mean subtracted from the variance over the markers
(:func:`dyssynchrony_steps`). That noise variance follows how the curve was made, delta = (x -
r) / (p - r), with r the mean over the rest lead-in and p the mean over the plateau: to first
order a step mean's error is mean_step(e) - (1 - delta) mean_rest(e) - delta mean_plateau(e) for
white noise e on the curve (:func:`step_noise_factor`). So the rest reference's error weighs
fully near rest and not at all on the plateau; subtracting it at full weight at every step (as
an earlier version did) over-corrected, by 13-17 % where the true spread is small.

The fits use ``delta_along`` when given (the displacement along each marker's principal
direction, whose noise has zero mean), METHOD.md's |d| / max |d| otherwise.

Uncertainty: a bootstrap over markers (``n_boot`` replicates, markers resampled with
replacement, the pooled fits redone as weighted fits) gives 2.5 / 97.5 % intervals.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocap.analysis.logistic_fit import fit_logistic


@dataclass(frozen=True)
class Ramp:
    """A ramp's fit window (frame slice) and its command line c(t) = p0 + p1 t."""

    start: int
    stop: int
    p0: float
    p1: float

    @property
    def direction(self) -> str:
        return "forward" if self.p1 > 0 else "backward"


@dataclass(frozen=True)
class SigmoidParams:
    alpha: float
    beta: float


@dataclass(frozen=True)
class DUProperties:
    du: int
    fwd: SigmoidParams
    bwd: SigmoidParams
    sensitivity: float
    hysteresis: float
    dyssynchrony: float
    dyssynchrony_raw: float
    n_markers: int
    ci: dict  # name -> (lo, hi)
    per_marker: dict  # alpha_fwd, beta_fwd, alpha_bwd, beta_bwd (n_markers,) arrays (NaN for left-out)
    ramps: tuple[Ramp, Ramp]


def find_ramps(command: np.ndarray, fps: float) -> tuple[Ramp, Ramp]:
    """The forward and backward ramps of a trapezoid-like command series (n_frames,)."""
    c = np.asarray(command, float)
    change = np.flatnonzero(np.diff(c) != 0) + 1
    if change.size < 2:
        raise ValueError("response take: the command never ramps (fewer than two changes)")
    up = change[c[change] > c[change - 1]]
    down = change[c[change] < c[change - 1]]
    if up.size < 2 or down.size < 2:
        raise ValueError("response take: expected a rising and a falling ramp of several steps")
    step = int(np.median(np.diff(change)))

    def line(frames):
        frames = np.r_[frames[0] - step, frames]
        t = frames / fps
        vals = c[np.clip(frames, 0, c.size - 1)]
        p1, p0 = np.polyfit(t, vals, 1)
        return p0, p1

    p0f, p1f = line(up)
    p0b, p1b = line(down)
    fwd = Ramp(max(up[0] - step, 0), min(up[-1] + step, c.size), p0f, p1f)
    bwd = Ramp(max(down[0] - step, 0), min(down[-1] + step, c.size), p0b, p1b)
    return fwd, bwd


def dyssynchrony(delta: np.ndarray, keep: np.ndarray, noise_var: np.ndarray | None = None,
                 smooth_frames: int = 30) -> float:
    """Mean over frames of the std over kept markers of delta (n_frames, n_markers).

    ``noise_var`` (n_markers,): each marker's noise variance in delta units; when given, the
    variance over markers is first averaged over ``smooth_frames`` frames (so its sampling
    fluctuation does not survive the floor at 0 as a bias), then the markers' mean noise
    variance is subtracted, floored at 0, and the square root taken.
    """
    d = delta[:, keep]
    import warnings

    from mocap.analysis.displacement import smoothed

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        var = np.nanvar(d, axis=1, ddof=1)
        if noise_var is not None:
            var = smoothed(var, smooth_frames)
            var = np.clip(var - np.nanmean(np.asarray(noise_var)[keep]), 0.0, None)
        return float(np.nanmean(np.sqrt(var)))


def _pooled(t, delta_w, weights=None):
    """Pooled logistic fit over markers: t (n,), delta_w (n, M); weights (B, M) or None."""
    n, M = delta_w.shape
    x = np.tile(t, M)
    y = delta_w.T.ravel()[None]
    if weights is None:
        return fit_logistic(x, y)
    W = np.repeat(weights, n, axis=1)
    first = fit_logistic(x, y)
    return fit_logistic(x, np.broadcast_to(y, W.shape), W,
                        a0=np.full(W.shape[0], first.a[0]), b0=np.full(W.shape[0], first.b[0]))


def command_runs(command: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(start, length) of the runs of constant command (the steps) of a command series."""
    c = np.asarray(command)
    start = np.r_[0, np.flatnonzero(np.diff(c) != 0) + 1]
    return start, np.diff(np.r_[start, c.size])


def rest_frame_count(command: np.ndarray) -> int:
    """Frames before the command's first change: the rest lead-in that v_m(0) averages."""
    c = np.asarray(command)
    nz = np.flatnonzero(c != c[0])
    return max(int(nz[0]) if nz.size else 0, 1)


def step_noise_factor(command: np.ndarray, step_delta: np.ndarray, rest_frames: int,
                      plateau: np.ndarray) -> np.ndarray:
    """(n_steps, M): variance of each marker's step-mean error per unit of its curve's white
    noise variance (per frame).

    The curve is delta(t) = (x(t) - r) / (p - r), r the mean over the first ``rest_frames``
    frames (A), p the mean over the plateau frames (H, ``plateau`` (n_frames, M) bool). For white
    noise e on x the error of the mean over a step F is, to first order (in delta units),
    ``mean_F(e) - (1 - d) mean_A(e) - d mean_H(e)``, d the step's delta, of variance
    ``sum_t w_t^2`` times the white variance, w = 1_F / |F| - (1 - d) 1_A / |A| - d 1_H / |H|.
    ``step_delta`` (n_steps, M) gives d (the observed step means; clipped to [0, 1]).
    """
    c = np.asarray(command)
    start, length = command_runs(c)
    seg = np.repeat(np.arange(start.size), length)
    H = np.asarray(plateau, bool)
    A = np.arange(c.size) < rest_frames
    nA = float(A.sum())
    nH = np.maximum(H.sum(axis=0), 1).astype(float)[None]
    FH = np.zeros((start.size, H.shape[1]))
    np.add.at(FH, seg, H)
    FA = np.bincount(seg, weights=A, minlength=start.size)[:, None]
    AH = (H & A[:, None]).sum(axis=0)[None]
    L = length[:, None].astype(float)
    d = np.clip(step_delta, 0.0, 1.0)
    return (1.0 / L + (1 - d) ** 2 / nA + d**2 / nH - 2 * (1 - d) * FA / (L * nA)
            - 2 * d * FH / (L * nH) + 2 * d * (1 - d) * AH / (nA * nH))


def dyssynchrony_steps(delta: np.ndarray, keep: np.ndarray, command: np.ndarray,
                       white_var: np.ndarray | None = None, *, rest_frames: int | None = None,
                       plateau: np.ndarray | None = None) -> float:
    """Dyssynchrony on command-step means, corrected for noise.

    The take is cut into runs of constant command (steps); each marker's curve is averaged over
    each step and the variance over the kept markers taken per step. With ``white_var`` (M,),
    each marker's white-noise variance per frame on its curve, the mean over the kept markers of
    its step mean's noise variance (``white_var`` x :func:`step_noise_factor`, the rest
    reference over ``rest_frames`` (default: the frames before the first command change) and
    the plateau ``plateau`` (n_frames, M) bool (default: the frames at the highest command)) is
    subtracted: an unbiased estimate of the noise-free variance over the markers. The result is
    floored at 0 and the square roots averaged with the steps' lengths as weights. For a face
    whose response is constant within a step this equals the paper's per-frame formula without
    noise; averaging within steps first shrinks the noise by the step length. The square root
    of an unbiased variance still leans (low where the spread is near its noise, high where it
    is near 0): a few per cent for the paper preset (tests/test_analysis.py's Monte-Carlo).
    """
    d = delta[:, keep]
    c = np.asarray(command)
    start, length = command_runs(c)
    ok = np.isfinite(d)
    sums = np.add.reduceat(np.where(ok, d, 0.0), start, axis=0)
    counts = np.add.reduceat(ok.astype(float), start, axis=0)
    import warnings

    with warnings.catch_warnings(), np.errstate(invalid="ignore", divide="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        means = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
        var = np.nanvar(means, axis=1, ddof=1)
        if white_var is not None:
            rest = rest_frame_count(c) if rest_frames is None else int(rest_frames)
            H = (np.broadcast_to((c == c.max())[:, None], d.shape) if plateau is None
                 else np.asarray(plateau, bool)[:, keep])
            f = step_noise_factor(c, means, rest, H)
            var = var - np.nanmean(np.asarray(white_var, float)[keep][None] * f, axis=1)
        u = np.sqrt(np.clip(var, 0.0, None))
        good = np.isfinite(u)
        return float(np.sum(u[good] * length[good]) / max(np.sum(length[good]), 1))


def du_properties(du: int, delta: np.ndarray, command: np.ndarray, fps: float, keep: np.ndarray,
                  *, n_boot: int = 200, seed: int = 0,
                  noise_var: np.ndarray | None = None,
                  plateau: np.ndarray | None = None) -> DUProperties:
    """Fit a DU's forward and backward responses and compute its indices.

    delta : (n_frames, n_markers) normalised displacement (trial mean).
    command : (n_frames,) the DU's command series.
    keep : (n_markers,) bool, markers not rejected for this DU.
    noise_var : optional (n_markers,) white-noise variance of each marker's delta per frame;
    plateau : optional (n_frames, n_markers) bool, the frames its normalisation averaged (default:
    those at the highest command); the rest reference is the lead-in before the first change.
    ``dyssynchrony`` is computed on command-step means with the noise removed
    (:func:`dyssynchrony_steps`), ``dyssynchrony_raw`` by the paper's per-frame formula.
    """
    fwd, bwd = find_ramps(command, fps)
    keep = np.asarray(keep, bool) & np.any(np.isfinite(delta), axis=0)
    idx = np.flatnonzero(keep)
    rng = np.random.default_rng(seed)
    boot_w = rng.multinomial(idx.size, np.full(idx.size, 1.0 / idx.size), size=n_boot).astype(float)
    out, per_marker, boots = {}, {}, {}
    for name, ramp in (("fwd", fwd), ("bwd", bwd)):
        t = np.arange(ramp.start, ramp.stop) / fps
        dw = delta[ramp.start: ramp.stop][:, idx]
        pooled = _pooled(t, dw)
        out[name] = SigmoidParams(float(pooled.a[0] / ramp.p1), float(ramp.p0 + ramp.p1 * pooled.b[0]))
        fits = fit_logistic(t, dw.T)
        am = np.full(delta.shape[1], np.nan)
        bm = np.full(delta.shape[1], np.nan)
        am[idx] = fits.a / ramp.p1
        bm[idx] = ramp.p0 + ramp.p1 * fits.b
        per_marker[f"alpha_{name}"] = am
        per_marker[f"beta_{name}"] = bm
        if n_boot:
            bf = _pooled(t, dw, boot_w)
            boots[f"alpha_{name}"] = bf.a / ramp.p1
            boots[f"beta_{name}"] = ramp.p0 + ramp.p1 * bf.b
    sens = 0.5 * (out["fwd"].alpha + out["bwd"].alpha)
    hyst = out["fwd"].beta - out["bwd"].beta
    ci = {}
    if n_boot:
        boots["sensitivity"] = 0.5 * (boots["alpha_fwd"] + boots["alpha_bwd"])
        boots["hysteresis"] = boots["beta_fwd"] - boots["beta_bwd"]
        for k, v in boots.items():
            ci[k] = (float(np.nanpercentile(v, 2.5)), float(np.nanpercentile(v, 97.5)))
    return DUProperties(du, out["fwd"], out["bwd"], float(sens), float(hyst),
                        dyssynchrony_steps(delta, keep, command, noise_var, plateau=plateau),
                        dyssynchrony(delta, keep),
                        int(idx.size), ci, per_marker, (fwd, bwd))
