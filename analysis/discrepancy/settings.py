"""Settings of the discrepancy workflow (:mod:`mocap.analysis.discrepancy.workflow`): the base
model's effects, the candidates tried, and the thresholds that name an effect (held-out BIC
units, fractions of the noise floor in mm, command units)."""

from __future__ import annotations

from dataclasses import dataclass

from mocap.analysis.model.effects import BASE, CANDIDATES


@dataclass(frozen=True)
class DiscrepancySettings:
    """Settings of the workflow (defaults as documented in
    :mod:`mocap.analysis.discrepancy.workflow`).

    base : the starting model's effects: by default what every face has (a PI hysteresis density,
        each marker's own path, per-trial bias shifts); ``("hysteresis",)`` is the paper's model
        with straight paths, ``()`` a static model without hysteresis.
    candidates : effect names to try (default: the missing effects of the catalogue; base
        effects are never candidates).
    margin : held-out BIC units a candidate must gain.  min_explained : fraction of the held-out
        excess over the noise floor it must explain.  min_rms_gain : the held-out RMS it must
        remove, as a fraction of the noise floor (a gain nobody could see in the data is not an
        effect, however significant statistically).  beyond_noise : ratio to the noise floor above
        which a residual is reported as a disagreement.
    active_mm : a DU moves a marker when the marker's 95th-percentile displacement in that DU's
        single-DU takes exceeds this (0: every scored marker is modelled for every DU; leaving
        out markers that move a little leaves their motion in the residual).
    stride : frames between the samples used (3 = 40 Hz at 120 fps), at least; coarser when a
        DU's single-DU takes hold more than ``max_samples_per_du`` samples.
    strong_fraction : a curve gets its own sigmoid when the marker's 95th-percentile
        displacement reaches this fraction of the DU's largest; the others take the DU's median
        shape and only their displacement vectors are fitted.
    local, local_explained, local_gain, local_min_n : with ``local`` (on by default), another
        way to pass the explained and RMS-gain tests: where the candidate acts (the held-out
        residual vectors it moves by more than half the noise floor, at least ``local_min_n`` of
        them), it removes at least ``local_explained`` of the excess over the noise floor and
        ``local_gain`` x the noise floor from the RMS (a stick-slip dead band: on the rows where
        it holds a DU's actuator, :func:`~mocap.analysis.discrepancy.crossval.hold_gain`). An
        effect that acts in a few places (a dead band at reversals) is plain there and lost in
        the session's RMS. It is safe only against the candidate's own null
        (:func:`~mocap.analysis.discrepancy.crossval.cv_candidate`): against the base, a
        candidate's extra polish of the curves is local too. The numbers are reported in every
        candidate's evidence either way.
    max_steps : effects to add at most.
    jobs : processes over the base fits (each fold, all takes) and the candidates (spawned;
        1 runs in this process). The results do not depend on it.
    """

    base: tuple[str, ...] = BASE
    candidates: tuple[str, ...] = CANDIDATES
    margin: float = 10.0
    min_explained: float = 0.2
    min_rms_gain: float = 0.03
    beyond_noise: float = 1.5
    active_mm: float = 0.0
    stride: int = 3
    max_samples_per_du: int = 1600
    strong_fraction: float = 0.15
    local: bool = True
    local_explained: float = 0.35
    local_gain: float = 0.25
    local_min_n: int = 100
    max_steps: int = 4
    jobs: int = 1
