"""Estimates of what the paper's recipe (``mocap.analysis.paper.indices``) gives on noise-free
positions of the same trials: capture noise removed, the trials' real differences kept.

Capture noise (``capture_noise_covariance``): white from frame to frame, per marker, any shape
(3 x 3 covariance Sigma_m of one trial's position in one frame). It is measured where the face is
still: within runs of constant command at least ``min_run_s`` long (the hold at the top, a
lead-in or tail at rest), after ``settle_s`` of settling, from frame-to-frame differences
(E[dx dx^T] = 2 Sigma for white noise; slow creep adds (v dt)^2, negligible). Trial-to-trial
variation of the face does not enter: each difference is within one trial.

Linearity (``corrected_linearity``): the pooled sample covariance of a marker's positions over
the schedule's frames of all trials is, in expectation, the noise-free pooled covariance plus
Sigma_m (the noise is independent of the position). Sigma_m alone is subtracted, not the
between-trial variance (which is real motion), and the first eigenvalue's share of the trace
taken without flooring any eigenvalue (flooring would turn the noise of the estimate into a
bias).

Dyssynchrony (``corrected_dyssynchrony``): the paper's gamma = mean_t std_m delta_m(t) with
delta_m = |d_m| / max |d_m|. Noise biases it three ways: |d + e| > |d| on average (most near
rest, and the more the smaller a marker's motion), max_t |d + e| picks the noise's largest
excursion, and the markers' independent errors add to the variance over markers. The estimate:

1. d_m(t) from the trial mean less the mean over the frames before the first command change (the
   face at rest; v_m(0) from one frame would carry a whole frame's noise into every frame),
   pooled, marker by marker and only where they agree within their noise, with the other
   takes' rest frames (``pooled_rest``: the session analysis passes the other DUs' response
   takes, the face at rest before each);
2. the noise-free chord |d_m(t)| estimated along the marker's own path: p = d . u (u the principal
   direction, from the noise-corrected second moment) and the perpendicular part w fitted as a
   cubic in p_s, p averaged over ``PATH_SMOOTH_S`` in time (a bowed or S-shaped path; a cubic in
   the raw p is unstable where p's noise is a fair share of the travel or the path curls onto
   its end point); chord g = sign(p) sqrt(p^2 + |w(p_s) - w(0)|^2) with the frame's own p. The
   perpendicular noise leaves (so |noise| adds no bias) and the remaining noise along the path
   has zero mean, also at rest (the sign keeps it so);
3. max |d| as the mean of g over the hold at the top command once settled (``hold_frames``): no
   noise excursion and no selection of frames by their noise (a plateau picked by thresholding
   the noisy curve keeps the frames whose noise is high: 4 % high for a 0.15 mm motion with
   3 trials at 0.05 mm); where the smoothed chord clearly exceeds that level elsewhere (a path
   bulging past its end point), the mean over the frames within 5 % of its smoothed maximum;
4. per frame, the variance over the markers of delta = g / max (each delta averaged over a box
   of ``box_s``, and of ``HOLD_BOX_S`` on the settled hold at the top, where the deltas are
   flat (the box cut at the hold's ends): the hold is most of the schedule and its true
   spread is near 0, so its noise, not its spread, is what reaches gamma there) less the mean
   over the markers of each delta's noise variance (first order: the frame's own error through
   the chord's slope, the rest reference's through the chord's ``rest_gain`` (an error along
   the path at rest moves the chord by the slope at rest near rest, up to 1.4 times the error
   on a bowed path, and by about the error itself at the far end), the maximum's, with their
   overlaps; ``delta_noise_variance``), an unbiased estimate of the noise-free variance;
5. that variance averaged over ``smooth_s`` (a few command steps) and turned into a standard
   deviation by a soft signed square root (``soft_signed_sqrt``): the plain root where the
   variance estimate is more than ``SOFT_ROOT`` = 3 standard deviations of its own noise where
   the markers' true deltas are equal (``variance_noise_sd(..., at_zero_spread=True)``, the
   short box's, on the hold too) from 0, linear in it below. The threshold is a property of
   the noise model, not of the realised deviations (computed from them it would rise with each
   frame's own noise and the roots' mean would lean low). On the hold the long box cuts the
   variance's noise while the threshold, and so the root's slope there, stay the short box's.
   A root of a zero-mean
   estimate is what costs the most: where the true spread is 0 (the hold, the rest) the signed root
   sign(v) sqrt(|v|) is unbiased but turns noise of sd tau into errors of sd ~0.9 sqrt(tau),
   and no smoothing helps (a longer box divides tau and the number of independent values
   alike); linear below 3 tau the errors there are ~tau / sqrt(3 tau), still with mean 0.
   Clipping at 0 instead would leave a positive bias of 0.4 sqrt(tau) per independent value;
6. finer resolutions where the spread stands well above their noise (``FINE_LEVELS_S``: a 0.025 s
   box and variance smoothing, then single frames). The 0.1 s box smooths away the spread between
   curves that step at different sub-step times (staircases: a marker with a dead time and no
   lag jumps at its own frame within each command step), and averaging the variance before its
   root inflates the root where the spread changes within the window: both are costs only where the spread is
   far above the noise, which is where the finer estimates can be afforded. Each finer level's
   root is blended over the coarser ones with a weight rising from 0 to 1 as the coarse variance
   goes from ``FINE_SNR`` = 2 to 5 standard deviations of the finer level's noise (never on
   the hold).
   The mean over the schedule's frames floored at 0.

Its limits (measured accuracy: docs/indices.md, benchmarks/index_monte_carlo.md): the rest reference
(the frames before the first command step, 6 per trial in the paper's schedule, fix d = 0 for
every later frame, so their error is a constant of each marker's curve that no averaging over
time removes: its expected variance is subtracted, its realisation is not; pooling the other
takes' rest frames, as the session analysis does, shrinks it 16-fold); the soft root, which leans
low where the true spread is positive but below ~3 tau (the edges of the ramps, the settling at
the top: -1 to -3 % of gamma on 3-trial takes at 0.05 mm: E sqrt is at most ~0.4 sqrt(tau)
short of sqrt(V) for V in (0, 3 tau), and no odd function of the estimate does much better);
the box, which smooths away part of the spread between curves that step at different sub-step
times where the spread is too close to the noise for the finer levels (step 6; off-chord faces,
whose markers have their own dead times and no lag, read low at 3 trials and 0.05 mm);
and the skew of the variance's noise with few markers (a few small markers dominate it). Where
the true spread is below the noise of the smallest markers' normalised curves the estimate is no
better than 0 to 2 x the truth (docs/indices.md).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import numpy as np

from mocap.analysis.paper.displacement import plateau_mask, smoothed
from mocap.analysis.paper.indices import TIME_TOL_S, ScheduleTiming

NORMALISE_S = 0.25  # smoothing of the chord for finding its plateau (3 s hold in the paper)
MIN_NOISE_DOF = 30  # per marker, below this the still frames do not measure the noise
PATH_DEGREE = 3  # the perpendicular part of a path as a polynomial of this degree in p
PATH_SMOOTH_S = 0.1  # the path fit's regressor: p averaged over this centred box in time
REST_GAIN_NODES = 32  # Gauss-Hermite nodes of the rest error's expected gain over p's noise
SOFT_ROOT = 3.0  # the spread's root is linear below this many sd of its variance's noise
HOLD_BOX_S = 1.0  # the box of the deltas over the settled hold (flat there), cut at its ends
FINE_LEVELS_S = (0.025, 0.0)  # finer boxes (and variance smoothing) where the spread allows; 0: a frame
FINE_SNR = (2.0, 5.0)  # a finer level's weight rises from 0 to 1 over this variance / its noise sd


@dataclass(frozen=True)
class NoiseCovariance:
    """Capture noise of one trial's position per frame: cov (M, 3, 3) mm^2, dof (M,)."""

    cov: np.ndarray
    dof: np.ndarray


def still_frames(command: np.ndarray, fps: float, *, min_run_s: float = 0.5,
                 settle_s: float = 0.25) -> np.ndarray:
    """(n_frames,) bool: frames in runs of constant command at least ``min_run_s`` long, after
    the first ``settle_s`` of the run (a face with lag has settled)."""
    c = np.asarray(command)
    start = np.r_[0, np.flatnonzero(np.diff(c) != 0) + 1]
    length = np.diff(np.r_[start, c.size])
    out = np.zeros(c.size, bool)
    settle = int(np.ceil(settle_s * fps))
    for s, n in zip(start, length):
        if n >= min_run_s * fps:
            out[s + settle: s + n] = True
    return out


def capture_noise_covariance(trials: np.ndarray, command: np.ndarray, fps: float, *,
                             fallback: np.ndarray | None = None, **still) -> NoiseCovariance:
    """Per-marker capture-noise covariance from frame-to-frame differences on still frames.

    trials : (K, n_frames, M, 3) mm; command : (n_frames,). ``fallback`` (M, 3, 3) mm^2 (e.g. the
    rest take's covariance) replaces markers with fewer than ``MIN_NOISE_DOF`` differences.
    """
    X = np.asarray(trials, float)
    s = still_frames(command, fps, **still)
    pair = s[1:] & s[:-1]
    D = np.diff(X, axis=1)[:, pair]  # (K, n_pairs, M, 3)
    ok = np.all(np.isfinite(D), axis=-1)
    Z = np.where(ok[..., None], D, 0.0)
    dof = ok.sum(axis=(0, 1))
    cov = 0.5 * np.einsum("kfmi,kfmj->mij", Z, Z) / np.maximum(dof, 1)[:, None, None]
    few = dof < MIN_NOISE_DOF
    if few.any() and fallback is not None:
        cov[few] = np.asarray(fallback, float)[few]
    return NoiseCovariance(cov, dof)


def corrected_linearity(trials: np.ndarray, timing: ScheduleTiming, fps: float,
                        noise_cov: np.ndarray) -> np.ndarray:
    """(M,) PCA share of the noise-free pooled positions over the schedule's frames (module
    docstring). trials (K, n_frames, M, 3) mm; noise_cov (M, 3, 3) mm^2 per trial and frame.
    NaN where the corrected total variance is not positive; can leave [0, 1] by the noise of the
    estimate where a marker barely moves or its path is straight (the session analysis clips:
    ``mocap.analysis.paper.linearity.share_mean`` for the mean, each share for linearity.csv)."""
    T = np.asarray(trials, float)[:, timing.schedule(np.shape(trials)[1], fps)]
    P = T.reshape(-1, *T.shape[2:])
    ok = np.all(np.isfinite(P), axis=-1)
    n = ok.sum(axis=0)
    Z = np.where(ok[..., None], P, 0.0)
    mean = Z.sum(axis=0) / np.maximum(n, 1)[:, None]
    Dv = np.where(ok[..., None], P - mean[None], 0.0)
    cov = np.einsum("smi,smj->mij", Dv, Dv) / np.maximum(n - 1, 1)[:, None, None] - noise_cov
    lam = np.linalg.eigvalsh(cov)
    total = lam.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where((n >= 3) & (total > 0), lam[:, -1] / total, np.nan)


def hold_frames(n_frames: int, timing: ScheduleTiming, fps: float, settle_s: float = 0.25) -> np.ndarray:
    """(n_frames,) bool: the hold at the top command (t from T_fwd to t_end - T_bwd), after
    ``settle_s`` (or half the hold when it is shorter)."""
    t = timing.frame_times(n_frames, fps)
    start, stop = timing.fwd_s, timing.t_end_s - timing.t0_s - timing.bwd_s
    settle = min(settle_s, 0.5 * max(stop - start, 0.0))
    return (t >= start + settle - TIME_TOL_S) & (t <= stop + TIME_TOL_S)


def rest_sums(trials: np.ndarray, timing: ScheduleTiming, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """(sum (M, 3) mm, count (M,)) of a take's single-trial positions over its rest frames (before
    the first rising step), for pooling the face's rest over takes (:func:`pooled_rest`)."""
    T = np.asarray(trials, float)
    rest = timing.frame_times(T.shape[1], fps) < timing.step_s - TIME_TOL_S
    R = T[:, rest]
    ok = np.all(np.isfinite(R), axis=-1)
    return np.where(ok[..., None], R, 0.0).sum(axis=(0, 1)), ok.sum(axis=(0, 1)).astype(float)


def pooled_rest(r_own: np.ndarray, n_own: np.ndarray, r_prior: np.ndarray, n_prior: np.ndarray,
                noise_cov: np.ndarray, chi2: float = 16.27) -> tuple[np.ndarray, np.ndarray]:
    """(rest (M, 3), samples (M,)): this take's rest pooled with a prior where they agree.

    The difference's covariance is Sigma (1 / n_own + 1 / n_prior); a marker whose squared
    Mahalanobis distance exceeds ``chi2`` (3 dof, 0.1 %) keeps its own rest."""
    diff = r_prior - r_own
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = 1.0 / np.maximum(n_own, 1) + np.where(n_prior > 0, 1.0 / n_prior, np.inf)
        C = noise_cov * scale[:, None, None] + 1e-12 * np.eye(3)  # (not used where not ok)
    ok = np.isfinite(diff).all(axis=1) & (n_prior > 0) & (n_own > 0) & np.isfinite(scale)
    m2 = np.full(diff.shape[0], np.inf)
    if ok.any():
        m2[ok] = np.einsum("mi,mi->m", diff[ok], np.linalg.solve(C[ok], diff[ok][..., None])[..., 0])
    use = ok & (m2 < chi2)
    w = np.where(use, n_prior, 0.0)
    rest = np.where(use[:, None], (n_own[:, None] * r_own + w[:, None] * np.nan_to_num(r_prior))
                    / (n_own + w)[:, None], r_own)
    return rest, n_own + w


@dataclass(frozen=True)
class PathChord:
    """Noise-free chord estimate of each marker's trial-mean displacement.

    chord (n_frames, M) mm signed; delta (n_frames, M) chord / peak; peak (M,) mm; slope
    (n_frames, M) d chord / d p (how noise along the path reaches the chord); rest_gain
    (n_frames, M) how an error of the rest reference along the path reaches the chord (the
    chord's direction dotted with the path's tangent at rest: the slope at rest near rest, about
    1 at the far end of a path that bows); along_var (M,)
    mm^2 the noise variance along the path of one trial's frame; rest (n_frames,) bool the rest
    frames; plateau (n_frames, M) bool; rest_samples (M,) how many single-trial frames the rest
    reference averages (this take's rest frames, plus the other takes' when pooled).
    """

    chord: np.ndarray
    delta: np.ndarray
    peak: np.ndarray
    slope: np.ndarray
    rest_gain: np.ndarray
    along_var: np.ndarray
    rest: np.ndarray
    plateau: np.ndarray
    rest_samples: np.ndarray  # (M,) single-trial frames the rest reference averages


def path_chord(mean: np.ndarray, n_trials: np.ndarray, timing: ScheduleTiming, fps: float,
               noise_cov: np.ndarray, rest_prior: tuple[np.ndarray, np.ndarray] | None = None
               ) -> PathChord:
    """Steps 1-3 of the module docstring on trial-mean positions ``mean`` (n_frames, M, 3) mm seen
    by ``n_trials`` (n_frames, M) trials.

    ``rest_prior``: (position (M, 3) mm, samples (M,)), the face's rest measured elsewhere (the
    mean over other takes' rest frames and how many single-trial frames it averages). Where it
    agrees with this take's rest frames within their noise (chi-square, 3 dof, 0.1 %), the two
    are pooled: the rest reference's error is the limit of the dyssynchrony's correction.
    """
    v = np.asarray(mean, float)
    n, M = v.shape[:2]
    t = timing.frame_times(n, fps)
    rest = t < timing.step_s - TIME_TOL_S  # before the first rising step: at rest
    sched = np.zeros(n, bool)
    sched[timing.schedule(n, fps)] = True
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        r = np.nanmean(v[rest], axis=0)
    own = np.sum(np.where(np.isfinite(v[rest][..., 0]), n_trials[rest], 0), axis=0).astype(float)
    samples = own
    if rest_prior is not None:
        r, samples = pooled_rest(r, own, rest_prior[0], np.asarray(rest_prior[1], float), noise_cov)
    d = v - r[None]
    ok = np.all(np.isfinite(d), axis=-1) & sched[:, None]
    Z = np.where(ok[..., None], d, 0.0)
    with warnings.catch_warnings():  # a marker with no usable frame: NaN, and marked unseen
        warnings.simplefilter("ignore", RuntimeWarning)
        k_mean = np.maximum(np.nanmean(np.where(ok, n_trials, np.nan), axis=0), 1)
    second = (np.einsum("fmi,fmj->mij", Z, Z) / np.maximum(ok.sum(axis=0), 1)[:, None, None]
              - noise_cov / k_mean[:, None, None])
    unseen = ~np.isfinite(second).all(axis=(1, 2))  # a marker no sample of which is usable
    _, vec = np.linalg.eigh(np.where(unseen[:, None, None], np.eye(3), second))
    u = np.where(unseen[:, None], np.nan, vec[..., -1])
    p = np.einsum("fmk,mk->fm", d, u)
    # signed so that the hold (not the noise's largest excursion) lies ahead
    hold = hold_frames(n, timing, fps)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        ahead = np.nanmean(np.where(hold[:, None] & ok, p, np.nan), axis=0)
    u = u * np.where(ahead < 0, -1.0, 1.0)[:, None]
    p = np.einsum("fmk,mk->fm", d, u)
    w = d - p[..., None] * u[None]
    # w(p) = a0 + a1 p + a2 p^2 per marker and axis, least squares over the schedule's frames
    with warnings.catch_warnings():  # an unseen marker's scale is NaN (its chord stays NaN)
        warnings.simplefilter("ignore", RuntimeWarning)
        scale = np.nanmax(np.where(ok, np.abs(p), np.nan), axis=0)
    sc = np.where(scale > 0, scale, 1.0)
    # the regressor: p averaged over a short centred box in time (the path's parameter tied to
    # time), its noise down by the box's length; w is fitted and evaluated on it
    q = p / sc[None]  # conditioning: q in about [-1, 1]
    q_s, _ = box_mean(np.where(ok, q, np.nan), path_smooth_frames(fps))
    q = np.where(ok & np.isfinite(q_s), q_s, q)
    A = np.stack([q**k for k in range(PATH_DEGREE + 1)], axis=-1)  # (n, M, degree + 1)
    A = np.where(ok[..., None], A, 0.0)
    W = np.where(ok[..., None], w, 0.0)
    AtA = np.einsum("fmi,fmj->mij", A, A) + 1e-12 * np.eye(PATH_DEGREE + 1)
    AtW = np.einsum("fmi,fmk->mik", A, W)
    coef = np.linalg.solve(AtA, AtW)  # (M, powers, 3 axes)
    wp = sum(q[..., None] ** k * coef[None, :, k] for k in range(1, PATH_DEGREE + 1))  # w - w(0)
    dwp = sum(k * q[..., None] ** (k - 1) * coef[None, :, k] for k in range(1, PATH_DEGREE + 1))
    dwp = dwp / sc[None, :, None]
    W2 = np.sum(wp * wp, axis=-1)  # |w(q_s) - w(0)|^2, the path's perpendicular part squared
    # the chord at the frame's own p (its noise along the path white and zero-mean)
    # with the path's perpendicular part at the smoothed one
    g2 = p * p + W2
    chord = np.sign(p) * np.sqrt(g2)
    dw0 = coef[:, 1] / sc[:, None]  # (M, 3) the path's w'(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        slope = np.where(g2 > 0, np.sign(p) * (p + np.sum(wp * dwp, axis=-1)) / np.sqrt(g2), 1.0)
    along_var = np.einsum("mi,mij,mj->m", u, noise_cov, u)
    sigma = np.sqrt(along_var[None] / np.maximum(np.asarray(n_trials, float), 1.0))
    rest_gain = _rest_gain(q * sc[None], sigma, W2, np.sum(wp * dw0[None], axis=-1),
                           np.sqrt(1.0 + np.sum(dw0 * dw0, axis=-1)))
    # the maximum: the mean over the settled hold at the top command (no noise excursion, no
    # selection by the noise); where the smoothed chord clearly rises above it elsewhere (a path
    # bulging beyond its end point), the mean over the frames near that maximum instead
    plateau = np.broadcast_to(hold[:, None], (n, M)) & np.isfinite(chord)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        level = np.nanmean(np.where(plateau, chord, np.nan), axis=0)
    frames = max(1, int(round(NORMALISE_S * fps)))
    cs = np.where(sched[:, None], chord, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        k_min = np.maximum(np.nanmin(np.where(ok, n_trials, np.nan), axis=0), 1)
    # the smoothed maximum of pure noise over a few hundred frames reaches ~3.5 of its sd
    se = np.sqrt(np.einsum("mi,mij,mj->m", u, noise_cov, u) / k_min / frames)
    bulge, top = plateau_mask(cs, frames)
    beyond = ~np.isfinite(level) | (top > 1.01 * level + 6.0 * se)
    plateau = np.where(beyond[None], bulge, plateau)
    level = np.where(beyond, np.where(bulge, cs, 0.0).sum(axis=0) / np.maximum(bulge.sum(axis=0), 1),
                     level)
    peak = np.where(plateau.any(axis=0), level, top)
    with np.errstate(invalid="ignore", divide="ignore"):
        delta = chord / np.where(peak > 0, peak, np.nan)[None]
    return PathChord(chord, delta, peak, slope, rest_gain, along_var, rest, plateau, samples)


def path_smooth_frames(fps: float) -> int:
    """The odd number of frames of the path fit's regressor box (``PATH_SMOOTH_S``)."""
    return 2 * int(round(0.5 * PATH_SMOOTH_S * fps)) + 1


def _rest_gain(p_s: np.ndarray, sigma: np.ndarray, W2: np.ndarray, Wd: np.ndarray,
               at_rest: np.ndarray) -> np.ndarray:
    """(n_frames, M) how an error e of the rest reference along the path moves each frame's chord
    (the chord changes by -gain e), in expectation over the frame's own noise along the path.

    The chord is G(x) = sign(x) sqrt(x^2 + W^2) of the frame's own p = x (noise sd ``sigma``,
    around the smoothed p ``p_s``) with the path's perpendicular part W (``W2`` = W^2) from the
    smoothed p; a rest reference off by e measures from the path's point at p = e, so
    dG/de = -sign(x) (x + Wd) / G with Wd = (w(p_s) - w(0)) . w'(0). The expectation over x
    (Gauss-Hermite) and the sign's jump of 2 W at x = 0 (its expected slope 2 W pdf_x(0)):
    far from rest the path's gain, chord direction . (u + w'(0)); at rest, where x is mostly
    noise and W small, about 1. Without noise (sigma 0): the path's gain at p_s; where the chord
    has no length: ``at_rest`` (M,) = |u + w'(0)|."""
    with np.errstate(invalid="ignore", divide="ignore"):
        g = np.sqrt(p_s * p_s + W2)
        gain = np.where(g > 0, np.sign(p_s) * (p_s + Wd) / g, at_rest[None])  # without noise
    # within a few sd of rest the noise counts; beyond 10 sd its effect on the expectation is
    # under (sd / chord)^2 < 1 %, and the jump's weight exp(-50): the path's gain at p_s
    near = (sigma > 0) & (np.abs(p_s) < 10.0 * sigma) & np.isfinite(p_s)
    if near.any():
        z, wz = np.polynomial.hermite_e.hermegauss(REST_GAIN_NODES)
        wz = wz / wz.sum()
        ps, sg, w2, wd = p_s[near], sigma[near], W2[near], Wd[near]
        ar = np.broadcast_to(at_rest[None], p_s.shape)[near]
        acc = np.zeros(ps.shape)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            for zk, wk in zip(z, wz):
                x = ps + zk * sg
                gx = np.sqrt(x * x + w2)
                acc += wk * np.where(gx > 0, np.sign(x) * (x + wd) / gx, ar)
            acc += 2.0 * np.sqrt(w2) * np.exp(-0.5 * (ps / sg) ** 2) / (sg * np.sqrt(2.0 * np.pi))
        gain[near] = acc
    return np.where(np.isfinite(gain), gain, at_rest[None])


def box_mean(x: np.ndarray, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean, count): NaN-aware centred box mean of x (n_frames, ...) over ``frames`` frames (the
    window shortened at the ends and over NaN), and the number of values it averaged."""
    from scipy.ndimage import convolve1d

    ok = np.isfinite(x)
    k = np.ones(int(frames))
    num = convolve1d(np.where(ok, x, 0.0), k, axis=0, mode="constant")
    cnt = convolve1d(ok.astype(float), k, axis=0, mode="constant")
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, num / cnt, np.nan), cnt


def delta_noise_variance(pc: PathChord, n_trials: np.ndarray, frames: int = 1) -> np.ndarray:
    """(n_frames, M) first-order noise variance of each path-chord delta averaged over a centred
    box of ``frames`` frames (module docstring, 4).

    delta_hat = delta + (J e_t - (c - delta c_H) e_A - delta e_H) / peak with e_t the frame's
    error along the path (variance along_var / n_trials; J the chord's slope), e_A the rest
    reference's along the path (c the chord's ``rest_gain``, c_H its mean over H; the mean of
    ``rest_samples`` single-trial frames: the rest frames A, and the other takes' when pooled;
    variance along_var / rest_samples) and e_H the maximum's (the mean over the frames H,
    ``plateau``). Over a box F of |F| frames the first term's variance is
    sum_F J^2 s^2 / |F|^2, and a box overlapping A (or H) shares its frames' errors with e_A
    (or e_H): the cross terms below.
    """
    from scipy.ndimage import convolve1d

    K = np.maximum(np.asarray(n_trials, float), 1)
    s2 = pc.along_var[None] / K  # (n, M) per-frame trial-mean variance along the path
    J = pc.slope
    A = np.broadcast_to(pc.rest[:, None], s2.shape)
    H = pc.plateau
    nR = np.maximum(pc.rest_samples, 1.0)[None]  # single-trial frames in the rest reference
    nH = np.maximum(H.sum(axis=0), 1).astype(float)[None]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        vA = pc.along_var[None] / nR  # var of e_A
        vH = (np.nanmean(np.where(H, s2, np.nan), axis=0) / nH[0])[None]
    vH = np.where(np.isfinite(vH), vH, 0.0)
    d, cnt = box_mean(np.clip(pc.delta, 0.0, 1.0), frames)
    valid = np.isfinite(pc.delta)
    k = np.ones(int(frames))

    def box_sum(x):
        return convolve1d(np.where(valid, x, 0.0), k, axis=0, mode="constant")

    cnt = np.maximum(cnt, 1)
    own = box_sum(J * J * s2) / cnt**2
    # the rest error e_A reaches the chord as -c e_A (c = rest_gain) and the maximum as -c_H e_A
    # (c_H its mean over H): delta's error carries -(c - delta c_H) e_A
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        cH = np.nanmean(np.where(H, pc.rest_gain, np.nan), axis=0)[None]
    cA = box_sum(pc.rest_gain) / cnt - d * np.where(np.isfinite(cH), cH, 1.0)
    # a trial-mean rest frame seen by K trials weighs K / nR in the reference: cov = var / nR
    withA = box_sum(np.where(A, J * pc.along_var[None], 0.0)) / (cnt * nR)
    withH = box_sum(np.where(H, J * s2, 0.0)) / (cnt * nH)
    var = own + cA**2 * vA + d**2 * vH - 2 * cA * withA - 2 * d * withH
    with np.errstate(invalid="ignore", divide="ignore"):
        return var / pc.peak[None] ** 2


def signed_sqrt(v: np.ndarray) -> np.ndarray:
    """sign(v) sqrt(|v|): unbiased for a standard deviation of 0 from a zero-mean variance estimate."""
    return np.sign(v) * np.sqrt(np.abs(v))


def soft_signed_sqrt(v: np.ndarray, threshold: np.ndarray) -> np.ndarray:
    """sqrt(v) where |v| >= threshold, v / sqrt(threshold) below it (continuous, odd).

    For a variance estimate v = V + N with zero-mean noise N, the signed root is unbiased at V = 0
    but turns N of sd tau into errors of sd ~0.9 sqrt(tau), and these do not average out with
    smoothing (a box of W frames divides tau by W and the number of independent values by W as
    well). Linear below ``threshold`` (a few tau), the root keeps E = 0 at V = 0 with errors of sd
    tau / sqrt(threshold), and is the plain root where V is well above its noise; it leans low
    only where 0 < V < threshold."""
    v = np.asarray(v, float)
    thr = np.asarray(threshold, float)
    with np.errstate(invalid="ignore", divide="ignore"):
        lin = np.where(thr > 0, v / np.sqrt(thr), 0.0)
    return np.where(np.abs(v) >= thr, signed_sqrt(v), lin)


def variance_noise_sd(d: np.ndarray, nv: np.ndarray, box: int, smooth: int, *,
                      at_zero_spread: bool = False) -> np.ndarray:
    """(n_frames,) sd of the noise of the per-frame variance over markers of box-averaged deltas
    ``d`` (n_frames, M) less their noise ``nv`` (n_frames, M), once averaged over ``smooth``
    frames: for independent errors e_m of variance nv_m, var(sum_m (d_m - mean)^2 / (M - 1)) =
    (2 sum nv^2 + 4 sum (d_m - mean)^2 nv) / (M - 1)^2, and a box of ``box`` frames makes
    successive errors correlated (rho(k) = 1 - |k| / box), which the average over ``smooth``
    frames keeps (sum over its pairs of rho^2 and rho). (d_m - mean)^2 is taken less nv_m, its
    own noise's share.

    ``at_zero_spread``: the first term only, the sd where the markers' true deltas are equal (the
    null the soft root's threshold asks about). It depends on the noise model alone, not on the
    realised deviations, which carry the very noise the threshold judges: with them in, a frame
    whose noise came out high gets a higher threshold (a flatter root) and one whose noise came
    out low a steeper one, and the mean of the roots leans low."""
    lags = np.arange(-(smooth - 1), smooth)
    pairs = smooth - np.abs(lags)
    rho = np.maximum(0.0, 1.0 - np.abs(lags) / max(box, 1))
    f2, f1 = np.sum(pairs * rho**2) / smooth**2, np.sum(pairs * rho) / smooth**2
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        m = np.sum(np.isfinite(d) & np.isfinite(nv), axis=1).astype(float)
        v = 2 * f2 * np.nansum(nv**2, axis=1)
        if not at_zero_spread:
            # the true deviations' squares: the noisy ones less their noise (else counted twice)
            dev2 = (d - np.nanmean(d, axis=1, keepdims=True)) ** 2 - nv
            v = v + np.maximum(4 * f1 * np.nansum(dev2 * nv, axis=1), 0.0)
        v = v / (m - 1) ** 2
    return smoothed(np.sqrt(np.where(m > 1, v, np.nan)), smooth)


def corrected_dyssynchrony(mean: np.ndarray, n_trials: np.ndarray, keep: np.ndarray,
                           timing: ScheduleTiming, fps: float, noise_cov: np.ndarray, *,
                           box_s: float = 0.1, smooth_s: float = 0.1, hold_box_s: float = HOLD_BOX_S,
                           rest_prior: tuple[np.ndarray, np.ndarray] | None = None
                           ) -> tuple[float, PathChord]:
    """The paper's dyssynchrony on noise-free positions, estimated (module docstring).

    mean (n_frames, M, 3) mm trial means; n_trials (n_frames, M); keep (M,) bool; noise_cov
    (M, 3, 3) mm^2 per trial and frame; rest_prior: see :func:`path_chord`. Each delta is
    averaged over a centred box of ``box_s`` (its white noise down by the box's length; a box far
    shorter than a ramp barely changes the spread between markers), and over ``hold_box_s`` on the
    settled hold at the top command (the deltas are flat there; the box cut at the hold's ends), the
    variance over markers less its noise averaged over ``smooth_s``; where that variance is well
    above the noise of finer boxes (``FINE_LEVELS_S``), their roots take over (step 6). Returns
    (gamma, the path chords).
    """
    pc = path_chord(mean, n_trials, timing, fps, noise_cov, rest_prior)
    n = np.shape(mean)[0]
    keep = np.asarray(keep, bool) & np.any(np.isfinite(pc.delta), axis=0)
    sched = timing.schedule(n, fps)
    if keep.sum() < 2:
        return float("nan"), pc
    inside = np.zeros(n, bool)
    inside[sched] = True
    frames = max(1, int(round(box_s * fps)))
    smooth = max(1, int(round(smooth_s * fps)))
    pc_in = replace(pc, delta=np.where(inside[:, None], pc.delta, np.nan))
    d, _ = box_mean(pc_in.delta, frames)
    nv = delta_noise_variance(pc_in, n_trials, frames)
    # the soft root's threshold: the short box's noise at zero spread, also on the hold (a
    # threshold from the long box there would steepen the root as much as the box cuts the noise)
    tau = variance_noise_sd(d[sched][:, keep], nv[sched][:, keep], frames, smooth,
                            at_zero_spread=True)
    # the settled hold's deltas are flat: every frame of it takes the long box, the box cut
    # at the hold's ends (there it averages the hold's frames on one side only, still far more
    # than the short box; a box that had to fit whole would leave the hold's ends, where most
    # of the hold's noise reaches gamma, to the short box)
    long = max(frames, int(round(hold_box_s * fps)))
    hold = hold_frames(n, timing, fps) & inside
    if long > frames and hold.any():
        pc_h = replace(pc, delta=np.where(hold[:, None], pc.delta, np.nan))
        d = np.where(hold[:, None], box_mean(pc_h.delta, long)[0], d)
        nv = np.where(hold[:, None], delta_noise_variance(pc_h, n_trials, long), nv)
    var = _spread_variance(d[sched][:, keep], nv[sched][:, keep], smooth)
    # the mean of the (soft) signed roots is unbiased where the spread is 0 or well above its
    # noise; it is negative only where the spread is lost in the noise, and a standard deviation
    # is reported as such: floored at 0
    root = soft_signed_sqrt(var, SOFT_ROOT * np.where(np.isfinite(tau), tau, 0.0))
    # finer resolutions where the spread stands well above their noise (coarse to fine: each
    # blended over the coarser ones by the box's variance against its own noise)
    for level_s in FINE_LEVELS_S:
        f = max(1, int(round(level_s * fps)))
        d_f, _ = box_mean(pc_in.delta, f)
        nv_f = delta_noise_variance(pc_in, n_trials, f)
        d_f, nv_f = d_f[sched][:, keep], nv_f[sched][:, keep]
        tau_f = variance_noise_sd(d_f, nv_f, f, f, at_zero_spread=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            w = np.clip((var / tau_f - FINE_SNR[0]) / (FINE_SNR[1] - FINE_SNR[0]), 0.0, 1.0)
        w = np.where(np.isfinite(w) & ~hold[sched], w, 0.0)
        if w.any():
            fine = soft_signed_sqrt(_spread_variance(d_f, nv_f, f),
                                    SOFT_ROOT * np.where(np.isfinite(tau_f), tau_f, 0.0))
            root = np.where(w > 0, w * fine + (1.0 - w) * root, root)
    return max(float(np.nanmean(root)), 0.0), pc


def _spread_variance(d: np.ndarray, nv: np.ndarray, smooth: int) -> np.ndarray:
    """(n_frames,) the variance over markers of the deltas d (n_frames, M) less the mean of their
    noise variances nv (n_frames, M), averaged over ``smooth`` frames."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        var = np.nanvar(d, axis=1, ddof=1) - np.nanmean(nv, axis=1)
    return smoothed(var, smooth)


def corrected_fits(pc: PathChord, keep: np.ndarray, timing: ScheduleTiming,
                   fps: float) -> dict:
    """The paper's two sigmoid fits (its windows, abscissa and pooling) on the path-chord delta
    instead of |d| / max |d|: an estimate of the fits on noise-free positions (the chord's noise
    has zero mean at rest and on small motions, and its maximum no noise excursion, so the
    pooled least squares is not pulled flat). Returns alpha_fwd, beta_fwd, alpha_bwd, beta_bwd,
    sensitivity, hysteresis (1/command unit, command units)."""
    from mocap.analysis.paper.indices import fit_sigmoid

    n = pc.delta.shape[0]
    idx = np.flatnonzero(np.asarray(keep, bool) & np.any(np.isfinite(pc.delta), axis=0))
    out = {}
    for name, (frames, c) in (("fwd", timing.forward(n, fps)), ("bwd", timing.backward(n, fps))):
        y = pc.delta[frames][:, idx]
        x = np.broadcast_to(c[:, None], y.shape)
        ok = np.isfinite(y)
        out[f"alpha_{name}"], out[f"beta_{name}"] = fit_sigmoid(x[ok], y[ok])
    out["sensitivity"] = 0.5 * (out["alpha_fwd"] + out["alpha_bwd"])
    out["hysteresis"] = out["beta_fwd"] - out["beta_bwd"]
    return out
