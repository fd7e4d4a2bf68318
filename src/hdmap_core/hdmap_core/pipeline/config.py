"""The configuration of the whole method: one typed, frozen dataclass per stage.

``PipelineConfig()`` IS the recommended method (the "default" preset): its field defaults are the
stage settings measured and adopted (docs/pipeline.md). The presets ``paper`` and ``naive``
(``hdmap_core.pipeline.presets``) list only where they differ from it; ``config_from``
(``hdmap_core.pipeline.overrides``) applies ``--set KEY=VALUE`` changes to any of them.

The stage classes' own defaults (``AlignmentConfig()``, ...) are, for stages 1-4, the paper's
reading; the recommended values of those stages are the module constants below.

Two passes (Sec. IV plus ``hdmap_core.pipeline.adjustment``): with ``final_pass`` set, a first pass
collects per-step observations, one global adjustment estimates every drive's offset curve from
them, and the final pass samples and aligns again with the samples shifted by that curve: the
first pass's settings without offset estimation and with the few fields of ``PassConfig``
instead. ``final_pass=None``: one pass, no adjustment.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

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

__all__ = [
    "PassConfig",
    "PipelineConfig",
    "RECOMMENDED_SAMPLING",
    "RECOMMENDED_ALIGNMENT",
    "RECOMMENDED_AGGREGATION",
    "RECOMMENDED_CONNECTION",
    "RECOMMENDED_STITCHING",
]

# A step whose pivot lies over 2 m beyond its smoothed cut is on no road the cut describes
# (junctions: docs/pipeline.md, "Steps off their pivot's road"); an open side (no border) ends at
# a 4 m gap in its samples; a border needs the support of 5 % of the step's drives.
RECOMMENDED_SAMPLING = SamplingConfig(min_border_support_fraction=0.05, open_side_gap_m=4.0, max_pivot_outside_m=2.0)

# The fast exact per-step EM: closed form, gap clustering once every drive has an offset carried
# along the pivot, offsets smoothed along a drive.
RECOMMENDED_ALIGNMENT = AlignmentConfig(
    clustering="auto",
    solver="closed_form",
    n_iterations=4,
    prior_weight=1.0,
    robust_loss=True,
    min_cluster_drives=1,
    # Labels are fixed in the M-step and the closed form minimises the variance; the penalty
    # would only push apart clusters of one feature split by a gap.
    penalty_lm_threshold=2.0,
    lone_cluster_max_std_m=0.3,
    # Steps of <= 3 drives: judged without the one-sample clusters (lines one drive misses), when
    # every cluster is tight; type-clashing singletons dropped.
    sparse_step_max_drives=3,
    sparse_step_max_std_m=0.3,
    sparse_type_clash_m=1.0,
)

# The adjustment's prior of one drive's lateral error (bias and drift) is the error a map point
# keeps from its drives on average (AggregationConfig.common_sigma_m).
_PRIOR = AdjustConfig()
RECOMMENDED_AGGREGATION = AggregationConfig(
    kde_bandwidth_factor=1.0,
    kde_min_bandwidth_m=0.15,
    tie_by_position=True,
    # two drives' border on a line is a border there too (docs/pipeline.md, "Borders on lines")
    border_beside_marking_drives=2,
    common_sigma_m=float(math.hypot(_PRIOR.bias_sigma_m, _PRIOR.drift_sigma_m)),
)

# Negative evidence judged where >= 2 detections are expected (3 in the class): the 30-drive
# fleets' false fills lie where 1-4 drives pass (docs/pipeline.md, "Negative evidence").
_EVIDENCE = EvidenceConfig(min_expected=2.0)

RECOMMENDED_CONNECTION = ConnectionConfig(
    # the last step's open ends are paired first, ends bridged from earlier steps take what is
    # left (docs/pipeline.md "Fresh tips first")
    fresh_first=True,
    support_window_m=4.0,
    window_min_count=1,
    # ... and a line a lane from both its neighbours, whatever its support (one drive's lane
    # beside lines many saw; docs/pipeline.md "Lone lines")
    lone_line_gap_m=3.0,
    # ... an edge line only 0.8 m from its border, and only on its outer side (docs/pipeline.md
    # "Lone edge lines")
    lone_line_border_gap_m=0.8,
    lone_line_border_outer=True,
    # a topology node reaches 0.5 m beyond its pivot (docs/pipeline.md "The pivot's own road in
    # its topology node")
    topo_pivot_lane_m=0.5,
    separation_count_ratio=0.5,
    # straight carriageway lines crossed at 12-30 deg paired in their own direction (an entry
    # ramp's pivot; docs/pipeline.md, "Lines crossed by an entering pivot")
    line_frame_deg=12.0,
    line_frame_bend_deg=5.0,
    # a step's connection angles are judged less the maxima's noise: tight loops
    # (docs/pipeline.md "Connection angles on tight curves")
    mean_angle_slack=True,
)

RECOMMENDED_STITCHING = StitchConfig(
    # junction pieces already joined to the map through one end get their other end linked too;
    # a ramp chain ending short of the gore follows its own arc onto the road (docs/graph.md)
    link_within_component=True,
    path_search_m=36.0,
    path_max_turn_deg=60.0,
    # an end follows the path its pivot drove through a junction whose steps failed, onto the
    # road it entered (docs/graph.md, "Track links") ...
    track_search_m=60.0,
    track_linked_ends=True,
    # ... but not onto a road that runs into what the end reaches anyway (docs/graph.md, "Side
    # steps"), nor across the split behind an end or the merge ahead of a start
    track_rejoin_m=30.0,
    track_rejoin_both=True,
    # ... landing where its pivot has settled onto the road (docs/graph.md)
    track_settle_deg=8.0,
    # ... and a pivot's track leaving one mapped road through failed steps onto another links the
    # two where no chain ends there (docs/graph.md, "Track bridges"), also from a road whose
    # cross-section the track's first point after a gap misses by up to 2 m
    track_bridge_m=60.0,
    track_bridge_leave_margin_m=2.0,
    # tracks are the pivot's own corrected positions, not its steps' cut midpoints
    # (docs/graph.md, "Tracks of poses")
    track_pose=True,
    # fills through stretches the drives saw empty are dropped (the profiles come from
    # ``PipelineConfig.evidence``; docs/pipeline.md, "Negative evidence")
    fill_evidence=_EVIDENCE,
    # two roads side by side join only at a shallow angle, also when their lines barely overlap
    side_link_angle_deg=30.0,
    side_link_overlap=0.5,
    # ... and never backward for the partner (docs/graph.md)
    partner_angle_deg=90.0,
    # type flicker on sparse lines: a run of >= 2 drives relabelled only as a minority, one
    # drive's misclassified stretch up to 250 m, only runs of <= 3 drives, also a one-drive run at
    # a line's end, also beyond a leftover edge (docs/pipeline.md, sparse fleets)
    sparse_minority_only=True,
    single_drive_run_m=250.0,
    sparse_drive_count=3,
    single_drive_end_run_m=250.0,
    single_drive_end_through_leftover=True,
    # loose ends also compared in their lines' frame from 3 deg off the pivot's heading, such
    # joins refused where a pivot turned through the gap (docs/pipeline.md, sparse fleets)
    join_line_heading_deg=3.0,
    join_line_cross_deg=30.0,
    # a solid end joins a dashed start (or the reverse) up to 10 m ahead (docs/pipeline.md,
    # "Loose ends of the other marking type")
    join_other_marking_m=10.0,
    # an isolated 1-2-drive border between lane lines is a misclassified marking
    # (docs/pipeline.md, "Inner borders kept as lane lines")
    inner_border_max_m=5.0,
    inner_border_max_drives=2,
    inner_border_dashed_drives=1,
    # one drive's (or a disputed) marking within 1.5 m of the border is the solid edge line
    edge_line_solid_m=1.5,
    # a loose end's stub of <= 12 m reached by a fill jumping sideways is dropped where other lines
    # map its cross-section (docs/pipeline.md, "Town04's stray pieces")
    end_stub_max_m=12.0,
)


@dataclass(frozen=True)
class PassConfig:
    """Where the final pass samples and aligns unlike the first.

    The final pass keeps the offsets of the adjustment: its EM estimates none (no M-step, no prior,
    gap clustering of the shifted samples; ``PipelineConfig.final_alignment``). Everything else is
    the first pass's ``sampling`` / ``alignment`` with these fields instead (docs/pipeline.md,
    sparse fleets; the first pass, whose steps feed the adjustment, keeps its own rules).

    Attributes:
        outer_border_reach: ``SamplingConfig.outer_border_reach`` of the final pass: a side
            without a first border keeps its samples up to a border only one drive saw when
            nothing lies beyond it ("Far borders one drive saw").
        sparse_step_max_drives: ``AlignmentConfig.sparse_step_max_drives`` of the final pass:
            steps of up to 4 drives are judged by the sparse-step rule.
        sparse_singletons_accept: ``AlignmentConfig.sparse_singletons_accept``: a sparse step of
            singletons and one shared cluster is accepted when tight.
        sparse_type_clash_max_drives: ``AlignmentConfig.sparse_type_clash_max_drives``:
            type-clashing singletons dropped only in steps of <= 3 drives.
        sparse_disjoint_apart_m: ``AlignmentConfig.sparse_disjoint_apart_m``: two drives that
            share no line but contradict none (their lines 2+ m apart) are accepted as one drive
            alone would be [m].
        sparse_type_clash_keep: ``AlignmentConfig.sparse_type_clash_keep``: drives that place a
            line at one spot but disagree on solid/dashed saw a line: kept, of unknown type
            ("Type clashes kept").
    """

    outer_border_reach: bool = True
    sparse_step_max_drives: int = 4
    sparse_singletons_accept: bool = True
    sparse_type_clash_max_drives: int = 3
    sparse_disjoint_apart_m: float = 2.0
    sparse_type_clash_keep: bool = True

    def __post_init__(self) -> None:
        check_range(self, ("sparse_step_max_drives", "sparse_type_clash_max_drives"), low=0, integer=True)
        check_range(self, ("sparse_disjoint_apart_m",), low=0.0, finite=True)

    def sampling(self, first: SamplingConfig) -> SamplingConfig:
        """The final pass's sampling: ``first`` (the first pass's) with this pass's fields."""
        return replace(first, outer_border_reach=self.outer_border_reach)

    def alignment(self, first: AlignmentConfig) -> AlignmentConfig:
        """The final pass's EM: ``first`` without offset estimation, with this pass's fields."""
        return replace(
            first,
            # RULE: the final pass keeps the adjustment's offsets (its samples are shifted by them)
            estimate_offsets=False,
            clustering="gap",
            prior_weight=0.0,
            sparse_step_max_drives=self.sparse_step_max_drives,
            sparse_singletons_accept=self.sparse_singletons_accept,
            sparse_type_clash_max_drives=self.sparse_type_clash_max_drives,
            sparse_disjoint_apart_m=self.sparse_disjoint_apart_m,
            sparse_type_clash_keep=self.sparse_type_clash_keep,
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
            a pivot there.
        evidence: negative evidence per step of the returned pass (``StepResult.empty_m``; the
            stitcher drops fills through empty places when ``stitching.fill_evidence`` is set).
            None: no profiles.
        name: the preset this config came from, with "+" when changed by overrides.
    """

    preprocess: PreprocessConfig = PreprocessConfig()
    sampling: SamplingConfig = RECOMMENDED_SAMPLING
    alignment: AlignmentConfig = RECOMMENDED_ALIGNMENT
    aggregation: AggregationConfig = RECOMMENDED_AGGREGATION
    adjustment: AdjustConfig = _PRIOR
    final_pass: PassConfig | None = PassConfig()
    observation_stride: int = 2
    connection: ConnectionConfig = RECOMMENDED_CONNECTION
    stitching: StitchConfig = RECOMMENDED_STITCHING
    mark_on_cut_only: bool = True
    evidence: EvidenceConfig | None = _EVIDENCE
    name: str = "default"

    def __post_init__(self) -> None:
        check_range(self, ("observation_stride",), low=1, integer=True)
        # The stitcher's fill test reads the profiles ``evidence`` makes; without them it would
        # silently test nothing.
        if self.stitching.fill_evidence is not None and self.evidence is None:
            raise ConfigError(
                "PipelineConfig.stitching.fill_evidence needs the negative-evidence profiles of "
                "PipelineConfig.evidence, which is None: set both (or neither)"
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
