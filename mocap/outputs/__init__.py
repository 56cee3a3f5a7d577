"""Outputs: the figures (matplotlib), the Rerun recording and the writers that put a run's results
on disk. The only layer that imports matplotlib or rerun."""
