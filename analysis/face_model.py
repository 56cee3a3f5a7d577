"""The face model: every marker's 3D position for any command time series on any set of DUs.

The paper's static model, with a rule for reversals, plus composable effects
(:mod:`mocap.analysis.model_effects`). For DU n and marker m (summed over the DUs of a take)::

    a_n(t)   = actuator-stage effects of the command c_n(t)       (identity in the base model)
    P_nmf(t) = play_{r_nm f}[a_n](t)      plays of half-widths r_nm f, f in DENSITY_FRACTIONS
               (0, .25, ..., 2), from rest (r = 0 without ``hysteresis``)
    w_nm(t)  = sum_f q_nf P_nmf(t)        their Prandtl-Ishlinskii operator with a DENSITY q_nf >= 0
               summing to 1 per DU (identified; the paper-model's equal plays at f = 0, .5, 1,
               1.5, 2 are the default)
    y_nm(t)  = sum_f q_nf L(mix_n w + (1 - mix_n) P_nmf;
                            alpha_nm, beta_nm + s + kappa_n (f - fbar_n) r_nm)
               L(x; alpha, b) = (S(x) - S(0)) / (S(255) - S(0)),  S(x) = 1 / (1 + exp(-alpha (x - b)))
               fbar_n = sum_f q_nf f;  s = the effects' bias shifts for the take's trial + the
               take's own shift s_kn (``takeshift``: one per take and DU, identified on the take)
               (mix, kappa) per DU, the BRANCH parameters: with mix = 1, kappa = 0 this is the
               logistic of the PI operator, L(w); with mix = 0 a density-weighted mean of
               sigmoids of plays (a Preisach operator: on each width, relays whose centres are
               spread logistically around that play's own centre), kappa > 0 putting the wide plays' centres later (a shallow
               forward branch and a steep backward one), kappa < 0 the other way
    y       -> interact(y)                                   (several DUs at once)
    d_m(t)   = sum_n [y_nm D_nm + sum_k b_k(y_nm) B_nmk]      each marker's own path
               (``curvature``: b = 4 y (1 - y), 6 sqrt 3 y (1 - y) (1 - 2 y), 16 y^2 (1 - y)^2)
             + sum_{n < n'} y_nm y_n'm C_nn'm                 (``coupling``: a 3D vector per DU
                                                               pair driven together and marker)
    x_m(t)   = rest_m + output(d_m(t))                        (``saturation``)

The base model of the discrepancy workflow (``model_effects.BASE``) is ``hysteresis`` (the
density and the branch parameters), ``curvature`` (each marker's path, any quartic in y through
rest: bows, paths that end off the chord, a per-DU compression of the displacement) and ``takeshift``: what every face has,
so that a face with no missing effect fits to its noise floor whatever its hysteresis operator
and path shape.

The rule for reversals is the PI operator's: on a full sweep 0 -> 255 -> 0 the forward branch is
the logistic of about c - r sum q f and the backward one of about c + r sum q f (loop width
2 r sum_f q_f f); after a reversal inside the range the response moves at once with the weight
of the narrow plays and steepens as wider plays release (Preisach minor loops); a density on one
width is a branch play (flat after a reversal until the other branch), a spread one follows
smooth (Bouc-Wen-like) loops. The branch parameters shape the two branches apart: a Preisach
face whose wide relays switch later (shallow forward, steep backward branch) is
mix ~ 0.2, kappa ~ 0.5; a single sigmoid of the PI output has one steepness on both.

Time: commands are sampled per FORMAT.md on a grid ``OVERSAMPLE`` times finer than the frames
(for the actuator dynamics and the plays); responses are read at the frames.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd

from mocap.analysis.hysteresis_fit import PLAY_FRACTIONS
from mocap.analysis.model_effects import CATALOGUE, Effect
from mocap.analysis.play_kernel import pi_logistic_from_table, play_table
from mocap.schedules import sample_commands

OVERSAMPLE = 4
R_MAX = 80.0  # largest play width r, command units (the table holds half-widths up to 2 r); the
#               simulator's DU 4 has markers with loop half-widths of 77 (48 cut them: a
#               branch-play face's held-out RMS 1.69 -> 1.22 x the noise floor with 80)
# the PI density's grid: play half-widths / r; the paper-model's equal plays sit on every second
DENSITY_FRACTIONS = np.round(np.arange(0.0, 2.0001, 0.25), 6)  # (F,)
PI_BRANCH = np.array([1.0, 0.0])  # (mix, kappa) of the PI form: one sigmoid of the PI output
EQUAL_DENSITY = np.where(np.isin(DENSITY_FRACTIONS, PLAY_FRACTIONS), 1.0 / PLAY_FRACTIONS.size, 0.0)


def actuator_effects(effects) -> list[Effect]:
    return sorted((e for e in effects if type(e).stage == "actuator"), key=lambda e: type(e).order)


def actuator_series(rows: pd.DataFrame, dus, n_frames: int, fps: float, effects) -> np.ndarray:
    """Actuator input (n_frames * OVERSAMPLE, n_dus) of a take, command units, fine grid."""
    t = np.arange(n_frames * OVERSAMPLE) / (fps * OVERSAMPLE)

    def sampler(times):
        return sample_commands(rows, list(dus), times)

    a = sampler(t)
    for e in actuator_effects(effects):
        a = e.actuator(a, t, sampler)
    return a


def take_tables(rows: pd.DataFrame, dus, n_frames: int, fps: float, effects,
                stride: int = 1) -> list[np.ndarray]:
    """Play tables, one (ceil(n_frames / stride), H) array per DU of ``dus``, frames 0, stride, ...

    The actuator dynamics run on the fine grid; the plays on the frames (exact for commands held
    at least a frame, as FORMAT.md's step times are; within 0.005 mm with a lag, tested).
    """
    a = actuator_series(rows, dus, n_frames, fps, effects)[::OVERSAMPLE]
    return [play_table(a[:, j], keep_every=stride) for j in range(a.shape[1])]


def _sum_over_dus(y: np.ndarray, V: np.ndarray) -> np.ndarray:
    """sum_n y[s, n, m] V[n, m, k] -> (S, M, 3): y (S, N, M), V (N, M, 3). One batched matrix
    product per marker (the einsum's loop took 2-4 x longer on the design's small blocks)."""
    return np.matmul(y.transpose(2, 0, 1), V.transpose(1, 0, 2)).transpose(1, 0, 2)


@dataclass
class FaceModel:
    """An identified face model (plain arrays; see the module docstring for the equations).

    Attributes
    ----------
    fps : frame rate the model predicts at, frames/s.
    marker_names : (M,) names.  rest_mm : (M, 3) rest positions, mm.
    du_ids : (N,) DU ids.
    active : (N, M) bool, the markers each DU moves (others get no displacement from it).
    alpha : (N, M) 1/command unit.  beta : (N, M) command units.  r : (N, M) play width,
        command units (0 without hysteresis).
    D : (N, M, 3) mm, the displacement at full response.
    B : (N, M, K, 3) mm, the path-basis vectors (K = total extra bases of the effects).
    effects : the model's effects (the base model of the paper has ``hysteresis`` only).
    density : (N, F) each DU's weights of the plays at DENSITY_FRACTIONS (sum 1).
    branch : (N, 2) each DU's (mix, kappa), dimensionless (default PI_BRANCH: L of the PI output).
    """

    fps: float
    marker_names: tuple[str, ...]
    rest_mm: np.ndarray
    du_ids: tuple[int, ...]
    active: np.ndarray
    alpha: np.ndarray
    beta: np.ndarray
    r: np.ndarray
    D: np.ndarray
    B: np.ndarray
    effects: tuple[Effect, ...] = ()
    info: dict = field(default_factory=dict)
    density: np.ndarray | None = None
    take_shifts: dict = field(default_factory=dict)  # take name -> {DU id: bias shift}
    pairs: tuple[tuple[int, int], ...] = ()
    C: np.ndarray | None = None
    C2: np.ndarray | None = None  # (P, 2, M, 3) mm: the pairs' second order (pair_features)
    branch: np.ndarray | None = None  # (N, 2) per DU: (mix, kappa), see the module docstring

    def __post_init__(self) -> None:
        if self.density is None:
            self.density = np.tile(EQUAL_DENSITY, (len(self.du_ids), 1))
        if self.branch is None:
            self.branch = np.tile(PI_BRANCH, (len(self.du_ids), 1))
        if self.C is None:
            self.C = np.zeros((len(self.pairs), len(self.marker_names), 3))

    @property
    def effect_names(self) -> list[str]:
        return [type(e).name for e in self.effects]

    def effect(self, name: str) -> Effect | None:
        for e in self.effects:
            if type(e).name == name:
                return e
        return None

    @property
    def hysteresis(self) -> bool:
        return any(type(e).frees_r for e in self.effects)

    def with_effects(self, effects) -> "FaceModel":
        return replace(self, effects=tuple(effects))

    # -- prediction ---------------------------------------------------------------------------
    def bias_shift(self, trial) -> np.ndarray | float:
        return sum((e.beta_shift(trial) for e in self.effects), 0.0)

    @property
    def shifts_takes(self) -> bool:
        """Whether the model holds a bias shift per take and DU (the ``takeshift`` base effect)."""
        return self.effect("takeshift") is not None

    def loop_width(self) -> np.ndarray:
        """Full-sweep loop width (N, M) of each curve, command units: 2 r x the density's mean
        fraction (the forward branch runs at c - r sum_f q_f f, the backward one at c + ...)."""
        return 2.0 * self.r * (self.density @ DENSITY_FRACTIONS)[:, None]

    def response(self, tables: list[np.ndarray], dus, trial, take_shift=None) -> np.ndarray:
        """Normalised responses y (S, n_take_dus, M) from the take's play tables.

        take_shift : (n_take_dus,) the take's own bias shift per DU, command units (None: 0).
        """
        S = tables[0].shape[0] if tables else 0
        y = np.zeros((S, len(dus), len(self.marker_names)))
        base = np.broadcast_to(np.asarray(self.bias_shift(trial), float), (S,))
        for j, du in enumerate(dus):
            shift = base if take_shift is None else base + float(take_shift[j])
            if du not in self.du_ids:
                continue
            n = self.du_ids.index(du)
            act = np.flatnonzero(self.active[n])
            if act.size == 0:
                continue
            # the weak curves share their DU's median shape: each distinct curve computed once
            par, inv = np.unique(np.stack([self.r[n, act], self.alpha[n, act], self.beta[n, act]]),
                                 axis=1, return_inverse=True)
            y[:, j, act] = pi_logistic_from_table(tables[j], par[0], par[1], par[2], shift,
                                                  DENSITY_FRACTIONS, weights=self.density[n],
                                                  mix=self.branch[n, 0],
                                                  kappa=self.branch[n, 1])[:, inv.ravel()]
        return y

    def displacement_from_response(self, y: np.ndarray, dus) -> np.ndarray:
        """Displacements (S, M, 3) mm from normalised responses y (S, n_take_dus, M)."""
        rows = [self.du_ids.index(d) if d in self.du_ids else -1 for d in dus]
        keep = [i for i, r in enumerate(rows) if r >= 0]
        y = y[:, keep]
        rows = [rows[i] for i in keep]
        M = len(self.marker_names)
        if not rows:
            return np.zeros((y.shape[0], M, 3))
        D = self.D[rows]
        y_eff = y
        for e in self.effects:
            y_eff = e.interact(y_eff, D)
        d = _sum_over_dus(y_eff, D)
        if self.pairs:
            d = d + pair_terms(y, [self.du_ids[r] for r in rows], self.pairs, self.C, self.C2)
        k = 0
        for e in self.effects:
            for basis in e.bases(y_eff):  # the path is followed to where the response got
                d = d + _sum_over_dus(basis, self.B[rows, :, k])
                k += 1
        for e in self.effects:
            d = e.output(d)
        return d

    def predict_tables(self, tables, dus, trial, take_shift=None) -> np.ndarray:
        return self.displacement_from_response(self.response(tables, dus, trial, take_shift), dus)

    def predict(self, rows: pd.DataFrame, n_frames: int, trial: int = 1) -> np.ndarray:
        """Marker positions (n_frames, M, 3) mm for a command schedule (FORMAT.md rows).

        DUs of ``rows`` the model does not know are ignored; a take without commands rests.
        """
        dus = sorted(int(d) for d in pd.unique(rows["du"])) if len(rows) else []
        if not dus:
            return np.broadcast_to(self.rest_mm, (n_frames, len(self.marker_names), 3)).copy()
        tables = take_tables(rows, dus, n_frames, self.fps, self.effects)
        return self.rest_mm + self.predict_tables(tables, dus, trial)

    # -- summaries ------------------------------------------------------------------------------
    def parameters(self) -> dict:
        """Each effect's main parameter (median over curves for per-curve effects)."""
        out = {}
        for e in self.effects:
            cls = type(e)
            if cls.name == "hysteresis":
                out[cls.parameter] = float(np.median(self.loop_width()[self.active]))
            elif cls.name == "coupling" and self.pairs:
                out[cls.parameter] = float(self.info.get("coupling_kappa", pair_kappa(self)))
            elif cls.name == "curvature":
                out[cls.parameter] = bow_ratio(self)
            else:
                out[cls.parameter] = float(e.describe()["value"])
        return out


def pair_features(y: np.ndarray, dus, pairs, order: int = 1) -> tuple[list[int], np.ndarray]:
    """The pairwise interaction features of a take's DUs ``dus`` for the model's ``pairs``
    present in the take, and their indices into ``pairs``: y_n y_n' (S, P_take, M) for
    ``order`` 1; for ``order`` 2 (S, P_take, 3, M): y_n y_n', then y_n^2 y_n' and y_n y_n'^2,
    the first order of how the interaction changes with each drive (a coupling of any smooth
    shape g(y_n, y_n') that vanishes when either DU rests, g = y_n y_n' h, to first order in h)."""
    pos = {d: i for i, d in enumerate(dus)}
    idx = [k for k, (a, b) in enumerate(pairs) if a in pos and b in pos]
    shape = (y.shape[0], 0, y.shape[2]) if order == 1 else (y.shape[0], 0, 3, y.shape[2])
    if not idx:
        return [], np.zeros(shape)
    ya = np.stack([y[:, pos[pairs[k][0]]] for k in idx], axis=1)
    yb = np.stack([y[:, pos[pairs[k][1]]] for k in idx], axis=1)
    F = ya * yb
    if order == 1:
        return idx, F
    return idx, np.stack([F, F * ya, F * yb], axis=2)


def pair_terms(y: np.ndarray, dus, pairs, C: np.ndarray, C2: np.ndarray | None = None) -> np.ndarray:
    """Sum over the take's DU pairs of y_n y_n' C_pair,m (S, M, 3) mm, plus y_n^2 y_n' C2_0 +
    y_n y_n'^2 C2_1 where the model holds the second order C2 (P, 2, M, 3); y (S, n_dus, M)."""
    idx, F = pair_features(y, dus, pairs, order=1 if C2 is None else 2)
    if not idx:
        return np.zeros((y.shape[0], y.shape[2], 3))
    if C2 is None:
        return np.einsum("spm,pmk->smk", F, C[idx])
    Call = np.concatenate([C[idx][:, None], C2[idx]], axis=1)  # (P_take, 3, M, 3)
    return np.einsum("sprm,prmk->smk", F, Call)


def pair_kappa(model: FaceModel) -> float:
    """The coupling's kappa read from the fitted pair vectors: the fraction of a DU's displacement
    lost while another DU is at full command, at the markers most in the other DU's field.

    Per pair and marker, C_m = -(a_m D_nm + b_m D_n'm) by least squares gives the fractions lost
    by each DU; two laws are fitted to them, weighted by |D|^2: a_m = kappa o_n'm (the loss
    grows with the other DU's relative pull o = |D_n'm| / max_m |D_n'm|) and a_m = kappa (the
    same at every marker); the better fit's kappa is returned (both laws agree on it where
    o = 1, the marker most in the other DU's field)."""
    if not model.pairs or model.C is None:
        return 0.0
    # the loss with both DUs at full command: the first order plus the second's two terms
    C_full = model.C if model.C2 is None else model.C + model.C2.sum(axis=1)
    mag = np.linalg.norm(model.D, axis=-1)
    o = mag / np.maximum(mag.max(axis=1, keepdims=True), 1e-12)
    loss, pull, wt = [], [], []
    for k, (a, b) in enumerate(model.pairs):
        i, j = model.du_ids.index(a), model.du_ids.index(b)
        A = -np.stack([model.D[i], model.D[j]], axis=-1)  # (M, 3, 2)
        G = np.einsum("mxp,mxq->mpq", A, A)
        ok = (model.active[i] & model.active[j] & (np.linalg.det(G) >
                                                   1e-6 * np.einsum("mpp->m", G) ** 2 + 1e-18))
        if not ok.any():
            continue
        f = np.linalg.solve(G[ok], np.einsum("mxp,mx->mp", A[ok], C_full[k, ok])[..., None])[..., 0]
        loss += [f[:, 0], f[:, 1]]
        pull += [o[j, ok], o[i, ok]]
        wt += [mag[i, ok] ** 2, mag[j, ok] ** 2]
    if not loss:
        return 0.0
    a, p, w = np.concatenate(loss), np.concatenate(pull), np.concatenate(wt)
    k1 = float(np.sum(w * a * p) / max(np.sum(w * p * p), 1e-300))
    k2 = float(np.sum(w * a) / max(np.sum(w), 1e-300))
    sse1 = float(np.sum(w * (a - k1 * p) ** 2))
    sse2 = float(np.sum(w * (a - k2) ** 2))
    return k1 if sse1 <= sse2 else k2


def bow_ratio(model: FaceModel) -> float:
    """Median over active curves of |B| / |D| (the mid-range bow per unit displacement),
    weighted towards well-measured curves (|D| >= half the DU's largest)."""
    if model.B.shape[2] == 0:
        return 0.0
    magD = np.linalg.norm(model.D, axis=-1)
    big = model.active & (magD >= 0.5 * magD.max(axis=1, keepdims=True))
    ratio = np.linalg.norm(model.B[:, :, 0], axis=-1) / np.maximum(magD, 1e-12)
    return float(np.median(ratio[big])) if big.any() else 0.0


def make_effects(names) -> tuple[Effect, ...]:
    """Effects by name (default parameter values 0), e.g. ``make_effects(["hysteresis"])``."""
    out = []
    for n in names:
        if n not in CATALOGUE:
            raise ValueError(f"face model: unknown effect {n!r} (known: {', '.join(CATALOGUE)})")
        out.append(CATALOGUE[n]())
    return tuple(out)


def n_bases(effects) -> int:
    return int(sum(type(e).n_bases for e in effects))
