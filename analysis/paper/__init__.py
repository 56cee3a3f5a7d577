"""The paper's analyses, literally: displacements, spatial linearity, the forward and backward
sigmoids and the static-response indices (sensitivity, hysteresis, dyssynchrony)."""
