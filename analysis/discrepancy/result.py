"""What the discrepancy workflow returns: a :class:`Step` per effect it names (parameters in
the effect's reported units, held-out RMS in mm) and the session's :class:`DiscrepancyResult`."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mocap.analysis.model.face_model import FaceModel


@dataclass
class Step:
    """One named effect: parameters (all takes), uncertainty, held-out gap before/after."""

    effect: str
    parameters: dict
    uncertainty: dict
    heldout_rms_before_mm: float
    heldout_rms_after_mm: float
    evidence: list[dict]
    explained: float
    per_du: dict = field(default_factory=dict)  # DU id -> the parameter from its own takes
    named: bool = True  # False: kept in the model, but an alternative explains it as well
    form: str | None = None  # the effect's form, where it has several (backlash: play, stick-slip)
    interval: dict = field(default_factory=dict)  # parameter -> [lo, hi] that fit equally well
    interval_note: str = ""  # what the interval is, where not the values that fit alike
    meaning: str = ""  # what the effect is, in the form it was named in
    reading: str = ""  # how the parameter was read from the data, where not from the fit


@dataclass
class DiscrepancyResult:
    """What the workflow found (see
    :func:`~mocap.analysis.discrepancy.workflow.run_discrepancy`)."""

    named: list[str]
    steps: list[Step]
    noise_floor_mm: float
    noise_source: str
    base_effects: tuple[str, ...]
    untestable: dict[str, str]
    stages: list[dict]  # per stage (base, then after each step): held-out diagnostics
    final_model: FaceModel
    final_evidence: list[dict]
    excluded_markers: list[str]
    heldout_residuals: list[list[np.ndarray]]  # per stage, per take (S, M, 3)
    models_by_stage: list[FaceModel]
    base_report: dict = field(default_factory=dict)  # what the base model holds (path, loop, shifts)
    alternatives: list[dict] = field(default_factory=list)  # explanations the data cannot tell apart

    @property
    def final_heldout_rms_mm(self) -> float:
        return self.stages[-1]["heldout_rms_mm"]
