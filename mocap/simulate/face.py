"""The virtual face: marker layout on a curved half-face and each DU's true response.

Geometry (world frame of the ground square, mm; y up, the face looking towards +z): markers on
the right half of a face-shaped surface about 70 mm wide and 130 mm tall, centred at
``FACE_CENTER``, on a hexagonal lattice (spacing chosen so the requested number fits; the paper's
116 markers come out about 8.5 mm apart). One marker on the nose bridge sits in the shadow of the
nose.

True static response of marker m to DU n (all DUs at once are summed; see ``effects`` for what a
hidden effect changes)::

    w_nm(t)  = PI_nm[c_n](t)            Prandtl-Ishlinskii hysteresis of the command (plays of
                                        half-widths r_i = r_nm * (0, .5, 1, 1.5, 2), equal weights,
                                        starting at rest)
    y_nm(t)  = (S(w) - S(0)) / (S(255) - S(0)),   S(w) = 1 / (1 + exp(-alpha_nm (w - beta_nm)))
    d_m(t)   = sum_n y_nm(t) * D_nm          D_nm: peak displacement vector (mm), straight paths

On a full sweep 0 -> 255 -> 0 the forward branch is the logistic with bias about
``beta + r`` and the backward one about ``beta - r`` (the paper's hysteresis ``2 r``); under
arbitrary reversals the PI operator gives Preisach-type minor loops: after a reversal the output
moves at once with the slope of the zero-width play (weight 1/5) and steepens as wider plays
release. Per trial, each marker's amplitude varies by a factor ``1 + N(0, 0.003)`` and each
DU's bias by ``N(0, 0.4)`` command units, and the skin carries a physical jitter of 0.008 mm per
axis and frame: the trial-to-trial variation of 0.01 to 0.03 mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mocap.simulate import hysteresis_ops as ops
from mocap.simulate.dus import DU_BY_ID
from mocap.simulate.families import (
    BOUC_WEN_B,
    BOUC_WEN_G,
    PI_FAMILY,
    PLAY_FRACTIONS,
    PREISACH_CENTRE_SLOPE,
    PREISACH_ETA,
    FaceFamily,
    FamilyTraits,
    draw_traits,
    path_displacement,
)

FACE_CENTER = np.array([35.0, 145.0, 0.0])  # mm, world
HALF_WIDTH_MM = 70.0
HALF_HEIGHT_MM = 65.0
NOSE_BRIDGE_FACE_XY = (3.0, 22.0)  # face-plane mm
TRIAL_AMPLITUDE_SD = 0.003
TRIAL_BETA_SD = 0.4
SKIN_JITTER_MM = 0.008


def surface_height(x, y):
    """Face surface z (mm) over face-plane coordinates (x right of the midline, y up), mm."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    base = 45.0 * np.sqrt(np.clip(1.0 - (x / 85.0) ** 2 - (y / 100.0) ** 2, 0.0, None))
    nose_y = np.exp(-(((y - 4.0) / 24.0) ** 2))
    nose = 13.0 * np.exp(-((x / 11.0) ** 2)) * nose_y
    # eye socket: a shallow dip around the eye
    eye = -5.0 * np.exp(-(((x - 30.0) / 13.0) ** 2 + ((y - 22.0) / 9.0) ** 2))
    return base + nose + eye


def surface_normals(x, y, h: float = 0.01):
    """Unit outward normals (..., 3) of the surface at face-plane points (finite differences)."""
    dzdx = (surface_height(x + h, y) - surface_height(x - h, y)) / (2 * h)
    dzdy = (surface_height(x, y + h) - surface_height(x, y - h)) / (2 * h)
    n = np.stack([-dzdx, -dzdy, np.ones_like(dzdx)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _hex_lattice(spacing: float) -> np.ndarray:
    ys = np.arange(-HALF_HEIGHT_MM, HALF_HEIGHT_MM + 1e-9, spacing * np.sqrt(3) / 2)
    pts = []
    for i, y in enumerate(ys):
        xs = np.arange(2.0 + (spacing / 2 if i % 2 else 0.0), HALF_WIDTH_MM, spacing)
        pts.append(np.stack([xs, np.full_like(xs, y)], axis=1))
    p = np.concatenate(pts)
    inside = (p[:, 0] / HALF_WIDTH_MM) ** 2 + (p[:, 1] / HALF_HEIGHT_MM) ** 2 <= 1.0
    return p[inside]


def marker_layout(n_markers: int) -> tuple[np.ndarray, int]:
    """Face-plane positions (n_markers, 2) mm on a hex lattice, and the nose-bridge index.

    The spacing is the largest for which the half-face holds ``n_markers`` points; extra points
    farthest from the face centre are dropped. One point is moved onto the nose bridge.
    """
    if n_markers < 5:
        raise ValueError(f"virtual face: expected at least 5 markers, got {n_markers}")
    lo, hi = 2.0, 40.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if len(_hex_lattice(mid)) >= n_markers:
            lo = mid
        else:
            hi = mid
    p = _hex_lattice(lo)
    p = p[np.argsort(np.hypot(p[:, 0] / HALF_WIDTH_MM, p[:, 1] / HALF_HEIGHT_MM), kind="stable")]
    p = p[:n_markers]
    nb = int(np.argmin(np.hypot(p[:, 0] - NOSE_BRIDGE_FACE_XY[0], p[:, 1] - NOSE_BRIDGE_FACE_XY[1])))
    p[nb] = NOSE_BRIDGE_FACE_XY
    # names in reading order: top to bottom, midline outwards
    order = np.lexsort((p[:, 0], -np.round(p[:, 1], 3)))
    p = p[order]
    nb = int(np.flatnonzero(order == nb)[0])
    return p, nb


@dataclass(frozen=True)
class VirtualFace:
    """True parameters of the virtual face.

    Attributes
    ----------
    marker_names : (n_markers,) str, ``M001``... in reading order.
    rest_mm : (n_markers, 3) rest positions, world mm.
    normals : (n_markers, 3) outward surface normals at rest.
    nose_bridge : index of the nose-bridge marker.
    du_ids : (n_dus,) DU ids.
    D_mm : (n_dus, n_markers, 3) peak displacement vectors (full command), mm.
    alpha : (n_dus, n_markers) logistic sensitivity, 1/command unit.
    beta : (n_dus, n_markers) logistic bias of the hysteresis output, command units.
    r_half : (n_dus, n_markers) mean play half-width r (loop width 2 r), command units.
    family : the base-face family (``mocap.simulate.families``); ``traits`` its per-face arrays
        (None for ``pi``).
    """

    marker_names: tuple[str, ...]
    rest_mm: np.ndarray
    normals: np.ndarray
    nose_bridge: int
    du_ids: tuple[int, ...]
    D_mm: np.ndarray
    alpha: np.ndarray
    beta: np.ndarray
    r_half: np.ndarray
    meta: dict = field(default_factory=dict)
    family: FaceFamily = PI_FAMILY
    traits: FamilyTraits | None = None

    @property
    def n_markers(self) -> int:
        return len(self.marker_names)

    def du_index(self, du: int) -> int:
        return self.du_ids.index(du)

    def hysteresis_state(self, c: np.ndarray, du_rows: np.ndarray) -> np.ndarray:
        """PI output w (n_samples, n_sel, n_markers) for command series c (n_samples, n_sel).

        ``du_rows`` are the DU indices (into ``du_ids``) of c's columns.
        """
        thr = self.r_half[du_rows][..., None] * PLAY_FRACTIONS  # (n_sel, n_markers, n_plays)
        return ops.pi_mean(c, thr)

    def static_map(self, w: np.ndarray, du_rows: np.ndarray, beta_shift=0.0) -> np.ndarray:
        """Normalised response y = (S(w) - S(0)) / (S(255) - S(0)), same shape as ``w``."""
        return ops.logistic01(w, self.alpha[du_rows], self.beta[du_rows] + beta_shift)

    def response(self, a: np.ndarray, du_rows: np.ndarray, beta_shift=0.0, step: int = 1) -> np.ndarray:
        """The family's normalised response y (n_out, n_sel, n_markers) to actuator inputs a
        (n_samples, n_sel) command units, every ``step``-th sample (n_out = ceil(n_samples / step)).

        ``beta_shift`` : scalar or (n_sel, 1) bias shift (trial shift, drift), command units.
        """
        hyst = self.family.hysteresis
        if hyst == "pi":
            return self.static_map(self.hysteresis_state(a, du_rows)[::step], du_rows, beta_shift)
        alpha = self.alpha[du_rows]
        beta = self.beta[du_rows] + beta_shift
        r = self.r_half[du_rows]
        x = np.broadcast_to(np.asarray(a, float)[:, :, None], a.shape + (self.n_markers,))
        if hyst == "branchplay":
            ab = self.traits.alpha_bwd[du_rows]
            return ops.branch_play(x, lambda v: ops.logistic01(v, alpha, beta + r),
                                   lambda v: ops.logistic01(v, ab, beta - r))[::step]
        if hyst == "preisach":
            h = r[..., None] * (1.0 + 0.5 * PREISACH_ETA)
            w = np.exp(-0.5 * PREISACH_ETA**2)
            mu = beta[..., None] + PREISACH_CENTRE_SLOPE * (h - r[..., None])
            spread = np.pi / np.sqrt(3.0) / alpha
            return ops.preisach_gaussian(a, h, w / w.sum(), mu, spread, step=step)
        if hyst == "boucwen":
            z = ops.bouc_wen_state(x, BOUC_WEN_B / r, BOUC_WEN_G / r)[::step]
            return ops.logistic01(x[::step] - z, alpha, beta)
        raise ValueError(f"virtual face: unknown hysteresis {hyst!r}")

    def displacement(self, y: np.ndarray, D: np.ndarray, du_rows: np.ndarray) -> np.ndarray:
        """Per-DU displacements (n_samples, n_sel, n_markers, 3) mm along the family's paths.

        y : (n_samples, n_sel, n_markers); D : (n_sel, n_markers, 3) this take's peak vectors.
        """
        vec = self.traits.path_vec[du_rows] if self.traits is not None else np.zeros_like(D)
        return path_displacement(self.family.path, y, D, vec)

    def travel_kappa(self, kappa: float, pull_weighted: bool = False, groups=None) -> float:
        """A coupling's kappa as data can read it: in travel along each marker's path rather
        than in this simulator's drive.

        The travel is the displacement's projection on the marker's chord (its displacement at
        full command) over |chord|^2. For each group of DUs driven together (``groups``: DU id
        tuples, default every pair of the face's DUs) with all of them at full command, DU n's
        drive at marker m drops from 1 to 1 - kappa x_nm, x_nm = sum over the others of o_n'm
        (o = 1, or the other DU's relative pull |D_n'm| / max_m |D_n'm| for the pull-weighted
        law), and the marker loses L_nm of its travel; returned is the least-squares slope of L
        on x over the groups, DUs and markers, weighted by |D_nm|^2 (with o = 1 in pairs: the
        weighted mean loss). A loss of drive shows as a loss of travel, and the drive is this
        simulator's parametrisation of the path (a model reparametrises it freely). Equal to
        kappa on straight and bowed paths (the bow is perpendicular to the chord); on paths that
        end off the chord the travel runs ahead of the drive (3 y (1 - y)^2 cos t + 2 y^2
        (1 - y) + y^3), so less is lost.
        """
        n, M = self.D_mm.shape[:2]
        mag = np.linalg.norm(self.D_mm, axis=-1)  # (n, M)
        o = mag / mag.max(axis=1, keepdims=True) if pull_weighted else np.ones((n, M))
        full = self.displacement(np.ones((1, n, M)), self.D_mm, np.arange(n))[0]  # (n, M, 3)
        c2 = np.sum(full**2, axis=-1)
        if groups is None:
            groups = [(a, b) for a in self.du_ids for b in self.du_ids if a < b]
        num = den = 0.0
        for group in groups:
            rows = [self.du_index(d) for d in group]
            for a in rows:
                x = sum(o[b] for b in rows if b != a)  # (M,)
                y = np.ones((1, n, M))
                y[0, a] = 1.0 - kappa * x
                d = self.displacement(y, self.D_mm, np.arange(n))[0, a]  # (M, 3)
                lost = 1.0 - np.sum(d * full[a], axis=-1) / np.where(c2[a] > 0, c2[a], 1.0)
                num += np.sum(c2[a] * x * lost)
                den += np.sum(c2[a] * x * x)
        return float(num / den) if den > 0 else float(kappa)


def make_face(rng: np.random.Generator, n_markers: int, du_ids, family: FaceFamily = PI_FAMILY,
              family_rng: np.random.Generator | None = None) -> VirtualFace:
    """Draw a virtual face: layout, DU fields and per-marker response parameters.

    The base face comes from ``rng`` alone, whatever the family; a family other than ``pi`` then
    adds its per-marker scatter and traits from ``family_rng`` (required for those families).
    """
    xy, nose_bridge = marker_layout(n_markers)
    z = surface_height(xy[:, 0], xy[:, 1])
    normals = surface_normals(xy[:, 0], xy[:, 1])
    rest = np.column_stack([xy, z]) + FACE_CENTER
    n = len(du_ids)
    D = np.zeros((n, n_markers, 3))
    alpha = np.zeros((n, n_markers))
    beta = np.zeros((n, n_markers))
    r_half = np.zeros((n, n_markers))
    for i, du in enumerate(du_ids):
        spec = DU_BY_ID[du]
        a_xy = np.asarray(spec.attach_mm, float)
        dist = np.hypot(*(xy - a_xy).T)
        amp = spec.peak_mm * np.exp(-0.5 * (dist / spec.sigma_mm) ** 2)
        amp *= np.exp(rng.normal(0.0, 0.08, n_markers))
        u = np.asarray(spec.direction, float)
        u = u / np.linalg.norm(u)
        toward = np.column_stack([a_xy - xy, np.zeros(n_markers)]) / spec.sigma_mm
        d = u + 0.25 * toward
        d -= np.sum(d * normals, axis=1, keepdims=True) * normals  # tangent to the skin
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        D[i] = amp[:, None] * d
        alpha[i] = spec.alpha * np.exp(rng.normal(0.0, 0.06, n_markers))
        beta[i] = spec.beta + rng.normal(0.0, spec.spread_beta, n_markers)
        r_half[i] = 0.5 * spec.hysteresis * np.exp(rng.normal(0.0, 0.05, n_markers))
    names = tuple(f"M{k + 1:03d}" for k in range(n_markers))
    traits = None
    if family.hysteresis != "pi" or family.path != "straight" or family.varies:
        if family_rng is None:
            raise ValueError(f"virtual face: family {family.name!r} needs its own random stream")
        alpha = alpha * np.exp(family_rng.normal(0.0, family.alpha_scatter, alpha.shape))
        beta = beta + family_rng.normal(0.0, family.beta_scatter, beta.shape)
        r_half = r_half * np.exp(family_rng.normal(0.0, family.width_scatter, r_half.shape))
        D = D * np.exp(family_rng.normal(0.0, family.amp_scatter, alpha.shape))[..., None]
        traits = draw_traits(family_rng, family, D, normals, alpha)
    return VirtualFace(
        marker_names=names,
        rest_mm=rest,
        normals=normals,
        nose_bridge=nose_bridge,
        du_ids=tuple(int(d) for d in du_ids),
        D_mm=D,
        alpha=alpha,
        beta=beta,
        r_half=r_half,
        family=family,
        traits=traits,
    )
