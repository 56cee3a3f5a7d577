"""Pooled logistic fits (samples sharing abscissae, as over markers and their bootstrap) fitted
through their sums per abscissa: the same fit as on every sample."""

import numpy as np
from scipy.optimize import least_squares

from mocap.analysis.paper.logistic_fit import _model, fit_logistic, grouped_samples


def pooled_data(seed: int = 0, n: int = 150, markers: int = 40):
    """A ramp's times tiled over markers with per-marker biases, noise and missing samples;
    bootstrap-like weights (multinomial counts per marker)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 2.5, n)
    bias = 1.1 + rng.normal(0, 0.08, markers)
    y = 1.0 / (1.0 + np.exp(-7.0 * (t[None] - bias[:, None]))) + rng.normal(0, 0.02, (markers, n))
    y[rng.random(y.shape) < 0.05] = np.nan
    x = np.tile(t, markers)
    counts = rng.multinomial(markers, np.full(markers, 1.0 / markers), size=6).astype(float)
    W = np.repeat(counts, n, axis=1)
    return x, y.ravel(), W


def test_grouped_cost_equals_the_cost_over_every_sample():
    x, y, W = pooled_data(1)
    Y = np.broadcast_to(y, W.shape)
    W = np.where(np.isfinite(Y), W, 0.0)
    Y = np.where(np.isfinite(Y), Y, 0.0)
    u, Ybar, S, const = grouped_samples(x, Y, W)
    assert u.size * 10 < x.size
    rng = np.random.default_rng(2)
    for _ in range(5):
        a, b = rng.uniform(2, 12, W.shape[0]), rng.uniform(0.5, 1.8, W.shape[0])
        direct = np.sum(W * (_model(x, a, b) - Y) ** 2, axis=1)
        grouped = np.sum(S * (_model(u, a, b) - Ybar) ** 2, axis=1) + const
        np.testing.assert_allclose(grouped, direct, rtol=1e-11)


def test_pooled_bootstrap_fit_equals_a_fit_on_every_sample():
    x, y, W = pooled_data(3)
    fit = fit_logistic(x, np.broadcast_to(y, W.shape), W, a0=np.full(W.shape[0], 5.0),
                       b0=np.full(W.shape[0], 1.0))
    assert fit.converged.all()
    ok = np.isfinite(y)
    for k in range(W.shape[0]):  # scipy's trust-region solver on the raw weighted samples
        sw = np.sqrt(W[k, ok])

        def resid(p, sw=sw):
            return sw * (1.0 / (1.0 + np.exp(-p[0] * (x[ok] - p[1]))) - y[ok])

        ref = least_squares(resid, [5.0, 1.0], xtol=1e-15, ftol=1e-15, gtol=1e-15)
        np.testing.assert_allclose([fit.a[k], fit.b[k]], ref.x, rtol=1e-7)
        rms = np.sqrt(np.sum(resid(ref.x) ** 2) / np.sum(W[k, ok]))
        np.testing.assert_allclose(fit.rms[k], rms, rtol=1e-9)
