"""Sparse bundle adjustment of a camera rig on a rigid wand.

Unknowns:

- per camera: rotation vector (3), translation (3, mm), and 7 intrinsics: one focal length
  ``f`` (px; square pixels and zero skew, as every machine-vision sensor has), the principal
  point ``cx, cy`` (px), and distortion ``k1, k2, p1, p2``. ``k3`` stays 0: over a face-sized
  volume seen near the image centre it is not separable from ``k1, k2`` and only adds variance.
  Which intrinsics are estimated is an :class:`IntrinsicsModel` (``fixed_params``: the others are
  held). One camera's pose is held fixed (the gauge, the first camera's in the calibration: the
  world frame is then its own, or the ground square's set afterwards);
- per wand frame: the wand's centre (3, mm) and its direction, as two coordinates in the tangent
  plane of an initial direction ``u0`` (``u = normalise(u0 + a e1 + b e2)``, no singularity). The
  wand's geometry is exact by construction: marker k sits at ``centre + (o_k - o_mid) u``, so the
  wand's length fixes the scale.

Residuals: projected minus observed pixel of every wand marker in every sighting (distorted,
px). The Jacobian is analytic and sparse (each sighting depends on one camera and one frame).

Two solvers share the residuals and the Jacobian:

- :func:`solve_schur` (used by the calibration): Levenberg-Marquardt on the normal equations with
  the frame parameters eliminated by the Schur complement (each frame's 5x5 block inverts on its
  own), leaving a dense system over the cameras' parameters (13 per camera); robust losses by
  iteratively reweighted least squares. It converges in tens of iterations, well under a second
  for 600 frames and six cameras.
- :func:`solve` : ``scipy.optimize.least_squares`` (trust region with LSMR, ``x_scale="jac"``, the
  same robust losses) on the sparse Jacobian. Same optimum, but its inexact LSMR steps need
  hundreds of iterations on this ill-conditioned problem (about 10 s); kept as the reference the
  tests compare against.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

from mocap.calib.camera import Camera, CameraRig, rodrigues_from_rotation, rotation_from_rodrigues

N_CAM = 13  # rvec 3, t 3, f, cx, cy, k1, k2, p1, p2
N_FRAME = 5  # centre 3, tangent 2
INTRINSIC_NAMES = ("f", "cx", "cy", "k1", "k2", "p1", "p2")
DISTORTION_MODELS = {"none": (), "k1": ("k1",), "k1k2": ("k1", "k2"),
                     "k1k2p1p2": ("k1", "k2", "p1", "p2")}


@dataclass(frozen=True)
class IntrinsicsModel:
    """Which intrinsics the bundle adjustment estimates, as the field's tools offer them.

    principal_point : "free" (estimated) or "fixed" (held where it starts: the image centre).
    distortion : "none", "k1", "k1k2" or "k1k2p1p2" (Brown-Conrady terms estimated; the others
        held at 0). The focal length is always estimated.
    """

    principal_point: str = "free"
    distortion: str = "k1k2p1p2"

    def __post_init__(self) -> None:
        if self.principal_point not in ("free", "fixed"):
            raise ValueError(f"principal point: expected 'free' or 'fixed', got {self.principal_point!r}")
        if self.distortion not in DISTORTION_MODELS:
            raise ValueError(f"distortion: expected one of {sorted(DISTORTION_MODELS)}, "
                             f"got {self.distortion!r}")

    @property
    def n_free(self) -> int:
        """Free intrinsics per camera."""
        return 1 + (2 if self.principal_point == "free" else 0) + len(DISTORTION_MODELS[self.distortion])

    def fixed_mask(self) -> np.ndarray:
        """(13,) bool: the camera parameters this model holds (pose entries are free)."""
        m = np.zeros(N_CAM, bool)
        if self.principal_point == "fixed":
            m[7:9] = True
        free = DISTORTION_MODELS[self.distortion]
        for k, name in enumerate(("k1", "k2", "p1", "p2")):
            m[9 + k] = name not in free
        return m


def _tangent_basis(u0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (n, 3) perpendicular to each u0 (n, 3) and to each other."""
    helper = np.where(np.abs(u0[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(u0, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(u0, e1)
    return e1, e2


def camera_vector(cam: Camera) -> np.ndarray:
    K, d = cam.K, cam.dist
    return np.concatenate([rodrigues_from_rotation(cam.R), cam.t,
                           [0.5 * (K[0, 0] + K[1, 1]), K[0, 2], K[1, 2], d[0], d[1], d[2], d[3]]])


def camera_from_vector(v: np.ndarray, like: Camera) -> Camera:
    f, cx, cy, k1, k2, p1, p2 = v[6:13]
    return Camera(id=like.id, width=like.width, height=like.height,
                  K=[[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]],
                  dist=[k1, k2, p1, p2, like.dist[4]], R=rotation_from_rodrigues(v[:3]), t=v[3:6])


@dataclass(frozen=True)
class WandProblem:
    """A wand bundle-adjustment problem: the observation table and the fixed structure.

    obs_cam, obs_frame : (n_obs,) camera and (local) frame index of each sighting.
    obs_uv : (n_obs, n_w, 2) observed pixels, in wand-offset order.
    offsets : (n_w,) marker offsets relative to the wand's middle, mm.
    u0, e1, e2 : (n_frames, 3) initial direction and its tangent basis per frame.
    fixed_camera : the camera whose pose is held (gauge).
    fixed_params : (n_cameras, 13) bool, camera parameters held at their start values (the
        intrinsics an :class:`IntrinsicsModel` does not estimate); None: all free.
    k3 : (n_cameras,) each camera's third radial term, held (a prior's; 0 when None).
    prior_mean, prior_weight : (n_cameras, 13) a Gaussian prior on the camera parameters: the
        cost gains ``0.5 * sum(prior_weight * (x - prior_mean)^2)`` (weight in px^2 per unit^2:
        the pixel noise's variance over the prior's; 0 where there is no prior); None: none.
    points : static points with known correspondence (:class:`PointSightings`), or None.
    """

    obs_cam: np.ndarray
    obs_frame: np.ndarray
    obs_uv: np.ndarray
    offsets: np.ndarray
    u0: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    n_cameras: int
    fixed_camera: int
    fixed_params: np.ndarray | None = None
    k3: np.ndarray | None = None
    prior_mean: np.ndarray | None = None
    prior_weight: np.ndarray | None = None
    points: "PointSightings | None" = None
    noise_px: float | None = None  # the pixel noise the prior's weight assumes (covariance scale)

    def held(self) -> np.ndarray:
        """(n_cameras * 13,) bool: camera parameters not estimated (gauge and fixed intrinsics)."""
        m = np.zeros((self.n_cameras, N_CAM), bool)
        if self.fixed_params is not None:
            m |= self.fixed_params
        m[self.fixed_camera, :6] = True
        return m.ravel()

    @property
    def n_frames(self) -> int:
        return self.u0.shape[0]

    @property
    def n_points(self) -> int:
        return 0 if self.points is None else self.points.n_points

    def prior_cost(self, cams: np.ndarray) -> float:
        if self.prior_weight is None:
            return 0.0
        return 0.5 * float(np.sum(self.prior_weight * (cams - self.prior_mean) ** 2))

    @property
    def n_w(self) -> int:
        return self.offsets.size

    def free_mask(self) -> np.ndarray:
        mask = np.ones(self.n_cameras * N_CAM + self.n_frames * N_FRAME + 3 * self.n_points, bool)
        mask[: self.n_cameras * N_CAM] = ~self.held()
        return mask

    def split(self, x_full: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cameras (n_cameras, 13) and wand frames (n_frames, 5) of a full parameter vector
        (static points, when any, follow the frames: :meth:`split_points`)."""
        nc = self.n_cameras * N_CAM
        cams = x_full[:nc].reshape(self.n_cameras, N_CAM)
        frames = x_full[nc:nc + self.n_frames * N_FRAME].reshape(self.n_frames, N_FRAME)
        return cams, frames

    def split_points(self, x_full: np.ndarray) -> np.ndarray:
        """(n_points, 3) static points, mm, of a full parameter vector."""
        start = self.n_cameras * N_CAM + self.n_frames * N_FRAME
        return x_full[start:start + 3 * self.n_points].reshape(self.n_points, 3)

    def wand_points(self, frames: np.ndarray) -> np.ndarray:
        """(n_frames, n_w, 3) marker positions from frame parameters."""
        u = self.u0 + frames[:, 3:4] * self.e1 + frames[:, 4:5] * self.e2
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        return frames[:, None, :3] + self.offsets[None, :, None] * u[:, None, :]

    # -- residuals and Jacobian ---------------------------------------------------------------
    def _project_at(self, cams: np.ndarray, c: np.ndarray, P: np.ndarray, jac: bool):
        """Project points P (n, k, 3) mm by cameras c (n,): pixels (n, k, 2) and, with ``jac``,
        d uv / d camera (n, k, 2, 13) and d uv / d P (n, k, 2, 3)."""
        R = rotation_from_rodrigues(cams[:, :3])  # (C, 3, 3)
        Rc = R[c]
        Xc = np.einsum("oij,okj->oki", Rc, P) + cams[c, None, 3:6]
        z = Xc[..., 2]
        xn = Xc[..., 0] / z
        yn = Xc[..., 1] / z
        f, cx, cy, k1, k2, p1, p2 = (cams[c, 6 + i][:, None] for i in range(7))
        k3 = (np.zeros(c.size) if self.k3 is None else self.k3[c])[:, None]
        r2 = xn * xn + yn * yn
        radial = 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
        xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
        uv = np.stack([f * xd + cx, f * yd + cy], axis=-1)
        if not jac:
            return uv, None, None
        n_obs, n_w = xn.shape
        # d(xd, yd) / d(xn, yn)
        dr = k1 + 2.0 * k2 * r2 + 3.0 * k3 * r2 * r2  # d radial / d r2
        dxd_dxn = radial + 2.0 * xn * xn * dr + 2.0 * p1 * yn + 6.0 * p2 * xn
        dxd_dyn = 2.0 * xn * yn * dr + 2.0 * p1 * xn + 2.0 * p2 * yn
        dyd_dxn = 2.0 * xn * yn * dr + 2.0 * p1 * xn + 2.0 * p2 * yn
        dyd_dyn = radial + 2.0 * yn * yn * dr + 6.0 * p1 * yn + 2.0 * p2 * xn
        # d(xn, yn) / d Xc
        iz = 1.0 / z
        A = np.zeros((n_obs, n_w, 2, 3))
        A[..., 0, 0] = f * (dxd_dxn * iz)
        A[..., 0, 1] = f * (dxd_dyn * iz)
        A[..., 0, 2] = f * (-(dxd_dxn * xn + dxd_dyn * yn) * iz)
        A[..., 1, 0] = f * (dyd_dxn * iz)
        A[..., 1, 1] = f * (dyd_dyn * iz)
        A[..., 1, 2] = f * (-(dyd_dxn * xn + dyd_dyn * yn) * iz)
        # camera block: rotation (small-angle perturbation on the left, mapped to rvec via the
        # right Jacobian would be exact; we use d Xc / d omega = -[Xc - t]_x with the rvec
        # updated additively, which is exact at omega -> 0 and a good quasi-Newton step)
        Y = Xc - cams[c, None, 3:6]  # R P
        cross = np.zeros((n_obs, n_w, 3, 3))
        cross[..., 0, 1] = Y[..., 2]
        cross[..., 0, 2] = -Y[..., 1]
        cross[..., 1, 0] = -Y[..., 2]
        cross[..., 1, 2] = Y[..., 0]
        cross[..., 2, 0] = Y[..., 1]
        cross[..., 2, 1] = -Y[..., 0]
        Jr = np.einsum("owij,owjk->owik", A, cross @ _rvec_jacobian(cams[:, :3])[c][:, None])
        Jt = A
        Jf = np.stack([xd, yd], axis=-1)[..., None]
        Jc = np.zeros((n_obs, n_w, 2, 2))
        Jc[..., 0, 0] = 1.0
        Jc[..., 1, 1] = 1.0
        Jk = np.zeros((n_obs, n_w, 2, 4))
        Jk[..., 0, 0] = f * xn * r2
        Jk[..., 1, 0] = f * yn * r2
        Jk[..., 0, 1] = f * xn * r2 * r2
        Jk[..., 1, 1] = f * yn * r2 * r2
        Jk[..., 0, 2] = f * 2.0 * xn * yn
        Jk[..., 1, 2] = f * (r2 + 2.0 * yn * yn)
        Jk[..., 0, 3] = f * (r2 + 2.0 * xn * xn)
        Jk[..., 1, 3] = f * 2.0 * xn * yn
        Jcam = np.concatenate([Jr, Jt, Jf, Jc, Jk], axis=-1)  # (o, w, 2, 13)
        JP = np.einsum("owij,ojk->owik", A, Rc)  # (o, w, 2, 3)
        return uv, Jcam, JP

    def _project(self, cams: np.ndarray, frames: np.ndarray, jac: bool):
        P = self.wand_points(frames)[self.obs_frame]  # (n_obs, n_w, 3)
        return self._project_at(cams, self.obs_cam, P, jac)

    def residuals(self, x_full: np.ndarray) -> np.ndarray:
        """Every reprojection residual, px: the wand's (n_obs * n_w * 2) then the static
        points' (n_point_sightings * 2)."""
        cams, frames = self.split(x_full)
        uv, _, _ = self._project(cams, frames, jac=False)
        r = (uv - self.obs_uv).ravel()
        if self.points is None:
            return r
        rp, _, _ = self.point_blocks(x_full, jac=False)
        return np.concatenate([r, rp.ravel()])

    def jacobian(self, x_full: np.ndarray) -> sp.csr_matrix:
        """Analytic sparse Jacobian (len(residuals), n_params_full)."""
        _, Jcam, Jfr = self.blocks(x_full)
        n_obs, n_w = Jcam.shape[:2]
        rows = np.arange(n_obs * n_w * 2).reshape(n_obs, n_w, 2)
        cam_cols = self.obs_cam[:, None] * N_CAM + np.arange(N_CAM)[None]
        frame_cols = (self.n_cameras * N_CAM + self.obs_frame[:, None] * N_FRAME
                      + np.arange(N_FRAME)[None])
        r_idx = [np.broadcast_to(rows[..., None], (n_obs, n_w, 2, N_CAM)).ravel(),
                 np.broadcast_to(rows[..., None], (n_obs, n_w, 2, N_FRAME)).ravel()]
        c_idx = [np.broadcast_to(cam_cols[:, None, None, :], (n_obs, n_w, 2, N_CAM)).ravel(),
                 np.broadcast_to(frame_cols[:, None, None, :], (n_obs, n_w, 2, N_FRAME)).ravel()]
        vals = [Jcam.ravel(), Jfr.ravel()]
        n_rows = n_obs * n_w * 2
        if self.points is not None:
            _, Jpc, Jpp = self.point_blocks(x_full, jac=True)
            m = Jpc.shape[0]
            prow = n_rows + np.arange(m * 2).reshape(m, 2)
            pcam = self.points.camera[:, None] * N_CAM + np.arange(N_CAM)[None]
            ppt = (self.n_cameras * N_CAM + self.n_frames * N_FRAME
                   + self.points.point[:, None] * 3 + np.arange(3)[None])
            r_idx += [np.broadcast_to(prow[..., None], (m, 2, N_CAM)).ravel(),
                      np.broadcast_to(prow[..., None], (m, 2, 3)).ravel()]
            c_idx += [np.broadcast_to(pcam[:, None, :], (m, 2, N_CAM)).ravel(),
                      np.broadcast_to(ppt[:, None, :], (m, 2, 3)).ravel()]
            vals += [Jpc.ravel(), Jpp.ravel()]
            n_rows += 2 * m
        n_par = self.free_mask().size
        return sp.csr_matrix((np.concatenate(vals), (np.concatenate(r_idx), np.concatenate(c_idx))),
                             shape=(n_rows, n_par))

    def point_blocks(self, x_full: np.ndarray, jac: bool = True):
        """The static points' residuals (m, 2) px and Jacobian blocks: with respect to the
        sighting's camera (m, 2, 13) and to its point (m, 2, 3); None without ``jac``."""
        cams, _ = self.split(x_full)
        pts = self.split_points(x_full)
        ps = self.points
        uv, Jc, JP = self._project_at(cams, ps.camera, pts[ps.point][:, None, :], jac)
        r = uv[:, 0] - ps.uv
        if not jac:
            return r, None, None
        return r, Jc[:, 0], JP[:, 0]

    def blocks(self, x_full: np.ndarray):
        """Residuals (n_obs, n_w, 2) px and the Jacobian's blocks: with respect to the
        sighting's camera (n_obs, n_w, 2, 13) and to its frame (n_obs, n_w, 2, 5)."""
        cams, frames = self.split(x_full)
        uv, Jcam, JP = self._project(cams, frames, jac=True)
        # frame block: d P / d centre = I; d P / d (a, b) = s_k * d u / d (a, b)
        n_w = self.n_w
        u_raw = self.u0 + frames[:, 3:4] * self.e1 + frames[:, 4:5] * self.e2
        nrm = np.linalg.norm(u_raw, axis=1, keepdims=True)
        u = u_raw / nrm
        proj = (np.eye(3)[None] - u[:, :, None] * u[:, None, :]) / nrm[:, :, None]  # (F, 3, 3)
        du_da = np.einsum("fij,fj->fi", proj, self.e1)
        du_db = np.einsum("fij,fj->fi", proj, self.e2)
        dP = np.zeros((self.n_frames, n_w, 3, 5))
        dP[:, :, :, :3] = np.eye(3)
        dP[:, :, :, 3] = self.offsets[None, :, None] * du_da[:, None, :]
        dP[:, :, :, 4] = self.offsets[None, :, None] * du_db[:, None, :]
        Jfr = np.einsum("owij,owjk->owik", JP, dP[self.obs_frame])  # (o, w, 2, 5)
        return uv - self.obs_uv, Jcam, Jfr


@dataclass(frozen=True)
class PointSightings:
    """Static points with known correspondence (a ``points`` take): each point one unknown
    position, seen once by each camera that saw it.

    camera, point : (m,) camera index and (local) point index of each sighting.
    uv : (m, 2) observed pixels (raw, distorted).
    n_points : how many points.
    """

    camera: np.ndarray
    point: np.ndarray
    uv: np.ndarray
    n_points: int


def _rvec_jacobian(rvec: np.ndarray) -> np.ndarray:
    """(C, 3, 3) map from an additive rvec change to the left-perturbation angle: the
    left Jacobian of SO(3) at ``rvec`` (so d(R P) / d rvec = -[R P]_x J_l)."""
    theta = np.linalg.norm(rvec, axis=1)
    out = np.empty((rvec.shape[0], 3, 3))
    for i, (w, th) in enumerate(zip(rvec, theta)):
        if th < 1e-8:
            out[i] = np.eye(3)
            continue
        k = w / th
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        out[i] = (np.eye(3) + (1 - np.cos(th)) / th * K + (th - np.sin(th)) / th * (K @ K))
    return out


@dataclass(frozen=True)
class BundleResult:
    """cameras (n_cameras, 13); frames (n_frames, 5); residuals (n_obs, n_w, 2) px;
    camera_covariance (n_cameras * 13, n_cameras * 13): the cameras' parameters' covariance
    (Gauss-Newton, frames marginalised, scaled by the residuals' variance; zero for held
    parameters), or None."""

    cameras: np.ndarray
    frames: np.ndarray
    residuals: np.ndarray
    cost: float
    nfev: int
    success: bool
    message: str
    camera_covariance: np.ndarray | None = None
    points: np.ndarray | None = None  # (n_points, 3) mm: the static points, when any
    point_residuals: np.ndarray | None = None  # (n_point_sightings, 2) px


def solve(problem: WandProblem, x0_full: np.ndarray, *, loss: str = "linear",
          f_scale: float = 1.0, max_nfev: int = 200) -> BundleResult:
    """Minimise the reprojection error over the free parameters (camera 0's pose held), with
    ``scipy.optimize.least_squares`` (the prior, when any, as extra residual rows; the loss
    applies to each residual component here)."""
    free = problem.free_mask()
    base = x0_full.copy()
    n_cam = problem.n_cameras * N_CAM
    sw = None if problem.prior_weight is None else np.sqrt(problem.prior_weight.ravel())

    def full(x):
        out = base.copy()
        out[free] = x
        return out

    def fun(x):
        xf = full(x)
        r = problem.residuals(xf)
        if sw is None:
            return r
        return np.concatenate([r, sw * (xf[:n_cam] - problem.prior_mean.ravel())])

    def jac(x):
        J = problem.jacobian(full(x))
        if sw is not None:
            P = sp.hstack([sp.diags(sw), sp.csr_matrix((n_cam, J.shape[1] - n_cam))])
            J = sp.vstack([J, P]).tocsr()
        return J[:, free]

    res = least_squares(fun, x0_full[free], jac=jac, method="trf", tr_solver="lsmr",
                        x_scale="jac", loss=loss, f_scale=f_scale, max_nfev=max_nfev,
                        xtol=1e-12, ftol=1e-12, gtol=1e-10)
    xf = full(res.x)
    cams, frames = problem.split(xf)
    r_all = problem.residuals(xf)
    n_wand = problem.obs_uv.size
    r = r_all[:n_wand].reshape(problem.obs_uv.shape)
    pts = problem.split_points(xf).copy() if problem.points is not None else None
    pr = r_all[n_wand:].reshape(-1, 2) if problem.points is not None else None
    return BundleResult(cams.copy(), frames.copy(), r, float(res.cost), int(res.nfev),
                        bool(res.success), str(res.message), None, pts, pr)


def _loss_weights(z: np.ndarray, loss: str) -> tuple[np.ndarray, np.ndarray]:
    """rho(z) and rho'(z) of scipy's losses, z = squared residual norm / f_scale^2."""
    if loss == "linear":
        return z, np.ones_like(z)
    if loss == "soft_l1":
        s = np.sqrt(1.0 + z)
        return 2.0 * (s - 1.0), 1.0 / s
    if loss == "huber":
        big = z > 1.0
        rho = np.where(big, 2.0 * np.sqrt(z) - 1.0, z)
        return rho, np.where(big, 1.0 / np.sqrt(np.where(big, z, 1.0)), 1.0)
    if loss == "cauchy":
        return np.log1p(z), 1.0 / (1.0 + z)
    raise ValueError(f"bundle adjustment: expected loss linear, soft_l1, huber or cauchy, got {loss!r}")


def _groups(problem: WandProblem, x: np.ndarray):
    """The blocks eliminated by the Schur complement, each a dict: ``r`` residuals (o, k) px,
    ``Jc`` (o, k, 13) and ``Jb`` (o, k, nb) Jacobians, ``cam`` (o,) and ``block`` (o,) indices,
    ``n`` blocks of ``nb`` parameters, ``norm_axis``: how a sighting's residuals group into
    markers for the loss. The wand's frames (nb 5) and, when any, the static points (nb 3)."""
    r, Jc, Jf = problem.blocks(x)
    n_obs, n_w = r.shape[:2]
    out = [dict(r=r, Jc=Jc.reshape(n_obs, -1, N_CAM), Jb=Jf.reshape(n_obs, -1, N_FRAME),
                cam=problem.obs_cam, block=problem.obs_frame, n=problem.n_frames, nb=N_FRAME)]
    if problem.points is not None:
        rp, Jpc, Jpp = problem.point_blocks(x)
        out.append(dict(r=rp[:, None, :], Jc=Jpc, Jb=Jpp, cam=problem.points.camera,
                        block=problem.points.point, n=problem.n_points, nb=3))
    return out


def solve_schur(problem: WandProblem, x0_full: np.ndarray, *, loss: str = "linear",
                f_scale: float = 1.0, max_iter: int = 100, tol: float = 1e-10) -> BundleResult:
    """Levenberg-Marquardt with the Schur complement over the frames (see module docstring);
    the static points (when any) are eliminated the same way, and the prior (when any) adds to
    the cameras' block.

    The loss applies to each marker's squared residual norm (px^2) scaled by ``f_scale``.
    """
    C = problem.n_cameras
    gauge = problem.held()
    x = x0_full.copy()
    n_cam = C * N_CAM
    pm = None if problem.prior_weight is None else problem.prior_mean.ravel()
    pw = None if problem.prior_weight is None else problem.prior_weight.ravel()

    def cost_of(groups, xx):
        c = 0.0
        for g in groups:
            z = np.sum(g["r"] ** 2, axis=-1) / f_scale**2
            c += 0.5 * f_scale**2 * float(np.sum(_loss_weights(z, loss)[0]))
        return c + problem.prior_cost(xx[:n_cam].reshape(C, N_CAM))

    groups = _groups(problem, x)
    cost = cost_of(groups, x)
    lam = 1e-4
    nfev = 1
    message = "maximum iterations reached"
    success = False
    for _ in range(max_iter):
        U = np.zeros((C, N_CAM, N_CAM))
        gc = np.zeros((C, N_CAM))
        parts = []
        for g in groups:
            z = np.sum(g["r"] ** 2, axis=-1) / f_scale**2
            w = np.repeat(_loss_weights(z, loss)[1], 2, axis=-1)[..., None]  # (o, k, 1)
            # per sighting, the rows stacked: batched matrix products, summed per camera/block
            Jcw_T = (g["Jc"] * w).transpose(0, 2, 1)
            Jbw_T = (g["Jb"] * w).transpose(0, 2, 1)
            r2 = g["r"].reshape(g["r"].shape[0], -1, 1)
            by_camera = [np.flatnonzero(g["cam"] == c) for c in range(C)]
            Ug, gcg = _camera_normal(Jcw_T, g["Jc"], r2, by_camera)
            U += Ug
            gc += gcg
            V = _sum_by(g["block"], Jbw_T @ g["Jb"], g["n"])
            gb = _sum_by(g["block"], (Jbw_T @ r2)[..., 0], g["n"])
            W = np.zeros((g["n"], C, N_CAM, g["nb"]))
            W[g["block"], g["cam"]] = Jcw_T @ g["Jb"]
            parts.append((V, gb, W, g["nb"]))
        if pw is not None:
            U += (np.eye(N_CAM)[None] * pw.reshape(C, N_CAM)[:, None, :])
            gc += (pw * (x[:n_cam] - pm)).reshape(C, N_CAM)
        while True:
            Ud = U + lam * np.einsum("cii->ci", U)[..., None] * np.eye(N_CAM)
            S = np.zeros((n_cam, n_cam))
            rhs = -gc.ravel()
            elim = []
            for V, gb, W, nb in parts:
                Vd = V + lam * np.einsum("fii->fi", V)[..., None] * np.eye(nb)
                Vinv = np.linalg.inv(Vd + 1e-12 * np.eye(nb))
                Y = W @ Vinv[:, None]  # (n, C, 13, nb)
                S -= _schur_product(Y, W)
                rhs += np.einsum("fcik,fk->ci", Y, gb).ravel()
                elim.append(Vinv)
            for c in range(C):
                sl = slice(c * N_CAM, (c + 1) * N_CAM)
                S[sl, sl] += Ud[c]
            S[gauge, :] = 0.0
            S[:, gauge] = 0.0
            S[gauge, gauge] = 1.0
            rhs[gauge] = 0.0
            try:
                dc = np.linalg.solve(S, rhs)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            steps = [dc]
            for (_, gb, W, _), Vinv in zip(parts, elim):
                db = np.einsum("fkl,fl->fk", Vinv,
                               -gb - np.einsum("fcik,ci->fk", W, dc.reshape(C, N_CAM)))
                steps.append(db.ravel())
            x_new = x + np.concatenate(steps)
            groups_new = _groups(problem, x_new)
            nfev += 1
            cost_new = cost_of(groups_new, x_new)
            if np.isfinite(cost_new) and cost_new <= cost:
                break
            lam *= 4.0
            if lam > 1e12:
                break
        if lam > 1e12:
            message = "no further decrease"
            success = True
            break
        rel = (cost - cost_new) / max(cost, 1e-300)
        x, groups, cost = x_new, groups_new, cost_new
        lam = max(lam / 5.0, 1e-9)
        if rel < tol:
            message = "cost converged"
            success = True
            break
    cams, frames = problem.split(x)
    cov = _camera_covariance(problem, groups, gauge)
    points = None
    point_residuals = None
    if problem.points is not None:
        points = problem.split_points(x).copy()
        point_residuals = groups[1]["r"][:, 0, :]
    return BundleResult(cams.copy(), frames.copy(), groups[0]["r"], cost, nfev, success, message,
                        cov, points, point_residuals)


def _camera_normal(JwT: np.ndarray, J: np.ndarray, r: np.ndarray, by_camera: list[np.ndarray]):
    """Each camera's block of the normal equations, one matrix product over all its sightings'
    rows: JwT (o, 13, k) weighted Jacobian transposed, J (o, k, 13), r (o, k, 1) residuals ->
    U (C, 13, 13), g (C, 13)."""
    U = np.empty((len(by_camera), N_CAM, N_CAM))
    g = np.empty((len(by_camera), N_CAM))
    for c, rows in enumerate(by_camera):
        A = JwT[rows].transpose(1, 0, 2).reshape(N_CAM, -1)  # (13, n_c k)
        U[c] = A @ J[rows].reshape(-1, N_CAM)
        g[c] = A @ r[rows].reshape(-1)
    return U, g


def _sum_by(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """``out[k] = sum of values[i] where index[i] == k``: (m, ...) -> (n, ...), by one
    bincount over the flattened components (``np.add.at`` is unbuffered and slow)."""
    flat = values.reshape(len(index), -1)
    k = flat.shape[1]
    keys = (index[:, None] * k + np.arange(k)).ravel()
    out = np.bincount(keys, weights=flat.ravel(), minlength=n * k)
    return out.reshape((n,) + values.shape[1:])


def _schur_product(Y: np.ndarray, W: np.ndarray) -> np.ndarray:
    """sum_f Y[f] W[f]^T over frames (or points), as one matrix product: Y, W (F, C, 13, nb) ->
    (C * 13, C * 13)."""
    F, C, _, nb = Y.shape
    Yr = Y.transpose(1, 2, 0, 3).reshape(C * N_CAM, F * nb)
    Wr = W.transpose(1, 2, 0, 3).reshape(C * N_CAM, F * nb)
    return Yr @ Wr.T


def _camera_covariance(problem: WandProblem, groups, gauge) -> np.ndarray:
    """Covariance of the cameras' free parameters at the solution (see BundleResult): the
    Gauss-Newton normal matrix with the frames and points marginalised, plus the prior's
    information, scaled by the residuals' variance."""
    C = problem.n_cameras
    n_cam = C * N_CAM
    S = np.zeros((n_cam, n_cam))
    sq, n_res, n_blockpar = 0.0, 0, 0
    for g in groups:
        J, Jb = g["Jc"], g["Jb"]
        U = _sum_by(g["cam"], J.transpose(0, 2, 1) @ J, C)
        V = _sum_by(g["block"], Jb.transpose(0, 2, 1) @ Jb, g["n"])
        W = np.zeros((g["n"], C, N_CAM, g["nb"]))
        W[g["block"], g["cam"]] = J.transpose(0, 2, 1) @ Jb
        Y = W @ np.linalg.pinv(V)[:, None]
        S -= _schur_product(Y, W)
        for c in range(C):
            sl = slice(c * N_CAM, (c + 1) * N_CAM)
            S[sl, sl] += U[c]
        sq += float(np.sum(g["r"] ** 2))
        n_res += g["r"].size
        n_blockpar += g["n"] * g["nb"]
    if problem.prior_weight is not None:
        S[np.diag_indices(n_cam)] += problem.prior_weight.ravel()
    free = ~gauge
    dof = max(n_res - int(free.sum()) - n_blockpar, 1)
    sigma2 = sq / dof if problem.noise_px is None else problem.noise_px**2
    cov = np.zeros((n_cam, n_cam))
    Sf = S[np.ix_(free, free)]
    d = np.sqrt(np.maximum(np.diag(Sf), 1e-300))  # Jacobi scaling: parameters span 1e-6 to 1e5
    try:
        cov[np.ix_(free, free)] = np.linalg.inv(Sf / np.outer(d, d)) / np.outer(d, d) * sigma2
    except np.linalg.LinAlgError:
        cov[:] = np.nan
    return cov


def rig_from_vectors(cams: np.ndarray, like: CameraRig) -> CameraRig:
    return CameraRig(tuple(camera_from_vector(v, c) for v, c in zip(cams, like)))
