"""The discrepancy workflow's figures and Rerun recording (outputs layer): the writers
``mocap discrepancy`` passes to :func:`mocap.workflows.discrepancy.results.run`
(:class:`mocap.workflows.discrepancy.results.DiscrepancyWriters`), so the workflow never imports matplotlib
or rerun."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mocap.analysis.discrepancy.prepare import PHASES, Prepared
from mocap.analysis.discrepancy.report import worst_marker
from mocap.analysis.discrepancy.result import DiscrepancyResult
from mocap.workflows.discrepancy.results import DiscrepancyWriters

__all__ = ["write_figures", "write_recording", "WRITERS"]


def write_figures(res: DiscrepancyResult, prep: Prepared, fig_dir: Path) -> dict:
    """The workflow's figures into ``fig_dir``: per stage the localisation grid (take x phase),
    the per-marker map, the gap per step, and per named effect the measured against the
    simulated traces; caption -> "figures/<file>.png"."""
    from mocap.outputs import figures as F

    out = {}
    data = prep.data
    floor = res.noise_floor_mm
    takes = [t.name for t in data.takes]
    for i, st in enumerate(res.stages):
        grid = np.array([[st["take_phases"][t].get(ph, np.nan) for ph in PHASES] for t in takes])
        p = fig_dir / f"discrepancy_localisation_stage{i}.png"
        F.save(F.discrepancy_localisation(takes, list(PHASES), grid, f"stage {i}: {st['model']}"), p)
        out[f"localisation, stage {i}"] = f"figures/{p.name}"
    names = list(data.marker_names)
    ratios = []
    for st in res.stages:
        r = np.full(len(names), np.nan)
        for mname, v in st["markers"].items():
            r[names.index(mname)] = v["ratio"]
        ratios.append(r)
    p = fig_dir / "discrepancy_markers.png"
    F.save(F.discrepancy_marker_map(data.rest_mm, ratios, [f"stage {i}: {st['model']}"
                                                           for i, st in enumerate(res.stages)]), p)
    out["per marker, every stage"] = f"figures/{p.name}"
    p = fig_dir / "discrepancy_gap.png"
    F.save(F.discrepancy_gap([st["model"] for st in res.stages],
                             [st["heldout_rms_mm"] for st in res.stages],
                             {du: [st["dus"].get(du, {}).get("rms_mm", np.nan) for st in res.stages]
                              for du in res.stages[0]["dus"]}, floor), p)
    out["gap per step"] = f"figures/{p.name}"
    # measured against simulated, before and after each step, on the takes where the gap was largest
    for i in range(len(res.steps)):
        gaps = res.stages[i]["takes"]
        worst = sorted(gaps, key=lambda k: -(gaps[k]["rms_mm"] or 0))[:3]
        panels = []
        for name in worst:
            k = takes.index(name)
            obs = data.observed(k)
            e0, e1 = res.heldout_residuals[i][k], res.heldout_residuals[i + 1][k]
            m, u = worst_marker(e0, data.used)
            tt = data.samples(k) / data.fps
            panels.append((f"{name}, marker {data.marker_names[m]} (along its largest residual)",
                           tt, obs[:, m] @ u, (obs[:, m] - e0[:, m]) @ u, (obs[:, m] - e1[:, m]) @ u))
        p = fig_dir / f"discrepancy_traces_step{i + 1}_{res.steps[i].effect}.png"
        F.save(F.discrepancy_traces(panels, res.stages[i]["model"], res.stages[i + 1]["model"]), p)
        out[f"measured vs simulated, step {i + 1} ({res.steps[i].effect})"] = f"figures/{p.name}"
    return out




def write_recording(path: Path, res: DiscrepancyResult, data, session_name: str) -> Path:
    """discrepancy.rrd (``mocap.outputs.recording.write_discrepancy_recording``)."""
    from mocap.outputs.recording import write_discrepancy_recording

    return write_discrepancy_recording(path, res, data, session_name)


WRITERS = DiscrepancyWriters(figures=write_figures, recording=write_recording)
