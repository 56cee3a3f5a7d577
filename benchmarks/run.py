"""Benchmarks at full-study scale (the ``paper`` preset), on this machine.

    python benchmarks/run.py                 # every stage; the paper session is cached
    python benchmarks/run.py --stages simulate,calibrate

Each stage runs in a fresh Python process so its wall time and peak resident memory (ru_maxrss)
are its own. Results go to ``benchmarks/results.json`` and ``benchmarks/results.md``; the paper
session is cached in ``benchmarks/cache/paper`` (not committed).

Stages:
- ``simulate``: ``mocap simulate --preset paper`` (target: under 10 minutes, under 4 GB);
- ``calibrate``: wand calibration of the paper session's rig (target: under 20 s on 2 cores);
- ``triangulate``: known correspondences, 2 M points x 6 cameras (target >= 3 M points/s);
- ``peer``: the same on 200 k points against aniposelib, installed only in a venv of its own under
  ``benchmarks/cache`` (target: >= 30 x its throughput with an equal or smaller 3D error);
- ``reconstruct``: correspondence, triangulation and labeling of every face take (targets: the
  whole preset under 3 minutes, >= 300 k points/s, under 8 GB);
- ``run``: ``mocap run`` end to end (target: under 5 minutes, 8 GB), and the paper indices
  against the simulator's truth (same markers, same estimator on the noise-free response).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
CACHE = HERE / "cache" / "paper"
TARGETS = {"simulate": {"seconds": 600, "peak_gb": 4.0}, "calibrate": {"seconds": 20},
           "triangulate": {"kernel_points_per_s": 3_000_000},
           "peer": {"throughput_ratio": 30},
           "reconstruct": {"reconstruct_seconds": 180, "points_per_s": 300_000, "peak_gb": 8.0},
           "run": {"end_to_end_seconds": 300, "peak_gb": 8.0},
           "discrepancy": {"seconds": 600}}


def stage_simulate() -> dict:
    from mocap.simulate import preset, simulate

    if CACHE.exists():
        shutil.rmtree(CACHE)
    summary = simulate(preset("paper", seed=2018), CACHE)
    size = sum(p.stat().st_size for p in (CACHE / "session").rglob("*") if p.is_file())
    return {"takes": summary["takes"], "rows": summary["rows"], "session_mb": round(size / 1e6, 1)}


def stage_calibrate() -> dict:
    from mocap.calib.calibration_file import read_calibration
    from mocap.calib.wand_calibration import calibrate_session
    from mocap.session import load_session

    import numpy as np

    r = calibrate_session(load_session(CACHE / "session"))
    truth, _ = read_calibration(CACHE / "truth" / "cameras.toml")
    centre = max(float(np.linalg.norm(c.center - t.center)) for c, t in zip(r.rig, truth))
    q = r.quality
    return {"centre_error_max_mm": round(centre, 4), "rating": q["rating"],
            "wand_length_error_sd_mm": round(q["wand_length_error_sd_mm"], 4),
            "reprojection_rms_px": round(q["reprojection_rms_px_all"], 4)}


def stage_triangulate() -> dict:
    """Known correspondences: 2 million points seen by the 6 cameras of the paper rig."""
    import numpy as np

    from mocap.calib.calibration_file import read_calibration
    from mocap.calib.triangulation import normalized_observations, triangulate
    from mocap.calib.triangulation_kernel import triangulate_normalized

    rig, _ = read_calibration(CACHE / "truth" / "cameras.toml")
    rng = np.random.default_rng(0)
    n = 2_000_000
    X = rng.uniform([-40, 60, -20], [110, 220, 60], (n, 3))
    uv = rig.project(X) + rng.normal(0, 0.08, (len(rig), n, 2))
    Rt = np.stack([np.hstack([c.R, c.t[:, None]]) for c in rig])
    f = np.array([c.focal_px for c in rig])
    xn = normalized_observations(rig, uv)
    triangulate_normalized(Rt, f, xn[:, :1000], 1)  # compile / load the cached kernel
    t0 = time.perf_counter()
    Xk = triangulate_normalized(Rt, f, xn, 1)
    t_kernel = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = triangulate(rig, uv, min_cameras=2)
    t_full = time.perf_counter() - t0
    err = np.sqrt(np.mean(np.sum((Xk - X) ** 2, axis=1)))
    return {"points": n, "kernel_points_per_s": round(n / t_kernel),
            "with_undistortion_points_per_s": round(n / t_full),
            "rms_error_mm": round(float(err), 5),
            "residual_px_mean": round(float(np.nanmean(res.residual_px)), 4)}


def stage_peer() -> dict:
    """Ours against aniposelib (installed only in the benchmark's own venv) on the same
    cameras and correspondences: throughput ratio and both 3D errors."""
    import numpy as np

    from mocap.calib.calibration_file import read_calibration
    from mocap.calib.camera import rodrigues_from_rotation
    from mocap.calib.triangulation import triangulate

    venv = HERE / "cache" / "peer-venv"
    py = venv / "bin" / "python"
    if not py.exists():
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
        subprocess.run([str(py), "-m", "pip", "install", "-q", "aniposelib"], check=True)
    rig, _ = read_calibration(CACHE / "truth" / "cameras.toml")
    rng = np.random.default_rng(1)
    n = 200_000
    X = rng.uniform([-40, 60, -20], [110, 220, 60], (n, 3))
    uv = rig.project(X) + rng.normal(0, 0.08, (len(rig), n, 2))
    work = HERE / "cache"
    np.savez(work / "peer_obs.npz", uv=uv, X=X)
    cams = [{"id": c.id, "width": c.width, "height": c.height, "K": c.K.tolist(),
             "dist": c.dist.tolist(), "rvec": rodrigues_from_rotation(c.R).tolist(),
             "t": c.t.tolist()} for c in rig]
    (work / "peer_cams.json").write_text(json.dumps(cams))
    out = subprocess.run([str(py), str(HERE / "peer_triangulate.py"), str(work / "peer_cams.json"),
                          str(work / "peer_obs.npz")], check=True, capture_output=True, text=True)
    peer = json.loads(out.stdout.strip().splitlines()[-1])
    from mocap.calib.triangulation import normalized_observations
    from mocap.calib.triangulation_kernel import triangulate_normalized

    triangulate(rig, uv[:, :1000])
    t0 = time.perf_counter()
    ours = triangulate(rig, uv)  # undistortion, kernel, and per-point reprojection residuals
    dt = time.perf_counter() - t0
    xn = normalized_observations(rig, uv)
    Rt = np.stack([np.hstack([c.R, c.t[:, None]]) for c in rig])
    f = np.array([c.focal_px for c in rig])
    t0 = time.perf_counter()
    triangulate_normalized(Rt, f, xn, 1)
    dk = time.perf_counter() - t0
    err = float(np.sqrt(np.mean(np.sum((ours.X - X) ** 2, axis=1))))
    return {"points": n, "ours_points_per_s": round(n / dt), "ours_rms_error_mm": round(err, 5),
            "ours_kernel_points_per_s": round(n / dk),
            "kernel_throughput_ratio": round(n / dk / peer["points_per_s"], 1),
            "aniposelib_points_per_s": round(peer["points_per_s"]),
            "aniposelib_rms_error_mm": round(peer["rms_error_mm"], 5),
            "throughput_ratio": round(n / dt / peer["points_per_s"], 1)}


def stage_reconstruct() -> dict:
    """Correspondence + triangulation + labeling of every face take of the paper session."""
    from mocap.calib.wand_calibration import calibrate_session
    from mocap.pipeline import RunSettings, reconstruct_all
    from mocap.session import load_session

    session = load_session(CACHE / "session")
    calibration = calibrate_session(session)
    out = HERE / "cache" / "paper_out"
    t0 = time.perf_counter()
    recon = reconstruct_all(session, out, calibration, RunSettings(), lambda m: None)
    dt = time.perf_counter() - t0
    pts = recon.stats["labeled_points"]
    blobs = sum(s.get("blobs", 0) for s in recon.stats["takes"].values())
    return {"takes": len(recon.stats["takes"]), "labeled_points": pts, "blobs": blobs,
            "reconstruct_seconds": round(dt, 1), "points_per_s": round(pts / dt),
            "blobs_per_s": round(blobs / dt)}


def stage_run() -> dict:
    """``mocap run`` end to end on the paper session, and its properties against the truth."""
    import numpy as np
    import pandas as pd

    from mocap.pipeline import run_session
    from mocap.simulate import preset
    from mocap.simulate.session_writer import virtual_rig_and_face
    from mocap.truth_properties import true_properties

    out = HERE / "cache" / "paper_run"
    t0 = time.perf_counter()
    res = run_session(CACHE / "session", out)
    dt = time.perf_counter() - t0
    cfg = preset("paper", seed=2018)
    _, _, face = virtual_rig_and_face(cfg)
    mp = pd.read_csv(out / "marker_properties.csv")
    fitted = {du: set(g["marker"][g["fitted"]]) for du, g in mp.groupby("du")}
    truth = true_properties(cfg, face, keep=fitted).set_index("du")
    est = pd.read_csv(out / "properties.csv").set_index("du")
    err = {
        "alpha_rel_max": float(np.max(np.abs(est["sensitivity"] / truth["sensitivity"] - 1))),
        "beta_fwd_abs_max": float(np.max(np.abs(est["beta_fwd"] - truth["beta_fwd"]))),
        "beta_bwd_abs_max": float(np.max(np.abs(est["beta_bwd"] - truth["beta_bwd"]))),
        "hysteresis_abs_max": float(np.max(np.abs(est["hysteresis"] - truth["hysteresis"]))),
        "dyssynchrony_rel_max": float(np.max(np.abs(est["dyssynchrony"] / truth["dyssynchrony"] - 1))),
        # the true paths are straight: the estimator's formula on the noise-free truth gives 1
        "linearity_corrected_abs_max": float(np.max(np.abs(est["linearity_corrected_mean"] - 1))),
    }
    feedback = est.loc[[1, 2, 12]]
    others = est.drop(index=[1, 2, 12])
    return {"end_to_end_seconds": round(dt, 1), "timings": res.summary["timings_s"],
            "errors_vs_truth": {k: round(v, 4) for k, v in err.items()},
            "feedback_alpha_max": round(float(feedback["sensitivity"].max()), 4),
            "open_loop_alpha_min": round(float(others["sensitivity"].min()), 4),
            "calibration": res.summary.get("calibration"),
            "rrd_mb": round((out / "session.rrd").stat().st_size / 1e6, 1)
            if (out / "session.rrd").exists() else None,
            "labeled_points": res.summary["reconstruction"]["labeled_points"],
            "reconstruct_points_per_s": round(res.summary["reconstruction"]["labeled_points"]
                                              / res.summary["timings_s"]["reconstruct_s"]),
            "noise_floor_mm": res.summary.get("noise_floor_mm"),
            "rejections": res.summary.get("rejections")}


def stage_discrepancy() -> dict:
    """``mocap discrepancy`` on the paper run's output (no hidden effect: names nothing)."""
    from mocap.analysis.discrepancy import DiscrepancySettings
    from mocap.discrepancy_io import run

    src = HERE / "cache" / "paper_run"
    if not (src / "summary.json").exists():
        raise SystemExit("run the 'run' stage first (the discrepancy stage reads its trajectories)")
    out = HERE / "cache" / "paper_discrepancy"
    t0 = time.perf_counter()
    res = run(src, out, DiscrepancySettings(jobs=os.cpu_count() or 1))
    dt = time.perf_counter() - t0
    return {"workflow_seconds": round(dt, 1), "named": res.named,
            "heldout_rms_mm": round(res.final_heldout_rms_mm, 4),
            "noise_floor_mm": round(res.noise_floor_mm, 4),
            "takes": len(res.heldout_residuals[0])}


STAGES = {"simulate": stage_simulate, "calibrate": stage_calibrate,
          "triangulate": stage_triangulate, "peer": stage_peer, "reconstruct": stage_reconstruct,
          "run": stage_run, "discrepancy": stage_discrepancy}


def run_stage(name: str) -> dict:
    t0 = time.perf_counter()
    info = STAGES[name]()
    info["seconds"] = round(time.perf_counter() - t0, 2)
    info["peak_gb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2, 3)
    return info


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stages", default=",".join(STAGES))
    ap.add_argument("--stage", help=argparse.SUPPRESS)  # internal: run one stage, print JSON
    args = ap.parse_args()
    if args.stage:
        print(json.dumps(run_stage(args.stage)))
        return 0
    names = [s for s in args.stages.split(",") if s]
    results_path = HERE / "results.json"
    results = json.loads(results_path.read_text()) if results_path.exists() else {}
    results["machine"] = {"cpus": os.cpu_count(), "python": platform.python_version(),
                          "platform": platform.platform()}
    for name in names:
        if name != "simulate" and not (CACHE / "session" / "session.toml").exists():
            print("paper session not cached: running simulate first", file=sys.stderr)
            names.insert(names.index(name), "simulate")
        print(f"== {name}", file=sys.stderr, flush=True)
        out = subprocess.run([sys.executable, __file__, "--stage", name], check=True,
                             capture_output=True, text=True)
        info = json.loads(out.stdout.strip().splitlines()[-1])
        info["targets"] = TARGETS.get(name, {})
        info["date"] = time.strftime("%Y-%m-%d")
        results.setdefault("stages", {})[name] = info
        print(json.dumps(info), file=sys.stderr)
    results_path.write_text(json.dumps(results, indent=2) + "\n")
    lines = ["# Benchmarks (paper preset)", "",
             f"Machine: {results['machine']['cpus']} CPUs, Python {results['machine']['python']}.", "",
             "| stage | seconds | peak memory (GB) | target | details |", "|---|---|---|---|---|"]
    for name, info in results.get("stages", {}).items():
        details = ", ".join(f"{k}={v}" for k, v in info.items()
                            if k not in ("seconds", "peak_gb", "targets", "date"))
        lines.append(f"| {name} | {info['seconds']} | {info['peak_gb']} | {info['targets']} | {details} |")
    (HERE / "results.md").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
