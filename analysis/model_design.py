"""Motion design through the identified face model (issue #11): commands that make the markers
follow a plan, found by optimising the command sequence through the whole model.

The paper designs commands by inverting full-sweep sigmoids (:func:`mocap.analysis.design.paper_design`):
it knows nothing of reversals inside the range (minor loops), actuator dynamics (lag, dead time,
backlash) or several DUs acting at once. Here the command of every DU at every command step is
chosen so that the model's predicted normalised displacement of the chosen markers follows the
reference (the plan), by a causal search (model predictive control over integer commands):

    at step i, for each DU n in turn (the others hold their latest commands), over candidate
    integer commands c (0..255 every 8, then the 15 around the best):
        simulate the model from its current state with c held over steps i .. i + preview - 1,
        at ``SUBSTEPS`` points per step (vectorised over candidates and markers)
        cost(c) = sum_points [ (sum_m w_m e_m)^2 + spread_weight sum_m w_m e_m^2 ],
        e_m = |d_m(t)| / n_m - r_m(t)
    keep the best c, advance the model's state over step i with every DU's choice.

The preview (:func:`default_preview`): with an actuator lag or a dead time a command shows in
the markers mostly after the step it is sent in, and a greedy pass (preview 1) drives it as if
it did not; holding the candidate over two steps and scoring both lets the pass see where it
leads. On a face that responds at once the same preview holds each command over a step it does
not belong to, so the default is 2 where the model has a lag or a dead time and 1 otherwise.

Optional later passes (``sweeps``) score step i's command over a longer ``horizon`` with the
following steps at the previous pass's commands (Gauss-Seidel on the whole plan's cost), which
lets a command anticipate where a later one saturates.

d_m is the model's displacement of marker m (every effect of the model: coupling, curvature and
saturation act on the stacked responses of the DUs), n_m its displacement at full motion (the
steady response to 255 - ``headroom``: the evaluation normalises each marker by its own largest
displacement, so the design may call a slightly smaller motion "1" and keep some command in hand
to drive a lagging actuator towards it), r_m(t) the reference (the plan's ideal, the same for
every marker; per marker in a refinement) and w_m the marker weights (:func:`marker_weights`).
The markers' mean follows the plan (what the evaluation measures); their spread around it is
mostly beyond any command, and with several DUs decides how they share the work. That share
matters even though only the mean is scored: the evaluation normalises each marker by its own
largest displacement in the take, so a DU driven past its share for a moment and backed off
later (the mean held by another DU) leaves its markers below 1 for the rest of the take. With a
weak spread term (0.05) the search traded work between DUs at the end of a fast rise (DU 7 at
207, then 45; its markers held at 0.95 of their peak): plan E on a Bouc-Wen bowed face with a
hidden second-order lag (0.08 s) tracked at 0.37 of the paper method's RMS; with 0.2, 0.11
(plan A 0.18 either way; benchmarks/design_sweep.md).

The model's state is stepped exactly between command steps: a command held over a step drives
the actuator monotonically (first-order lag: a(t) = c + (a0 - c) exp(-t / tau)), so every
play operator (backlash, the Prandtl-Ishlinskii plays of the skin) at any point inside the step
is the clip of its state at the step's start; a dead time L shifts the reference by L instead
(the command of step i acts from t_i + L). The lag and the dead band are inverted this way
through the search; hysteresis under arbitrary reversals is the model's own. Python loops run
over command steps and DUs only; everything per candidate, point and marker is vectorised.

The hold (:func:`design_plan`): the evaluation normalises each marker by its plateau, the mean
of its displacement over the frames within 5 % of its largest, and those frames include the top
of the rise and the start of the fall, so a take that follows the plan exactly reads above it
on the hold and the upper rise. Where that matters depends on the marker paths (on a bowed path
|d| can pass its final value during the rise), so a plan's first design is made for a few hold
levels and the one whose take the model predicts to score best is kept.

Iterative refinement (:func:`refined_reference`) is reference-adaptation iterative learning
control: a played take's tracking error updates the reference the model tracks,
r_{k+1}(t) = r_k(t) + gain sum_m w'_m (P(t) - delta_m(t)) over the plan's rise and fall, with
r_k the previous reference (or, without one, the model's own prediction of the played commands),
delta_m read without the bias of noise (:func:`debiased_delta`) and w'_m the design's weights
times each marker's signal to noise; the commands are then designed again through the model.
The signal-to-noise weights keep the small markers' noise out, but a mean in other weights than
the design's is another mean: the markers differ in timing and path, so it learns another error
(on a Preisach off-chord face, plan A with 0.03 mm noise, refinement went 0.209 -> 0.23 of the
paper method's RMS while noise-free plays reached 0.19). The model's prediction of the played
commands is therefore used as a control variate: its error against the plan is taken in the
design's weights (noise-free) and only the model's error, delta_m - prediction_m, which is far
more alike across markers, is read from the noisy take in the signal-to-noise weights (the same
case: 0.195 after one play, 0.19-0.194 after more, as noise-free; noise-free plays are unchanged,
the two weights being equal there).

Times in s, commands in command units (integers 0..255), displacements in mm; a reference is
dimensionless (0 at rest, 1 at the plan's full motion).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from mocap.analysis.design import PlanTiming
from mocap.analysis.face_model import DENSITY_FRACTIONS, FaceModel
from mocap.analysis.hysteresis_fit import normalized_logistic
from mocap.analysis.plans import PLAN_NAMES

SUBSTEPS = np.array([1.0 / 3.0, 2.0 / 3.0, 1.0])  # points per command step where the cost is read
COARSE = 8  # coarse candidate spacing, command units (then +-COARSE-1 around the best)
SELECT_S = 0.5  # longest smoothing that picks a measured take's plateau (debiased_delta)
SNR_NOISE = 20.0  # a marker teaches the refinement with weight s^2 / (s^2 + (SNR_NOISE noise)^2)


# ----------------------------------------------------------------------------------------------
# references


@dataclass(frozen=True)
class Reference:
    """What the markers should do: a normalised displacement over time.

    t_s : (T,) increasing times, s from the take's first frame.
    r : (T,) the same for every marker, or (T, M) per marker of the model (NaN: no target).
    ideal : (T,) what the evaluation compares the take with (the plan's ideal).
    rise, fall : (start_s, end_s) of the parts evaluated as forward and backward motion.
    start_s : when the motion starts (no command before it).  end_s : the take's length.
    label : the plan's name (A-E) or the file it came from.
    """

    t_s: np.ndarray
    r: np.ndarray
    ideal: np.ndarray
    rise: tuple[float, float]
    fall: tuple[float, float]
    start_s: float
    end_s: float
    label: str

    def at(self, t_s: np.ndarray, n_markers: int) -> np.ndarray:
        """Reference (len(t_s), n_markers) at times t_s (held outside the table)."""
        t_s = np.asarray(t_s, float)
        if self.r.ndim == 1:
            v = np.interp(t_s, self.t_s, self.r)
            return np.broadcast_to(v[:, None], (t_s.size, n_markers)).copy()
        idx = np.clip(np.searchsorted(self.t_s, t_s, side="right") - 1, 0, self.t_s.size - 2)
        lam = np.clip((t_s - self.t_s[idx]) / (self.t_s[idx + 1] - self.t_s[idx]), 0.0, 1.0)
        return self.r[idx] * (1.0 - lam[:, None]) + self.r[idx + 1] * lam[:, None]

    def with_markers(self, r: np.ndarray) -> "Reference":
        return Reference(self.t_s, r, self.ideal, self.rise, self.fall, self.start_s, self.end_s,
                         self.label)


def plan_reference(plan: str, timing: PlanTiming = PlanTiming(), dt_s: float = 0.002) -> Reference:
    """The ideal of plan A-E (rest, P rising, hold, 1 - P, rest), as :meth:`PlanTiming.ideal`,
    except that the hold is the full motion 1 (plans B and D end their rise at 0.993; the
    evaluation normalises each marker by its largest displacement, which is the hold's)."""
    if plan.upper() not in PLAN_NAMES:
        raise ValueError(f"motion plan: expected one of {', '.join(PLAN_NAMES)}, got {plan!r}")
    t = np.arange(0.0, timing.total_s + dt_s, dt_s)
    back = timing.start_s + timing.duration_s + timing.hold_s
    ideal = timing.ideal(t, plan.upper())
    r = np.where((t >= timing.start_s + timing.duration_s) & (t < back), 1.0, ideal)
    return Reference(t, r, ideal,
                     (timing.start_s, timing.start_s + timing.duration_s),
                     (back, back + timing.duration_s), timing.start_s, timing.total_s, plan.upper())


def file_reference(path, timing: PlanTiming = PlanTiming(), dt_s: float = 0.002) -> Reference:
    """A plan from a CSV with columns time_s (s from the plan's start) and P (0..1).

    The take rests for ``timing.start_s``, follows P(time_s) over the file's span, holds its last
    value for ``timing.hold_s`` and rests ``timing.tail_s`` more; a file may reverse anywhere
    (a smile that relaxes half-way and comes back). Forward = the file's span; backward = its
    second half (where a plan with a return comes back). P is the fraction of the full motion
    the design aims at; the evaluation compares the take, normalised by its own largest
    displacement, with P / max(P).
    """
    df = pd.read_csv(path)
    missing = {"time_s", "P"} - set(df.columns)
    if missing:
        raise ValueError(f"{path}: expected columns time_s,P; missing {sorted(missing)}")
    ts = df["time_s"].to_numpy(float)
    p = df["P"].to_numpy(float)
    if ts.size < 2 or not np.all(np.diff(ts) > 0):
        raise ValueError(f"{path}: expected at least two rows with increasing time_s")
    bad = np.flatnonzero(~np.isfinite(p) | (p < 0) | (p > 1))
    if bad.size:
        raise ValueError(f"{path}: row {int(bad[0]) + 2}: expected P in 0..1, got {p[bad[0]]}")
    span = float(ts[-1] - ts[0])
    end = timing.start_s + span + timing.hold_s + timing.tail_s
    t = np.arange(0.0, end + dt_s, dt_s)
    r = np.where(t < timing.start_s, 0.0, np.interp(t - timing.start_s + ts[0], ts, p))
    mid = timing.start_s + 0.5 * span
    ideal = r / max(float(p.max()), 1e-9)
    return Reference(t, r, ideal, (timing.start_s, timing.start_s + span), (mid, timing.start_s + span),
                     timing.start_s, end, str(path))


def command_times(ref: Reference, step_s: float, fall_start_s: float | None = None) -> np.ndarray:
    """Row times (s) of a designed command file: 0, then one row every ``step_s`` from the
    motion's start to the take's end; with ``fall_start_s`` (the paper's return) a second grid
    starts there, so the return is commanded on its own steps (no gap shorter than ``step_s``)."""
    if step_s <= 0:
        raise ValueError(f"design: expected a step time > 0 s, got {step_s}")
    eps = 1e-9
    if fall_start_s is None:
        grid = ref.start_s + step_s * np.arange(int(np.floor((ref.end_s - ref.start_s) / step_s + eps)))
    else:
        n1 = int(np.floor((fall_start_s - ref.start_s) / step_s + eps))
        g1 = ref.start_s + step_s * np.arange(n1)
        g1 = g1[g1 <= fall_start_s - step_s + eps]
        n2 = int(np.floor((ref.end_s - fall_start_s) / step_s + eps))
        grid = np.concatenate([g1, fall_start_s + step_s * np.arange(n2)])
    return np.concatenate([[0.0], grid[grid > eps]])


# ----------------------------------------------------------------------------------------------
# the model as a stepped plant


@dataclass(frozen=True)
class DuPlant:
    """One DU of a face model, ready to be stepped.

    markers : (Ma,) indices of the markers it moves.  halfwidths : (Ma, P) play half-widths,
    command units.  alpha, beta : (Ma,) its logistic (beta with the trial's bias shift).
    tau_s : actuator lag (0: none).  backlash : dead band half-width, command units (0: none).
    stick_slip : the dead band releases with a jump (the stick-slip form) instead of trailing
        the command (a play).
    weights : (P,) the plays' weights (the model's PI density; None: equal).
    mix, kappa : the model's branch parameters (:mod:`mocap.analysis.face_model`; 1 and 0: one
        sigmoid of the PI output).  offsets : (Ma, P) each play's sigmoid-centre offset
        kappa (f - fbar) r, command units (None: 0).
    """

    du: int
    markers: np.ndarray
    halfwidths: np.ndarray
    alpha: np.ndarray
    beta: np.ndarray
    tau_s: float
    backlash: float
    weights: np.ndarray | None = None
    mix: float = 1.0
    offsets: np.ndarray | None = None
    stick_slip: bool = False

    def response(self, plays: np.ndarray) -> np.ndarray:
        """Normalised responses (..., Ma) of play outputs (..., Ma, P), command units: the
        face model's, sum_p q_p L(mix w + (1 - mix) play_p; alpha, beta + offset_p)."""
        q = (np.full(self.halfwidths.shape[1], 1.0 / self.halfwidths.shape[1])
             if self.weights is None else self.weights)
        w = np.einsum("...mp,p->...m", plays, q)
        if self.mix == 1.0 and self.offsets is None:
            return normalized_logistic(w, self.alpha, self.beta)
        x = self.mix * w[..., None] + (1.0 - self.mix) * plays
        off = 0.0 if self.offsets is None else self.offsets
        y = normalized_logistic(x, self.alpha[:, None], self.beta[:, None] + off)
        return np.einsum("...mp,p->...m", y, q)


@dataclass
class PlantState:
    """State of one DU: actuator (lag) output a, backlash output b, plays (Ma, 5) (command units),
    and the direction of the dead band's last motion (+1 up, -1 down; the stick-slip form)."""

    a: float
    b: float
    plays: np.ndarray
    d: float = 1.0


def plants(model: FaceModel, dus, trial: int = 1) -> list[DuPlant]:
    """The stepped plants of ``dus`` (each must be a DU of the model)."""
    unknown = [d for d in dus if d not in model.du_ids]
    if unknown:
        raise ValueError(f"design: the face model has no DUs {unknown} (it has {list(model.du_ids)})")
    lag = model.effect("lag")
    bl = model.effect("backlash")
    shift = float(np.mean(model.bias_shift(trial)))
    out = []
    for du in dus:
        n = model.du_ids.index(du)
        act = np.flatnonzero(model.active[n])
        q = model.density[n]
        keep = q > 1e-6  # plays of weight 0 need no state
        mix, kappa = (float(v) for v in model.branch[n])
        fbar = float(q @ DENSITY_FRACTIONS)
        offsets = (None if (mix == 1.0 and kappa == 0.0) else
                   kappa * (DENSITY_FRACTIONS[None, keep] - fbar) * model.r[n, act, None])
        out.append(DuPlant(int(du), act, model.r[n, act, None] * DENSITY_FRACTIONS[None, keep],
                           model.alpha[n, act], model.beta[n, act] + shift,
                           float(lag.value) if lag is not None else 0.0,
                           float(bl.value) if bl is not None else 0.0, q[keep] / q[keep].sum(),
                           mix, offsets, getattr(bl, "form", "play") == "stick-slip"))
    return out


def _stick_slip_step(a: np.ndarray, b0: np.ndarray, d0: np.ndarray, halfwidth: float):
    """The stick-slip dead band over one step's points a (C, J), from held outputs b0 (C,) and
    directions d0 (C,): (b (C, J), d (C,) after the step). Exact as the actuator moves
    monotonically within a step: once it follows or releases, it follows to the step's end."""
    follow = (a - b0[:, None]) * d0[:, None] >= 0.0
    release = np.logical_or.accumulate(~follow & (np.abs(a - b0[:, None]) >= 2.0 * halfwidth),
                                       axis=1)
    b = np.where(follow | release, a, b0[:, None])
    return b, np.where(release[:, -1], -d0, d0)


def rest_state(p: DuPlant) -> PlantState:
    return PlantState(0.0, 0.0, np.zeros_like(p.halfwidths))


def simulate_steps(p: DuPlant, state: PlantState, c: np.ndarray, durations_s: np.ndarray,
                   fractions: np.ndarray = SUBSTEPS):
    """Candidate command sequences over consecutive steps, from ``state``.

    Parameters
    ----------
    c : (C,) candidate commands held over every step, or (C, H) one command per step
        (command units).
    durations_s : (H,) the steps' durations, s.
    fractions : (J,) increasing points inside each step (fractions of its duration, at most 1).

    Returns
    -------
    y : (C, H * J, Ma) normalised responses at the points.
    end : the state after the first step, (a (C,), b (C,), plays (C, Ma, 5), d (C,)).
    """
    durations_s = np.asarray(durations_s, float)
    H = durations_s.size
    c = np.asarray(c, float)
    c = np.broadcast_to(c[:, None], (c.size, H)) if c.ndim == 1 else c
    C = c.shape[0]
    a0 = np.full(C, state.a)
    b0 = np.full(C, state.b)
    d0 = np.full(C, state.d)
    pl0 = np.broadcast_to(state.plays, (C,) + state.plays.shape)
    hw = p.halfwidths[None]
    fr = np.asarray(fractions, float)
    J = fr.size
    if fr[-1] != 1.0:  # the state carries over from the step's end
        fr = np.append(fr, 1.0)
    ys, first = [], None
    for h in range(H):
        ch = c[:, h]
        s = fr * durations_s[h]  # (J,) or (J + 1,)
        if p.tau_s > 0:
            a = ch[:, None] + (a0 - ch)[:, None] * np.exp(-s / p.tau_s)[None]  # (C, J)
        else:
            a = np.broadcast_to(ch[:, None], (C, s.size))
        if p.backlash > 0 and p.stick_slip:
            b, d0 = _stick_slip_step(a, b0, d0, p.backlash)
        elif p.backlash > 0:  # a play; exact as the actuator moves monotonically within a step
            b = np.clip(b0[:, None], a - p.backlash, a + p.backlash)
        else:
            b = a
        plays = np.clip(pl0[:, None], b[..., None, None] - hw[:, None], b[..., None, None] + hw[:, None])
        ys.append(p.response(plays[:, :J]))  # (C, J, Ma)
        a0, b0, pl0 = a[:, -1].copy(), b[:, -1].copy(), plays[:, -1]
        if h == 0:
            first = (a0, b0, pl0, d0.copy())
    return np.concatenate(ys, axis=1), first


def responses_of(model: FaceModel, plist: list[DuPlant], ys: list[np.ndarray]) -> np.ndarray:
    """Stack per-DU responses [(S, Ma_n)] into y (S, N, M) of the model's markers."""
    S = ys[0].shape[0]
    y = np.zeros((S, len(plist), len(model.marker_names)))
    for n, (p, yn) in enumerate(zip(plist, ys)):
        y[:, n, p.markers] = yn
    return y


def full_scale(model: FaceModel, plist: list[DuPlant], hold_s: float = 2.0,
               headroom: float = 0.0) -> np.ndarray:
    """|d_m| (M,) mm with every DU risen from rest to 255 - ``headroom`` and held ``hold_s``:
    the displacement the design calls 1 (the full motion)."""
    top = np.array([255.0 - headroom])
    ys = [simulate_steps(p, rest_state(p), top, np.array([hold_s]))[0][0, -1:]
          for p in plist]
    d = model.displacement_from_response(responses_of(model, plist, ys), [p.du for p in plist])
    return np.linalg.norm(d[0], axis=-1)


# ----------------------------------------------------------------------------------------------
# weights


def marker_weights(model: FaceModel, dus, markers=None, min_scale_mm: float = 0.05,
                   trial: int = 1) -> np.ndarray:
    """Weights (M,) of the model's markers in the design's cost.

    markers : None (every marker the DUs move by at least ``min_scale_mm`` at full command), a
        sequence of marker names, or ``("near", NAME, RADIUS_MM)``: the markers within RADIUS_MM
        of NAME at rest (a region). Markers that move less than ``min_scale_mm`` get weight 0
        (their normalised displacement is noise).
    """
    scale = full_scale(model, plants(model, dus, trial))
    w = (scale >= min_scale_mm).astype(float)
    names = list(model.marker_names)
    if markers is None:
        pass
    elif isinstance(markers, tuple) and len(markers) == 3 and markers[0] == "near":
        _, name, radius = markers
        if name not in names:
            raise ValueError(f"design: marker {name!r} is not in the model ({len(names)} markers)")
        dist = np.linalg.norm(model.rest_mm - model.rest_mm[names.index(name)], axis=-1)
        w = w * (dist <= float(radius))
    else:
        unknown = [m for m in markers if m not in names]
        if unknown:
            raise ValueError(f"design: markers {unknown} are not in the model "
                             f"(it has {names[0]}..{names[-1]})")
        sel = np.zeros(len(names))
        sel[[names.index(m) for m in markers]] = 1.0
        w = w * sel
    if w.sum() == 0:
        raise ValueError("design: no chosen marker moves with these DUs (nothing to track)")
    return w / w.sum()


# ----------------------------------------------------------------------------------------------
# the design


@dataclass(frozen=True)
class ModelDesign:
    """A designed command file and what the model predicts of it.

    rows : FORMAT.md command rows (time_s, du, command), integers 0..255.
    t_s : (S,) the cost points, s.  predicted : (S, M) the model's normalised displacement there.
    target : (S, M) the reference there.  cost : the final cost per point (see ``spread_weight``).
    seconds : time spent.
    """

    rows: pd.DataFrame
    t_s: np.ndarray
    predicted: np.ndarray
    target: np.ndarray
    cost: float
    seconds: float
    reference: "Reference | None" = None  # the reference designed for (hold level included)
    hold_level: float | None = None  # the hold :func:`design_plan` chose (None: not searched)
    tried: tuple["HoldTrial", ...] = ()  # every hold level design_plan designed for, in order


@dataclass(frozen=True)
class HoldTrial:
    """One hold level :func:`design_plan` designed for: the level (1 = the plan's own hold),
    the RMS the evaluation gives the model's predicted take (0.5 (forward + backward), the
    normalised displacement's units) and the command rows."""

    level: float
    predicted_rms: float
    rows: pd.DataFrame


def _candidates(center: int | None) -> np.ndarray:
    if center is None:
        return np.unique(np.append(np.arange(0, 256, COARSE), 255))
    return np.arange(max(center - COARSE + 1, 0), min(center + COARSE, 256))


@dataclass
class _Problem:
    """Everything a sweep reads (see :func:`design_commands`)."""

    model: FaceModel
    plist: list
    dus: list
    dur: np.ndarray  # (n_rows,) s
    target: np.ndarray  # (n_rows, J, M)
    ok: np.ndarray  # (n_rows, J, M) bool
    w: np.ndarray  # (M,)
    inv_scale: np.ndarray  # (M,)
    spread_weight: float
    t_s: np.ndarray  # (n_rows * J,) the cost points on the plan's clock (dead time added), s

    def cost(self, nd: np.ndarray, tgt: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """Cost (C,) of normalised displacements nd (C, Q, M) against tgt (Q, M): the squared
        weighted mean error over markers plus ``spread_weight`` times the weighted mean square."""
        wt = self.w[None] * ok  # (Q, M)
        e = nd - tgt[None]
        mean_e = np.sum(wt[None] * e, axis=2)
        return np.sum(mean_e ** 2, axis=1) + self.spread_weight * np.sum(wt[None] * e ** 2, axis=(1, 2))

    def normalised(self, ys: list[np.ndarray]) -> np.ndarray:
        """|d_m| / n_m (S, M) from per-DU responses [(S, Ma_n)]."""
        d = self.model.displacement_from_response(responses_of(self.model, self.plist, ys), self.dus)
        return np.linalg.norm(d, axis=-1) * self.inv_scale


def _advance(pb: _Problem, states: list[PlantState], i: int, commands: np.ndarray) -> np.ndarray:
    """Step every DU's state over row i with ``commands`` (N,); returns the predicted
    normalised displacement over the row (J, M). ``states`` is updated in place."""
    ys_step = []
    for n, p in enumerate(pb.plist):
        y1, (a, b, pl, d) = simulate_steps(p, states[n], np.array([commands[n]]), pb.dur[i:i + 1])
        states[n] = PlantState(float(a[0]), float(b[0]), pl[0], float(d[0]))
        ys_step.append(y1[0])
    return pb.normalised(ys_step)


def _sweep(pb: _Problem, prev: np.ndarray | None, horizon: int, preview: int,
           prefix: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One pass over the steps. Without ``prev`` (the first pass) a candidate is held over
    ``preview`` steps; with it, step i's candidate is followed by ``prev``'s commands over the
    next ``horizon - 1`` steps (Gauss-Seidel on the whole tracking cost). ``prefix`` (k, N): the
    first pass's commands of its first k rows, known already (a causal pass chooses them from
    the reference's first k + preview - 1 rows alone): they are replayed, not searched. Returns
    the commands (n_rows, N) and the predicted normalised displacement (n_rows, J, M)."""
    n_rows, J, M = pb.target.shape
    N = len(pb.plist)
    states = [rest_state(p) for p in pb.plist]
    chosen = np.zeros((n_rows, N), int) if prev is None else prev.copy()
    pred = np.zeros((n_rows, J, M))
    k = 0
    if prefix is not None and prev is None:
        k = min(len(prefix), n_rows)
        chosen[:k] = prefix[:k]
        for i in range(k):
            pred[i] = _advance(pb, states, i, chosen[i])
    for i in range(k, n_rows):
        H = (preview if prev is None else horizon)
        h = slice(i, min(i + H, n_rows))
        nh = h.stop - h.start
        tgt = pb.target[h].reshape(-1, M)
        okh = pb.ok[h].reshape(-1, M)
        if prev is None and i > 0:
            chosen[i] = chosen[i - 1]
        for n, p in enumerate(pb.plist):
            seq = np.broadcast_to(chosen[h], (nh, N)).copy()
            if prev is None:
                seq[:] = chosen[i]
            others = {k: simulate_steps(q, states[k], seq[None, :, k], pb.dur[h])[0][0]
                      for k, q in enumerate(pb.plist) if k != n}
            best = None
            for _ in range(2):
                cand = _candidates(best)
                cs = np.repeat(seq[None, :, n], cand.size, axis=0).astype(float)
                cs[:, 0] = cand
                if prev is None:
                    cs[:] = cand[:, None]
                yc, _ = simulate_steps(p, states[n], cs, pb.dur[h])
                C, Q = yc.shape[:2]
                ys = [yc.reshape(C * Q, -1) if k == n else np.tile(others[k], (C, 1))
                      for k in range(N)]
                nd = pb.normalised(ys).reshape(C, Q, M)
                cost = pb.cost(nd, tgt, okh)
                best = int(cand[int(np.argmin(cost))])
            chosen[i, n] = best
        pred[i] = _advance(pb, states, i, chosen[i])
    return chosen, pred


def design_commands(model: FaceModel, ref: Reference, dus, *, step_s: float = 0.016,
                    fall_start_s: float | None = None, weights: np.ndarray | None = None,
                    preview: int | None = None, horizon: int = 12, sweeps: int = 0,
                    headroom: float = 24.0, spread_weight: float = 0.2,
                    trial: int = 1) -> ModelDesign:
    """Commands of ``dus`` whose model response follows ``ref`` (see the module docstring).

    Parameters
    ----------
    model : the identified face model (its effects are all used).
    ref : the reference (:func:`plan_reference`, :func:`file_reference`, or a refinement's).
    step_s : the rig's command step, s; one row per step from ``ref.start_s``.
    fall_start_s : start of the return in the paper's timing (its own step grid), or None.
    weights : (M,) marker weights (default :func:`marker_weights` of every moving marker).
    preview : steps over which a candidate is held in the first, causal pass (1: greedy);
        None: :func:`default_preview` of the model (2 with actuator dynamics, else 1).
    horizon : steps over which a step's command is scored in the later passes, the following
        steps keeping the previous pass's commands (a few actuator time constants: this is what
        lets a command anticipate where a later one saturates at 0 or 255).
    sweeps : passes after the first (0: the causal design alone).
    headroom : the full motion (1) is the steady response to 255 - headroom (command units),
        so that a lagging actuator can still be driven towards it faster than it settles
        (the logistic is flat there: a few units cost a fraction of a percent of motion).
    spread_weight : weight of the markers' own errors against the error of their mean (the
        mean is what follows the plan; the markers' spread around it is partly beyond any
        command, and with several DUs this term decides how they share the work: each marker
        should rise monotonically to its hold, see the module docstring).
    trial : the trial the commands are designed for (the ``drift`` effect's bias).
    """
    import time

    t0 = time.perf_counter()
    pb, times = _problem(model, ref, dus, step_s, fall_start_s, weights, headroom, spread_weight,
                         trial)
    preview = _preview(model, preview)
    return _design(pb, times, ref, horizon, preview, sweeps, None, t0)[0]


def default_preview(model: FaceModel) -> int:
    """The causal pass's preview for ``model``: 2 command steps when it has actuator dynamics (a
    lag or a dead time), else 1 (greedy).

    A candidate held over the next two steps and scored on both is what a lagging actuator
    needs: its command shows in the markers mostly after the step it is sent in, and the greedy
    pass drives it as if it did not (overshooting into the next step; on a straight-path face
    with a second-order lag, which the model's first-order one only approximates, plan E played
    at 0.36 of the paper method's RMS greedy, 0.31 with the preview). On a face that responds
    at once the same preview holds each command over a step it does not belong to, half a step
    behind a rising plan: it doubles the RMS (plan A on the PI straight face without effects
    0.32 -> 0.60). benchmarks/design_sweep.md has both on every base-face family.
    """
    dynamic = model.effect("lag") is not None or model.effect("deadtime") is not None
    return 2 if dynamic else 1


def _preview(model: FaceModel, preview) -> int:
    if preview is None:
        return default_preview(model)
    if isinstance(preview, bool) or int(preview) != preview or preview < 1:
        raise ValueError(f"preview: expected a whole number of command steps >= 1, got {preview!r}")
    return int(preview)


def _problem(model: FaceModel, ref: Reference, dus, step_s: float, fall_start_s: float | None,
             weights: np.ndarray | None, headroom: float, spread_weight: float, trial: int
             ) -> tuple[_Problem, np.ndarray]:
    """The search problem of :func:`design_commands` and its command times (n_rows + 1,) s."""
    dus = [int(d) for d in dus]
    plist = plants(model, dus, trial)
    M = len(model.marker_names)
    scale = full_scale(model, plist, headroom=headroom)
    w = marker_weights(model, dus, trial=trial) if weights is None else np.asarray(weights, float)
    if w.shape != (M,):
        raise ValueError(f"design: expected weights of shape ({M},), got {w.shape}")
    w = np.where(scale > 1e-9, w, 0.0)
    inv_scale = np.where(scale > 1e-9, 1.0 / np.maximum(scale, 1e-12), 0.0)
    dead = model.effect("deadtime")
    delay = float(dead.value) if dead is not None else 0.0

    times = command_times(ref, step_s, fall_start_s)
    row_t = times[1:]
    dur = np.diff(np.append(row_t, ref.end_s))
    n_rows, J = row_t.size, SUBSTEPS.size
    pts = (row_t[:, None] + SUBSTEPS[None] * dur[:, None]).ravel()  # (n_rows * J,)
    target = ref.at(pts + delay, M).reshape(n_rows, J, M)
    ok = np.isfinite(target)
    pb = _Problem(model, plist, dus, dur, np.where(ok, target, 0.0), ok, w, inv_scale,
                  spread_weight, pts + delay)
    return pb, times


def _design(pb: _Problem, times: np.ndarray, ref: Reference, horizon: int, preview: int,
            sweeps: int, prefix: np.ndarray | None, t0: float) -> tuple[ModelDesign, np.ndarray]:
    """The design of ``pb`` and its first (causal) pass's commands (n_rows, N), which another
    hold level's design may share (``prefix``)."""
    import time

    n_rows, J, M = pb.target.shape
    chosen, pred = _sweep(pb, None, horizon, preview, prefix)
    causal = chosen.copy()
    for _ in range(sweeps):
        chosen, pred = _sweep(pb, chosen, horizon, preview)
    cost = float(pb.cost(pred.reshape(1, -1, M), pb.target.reshape(-1, M),
                         pb.ok.reshape(-1, M))[0] / max(n_rows * J, 1))
    frames = [pd.DataFrame({"time_s": np.round(times, 9), "du": du,
                            "command": np.concatenate([[0], chosen[:, n]]).astype(np.int64)})
              for n, du in enumerate(pb.dus)]
    rows = pd.concat(frames, ignore_index=True)
    return ModelDesign(rows, pb.t_s, pred.reshape(-1, M), pb.target.reshape(-1, M), cost,
                       time.perf_counter() - t0, ref), causal


# hold levels tried by design_plan, in units of hold_lift() (1.5 was tried too: on PI straight,
# Preisach straight and PI bowed faces, plans A-E, the model never chose it)
HOLD_LIFTS = (0.0, 0.5, 1.0)


def _hold_frames(ref: Reference) -> np.ndarray:
    """(len(ref.t_s),) bool: the plan's hold, between the end of the rise and the fall."""
    return (ref.t_s >= ref.rise[1]) & (ref.t_s < ref.fall[0])


def hold_lift(ref: Reference, band: float = 0.95) -> float:
    """How far the hold would have to rise for the plan's own frames within 5 % of its top to
    average 1: sum(1 - ideal) over the frames outside the hold where ideal >= ``band``, per hold
    frame (0 without a hold).

    The evaluation divides each marker by its plateau level, the mean of its displacement over
    the frames within 5 % of its largest (:func:`mocap.analysis.displacement.plateau_level`),
    and those take in the top of the rise and the start of the fall as well as the hold: a
    marker that follows the plan exactly reads above 1 on the hold and above the plan on the
    rise (+0.0026 over the second half of plan A's rise on a face whose markers move on straight
    lines). A hold above 1 brings the normaliser back up; how far is right depends on the face's
    paths (on a bowed path |d| may pass its final value during the rise and the plateau already
    reads high), so :func:`design_plan` chooses it on the model's prediction."""
    hold = _hold_frames(ref)
    if not hold.any():
        return 0.0
    top = ~hold & (ref.ideal >= band)
    return float(np.sum(1.0 - ref.ideal[top]) / hold.sum())


def with_hold(ref: Reference, level: float) -> Reference:
    """``ref`` with its hold at ``level`` (the rest unchanged; per-marker references too)."""
    hold = _hold_frames(ref)
    r = ref.r.copy()
    r[hold] = level
    return Reference(ref.t_s, r, ref.ideal, ref.rise, ref.fall, ref.start_s, ref.end_s, ref.label)


def design_plan(model: FaceModel, ref: Reference, dus, *, lifts=HOLD_LIFTS, tail_s: float = 0.25,
                trial: int = 1, **kwargs) -> ModelDesign:
    """:func:`design_commands` for a plan with a hold, the hold's level chosen on the model.

    For each lift f in ``lifts`` the commands are designed for the plan with its hold at
    1 + f * :func:`hold_lift`, the model predicts the take (``ref.end_s + tail_s`` long, the
    evaluated take), and the design whose prediction the evaluation scores best against the plan
    (:func:`evaluate_design`, 0.5 (forward + backward)) is returned, with ``hold_level`` and the
    ``reference`` it was designed for (a refinement starts from that reference). The choice is
    the model's: on a face whose markers move on straight lines it lifts the hold (plan A on the
    PI straight face: 0.335 -> 0.322 of the paper method's RMS played), on a bowed one it keeps
    it at 1 (plan B on the PI bowed face: 0.058 with the hold at 1, 0.085 lifted by 1). A plan
    without a hold, or ``lifts=(0,)``, is :func:`design_commands` itself.

    Every level's design is exactly :func:`design_commands`' for the plan with that hold, but the
    rise they share is searched once: the causal pass chooses a row from the reference's next
    ``preview`` rows alone, so the rows before the hold are the first level's, replayed. Every
    level tried is kept in ``tried`` (level, predicted RMS, rows).
    """
    import time

    t0 = time.perf_counter()
    a = hold_lift(ref)
    levels = sorted({1.0 + float(f) * a for f in lifts}) if a > 0 else [None]
    if len(levels) == 1:
        r = ref if levels[0] is None else with_hold(ref, levels[0])
        return design_commands(model, r, dus, trial=trial, **kwargs)
    import inspect

    opts = {k: v.default for k, v in inspect.signature(design_commands).parameters.items()
            if v.kind is inspect.Parameter.KEYWORD_ONLY and k != "trial"}
    unknown = set(kwargs) - set(opts)
    if unknown:
        raise TypeError(f"design_plan: unexpected keyword arguments {sorted(unknown)}")
    opts.update(kwargs)
    opts["preview"] = _preview(model, opts["preview"])
    n = int(round((ref.end_s + tail_s) * model.fps))
    first, tried, best = None, [], None
    for level in levels:
        r = with_hold(ref, level)
        pb, times = _problem(model, r, dus, opts["step_s"], opts["fall_start_s"], opts["weights"],
                             opts["headroom"], opts["spread_weight"], trial)
        prefix = None
        if first is not None:
            # the causal pass chooses row i's commands from rows i .. i + preview - 1 of the
            # reference alone: the rows before the first that the hold's level changes are the
            # first level's causal pass (the rise), replayed instead of searched; later sweeps
            # run in full
            differs = np.any((pb.target != first[0].target) | (pb.ok != first[0].ok), axis=(1, 2))
            k = int(np.argmax(differs)) if differs.any() else differs.size
            prefix = first[1][:max(k - opts["preview"] + 1, 0)]
        des, causal = _design(pb, times, r, opts["horizon"], opts["preview"], opts["sweeps"],
                              prefix, time.perf_counter())
        if first is None:
            first = (pb, causal)
        ev = evaluate_design(model.predict(des.rows, n, trial), des.rows, model.fps, ref)
        score = 0.5 * (ev.rms_forward + ev.rms_backward)
        tried.append(HoldTrial(level, score, des.rows))
        if best is None or score < best[0]:
            best = (score, level, des)
    from dataclasses import replace

    return replace(best[2], hold_level=best[1], tried=tuple(tried),
                   seconds=time.perf_counter() - t0)



# ----------------------------------------------------------------------------------------------
# iterative refinement (iterative learning control on top of the model-based design)


def commands_matrix(rows: pd.DataFrame, dus, n_frames: int, fps: float) -> np.ndarray:
    """Commands (n_frames, n_dus) of ``rows`` at the frames (FORMAT.md sampling)."""
    from mocap.schedules import sample_commands

    return sample_commands(rows, list(dus), np.arange(n_frames) / fps)


def predicted_delta(model: FaceModel, rows: pd.DataFrame, n_frames: int, trial: int = 1) -> np.ndarray:
    """The model's normalised displacement (n_frames, M) of a command file, as the evaluation
    measures it (:func:`mocap.analysis.evaluation.realized_delta`)."""
    from mocap.analysis.evaluation import realized_delta

    dus = sorted(int(d) for d in pd.unique(rows["du"]))
    X = model.predict(rows, n_frames, trial)
    return realized_delta(X, commands_matrix(rows, dus, n_frames, model.fps))


def debiased_delta(X: np.ndarray, command: np.ndarray, smooth_frames: int = 6,
                   max_select_frames: int = 60) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normalised displacement of a measured take without the bias of noise.

    As :func:`mocap.analysis.evaluation.realized_delta` (which noise-free data give exactly), with
    the three ways white noise of s_m mm per axis biases it removed, because a refinement learns
    every bias as a tracking error (measured on a 20-marker Preisach off-chord face playing plan
    A, 0.03 mm, 30 noise draws: the markers' mean error of the plain reading -0.011 on the hold and
    +0.008 after the motion, of this one -0.0004 to -0.003; the paper method's RMS on that plan is
    0.065, so the refinement's target 1/5 of it is 0.013):

    - |d|^2 of noise is positive: the length is sqrt(max(|d|^2 - 3 s_m^2 (1 + 1 / n_rest), 0))
      (the rest reference averages n_rest frames);
    - that clipped length is still positive on average where the marker is at rest: within 4 s_m
      of the rest it takes the sign of d along the marker's principal direction, so that its mean
      there is 0 (the face's true length is 0 at rest and the noise symmetric);
    - the plateau (the frames within 5 % of the smoothed maximum, whose mean length divides) is
      picked on a curve smoothed long enough that its noise does not pick the frames: the
      noise of a mean of W frames, s_m / sqrt(W), at most a tenth of the 5 % band (W from
      ``smooth_frames`` up to ``max_select_frames``); frames selected by their own noise read
      the plateau high.

    s_m is the marker's noise per axis, its standard deviation over the rest frames before the
    first command change (0 with fewer than 3: then nothing is corrected).

    X (n_frames, M, 3) mm, NaN where a marker is missing; command (n_frames,) or (n_frames,
    n_dus). Returns delta (n_frames, M) (NaN where X is), the plateau length (M,) mm (NaN for a
    marker never seen) and s_m (M,) mm.
    """
    import warnings

    from mocap.analysis.noise_corrected import box_mean
    from mocap.reconstruct.displacement import PLATEAU, principal_direction, smoothed

    change = np.flatnonzero(np.any(np.diff(np.asarray(command).reshape(len(command), -1), axis=0)
                                   != 0, axis=-1))
    lead = int(change[0]) + 1 if change.size else 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        rest = np.nanmean(X[:lead], axis=0)
        var = (np.nanmean(np.nanvar(X[:lead], axis=0, ddof=1), axis=-1) if lead > 2
               else np.zeros(X.shape[1]))
    var = np.nan_to_num(var)
    n_rest = np.sum(np.all(np.isfinite(X[:lead]), axis=-1), axis=0).astype(float)
    d = X - rest[None]
    d2 = np.sum(d * d, axis=-1)
    length = np.sqrt(np.clip(d2 - 3.0 * var[None] * (1.0 + 1.0 / np.maximum(n_rest, 1.0))[None],
                             0.0, None))
    if np.any(var > 0):
        p = np.einsum("fmi,mi->fm", np.nan_to_num(d), principal_direction(d))
        length = np.where(d2 < 16.0 * var[None], np.sign(p) * length, length)
    # the plateau: selected on a curve smoothed over W_m frames, then the plain mean over it
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        rough = np.nanmax(np.where(np.isfinite(length), smoothed(length, smooth_frames), -np.inf),
                          axis=0)
        band = 0.1 * (1.0 - PLATEAU) * np.where(rough > 0, rough, np.nan)
        W = np.where(var > 0, np.ceil(var / band**2), smooth_frames)
    W = np.clip(np.nan_to_num(W, nan=max_select_frames), smooth_frames, max(max_select_frames,
                                                                             smooth_frames))
    peak = np.full(X.shape[1], np.nan)
    for w in np.unique(W).astype(int):
        cols = np.flatnonzero(W == w)
        # beyond the evaluation's own smoothing the noise matters: leave each frame's out
        if w > smooth_frames:  # each frame left out of its own window's mean
            x = length[:, cols]
            mean, cnt = box_mean(x, w + (1 - w % 2))  # odd: centred
            with np.errstate(invalid="ignore", divide="ignore"):
                s = np.where(np.isfinite(x), np.where(cnt > 1, (mean * cnt - np.nan_to_num(x))
                                                      / (cnt - 1), np.nan), mean)
        else:
            s = smoothed(length[:, cols], w)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            top = np.nanmax(np.where(np.isfinite(s), s, -np.inf), axis=0)
            on = np.isfinite(length[:, cols]) & (s >= PLATEAU * top[None]) & (top[None] > 0)
        level = np.where(on, length[:, cols], 0.0).sum(axis=0) / np.maximum(on.sum(axis=0), 1)
        peak[cols] = np.where(on.any(axis=0), level, np.where(np.isfinite(top), top, np.nan))
    with np.errstate(invalid="ignore", divide="ignore"):
        return length / np.where(peak > 0, peak, np.nan)[None], peak, np.sqrt(var)


def _smooth_nan(x: np.ndarray, frames: int) -> np.ndarray:
    """NaN-aware centred moving average of x (n_frames, M) over ``frames`` frames (edges
    repeated); NaN where the window holds no value."""
    if frames <= 1:
        return x
    from scipy.ndimage import uniform_filter1d

    ok = np.isfinite(x)
    num = uniform_filter1d(np.where(ok, x, 0.0), frames, axis=0, mode="nearest")
    cnt = uniform_filter1d(ok * 1.0, frames, axis=0, mode="nearest")
    return np.where(cnt > 0, num / np.maximum(cnt, 1e-12), np.nan)


def _weighted_mean(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(n_frames,) mean over markers of x (n_frames, M) in weights w (M,), over the finite values
    of positive weight; NaN where there is none."""
    ok = np.isfinite(x) & (w[None] > 0)
    den = np.sum(ok * w[None], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, np.sum(np.where(ok, x, 0.0) * w[None], axis=1) / den, np.nan)


def refined_reference(model: FaceModel, plan_ref: Reference, rows: pd.DataFrame,
                      measured: np.ndarray, measured_names, *, previous: Reference | None = None,
                      gain: float = 1.0, smooth_frames: int = 7, weights: np.ndarray | None = None,
                      trial: int = 1, control: bool = True) -> Reference:
    """The next reference of iterative learning control from a played take.

    Parameters
    ----------
    plan_ref : the plan (what the markers should do).
    rows : the commands that were played.  measured : (n_frames, M') marker positions (mm) of
        the played take at the model's frame rate, NaN where missing; measured_names : (M',).
        Its normalised displacement is read without the bias of noise (:func:`debiased_delta`).
    previous : the reference those commands were designed for (per marker or not); without it
        the model's own prediction of ``rows`` stands for it.
    gain : learning gain (1: the whole error at once).
    smooth_frames : moving-average window of the error (frames; measurement noise).
    weights : (M,) marker weights of the design (default :func:`marker_weights`), times each
        marker's signal-to-noise factor s^2 / (s^2 + (20 noise)^2) (s its measured plateau).

    control : the model's prediction as a control variate (module docstring): the error is
        sum_m w0_m (P - pred_m) + sum_m w_m (pred_m - delta_m) with w0 the design's weights and
        w the signal-to-noise ones (each normalised to sum 1); False: sum_m w_m (P - delta_m).

    Returns the reference r_{k+1}(t) = r_k(t) + gain e(t) over the plan's rise and fall
    (elsewhere r_k), on the take's frames, e the markers' mean error. The markers' weighted mean error
    is learnt, not each marker's: the mean is what a command can move, while a marker whose
    normalised displacement cannot follow the plan (pulled two ways by two DUs) would wind its
    own reference up without end.
    """

    names = list(model.marker_names)
    n_frames = measured.shape[0]
    if measured.ndim != 3 or measured.shape[1] != len(measured_names):
        raise ValueError(f"refine: expected measured positions (n_frames, {len(measured_names)}, 3), "
                         f"got {measured.shape}")
    dus = sorted(int(d) for d in pd.unique(rows["du"]))
    delta_meas, peak_meas, noise_meas = debiased_delta(
        measured, commands_matrix(rows, dus, n_frames, model.fps),
        max_select_frames=max(6, int(round(SELECT_S * model.fps))))
    M = len(names)
    delta = np.full((n_frames, M), np.nan)
    snr = np.zeros(M)
    pos = {n: i for i, n in enumerate(measured_names)}
    for m, n in enumerate(names):
        if n in pos:
            delta[:, m] = delta_meas[:, pos[n]]
            s2 = np.nan_to_num(peak_meas[pos[n]]) ** 2
            snr[m] = s2 / max(s2 + (SNR_NOISE * noise_meas[pos[n]]) ** 2, 1e-300) if s2 > 0 else 0.0
    t = np.arange(n_frames) / model.fps
    # only the evaluated parts learn: the hold and the rests anchor the scale (the normalised
    # displacement divides by the take's own plateau, so an error there cannot be corrected and
    # learning it would drift the whole motion's scale)
    learn = ((t >= plan_ref.rise[0]) & (t < plan_ref.rise[1])) | \
        ((t >= plan_ref.fall[0]) & (t < plan_ref.fall[1]))
    w0 = marker_weights(model, dus, trial=trial) if weights is None else np.asarray(weights, float)
    w = w0 * snr  # markers that barely move above the noise teach little
    target = plan_ref.at(t, M)
    pred = predicted_delta(model, rows, n_frames, trial) if control or previous is None else None
    if control:
        # the model's prediction as a control variate: its error against the plan in the design's
        # own weights (noise-free), plus what only the noisy take can tell, the model's error
        # pred - delta, read in the signal-to-noise weights (far more alike across markers than
        # the tracking error itself, so the other weights barely change its mean)
        e_mean = (_weighted_mean(_smooth_nan(target - pred, smooth_frames), w0)
                  + _weighted_mean(_smooth_nan(pred - delta, smooth_frames), w))
    else:
        e_mean = _weighted_mean(_smooth_nan(target - delta, smooth_frames), w)
    e_mean = np.where(learn & np.isfinite(e_mean), e_mean, 0.0)
    r_prev = previous.at(t, M) if previous is not None else pred
    r_new = r_prev + gain * (e_mean[:, None] if r_prev.ndim == 2 else e_mean)
    # before the motion starts nothing is asked; the reference stays a normalised displacement
    r_new[t < plan_ref.start_s] = 0.0
    ideal = np.interp(t, plan_ref.t_s, plan_ref.ideal)
    return Reference(t, np.clip(r_new, -0.5, 1.5), ideal, plan_ref.rise, plan_ref.fall,
                     plan_ref.start_s, plan_ref.end_s, plan_ref.label)


# ----------------------------------------------------------------------------------------------
# evaluation


def evaluate_design(X: np.ndarray, rows: pd.DataFrame, fps: float, ref: Reference,
                    keep: np.ndarray | None = None):
    """A played (or predicted) take of a design against its plan, as 'mocap run' evaluates
    motions (:func:`mocap.analysis.evaluation.evaluate_motion`): X (n_frames, M, 3) mm, markers
    ``keep`` (default all) that move at least 0.05 mm; forward = ``ref.rise``, backward =
    ``ref.fall``. Returns a :class:`mocap.analysis.evaluation.MotionEvaluation`."""
    from mocap.analysis.evaluation import evaluate_motion, realized_delta

    n, M = X.shape[:2]
    dus = sorted(int(d) for d in pd.unique(rows["du"]))
    cmd = commands_matrix(rows, dus, n, fps)
    delta = realized_delta(X, cmd)
    t = np.arange(n) / fps
    ideal = np.interp(t, ref.t_s, ref.ideal)
    f0 = int(round(ref.start_s * fps))
    with np.errstate(invalid="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            peak = np.nanmax(np.linalg.norm(X - np.nanmean(X[: max(f0, 1)], axis=0)[None], axis=-1),
                             axis=0)
    k = (np.ones(M, bool) if keep is None else np.asarray(keep, bool)) & (peak >= 0.05)

    def window(a_b):
        return slice(int(round(a_b[0] * fps)), min(int(round(a_b[1] * fps)), n))

    return evaluate_motion(delta, ideal, fps, window(ref.rise), window(ref.fall), k)


@dataclass(frozen=True)
class TrackingFloor:
    """The least tracking RMS any command file on a command grid can reach on a face that
    responds at once (:func:`tracking_floor`); the parts in the evaluation's units (normalised
    displacement), averaged as the design's score is: 0.5 (forward + backward)."""

    forward: float  # staircase of the held commands over the rise
    backward: float  # staircase over the fall, no lower than the face's set at command 0
    set_level: float  # the mean normalised displacement the face keeps at command 0 (given)

    @property
    def rms(self) -> float:
        return 0.5 * (self.forward + self.backward)


def set_at_rest(plays, fps: float, tail_s: float = 0.2) -> float:
    """The set a face keeps at command 0 after a motion, read on played takes: the lowest median
    mean normalised displacement over the last ``tail_s`` of the plays (pairs of command rows
    and their :func:`evaluate_design`) whose every DU ends at command 0; 0.0 if none does (the
    floor then counts the staircase only, still a floor)."""
    ends = []
    for rows, ev in plays:
        last = rows.sort_values("time_s", kind="stable").groupby("du")["command"].last()
        if (last == 0).all():
            ends.append(float(np.nanmedian(ev.mean[-max(1, int(round(tail_s * fps))):])))
    return min(ends) if ends else 0.0


def tracking_floor(ref: Reference, command_times_s: np.ndarray, fps: float,
                   set_level: float = 0.0) -> TrackingFloor:
    """The tracking RMS below which no command file on the grid ``command_times_s`` (s, the rows'
    times; :func:`command_times`) can go, for a face whose markers respond at once and whose
    lowest displacement after the motion is ``set_level`` (mean normalised displacement at
    command 0 after the full motion: the set a hysteresis leaves; 0 for none).

    A frame at t is driven by the last row at or before t (FORMAT.md), so a face without dynamics
    holds every marker's normalised displacement, and their mean, constant between two rows: the
    best constant over a step is the plan's mean over that step's frames, and over the fall no
    lower than the set (on the way down a play-type hysteresis is lowest at command 0). The RMS
    of that best staircase against the plan over the evaluation's windows is the floor. It is not
    a bound for a face with actuator dynamics (a lag smooths the staircase) and is only as good
    as ``set_level``; the design sweep measures the set on a played take of the true face."""
    times = np.sort(np.asarray(command_times_s, float))
    n = int(np.ceil(ref.end_s * fps)) + 1
    t = np.arange(n) / fps
    ideal = np.interp(t, ref.t_s, ref.ideal)
    step = np.searchsorted(times, t + 1e-9, side="right")  # 0 before the first row
    sums = np.bincount(step, weights=ideal, minlength=times.size + 1)
    counts = np.bincount(step, minlength=times.size + 1)
    best = (sums / np.maximum(counts, 1))[step]

    def rms(a_b, lo):
        sl = slice(int(round(a_b[0] * fps)), min(int(round(a_b[1] * fps)), n))
        return float(np.sqrt(np.mean((np.maximum(best[sl], lo) - ideal[sl]) ** 2)))

    return TrackingFloor(rms(ref.rise, -np.inf), rms(ref.fall, float(set_level)), float(set_level))
