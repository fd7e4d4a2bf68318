"""Fleets simulated on ground-truth maps: drives, sensor noise, synthetic highways."""
