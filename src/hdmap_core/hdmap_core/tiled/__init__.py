"""Out-of-core builds by tiles: the per-place stages as tasks per spatial tile (``tasks``), on one
process or a Dask cluster (``cluster``), then one offset adjustment and the stitch (``build``)."""
