"""The core layer: session types, the manifest and its readers, command schedules, atomic writes
and output paths. Imports nothing else of the package."""
