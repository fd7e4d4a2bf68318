"""The method of Immel et al. 2023, Sec. III-IV: preprocessing, sampling, alignment, aggregation,
the network-wide offset adjustment, and the driver that runs them (build_map)."""
