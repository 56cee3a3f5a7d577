"""Prior intrinsics: a camera's lens as a profile or a board calibration measured it.

Real wand tools separate the lens (a lens profile, a checkerboard or ChArUco calibration) from
the rig (the wand). An :class:`IntrinsicPrior` is one camera's focal length, principal point and
Brown-Conrady distortion, with how the calibration uses it:

- ``"fixed"``: used as given; the wand fits the poses only;
- ``"refine"``: the starting point and a Gaussian prior; the wand adjusts each parameter as far
  as its coverage determines it (the calibration's report says by how much). The prior's
  standard deviation of each parameter is what moves the image corner by ``PRIOR_CORNER_PX``
  (1 sd): the principal point by that many px, the focal length by ``PRIOR_CORNER_PX / r`` px
  (r: the corner's normalised radius), k1 and k2 by ``PRIOR_CORNER_PX / (f r^3)`` and
  ``/ (f r^5)``, p1 and p2 by ``PRIOR_CORNER_PX / (2 f r^2)`` (their displacements at the
  corner per unit term).

Files read (:func:`read_priors`), each giving priors per camera id:

- aniposelib's ``calibration.toml`` (anipose, Pose2Sim, caliscope): ``[cam_k]`` tables with
  ``name``, ``size`` [width, height], ``matrix`` (3x3 K) and ``distortion`` (k1 k2 p1 p2 k3);
  the camera id is ``name``;
- OpenCV FileStorage YAML/XML (``cv2.FileStorage``): ``camera_matrix`` and
  ``distortion_coefficients`` (4, 5 or more terms; beyond k3 must be 0), ``image_width`` and
  ``image_height`` when present; the camera id is ``camera_id`` when present, else the file's
  stem;
- Argus / easyWand camera profiles (``.txt``, whitespace or comma separated, ``#`` comments):
  one row per camera, ``camera focal_px width height cx cy aspect_ratio k1 k2 t1 t2 k3``;
  camera ``c`` is id ``cam<c>``. The principal point is in the digitising tools' pixel
  coordinates (origin at the bottom-left, 1-based, as DLTdv's points): ``x = cx - 1``,
  ``y = height - cy``; the tangential ``t1`` changes sign with the flipped y axis
  (``p1 = -t1``, ``p2 = t2``). The aspect ratio must be 1 (square pixels, as this package's
  camera model has). A row of 6 values (no distortion columns) gives the focal length and the
  principal point with zero distortion.

References: OpenCV's camera model (``cv2.projectPoints``); aniposelib's ``CameraGroup.dump``;
Argus (Jackson et al. 2016, Integrative and Comparative Biology) and easyWand (Theriault et al.
2014, Bioinspiration & Biomimetics) profile files.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

PRIOR_CORNER_PX = 1.0
PRIOR_MODES = ("fixed", "refine")
# the bundle adjustment's camera vector: rvec 3, t 3, f, cx, cy, k1, k2, p1, p2
INTRINSIC_SLICE = slice(6, 13)
INTRINSIC_NAMES = ("f", "cx", "cy", "k1", "k2", "p1", "p2")


class PriorFileError(ValueError):
    """A prior-intrinsics file that cannot be read; the message names the file and the row/key."""


@dataclass(frozen=True)
class IntrinsicPrior:
    """One camera's prior intrinsics.

    Attributes
    ----------
    camera_id : the camera's id.
    focal_px : focal length, px.
    principal_px : (2,) principal point, px, origin at the top-left pixel's centre.
    distortion : (5,) Brown-Conrady ``k1 k2 p1 p2 k3`` (OpenCV's).
    mode : "fixed" or "refine".
    size : (width, height) px the prior was measured at, or None when the file does not say.
    source : where it came from (a file name or ``session.toml``), for the report.
    distortion_given : False where the file gave no distortion (a 6-column Argus / easyWand
        row: focal length and principal point only), so ``distortion`` is zeros by default.
    """

    camera_id: str
    focal_px: float
    principal_px: tuple[float, float]
    distortion: tuple[float, float, float, float, float]
    mode: str = "refine"
    size: tuple[int, int] | None = None
    source: str = ""
    distortion_given: bool = True

    def __post_init__(self) -> None:
        if self.mode not in PRIOR_MODES:
            raise ValueError(f"intrinsics: expected 'fixed' or 'refine', got {self.mode!r}")
        if not (np.isfinite(self.focal_px) and self.focal_px > 0):
            raise ValueError(f"camera {self.camera_id}: focal length must be positive, got "
                             f"{self.focal_px}")

    def with_mode(self, mode: str) -> "IntrinsicPrior":
        return replace(self, mode=mode)

    def vector(self) -> np.ndarray:
        """(7,) f, cx, cy, k1, k2, p1, p2 as the bundle adjustment orders them."""
        d = self.distortion
        return np.array([self.focal_px, *self.principal_px, d[0], d[1], d[2], d[3]], float)

    def sd(self, width: int, height: int) -> np.ndarray:
        """(7,) the prior's standard deviation of f, cx, cy, k1, k2, p1, p2 (module docstring)."""
        f = self.focal_px
        r = 0.5 * np.hypot(width, height) / f  # the corner's normalised radius
        px = PRIOR_CORNER_PX
        return np.array([px / r, px, px, px / (f * r**3), px / (f * r**5), px / (2 * f * r**2),
                         px / (2 * f * r**2)])


def prior_from_camera_info(info) -> IntrinsicPrior | None:
    """The prior of a session's :class:`mocap.core.session.CameraInfo`, or None without one."""
    if not getattr(info, "has_prior", False):
        return None
    pp = info.principal_px or ((info.width - 1) / 2.0, (info.height - 1) / 2.0)
    d = info.distortion or (0.0,) * 5
    return IntrinsicPrior(info.id, float(info.focal_px), tuple(pp), tuple(d),
                          info.intrinsics or "refine", (info.width, info.height), "session.toml")


# -- files ---------------------------------------------------------------------------------------

def read_priors(path: str | os.PathLike, *, mode: str = "refine") -> dict[str, IntrinsicPrior]:
    """Prior intrinsics per camera id from an aniposelib ``calibration.toml``, an OpenCV
    YAML/XML file or an Argus/easyWand profile (by extension: ``.toml``; ``.yml``, ``.yaml``,
    ``.xml``; anything else is read as a profile). Raises :class:`PriorFileError`."""
    path = Path(path)
    if not path.is_file():
        raise PriorFileError(f"{path}: file not found")
    ext = path.suffix.lower()
    if ext == ".toml":
        return _read_anipose(path, mode)
    if ext in (".yml", ".yaml", ".xml"):
        p = _read_opencv(path, mode)
        return {p.camera_id: p}
    return _read_profile(path, mode)


def _prior(cid, K, dist, mode, size, source, where) -> IntrinsicPrior:
    K = np.asarray(K, float)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise PriorFileError(f"{where}: expected a 3x3 camera matrix of numbers")
    if abs(K[0, 1]) > 1e-6 * K[0, 0]:
        raise PriorFileError(f"{where}: the camera matrix has skew; this package's cameras have none")
    fx, fy = K[0, 0], K[1, 1]
    if fx <= 0 or fy <= 0:
        raise PriorFileError(f"{where}: focal lengths must be positive, got {fx}, {fy}")
    if abs(fx / fy - 1.0) > 1e-3:
        raise PriorFileError(f"{where}: fx {fx:g} and fy {fy:g} differ (non-square pixels); "
                             "this package's cameras have square pixels")
    d = np.asarray(dist, float).ravel()
    if d.size < 4 or not np.all(np.isfinite(d)):
        raise PriorFileError(f"{where}: expected 4 or 5 distortion terms k1 k2 p1 p2 [k3]")
    if d.size > 5 and np.any(d[5:] != 0):
        raise PriorFileError(f"{where}: distortion terms beyond k3 (OpenCV's rational or thin-"
                             "prism model) are not supported; give k1 k2 p1 p2 k3")
    d = np.r_[d[:5], np.zeros(5)][:5]
    return IntrinsicPrior(str(cid), float(0.5 * (fx + fy)), (float(K[0, 2]), float(K[1, 2])),
                          tuple(float(v) for v in d), mode, size, source)


def _read_anipose(path: Path, mode: str) -> dict[str, IntrinsicPrior]:
    import tomllib

    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise PriorFileError(f"{path}: not a TOML file ({e})") from None
    out = {}
    for key, tbl in doc.items():
        if key == "metadata" or not isinstance(tbl, dict):
            continue
        where = f"{path}: [{key}]"
        for k in ("matrix", "distortion"):
            if k not in tbl:
                raise PriorFileError(f"{where}: missing key {k!r} (aniposelib's calibration.toml "
                                     "has name, size, matrix, distortion per camera)")
        size = tuple(int(v) for v in tbl["size"]) if "size" in tbl else None
        cid = str(tbl.get("name", key))
        out[cid] = _prior(cid, tbl["matrix"], tbl["distortion"], mode, size, path.name, where)
    if not out:
        raise PriorFileError(f"{path}: no camera tables ([cam_0], ...)")
    return out


def _read_opencv(path: Path, mode: str) -> IntrinsicPrior:
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise PriorFileError(f"{path}: not an OpenCV FileStorage file")
    try:
        K = fs.getNode("camera_matrix")
        D = fs.getNode("distortion_coefficients")
        for key, node in (("camera_matrix", K), ("distortion_coefficients", D)):
            if node.empty():
                raise PriorFileError(f"{path}: missing key {key!r}")
        w, h = fs.getNode("image_width"), fs.getNode("image_height")
        size = (int(w.real()), int(h.real())) if not (w.empty() or h.empty()) else None
        node = fs.getNode("camera_id")
        cid = node.string() if not node.empty() and node.string() else path.stem
        return _prior(cid, K.mat(), D.mat(), mode, size, path.name, str(path))
    finally:
        fs.release()


def _read_profile(path: Path, mode: str) -> dict[str, IntrinsicPrior]:
    out = {}
    text = path.read_text(encoding="utf-8", errors="replace")
    for i, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = [p for p in re.split(r"[\s,;]+", line) if p]
        where = f"{path}: line {i}"
        try:
            v = [float(p) for p in parts]
        except ValueError:
            raise PriorFileError(f"{where}: expected numbers, got {line!r}") from None
        if len(v) not in (6, 12):
            raise PriorFileError(f"{where}: expected 12 columns (camera, focal length px, width, "
                                 "height, cx, cy, aspect ratio, k1, k2, t1, t2, k3) or the first 6; "
                                 f"got {len(v)}")
        cam, f, w, h, cx, cy = v[:6]
        if f <= 0 or w <= 0 or h <= 0:
            raise PriorFileError(f"{where}: focal length and image size must be positive")
        if cam != int(cam) or cam < 0:
            raise PriorFileError(f"{where}: the camera number must be a whole number, got {cam}")
        k1 = k2 = t1 = t2 = k3 = 0.0
        if len(v) == 12:
            ar, k1, k2, t1, t2, k3 = v[6:]
            if abs(ar - 1.0) > 1e-3:
                raise PriorFileError(f"{where}: aspect ratio {ar:g}; this package's cameras have "
                                     "square pixels (1)")
        cid = f"cam{int(cam)}"
        if cid in out:
            raise PriorFileError(f"{where}: camera {int(cam)} given twice")
        out[cid] = IntrinsicPrior(cid, f, (cx - 1.0, h - cy), (k1, k2, -t1, t2, k3), mode,
                                  (int(w), int(h)), path.name, distortion_given=len(v) == 12)
    if not out:
        raise PriorFileError(f"{path}: no camera rows")
    return out


def merge_priors(session_priors: dict, file_priors: dict, cameras) -> dict[str, IntrinsicPrior]:
    """The priors the calibration uses: the session's, overridden by files' (per camera id).

    ``cameras``: the session's :class:`mocap.core.session.CameraInfo`; a file's camera that is not in
    the session, or whose image size differs from the session's, is an error.
    """
    by_id = {c.id: c for c in cameras}
    out = dict(session_priors)
    for cid, p in file_priors.items():
        if cid not in by_id:
            raise PriorFileError(f"{p.source}: camera {cid!r} is not in the session (cameras: "
                                 f"{', '.join(by_id)}); rename it in the file or the session")
        c = by_id[cid]
        if p.size is not None and tuple(p.size) != (c.width, c.height):
            raise PriorFileError(f"{p.source}: camera {cid!r} was measured at {p.size[0]}x"
                                 f"{p.size[1]} px, the session's is {c.width}x{c.height}")
        out[cid] = p
    return out


def prior_arrays(cameras, priors: dict[str, IntrinsicPrior]):
    """The bundle adjustment's view of the priors, for cameras (each with ``id``, ``width``,
    ``height``): held (C, 13) bool (a fixed prior's intrinsics), mean (C, 13) and sd (C, 13)
    (inf where no prior acts: poses, cameras without one, fixed priors)."""
    C = len(cameras)
    held = np.zeros((C, 13), bool)
    mean = np.zeros((C, 13))
    sd = np.full((C, 13), np.inf)
    for i, c in enumerate(cameras):
        p = priors.get(c.id)
        if p is None:
            continue
        mean[i, INTRINSIC_SLICE] = p.vector()
        if p.mode == "fixed":
            held[i, INTRINSIC_SLICE] = True
        else:
            sd[i, INTRINSIC_SLICE] = p.sd(c.width, c.height)
    return held, mean, sd


def refinement_report(rig, priors: dict[str, IntrinsicPrior], cov: np.ndarray | None) -> dict:
    """Per camera with a refined prior, per intrinsic: the prior, the estimate, the change, the
    prior's and the posterior's sd and ``wand_share = 1 - posterior variance / prior variance``
    (0: the wand added nothing, the prior alone; near 1: the wand determines it). Fixed priors:
    ``{"fixed": True}``."""
    from mocap.calib.bundle import camera_vector

    out = {}
    for i, c in enumerate(rig):
        p = priors.get(c.id)
        if p is None:
            continue
        if p.mode == "fixed":
            out[c.id] = {"mode": "fixed", "source": p.source}
            continue
        est = camera_vector(c)[INTRINSIC_SLICE]
        sd0 = p.sd(c.width, c.height)
        post = (np.sqrt(np.maximum(np.diag(cov[i * 13 + 6:i * 13 + 13, i * 13 + 6:i * 13 + 13]), 0))
                if cov is not None else np.full(7, np.nan))
        params = {}
        for k, name in enumerate(INTRINSIC_NAMES):
            share = 1.0 - (post[k] / sd0[k]) ** 2 if np.isfinite(post[k]) else float("nan")
            params[name] = {"prior": float(p.vector()[k]), "estimate": float(est[k]),
                            "change": float(est[k] - p.vector()[k]), "prior_sd": float(sd0[k]),
                            "posterior_sd": float(post[k]),
                            "wand_share": float(np.clip(share, 0.0, 1.0))}
        out[c.id] = {"mode": "refine", "source": p.source, "parameters": params}
    return out
