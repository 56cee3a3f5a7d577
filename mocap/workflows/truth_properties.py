"""The paper's indices of a simulated face, defined as the estimator defines them.

A workflow-level helper: it runs the analysis's own normalisation and fit on the simulator's
noise-free true responses, so it sits above both (the simulator imports nothing from the
analysis). ``mocap simulate`` writes its table to ``truth/properties.csv`` (under the along-path
columns' names); tests and benchmarks call :func:`true_properties` with the markers the pipeline
fitted.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from mocap.analysis.paper.displacement import normalized, normalized_along
from mocap.analysis.paper.properties import du_properties
from mocap.core.atomic import write_csv
from mocap.reconstruction.trials import NORMALISE_S
from mocap.core.schedules import sample_commands, trapezoid
from mocap.simulate.config import SimConfig
from mocap.simulate.dus import DU_BY_ID
from mocap.simulate.face import VirtualFace
from mocap.simulate.motion import true_positions
from mocap.simulate.session_writer import RESPONSE_TAIL_S, take_rng, virtual_rig_and_face


def true_properties(cfg: SimConfig, face: VirtualFace, min_displacement_mm: float | None = None,
                    keep: dict | None = None) -> pd.DataFrame:
    """The paper's indices of the true face, defined as the estimator defines them.

    Per DU: the mean over the session's trials of the true responses to the paper's trapezoid
    (each trial with its own trial-to-trial variation and the hidden effect, as the pipeline
    averages them, but without the skin's frame-to-frame jitter and without measurement noise),
    normalised like the pipeline's (``mocap.analysis.paper.displacement.normalized_along``), fitted by the
    same code (``mocap.analysis.paper.properties.du_properties``). Markers: ``keep[du]`` (a set of
    marker names, e.g. the ones the pipeline fitted) when given; else those whose true peak
    displacement reaches ``min_displacement_mm`` (default: the pipeline's signal-to-noise rule at
    the nominal noise, 20 x 0.025 mm / sqrt(trials), and at least 0.05 mm), the nose-bridge marker
    left out as the pipeline leaves it.
    """
    if min_displacement_mm is None:
        min_displacement_mm = max(0.05, 20.0 * 0.025 / np.sqrt(cfg.n_trials))
    rows = []
    for du in face.du_ids:
        sched = trapezoid(du)
        n_frames = int(round((float(sched.time_s.max()) + RESPONSE_TAIL_S) * cfg.fps))
        pos = np.mean([true_positions(face, cfg.effect, sched, n_frames, cfg.fps, k,
                                      take_rng(cfg.seed, f"du{du:02d}_t{k:02d}"), skin_jitter=False)
                       for k in range(1, cfg.n_trials + 1)], axis=0)
        d = pos - face.rest_mm[None]
        window = max(1, int(round(NORMALISE_S * cfg.fps)))
        disp, _ = normalized(d, window)
        _, delta = normalized_along(d, window)
        if keep is not None:
            k = np.isin(np.asarray(face.marker_names), list(keep[du]))
        else:
            k = np.nanmax(disp, axis=0) >= min_displacement_mm
            k[face.nose_bridge] = False
        command = sample_commands(sched, [du], np.arange(n_frames) / cfg.fps)[:, 0]
        p = du_properties(du, delta, command, cfg.fps, k, n_boot=0)
        rows.append({"du": du, "name": DU_BY_ID[du].name, "alpha_fwd": p.fwd.alpha,
                     "beta_fwd": p.fwd.beta, "alpha_bwd": p.bwd.alpha, "beta_bwd": p.bwd.beta,
                     "sensitivity": p.sensitivity, "hysteresis": p.hysteresis,
                     "dyssynchrony": p.dyssynchrony, "max_displacement_mm": float(np.nanmax(disp)),
                     "n_markers": int(k.sum())})
    return pd.DataFrame(rows)


# truth/properties.csv names each value as properties.csv names the estimator that targets it
# (docs/outputs.md: a plain name there is the paper's computation literally, which this is not)
FILE_COLUMNS = {"alpha_fwd": "alpha_fwd_along_path", "beta_fwd": "beta_fwd_along_path",
                "alpha_bwd": "alpha_bwd_along_path", "beta_bwd": "beta_bwd_along_path",
                "sensitivity": "sensitivity_along_path", "hysteresis": "hysteresis_along_path",
                "dyssynchrony": "dyssynchrony_step_means", "n_markers": "n_markers_along_path"}


def write_true_properties(cfg: SimConfig, out_dir: str | Path) -> Path:
    """Write ``out_dir/truth/properties.csv`` for the session ``simulate(cfg, out_dir)`` wrote:
    :func:`true_properties` with its columns named as properties.csv's along-path estimator's
    (``sensitivity_along_path``, ..., ``dyssynchrony_step_means``, ``n_markers_along_path``;
    :data:`FILE_COLUMNS`), the columns that estimate them."""
    _, _, face = virtual_rig_and_face(cfg)
    path = Path(out_dir) / "truth" / "properties.csv"
    write_csv(true_properties(cfg, face).rename(columns=FILE_COLUMNS), path)
    return path
