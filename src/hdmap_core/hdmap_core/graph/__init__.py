"""Sec. V-VI: steps connected into polylines per segment, segments stitched into the hierarchical map graph."""
