"""Live mapping by tiles: which tiles a drive touches, mapping and stitching them."""
