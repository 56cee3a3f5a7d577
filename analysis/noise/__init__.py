"""Noise-corrected estimates of the paper's indices: what its recipe gives on noise-free positions."""
