"""Sec. VII: the map scored against ground truth (cuts, topology, roads, links), summary and plot."""
