"""Batched least-squares fits of the logistic ``y = 1 / (1 + exp(-a (x - b)))``.

Many independent curves (markers, bootstrap replicates) are fitted at once by a damped
Gauss-Newton (Levenberg-Marquardt) iteration vectorised over curves: each curve has two
parameters, so each step solves a 2 x 2 system per curve in closed form. Samples carry weights
(0 drops a sample: NaN data, resampling counts). Samples sharing an abscissa (pooled fits over
markers, their bootstrap) are fitted through their sums per abscissa (:func:`grouped_samples`):
the same steps on ~100 x fewer samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LogisticFit:
    """Fitted gains ``a`` and biases ``b`` (n_curves,), weighted RMS residual, and success."""

    a: np.ndarray
    b: np.ndarray
    rms: np.ndarray
    converged: np.ndarray


def _model(x, a, b):
    z = np.clip(-a[:, None] * (x - b[:, None]), -500, 500)
    return 1.0 / (1.0 + np.exp(z))


def initial_guess(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bias where the weighted data cross 0.5; gain from the 10-90 % rise width."""
    n = y.shape[0]
    b = np.empty(n)
    a = np.empty(n)
    order = np.argsort(x)
    xs = x[order]
    for i in range(n):  # per curve, only for the starting point (cheap)
        yi = y[i, order]
        wi = w[i, order] > 0
        xi, yi = xs[wi], yi[wi]
        if xi.size < 3:
            a[i], b[i] = 0.05, np.nan
            continue
        lo, hi = np.nanpercentile(yi, 5), np.nanpercentile(yi, 95)
        rising = np.nanmean(yi[: max(1, yi.size // 3)]) < np.nanmean(yi[-max(1, yi.size // 3):])
        mid = 0.5 * (lo + hi)
        k = np.flatnonzero(yi >= mid) if rising else np.flatnonzero(yi <= mid)
        b[i] = xi[k[0]] if k.size else np.median(xi)
        q10 = xi[np.flatnonzero(yi >= lo + 0.1 * (hi - lo))] if rising else xi[np.flatnonzero(yi <= hi - 0.1 * (hi - lo))]
        q90 = xi[np.flatnonzero(yi >= lo + 0.9 * (hi - lo))] if rising else xi[np.flatnonzero(yi <= hi - 0.9 * (hi - lo))]
        width = (q90[0] - q10[0]) if (q10.size and q90.size) else np.ptp(xi) / 4
        a[i] = 4.4 / max(width, 1e-6 * max(np.ptp(xi), 1.0))
        if not rising:
            a[i] = -a[i]
    return a, b


def grouped_samples(x: np.ndarray, Y: np.ndarray, W: np.ndarray):
    """The weighted least-squares problem on the distinct abscissae of ``x``.

    Samples sharing an abscissa (a pooled fit over markers: ``x`` the ramp's times tiled once
    per marker) enter every sum of the fit through three sums per abscissa: the weight S, the
    weighted data and the weighted squared data. With Ybar their weighted mean,
    ``sum_s W_s (p(x_s) - Y_s)^2 = sum_k S_k (p(u_k) - Ybar_k)^2 + const``, ``const`` not
    depending on the curve's parameters, and so do the gradient and the Gauss-Newton matrix: the
    fit on (u, Ybar, S) takes the same steps on n_distinct instead of n_samples samples.

    x (n,); Y, W (n_curves, n) (W 0 where Y is missing). Returns (x, Y, W, const (n_curves,))
    grouped, or the inputs and zeros when fewer than half the abscissae repeat.
    """
    u, inverse = np.unique(x, return_inverse=True)
    if 2 * u.size > x.size:
        return x, Y, W, np.zeros(Y.shape[0])
    from scipy.sparse import csr_matrix

    G = csr_matrix((np.ones(x.size), (np.arange(x.size), inverse)), shape=(x.size, u.size))
    WY = W * Y
    S = np.asarray(W @ G)
    SY = np.asarray(WY @ G)
    SYY = np.asarray((WY * Y) @ G)
    with np.errstate(invalid="ignore", divide="ignore"):
        Ybar = np.where(S > 0, SY / S, 0.0)
        const = np.sum(np.where(S > 0, SYY - SY * Ybar, 0.0), axis=1)
    return u, Ybar, S, np.maximum(const, 0.0)


def fit_logistic(x: np.ndarray, y: np.ndarray, w: np.ndarray | None = None, *,
                 a0: np.ndarray | None = None, b0: np.ndarray | None = None,
                 max_iter: int = 200, tol: float = 1e-12) -> LogisticFit:
    """Fit every row of ``y`` against the shared abscissa ``x``.

    Parameters
    ----------
    x : (n_samples,) abscissa (time in s, or command units).
    y : (n_curves, n_samples) data; NaN samples are ignored.
    w : optional (n_curves, n_samples) or (n_samples,) non-negative weights.

    Returns
    -------
    LogisticFit with (n_curves,) arrays. A falling curve gets a negative gain.
    """
    x = np.asarray(x, float)
    y = np.atleast_2d(np.asarray(y, float))
    W = np.ones_like(y) if w is None else np.broadcast_to(np.asarray(w, float), y.shape).copy()
    W = np.where(np.isfinite(y), W, 0.0)
    Y = np.where(np.isfinite(y), y, 0.0)
    ga, gb = initial_guess(x, Y, W) if (a0 is None or b0 is None) else (None, None)
    a = np.array(a0 if a0 is not None else ga, float).copy()
    b = np.array(b0 if b0 is not None else gb, float).copy()
    b = np.where(np.isfinite(b), b, np.median(x))
    lam = np.full(y.shape[0], 1e-3)
    total_w = np.sum(W, axis=1)
    x, Y, W, const = grouped_samples(x, Y, W)

    def cost(a, b):
        r = _model(x, a, b) - Y
        return np.sum(W * r * r, axis=1) + const

    c = cost(a, b)
    converged = np.zeros(y.shape[0], bool)
    for _ in range(max_iter):
        p = _model(x, a, b)
        r = p - Y
        dp = p * (1.0 - p)
        ja = dp * (x - b[:, None])  # d p / d a
        jb = -dp * a[:, None]  # d p / d b
        haa = np.sum(W * ja * ja, axis=1)
        hab = np.sum(W * ja * jb, axis=1)
        hbb = np.sum(W * jb * jb, axis=1)
        ga_ = np.sum(W * ja * r, axis=1)
        gb_ = np.sum(W * jb * r, axis=1)
        haa_d = haa * (1 + lam) + 1e-30
        hbb_d = hbb * (1 + lam) + 1e-30
        det = haa_d * hbb_d - hab * hab
        da = -(hbb_d * ga_ - hab * gb_) / det
        db = -(haa_d * gb_ - hab * ga_) / det
        a_new, b_new = a + da, b + db
        c_new = cost(a_new, b_new)
        better = np.isfinite(c_new) & (c_new <= c)
        rel = np.where(better, (c - c_new) / np.maximum(c, 1e-300), 0.0)
        a = np.where(better, a_new, a)
        b = np.where(better, b_new, b)
        c = np.where(better, c_new, c)
        lam = np.where(better, np.maximum(lam / 3, 1e-12), lam * 8)
        converged |= better & (rel < tol)
        converged |= lam > 1e10
        if converged.all():
            break
    rms = np.sqrt(np.maximum(c, 0.0) / np.maximum(total_w, 1e-300))  # weighted RMS residual
    return LogisticFit(a, b, rms, converged)
