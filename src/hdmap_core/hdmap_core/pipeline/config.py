"""The configuration of the whole method: one typed, frozen dataclass per stage.

``PipelineConfig()`` IS the recommended method (the "default" preset), and so is every stage
class's own default (``SamplingConfig()``, ``StitchConfig()``, ...): the stage settings measured
and adopted (docs/pipeline.md). The presets ``paper`` and ``naive``
(``hdmap_core.pipeline.presets``) list only where they differ from it; ``config_from``
(``hdmap_core.pipeline.overrides``) applies ``--set KEY=VALUE`` changes to any of them.

Two passes (Sec. IV plus ``hdmap_core.pipeline.adjustment``): with ``final_pass`` set, a first pass
collects per-step observations, one global adjustment estimates every drive's offset curve from
them, and the final pass samples and aligns again with the samples shifted by that curve: the
first pass's settings without offset estimation and with the final pass's own rules
(``FinalSampling``, ``FinalAlignment``). ``final_pass=None``: one pass, no adjustment.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import ClassVar

from hdmap_core.checks import check_range
from hdmap_core.errors import ConfigError
from hdmap_core.graph.connection_config import ConnectionConfig
from hdmap_core.graph.stitch_config import StitchConfig
from hdmap_core.pipeline.adjustment import AdjustConfig
from hdmap_core.pipeline.aggregation import AggregationConfig
from hdmap_core.pipeline.alignment import AlignmentConfig
from hdmap_core.pipeline.evidence import EvidenceConfig
from hdmap_core.pipeline.preprocess import PreprocessConfig
from hdmap_core.pipeline.sampling import SamplingConfig
from hdmap_core.plausibility import PhysicalBounds

__all__ = ["FinalAlignment", "FinalSampling", "PassConfig", "PipelineConfig"]


@dataclass(frozen=True)
class FinalSampling(SamplingConfig):
    """The final pass's sampling: the first pass's fields, and its own rule below."""

    #: a side without a first border keeps its samples up to a border only one drive saw when
    #: nothing lies beyond it ("Far borders one drive saw"; the first pass, whose steps feed the
    #: adjustment, keeps the paper's rule)
    outer_border_reach: ClassVar[bool] = True


@dataclass(frozen=True)
class FinalAlignment(AlignmentConfig):
    """The final pass's EM: the first pass's fields (without offset estimation, see
    ``PassConfig.alignment``), and its own sparse-step rules below (docs/pipeline.md, sparse
    fleets): its samples are corrected already, so sparse steps are judged more leniently."""

    #: a sparse step of singletons and one shared cluster is accepted when tight
    sparse_singletons_accept: ClassVar[bool] = True
    #: type-clashing singletons dropped only in steps of <= 3 drives (with 4, such a singleton
    #: beside another drive's line of the other type can be a real line)
    sparse_type_clash_max_drives: ClassVar[int] = 3
    #: two drives that share no line but contradict none (their lines 2+ m apart) are accepted
    #: as one drive alone would be [m]
    sparse_disjoint_apart_m: ClassVar[float] = 2.0
    #: drives that place a line at one spot but disagree on solid/dashed saw a line: kept, of
    #: unknown type ("Type clashes kept")
    sparse_type_clash_keep: ClassVar[bool] = True


@dataclass(frozen=True)
class PassConfig:
    """Where the final pass samples and aligns unlike the first.

    The final pass keeps the offsets of the adjustment: its EM estimates none (no M-step, no prior,
    gap clustering of the shifted samples). Everything else is the first pass's ``sampling`` /
    ``alignment`` with this field instead and the final pass's own rules (``FinalSampling``,
    ``FinalAlignment``; the first pass, whose steps feed the adjustment, keeps its own).

    Attributes:
        sparse_step_max_drives: ``AlignmentConfig.sparse_step_max_drives`` of the final pass:
            steps of up to this many drives are judged by the sparse-step rules.
    """

    sparse_step_max_drives: int = 4

    def __post_init__(self) -> None:
        check_range(self, ("sparse_step_max_drives",), low=0, integer=True)

    def sampling(self, first: SamplingConfig) -> FinalSampling:
        """The final pass's sampling: ``first`` (the first pass's) with this pass's rules."""
        return FinalSampling(**{f.name: getattr(first, f.name) for f in fields(first)})

    def alignment(self, first: AlignmentConfig) -> FinalAlignment:
        """The final pass's EM: ``first`` without offset estimation, with this pass's rules."""
        kept = {f.name: getattr(first, f.name) for f in fields(first)}
        return FinalAlignment(
            **{
                **kept,
                # RULE: the final pass keeps the adjustment's offsets (its samples are shifted by them)
                "estimate_offsets": False,
                "clustering": "gap",
                "prior_weight": 0.0,
                "sparse_step_max_drives": self.sparse_step_max_drives,
            }
        )


@dataclass(frozen=True)
class PipelineConfig:
    """All options of the method; the defaults are the recommended method ("default").

    Attributes:
        preprocess, sampling, alignment, aggregation: stages 1-4 (of the first pass; the final
            pass aggregates with the same ``aggregation``).
        adjustment: the global joint per-drive offset adjustment between the passes
            (``hdmap_core.pipeline.adjustment``); used only with ``final_pass``.
        final_pass: where the final pass (after the adjustment) samples and aligns unlike the
            first (``PassConfig``; its configs: ``final_sampling``, ``final_alignment``); None:
            one pass, no adjustment.
        observation_stride: with ``final_pass``, the first pass (it only feeds the adjustment,
            whose knots lie 200 m apart) runs the EM at every this-th step; 1 = every step.
        connection: Sec. V (``hdmap_core.graph.connection``).
        stitching: Sec. VI (``hdmap_core.graph.map_graph``).
        mark_on_cut_only: a drive's stretch is stored as processed at an accepted step only when
            the drive itself was on the step's refined cut. False (the paper's reading): every
            drive whose samples took part is marked, so a ramp beside the ego road never becomes
            a pivot there. The observation pass of two passes counts a drive up to
            ``sampling.max_pivot_outside_m`` beyond the cut as on it (a badly localised drive
            between two roads would sample the place again as a pivot).
        evidence: negative evidence per step of the returned pass (``StepResult.empty_m``; the
            stitcher drops fills through empty places with ``stitching.fill_evidence``).
            None: no profiles.
        plausibility: the physical bounds a drive must keep to be used at all
            (``hdmap_core.plausibility``); a drive outside them is rejected with a named reason.
        name: the preset this config came from, with "+" when changed by overrides.
    """

    preprocess: PreprocessConfig = PreprocessConfig()
    sampling: SamplingConfig = SamplingConfig()
    alignment: AlignmentConfig = AlignmentConfig()
    aggregation: AggregationConfig = AggregationConfig()
    adjustment: AdjustConfig = AdjustConfig()
    final_pass: PassConfig | None = PassConfig()
    observation_stride: int = 2
    connection: ConnectionConfig = ConnectionConfig()
    stitching: StitchConfig = StitchConfig()
    mark_on_cut_only: bool = True
    evidence: EvidenceConfig | None = EvidenceConfig()
    plausibility: PhysicalBounds = PhysicalBounds()
    name: str = "default"

    def __post_init__(self) -> None:
        check_range(self, ("observation_stride",), low=1, integer=True)
        # The stitcher's fill test reads the profiles ``evidence`` makes; without them it would
        # silently test nothing.
        if self.stitching.fill_evidence and self.evidence is None:
            raise ConfigError(
                "PipelineConfig.stitching.fill_evidence needs the negative-evidence profiles of "
                "PipelineConfig.evidence, which is None: set both (or neither: stitching.fill_evidence=false)"
            )

    @property
    def final_sampling(self) -> SamplingConfig:
        """The final pass's sampling (``sampling`` when there is no final pass)."""
        return self.sampling if self.final_pass is None else self.final_pass.sampling(self.sampling)

    @property
    def final_alignment(self) -> AlignmentConfig:
        """The final pass's EM (``alignment`` when there is no final pass)."""
        return self.alignment if self.final_pass is None else self.final_pass.alignment(self.alignment)

    @property
    def use_global_adjustment(self) -> bool:
        """Whether the adjustment and a final pass follow the first pass (``final_pass`` set)."""
        return self.final_pass is not None
