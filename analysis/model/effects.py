"""Effects: composable terms of the face model, each with its parameter, its fit and its meaning.

The face model (:mod:`mocap.analysis.model.face_model`) computes a take's marker displacements in four
stages; an effect acts on one stage through a hook and leaves the others alone (the defaults
below are the identity), so adding an effect is writing one class here and registering it in
:data:`CATALOGUE`:

1. ``actuator(a, t, sampler)``: the command side, per DU, on a fine time grid (command units).
2. ``beta_shift(trial)``: the static map's bias moves (command units).
3. ``interact(y, D)``: several DUs acting at once change each other's normalised responses.
4. ``output(d)``: the total displacement (mm) is mapped (``output_inverse`` gives the fitter the
   inverse map on single-DU data, with the weights of a first-order forward residual).

Two effects add per-(DU, marker) parameters instead of one global value: ``hysteresis`` frees
each curve's play width r (a base model without it has r = 0), and ``curvature`` adds a path
basis 4 y (1 - y) with its own 3D vector per curve (paths bow sideways). Global parameters are
identified by a profile over ``grid`` followed by a bounded scalar refinement, refitting every
curve inside (dead time, piecewise smooth in sampled data, on a 25 ms grid first, and
with its uncertainty floored at the fine time grid's step).

Effects are frozen dataclasses; ``value`` is the global parameter (ignored by per-curve effects).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np



@dataclass(frozen=True)
class ScheduleSummary:
    """What a session's commanded takes can reveal (see :func:`summarize_schedules`)."""

    n_rates: int  # distinct ramp rates (command units per s, rounded), over all takes
    falling: bool  # some take lowers a command
    inner_reversals: bool  # some command reverses inside the range (minor loops)
    multi_du: bool  # some take drives two or more DUs at once
    repeated_trials: bool  # some schedule was played in two or more trials


@dataclass(frozen=True)
class Effect:
    """Base class: the identity at every stage. ``value`` is the global parameter."""

    value: float = 0.0

    name: ClassVar[str] = "base"
    parameter: ClassVar[str] = ""
    unit: ClassVar[str] = ""
    meaning: ClassVar[str] = ""
    stage: ClassVar[str] = ""
    order: ClassVar[int] = 0  # order among actuator-stage effects
    grid: ClassVar[tuple[float, ...]] = ()  # coarse profile grid of ``value``
    bounds: ClassVar[tuple[float, float]] = (0.0, 0.0)
    per_curve: ClassVar[bool] = False
    frees_r: ClassVar[bool] = False
    acts_where_held: ClassVar[bool] = False  # its local evidence is read where it holds the
    #                                          actuator off the command (discrepancy.hold_gain)
    n_bases: ClassVar[int] = 0  # extra path bases per curve
    pairwise: ClassVar[bool] = False  # adds a 3D vector per DU pair and marker (y_n y_n' terms)
    fine_grid: ClassVar[bool] = False  # a time shift: resolved to the fine time grid at best
    command_grid: ClassVar[bool] = False  # a dead band: resolved to half a command step at best
    continuation: ClassVar[bool] = False  # profile warm-started from the nearest value tried
    #                                        (a rough profile: profiles.profile_effect)
    min_plausible: ClassVar[float] = 0.0  # |value| below this is no effect at all
    affects_curves: ClassVar[bool] = True  # False: single-DU takes do not depend on the value,
    #                                         so the curves are fitted once for its profile

    # -- hooks ------------------------------------------------------------------------------
    def actuator(self, a: np.ndarray, t: np.ndarray, sampler) -> np.ndarray:
        """Actuator input (T, n_dus) from the one before (T, n_dus); t (T,) s on a fine grid."""
        return a

    def beta_shift(self, trial) -> np.ndarray | float:
        """Shift of every curve's logistic bias in a take of this trial (command units)."""
        return 0.0

    def interact(self, y: np.ndarray, D: np.ndarray) -> np.ndarray:
        """Normalised responses (S, N, M) of a take's N DUs acting together; D (N, M, 3) mm."""
        return y

    def output(self, d: np.ndarray) -> np.ndarray:
        """Total displacement map (S, M, 3) mm -> (S, M, 3) mm."""
        return d

    def output_inverse(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Inverse of :meth:`output` on data, and the weight (S, M) of each sample (or None)."""
        return d, None

    def bases(self, y: np.ndarray) -> list[np.ndarray]:
        """Extra path bases (each shaped like y) multiplying per-curve 3D vectors."""
        return []

    def bases_derivative(self, y: np.ndarray) -> list[np.ndarray]:
        """d(basis)/dy for each of :meth:`bases`."""
        return []

    # -- bookkeeping --------------------------------------------------------------------------
    def with_value(self, value: float) -> "Effect":
        return replace(self, value=float(value))

    def untestable(self, s: ScheduleSummary) -> str | None:
        """Why the session's takes cannot tell this effect apart, or None when they can."""
        return None

    def plausible(self) -> bool:
        """Whether ``value`` (for per-curve effects: their summary parameter) is an effect at all."""
        return abs(self.value) >= self.min_plausible

    def describe(self) -> dict:
        return {"effect": self.name, "parameter": self.parameter, "value": self.value,
                "unit": self.unit, "meaning": self.meaning}


@dataclass(frozen=True)
class Hysteresis(Effect):
    name: ClassVar[str] = "hysteresis"
    parameter: ClassVar[str] = "loop_width"
    unit: ClassVar[str] = "command units"
    meaning: ClassVar[str] = ("rate-independent memory of the skin: forward and backward branches "
                              "offset by a loop width, Preisach minor loops at reversals")
    stage: ClassVar[str] = "static"
    per_curve: ClassVar[bool] = True
    frees_r: ClassVar[bool] = True
    min_plausible: ClassVar[float] = 1.0  # median loop width, command units

    def untestable(self, s):
        return None if s.falling else "no take lowers a command"


@dataclass(frozen=True)
class Lag(Effect):
    name: ClassVar[str] = "lag"
    parameter: ClassVar[str] = "tau_s"
    unit: ClassVar[str] = "s"
    meaning: ClassVar[str] = "first-order actuator dynamics: tau da/dt = c - a"
    stage: ClassVar[str] = "actuator"
    order: ClassVar[int] = 1
    grid: ClassVar[tuple[float, ...]] = (0.0, 0.02, 0.05, 0.1, 0.2, 0.4)
    bounds: ClassVar[tuple[float, float]] = (0.0, 0.6)
    min_plausible: ClassVar[float] = 0.004

    def actuator(self, a, t, sampler):
        if self.value <= 0:
            return a
        from scipy.signal import lfilter

        dt = float(t[1] - t[0]) if t.size > 1 else 1.0
        g = 1.0 - np.exp(-dt / self.value)
        return lfilter([0.0, g], [1.0, -(1.0 - g)], a, axis=0)

    def untestable(self, s):
        return None if s.n_rates >= 2 else "all ramps at one rate: a lag looks like a wider hysteresis"


@dataclass(frozen=True)
class SecondOrderLag(Lag):
    """A lag of the same mean delay tau with two equal poles (critically damped): the other
    explanation of a step response that a first-order lag plus a small dead time fits. Not a
    candidate of its own (the same name as :class:`Lag`, so profiling it replaces the lag): the
    workflow weighs it against a dead time named after a lag."""

    meaning: ClassVar[str] = "second-order actuator dynamics: (tau/2 d/dt + 1)^2 a = c"

    def actuator(self, a, t, sampler):
        if self.value <= 0:
            return a
        half = Lag(0.5 * self.value)
        return half.actuator(half.actuator(a, t, sampler), t, sampler)


@dataclass(frozen=True)
class DeadTime(Effect):
    name: ClassVar[str] = "deadtime"
    parameter: ClassVar[str] = "delay_s"
    unit: ClassVar[str] = "s"
    meaning: ClassVar[str] = "pure transport delay between command and actuator: a(t) = c(t - L)"
    stage: ClassVar[str] = "actuator"
    order: ClassVar[int] = 0
    grid: ClassVar[tuple[float, ...]] = tuple(np.round(np.arange(0.0, 0.2001, 1 / 40), 6))
    bounds: ClassVar[tuple[float, float]] = (0.0, 0.4)
    fine_grid: ClassVar[bool] = True
    continuation: ClassVar[bool] = True
    min_plausible: ClassVar[float] = 0.003

    def actuator(self, a, t, sampler):
        if self.value <= 0:
            return a
        return sampler(t - self.value)

    def untestable(self, s):
        return None if s.n_rates >= 2 else "all ramps at one rate: a dead time looks like hysteresis"


@dataclass(frozen=True)
class Backlash(Effect):
    name: ClassVar[str] = "backlash"
    parameter: ClassVar[str] = "halfwidth"
    unit: ClassVar[str] = "command units"
    meaning: ClassVar[str] = "mechanical dead band of width 2 b at every command reversal"
    stage: ClassVar[str] = "actuator"
    order: ClassVar[int] = 2
    grid: ClassVar[tuple[float, ...]] = (0.0, 3.0, 7.0, 12.0, 18.0, 26.0)
    bounds: ClassVar[tuple[float, float]] = (0.0, 50.0)
    # a dead band of a few units is what a branch shape the base cannot follow looks like
    min_plausible: ClassVar[float] = 3.0
    command_grid: ClassVar[bool] = True

    def actuator(self, a, t, sampler):
        if self.value <= 0:
            return a
        from mocap.analysis.model.play_kernel import play_table

        h = np.array([self.value])
        return np.column_stack([play_table(a[:, j], 1, h)[:, 0] for j in range(a.shape[1])])

    form: ClassVar[str] = "play"

    def untestable(self, s):
        return (None if s.inner_reversals else
                "no reversals inside the range (minor loops): a dead band hides inside hysteresis")

    def describe(self):
        return {**super().describe(), "form": self.form}


@dataclass(frozen=True)
class StickSlipBacklash(Backlash):
    """A dead band that releases with a jump: after a reversal the actuator holds until the
    command has come back 2 b, then jumps to the command (static friction in a gear or a cable
    sheath; no lasting offset, unlike the play of :class:`Backlash`, whose output trails the
    command by b). The other form of the backlash candidate: the workflow fits both and keeps the
    one that predicts the held-out takes better (:data:`FORMS`)."""

    meaning: ClassVar[str] = ("stick-slip dead band: after every command reversal the actuator "
                              "holds until the command has come back 2 b, then jumps to it")
    form: ClassVar[str] = "stick-slip"
    acts_where_held: ClassVar[bool] = True

    def actuator(self, a, t, sampler):
        if self.value <= 0:
            return a
        from mocap.analysis.model.play_kernel import stick_slip

        return stick_slip(a, self.value)


@dataclass(frozen=True)
class Coupling(Effect):
    name: ClassVar[str] = "coupling"
    parameter: ClassVar[str] = "kappa"
    unit: ClassVar[str] = ""
    meaning: ClassVar[str] = ("DUs share skin: each marker moves by y_n y_n' C_nn'm more than the sum "
                              "of the DUs' motions (C a 3D vector per DU pair and marker, fitted on "
                              "takes driving several DUs); kappa is the fraction of its travel along "
                              "each marker's path a DU loses while another DU is at full command, "
                              "read where the takes hold them there")
    stage: ClassVar[str] = "interact"
    affects_curves: ClassVar[bool] = False
    per_curve: ClassVar[bool] = True
    pairwise: ClassVar[bool] = True
    grid: ClassVar[tuple[float, ...]] = (-0.3, 0.0, 0.2, 0.4, 0.7)
    bounds: ClassVar[tuple[float, float]] = (-1.0, 1.0)
    min_plausible: ClassVar[float] = 0.02

    uniform: bool = False  # the scalar law's loss the same at every marker (o = 1)

    def interact(self, y, D):
        if self.value == 0 or y.shape[1] < 2:
            return y
        mag = np.linalg.norm(D, axis=-1)  # (N, M)
        o = mag / np.maximum(mag.max(axis=1, keepdims=True), 1e-12)
        if self.uniform:
            o = np.ones_like(o)
        yo = y * o[None]
        others = yo.sum(axis=1, keepdims=True) - yo
        return y * (1.0 - self.value * others)

    def untestable(self, s):
        return None if s.multi_du else "no take drives two DUs at once"

    form: ClassVar[str] = "pair vectors"

    def describe(self):
        return {**super().describe(), "form": self.form}


@dataclass(frozen=True)
class CouplingLaw(Coupling):
    """The coupling as a scalar law on the DUs' drives, before each marker's path, with the pair
    vectors of :class:`Coupling` on top for what the law leaves: y_n -> y_n (1 - kappa
    sum_other y_n' o_n'm), o the other DU's relative pull at the marker (|D_n'm| / max_m
    |D_n'm|). The pair vectors alone are the law's first order in d-space, a fixed 3D vector per
    pair and marker, C = -kappa (o_n' D_n + o_n D_n'); the law moves the marker along its own
    path to where the reduced drive gets it, and on a bowed path or one that ends off the chord
    the two part by kappa y y' (the path's tangent - its chord). The law alone is not enough
    either: the model's y is the face's drive only up to a reparametrisation the path absorbs on
    single-DU takes (on off-chord paths the law alone and the pair vectors alone both hold out
    worse than the two together). One global parameter (profiled, the curves held: single-DU takes do not
    depend on it), the pair vectors refitted at each value; kappa is reported as
    :class:`Coupling`'s, read from the data in travel along the paths
    (:func:`mocap.analysis.model.coupling.coupling_kappa`), not the law's share of the fit."""

    meaning: ClassVar[str] = ("DUs share skin: each DU's drive loses kappa x the others' drives "
                              "(weighted by their relative pull at the marker) before it moves "
                              "the marker along its own path, y_n -> y_n (1 - kappa sum_other "
                              "y_n' o_n'm), and a 3D vector per DU pair and marker takes what "
                              "the law leaves; the kappa reported is the fraction of its travel a "
                              "DU loses while another is at full command, read from the takes")
    form: ClassVar[str] = "law, pull-weighted"
    per_curve: ClassVar[bool] = False


@dataclass(frozen=True)
class UniformCouplingLaw(CouplingLaw):
    """:class:`CouplingLaw` with the same loss at every marker (o = 1): a drive shared at the
    actuators (a common supply, a shared cable) rather than through the skin."""

    meaning: ClassVar[str] = ("DUs share their drive: each DU's drive loses kappa x the others' "
                              "drives, the same at every marker, before it moves the marker along "
                              "its own path, y_n -> y_n (1 - kappa sum_other y_n'), and a 3D "
                              "vector per DU pair and marker takes what the law leaves; the kappa "
                              "reported is the fraction of its travel a DU loses while another is "
                              "at full command, read from the takes")
    form: ClassVar[str] = "law, uniform"
    uniform: bool = True


@dataclass(frozen=True)
class Drift(Effect):
    name: ClassVar[str] = "drift"
    parameter: ClassVar[str] = "beta_per_trial"
    unit: ClassVar[str] = "command units per trial"
    meaning: ClassVar[str] = "the response's bias moves from trial to trial: beta + k (trial - 1)"
    stage: ClassVar[str] = "static"
    grid: ClassVar[tuple[float, ...]] = (-8.0, -3.0, 0.0, 3.0, 8.0)
    bounds: ClassVar[tuple[float, float]] = (-20.0, 20.0)
    min_plausible: ClassVar[float] = 0.3

    def beta_shift(self, trial):
        return self.value * (np.asarray(trial, float) - 1.0)

    def untestable(self, s):
        return None if s.repeated_trials else "no schedule was repeated in several trials"


@dataclass(frozen=True)
class Saturation(Effect):
    """``value`` is 1 / L (1/mm): 0 is no saturation; reported as ``limit_mm`` = L."""

    name: ClassVar[str] = "saturation"
    parameter: ClassVar[str] = "limit_mm"
    unit: ClassVar[str] = "mm"
    meaning: ClassVar[str] = "the skin stretches at most about L: d -> L tanh(|d| / L) d / |d|"
    stage: ClassVar[str] = "output"
    grid: ClassVar[tuple[float, ...]] = (0.0, 0.05, 0.12, 0.25, 0.5)
    bounds: ClassVar[tuple[float, float]] = (0.0, 1.0)
    min_plausible: ClassVar[float] = 0.01

    @property
    def limit_mm(self) -> float:
        return 1.0 / self.value if self.value > 0 else float("inf")

    def output(self, d):
        if self.value <= 0:
            return d
        L = self.limit_mm
        mag = np.linalg.norm(d, axis=-1, keepdims=True)
        safe = np.where(mag > 1e-12, mag, 1.0)
        return np.where(mag > 1e-12, d * (L * np.tanh(mag / L) / safe), d)

    def output_inverse(self, d):
        if self.value <= 0:
            return d, None
        L = self.limit_mm
        mag = np.linalg.norm(d, axis=-1, keepdims=True)
        x = np.clip(mag / L, 0.0, 0.995)
        safe = np.where(mag > 1e-12, mag, 1.0)
        v = np.where(mag > 1e-12, d * (L * np.arctanh(x) / safe), d)
        return v, (1.0 - x[..., 0] ** 2) ** 2

    def describe(self):
        out = super().describe()
        out["value"] = self.limit_mm
        return out


SQ3 = 6.0 * np.sqrt(3.0)  # scales y (1 - y) (1 - 2 y) to a peak of 1


@dataclass(frozen=True)
class Curvature(Effect):
    """Each marker's own path: d = y D + sum_k b_k(y) B_k, b_k = 4 y (1 - y) (the mid-range bow),
    6 sqrt(3) y (1 - y) (1 - 2 y) (an S bend) and 16 y^2 (1 - y)^2; with D any quartic curve
    through the rest position in y, so a path that bows, ends off the chord, or whose speed
    along it is not the logistic's (a per-DU compression of the displacement) is held.
    Part of the base model: the path shape is reported (|B_1| / |D|, the paper's linearity
    measures it), not named as a missing effect."""

    name: ClassVar[str] = "curvature"
    parameter: ClassVar[str] = "kappa"
    unit: ClassVar[str] = ""
    meaning: ClassVar[str] = ("each marker's path from the data: d = y D + sum_k b_k(y) B_k (quartic "
                              "in y through rest); |B_1| / |D| the mid-range bow")
    stage: ClassVar[str] = "path"
    per_curve: ClassVar[bool] = True
    n_bases: ClassVar[int] = 3
    min_plausible: ClassVar[float] = 0.02  # median bow / displacement

    def bases(self, y):
        u = y * (1.0 - y)
        return [4.0 * u, SQ3 * u * (1.0 - 2.0 * y), 16.0 * u * u]

    def bases_derivative(self, y):
        return [4.0 - 8.0 * y, SQ3 * (1.0 - 6.0 * y + 6.0 * y * y),
                32.0 * y * (1.0 - y) * (1.0 - 2.0 * y)]


@dataclass(frozen=True)
class TakeShift(Effect):
    """Each take shifts each of its DUs' biases by its own amount (the face is not quite the same
    from one take to the next: temperature, settling, re-seating; random, not a trend). Part of
    the base model, a nuisance parameter per (take, DU): identified on the take itself, also on a
    held-out take (its prediction is conditional on the take's bias). A drift is a trend of these
    shifts over the trial number."""

    name: ClassVar[str] = "takeshift"
    parameter: ClassVar[str] = "shift_sd"
    unit: ClassVar[str] = "command units"
    meaning: ClassVar[str] = ("each take shifts each DU's bias by its own amount (take-to-take "
                              "variation of the face)")
    stage: ClassVar[str] = "static"
    per_curve: ClassVar[bool] = True


CATALOGUE: dict[str, type[Effect]] = {
    cls.name: cls for cls in (Hysteresis, Lag, DeadTime, Backlash, Coupling, Drift, Saturation, Curvature,
                              TakeShift)
}
# a candidate's other forms (the same name and parameter, other equations): each is fitted and
# the one that gains the most on its own null in held-out takes is kept
FORMS: dict[str, tuple[type[Effect], ...]] = {
    "backlash": (Backlash, StickSlipBacklash),
    "coupling": (Coupling, CouplingLaw, UniformCouplingLaw),
}
BASE = ("hysteresis", "curvature", "takeshift")  # what every face has: the base model
CANDIDATES = ("lag", "deadtime", "backlash", "coupling", "drift", "saturation")


def command_moves(g) -> tuple[np.ndarray, bool, bool]:
    """One DU's command rows (time_s, command): the rate of each row that changes the command
    (command units/s, over the time since the row before), whether it ever falls, and whether
    it turns back inside the range (5-95 % of 255: a minor loop)."""
    g = g.sort_values("time_s", kind="stable")
    c = g["command"].to_numpy(float)
    dc = np.diff(c)
    dt = np.diff(g["time_s"].to_numpy(float))
    moving = dc != 0
    s = np.sign(dc[moving])
    levels = c[1:][moving][np.flatnonzero(s[1:] != s[:-1])]
    return (np.abs(dc[moving]) / np.maximum(dt[moving], 1e-6), bool((dc < 0).any()),
            bool(np.any((levels > 0.05 * 255) & (levels < 0.95 * 255))))


def summarize_schedules(rows_list, fps: float) -> ScheduleSummary:
    """What the commanded takes can reveal.

    rows_list : list of (rows DataFrame (time_s, du, command), trial or None, schedule key).
    """
    rates: set[int] = set()
    falling = inner = multi = False
    seen: dict[str, int] = {}
    for rows, _trial, key in rows_list:
        seen[key] = seen.get(key, 0) + 1
        active = [d for d, g in rows.groupby("du") if (g["command"] > 0).any()]
        multi |= len(active) >= 2
        for _du, g in rows.groupby("du"):
            step_rate, fall, turns_inside = command_moves(g)
            if step_rate.size == 0:
                continue
            falling |= fall
            # ramp rate: a change per step over the step's duration, binned by octaves
            rates.update(np.round(np.log2(step_rate)).astype(int).tolist())
            inner |= turns_inside
    return ScheduleSummary(n_rates=len(rates), falling=falling, inner_reversals=inner,
                           multi_du=multi, repeated_trials=any(v >= 2 for v in seen.values()))
