"""The paper's response function: a logistic sigmoid of the command, and its inverse.

``R(c) = 1 / (1 + exp(-alpha (c - beta)))`` with ``c`` in command units (0..255), ``alpha`` in
1/command unit (the sensitivity) and ``beta`` in command units (the bias; forward minus backward
beta is the hysteresis).
"""

from __future__ import annotations

import numpy as np


def sigmoid(c, alpha, beta):
    """R(c) = 1 / (1 + exp(-alpha (c - beta))), broadcasting over all arguments."""
    z = -np.asarray(alpha, float) * (np.asarray(c, float) - np.asarray(beta, float))
    return 1.0 / (1.0 + np.exp(np.clip(z, -700.0, 700.0)))


def inverse_sigmoid(delta, alpha, beta, *, eps: float = 1e-6):
    """c = beta - ln((1 - delta) / delta) / alpha (METHOD.md), delta clipped to [eps, 1 - eps].

    Returns command units as floats (not rounded or clipped to 0..255).
    """
    d = np.clip(np.asarray(delta, float), eps, 1.0 - eps)
    return np.asarray(beta, float) - np.log((1.0 - d) / d) / np.asarray(alpha, float)


def normalized_sigmoid(c, alpha, beta, c_min: float = 0.0, c_max: float = 255.0):
    """The sigmoid rescaled so that it is exactly 0 at ``c_min`` and 1 at ``c_max``.

    ``(R(c) - R(c_min)) / (R(c_max) - R(c_min))``: a face at rest has zero displacement and the
    full command its full displacement, while the shape in between is the paper's sigmoid.
    """
    lo = sigmoid(c_min, alpha, beta)
    hi = sigmoid(c_max, alpha, beta)
    return (sigmoid(c, alpha, beta) - lo) / (hi - lo)
