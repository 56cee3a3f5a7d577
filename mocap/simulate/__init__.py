"""The virtual face and camera rig: sessions with known truth and hidden effects.

``simulate(preset("small", seed=1), "out/")`` writes ``out/session`` (FORMAT.md) and
``out/truth`` (never read by the pipeline). See ``face`` (the true face), ``families`` (base-face
families: hysteresis operators and marker paths the analysis model does not share),
``hysteresis_ops`` (the operators), ``effects`` (hidden effects and their equations), ``rig``
(cameras, wand, ground square), ``capture`` (blobs).

A cross-family sweep::

    from mocap.simulate import FAMILIES, make_effect, preset, simulate
    for fam in FAMILIES:
        simulate(preset("small", seed=s, face_family=fam, effect=make_effect("lag"),
                        labeled=True, labeled_noise_mm=0.03), out / fam)
"""

from mocap.simulate.config import PRESETS, SimConfig, preset
from mocap.simulate.effects import EFFECTS, HiddenEffect, make_effect
from mocap.simulate.families import FAMILIES, FAMILY_NAMES
from mocap.simulate.session_writer import simulate

__all__ = ["PRESETS", "SimConfig", "preset", "EFFECTS", "HiddenEffect", "make_effect",
           "FAMILIES", "FAMILY_NAMES", "simulate"]
