"""Hidden effects: what the true virtual face does beyond the paper's static model.

Each effect has a stable keyword (OUTPUTS.md's effect names), one parameter with a default
strength, and an equation. It is applied to the true face only; the pipeline never sees it.
The true response of a take is computed in three stages (``mocap.simulate.motion``):

1. command side, per DU (``c`` command units, on a fine time grid of step ``dt``):
   - ``deadtime`` L (s):   a(t) = c(t - L)
   - ``lag`` tau (s):      tau da/dt = c - a   (first-order actuator dynamics, exact for c held
                           over each sample: a_k = a_{k-1} + (1 - exp(-dt/tau)) (c_{k-1} - a_{k-1}))
   - ``backlash`` b (command units): a = play_b(c) (a dead band of width 2 b at every reversal,
                           before the skin's own hysteresis)
2. static map, per DU and marker: y = normalised logistic of the PI hysteresis of ``a``
   - ``drift`` k (command units per trial): beta_nm -> beta_nm + k (trial - 1) (the response
                           shifts as the skin settles over repeated trials)
3. displacement, per marker, from the DUs' y_n and peak vectors D_nm:
   - none:                 d_m = sum_n y_n D_nm
   - ``coupling`` kappa:   d_m = sum_n y_n D_nm (1 - kappa sum_{n' != n} y_n' o_n'm), with
                           o_n'm = |D_n'm| / max_m |D_n'm| (skin already pulled by one DU yields
                           less to another: multi-DU action is less than the sum)
   - ``saturation`` L (mm): d_m -> d_m L tanh(|d_m| / L) / |d_m| (the skin stretches at most
                           about L)
   - ``curvature`` kappa:  d_m = sum_n (y_n D_nm + 4 kappa y_n (1 - y_n) |D_nm| b_nm), b_nm the
                           unit tangent perpendicular to D_nm (paths bow sideways by kappa |D|
                           at mid-range)

With a face family whose paths are not straight, ``sum_n y_n D_nm`` reads ``sum_n p_nm(y_n)``,
the family's path (``families``). ``form="alt"`` (``--effect-form alt``) replaces each equation
by a second form the analysis model does not share, with the same parameter and unit
(``effects_alt``). ``form="alt2"`` is a third form where the model has since grown the alt
form's equation (coupling: the analysis now fits the uniform law of the alt form, so an honest
test of it needs a law it does not have); effects without a third form use their alt form.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocap.simulate import effects_alt as alt
from mocap.simulate.hysteresis_ops import play

EFFECTS: dict[str, tuple[str, float, str]] = {
    # name: (parameter, default strength, unit)
    "none": ("", 0.0, ""),
    "lag": ("tau_s", 0.08, "s"),
    "deadtime": ("delay_s", 0.06, "s"),
    "backlash": ("halfwidth", 12.0, "command units"),
    "coupling": ("kappa", 0.35, ""),
    "drift": ("beta_per_trial", 4.0, "command units per trial"),
    "saturation": ("limit_mm", 4.0, "mm"),
    "curvature": ("kappa", 0.3, ""),
}

MEANINGS = {
    "none": "no effect beyond the paper's static model with Prandtl-Ishlinskii hysteresis",
    "lag": "first-order actuator dynamics: the actuator approaches its command with time constant tau",
    "deadtime": "pure transport delay between command and actuator",
    "backlash": "mechanical dead band at every command reversal",
    "coupling": "DUs share skin: a marker pulled by one DU moves less under another",
    "drift": "the response's bias moves from trial to trial as the skin settles",
    "saturation": "the skin stretches at most about L: large total displacements flatten",
    "curvature": "marker paths bow sideways at mid-range instead of running straight",
}


FORMS = ("model", "alt", "alt2")

ALT_TRUTH = {
    "none": "",
    "lag": "critically damped second order (tau/2 d/dt + 1)^2 a = c; tau is the mean delay "
           "(the first-order tau with the same mean delay)",
    "deadtime": "distributed delay: a(t) = mean of c over [t - 1.25 L, t - 0.75 L]; L is the mean delay",
    "backlash": "stick-slip dead band: after a reversal the actuator holds until the command has "
                "come back 2 b, then jumps to the command; b is half the dead band",
    "coupling": "y_n (1 - kappa sum_{n' != n} y_n') at every marker; kappa is the fraction a DU's "
                "response loses while another is at full command",
    "drift": "per-marker bias drift k (1 + xi_m / 2) (trial - 1), xi_m = sqrt(2) sin(2.39996 m); "
             "k is the mean over markers",
    "saturation": "per DU before summation: d_n / sqrt(1 + (|d_n| / L)^2); L is one DU's "
                  "asymptotic largest displacement",
    "curvature": "skewed bow 27/4 kappa y (1 - y)^2 |D| sideways; kappa is the largest sideways "
                 "deviation over |D|",
}

ALT2_TRUTH = {
    "coupling": "strain-stiffening shared skin: y_n (1 - kappa sum_{n' != n} y_n'^2) at every "
                "marker (the other DU's pull costs little at first, most near full command); kappa "
                "is the fraction a DU's response loses while another is at full command",
}


@dataclass(frozen=True)
class HiddenEffect:
    """A hidden effect and its strength (see the module docstring for equations).

    form : "model" (the equations above), "alt" (``effects_alt``: the same parameter, a form
    the analysis model does not share) or "alt2" (a third form where one is written, see
    :data:`ALT2_TRUTH`; the alt form otherwise).
    """

    name: str = "none"
    strength: float = 0.0
    form: str = "model"

    def __post_init__(self) -> None:
        if self.name not in EFFECTS:
            raise ValueError(f"hidden effect: expected one of {sorted(EFFECTS)}, got {self.name!r}")
        if self.strength < 0 or not np.isfinite(self.strength):
            raise ValueError(f"hidden effect {self.name}: expected strength >= 0, got {self.strength}")
        if self.form not in FORMS:
            raise ValueError(f"hidden effect {self.name}: expected form among {FORMS}, got {self.form!r}")

    @classmethod
    def default(cls, name: str, strength: float | None = None, form: str = "model") -> "HiddenEffect":
        if name not in EFFECTS:
            raise ValueError(f"hidden effect: expected one of {sorted(EFFECTS)}, got {name!r}")
        return cls(name, EFFECTS[name][1] if strength is None else float(strength), form)

    @property
    def parameter(self) -> str:
        return EFFECTS[self.name][0]

    def describe(self) -> dict:
        return {
            "name": self.name,
            "strength": self.strength,
            "parameters": {self.parameter: self.strength} if self.name != "none" else {},
            "unit": EFFECTS[self.name][2],
            "meaning": MEANINGS[self.name],
            "form": self.form,
            **({"alt_equation": self.equation} if self.form != "model" else {}),
        }

    @property
    def alt(self) -> bool:
        """Whether the effect acts in a form other than the model's (alt or alt2)."""
        return self.form != "model"

    @property
    def equation(self) -> str:
        """The written equation of an alt or alt2 form (empty for the model form)."""
        if self.form == "alt2" and self.name in ALT2_TRUTH:
            return ALT2_TRUTH[self.name]
        return ALT_TRUTH[self.name] if self.alt else ""

    # -- stage 1: command side -------------------------------------------------------------
    def command(self, c: np.ndarray, t: np.ndarray, sampler) -> np.ndarray:
        """Actuator input (n_samples, n_dus) from commands c sampled at times t (s).

        ``sampler(times) -> (n_samples, n_dus)`` evaluates the command schedule at any times
        (used by dead time to shift exactly).
        """
        if self.alt:
            if self.name == "deadtime" and self.strength > 0:
                return alt.distributed_delay(t, sampler, self.strength)
            if self.name == "lag" and self.strength > 0:
                return alt.lag_second_order(c, t, self.strength)
            if self.name == "backlash":
                return alt.stick_slip(c, self.strength)
            return c
        if self.name == "deadtime":
            return sampler(t - self.strength)
        if self.name == "lag" and self.strength > 0:
            dt = float(t[1] - t[0]) if t.size > 1 else 1.0
            g = 1.0 - np.exp(-dt / self.strength)
            # a_k = (1-g) a_{k-1} + g c_{k-1}, from rest (a_0 = 0): exact zero-order hold
            from scipy.signal import lfilter

            return lfilter([0.0, g], [1.0, -(1.0 - g)], c, axis=0)
        if self.name == "backlash":
            return play(c, self.strength, 0.0)
        return c

    # -- stage 2: static map -----------------------------------------------------------------
    def beta_shift(self, trial: int, n_markers: int | None = None):
        """The static map's bias shift in ``trial``, command units: a float, or (n_markers,)
        for the alt drift (which then needs ``n_markers``)."""
        if self.name == "drift":
            k = self.strength * (max(int(trial), 1) - 1)
            if self.alt:
                if n_markers is None:
                    raise ValueError("hidden effect drift (alt form): the bias shift needs n_markers")
                return k * alt.marker_drift_weights(n_markers)
            return k
        return 0.0

    # -- stage 3: displacement -------------------------------------------------------------
    def displacement(self, y: np.ndarray, D: np.ndarray, normals: np.ndarray,
                     paths=None) -> np.ndarray:
        """Marker displacements (n_samples, n_markers, 3) mm.

        y : (n_samples, n_dus, n_markers) normalised responses of the take's DUs.
        D : (n_dus, n_markers, 3) their peak vectors, mm.
        normals : (n_markers, 3) skin normals (for the sideways direction of ``curvature``).
        paths : None for straight paths (d = y D per DU), else ``paths(y) -> (n_samples, n_dus,
            n_markers, 3)`` the face family's per-DU displacements.
        """
        return compose_displacement((self,), y, D, normals, paths)


def compose_displacement(effects, y: np.ndarray, D: np.ndarray, normals: np.ndarray,
                         paths=None) -> np.ndarray:
    """Stage 3 of any set of effects: coupling scales y, curvature adds a bow, saturation caps.

    Shapes as :meth:`HiddenEffect.displacement`. Effects absent from ``effects`` are identity.
    """
    by_name = {e.name: e.strength for e in effects}
    forms = {e.name: e.form for e in effects}
    alt_forms = {n for n, f in forms.items() if f != "model"}
    if "coupling" in by_name and y.shape[1] > 1:
        if forms["coupling"] == "alt2":
            y_eff = alt.stiffening_coupling(y, by_name["coupling"])
        elif "coupling" in alt_forms:
            y_eff = alt.coupled_drives(y, by_name["coupling"])
        else:
            mag = np.linalg.norm(D, axis=-1)  # (n_dus, M)
            o = mag / mag.max(axis=1, keepdims=True)
            yo = y * o[None]  # (S, N, M)
            others = yo.sum(axis=1, keepdims=True) - yo
            y_eff = y * (1.0 - by_name["coupling"] * others)
    else:
        y_eff = y
    if "saturation" in alt_forms and by_name["saturation"] > 0:
        per_du = y_eff[..., None] * D if paths is None else paths(y_eff)
        d = alt.compress_per_du(per_du, by_name["saturation"]).sum(axis=1)
    elif paths is None:
        d = np.einsum("snm,nmk->smk", y_eff, D)
    else:
        d = paths(y_eff).sum(axis=1)
    if "curvature" in by_name:
        side = np.cross(normals[None], D)  # (N, M, 3) perpendicular, tangent
        norm = np.linalg.norm(side, axis=-1, keepdims=True)
        side = np.where(norm > 0, side / np.where(norm > 0, norm, 1.0), 0.0)
        mag = np.linalg.norm(D, axis=-1, keepdims=True)
        if "curvature" in alt_forms:
            bow = alt.skewed_bow(y, by_name["curvature"])
        else:
            bow = 4.0 * by_name["curvature"] * y * (1.0 - y)
        d = d + np.einsum("snm,nmk->smk", bow, side * mag)
    if "saturation" in by_name and by_name["saturation"] > 0 and "saturation" not in alt_forms:
        L = by_name["saturation"]
        mag = np.linalg.norm(d, axis=-1, keepdims=True)
        scale = np.where(mag > 1e-12, L * np.tanh(mag / L) / np.where(mag > 1e-12, mag, 1.0), 1.0)
        d = d * scale
    return d


COMMAND_ORDER = ("deadtime", "lag", "backlash")  # stage 1 order when several act at once


@dataclass(frozen=True)
class CombinedEffect:
    """Several hidden effects at once, applied in stage order (the same interface as one).

    Stage 1 applies dead time, then lag, then backlash; stage 2 adds the drifts; stage 3 is
    :func:`compose_displacement`.
    """

    effects: tuple[HiddenEffect, ...]

    def __post_init__(self) -> None:
        names = [e.name for e in self.effects]
        if len(set(names)) != len(names) or "none" in names or not names:
            raise ValueError(f"hidden effects: expected distinct effects other than none, got {names}")

    @property
    def name(self) -> str:
        return "+".join(e.name for e in self.effects)

    @property
    def strength(self) -> float:
        return self.effects[0].strength

    def describe(self) -> dict:
        parts = [e.describe() for e in self.effects]
        return {"name": self.name, "parameters": {p["name"]: p["parameters"] for p in parts},
                "effects": parts, "meaning": "; ".join(p["meaning"] for p in parts)}

    def command(self, c: np.ndarray, t: np.ndarray, sampler) -> np.ndarray:
        out = c
        for name in COMMAND_ORDER:
            for e in self.effects:
                if e.name != name:
                    continue
                # dead time reads the schedule itself (hence first in COMMAND_ORDER)
                out = e.command(out, t, sampler)
        return out

    def beta_shift(self, trial: int, n_markers: int | None = None):
        total = sum(e.beta_shift(trial, n_markers) for e in self.effects)
        return total if np.ndim(total) else float(total)

    def displacement(self, y: np.ndarray, D: np.ndarray, normals: np.ndarray,
                     paths=None) -> np.ndarray:
        return compose_displacement(self.effects, y, D, normals, paths)


def make_effect(names, strengths=None, form: str = "model"):
    """One :class:`HiddenEffect` or a :class:`CombinedEffect` from names and optional strengths.

    ``names`` : str ("lag", "lag,drift") or sequence; ``strengths`` : None, a number, a string
    "0.08,4" or a sequence, one per name (None entries take the default); ``form`` : "model",
    "alt" or "alt2" for every effect (see ``effects_alt``).
    """
    if isinstance(names, str):
        names = [n.strip() for n in names.split(",") if n.strip()]
    names = list(names) or ["none"]
    if strengths is None:
        strengths = [None] * len(names)
    elif isinstance(strengths, str):
        strengths = [float(v) if v.strip() else None for v in strengths.split(",")]
    elif np.isscalar(strengths):
        strengths = [float(strengths)]
    strengths = list(strengths)
    if len(strengths) != len(names):
        raise ValueError(f"hidden effects: {len(names)} names ({','.join(names)}) but "
                         f"{len(strengths)} strengths")
    effects = [HiddenEffect.default(n, s, form) for n, s in zip(names, strengths)]
    if len(effects) == 1:
        return effects[0]
    return CombinedEffect(tuple(effects))
