"""Base-face families: faces whose hysteresis and marker paths the analysis model does not share.

A family is a hysteresis operator and a path shape, plus (for every family but ``pi``) a
per-trial common shift of the branch biases and a per-marker scatter of gains, biases and loop
widths on top of the base face. Names are ``HYSTERESIS-PATH`` over the product of
``HYSTERESES`` x ``PATHS`` (``FAMILIES``: 12 names, what a cross-family sweep iterates), plus
``pi`` (the default: PI hysteresis on straight paths, no trial shift, no extra
scatter), and ``random`` (one of ``FAMILIES`` drawn from the seed; the draw is written to the truth
only). Per DU n and marker m, with the take's actuator input a_n(t) (command units) and bias shift
s (the trial's common shift plus any drift; command units)::

    pi          y = L(PI(a); alpha, beta + s)     PI = mean of plays of half-widths r (0,.5,1,1.5,2)
    branchplay  y_k = clip(y_{k-1}, F(a_k), B(a_k)),  F = L(.; alpha, beta + r + s),
                B = L(.; alpha_b, beta - r + s): flat after a reversal until it meets the other
                branch (alpha_b: the backward branch's own sensitivity)
    preisach    y = Preisach(a): relay half-widths h_j = r (1 + eta_j / 2), eta_j = -1.9..1.9
                (8 nodes), weights exp(-eta_j^2 / 2); relay centres on each half-width line
                N(beta + s + 0.6 (h_j - r), (pi / sqrt 3 / alpha)^2) (correlated: wider relays
                switch later); normalised to 0 at rest and 1 at full command
    boucwen     y = L(a - z; alpha, beta + s), dz = A da - b |da| z - g da |z|, A = 1/2,
                b = 0.35 / r, g = 0.15 / r (|z| <= A / (b + g) = r; rate-independent; the
                piezo-actuator form x - z: after a reversal a - z moves at once with slope
                1 - 2 A b / (b + g) = 0.3 of the command's and steepens smoothly to 1 as it
                approaches the other branch; from rest it starts with slope 1 - A = 0.5)

    L(x; alpha, beta) = (S(x) - S(0)) / (S(255) - S(0)),  S(x) = 1 / (1 + exp(-alpha (x - beta)))

Paths (displacement of marker m by DU n at normalised response y; D the peak vector, mm)::

    straight    d = y D
    bow         d = y D + 4 y (1 - y) B,  B = k |D| e,  e the unit skin tangent perpendicular to D,
                k = +-U(0.3, 0.6) (sign per DU): the path bows k |D| sideways at y = 0.5
    offchord    d = 3 y (1 - y)^2 P1 + 3 y^2 (1 - y) (2 D / 3) + y^3 D   (cubic Bezier), P1 =
                |D| (cos t D/|D| + sin t e), t = +-U(40, 70) degrees (sign per DU): the path
                leaves at angle t to its chord and ends at D, off that initial direction; its
                sideways deviation 3 |D| sin t y (1 - y)^2 peaks early (y = 1/3)

Trial-to-trial variation (every family but pi): each take adds to each of its DUs' biases a
common shift s ~ N(0, 1.5^2) command units (the face is not the same from one trial to the next), on
top of the base face's N(0, 0.4). Per-marker scatter (every family but pi): alpha x
exp(N(0, 0.12)), beta + N(0, 4), r x exp(N(0, 0.25)), |D| x exp(N(0, 0.1)).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

HYSTERESES = ("pi", "branchplay", "preisach", "boucwen")
PATHS = ("straight", "bow", "offchord")
PLAY_FRACTIONS = np.array([0.0, 0.5, 1.0, 1.5, 2.0])  # PI play half-widths / r (mean 1)
PREISACH_ETA = np.linspace(-1.9, 1.9, 8)
PREISACH_CENTRE_SLOPE = 0.6
BOUC_WEN_B, BOUC_WEN_G = 0.35, 0.15  # times 1 / r (with A = 1/2: |z| <= r)
BOW_RANGE = (0.3, 0.6)  # sideways bow / |D|: spatial linearity 0.86-0.96 (paper 0.8-0.9)
OFFCHORD_DEG = (40.0, 70.0)
OFFCHORD_P1 = 1.0  # |P1| / |D|: with those angles spatial linearity 0.94-0.98


@dataclass(frozen=True)
class FaceFamily:
    """A base-face family (see the module docstring for the equations).

    trial_shift_sd : sd of the per-take common bias shift per DU, command units.
    alpha_scatter, width_scatter, amp_scatter : log-normal sd of the extra per-marker scatter of
        sensitivity, loop half-width and peak displacement; beta_scatter : sd of the extra bias
        scatter, command units.
    """

    name: str
    hysteresis: str
    path: str
    trial_shift_sd: float = 1.5
    alpha_scatter: float = 0.12
    beta_scatter: float = 4.0
    width_scatter: float = 0.25
    amp_scatter: float = 0.1

    def __post_init__(self) -> None:
        if self.hysteresis not in HYSTERESES:
            raise ValueError(f"face family: expected hysteresis among {HYSTERESES}, got {self.hysteresis!r}")
        if self.path not in PATHS:
            raise ValueError(f"face family: expected path among {PATHS}, got {self.path!r}")

    @property
    def varies(self) -> bool:
        """Whether the family adds trial shifts or scatter to the base face."""
        return bool(self.trial_shift_sd or self.alpha_scatter or self.beta_scatter
                    or self.width_scatter or self.amp_scatter)

    def describe(self) -> dict:
        return {"name": self.name, "hysteresis": self.hysteresis, "path": self.path,
                "trial_shift_sd": self.trial_shift_sd, "alpha_scatter": self.alpha_scatter,
                "beta_scatter": self.beta_scatter, "width_scatter": self.width_scatter,
                "amp_scatter": self.amp_scatter}


PI_FAMILY = FaceFamily("pi", "pi", "straight", 0.0, 0.0, 0.0, 0.0, 0.0)
FAMILIES: dict[str, FaceFamily] = {
    f"{h}-{p}": FaceFamily(f"{h}-{p}", h, p) for h in HYSTERESES for p in PATHS
}
FAMILY_NAMES = ("pi",) + tuple(FAMILIES) + ("random",)  # what --face-family accepts


def family_stream(seed: int, what: str) -> np.random.Generator:
    """The random stream of a family draw (independent of the base face's stream)."""
    return np.random.default_rng([int(seed), zlib.crc32(f"face-family:{what}".encode())])


def resolve_family(name: str, seed: int) -> FaceFamily:
    """The family called ``name``; ``random`` draws one of ``FAMILIES`` from ``seed``."""
    if name == "random":
        keys = sorted(FAMILIES)
        return FAMILIES[keys[int(family_stream(seed, "choice").integers(len(keys)))]]
    if name == "pi":
        return PI_FAMILY
    if name not in FAMILIES:
        raise ValueError(f"face family: expected one of {', '.join(FAMILY_NAMES)}, got {name!r}")
    return FAMILIES[name]


@dataclass(frozen=True)
class FamilyTraits:
    """Per-face arrays a family adds to the base face.

    alpha_bwd : (n_dus, n_markers) backward-branch sensitivity (branchplay), 1/command unit.
    path_vec : (n_dus, n_markers, 3) mm: B (bow) or P1 (offchord); zeros for straight paths.
    """

    alpha_bwd: np.ndarray
    path_vec: np.ndarray


def skin_side(D: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Unit skin tangents (n_dus, n_markers, 3) perpendicular to D (n_dus, n_markers, 3)."""
    side = np.cross(normals[None], D)
    norm = np.linalg.norm(side, axis=-1, keepdims=True)
    return np.where(norm > 0, side / np.where(norm > 0, norm, 1.0), 0.0)


def draw_traits(rng: np.random.Generator, family: FaceFamily, D: np.ndarray, normals: np.ndarray,
                alpha: np.ndarray) -> FamilyTraits:
    """Draw a family's per-face arrays for peak vectors D (n_dus, n_markers, 3) mm."""
    n, m = alpha.shape
    alpha_bwd = alpha * np.exp(rng.normal(0.0, 0.15, (n, m)))
    sign = np.where(rng.random((n, 1)) < 0.5, -1.0, 1.0)
    side = skin_side(D, normals)
    mag = np.linalg.norm(D, axis=-1, keepdims=True)
    if family.path == "bow":
        k = sign * rng.uniform(*BOW_RANGE, (n, m))
        vec = k[..., None] * mag * side
    elif family.path == "offchord":
        t = np.deg2rad(sign * rng.uniform(*OFFCHORD_DEG, (n, m)))[..., None]
        unit = np.where(mag > 0, D / np.where(mag > 0, mag, 1.0), 0.0)
        vec = OFFCHORD_P1 * mag * (np.cos(t) * unit + np.sin(t) * side)
    else:
        vec = np.zeros_like(D)
    return FamilyTraits(alpha_bwd=alpha_bwd, path_vec=vec)


def path_displacement(path: str, y: np.ndarray, D: np.ndarray, vec: np.ndarray) -> np.ndarray:
    """Per-DU displacements (n_samples, n_dus, n_markers, 3) mm along a family's paths.

    y : (n_samples, n_dus, n_markers) normalised responses; D, vec : (n_dus, n_markers, 3) the
    peak vectors and the path vectors of ``FamilyTraits``.
    """
    yy = y[..., None]
    if path == "straight":
        return yy * D
    if path == "bow":
        return yy * D + 4.0 * yy * (1.0 - yy) * vec
    if path == "offchord":
        return (3.0 * yy * (1.0 - yy) ** 2 * vec + 2.0 * yy**2 * (1.0 - yy) * D + yy**3 * D)
    raise ValueError(f"face family: expected path among {PATHS}, got {path!r}")
