"""The face model: every marker's position for any command series, its effects and their fits."""
