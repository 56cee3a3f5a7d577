"""Runs inside the peer environment (aniposelib installed there, not in the project): triangulate
the same observations with aniposelib and print its throughput and 3D error as JSON.

    python benchmarks/peer_triangulate.py CAMERAS_JSON OBS_NPZ
"""

import json
import sys
import time

import numpy as np
from aniposelib.cameras import Camera, CameraGroup


def main() -> int:
    cams = json.loads(open(sys.argv[1]).read())
    data = np.load(sys.argv[2])
    uv, X = data["uv"], data["X"]
    group = CameraGroup([Camera(name=c["id"], size=(c["width"], c["height"]), matrix=c["K"],
                                dist=c["dist"], rvec=c["rvec"], tvec=c["t"]) for c in cams])
    group.triangulate(uv[:, :1000], undistort=True, progress=False)  # warm up numba
    t0 = time.perf_counter()
    est = group.triangulate(uv, undistort=True, progress=False)
    dt = time.perf_counter() - t0
    err = np.sqrt(np.mean(np.sum((est - X) ** 2, axis=1)))
    print(json.dumps({"points": int(X.shape[0]), "points_per_s": X.shape[0] / dt,
                      "rms_error_mm": float(err)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
