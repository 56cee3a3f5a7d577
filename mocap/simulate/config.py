"""Settings of a virtual capture session, and the presets."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from mocap.simulate.capture import CaptureNoise
from mocap.simulate.dus import DU_TABLE
from mocap.simulate.effects import HiddenEffect
from mocap.simulate.families import FAMILY_NAMES

PLANS = ("A", "B", "C", "D", "E")


@dataclass(frozen=True)
class SimConfig:
    """Everything that shapes a virtual session; deterministic for a given ``seed``.

    Attributes (units: s, px, mm)
    ----------
    du_ids : the face's DUs.  n_markers : markers on the half-face.  n_trials : response trials.
    noise : detection imperfections of every camera.
    degrade_camera / degraded : one camera with worse detections (audit tests).
    face_family : the base face's family (``mocap.simulate.families``): ``pi`` (default: PI
        hysteresis, straight paths), one of ``FAMILIES`` (``HYSTERESIS-PATH``) or ``random`` (one
        of ``FAMILIES`` drawn from ``seed``, recorded in the truth only).
    effect : the hidden effect applied to the true face.
    labeled : write labeled 3D takes (no cameras) instead of 2D blobs.
    take_format : "csv" or "parquet" for the take files.
    wand_duration_s, wand_gap_s : wand take length and seconds in its middle with the wand out of
        view.  wand_sparse_camera, wand_sparse_fraction : a camera that sees the wand only in that
        fraction of frames.
    wand_offsets_mm : the wand's marker offsets, mm (2 markers: an easyWand/Argus rod, ends alike).
    ground : record a ground square take and write [ground]; without it the session's world
        frame is the first camera's.
    motion_plans, motion_dus : designed motions (the paper's smile on DUs 1, 7, 12).
    battery : add the identification battery (fast/slow trapezoids, minor loops, DU pairs) as
        motion takes.  extra_commands : command files to play as extra motion takes.
    """

    preset: str = "small"
    seed: int = 0
    du_ids: tuple[int, ...] = (1, 4, 7, 12)
    n_markers: int = 40
    n_trials: int = 3
    n_cameras: int = 6
    fps: float = 120.0
    width: int = 1280
    height: int = 1024
    noise: CaptureNoise = CaptureNoise()
    degrade_camera: str | None = None
    degraded: CaptureNoise = CaptureNoise(noise_px=0.5, dropout=0.3, ghost_rate=0.2)
    face_family: str = "pi"
    effect: HiddenEffect = HiddenEffect()
    labeled: bool = False
    labeled_noise_mm: float = 0.02
    take_format: str = "csv"
    wand_duration_s: float = 30.0
    wand_gap_s: float = 0.0
    wand_sparse_camera: str | None = None
    wand_sparse_fraction: float = 0.2
    rest_s: float = 2.0
    ground_s: float = 1.0
    motion_plans: tuple[str, ...] = PLANS
    motion_dus: tuple[int, ...] = (1, 7, 12)
    battery: bool = True
    extra_commands: tuple[Path, ...] = field(default_factory=tuple)
    nose_bridge_cameras: int = 3
    nose_bridge_jitter_mm: float = 0.15
    wand_offsets_mm: tuple[float, ...] = (0.0, 50.0, 150.0)
    ground: bool = True

    def __post_init__(self) -> None:
        known = {d.id for d in DU_TABLE}
        bad = [d for d in self.du_ids if d not in known]
        if bad or not self.du_ids:
            raise ValueError(f"simulate: expected DU ids from {sorted(known)}, got {list(self.du_ids)}")
        if self.n_trials < 1:
            raise ValueError(f"simulate: expected at least 1 trial, got {self.n_trials}")
        if self.take_format not in ("csv", "parquet"):
            raise ValueError(f"simulate: expected take format csv or parquet, got {self.take_format!r}")
        if self.fps <= 0:
            raise ValueError(f"simulate: expected fps > 0, got {self.fps}")
        if self.n_cameras < 2:
            raise ValueError(f"simulate: expected at least 2 cameras, got {self.n_cameras}")
        if self.face_family not in FAMILY_NAMES:
            raise ValueError(f"simulate: expected a face family among {', '.join(FAMILY_NAMES)}, "
                             f"got {self.face_family!r}")
        if not (self.labeled_noise_mm >= 0):
            raise ValueError(f"simulate: expected labeled_noise_mm >= 0, got {self.labeled_noise_mm}")
        if len(self.wand_offsets_mm) < 2:
            raise ValueError(f"simulate: expected 2 or more wand offsets, got {list(self.wand_offsets_mm)}")
        if self.wand_duration_s <= self.wand_gap_s:
            raise ValueError("simulate: the wand gap must be shorter than the wand take")


PRESETS: dict[str, dict] = {
    # seconds to make, a few MB: the test bed
    "small": dict(du_ids=(1, 4, 7, 12), n_markers=40, n_trials=3, take_format="parquet"),
    # the committed sample session: as small without the battery, three plans (fits in 20 MB)
    "sample": dict(du_ids=(1, 4, 7, 12), n_markers=32, n_trials=3, take_format="parquet",
                   motion_plans=("A", "C", "E"), battery=False),
    # the paper's full study: 16 DUs, 10 trials, 116 markers, Parquet takes
    "paper": dict(du_ids=tuple(d.id for d in DU_TABLE), n_markers=116, n_trials=10,
                  take_format="parquet"),
}


def preset(name: str, **overrides) -> SimConfig:
    """The named preset's SimConfig, with keyword overrides."""
    if name not in PRESETS:
        raise ValueError(f"simulate: expected a preset among {sorted(PRESETS)}, got {name!r}")
    kwargs = dict(PRESETS[name])
    kwargs.update({k: v for k, v in overrides.items() if v is not None})
    return SimConfig(preset=name, **kwargs)


def replace(cfg: SimConfig, **changes) -> SimConfig:
    return dataclasses.replace(cfg, **changes)
