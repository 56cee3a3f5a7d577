"""Reading what a simulated session's truth says (``OUT/truth/truth.json``), for scoring.

Pure functions of the parsed ``truth.json`` dict: the sweeps read the file once and ask these.
"""

from __future__ import annotations

import numpy as np


def effect_parameters(info: dict) -> dict[str, dict[str, float]]:
    """{effect name: {parameter: value}} of the hidden effect(s) in ``info`` ({} for none)."""
    eff = info["effect"]
    parts = eff.get("effects", [eff])
    return {p["name"]: dict(p["parameters"]) for p in parts if p["name"] != "none"}


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
