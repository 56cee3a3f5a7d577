"""Each DU's PI density and branch parameters, the curves held or stepped with them.

The density q (F,) over :data:`~mocap.analysis.model.face_model.DENSITY_FRACTIONS` lies on the
simplex (q >= 0, sum 1); the branch parameters (mix, kappa) lie in :data:`BRANCH_BOUNDS`. The
alternation's step (:func:`_update_density`) is a projected Gauss-Newton step of (q, mix, kappa)
with the curves held; the joint polish (:func:`_joint_round`) is Levenberg-Marquardt over a DU's
strong curves (alpha, beta, r) and (q, mix, kappa) together. Costs are training sums of squares
in mm^2, the path coefficients projected out.
"""

from __future__ import annotations

import numpy as np

from mocap.analysis.model.curves import (
    _block,
    _Block,
    _dpred_dy,
    _path_basis,
    _project,
    _responses,
)
from mocap.analysis.model.data import ModelData
from mocap.analysis.model.face_model import DENSITY_FRACTIONS, R_MAX, FaceModel
from mocap.analysis.model.play_kernel import H_STEP


def _du_parts(data: ModelData, model: FaceModel, takes, n: int, du: int):
    """A DU's strong curves' block, parameters (Ms, 3), coefficients and derivative factor:
    (blk, p, y, dy (S, Ms, 3), g = d pred / d y (S, Ms, 3), residual (S, Ms, 3)); None when the
    DU has no single-DU takes."""
    act = np.flatnonzero(model.active[n] & data.strong[n])
    if act.size == 0:
        act = np.flatnonzero(model.active[n])
    if act.size == 0:
        return None
    blk = _block(data, du, takes, model.effects, act, model.take_shifts)
    if blk is None:
        return None
    blk.q = model.density[n]
    blk.branch = model.branch[n]
    p = np.column_stack([model.alpha[n, act], model.beta[n, act], model.r[n, act]])
    y, dy = _responses(blk, p, True, derivatives=True)
    coef = np.concatenate([model.D[n, act][:, None], model.B[n, act]], axis=1)  # (Ms, K+1, 3)
    g = np.broadcast_to(coef[None, :, 0, :], blk.v.shape)
    pred = y[..., None] * coef[None, :, 0, :]
    kk = 1
    for ef in model.effects:
        for basis, db in zip(ef.bases(y), ef.bases_derivative(y)):
            g = g + db[..., None] * coef[None, :, kk, :]
            pred = pred + basis[..., None] * coef[None, :, kk, :]
            kk += 1
    return blk, p, act, y, dy, g, blk.v - pred


SHARED_PULL = 0.05  # a DU's density is pulled towards the DUs' shared one with this x its
#                    data's mean curvature (where its own takes say nothing, the shared one holds)


BRANCH_BOUNDS = ((0.0, 1.0), (-1.5, 1.5))  # (mix, kappa)


def _mix_terms(blk: _Block, p: np.ndarray, q: np.ndarray, branch: np.ndarray):
    """The response y (S, Ms) and its Jacobian J (S, F + 2, Ms) in the DU's density q (F,) and
    branch parameters (mix, kappa), the curves p (Ms, 3) held (numpy; the fitter's density step).

    y = sum_f q_f L(x_f; alpha, b_f), x_f = mix w + (1 - mix) P_f, w = sum_g q_g P_g,
    b_f = beta + s + kappa (f - fbar) r, fbar = sum_g q_g f_g."""
    fr = DENSITY_FRACTIONS
    H = blk.P.shape[1]
    r = p[:, 2]
    x = np.clip(fr[:, None] * r[None, :] / H_STEP, 0.0, H - 1 - 1e-9)  # (F, Ms)
    i0 = np.floor(x).astype(np.int64)
    lam = x - i0
    Q = blk.P[:, i0] * (1 - lam) + blk.P[:, np.minimum(i0 + 1, H - 1)] * lam  # (S, F, Ms)
    mix, kappa = float(branch[0]), float(branch[1])
    w = np.einsum("sfm,f->sm", Q, q)
    fbar = float(q @ fr)
    xf = mix * w[:, None] + (1.0 - mix) * Q
    off = kappa * (fr - fbar)  # (F,)
    al = p[None, None, :, 0]
    bb = p[None, None, :, 1] + blk.shift[:, None, None] + off[None, :, None] * r[None, None]
    sg = 1.0 / (1.0 + np.exp(np.clip(-al * (xf - bb), -700, 700)))
    lo = 1.0 / (1.0 + np.exp(np.clip(al * bb, -700, 700)))
    hi = 1.0 / (1.0 + np.exp(np.clip(-al * (255.0 - bb), -700, 700)))
    span = np.maximum(hi - lo, 1e-12)
    L = (sg - lo) / span
    dx = al * sg * (1.0 - sg) / span
    db = (-al * sg * (1 - sg) + al * lo * (1 - lo)) / span - L / span * (-al * hi * (1 - hi) + al * lo * (1 - lo))
    y = np.einsum("sfm,f->sm", L, q)
    Gx = np.einsum("sfm,f->sm", dx, q)
    Gb = np.einsum("sfm,f->sm", db, q)
    Jq = L + mix * Q * Gx[:, None] - kappa * fr[None, :, None] * r[None, None] * Gb[:, None]
    Jmix = np.einsum("sfm,f->sm", dx * (w[:, None] - Q), q)
    Jkap = np.einsum("sfm,f->sm", db * (fr - fbar)[None, :, None], q) * r[None]
    return y, np.concatenate([Jq, Jmix[:, None], Jkap[:, None]], axis=1)


def _density_problem(data: ModelData, model: FaceModel, takes, n: int, du: int):
    """A DU's Gauss-Newton model of the training cost in theta = (q (F,), mix, kappa):
    cost ~ theta^T A theta - 2 z^T theta + const; (A, z, (blk, p, act)) or None."""
    parts = _du_parts(data, model, takes, n, du)
    if parts is None:
        return None
    blk, p, act, y, dy, g, e = parts
    _, J = _mix_terms(blk, p, model.density[n], model.branch[n])
    gg = np.einsum("smx,smx->sm", g, g)
    ge = np.einsum("smx,smx->sm", g, e)
    A = np.einsum("sfm,sgm->fg", J * (blk.wt * gg)[:, None], J)
    b = np.einsum("sfm,sm->f", J, blk.wt * ge)
    theta = np.concatenate([model.density[n], model.branch[n]])
    return A, A @ theta + b, (blk, p, act)


def _theta_lsq(A: np.ndarray, z: np.ndarray) -> np.ndarray:
    """argmin theta^T A theta - 2 z^T theta over the density's simplex (q >= 0, sum 1) and the
    branch parameters' bounds (:data:`BRANCH_BOUNDS`)."""
    from scipy.optimize import lsq_linear

    F = DENSITY_FRACTIONS.size
    K = A.shape[0]
    scale = np.trace(A[:F, :F]) / F + 1e-300
    R = np.linalg.cholesky(A + 1e-8 * scale * np.eye(K))
    rhs = np.linalg.solve(R, z)  # min |R^T theta - rhs|^2 = theta^T A theta - 2 z^T theta + c
    big = 1e3 * np.sqrt(scale)
    row = np.concatenate([np.ones(F), np.zeros(K - F)])
    lo = np.concatenate([np.zeros(F), [b[0] for b in BRANCH_BOUNDS]])
    hi = np.concatenate([np.full(F, np.inf), [b[1] for b in BRANCH_BOUNDS]])
    sol = lsq_linear(np.vstack([R.T, big * row]), np.append(rhs, big), bounds=(lo, hi),
                     method="bvls")
    th = sol.x.copy()
    th[:F] = np.maximum(th[:F], 0.0)
    th[:F] /= max(th[:F].sum(), 1e-12)
    return th


def _turns_inside(data: ModelData, k: int) -> bool:
    """Whether take k's commands turn back inside the range (a minor loop), cached per take."""
    key = ("turns", k)
    if key not in data._tables:
        from mocap.analysis.model.effects import command_moves

        data._tables[key] = any(command_moves(g)[2] for _, g in data.takes[k].rows.groupby("du"))
    return data._tables[key]


def _has_minor_loops(data: ModelData, du: int, takes) -> bool:
    """Whether a single-DU take of ``du`` among ``takes`` turns back inside the range."""
    return any(data.takes[k].dus == (du,) and _turns_inside(data, k) for k in takes)


def _update_density(data: ModelData, model: FaceModel, takes):
    """One projected Gauss-Newton step of each DU's density q (F,) (q >= 0, sum 1) and branch
    parameters (mix, kappa), with a halving line search on the training cost; the curves held.

    Full sweeps say little of the density (they reverse where the sigmoid saturates): a DU
    without minor loops among its training takes borrows them from the DUs with some. The DUs
    share the skin's hysteresis in units of each curve's own width r: such a DU's density step
    is pulled towards the density of the DUs with minor loops (their Gauss-Newton problems
    summed, each normalised to its mean curvature) by SHARED_PULL x its own mean curvature; a
    DU with minor loops of its own keeps its own (without the pull, a DU's full sweeps spread its
    density to hold per-marker branch asymmetries, which predicts minor loops that are not flat
    after a reversal).

    Returns (density (N, F), branch (N, 2))."""
    F = DENSITY_FRACTIONS.size
    dens, br = model.density.copy(), model.branch.copy()
    probs = {}
    for n, du in enumerate(data.du_ids):
        pr = _density_problem(data, model, takes, n, du)
        if pr is not None:
            probs[n] = pr
    if not probs:
        return dens, br
    minor = {n: _has_minor_loops(data, data.du_ids[n], takes) for n in probs}
    teach = [n for n in probs if minor[n]] or list(probs)
    sc = {n: np.trace(A[:F, :F]) / F + 1e-300 for n, (A, _, _) in probs.items()}
    shared = _theta_lsq(sum(probs[n][0] / sc[n] for n in teach),
                        sum(probs[n][1] / sc[n] for n in teach))
    for n, (A, z, (blk, p, _)) in probs.items():
        # the density only: each DU keeps its own branch parameters (the shape of its forward
        # and backward branches, which its full sweeps do show); pulling them too read a
        # hidden coupling 20 % lower on a branch-play face
        mu = (0.0 if minor[n] else SHARED_PULL * sc[n]) * np.r_[np.ones(F), 0.0, 0.0]
        theta = np.concatenate([model.density[n], model.branch[n]])
        new = _theta_lsq(A + np.diag(mu), z + mu * shared)

        def cost(th, blk=blk, p=p, mu=mu):
            return _du_cost(blk, p, th, model.effects) + float(np.sum(mu * (th - shared) ** 2))

        c0 = cost(theta)
        for _ in range(5):
            if cost(new) < c0:
                dens[n], br[n] = new[:F], new[F:]
                break
            new = 0.5 * (theta + new)
    return dens, br


def _du_cost(blk: _Block, p: np.ndarray, theta: np.ndarray, effects) -> float:
    """A DU's training cost (mm^2) with its strong curves p (Ms, 3) and theta = (q (F,), mix,
    kappa), the path coefficients projected out."""
    F = DENSITY_FRACTIONS.size
    b = _Block(blk.P, blk.shift, blk.v, blk.wt, theta[:F], blk.trial, theta[F:])
    return float(np.sum(_project(b, _responses(b, p, True), effects, blk.v, blk.wt)[2]))


# ----------------------------------------------------------------------------------------------
# joint polish: Levenberg-Marquardt over a DU's curves and its branch parameters (and density)
# together, after the alternation

JOINT_ROUNDS = 2  # joint polish rounds of a warm fit with iters >= 30 and 2 rounds or more
JOINT_ITERS = 12  # joint steps per round at most
JOINT_TOL = 1e-6  # relative cost decrease of an accepted step below which a DU has converged


def _joint_normal(blk: _Block, p: np.ndarray, theta: np.ndarray, effects):
    """A DU's Gauss-Newton normal equations in its strong curves' (alpha, beta, r) and its
    (q (F,), mix, kappa), the linear path coefficients projected out (Kaufman's variable-projection
    Jacobian: each parameter's column taken off its curve's basis span).

    Returns (H (Ms, P, P), b (Ms, P)): per curve, the projected J^T W J and J^T W e over the
    columns (alpha, beta, r, q, mix, kappa); the DU's shared block is their sum over curves."""
    F = DENSITY_FRACTIONS.size
    blk_t = _Block(blk.P, blk.shift, blk.v, blk.wt, theta[:F], blk.trial, theta[F:])
    y, dy = _responses(blk_t, p, True, derivatives=True)
    _, Jt = _mix_terms(blk_t, p, theta[:F], theta[F:])  # (S, F + 2, Ms)
    coef, e, _ = _project(blk_t, y, effects, blk.v, blk.wt)
    A = _path_basis(y, effects)  # (S, Ms, k)
    g = _dpred_dy(y, coef, effects)
    Y = np.concatenate([dy, Jt.transpose(0, 2, 1)], axis=-1)  # (S, Ms, P): d y / d parameter
    w = blk.wt
    wg = g * w[..., None]  # (S, Ms, 3)
    UU = np.einsum("sm,smi,smj->mij", np.einsum("smx,smx->sm", g, wg), Y, Y, optimize=True)
    AU = np.einsum("smk,smx,smi->mxki", A, wg, Y, optimize=True)  # (Ms, 3, k, P)
    G = np.einsum("smk,sm,sml->mkl", A, w, A, optimize=True) + 1e-9 * np.eye(A.shape[-1])
    GiAU = np.linalg.solve(G[:, None], AU)
    H = UU - np.einsum("mxki,mxkj->mij", AU, GiAU, optimize=True)
    b = np.einsum("smi,sm->mi", Y, np.einsum("smx,smx->sm", wg, e), optimize=True)
    return H, b


def _joint_du(blk: _Block, p: np.ndarray, theta: np.ndarray, effects, free_density: bool,
              iters: int = JOINT_ITERS, tol: float = JOINT_TOL) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt over one DU's strong curves p (Ms, 3) and theta = (q (F,), mix, kappa)
    together (the density only with ``free_density``; on its simplex, the branch parameters in
    :data:`BRANCH_BOUNDS`). The normal equations are an arrowhead (a 3 x 3 block per curve, a
    dense border for theta): the curves are eliminated (Schur complement), theta's step solved
    under its constraints, the curves' steps substituted back. Returns (p, theta)."""
    F = DENSITY_FRACTIONS.size
    border = np.arange(3, 3 + F + 2) if free_density else np.arange(3 + F, 3 + F + 2)
    cost = _du_cost(blk, p, theta, effects)
    lam = 1e-3
    for _ in range(iters):
        H, b = _joint_normal(blk, p, theta, effects)
        Hpp, Hpt = H[:, :3, :3], H[:, :3][:, :, border]
        Htt = H[:, border][:, :, border].sum(axis=0)
        bp, bt = b[:, :3], b[:, border].sum(axis=0)
        step_taken = False
        while lam < 1e8:
            Hd = Hpp + lam * np.einsum("mii->mi", Hpp)[..., None] * np.eye(3) + 1e-12 * np.eye(3)
            Hinv = np.linalg.inv(Hd)
            W = np.einsum("mji,mjk->mik", Hpt, Hinv)  # (Ms, T, 3): Hpt^T Hpp^-1
            S = Htt + lam * np.diag(np.diag(Htt)) - np.einsum("mik,mkj->ij", W, Hpt)
            z = bt - np.einsum("mik,mk->i", W, bp)
            S = 0.5 * (S + S.T)
            new = theta.copy()
            if free_density:
                new = _theta_lsq(S, S @ theta + z)
            else:
                lo, hi = np.array(BRANCH_BOUNDS).T
                new[F:] = np.clip(theta[F:] + np.linalg.solve(S + 1e-12 * np.trace(S) * np.eye(2), z),
                                  lo, hi)
            dth = (new - theta)[border - 3]
            dp = np.einsum("mij,mj->mi", Hinv, bp - np.einsum("mij,j->mi", Hpt, dth))
            q = p + dp
            q[:, 0] = np.clip(q[:, 0], 1e-3, 0.5)
            q[:, 1] = np.clip(q[:, 1], -100.0, 355.0)
            q[:, 2] = np.clip(q[:, 2], 0.0, R_MAX)
            c_new = _du_cost(blk, q, new, effects)
            if c_new < cost:
                rel = (cost - c_new) / max(cost, 1e-300)
                p, theta, cost = q, new, c_new
                lam = max(lam / 4, 1e-9)
                step_taken = True
                break
            lam *= 6
        if not step_taken or rel < tol:
            break
    return p, theta


def _joint_round(data: ModelData, model: FaceModel, takes) -> None:
    """Every DU's strong curves and branch parameters by joint steps (:func:`_joint_du`), with
    its density too where its training takes hold minor loops (elsewhere the density stays as
    the alternation pulled it: full sweeps alone do not identify it); in place. The weak curves'
    shapes and every path coefficient are refitted after (by the caller)."""
    F = DENSITY_FRACTIONS.size
    for n, du in enumerate(data.du_ids):
        parts = _du_parts(data, model, takes, n, du)
        if parts is None:
            continue
        blk, p, act = parts[:3]
        theta = np.concatenate([model.density[n], model.branch[n]])
        p_new, th = _joint_du(blk, p, theta, model.effects, _has_minor_loops(data, du, takes))
        model.alpha[n, act], model.beta[n, act], model.r[n, act] = p_new.T
        model.density[n], model.branch[n] = th[:F], th[F:]
