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

from mocap.analysis.hysteresis import play
from mocap.simulate.dus import DU_BY_ID

FACE_CENTER = np.array([35.0, 145.0, 0.0])  # mm, world
HALF_WIDTH_MM = 70.0
HALF_HEIGHT_MM = 65.0
NOSE_BRIDGE_FACE_XY = (3.0, 22.0)  # face-plane mm
PLAY_FRACTIONS = np.array([0.0, 0.5, 1.0, 1.5, 2.0])  # play half-widths / r (mean 1)
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
        x = np.broadcast_to(c[:, :, None, None], c.shape + thr.shape[1:])
        return play(x, thr, 0.0).mean(axis=-1)

    def static_map(self, w: np.ndarray, du_rows: np.ndarray, beta_shift=0.0) -> np.ndarray:
        """Normalised response y = (S(w) - S(0)) / (S(255) - S(0)), same shape as ``w``."""
        a = self.alpha[du_rows]
        b = self.beta[du_rows] + beta_shift
        lo = 1.0 / (1.0 + np.exp(a * b))
        hi = 1.0 / (1.0 + np.exp(-a * (255.0 - b)))
        s = 1.0 / (1.0 + np.exp(np.clip(-a * (w - b), -700, 700)))
        return (s - lo) / (hi - lo)


def make_face(rng: np.random.Generator, n_markers: int, du_ids) -> VirtualFace:
    """Draw a virtual face: layout, DU fields and per-marker response parameters."""
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
    )
