"""What the discrepancy workflow reports beside its steps: what the base model holds per DU,
how a parameter was read from the data, a named effect's parameter per DU, and the marker with
the largest residual (mm) with the direction of its largest residual."""

from __future__ import annotations

import numpy as np

from mocap.analysis.model.effects import CATALOGUE
from mocap.analysis.model.face_model import FaceModel
from mocap.analysis.model.data import ModelData
from mocap.analysis.model.profiles import profile_effect


def base_report(model: FaceModel) -> dict:
    """What the base model holds, per DU: the path bow (|B_1| / |D|, median), the loop width
    (median, command units), the PI density and branch parameters (mix, kappa), and the SD of the
    takes' bias shifts."""
    from mocap.analysis.model.face_model import DENSITY_FRACTIONS, bow_ratio

    out: dict = {}
    if model.effect("curvature") is not None:
        out["path_bow"] = round(bow_ratio(model), 4)
    if model.hysteresis:
        lw = model.loop_width()
        out["loop_width"] = {int(d): round(float(np.median(lw[n][model.active[n]])), 3)
                             for n, d in enumerate(model.du_ids) if model.active[n].any()}
        out["density_fractions"] = [float(f) for f in DENSITY_FRACTIONS]
        out["density"] = {int(d): [round(float(q), 4) for q in model.density[n]]
                          for n, d in enumerate(model.du_ids)}
        out["branch_mix_kappa"] = {int(d): [round(float(v), 4) for v in model.branch[n]]
                                   for n, d in enumerate(model.du_ids)}
    if model.shifts_takes and model.take_shifts:
        v = np.array([x for sh in model.take_shifts.values() for x in sh.values()], float)
        out["take_shift_sd"] = round(float(np.std(v)), 4)
    return out


READINGS = {
    "pull-weighted": "in travel along the measured paths where the multi-DU takes hold their DUs "
                     "at full command; the loss follows the other DU's pull at each marker "
                     "(skin shared where both DUs pull)",
    "uniform": "in travel along the measured paths where the multi-DU takes hold their DUs at "
               "full command; the same loss at every marker (a drive shared before the skin)",
    "drive": "in the model's drive, by the scalar law refitted on the multi-DU takes (no take "
             "holds its DUs at full command: a take driving them together to full command and "
             "holding there reads it in travel)",
}


def parameter_reading(name: str, model: FaceModel) -> str:
    """How the step's parameter was read where the data, not the fit, give it: the coupling's
    kappa (:func:`mocap.analysis.model.coupling.coupling_kappa`, its weighting in
    ``model.info["coupling_law"]``); "" otherwise."""
    if name != "coupling":
        return ""
    return READINGS.get(model.info.get("coupling_law", ""), "")


def per_du_values(data: ModelData, model: FaceModel, name: str) -> dict[int, float]:
    """A named global effect's parameter identified again from each DU's own single-DU takes
    (the model shares one value; a robot's actuators may differ): DU id -> value, in the
    effect's reported unit."""
    cls = CATALOGUE[name]
    out = {}
    for du in data.du_ids:
        takes = [k for k, t in enumerate(data.takes) if t.dus == (du,)]
        if not takes:
            continue
        prof = profile_effect(data, model, cls(), takes)
        out[int(du)] = float(prof.model.effect(name).describe()["value"])
    return out


def worst_marker(residual: np.ndarray, used: np.ndarray) -> tuple[int, np.ndarray]:
    """The marker with the largest residual (S, M, 3) among ``used``, and the unit direction
    (3,) in which its residual is largest (first principal axis)."""
    e = np.where(used[None, :, None], residual, np.nan)
    m = int(np.nanargmax(np.nansum(e ** 2, axis=(0, 2))))
    r = residual[:, m]
    r = r[np.isfinite(r).all(axis=1)]
    if len(r) < 3:
        return m, np.array([1.0, 0.0, 0.0])
    _, _, vt = np.linalg.svd(r - r.mean(axis=0), full_matrices=False)
    return m, vt[0]

