"""The virtual face's hysteresis operators, written for the simulator alone.

Conventions: time is axis 0 (``n_samples`` on the fine grid), commands and thresholds in command
units (0..255), outputs either command units (``play``, ``pi_mean``, ``bouc_wen_state``) or the
normalised response (0 at rest, 1 at full command after a rise). Every operator starts from a face
at rest (all inputs 0 before the first sample) and is rate-independent: the output depends on the
sequence of input values, not on when they come.

Operators (x the input, k the sample)::

    play_r(x)_k     = clip(p_{k-1}, x_k - r, x_k + r),  p_{-1} = 0
    pi_mean(x)      = mean_i play_{r_i}(x)                         (Prandtl-Ishlinskii, equal weights)
    branch_play     y_k = clip(y_{k-1}, min(F(x_k), B(x_k)), max(F(x_k), B(x_k))),  y_{-1} = 0
                    F, B: the marker's forward and backward branch curves (flat after a reversal
                    until the state meets the other branch)
    preisach        y = sum_j w_j Phi((play_{h_j}(x) - mu_j) / s), normalised to 0 at rest and 1
                    at full command: a Preisach model whose relay density is, in (centre, half-width)
                    coordinates, w_j at half-widths h_j and Gaussian N(mu_j, s^2) in the centre;
                    relay (centre c, half-width h) is on iff play_h(x) >= c, so each half-width
                    line integrates in closed form (at rest, play state 0, the relays with
                    centres <= 0 are on: the normalisation removes them)
    bouc_wen_state  dz = A dx - b |dx| z - g dx |z|   (Bouc-Wen with n = 1), integrated exactly
                    over each sample's increment; |z| <= A / (b + g)

The Bouc-Wen update is exact because the rate-independent form is an ODE in the input: with
u = |dx| and zeta = sign(dx) z, d zeta / du = A - (b + g) zeta for zeta >= 0 and
A - (b - g) zeta for zeta < 0, both linear.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy.special import ndtr

BOUC_WEN_A = 0.5  # the Bouc-Wen state's elastic slope (what makes x - z monotone for b <= 3 g)


def play(x: np.ndarray, r, y0=0.0) -> np.ndarray:
    """Play (backlash) operator of half-width ``r`` along axis 0.

    x : (n_samples, ...) input; r : half-widths >= 0 and y0 : initial states, both broadcast with
    ``x.shape[1:]``. Returns (n_samples, *shape) float, shape the broadcast of the three. x is
    never materialised at the broadcast shape (compiled loop over samples).
    """
    x = np.asarray(x, float)
    r = np.asarray(r, float)
    if np.any(r < 0):
        raise ValueError(f"play: expected half-widths r >= 0, got min {r.min()}")
    shape = np.broadcast_shapes(x.shape[1:], r.shape, np.shape(y0))
    col = np.broadcast_to(np.arange(int(np.prod(x.shape[1:], dtype=int))).reshape(x.shape[1:]), shape)
    out = _play_kernel(np.ascontiguousarray(x.reshape(x.shape[0], -1)),
                       np.ascontiguousarray(np.broadcast_to(r, shape)).ravel(),
                       np.ascontiguousarray(np.broadcast_to(np.asarray(y0, float), shape)).ravel(),
                       np.ascontiguousarray(col).ravel())
    return out.reshape((x.shape[0],) + shape)


@njit(cache=True)
def _play_kernel(x, r, y0, col):
    n = x.shape[0]
    m = r.shape[0]
    out = np.empty((n, m))
    for j in range(m):
        p = y0[j]
        c = col[j]
        for k in range(n):
            lo = x[k, c] - r[j]
            hi = x[k, c] + r[j]
            p = min(max(p, lo), hi)
            out[k, j] = p
    return out


def pi_mean(x: np.ndarray, half_widths: np.ndarray) -> np.ndarray:
    """Equal-weight Prandtl-Ishlinskii output (n_samples, ...) of x (n_samples, ...).

    half_widths : (..., n_plays) play half-widths broadcast against ``x.shape[1:]``.
    """
    return play(_lift(x, half_widths), half_widths, 0.0).mean(axis=-1)


def _lift(x, nodes):
    """x (n_samples, *a) reshaped to (n_samples, *a, 1, ...) to broadcast with nodes (*a, *b)."""
    x = np.asarray(x, float)
    return x.reshape(x.shape + (1,) * (np.ndim(nodes) - x.ndim + 1))


def logistic01(x, alpha, beta):
    """Normalised logistic (S(x) - S(0)) / (S(255) - S(0)), S = 1 / (1 + exp(-alpha (x - beta)))."""
    lo = 1.0 / (1.0 + np.exp(alpha * beta))
    hi = 1.0 / (1.0 + np.exp(-alpha * (255.0 - beta)))
    s = 1.0 / (1.0 + np.exp(np.clip(-alpha * (x - beta), -700, 700)))
    return (s - lo) / (hi - lo)


def branch_play(x: np.ndarray, fwd, bwd) -> np.ndarray:
    """Generalised play between two branch curves, from rest (state 0).

    x : (n_samples, ...) input. ``fwd(x)`` and ``bwd(x)`` map the input to the forward and
    backward branch values (same shape as x). Returns the state (n_samples, ...).
    """
    f = fwd(x)
    b = bwd(x)
    lo = np.minimum(f, b)
    hi = np.maximum(f, b)
    n = lo.shape[0]
    out = _clip_chain(np.ascontiguousarray(lo.reshape(n, -1)), np.ascontiguousarray(hi.reshape(n, -1)))
    return out.reshape(lo.shape)


@njit(cache=True)
def _clip_chain(lo, hi):
    """y_k = clip(y_{k-1}, lo_k, hi_k) from y_{-1} = 0, per column of (n_samples, m) arrays."""
    n, m = lo.shape
    out = np.empty((n, m))
    for j in range(m):
        y = 0.0
        for k in range(n):
            y = min(max(y, lo[k, j]), hi[k, j])
            out[k, j] = y
    return out


def preisach_gaussian(x: np.ndarray, half_widths, weights, centres, spread,
                      step: int = 1) -> np.ndarray:
    """Preisach output with a Gaussian relay density, normalised to 0 at rest, 1 at full command.

    x : (n_samples, ...) input. half_widths, weights, centres : (..., n_h) the density's half-width
    nodes h_j (>= 0), their weights w_j and the mean relay centre mu_j on each; spread : (...)
    the centres' standard deviation s (command units). Returns every ``step``-th sample
    (n_out, ...).
    """
    h = np.asarray(half_widths, float)
    p = play(_lift(x, h), h, 0.0)[::step]  # (n_out, ..., n_h)
    s = np.asarray(spread, float)[..., None]
    w = np.asarray(weights, float)
    mu = np.asarray(centres, float)
    raw = np.sum(w * ndtr((p - mu) / s), axis=-1)
    rest = np.sum(w * ndtr((0.0 - mu) / s), axis=-1)
    full = np.sum(w * ndtr((255.0 - h - mu) / s), axis=-1)
    return (raw - rest) / (full - rest)


def bouc_wen_state(x: np.ndarray, b, g, A: float = BOUC_WEN_A) -> np.ndarray:
    """Rate-independent Bouc-Wen state z (n_samples, ...) of input x (n_samples, ...), z_{-1} = 0.

    dz = A dx - b |dx| z - g dx |z| (n = 1); b, g (1 / command unit) broadcast against
    ``x.shape[1:]``, with b + g > 0 and b != g; |z| <= A / (b + g). Each sample's increment is
    integrated exactly (compiled loop over samples).
    """
    x = np.asarray(x, float)
    shape = np.broadcast_shapes(x.shape[1:], np.shape(b), np.shape(g))
    kp = np.broadcast_to(np.asarray(b, float) + g, shape)
    kn = np.broadcast_to(np.asarray(b, float) - g, shape)
    if np.any(kp <= 0) or np.any(kn == 0):
        raise ValueError("bouc_wen_state: expected b + g > 0 and b != g")
    xf = np.ascontiguousarray(np.broadcast_to(x, x.shape[:1] + shape).reshape(x.shape[0], -1))
    out = _bouc_wen_kernel(xf, np.ascontiguousarray(kp).ravel(), np.ascontiguousarray(kn).ravel(),
                           float(A))
    return out.reshape(x.shape[:1] + shape)


@njit(cache=True)
def _bouc_wen_kernel(x, kp, kn, A):
    n, m = x.shape
    out = np.empty((n, m))
    for j in range(m):
        z = 0.0
        prev = 0.0
        for k in range(n):
            dx = x[k, j] - prev
            prev = x[k, j]
            s = -1.0 if dx < 0 else 1.0
            u = abs(dx)
            zeta = s * z
            if zeta < 0:
                # zeta(u) = zeta0 e^{-kn u} + A (1 - e^{-kn u}) / kn, reaching 0 at u0
                u0 = np.log1p(-kn[j] * zeta / A) / kn[j]
                if u < u0:
                    zeta = zeta * np.exp(-kn[j] * u) - A * np.expm1(-kn[j] * u) / kn[j]
                    u = 0.0
                else:
                    zeta = 0.0
                    u = u - u0
            if zeta >= 0 and u > 0:
                # zeta(u) = A / kp + (zeta - A / kp) e^{-kp u}
                zeta = A / kp[j] + (zeta - A / kp[j]) * np.exp(-kp[j] * u)
            z = s * zeta
            out[k, j] = z
    return out
