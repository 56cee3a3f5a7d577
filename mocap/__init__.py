"""facemocap: facial motion capture from raw multi-camera exports to a quantitative face model.

Top-level packages
------------------
mocap     session I/O (the input contract), the virtual capture, reconstruction, the CLI.
calib     camera models and wand calibration of a camera rig.
analysis  the paper's analyses (displacements, linearity, sigmoid responses, motion design)
          and the model-discrepancy workflow.

Units everywhere: millimetres (mm), pixels (px), seconds (s), command units (integers 0..255).
"""

__version__ = "0.1.0"
