"""Reading what a simulated session's truth says (``OUT/truth/truth.json``), for scoring.

Pure functions of the parsed ``truth.json`` dict: the sweeps read the file once and ask these.
"""

from __future__ import annotations

import numpy as np


def effect_parts(info: dict) -> dict[str, dict]:
    """{effect name: its description (parameters, form, ...)} of the hidden effect(s) in
    ``info`` ({} for none)."""
    eff = info["effect"]
    return {p["name"]: p for p in eff.get("effects", [eff]) if p["name"] != "none"}


def effect_parameters(info: dict) -> dict[str, dict[str, float]]:
    """{effect name: {parameter: value}} of the hidden effect(s) in ``info`` ({} for none)."""
    return {name: dict(p["parameters"]) for name, p in effect_parts(info).items()}


def realised_bias_drift(info: dict, du: int) -> float:
    """Least-squares slope over the response trials of DU ``du`` of its realised bias shift,
    command units per trial: the drift's ``k (trial - 1)`` plus each take's recorded
    ``bias_shift`` (the base face's trial jitter and the family's trial shift).

    What a drift estimate from these takes can at best recover; equal to the drift's k up to the
    random shifts (exactly k for a face without trial variation and noise-free takes).
    """
    k = effect_parameters(info).get("drift", {}).get("beta_per_trial", 0.0)
    takes = [t for t in info["takes"] if t.get("kind") == "response" and t.get("du") == du]
    if len(takes) < 2:
        raise ValueError(f"truth.json: DU {du} has {len(takes)} response trials; a drift needs 2")
    trial = np.array([t["trial"] for t in takes], float)
    shift = np.array([t.get("bias_shift", {}).get(str(du), 0.0) for t in takes], float)
    bias = k * (trial - 1.0) + shift
    return float(np.polyfit(trial, bias, 1)[0])


def realised_session_drift(info: dict) -> float:
    """The drift trend the session's takes hold, command units per trial: the least-squares
    slope over the trial number of every take's realised bias per DU (the drift's
    ``k (trial - 1)`` plus the take's recorded ``bias_shift``), one intercept per DU, over every
    take that moves a DU (a take without a trial is played as trial 1).

    A drift is a process parameter k; a session of 3 trials holds k plus the slope of its random
    trial shifts (a trial shift of SD s moves one DU's slope by about s / sqrt(2)), and the
    takes outside the trapezoid's trials anchor trial 1. This is what an estimator of the trend
    can at best recover from the takes; it is computed from the truth's own shifts.
    """
    k = effect_parameters(info).get("drift", {}).get("beta_per_trial", 0.0)
    trial, du, bias = [], [], []
    for t in info["takes"]:
        for d, s in (t.get("bias_shift") or {}).items():
            n = int(t.get("trial") or 1)
            trial.append(n)
            du.append(int(d))
            bias.append(k * (n - 1.0) + float(s))
    tr, du, v = np.asarray(trial, float), np.asarray(du), np.asarray(bias, float)
    if np.unique(tr).size < 2:
        raise ValueError(f"truth.json: the takes span {np.unique(tr).size} trial; a drift needs 2")
    A = np.column_stack([tr] + [(du == d).astype(float) for d in np.unique(du)])
    return float(np.linalg.lstsq(A, v, rcond=None)[0][0])


def realised_coupling_kappa(info: dict) -> float:
    """The coupling's kappa as the takes show it: the loss of travel along each marker's path
    while another DU is at full command (``coupling_travel_kappa``, written by the simulator from
    its own paths: :meth:`mocap.simulate.face.VirtualFace.travel_kappa`); the law's kappa where the
    truth predates it. Equal to the law's kappa on straight and bowed paths."""
    if "coupling_travel_kappa" in info:
        return float(info["coupling_travel_kappa"])
    return float(effect_parameters(info)["coupling"]["kappa"])
