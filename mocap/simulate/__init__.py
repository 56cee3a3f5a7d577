"""The virtual face and camera rig: sessions with known truth and hidden effects.

``simulate(preset("small", seed=1), "out/")`` writes ``out/session`` (FORMAT.md) and
``out/truth`` (never read by the pipeline). See ``face`` (the true face), ``effects`` (hidden
effects and their equations), ``rig`` (cameras, wand, ground square), ``capture`` (blobs).
"""

from mocap.simulate.config import PRESETS, SimConfig, preset
from mocap.simulate.effects import EFFECTS, HiddenEffect
from mocap.simulate.session_writer import simulate

__all__ = ["PRESETS", "SimConfig", "preset", "EFFECTS", "HiddenEffect", "simulate"]
