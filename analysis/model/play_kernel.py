"""Compiled (numba) play-operator tables: the output of many play operators of different
half-widths on one input series, in one pass.

A Prandtl-Ishlinskii response of any width ``r`` is then a weighted sum of table columns
(:func:`pi_logistic_from_table`): fitting a width per marker needs no play loop at all (the table is computed
once per actuator series), which is what makes the face model's identification fast.
"""

from __future__ import annotations

import numpy as np
from numba import njit

H_STEP = 0.5  # command units between table columns
H_MAX = 165.0  # largest half-width in the table (PI widths r <= H_MAX / 2)
HALFWIDTHS = np.arange(0.0, H_MAX + 1e-9, H_STEP)  # (H,)


@njit(cache=True)
def _play_table(a, h, keep_every, out):
    T = a.shape[0]
    H = h.shape[0]
    for j in range(H):
        y = 0.0
        hj = h[j]
        k_out = 0
        for k in range(T):
            lo = a[k] - hj
            hi = a[k] + hj
            if y < lo:
                y = lo
            elif y > hi:
                y = hi
            if k % keep_every == 0:
                out[k_out, j] = y
                k_out += 1


def play_table(a: np.ndarray, keep_every: int = 1, halfwidths: np.ndarray = HALFWIDTHS) -> np.ndarray:
    """Outputs of plays of every half-width on ``a``, from rest (initial output 0).

    Parameters
    ----------
    a : (T,) input series (command units), in time order.
    keep_every : keep every k-th sample of the output (the plays run on every input sample).
    halfwidths : (H,) play half-widths, command units.

    Returns
    -------
    (ceil(T / keep_every), H) float64 outputs, command units.
    """
    a = np.ascontiguousarray(a, dtype=np.float64)
    h = np.ascontiguousarray(halfwidths, dtype=np.float64)
    n_out = (a.shape[0] + keep_every - 1) // keep_every
    out = np.empty((n_out, h.shape[0]))
    _play_table(a, h, int(keep_every), out)
    return out


@njit(cache=True)
def _stick_slip(a, halfwidth, out):
    T, n = a.shape
    for j in range(n):
        held = 0.0  # from rest, last motion upwards
        d = 1.0
        for k in range(T):
            x = a[k, j]
            if (x - held) * d >= 0.0:
                held = x
            elif abs(x - held) >= 2.0 * halfwidth:
                d = -d
                held = x
            out[k, j] = held


def stick_slip(a: np.ndarray, halfwidth: float) -> np.ndarray:
    """Stick-slip dead band of half-width ``halfwidth`` (command units) on inputs a (T, n) in
    time order, from rest: the output follows the input while it keeps going the same way;
    after a reversal it holds until the input has come back 2 halfwidth, then jumps to it (no
    lasting offset, unlike a play). Returns (T, n) float64, command units."""
    a2 = np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape(len(a), -1))
    out = np.empty_like(a2)
    _stick_slip(a2, float(halfwidth), out)
    return out.reshape(np.shape(a))


@njit(cache=True)
def _pi_logistic(P, i0, lam_i, fr, wf, h_step, r, alpha, beta, shift, mix, kappa, want, y, dy):
    S, H = P.shape
    nf, M = i0.shape
    fbar = 0.0
    for f in range(nf):
        fbar += wf[f] * fr[f]
    pi_form = mix == 1.0 and kappa == 0.0
    pf = np.empty(nf)
    dpf = np.empty(nf)
    # each play's normalisation L(0), L(255) depends on the sample only through its shift, which
    # is constant over a take: computed where the shift changes, reused (the same numbers)
    bc = np.empty((M, nf))
    loc = np.empty((M, nf))
    hic = np.empty((M, nf))
    spc = np.empty((M, nf))
    for s in range(S):
        fresh = s == 0 or shift[s] != shift[s - 1]
        for m in range(M):
            w = 0.0
            dw = 0.0
            for f in range(nf):
                j = i0[f, m]
                a0 = P[s, j]
                a1 = P[s, j + 1] if j + 1 < H else a0
                pf[f] = a0 + lam_i[f, m] * (a1 - a0)
                dpf[f] = fr[f] * (a1 - a0) / h_step
                w += wf[f] * pf[f]
                dw += wf[f] * dpf[f]
            al = alpha[m]
            yy = 0.0
            da = 0.0
            db = 0.0
            dr = 0.0
            for f in range(nf):
                if wf[f] == 0.0 or (pi_form and f > 0):
                    continue
                if pi_form:  # one sigmoid of the density's mean
                    x = w
                    dx = dw
                    off = 0.0
                    q = 1.0
                else:
                    x = mix * w + (1.0 - mix) * pf[f]
                    dx = mix * dw + (1.0 - mix) * dpf[f]
                    off = kappa * (fr[f] - fbar)
                    q = wf[f]
                if fresh:
                    b = beta[m] + shift[s] + off * r[m]
                    zl = al * b
                    zh = -al * (255.0 - b)
                    lo = 1.0 / (1.0 + np.exp(min(max(zl, -700.0), 700.0)))
                    hi = 1.0 / (1.0 + np.exp(min(max(zh, -700.0), 700.0)))
                    span = max(hi - lo, 1e-12)
                    bc[m, f] = b
                    loc[m, f] = lo
                    hic[m, f] = hi
                    spc[m, f] = span
                else:
                    b = bc[m, f]
                    lo = loc[m, f]
                    hi = hic[m, f]
                    span = spc[m, f]
                zs = -al * (x - b)
                sg = 1.0 / (1.0 + np.exp(min(max(zs, -700.0), 700.0)))
                yf = (sg - lo) / span
                yy += q * yf
                if want:
                    ss = sg * (1.0 - sg)
                    ll = lo * (1.0 - lo)
                    hh = hi * (1.0 - hi)
                    ds_a = ss * (x - b)
                    ds_b = -al * ss
                    dl_a = ll * (-b)
                    dl_b = -al * ll
                    dh_a = hh * (255.0 - b)
                    dh_b = -al * hh
                    dyb = (ds_b - dl_b) / span - yf / span * (dh_b - dl_b)
                    da += q * ((ds_a - dl_a) / span - yf / span * (dh_a - dl_a))
                    db += q * dyb
                    dr += q * (al * ss / span * dx + dyb * off)
            y[s, m] = yy
            if want:
                dy[s, m, 0] = da
                dy[s, m, 1] = db
                dy[s, m, 2] = dr


def pi_logistic_from_table(P: np.ndarray, r: np.ndarray, alpha: np.ndarray, beta: np.ndarray,
                           shift: np.ndarray | None = None, fractions=None,
                           derivatives: bool = False, weights=None, mix: float = 1.0,
                           kappa: float = 0.0):
    """Normalised response of the plays of width r, read from a play table.

    With ``mix`` = 1 and ``kappa`` = 0 (the default) the logistic of the PI operator,
    L(sum_f q_f play_{f r}); else the density-weighted mean of logistics of blended plays,
    sum_f q_f L(mix w + (1 - mix) play_{f r}; alpha, beta + kappa (f - fbar) r), w the PI
    output and fbar = sum_f q_f f (see :mod:`mocap.analysis.model.face_model`).

    P : (S, H) play table (:func:`play_table`).  r, alpha, beta : (M,) per curve (command units,
    1/command unit, command units).  shift : (S,) bias shift per sample (command units) or None.
    fractions : (F,) play half-widths / r (default the model's 0, .5, 1, 1.5, 2).
    weights : (F,) the plays' weights (the PI density; default equal, 1 / F each).
    mix : 0..1, the PI operator's share in each play's input.  kappa : how far a play's
    sigmoid centre moves per unit of its width (dimensionless; 0: all centred on beta).

    Returns y (S, M) and, with ``derivatives``, dy/d(alpha, beta, r) (S, M, 3).
    """
    from mocap.analysis.paper.hysteresis_fit import PLAY_FRACTIONS

    fr = np.asarray(PLAY_FRACTIONS if fractions is None else fractions, float)
    r = np.asarray(r, float)
    H = P.shape[1]
    x = np.clip(fr[:, None] * r[None, :] / H_STEP, 0.0, H - 1 - 1e-9)
    i0 = np.floor(x).astype(np.int64)
    lam = x - i0
    S, M = P.shape[0], r.size
    y = np.empty((S, M))
    dy = np.empty((S, M, 3)) if derivatives else np.empty((1, 1, 3))
    wf = (np.full(fr.size, 1.0 / fr.size) if weights is None
          else np.ascontiguousarray(weights, float))
    sh = np.zeros(S) if shift is None else np.ascontiguousarray(np.broadcast_to(shift, (S,)), float)
    _pi_logistic(np.ascontiguousarray(P, float), i0, lam, fr, wf, H_STEP, np.ascontiguousarray(r),
                 np.ascontiguousarray(alpha, float), np.ascontiguousarray(beta, float), sh,
                 float(mix), float(kappa), derivatives, y, dy)
    return (y, dy) if derivatives else y
