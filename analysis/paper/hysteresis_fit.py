"""Identification of a Prandtl-Ishlinskii-logistic response per marker.

Model (the paper's forward/backward sigmoids as the full-sweep limit of a hysteresis operator
followed by a logistic, valid under arbitrary command reversals)::

    w(t) = PI_r[c](t)       plays of half-widths r * (0, 0.5, 1, 1.5, 2), equal weights, from rest
    y(t) = (S(w) - S(0)) / (S(255) - S(0)),   S(w) = 1 / (1 + exp(-alpha (w - beta)))

On a full sweep the forward branch is the logistic of ``c - r`` and the backward one of
``c + r`` (hysteresis 2 r); after a reversal the output moves at once at a fifth of the slope and
steepens as wider plays release (Preisach-type minor loops). Its inverse is analytic on each
monotone branch, which motion design uses.

``fit_pi_logistic`` fits (alpha, beta, r) for many curves at once (Levenberg-Marquardt,
vectorised over curves, finite-difference Jacobian: three parameters per curve) from any command
series, not only the paper's trapezoid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocap.analysis.model.hysteresis import play

PLAY_FRACTIONS = np.array([0.0, 0.5, 1.0, 1.5, 2.0])


def pi_logistic(c: np.ndarray, alpha, beta, r) -> np.ndarray:
    """Normalised response y (n_samples, n_curves) to command c (n_samples,) or (n_samples, n_curves).

    alpha, beta, r : (n_curves,) parameters (1/command unit, command units, command units).
    """
    alpha = np.atleast_1d(np.asarray(alpha, float))
    beta = np.atleast_1d(np.asarray(beta, float))
    r = np.clip(np.atleast_1d(np.asarray(r, float)), 0.0, None)
    c = np.asarray(c, float)
    if c.ndim == 1:
        c = c[:, None]
    thr = r[:, None] * PLAY_FRACTIONS  # (n_curves, n_plays)
    w = play(np.broadcast_to(c[..., None], (c.shape[0], alpha.size, PLAY_FRACTIONS.size)), thr,
             0.0).mean(axis=-1)
    return normalized_logistic(w, alpha, beta)


def normalized_logistic(w: np.ndarray, alpha: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """y = (S(w) - S(0)) / (S(255) - S(0)), S(w) = 1 / (1 + exp(-alpha (w - beta))); broadcasts."""
    lo = 1.0 / (1.0 + np.exp(np.clip(alpha * beta, -700, 700)))
    hi = 1.0 / (1.0 + np.exp(np.clip(-alpha * (255.0 - beta), -700, 700)))
    s = 1.0 / (1.0 + np.exp(np.clip(-alpha * (w - beta), -700, 700)))
    return (s - lo) / np.maximum(hi - lo, 1e-12)


@dataclass(frozen=True)
class PILogisticFit:
    alpha: np.ndarray
    beta: np.ndarray
    r: np.ndarray
    rms: np.ndarray

    @property
    def hysteresis(self) -> np.ndarray:
        """Full-sweep loop width 2 r (command units)."""
        return 2.0 * self.r


def fit_pi_logistic(c: np.ndarray, y: np.ndarray, *, alpha0=0.05, beta0=128.0, r0=20.0,
                    max_iter: int = 60, tol: float = 1e-10) -> PILogisticFit:
    """Fit (alpha, beta, r) to each column of y (n_samples, n_curves) driven by command c.

    NaN samples are ignored. Starting values broadcast to the curves.
    """
    c = np.asarray(c, float)
    y = np.asarray(y, float)
    if y.ndim == 1:
        y = y[:, None]
    n = y.shape[1]
    ok = np.isfinite(y)
    Y = np.where(ok, y, 0.0)
    p = np.stack([np.broadcast_to(np.asarray(v, float), (n,)).copy()
                  for v in (alpha0, beta0, r0)], axis=1)  # (n, 3)
    scale = np.array([1e-4, 0.05, 0.05])

    def resid(p):
        return np.where(ok, pi_logistic(c, p[:, 0], p[:, 1], p[:, 2]) - Y, 0.0)

    r_now = resid(p)
    cost = np.sum(r_now**2, axis=0)
    lam = np.full(n, 1e-2)
    for _ in range(max_iter):
        J = np.empty(r_now.shape + (3,))
        for k in range(3):
            q = p.copy()
            q[:, k] += scale[k]
            J[..., k] = (resid(q) - r_now) / scale[k]
        H = np.einsum("sci,scj->cij", J, J)
        g = np.einsum("sci,sc->ci", J, r_now)
        Hd = H + lam[:, None, None] * np.einsum("cii->ci", H)[..., None] * np.eye(3) + 1e-12 * np.eye(3)
        step = -np.linalg.solve(Hd, g[..., None])[..., 0]
        q = p + step
        q[:, 2] = np.clip(q[:, 2], 0.0, 127.0)
        q[:, 0] = np.clip(q[:, 0], 1e-4, 1.0)
        r_new = resid(q)
        c_new = np.sum(r_new**2, axis=0)
        better = c_new <= cost
        rel = np.where(better, (cost - c_new) / np.maximum(cost, 1e-300), 0.0)
        p = np.where(better[:, None], q, p)
        r_now = np.where(better[None], r_new, r_now)
        cost = np.where(better, c_new, cost)
        lam = np.where(better, np.maximum(lam / 3, 1e-9), lam * 8)
        if np.all((better & (rel < tol)) | (lam > 1e8)):
            break
    rms = np.sqrt(cost / np.maximum(ok.sum(axis=0), 1))
    return PILogisticFit(p[:, 0], p[:, 1], p[:, 2], rms)
