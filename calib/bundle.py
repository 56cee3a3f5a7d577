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
                  dist=[k1, k2, p1, p2, 0.0], R=rotation_from_rodrigues(v[:3]), t=v[3:6])


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
    def n_w(self) -> int:
        return self.offsets.size

    def free_mask(self) -> np.ndarray:
        mask = np.ones(self.n_cameras * N_CAM + self.n_frames * N_FRAME, bool)
        mask[: self.n_cameras * N_CAM] = ~self.held()
        return mask

    def split(self, x_full: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cams = x_full[: self.n_cameras * N_CAM].reshape(self.n_cameras, N_CAM)
        frames = x_full[self.n_cameras * N_CAM:].reshape(self.n_frames, N_FRAME)
        return cams, frames

    def wand_points(self, frames: np.ndarray) -> np.ndarray:
        """(n_frames, n_w, 3) marker positions from frame parameters."""
        u = self.u0 + frames[:, 3:4] * self.e1 + frames[:, 4:5] * self.e2
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        return frames[:, None, :3] + self.offsets[None, :, None] * u[:, None, :]

    # -- residuals and Jacobian ---------------------------------------------------------------
    def _project(self, cams: np.ndarray, frames: np.ndarray, jac: bool):
        R = rotation_from_rodrigues(cams[:, :3])  # (C, 3, 3)
        P = self.wand_points(frames)[self.obs_frame]  # (n_obs, n_w, 3)
        c = self.obs_cam
        Rc = R[c]
        Xc = np.einsum("oij,okj->oki", Rc, P) + cams[c, None, 3:6]
        z = Xc[..., 2]
        xn = Xc[..., 0] / z
        yn = Xc[..., 1] / z
        f, cx, cy, k1, k2, p1, p2 = (cams[c, 6 + i][:, None] for i in range(7))
        r2 = xn * xn + yn * yn
        radial = 1.0 + k1 * r2 + k2 * r2 * r2
        xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
        uv = np.stack([f * xd + cx, f * yd + cy], axis=-1)
        if not jac:
            return uv, None
        return uv, (R, Rc, P, Xc, z, xn, yn, r2, radial, f, k1, k2, p1, p2, xd, yd)

    def residuals(self, x_full: np.ndarray) -> np.ndarray:
        cams, frames = self.split(x_full)
        uv, _ = self._project(cams, frames, jac=False)
        return (uv - self.obs_uv).ravel()

    def jacobian(self, x_full: np.ndarray) -> sp.csr_matrix:
        """Analytic sparse Jacobian (n_obs * n_w * 2, n_params_full)."""
        _, Jcam, Jfr = self.blocks(x_full)
        n_obs, n_w = Jcam.shape[:2]
        rows = np.arange(n_obs * n_w * 2).reshape(n_obs, n_w, 2)
        cam_cols = self.obs_cam[:, None] * N_CAM + np.arange(N_CAM)[None]
        frame_cols = (self.n_cameras * N_CAM + self.obs_frame[:, None] * N_FRAME
                      + np.arange(N_FRAME)[None])
        r_idx = np.concatenate([
            np.broadcast_to(rows[..., None], (n_obs, n_w, 2, N_CAM)).ravel(),
            np.broadcast_to(rows[..., None], (n_obs, n_w, 2, N_FRAME)).ravel()])
        c_idx = np.concatenate([
            np.broadcast_to(cam_cols[:, None, None, :], (n_obs, n_w, 2, N_CAM)).ravel(),
            np.broadcast_to(frame_cols[:, None, None, :], (n_obs, n_w, 2, N_FRAME)).ravel()])
        vals = np.concatenate([Jcam.ravel(), Jfr.ravel()])
        n_par = self.n_cameras * N_CAM + self.n_frames * N_FRAME
        return sp.csr_matrix((vals, (r_idx, c_idx)), shape=(n_obs * n_w * 2, n_par))

    def blocks(self, x_full: np.ndarray):
        """Residuals (n_obs, n_w, 2) px and the Jacobian's blocks: with respect to the sighting's
        camera (n_obs, n_w, 2, 13) and to its frame (n_obs, n_w, 2, 5)."""
        cams, frames = self.split(x_full)
        uv, parts = self._project(cams, frames, jac=True)
        R, Rc, P, Xc, z, xn, yn, r2, radial, f, k1, k2, p1, p2, xd, yd = parts
        n_obs, n_w = xn.shape
        # d(xd, yd) / d(xn, yn)
        dr = k1 + 2.0 * k2 * r2  # d radial / d r2
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
        Y = Xc - cams[self.obs_cam, None, 3:6]  # R P
        cross = np.zeros((n_obs, n_w, 3, 3))
        cross[..., 0, 1] = Y[..., 2]
        cross[..., 0, 2] = -Y[..., 1]
        cross[..., 1, 0] = -Y[..., 2]
        cross[..., 1, 2] = Y[..., 0]
        cross[..., 2, 0] = Y[..., 1]
        cross[..., 2, 1] = -Y[..., 0]
        Jr = np.einsum("owij,owjk->owik", A, cross @ _rvec_jacobian(cams[:, :3])[self.obs_cam][:, None])
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
        # frame block: d P / d centre = I; d P / d (a, b) = s_k * d u / d (a, b)
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
        ARc = np.einsum("owij,ojk->owik", A, Rc)
        Jfr = np.einsum("owij,owjk->owik", ARc, dP[self.obs_frame])  # (o, w, 2, 5)
        return uv - self.obs_uv, Jcam, Jfr


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


def solve(problem: WandProblem, x0_full: np.ndarray, *, loss: str = "linear",
          f_scale: float = 1.0, max_nfev: int = 200) -> BundleResult:
    """Minimise the reprojection error over the free parameters (camera 0's pose held)."""
    free = problem.free_mask()
    base = x0_full.copy()

    def full(x):
        out = base.copy()
        out[free] = x
        return out

    def fun(x):
        return problem.residuals(full(x))

    def jac(x):
        return problem.jacobian(full(x))[:, free]

    res = least_squares(fun, x0_full[free], jac=jac, method="trf", tr_solver="lsmr",
                        x_scale="jac", loss=loss, f_scale=f_scale, max_nfev=max_nfev,
                        xtol=1e-12, ftol=1e-12, gtol=1e-10)
    xf = full(res.x)
    cams, frames = problem.split(xf)
    r = problem.residuals(xf).reshape(problem.obs_uv.shape)
    return BundleResult(cams.copy(), frames.copy(), r, float(res.cost), int(res.nfev),
                        bool(res.success), str(res.message))


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


def solve_schur(problem: WandProblem, x0_full: np.ndarray, *, loss: str = "linear",
                f_scale: float = 1.0, max_iter: int = 100, tol: float = 1e-10) -> BundleResult:
    """Levenberg-Marquardt with the Schur complement over the frames (see module docstring).

    The loss applies to each marker's squared residual norm (px^2) scaled by ``f_scale``.
    """
    C, F = problem.n_cameras, problem.n_frames
    oc, of = problem.obs_cam, problem.obs_frame
    gauge = problem.held()
    x = x0_full.copy()
    by_camera = [np.flatnonzero(oc == c) for c in range(C)]

    def cost_of(r):
        z = np.sum(r**2, axis=-1) / f_scale**2
        return 0.5 * f_scale**2 * float(np.sum(_loss_weights(z, loss)[0]))

    r, Jc, Jf = problem.blocks(x)
    cost = cost_of(r)
    lam = 1e-4
    nfev = 1
    message = "maximum iterations reached"
    success = False
    for _ in range(max_iter):
        z = np.sum(r**2, axis=-1) / f_scale**2
        w = _loss_weights(z, loss)[1][..., None, None]  # (o, w, 1, 1)
        # per sighting, the (w, a) rows stacked: batched matrix products (einsum's generic
        # loop is about 8 x slower here), then summed per camera and per frame
        n_obs = r.shape[0]
        Jc2 = Jc.reshape(n_obs, -1, N_CAM)
        Jf2 = Jf.reshape(n_obs, -1, N_FRAME)
        Jcw_T = (Jc * w).reshape(n_obs, -1, N_CAM).transpose(0, 2, 1)
        Jfw_T = (Jf * w).reshape(n_obs, -1, N_FRAME).transpose(0, 2, 1)
        r2 = r.reshape(n_obs, -1, 1)
        U, gc = _camera_normal(Jcw_T, Jc2, r2, by_camera)
        V = _sum_by(of, Jfw_T @ Jf2, F)
        gf = _sum_by(of, (Jfw_T @ r2)[..., 0], F)
        Wfull = np.zeros((F, C, N_CAM, N_FRAME))
        Wfull[of, oc] = Jcw_T @ Jf2
        while True:
            Ud = U + lam * np.einsum("cii->ci", U)[..., None] * np.eye(N_CAM)
            Vd = V + lam * np.einsum("fii->fi", V)[..., None] * np.eye(N_FRAME)
            Vinv = np.linalg.inv(Vd + 1e-12 * np.eye(N_FRAME))
            Y = Wfull @ Vinv[:, None]  # (F, C, 13, 5)
            S = -_schur_product(Y, Wfull)
            S[np.diag_indices(C * N_CAM)] += 0.0
            for c in range(C):
                sl = slice(c * N_CAM, (c + 1) * N_CAM)
                S[sl, sl] += Ud[c]
            rhs = (-gc + np.einsum("fcik,fk->ci", Y, gf)).ravel()
            S[gauge, :] = 0.0
            S[:, gauge] = 0.0
            S[gauge, gauge] = 1.0
            rhs[gauge] = 0.0
            try:
                dc = np.linalg.solve(S, rhs)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            df = np.einsum("fkl,fl->fk", Vinv,
                           -gf - np.einsum("fcik,ci->fk", Wfull, dc.reshape(C, N_CAM)))
            x_new = x + np.concatenate([dc, df.ravel()])
            r_new, Jc_new, Jf_new = problem.blocks(x_new)
            nfev += 1
            cost_new = cost_of(r_new)
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
        x, r, Jc, Jf, cost = x_new, r_new, Jc_new, Jf_new, cost_new
        lam = max(lam / 5.0, 1e-9)
        if rel < tol:
            message = "cost converged"
            success = True
            break
    cams, frames = problem.split(x)
    cov = _camera_covariance(problem, Jc, Jf, r, gauge)
    return BundleResult(cams.copy(), frames.copy(), r, cost, nfev, success, message, cov)


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
    """sum_f Y[f] W[f]^T over frames, as one matrix product: Y, W (F, C, 13, 5) ->
    (C * 13, C * 13)."""
    F, C = Y.shape[:2]
    Yr = Y.transpose(1, 2, 0, 3).reshape(C * N_CAM, F * N_FRAME)
    Wr = W.transpose(1, 2, 0, 3).reshape(C * N_CAM, F * N_FRAME)
    return Yr @ Wr.T


def _camera_covariance(problem: WandProblem, Jc, Jf, r, gauge) -> np.ndarray:
    """Covariance of the cameras' free parameters at the solution (see BundleResult)."""
    C, F = problem.n_cameras, problem.n_frames
    oc, of = problem.obs_cam, problem.obs_frame
    n_obs = r.shape[0]
    Jc2 = Jc.reshape(n_obs, -1, N_CAM)
    Jf2 = Jf.reshape(n_obs, -1, N_FRAME)
    U = _sum_by(oc, Jc2.transpose(0, 2, 1) @ Jc2, C)
    V = _sum_by(of, Jf2.transpose(0, 2, 1) @ Jf2, F)
    Wfull = np.zeros((F, C, N_CAM, N_FRAME))
    Wfull[of, oc] = Jc2.transpose(0, 2, 1) @ Jf2
    Vinv = np.linalg.pinv(V)
    Y = Wfull @ Vinv[:, None]
    S = -_schur_product(Y, Wfull)
    for c in range(C):
        sl = slice(c * N_CAM, (c + 1) * N_CAM)
        S[sl, sl] += U[c]
    free = ~gauge
    n_free = int(free.sum()) + F * N_FRAME
    dof = max(r.size - n_free, 1)
    sigma2 = float(np.sum(r**2)) / dof
    cov = np.zeros((C * N_CAM, C * N_CAM))
    Sf = S[np.ix_(free, free)]
    d = np.sqrt(np.maximum(np.diag(Sf), 1e-300))  # Jacobi scaling: parameters span 1e-6 to 1e5
    try:
        cov[np.ix_(free, free)] = np.linalg.inv(Sf / np.outer(d, d)) / np.outer(d, d) * sigma2
    except np.linalg.LinAlgError:
        cov[:] = np.nan
    return cov


def rig_from_vectors(cams: np.ndarray, like: CameraRig) -> CameraRig:
    return CameraRig(tuple(camera_from_vector(v, c) for v, c in zip(cams, like)))
