"""Compiled inner terms of the curve fits' Levenberg-Marquardt step (:mod:`mocap.analysis.model.curves`).

The step needs, per sample and curve, the residual's and the path tangent's products with the
tangent g = d pred / d y = D + sum_k b_k'(y) B_k: g . e and g . g. In NumPy that materialises
g (S, M, 3) once per path basis and twice more for the two contractions; here it is one pass
that keeps g in registers, the same operations in the same order (so the same bits).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy")
def _tangent_products(db, coef, e, wt, ge, gg):
    S, M, K = db.shape
    for s in range(S):
        for m in range(M):
            g0 = coef[m, 0, 0]
            g1 = coef[m, 0, 1]
            g2 = coef[m, 0, 2]
            for k in range(K):
                d = db[s, m, k]
                g0 = g0 + d * coef[m, k + 1, 0]
                g1 = g1 + d * coef[m, k + 1, 1]
                g2 = g2 + d * coef[m, k + 1, 2]
            # summed (x0 + x2) + x1, the order of NumPy's einsum over three terms
            w = wt[s, m]
            ge[s, m] = ((g0 * e[s, m, 0] + g2 * e[s, m, 2]) + g1 * e[s, m, 1]) * w
            gg[s, m] = ((g0 * g0 + g2 * g2) + g1 * g1) * w


def tangent_products(db: np.ndarray, coef: np.ndarray, e: np.ndarray,
                     wt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(g . e w, g . g w), each (S, M), for the path tangent g = coef[:, 0] + sum_k db_k
    coef[:, k + 1] of basis derivatives db (S, M, K), coefficients coef (M, K + 1, 3) mm,
    residuals e (S, M, 3) mm and weights wt (S, M)."""
    S, M = wt.shape
    ge = np.empty((S, M))
    gg = np.empty((S, M))
    _tangent_products(np.asarray(db, float), np.asarray(coef, float), np.asarray(e, float),
                      np.asarray(wt, float), ge, gg)
    return ge, gg
