"""The curve fits' compiled tangent products against a plain NumPy computation."""

import numpy as np
import pytest

from mocap.analysis.model.curve_fit_kernel import tangent_products


@pytest.mark.parametrize("K", [0, 3])
def test_tangent_products_match_numpy(K):
    rng = np.random.default_rng(K)
    S, M = 40, 7
    db = rng.normal(size=(S, M, K))
    coef = rng.normal(size=(M, K + 1, 3))
    # the residuals as the variable projection returns them: a transposed (non-contiguous) view
    e = rng.normal(size=(M, S, 3)).transpose(1, 0, 2)
    wt = (rng.random((S, M)) > 0.2).astype(float)
    g = coef[None, :, 0, :] + np.einsum("smk,mkx->smx", db, coef[:, 1:, :])
    ge, gg = tangent_products(db, coef, e, wt)
    np.testing.assert_allclose(ge, (g * e).sum(axis=-1) * wt, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(gg, (g * g).sum(axis=-1) * wt, rtol=1e-12, atol=1e-12)
    assert np.all(ge[wt == 0] == 0) and np.all(gg[wt == 0] == 0)
