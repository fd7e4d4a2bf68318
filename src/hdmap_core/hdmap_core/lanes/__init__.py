"""Lanes derived from the road-feature graph: strips between adjacent boundaries, cut into lanelets."""
