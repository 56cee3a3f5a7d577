"""The virtual camera rig: cameras on an arc in front of the face, and the calibration props.

World frame: the ground square's (origin at its first marker, y up); the face looks towards +z.
Cameras sit 0.6 to 0.82 m from the capture volume's centre, spread over azimuths from a little
left of the midline to the right side of the face (the markers are on the right half), at mixed
heights, each aimed near the volume centre. Intrinsics: 1280 x 1024 px, focal 1150 to 1400 px,
principal point within 12 px of the centre, Brown-Conrady distortion with k1 in [-0.12, -0.04],
k2 in [0, 0.08], p1, p2 within 6e-4 and k3 = 0.
"""

from __future__ import annotations

import numpy as np

from mocap.calib.camera import Camera, CameraRig

VOLUME_CENTER = np.array([40.0, 120.0, 40.0])  # mm: between the ground square and the face
VOLUME_HALF_MM = np.array([220.0, 190.0, 170.0])  # where the wand is waved
GROUND_MARKERS_MM = np.array([[0.0, 0.0, 0.0], [120.0, 0.0, 0.0], [0.0, 0.0, 80.0]])
WAND_OFFSETS_MM = np.array([0.0, 50.0, 150.0])


def make_rig(rng: np.random.Generator, n_cameras: int = 6, *, width: int = 1280,
             height: int = 1024) -> CameraRig:
    """Draw a rig of ``n_cameras`` (ids ``cam1``...) around the face."""
    if n_cameras < 2:
        raise ValueError(f"virtual rig: expected at least 2 cameras, got {n_cameras}")
    az = np.deg2rad(np.linspace(-40.0, 70.0, n_cameras) + rng.uniform(-4, 4, n_cameras))
    el = np.deg2rad(np.resize([28.0, 6.0, 18.0], n_cameras) + rng.uniform(-3, 3, n_cameras))
    dist = rng.uniform(600.0, 820.0, n_cameras)
    face_c = np.array([35.0, 145.0, 20.0])
    cams = []
    for i in range(n_cameras):
        direction = np.array([np.sin(az[i]) * np.cos(el[i]), np.sin(el[i]), np.cos(az[i]) * np.cos(el[i])])
        center = face_c + dist[i] * direction
        target = VOLUME_CENTER + rng.normal(0.0, 10.0, 3)
        focal = rng.uniform(1150.0, 1400.0)
        principal = ((width - 1) / 2 + rng.uniform(-12, 12), (height - 1) / 2 + rng.uniform(-12, 12))
        dist_coef = (rng.uniform(-0.12, -0.04), rng.uniform(0.0, 0.08),
                     rng.uniform(-6e-4, 6e-4), rng.uniform(-6e-4, 6e-4), 0.0)
        cams.append(Camera.look_at(f"cam{i + 1}", center, target, width=width, height=height,
                                   focal_px=focal, principal=principal, dist=dist_coef))
    return CameraRig(tuple(cams))


def wand_motion(rng: np.random.Generator, n_frames: int, fps: float,
                offsets_mm: np.ndarray = WAND_OFFSETS_MM) -> np.ndarray:
    """The wand's markers waved through the volume: (n_frames, n_wand_markers, 3) mm.

    The wand's centre follows a sum of three slow sinusoids per axis (0.07 to 0.5 Hz) filling
    the volume; its direction sweeps all orientations (azimuth and elevation as slow sinusoids),
    so every camera sees it from many angles. Marker k sits at ``offsets_mm[k]`` from one end.
    """
    t = np.arange(n_frames) / fps
    centre = np.tile(VOLUME_CENTER, (n_frames, 1)).astype(float)
    for axis in range(3):
        f = rng.uniform(0.07, 0.5, 3)
        ph = rng.uniform(0, 2 * np.pi, 3)
        amp = rng.dirichlet(np.ones(3)) * VOLUME_HALF_MM[axis]
        centre[:, axis] += np.sum(amp * np.sin(2 * np.pi * f * t[:, None] + ph), axis=1)
    az = 2 * np.pi * rng.uniform(0.05, 0.12) * t + rng.uniform(0, 2 * np.pi)
    el = 1.2 * np.sin(2 * np.pi * rng.uniform(0.05, 0.15) * t + rng.uniform(0, 2 * np.pi))
    u = np.stack([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)], axis=1)
    offsets = np.asarray(offsets_mm, float)
    mid = 0.5 * (offsets.min() + offsets.max())
    return centre[:, None, :] + (offsets - mid)[None, :, None] * u[:, None, :]
