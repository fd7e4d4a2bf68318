"""Named configurations: each lists only where it differs from ``PipelineConfig()``.

- ``default()``: the recommended method, ``PipelineConfig()`` itself.
- ``paper()``: the method as the paper writes it (Immel et al. 2023), its open values read as in
  docs/pipeline.md: one pass, no adjustment, the stage classes' own (paper) settings for stages
  1-4, and for stages 5-6 every leftover joined and same-type unmodified assignment across
  segments, with none of our clean-up.
- ``naive()``: the baseline without any offset correction: cluster means of the raw samples. It
  is not "the default minus the correction": its stages 1-3 are the paper's (the stage classes'
  defaults) and its stages 5-6 are the graph classes' own defaults, exactly as listed below.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

from hdmap_core.errors import ConfigError
from hdmap_core.graph.connection_config import ConnectionConfig
from hdmap_core.graph.stitch_config import StitchConfig
from hdmap_core.pipeline.aggregation import AggregationConfig
from hdmap_core.pipeline.alignment import AlignmentConfig
from hdmap_core.pipeline.config import PipelineConfig
from hdmap_core.pipeline.sampling import SamplingConfig

__all__ = ["PRESETS", "default", "naive", "paper", "preset"]


def default() -> PipelineConfig:
    """The recommended method: ``PipelineConfig()``."""
    return PipelineConfig()


def paper() -> PipelineConfig:
    """The paper's method: one pass, the stage classes' paper settings, the paper's Sec. V-VI."""
    return PipelineConfig(
        sampling=SamplingConfig(),
        alignment=AlignmentConfig(),
        aggregation=AggregationConfig(),
        final_pass=None,
        observation_stride=1,
        connection=ConnectionConfig.paper(),
        stitching=StitchConfig.paper(),
        mark_on_cut_only=False,
        evidence=None,
        name="paper",
    )


def naive() -> PipelineConfig:
    """No offset correction: the paper's sampling, no M-step, no silhouette gate, plain cluster
    means without the overlap filter, and the graph classes' own defaults (not the paper's
    Sec. V-VI, not the recommended ones)."""
    return replace(
        paper(),
        alignment=AlignmentConfig(estimate_offsets=False, silhouette_gate=-1.0),
        aggregation=AggregationConfig(method="mean", overlap_filter=False),
        connection=ConnectionConfig(),
        stitching=StitchConfig(),
        name="naive",
    )


#: The presets by name (``--preset``), each a function returning a fresh config.
PRESETS: dict[str, Callable[[], PipelineConfig]] = {"default": default, "paper": paper, "naive": naive}


def preset(name: str) -> PipelineConfig:
    """The named preset ("default", "paper" or "naive").

    Raises:
        ConfigError: an unknown name.
    """
    try:
        return PRESETS[name]()
    except KeyError:
        raise ConfigError(f"unknown pipeline preset {name!r}; choose one of {tuple(PRESETS)}") from None
