"""The hidden effects written a second time: forms the analysis model does not share.

``HiddenEffect(name, strength, form="alt")`` (``mocap simulate --effect-form alt``) applies these
instead of the model-shaped equations of ``effects``. Each keeps its parameter's name and unit,
and the parameter keeps a meaning that a model's estimate can be scored against ("truth" below).
Time is axis 0; commands in command units; n the take's DUs, m the markers::

    lag        tau (s)      critically damped second order, two equal poles at 2 / tau:
                            (tau/2 d/dt + 1)^2 a = c, exact for c held over each sample.
                            Truth: tau is the mean delay of the step response (the first-order
                            tau with the same mean delay); its 63 % rise time is 1.07 tau.
    deadtime   L (s)        distributed delay: a(t) = mean of c over [t - 1.25 L, t - 0.75 L]
                            (a boxcar of width L / 2 centred on L). Truth: the mean delay L.
    backlash   b (units)    stick-slip dead band: the actuator follows the command while it keeps
                            going the same way; after a reversal it holds until the command has
                            come back 2 b, then jumps to the command (no lasting offset, unlike a
                            play). Truth: b is half the dead band at a reversal, as for a play.
    drift      k (units     per-marker bias drift: beta_m + k (1 + xi_m / 2) (trial - 1), with
               per trial)   xi_m = sqrt(2) sin(2.39996 m) (fixed, zero mean, unit rms over
                            markers). Truth: k is the mean drift over markers.
    coupling   kappa        product of the DUs' drives, the same at every marker:
                            y_n -> y_n (1 - kappa sum_{n' != n} y_n'). Truth: kappa is the
                            fraction each DU's response loses while another is at full command
                            (the model's kappa at the marker most in the other DU's field).
    coupling   kappa        (form "alt2", a law the model does not have: strain-stiffening skin)
      (alt2)                y_n -> y_n (1 - kappa sum_{n' != n} y_n'^2): the other DU's pull
                            costs little at first and most near full command. Truth: kappa as
                            for the alt form.
    saturation L (mm)       per DU, before summation: d_n -> d_n / sqrt(1 + (|d_n| / L)^2)
                            (algebraic, not tanh). Truth: L is the asymptotic largest
                            displacement of one DU.
    curvature  kappa        a skewed bow: d += 27/4 kappa y (1 - y)^2 |D_n| e_n (peaking at
                            y = 1/3). Truth: kappa is the largest sideways deviation over |D|.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import cont2discrete, lfilter

DRIFT_SPREAD = 0.5
DEADTIME_WINDOW = 0.5  # boxcar width / L
DEADTIME_TAPS = 16


def marker_drift_weights(n_markers: int) -> np.ndarray:
    """1 + xi_m / 2 (n_markers,), xi_m = sqrt(2) sin(2.39996 m): fixed, mean ~1 over markers."""
    m = np.arange(n_markers)
    return 1.0 + DRIFT_SPREAD * np.sqrt(2.0) * np.sin(2.39996 * m)


def lag_second_order(c: np.ndarray, t: np.ndarray, tau: float) -> np.ndarray:
    """(tau/2 d/dt + 1)^2 a = c from rest, exact under zero-order hold; c (n_samples, n_dus)."""
    dt = float(t[1] - t[0]) if t.size > 1 else 1.0
    t2 = 0.5 * tau
    num, den, _ = cont2discrete(([1.0], [t2 * t2, 2.0 * t2, 1.0]), dt, method="zoh")
    return lfilter(np.ravel(num), den, c, axis=0)


def distributed_delay(t: np.ndarray, sampler, delay_s: float) -> np.ndarray:
    """a(t) = mean of c over [t - 1.25 L, t - 0.75 L] (midpoint rule, DEADTIME_TAPS points)."""
    half = 0.5 * DEADTIME_WINDOW * delay_s
    offs = delay_s - half + (np.arange(DEADTIME_TAPS) + 0.5) / DEADTIME_TAPS * 2 * half
    return np.mean([sampler(t - o) for o in offs], axis=0)


def stick_slip(c: np.ndarray, halfwidth: float) -> np.ndarray:
    """Stick-slip dead band (n_samples, n_dus) from rest (actuator 0, last motion upwards)."""
    c = np.asarray(c, float)
    out = np.empty_like(c)
    a = np.zeros(c.shape[1:])
    d = np.ones(c.shape[1:])
    for k in range(c.shape[0]):
        ahead = (c[k] - a) * d >= 0
        back = ~ahead & (np.abs(c[k] - a) >= 2.0 * halfwidth)
        d = np.where(back, -d, d)
        a = np.where(ahead | back, c[k], a)
        out[k] = a
    return out


def coupled_drives(y: np.ndarray, kappa: float) -> np.ndarray:
    """y_n (1 - kappa sum_{n' != n} y_n') for y (n_samples, n_dus, n_markers)."""
    others = y.sum(axis=1, keepdims=True) - y
    return y * (1.0 - kappa * others)


def stiffening_coupling(y: np.ndarray, kappa: float) -> np.ndarray:
    """y_n (1 - kappa sum_{n' != n} y_n'^2) for y (n_samples, n_dus, n_markers)."""
    y2 = y * y
    others = y2.sum(axis=1, keepdims=True) - y2
    return y * (1.0 - kappa * others)


def compress_per_du(per_du: np.ndarray, limit_mm: float) -> np.ndarray:
    """d_n / sqrt(1 + (|d_n| / L)^2) for per-DU displacements (..., 3) mm."""
    mag = np.linalg.norm(per_du, axis=-1, keepdims=True)
    return per_du / np.sqrt(1.0 + (mag / limit_mm) ** 2)


def skewed_bow(y: np.ndarray, kappa: float) -> np.ndarray:
    """27/4 kappa y (1 - y)^2: the sideways deviation over |D| of the alt curvature."""
    return 6.75 * kappa * y * (1.0 - y) ** 2
