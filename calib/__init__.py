"""Camera models and wand calibration of a multi-camera rig.

Conventions (OpenCV's, as FORMAT.md): camera x right, y down, z forward; extrinsics are
camera-from-world, ``x_cam = R @ X + t`` with X in mm; pinhole ``K`` in px; Brown-Conrady
distortion ``dist = [k1, k2, p1, p2, k3]``; image origin at the top-left pixel's centre.
"""

from mocap.calib.camera import Camera, CameraRig

__all__ = ["Camera", "CameraRig"]
