"""Variable-projection Levenberg-Marquardt of one DU's curves, vectorised over its markers.

Per curve the nonlinear parameters (alpha, beta[, r]) are stepped by Levenberg-Marquardt; the
linear ones (the path coefficients D (3,) mm and B (K, 3) mm) are projected out in closed form
for given responses y. A :class:`_Block` stacks one DU's single-DU training samples: play table
P (S, H), bias shift (S,) in command units, observed displacements v (S, M_n, 3) mm and weights
(S, M_n).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from mocap.analysis.model.curve_fit_kernel import tangent_products
from mocap.analysis.model.data import ModelData
from mocap.analysis.model.face_model import DENSITY_FRACTIONS, EQUAL_DENSITY, PI_BRANCH, R_MAX
from mocap.analysis.model.play_kernel import pi_logistic_from_table


@dataclass
class _Block:
    """Stacked single-DU training samples of one DU: table P (S, H), bias shift (S,),
    transformed observations v (S, M_n, 3), weights wt (S, M_n), the PI density q (F,) and each
    sample's trial (S,)."""

    P: np.ndarray
    shift: np.ndarray
    v: np.ndarray
    wt: np.ndarray
    q: np.ndarray | None = None
    trial: np.ndarray | None = None
    branch: np.ndarray = field(default_factory=lambda: PI_BRANCH.copy())

    @cached_property
    def by_curve(self) -> np.ndarray:
        """v curve by curve (M_n, S, 3), contiguous (the variable projection's layout)."""
        return np.ascontiguousarray(self.v.transpose(1, 0, 2))

    def sub(self, cols) -> "_Block":
        return _Block(self.P, self.shift, self.v[:, cols], self.wt[:, cols], self.q, self.trial,
                      self.branch)


def _block(data: ModelData, du: int, takes, effects, markers: np.ndarray,
           take_shifts: dict | None = None) -> _Block | None:
    ks = [k for k in takes if data.takes[k].dus == (du,)]
    if not ks:
        return None
    outs = tuple((type(e).__qualname__, float(e.value)) for e in effects
                 if type(e).stage == "output")
    key = (du, tuple(ks), outs, markers.tobytes())
    if key not in data._blocks:
        V, W = [], []
        for k in ks:
            d = data.observed(k)[:, markers]
            ok = np.isfinite(d).all(axis=-1)
            d = np.where(ok[..., None], d, 0.0)
            wt = ok.astype(float)
            for e in effects:
                d, w_e = e.output_inverse(d)
                if w_e is not None:
                    wt = wt * w_e
            V.append(d)
            W.append(wt)
        if len(data._blocks) > 8 * len(data.du_ids):  # a few output-effect values at a time
            data._blocks.clear()
        data._blocks[key] = (np.concatenate(V), np.concatenate(W))
    v, wt = data._blocks[key]
    P = np.concatenate([data.tables(k, effects)[0] for k in ks])
    ts = take_shifts or {}
    shift = np.concatenate([np.full(data.observed(k).shape[0],
                                    float(np.asarray(sum((e.beta_shift(data.takes[k].trial)
                                                          for e in effects), 0.0)))
                                    + ts.get(data.takes[k].name, {}).get(du, 0.0))
                            for k in ks])
    trial = np.concatenate([np.full(data.observed(k).shape[0], data.takes[k].trial) for k in ks])
    return _Block(P, shift, v, wt, EQUAL_DENSITY, trial)


def _responses(blk: _Block, p: np.ndarray, hyst: bool, derivatives: bool = False):
    """y (S, M) and, with ``derivatives``, dy/d(alpha, beta[, r]) (S, M, P), analytically."""
    r = p[:, 2] if hyst else np.zeros(p.shape[0])
    mix, kappa = (blk.branch if hyst else PI_BRANCH)
    out = pi_logistic_from_table(blk.P, r, p[:, 0], p[:, 1], blk.shift, DENSITY_FRACTIONS,
                                 derivatives, weights=blk.q, mix=mix, kappa=kappa)
    if not derivatives:
        return out
    y, dy = out
    return y, (dy if hyst else dy[..., :2])


def _project(blk: _Block, y: np.ndarray, effects, v: np.ndarray, wt: np.ndarray):
    """Variable projection: coefficients (M, K+1, 3), residual (S, M, 3), cost (M,).

    Per curve m, with the basis A_m = [y, bases(y)] (S, K+1) and weights w: the normal
    equations (A^T W A + 1e-9 I) c = A^T W v, as batched matrix products over curves."""
    Am = _path_basis(y.T, effects)  # (M, S, k): curve by curve
    k = Am.shape[-1]
    wAm = Am * wt.T[..., None]
    G = np.matmul(wAm.transpose(0, 2, 1), Am) + 1e-9 * np.eye(k)  # (M, k, k)
    vm = blk.by_curve if v is blk.v else np.ascontiguousarray(v.transpose(1, 0, 2))  # (M, S, 3)
    coef = np.linalg.solve(G, np.matmul(wAm.transpose(0, 2, 1), vm))  # (M, k, 3)
    em = vm - np.matmul(Am, coef)  # (M, S, 3)
    cost = np.einsum("msx,ms->m", em * em, wt.T)
    return coef, em.transpose(1, 0, 2), cost


def _path_basis(y: np.ndarray, effects) -> np.ndarray:
    """The path's basis (S, M, K + 1) of responses y (S, M): [y, b_1(y), ...]."""
    return np.stack([y] + [b for e in effects for b in e.bases(y)], axis=-1)


def _dpred_dy(y: np.ndarray, coef: np.ndarray, effects) -> np.ndarray:
    """d pred / d y (S, M, 3) of the path d = y D + sum_k b_k(y) B_k: D + sum_k b_k'(y) B_k, for
    responses y (S, M) and coefficients coef (M, K + 1, 3) = [D, B_1, ...]."""
    g = np.broadcast_to(coef[None, :, 0, :], y.shape + (3,))
    db = _basis_derivatives(y, effects)
    for k in range(db.shape[-1]):
        g = g + db[..., k, None] * coef[None, :, k + 1, :]
    return g


def _basis_derivatives(y: np.ndarray, effects) -> np.ndarray:
    """d b_k / d y of the path's extra bases (S, M, K) at responses y (S, M) (K may be 0)."""
    db = [b for e in effects for b in e.bases_derivative(y)]
    return np.stack(db, axis=-1) if db else np.zeros(y.shape + (0,))


def _lm_curves(blk: _Block, p0: np.ndarray, effects, hyst: bool, iters: int = 30,
               tol: float = 1e-6):
    """Levenberg-Marquardt over (alpha, beta[, r]) per curve; returns (p, coef, cost)."""
    v, wt = blk.v, blk.wt
    p = p0.copy()
    npar = 3 if hyst else 2
    y, dy = _responses(blk, p, hyst, derivatives=True)
    coef, e, cost = _project(blk, y, effects, v, wt)
    lam = np.full(p.shape[0], 1e-3)
    for _ in range(iters):
        # d pred / dp_j = dy/dp_j * g,  g = coef_0 + sum_k basis_k'(y) coef_k   (Kaufman)
        ge, gg = tangent_products(_basis_derivatives(y, effects), coef, e, wt)
        J = np.ascontiguousarray(dy[..., :npar].transpose(1, 0, 2))  # (M, S, P)
        b = np.matmul(ge.T[:, None, :], J)[:, 0]  # (M, P)
        H = np.matmul((J * gg.T[..., None]).transpose(0, 2, 1), J)  # (M, P, P)
        Hd = H + lam[:, None, None] * (np.einsum("mii->mi", H)[..., None] * np.eye(npar)) + 1e-12 * np.eye(npar)
        step = np.linalg.solve(Hd, b[..., None])[..., 0]
        q = p.copy()
        q[:, :npar] += step
        q[:, 0] = np.clip(q[:, 0], 1e-3, 0.5)
        q[:, 1] = np.clip(q[:, 1], -100.0, 355.0)
        if hyst:
            q[:, 2] = np.clip(q[:, 2], 0.0, R_MAX)
        y_new, dy_new = _responses(blk, q, hyst, derivatives=True)
        coef_new, e_new, cost_new = _project(blk, y_new, effects, v, wt)
        better = cost_new < cost
        rel = np.where(better, (cost - cost_new) / np.maximum(cost, 1e-300), 0.0)
        if better.all():  # the usual case: every curve's step taken (no copies)
            p, y, dy, coef, e, cost = q, y_new, dy_new, coef_new, e_new, cost_new
        elif better.any():
            p = np.where(better[:, None], q, p)
            y = np.where(better[None], y_new, y)
            dy = np.where(better[None, :, None], dy_new, dy)
            coef = np.where(better[:, None, None], coef_new, coef)
            e = np.where(better[None, :, None], e_new, e)
            cost = np.where(better, cost_new, cost)
        lam = np.where(better, np.maximum(lam / 4, 1e-9), lam * 6)
        if np.all((better & (rel < tol)) | (lam > 1e7)):
            break
    return p, coef, cost
