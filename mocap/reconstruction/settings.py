"""Settings of the reconstruction stages (mm, px, s), one frozen dataclass per stage.

Each field documents itself (``metadata["help"]``); :mod:`mocap.workflows.run.settings` gathers them into
a run's settings. Kept apart from the algorithms so that settings (and cache keys) load without
the compiled kernels.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class ReconstructionSettings:
    """Knobs of the correspondence search (px, mm).

    ``min_cameras``: the fewest cameras a sample needs to enter the analyses (trial averages,
    noise floor, properties; :mod:`mocap.reconstruction.camera_count`). The reconstruction itself
    always keeps 2-view points (their ``n_cameras`` says so).
    """

    min_cameras: int = field(default=3, metadata={
        "help": "cameras a sample needs to enter the analyses (3 as the paper; 2 is the minimum); "
                "points two cameras see are always in the trajectories"})
    gate_min_px: float = field(default=0.75, metadata={
        "help": "smallest epipolar and reprojection gate of a camera (px)"})
    gate_sigmas: float = field(default=6.0, metadata={
        "help": "a camera's gate in units of its calibration reprojection RMS"})
    max_depth_mm: float = field(default=5000.0, metadata={
        "help": "points farther than this from a camera are rejected (mm)"})


@dataclass(frozen=True)
class LabelSettings:
    """Marker identities and tracking (mocap.reconstruction.labeling)."""

    link_gate_mm: float = field(default=2.0, metadata={
        "help": "largest motion of a marker from one frame to the next (mm)"})
    max_gap_frames: int = field(default=6, metadata={
        "help": "tracklets are joined across gaps of up to this many frames"})
    start_gate_mm: float = field(default=3.0, metadata={
        "help": "a new tracklet takes a marker within this distance of its last position (mm)"})
    min_presence: float = field(default=0.5, metadata={
        "help": "a marker is present in at least this share of the rest take's frames"})
    template_gate_mm: float = field(default=6.0, metadata={
        "help": "a marker takes a markers.csv name within this distance (mm)"})


@dataclass(frozen=True)
class RejectionSettings:
    """Markers and trajectories left out (mocap.reconstruction.trials)."""

    min_displacement_mm: float = field(default=0.05, metadata={
        "help": "a marker moving less than this for a DU is left out of its analysis (mm)"})
    smooth_s: float = field(default=0.25, metadata={
        "help": "centred window over which the peak displacement is taken (s)"})
    spread_k: float = field(default=5.0, metadata={
        "help": "abnormal across-trial spread: above the median + this many scaled MADs"})
    spread_ratio: float = field(default=2.0, metadata={
        "help": "... and above this many times the median spread"})
    max_gap_fraction: float = field(default=0.05, metadata={
        "help": "a marker missing from more than this share of response frames is left out"})
