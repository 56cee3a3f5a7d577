"""Workflows: the stages joined into what a command does (run, audit, batch, discrepancy, design).
They compose the layers below and return results; writing figures and recordings is the outputs
layer's job."""
