"""The model-discrepancy workflow: where the model and the measurement disagree, the missing effect
named, added, and the gap shown to shrink."""
