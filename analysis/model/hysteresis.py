"""Rate-independent hysteresis operators: the play (backlash) operator and the
Prandtl-Ishlinskii (PI) superposition of plays.

Conventions: the first axis of an input series is time (samples in order); further axes are
independent channels (DUs, markers). Inputs and outputs are in command units.

The play operator of half-width ``r >= 0`` with initial output ``y0``::

    y[0] = clip(y0, x[0] - r, x[0] + r)
    y[k] = clip(y[k-1], x[k] - r, x[k] + r)

It is exact for piecewise-monotone inputs sampled at their turning points (the operator is
rate-independent: only the order of values matters). A PI operator is ``sum_i w_i play_{r_i}``;
on a full sweep 0 -> X -> 0 it traces forward and backward branches offset by the weighted mean
half-width ``r_bar = sum_i w_i r_i / sum_i w_i`` (once ``x`` exceeds the largest threshold), and
under arbitrary reversals it gives the minor loops of a Preisach model with that distribution of
play widths. The paper's forward/backward sigmoid pair is the full-sweep limit of a PI operator
followed by a logistic.
"""

from __future__ import annotations

import numpy as np


def play(x: np.ndarray, r, y0=0.0) -> np.ndarray:
    """Play (backlash) operator of half-width ``r`` applied along axis 0.

    Parameters
    ----------
    x : (n_samples, ...) input series.
    r : scalar or array broadcastable to ``x.shape[1:]``; half-widths >= 0.
    y0 : scalar or array broadcastable to ``x.shape[1:]``; the initial output (state).

    Returns
    -------
    (n_samples, ...) output series, same dtype float.
    """
    x = np.asarray(x, float)
    r = np.asarray(r, float)
    if np.any(r < 0):
        raise ValueError(f"play: expected half-widths r >= 0, got min {r.min()}")
    shape = np.broadcast_shapes(x.shape[1:], np.shape(r), np.shape(y0))
    out = np.empty((x.shape[0],) + shape)
    y = np.broadcast_to(np.asarray(y0, float), shape).copy()
    lo = np.empty(shape)
    hi = np.empty(shape)
    for k in range(x.shape[0]):
        np.subtract(x[k], r, out=lo)
        np.add(x[k], r, out=hi)
        np.clip(y, lo, hi, out=y)
        out[k] = y
    return out


def prandtl_ishlinskii(x: np.ndarray, thresholds, weights, y0=None) -> np.ndarray:
    """Prandtl-Ishlinskii operator ``sum_i w_i play_{r_i}(x)`` along axis 0.

    Parameters
    ----------
    x : (n_samples, ...) input series.
    thresholds : (..., n_plays) half-widths r_i >= 0 (broadcast against ``x.shape[1:]``).
    weights : (..., n_plays) weights w_i (broadcast likewise); they need not sum to 1.
    y0 : optional (..., n_plays) initial play states (default 0: a face at rest).

    Returns
    -------
    (n_samples, ...) output series.
    """
    x = np.asarray(x, float)
    thr = np.asarray(thresholds, float)
    w = np.asarray(weights, float)
    plays = play(x[..., None], thr, 0.0 if y0 is None else y0)
    return np.sum(plays * w, axis=-1)


def pi_mean_halfwidth(thresholds, weights) -> np.ndarray:
    """The weighted mean half-width ``r_bar`` (command units): half the full-sweep loop width."""
    thr = np.asarray(thresholds, float)
    w = np.asarray(weights, float)
    return np.sum(thr * w, axis=-1) / np.sum(w, axis=-1)
