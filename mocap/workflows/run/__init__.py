"""`mocap run`: its settings, stages, composer, stored stage results and lock."""
