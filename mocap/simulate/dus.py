"""The virtual face's deformation units (DUs): names, actuators and nominal response.

DU names follow METHOD.md; the paper's text does not name DUs 8, 9, 10, 13 and 14, so the package
names them after common android-face actuators (nose wing raising, upper lip raising, mouth corner
pulling back, lip pursing, mouth corner lowering) and says so here.

Per DU: ``attach_mm`` is the connection point on the face (face-plane x, y, mm; x from the
midline to the right, y up from the face centre), ``direction`` the skin's pull direction there
(world axes), ``peak_mm`` the displacement at the attachment at full command, ``sigma_mm`` the
spatial decay (Gaussian), ``alpha`` (1/command unit) and ``beta`` (command units) the logistic's
nominal sensitivity and bias, ``hysteresis`` the full-sweep loop width (command units: forward
minus backward bias), ``spread_beta`` the per-marker standard deviation of the bias (command
units: what makes a DU's dyssynchrony). Feedback DUs (1, 2, 12) have alpha < 0.03; DUs 1 and 12
small hysteresis, every other DU 40 to 90 (METHOD.md, "Property chart"). The paper's indices as
measured (pooled fits of the normalised response) come out a little above the nominal alpha,
so the feedback DUs' nominal alphas sit at 0.021 to 0.023.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class DUSpec:
    id: int
    name: str
    feedback: bool
    attach_mm: tuple[float, float]
    direction: tuple[float, float, float]
    peak_mm: float
    sigma_mm: float
    alpha: float
    beta: float
    hysteresis: float
    spread_beta: float


DU_TABLE: tuple[DUSpec, ...] = (
    DUSpec(1, "upper eyelid lowering", True, (30, 27), (0, -1, 0.3), 4.0, 11, 0.022, 120, 6, 5),
    DUSpec(2, "eyeballs/eyepit turning up", True, (30, 24), (0, 1, -0.2), 2.0, 17, 0.023, 130, 48, 6),
    DUSpec(3, "lower eyelid raising", False, (30, 14), (0, 1, 0.2), 2.2, 10, 0.048, 125, 60, 8),
    DUSpec(4, "eyebrow raising", False, (32, 44), (0, 1, 0), 6.0, 22, 0.095, 135, 86, 5),
    DUSpec(5, "eyebrow centering", False, (18, 42), (-1, -0.2, 0), 3.0, 14, 0.080, 130, 72, 7),
    DUSpec(6, "middle cheek raising", False, (38, -4), (0.1, 1, 0.2), 4.0, 18, 0.055, 128, 80, 9),
    DUSpec(7, "middle cheek side-pulling", False, (46, -12), (1, 0.2, -0.3), 5.0, 20, 0.045, 122, 60, 8),
    DUSpec(8, "nose wing raising", False, (14, 2), (0.2, 1, 0), 2.0, 10, 0.060, 128, 55, 9),
    DUSpec(9, "upper lip raising", False, (14, -22), (0, 1, 0.1), 2.5, 12, 0.050, 125, 65, 10),
    DUSpec(10, "mouth corner pulling back", False, (32, -32), (1, 0, -0.5), 3.5, 15, 0.050, 130, 70, 9),
    DUSpec(11, "lower lip centering", False, (12, -42), (-1, 0, 0.2), 2.5, 14, 0.036, 128, 55, 26),
    DUSpec(12, "jaw opening", True, (18, -58), (0, -1, 0.1), 8.0, 42, 0.021, 125, 5, 6),
    DUSpec(13, "lip pursing", False, (10, -32), (-0.3, 0, 1), 2.5, 12, 0.060, 128, 60, 10),
    DUSpec(14, "mouth corner lowering", False, (31, -36), (0.2, -1, 0), 3.0, 13, 0.058, 130, 66, 9),
    DUSpec(15, "lower lip lowering", False, (12, -46), (0, -1, 0.2), 3.0, 15, 0.037, 126, 56, 24),
    DUSpec(16, "mouth corner raising", False, (32, -28), (0.5, 1, 0), 4.5, 16, 0.085, 132, 66, 6),
)

DU_BY_ID = {d.id: d for d in DU_TABLE}
