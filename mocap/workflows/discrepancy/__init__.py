"""The discrepancy workflow's inputs (a session or a run's output folder) and its written results."""
