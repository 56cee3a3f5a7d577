"""The paper's analyses (displacements, spatial linearity, sigmoid responses, motion design) and
the model-discrepancy workflow. Pure functions on numpy arrays and pandas frames; no I/O except in
the modules named for it; never imports rerun.

Index conventions (METHOD.md): n = deformation unit (DU), m = marker, t = frame.
"""
