"""Small synthetic faces for the paper's indices, written with numpy and scipy only (no mocap code): noise-free
trials of a static-response take, so that a test's truth is made another way than the package's.

A face: M markers, each with its own path (straight, bowed, or off the chord), amplitude D_m mm,
response timing (a per-marker bias of its sigmoid, a first-order lag or a dead time) and a
hysteresis (a play operator of half-width r in front of the sigmoid, or a creep on the hold);
each trial shifts the sigmoid's bias and scales the amplitude (trial-to-trial variation: real
motion). Capture noise is added separately (``add_noise``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

FPS = 120.0
STEP_S = 0.05


@dataclass(frozen=True)
class Take:
    """Noise-free trials (K, n_frames, M, 3) mm, the command rows (time_s, command) and the
    per-frame command (n_frames,)."""

    trials: np.ndarray
    time_s: np.ndarray
    command: np.ndarray
    series: np.ndarray


def paper_rows(lead_s: float = 0.0, n_ramp: int = 20, n_hold: int = 60):
    """The paper's trapezoid: step s at lead_s + s * 50 ms, c = round(255 s / 20) up, hold, down."""
    s = np.arange(2 * n_ramp + n_hold + 1)
    c = np.where(s <= n_ramp, 255.0 * s / n_ramp,
                 np.where(s <= n_ramp + n_hold, 255.0, 255.0 * (2 * n_ramp + n_hold - s) / n_ramp))
    return lead_s + STEP_S * s, np.floor(c + 0.5)


def series(time_s, command, n_frames):
    """Command at each frame: the last row with time_s <= t (+1e-9); 0 before the first row."""
    t = np.arange(n_frames) / FPS
    i = np.searchsorted(time_s, t + 1e-9, side="right") - 1
    return np.where(i >= 0, command[np.maximum(i, 0)], 0.0)


def play(c, r):
    """Play (backlash) operator of half-width r on a command series, starting at 0."""
    out = np.empty_like(c)
    w = 0.0
    for i, x in enumerate(c):
        w = min(max(w, x - r), x + r)
        out[i] = w
    return out


def make_take(rng, *, family: str = "bow", n_markers: int = 30, n_trials: int = 3,
              d_range=(0.15, 3.0), lead_s: float = 0.0, tail_s: float = 0.05) -> Take:
    """Noise-free trials of one DU's trapezoid take on a random face of ``family``:

    - "bow": bowed paths (sagitta up to 0.25 D), play hysteresis r ~ 25-45, per-marker bias
      scatter (sd 15) and first-order lag (0-100 ms), per-trial bias shift (sd 5) and amplitude
      (sd 3 %);
    - "offchord": paths off the chord on both sides (an S in 3D), per-marker dead time (0-120 ms)
      and bias scatter (sd 12), play hysteresis plus a creep of the hold (2 % of D, 0.4 s), per-trial
      bias shift (sd 8) and amplitude (sd 5 %).
    """
    time_s, cmd = paper_rows(lead_s)
    n = int(round((time_s[-1] + tail_s) * FPS))
    c = series(time_s, cmd, n)
    fine = 4
    cf = np.repeat(c, fine)
    M, K = n_markers, n_trials
    D = np.exp(rng.uniform(np.log(d_range[0]), np.log(d_range[1]), M))
    e1 = rng.normal(size=(M, 3))
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(e1, rng.normal(size=(M, 3)))
    e2 /= np.linalg.norm(e2, axis=1, keepdims=True)
    e3 = np.cross(e1, e2)
    rest = rng.uniform(-40, 40, (M, 3))
    alpha = rng.uniform(0.035, 0.07)
    beta = rng.uniform(110, 150)
    if family == "bow":
        r = rng.uniform(25, 45)
        beta_m = beta + rng.normal(0, 15, M)
        lag_s = rng.uniform(0, 0.1, M)
        delay = np.zeros(M, int)
        bow = rng.uniform(0, 0.25, M)
        trial_beta, trial_amp, creep = 5.0, 0.03, 0.0
    elif family == "offchord":
        r = rng.uniform(15, 35)
        beta_m = beta + rng.normal(0, 12, M)
        lag_s = np.zeros(M)
        delay = rng.integers(0, int(0.12 * FPS * fine) + 1, M)
        bow = rng.uniform(0.05, 0.2, M)
        trial_beta, trial_amp, creep = 8.0, 0.05, 0.02
    else:
        raise ValueError(f"family: expected 'bow' or 'offchord', got {family!r}")
    w = play(cf, r)
    t_fine = np.arange(cf.size) / (FPS * fine)
    hold = cf == cf.max()
    since = np.where(hold, t_fine - t_fine[np.argmax(hold)], 0.0)
    out = np.empty((K, n, M, 3))
    for k in range(K):
        b = beta_m + rng.normal(0, trial_beta)
        amp = D * (1 + rng.normal(0, trial_amp))
        lo = 1 / (1 + np.exp(alpha * b))
        hi = 1 / (1 + np.exp(-alpha * (255 - b)))
        y = (1 / (1 + np.exp(-alpha * (w[:, None] - b[None]))) - lo) / (hi - lo)  # (n fine, M)
        y = y + creep * (1 - np.exp(-since / 0.4))[:, None] * hold[:, None]
        if lag_s.any():  # first-order lag, exact for a held input over each fine sample
            a = np.exp(-1 / (FPS * fine * np.maximum(lag_s, 1e-9)))
            y = np.stack([lfilter([1 - a[m]], [1, -a[m]], y[:, m]) for m in range(M)], axis=1)
        if delay.any():
            idx = np.clip(np.arange(y.shape[0])[:, None] - delay[None], 0, None)
            y = np.take_along_axis(y, idx, axis=0)
        y = y[::fine]  # (n, M)
        if family == "bow":
            along = y
            side = 4 * bow[None] * y * (1 - y)
            off = np.zeros_like(y)
        else:
            along = y
            side = bow[None] * np.sin(np.pi * np.clip(y, 0, 1))
            off = 0.5 * bow[None] * np.sin(2 * np.pi * np.clip(y, 0, 1))
        path = along[..., None] * e1 + side[..., None] * e2 + off[..., None] * e3
        out[k] = rest[None] + amp[None, :, None] * path
    return Take(out, time_s, cmd, c)


def add_noise(rng, trials, sigma_mm: float):
    """Anisotropic white capture noise, per-axis sd about ``sigma_mm`` (a random covariance per
    marker: triangulation is worse along some directions), independent across frames and trials."""
    M = trials.shape[2]
    A = rng.normal(0, 1, (M, 3, 3)) * np.array([1.0, 0.8, 1.3])[None, :, None]
    A = A / np.sqrt(np.einsum("mij,mij->m", A, A) / 3)[:, None, None] * sigma_mm
    e = rng.normal(0, 1, trials.shape)
    return trials + np.einsum("mij,ktmj->ktmi", A, e), np.einsum("mik,mjk->mij", A, A)


def rest_seen_elsewhere(rng, trials, cov, n_prior: int):
    """(position (M, 3) mm, samples (M,)): the face's rest as ``n_prior`` single-trial frames of
    other takes saw it (``rest_prior`` of the corrected dyssynchrony): the noise-free rest of
    ``trials`` (K, n_frames, M, 3), averaged over trials, plus the mean of that many frames' noise
    of covariance ``cov`` (M, 3, 3), the same anisotropic shape as the take's."""
    M = trials.shape[2]
    noise = np.einsum("mij,mj->mi", np.linalg.cholesky(cov), rng.normal(size=(M, 3)))
    return trials[:, 0].mean(axis=0) + noise / np.sqrt(n_prior), np.full(M, float(n_prior))
