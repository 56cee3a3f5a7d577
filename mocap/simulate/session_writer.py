"""Make a whole virtual session: ``OUT_DIR/session`` (FORMAT.md) and ``OUT_DIR/truth``.

``truth/`` is never read by the pipeline. It holds:

- ``cameras.toml``: the true rig (calibration.toml layout);
- ``trajectories/<take>.parquet``: true 3D positions, long format (take, frame, marker, x, y, z)
  for every take (wand markers ``W1``.., ground markers ``G1``..); for face takes without the
  capture's measurement error (the nose-bridge marker's shadow jitter is a capture error);
- ``labels/<take>.parquet``: column ``label`` (int32), one row per blob row of the take file in
  the same order: index of the true point (marker order of ``face.parquet``; wand or ground marker
  index), -1 for a ghost, -2 for a merged blob;
- ``face.parquet``: per DU and marker the true peak displacement vector and response parameters;
- ``properties.csv`` (written by ``mocap simulate``, not by :func:`simulate`): the paper's
  indices of the true face per DU, defined as the estimator defines them
  (``mocap.truth_properties``, which lives above the analysis: the simulator imports nothing
  from it);
- ``truth.json``: the configuration, seed, face family (``face_family``: the family drawn when
  the configuration asked for ``random``, with its settings), hidden effect and its equation's
  parameters, the nose-bridge marker, the degraded camera, per-take metadata (with each DU's
  common bias shift in the take, ``bias_shift``, and the family's part of it, ``family_shift``,
  command units).

The session itself never names the face family.

Every take gets its own random stream (seeded by the session seed and the take's name), so a
session is deterministic for a seed and one take does not change when others are added.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from mocap.calib.calibration_file import write_calibration
from mocap import __version__
from mocap.atomic import write_csv, write_parquet, write_text
from mocap.schedules import identification_battery, trapezoid
from mocap.simulate.capture import observe
from mocap.simulate.config import SimConfig
from mocap.simulate.dus import DU_BY_ID
from mocap.simulate.face import VirtualFace, make_face
from mocap.simulate.families import family_stream, resolve_family
from mocap.simulate.motion import true_take
from mocap.simulate.rig import GROUND_MARKERS_MM, make_rig, wand_motion
from mocap.simulate.smile import SmileTiming, nominal_branches, smile_commands
from mocap.simulate.truth import effect_parts

RESPONSE_TAIL_S = 0.05  # one more step at 0 after the trapezoid's last row
BATTERY_TAIL_S = 0.5


@dataclass
class PlannedTake:
    name: str
    kind: str
    rows: pd.DataFrame | None = None
    du: int | None = None
    trial: int | None = None
    plan: str | None = None
    duration_s: float = 0.0
    purpose: str = ""


def take_rng(seed: int, name: str) -> np.random.Generator:
    return np.random.default_rng([int(seed), zlib.crc32(name.encode())])


def field_pairs(face: VirtualFace, max_pairs: int) -> list[tuple[int, int]]:
    """DU pairs whose displacement fields overlap most (greedy, each DU in one pair at most)."""
    mag = np.linalg.norm(face.D_mm, axis=-1)
    norm = mag / np.linalg.norm(mag, axis=1, keepdims=True)
    overlap = norm @ norm.T
    n = len(face.du_ids)
    cand = sorted(((overlap[i, j], i, j) for i in range(n) for j in range(i + 1, n)), reverse=True)
    used: set[int] = set()
    pairs = []
    for _, i, j in cand:
        if i in used or j in used:
            continue
        pairs.append((face.du_ids[i], face.du_ids[j]))
        used |= {i, j}
        if len(pairs) >= max_pairs:
            break
    return pairs


def plan_takes(cfg: SimConfig, face: VirtualFace) -> list[PlannedTake]:
    """The session's takes in manifest order."""
    takes: list[PlannedTake] = []
    if not cfg.labeled:
        takes.append(PlannedTake("wand", "wand", duration_s=cfg.wand_duration_s))
        if cfg.ground:
            takes.append(PlannedTake("ground", "ground", duration_s=cfg.ground_s))
    takes.append(PlannedTake("rest", "rest", duration_s=cfg.rest_s))
    for du in cfg.du_ids:
        rows = trapezoid(du)
        for k in range(1, cfg.n_trials + 1):
            takes.append(PlannedTake(f"du{du:02d}_t{k:02d}", "response", rows, du=du, trial=k,
                                     duration_s=float(rows.time_s.max()) + RESPONSE_TAIL_S,
                                     purpose="the paper's trapezoid"))
    motion_dus = [d for d in cfg.motion_dus if d in face.du_ids]
    if motion_dus and cfg.motion_plans:
        timing = SmileTiming()
        branches = nominal_branches(motion_dus)
        label = "_".join(f"{d:02d}" for d in motion_dus)
        for p in cfg.motion_plans:
            rows = smile_commands(p, branches, timing)
            takes.append(PlannedTake(f"smile_du{label}_plan{p}", "motion", rows, plan=p,
                                     duration_s=timing.total_s,
                                     purpose="the paper's smile design through inverse sigmoids"))
    if cfg.battery:
        pairs = field_pairs(face, max(1, len(face.du_ids) // 2)) if len(face.du_ids) > 1 else []
        for b in identification_battery(face.du_ids, pairs):
            takes.append(PlannedTake(b.name, "motion", b.rows, plan="identification",
                                     duration_s=float(b.rows.time_s.max()) + BATTERY_TAIL_S,
                                     purpose=b.purpose))
    for i, path in enumerate(cfg.extra_commands, start=1):
        rows = pd.read_csv(path)
        missing = {"time_s", "du", "command"} - set(rows.columns)
        if missing:
            raise ValueError(f"{path}: expected columns time_s,du,command; missing {sorted(missing)}")
        stem = Path(path).stem
        # a file named ..._planA.csv plays plan A (so 'mocap run' evaluates it against A)
        label = stem[-1].upper() if stem[:-1].lower().endswith("_plan") else stem
        takes.append(PlannedTake(f"commands_{i:02d}_{stem}", "motion", rows, plan=label,
                                 duration_s=float(rows.time_s.max()) + BATTERY_TAIL_S,
                                 purpose=f"commands from {Path(path).name}"))
    return takes


def _toml_str(s: str) -> str:
    return '"' + str(s).replace("\\", "\\\\").replace('"', '\\"') + '"'


def manifest_text(cfg: SimConfig, rig, takes: list[PlannedTake], files: dict, cmd_files: dict) -> str:
    lines = [
        'schema = "mocap-session/1"',
        f'name = "virtual-face-{cfg.preset}-seed{cfg.seed}"',
        f"fps = {float(cfg.fps)!r}",
        "",
    ]
    if not cfg.labeled:
        for cam in rig:
            focal = round(float(cam.focal_px) * (1.0 + 0.06 * np.sin(7.0 * len(cam.id) + cam.K[0, 2])), 1)
            lines += ["[[cameras]]", f"id = {_toml_str(cam.id)}", f"width = {cam.width}",
                      f"height = {cam.height}", f"focal_px = {float(focal)!r}", ""]
        lines += ["[wand]", f"marker_offsets_mm = {[float(v) for v in cfg.wand_offsets_mm]}", ""]
        if cfg.ground:
            lines += ["[ground]",
                      f"markers_mm = {[[float(v) for v in r] for r in GROUND_MARKERS_MM]}", ""]
    for du in cfg.du_ids:
        s = DU_BY_ID[du]
        lines += ["[[dus]]", f"id = {du}", f"name = {_toml_str(s.name)}",
                  f"feedback = {'true' if s.feedback else 'false'}", ""]
    for t in takes:
        lines += ["[[takes]]", f"name = {_toml_str(t.name)}", f"kind = {_toml_str(t.kind)}",
                  f"file = {_toml_str(files[t.name])}"]
        if t.name in cmd_files:
            lines.append(f"commands = {_toml_str(cmd_files[t.name])}")
        if t.du is not None:
            lines.append(f"du = {t.du}")
        if t.trial is not None:
            lines.append(f"trial = {t.trial}")
        if t.plan is not None:
            lines.append(f"plan = {_toml_str(t.plan)}")
        lines.append("")
    return "\n".join(lines)


def _write_table(df: pd.DataFrame, path: Path, fmt: str) -> None:
    if fmt == "parquet":
        write_parquet(df, path)
    else:
        write_csv(df, path, decimals=4)


def _long(take: str, names, pos: np.ndarray) -> pd.DataFrame:
    n_frames, n_points, _ = pos.shape
    return pd.DataFrame({
        "take": take,
        "frame": np.repeat(np.arange(n_frames, dtype=np.int64), n_points),
        "marker": np.tile(np.asarray(names, dtype=object), n_frames),
        "x": pos[..., 0].ravel(),
        "y": pos[..., 1].ravel(),
        "z": pos[..., 2].ravel(),
    })


def virtual_rig_and_face(cfg: SimConfig):
    """The true rig and face of a configuration (what ``simulate`` draws first)."""
    master = np.random.default_rng(cfg.seed)
    rig = make_rig(master, cfg.n_cameras, width=cfg.width, height=cfg.height)
    family = resolve_family(cfg.face_family, cfg.seed)
    face = make_face(master, cfg.n_markers, cfg.du_ids, family=family,
                     family_rng=family_stream(cfg.seed, "traits"))
    return master, rig, face


def simulate(cfg: SimConfig, out_dir: str | Path,
             progress: Callable[[str], None] | None = None) -> dict:
    """Write a virtual session to ``out_dir/session`` and its truth to ``out_dir/truth``.

    Returns a summary dict (paths, takes, blob counts, seconds). Memory is bounded by one take.
    """
    t_start = time.perf_counter()
    say = progress or (lambda msg: None)
    out = Path(out_dir)
    sess = out / "session"
    truth = out / "truth"
    master, rig, face = virtual_rig_and_face(cfg)
    takes = plan_takes(cfg, face)
    ext = "parquet" if cfg.take_format == "parquet" else "csv"
    files = {t.name: f"takes/{t.name}.{ext}" for t in takes}
    cmd_files = {t.name: f"takes/{t.name}_commands.csv" for t in takes if t.rows is not None}

    # shadowed nose-bridge marker: only the cameras facing it most squarely see it
    allowed = np.ones((len(rig), face.n_markers), bool)
    to_cams = np.stack([c.center for c in rig]) - face.rest_mm[face.nose_bridge]
    cosang = (to_cams / np.linalg.norm(to_cams, axis=1, keepdims=True)) @ face.normals[face.nose_bridge]
    nb_cams = np.argsort(-cosang)[: cfg.nose_bridge_cameras]
    allowed[:, face.nose_bridge] = False
    allowed[nb_cams, face.nose_bridge] = True
    jitter = np.zeros(face.n_markers)
    jitter[face.nose_bridge] = cfg.nose_bridge_jitter_mm
    per_camera = {cfg.degrade_camera: cfg.degraded} if cfg.degrade_camera else None
    if cfg.degrade_camera and cfg.degrade_camera not in rig.ids:
        raise ValueError(f"simulate: degrade_camera {cfg.degrade_camera!r} not in {rig.ids}")
    if cfg.wand_sparse_camera and cfg.wand_sparse_camera not in rig.ids:
        raise ValueError(f"simulate: wand_sparse_camera {cfg.wand_sparse_camera!r} not in {rig.ids}")

    take_meta = []
    n_blobs_total = 0
    for i, t in enumerate(takes, start=1):
        rng = take_rng(cfg.seed, t.name)
        shifts = {}
        n_frames = int(round(t.duration_s * cfg.fps))
        if t.kind == "wand":
            pos = wand_motion(rng, n_frames, cfg.fps, np.asarray(cfg.wand_offsets_mm, float))
            if cfg.wand_gap_s > 0:
                g0 = int((n_frames - cfg.wand_gap_s * cfg.fps) / 2)
                pos[g0: g0 + int(cfg.wand_gap_s * cfg.fps)] = np.nan
            names = [f"W{k + 1}" for k in range(pos.shape[1])]
            normals, allow, jit, obs_points = None, None, None, pos
        elif t.kind == "ground":
            pos = np.broadcast_to(GROUND_MARKERS_MM, (n_frames,) + GROUND_MARKERS_MM.shape).copy()
            names = [f"G{k + 1}" for k in range(pos.shape[1])]
            normals, allow, jit, obs_points = None, None, None, pos
        else:
            tt = true_take(face, cfg.effect, t.rows, n_frames, cfg.fps, t.trial or 1, rng)
            pos = tt.positions
            shifts = {"bias_shift": {str(d): float(v) for d, v in zip(tt.dus, tt.bias_shift)},
                      "family_shift": {str(d): float(v) for d, v in zip(tt.dus, tt.family_shift)}}
            names = list(face.marker_names)
            normals, allow, jit, obs_points = face.normals, allowed, jitter, pos
        write_parquet(_long(t.name, names, pos), truth / "trajectories" / f"{t.name}.parquet")
        if t.rows is not None:
            write_csv(t.rows.sort_values("time_s", kind="stable"), sess / cmd_files[t.name],
                      decimals=6)
        if cfg.labeled:
            meas = pos + labeled_noise(rng, pos.shape, cfg.labeled_noise_mm, jitter)
            lost = rng.random(pos.shape[:2]) < 0.002
            lost[:, face.nose_bridge] |= rng.random(n_frames) < 0.1
            meas[lost] = np.nan
            df = _long(t.name, names, meas).drop(columns="take")
            _write_table(df, sess / files[t.name], cfg.take_format)
            n_rows = len(df)
        else:
            blobs, labels = observe(rig, obs_points, rng, noise=cfg.noise,
                                    per_camera_noise=per_camera, normals=normals,
                                    allowed=allow, measurement_jitter_mm=jit)
            if t.kind == "wand" and cfg.wand_sparse_camera:
                # that camera sees the wand only in a fraction of frames (four blocks)
                seen = np.zeros(n_frames, bool)
                block = int(cfg.wand_sparse_fraction * n_frames / 4)
                for s0 in np.linspace(0, n_frames - block, 4).astype(int):
                    seen[s0: s0 + block] = True
                drop = ((blobs["camera"].to_numpy() == cfg.wand_sparse_camera)
                        & ~seen[blobs["frame"].to_numpy()] & (labels != -1))
                blobs, labels = blobs[~drop].reset_index(drop=True), labels[~drop]
            if cfg.take_format == "parquet":
                blobs = blobs.astype({"x": "float32", "y": "float32"})
            _write_table(blobs, sess / files[t.name], cfg.take_format)
            write_parquet(pd.DataFrame({"label": labels}), truth / "labels" / f"{t.name}.parquet")
            n_rows = len(blobs)
        n_blobs_total += n_rows
        take_meta.append({"name": t.name, "kind": t.kind, "frames": n_frames, "rows": n_rows,
                          "du": t.du, "trial": t.trial, "plan": t.plan, "purpose": t.purpose,
                          "dus": sorted(set(int(d) for d in t.rows["du"])) if t.rows is not None else [],
                          **shifts})
        say(f"[{i}/{len(takes)}] {t.name}: {n_frames} frames, {n_rows} rows")

    if not cfg.labeled:
        write_calibration(truth / "cameras.toml", rig, header={"source": "facemocap simulator truth"})
    markers_rng = np.random.default_rng([cfg.seed, 7])
    approx = face.rest_mm + markers_rng.normal(0.0, 1.0, face.rest_mm.shape)
    if not cfg.ground and not cfg.labeled:  # FORMAT.md: the world frame is the first camera's
        approx = rig[0].world_to_camera(approx)
    write_csv(pd.DataFrame({"name": face.marker_names, "x": approx[:, 0], "y": approx[:, 1],
                            "z": approx[:, 2]}), sess / "markers.csv", decimals=2)
    write_parquet(face_table(face), truth / "face.parquet")
    info = {
        "generator": f"facemocap {__version__} mocap simulate",
        "config": _jsonable(dataclasses.asdict(cfg)),
        "face_family": {**face.family.describe(), "requested": cfg.face_family},
        "effect": cfg.effect.describe(),
        "nose_bridge_marker": face.marker_names[face.nose_bridge],
        "nose_bridge_cameras": [rig.ids[i] for i in nb_cams],
        "degraded_camera": cfg.degrade_camera,
        "wand_offsets_mm": [float(v) for v in cfg.wand_offsets_mm],
        "ground": bool(cfg.ground),
        "takes": take_meta,
    }
    coupling = effect_parts(info).get("coupling")
    if coupling:
        # the coupling's loss as the takes show it: in travel along each marker's path, for
        # the groups of DUs the session drives together
        groups = sorted({tuple(t["dus"]) for t in take_meta if len(t["dus"]) > 1})
        info["coupling_travel_kappa"] = face.travel_kappa(
            coupling["parameters"]["kappa"], pull_weighted=coupling.get("form", "model") == "model",
            groups=groups or None)
    write_text(truth / "truth.json", json.dumps(info, indent=2))
    write_text(sess / "session.toml", manifest_text(cfg, rig, takes, files, cmd_files))
    return {"session": str(sess), "truth": str(truth), "takes": len(takes),
            "rows": n_blobs_total, "seconds": time.perf_counter() - t_start}


def labeled_noise(rng, shape, sd_mm, extra_mm):
    """Measurement noise of labeled 3D takes (n_frames, n_markers, 3): sd_mm per axis, plus each
    marker's extra shadow jitter extra_mm (n_markers,)."""
    return rng.normal(0.0, 1.0, shape) * np.sqrt(sd_mm**2 + extra_mm**2)[None, :, None]


def face_table(face: VirtualFace) -> pd.DataFrame:
    """Per DU and marker: rest position, peak vector, response parameters (and the family's
    traits, ``alpha_bwd`` and the path vector ``path_x/y/z`` mm, for families other than pi)."""
    n, m = face.alpha.shape
    extra = {}
    if face.traits is not None:
        extra = {"alpha_bwd": face.traits.alpha_bwd.ravel(),
                 "path_x": face.traits.path_vec[..., 0].ravel(),
                 "path_y": face.traits.path_vec[..., 1].ravel(),
                 "path_z": face.traits.path_vec[..., 2].ravel()}
    return pd.DataFrame({
        "du": np.repeat(face.du_ids, m),
        "marker": np.tile(face.marker_names, n),
        "rest_x": np.tile(face.rest_mm[:, 0], n),
        "rest_y": np.tile(face.rest_mm[:, 1], n),
        "rest_z": np.tile(face.rest_mm[:, 2], n),
        "peak_x": face.D_mm[..., 0].ravel(),
        "peak_y": face.D_mm[..., 1].ravel(),
        "peak_z": face.D_mm[..., 2].ravel(),
        "peak_mm": np.linalg.norm(face.D_mm, axis=-1).ravel(),
        "alpha": face.alpha.ravel(),
        "beta": face.beta.ravel(),
        "r_half": face.r_half.ravel(),
        **extra,
    })


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, Path):
        return str(x)
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x


def print_progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


