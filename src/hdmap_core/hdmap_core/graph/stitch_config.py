"""Parameters of the inter-segment connection (``stitching.py``, Sec. VI of Immel et al. 2023).

``StitchConfig()`` is the recommended stitcher. Its public fields are the search radii and the
three switches the presets flip; every other rule is a fixed :class:`~hdmap_core.checks.Rule` (or
constant) of the class, its value below with what it does (docs/graph.md, docs/pipeline.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from hdmap_core.checks import Rule, check_range

__all__ = ["StitchConfig"]


@dataclass(frozen=True)
class StitchConfig:
    """Parameters of the inter-segment connection (the paper gives no numbers).

    Attributes:
        max_distance_m: kd-tree search radius for a component end's neighbour [m].
        max_heading_diff_deg: the two topology nodes' headings differ at most this much [deg].
        max_connection_angle_deg: the link from one node to the other deviates at most this much
            from the driving direction (checked for links longer than ``links._ANGLE_FREE_M``) [deg].
        join_radius_m: how far ahead of a loose end a loose start may begin [m].
        fill_spacing_m: a polyline edge longer than 1.5 x this (a bridged gap or join) is filled
            with points on a cubic Hermite curve through the end tangents, this far apart; the
            filled points carry drive_count 0 (no drive saw them). 0 disables (the paper) [m].
        min_isolated_length_m: polylines without any link and shorter than this are dropped
            (single-step specks, false positives). 0 disables (the paper) [m].
        cleanup: the clean-up rules of the first implementation (its fixed ``cleanup`` rules:
            overlap trimming, loose-end joins, type runs, spurs, bubbles, gores, lines through
            splits). False: the paper's topology links and same-type assignment only.
        refined: the rules measured and adopted on the simulated and CARLA fleets since (its
            fixed ``refined`` rules: sparse type runs, inner borders, edge lines, end stubs,
            path search and link angle limits). False: the paper (and ``naive``).
        track_links: component ends follow the path their pivot drove (``SegmentGraph.track_xy``
            or its poses) through a junction whose steps failed, and link where it lands
            (docs/graph.md, "Track links", "Track bridges", "Side steps"). False: the paper.
        fill_evidence: at export, a feature edge long enough to be filled is dropped when most of
            it runs where the drives that passed saw nothing (``hdmap_core.pipeline.evidence``,
            from the segments' ``StepResult.empty_m``, made by ``PipelineConfig.evidence``): its
            ends stay loose ends. False: off (the paper).
    """

    max_distance_m: float = 12.0
    max_heading_diff_deg: float = 30.0
    max_connection_angle_deg: float = 80.0
    join_radius_m: float = 60.0
    fill_spacing_m: float = 2.0
    min_isolated_length_m: float = 20.0
    cleanup: bool = True
    refined: bool = True
    track_links: bool = True
    fill_evidence: bool = True

    # Fixed in every preset.
    #: join features of the same type only (a solid-dashed join measured no gain)
    same_type_only: ClassVar[bool] = True
    #: assignment cost added to a solid-dashed pair [m]
    type_mismatch_cost_m: ClassVar[float] = 0.3
    #: an overlap trims the shorter piece (in topology nodes), not always the new graph
    trim_keep_longer: ClassVar[bool] = True
    #: a node does not give way to a new node that will itself give way to a third graph's node
    trim_lookahead: ClassVar[bool] = True
    #: a node of another pivot up to this far away may overlap one (cut midpoints differ) [m]
    overlap_search_m: ClassVar[float] = 8.0
    #: loose ends of one segment (split by a gap longer than ``max_gap_m``) are joined too
    join_same_segment: ClassVar[bool] = True
    #: a loose start up to this far behind a loose end is joined, the overlap dropped [m]
    join_overlap_m: ClassVar[float] = 8.0
    #: an unjoined loose start joining another polyline this far across (a split); 0: off [m]
    branch_lateral_m: ClassVar[float] = 0.0
    #: lateral reach of the join gap check (``join_gap_check_m``) [m]
    join_gap_lateral_m: ClassVar[float] = 12.0
    #: an end stub is dropped only where other lines lie within this across (0: always) [m]
    end_stub_cover_m: ClassVar[float] = 8.0

    # With ``cleanup`` (the paper: off).
    #: drop component end nodes that lie on a place already in the map
    trim_overlap = Rule("cleanup", True, False)
    #: drop dangling ends/starts running on top of another segment's polyline of the same class
    dedupe_loose_ends = Rule("cleanup", True, False)
    #: join loose ends and starts of different segments that continue each other
    join_loose_ends = Rule("cleanup", True, False)
    #: a loose end is compared by its own line's direction from this far back, when it differs [m]
    join_line_heading_m = Rule("cleanup", 4.0, 0.0)
    #: a loose-end join longer than this is refused where drives passed the gap but saw no line [m]
    join_gap_check_m = Rule("cleanup", 20.0, 0.0)
    #: a piece isolated by refuted fills is kept unless shorter than this and of one drive [m]
    refuted_piece_min_m = Rule("cleanup", 6.0, 0.0)
    #: a run of one marking type shorter than this takes its neighbours' type (RULE 1 flicker) [m]
    min_type_run_m = Rule("cleanup", 20.0, 0.0)
    #: a flicker run of <= ``sparse_drive_count`` drives shorter than this is relabelled [m]
    sparse_type_run_m = Rule("cleanup", 100.0, 0.0)
    #: a polyline shorter than this hanging off a split (into a merge) is a spur, dropped [m]
    spur_max_m = Rule("cleanup", 12.0, 0.0)
    #: of two branches from one split to one merge shorter than this, the weaker is dropped [m]
    bubble_max_m = Rule("cleanup", 60.0, 0.0)
    #: a common piece up to this long before a split of its type is given to both branches [m]
    gore_max_m = Rule("cleanup", 100.0, 0.0)
    #: a polyline whose only successor has it as only predecessor, same type, is one polyline
    merge_continuations = Rule("cleanup", True, False)
    #: at a split or merge with one continuing candidate of its type, the polyline goes through
    through_lines = Rule("cleanup", True, False)

    # With ``refined`` (the paper and ``naive``: off).
    #: a loose end uses its line's direction when it is more than this off the topology's [deg]
    join_line_heading_deg = Rule("refined", 3.0, 10.0)
    #: a long join in its lines' direction is refused where a node in the gap heads this far off [deg]
    join_line_cross_deg = Rule("refined", 30.0, 0.0)
    #: a loose end joins a start of the other marking type up to this far ahead [m]
    join_other_marking_m = Rule("refined", 10.0, 0.0)
    #: an unlinked border of few drives with markings this close on both sides is dropped [m]
    inner_border_max_m = Rule("refined", 5.0, 0.0)
    #: ... when seen by at most this many drives
    inner_border_max_drives = Rule("refined", 2, 1)
    #: ... and kept as a dashed lane line when seen by at most this many
    inner_border_dashed_drives = Rule("refined", 1, 0)
    #: a flicker run of at most this many drives is judged by ``sparse_type_run_m``
    sparse_drive_count = Rule("refined", 3, 5)
    #: ... a run of two or more drives only when its better supported neighbour has more
    sparse_minority_only = Rule("refined", True, False)
    #: a one-drive flicker run shorter than this takes the type around it [m]
    single_drive_run_m = Rule("refined", 250.0, 0.0)
    #: a one-drive run at a line's end shorter than this takes its neighbour run's type [m]
    single_drive_end_run_m = Rule("refined", 250.0, 0.0)
    #: ... judged again along chains through the leftover assignment's 1:1 edges
    single_drive_end_through_leftover = Rule("refined", True, False)
    #: a one-drive marking within this of a border node of its cross-section is the solid edge line [m]
    edge_line_solid_m = Rule("refined", 1.5, 0.0)
    #: a loose end's stub up to this long reached by a fill jumping sideways is dropped [m]
    end_stub_max_m = Rule("refined", 12.0, 0.0)
    #: a component end with no partner elsewhere may link within its own component (no short cycle)
    link_within_component = Rule("refined", True, False)
    #: an end still unlinked follows its chain's own arc this far to a node [m]
    path_search_m = Rule("refined", 36.0, 0.0)
    #: ... until the arc has turned this much [deg]
    path_max_turn_deg = Rule("refined", 60.0, 180.0)
    #: two roads side by side link only within this angle of the end's heading (90: off) [deg]
    side_link_angle_deg = Rule("refined", 30.0, 90.0)
    #: ... also when their features' lateral spans overlap by less than this share
    side_link_overlap = Rule("refined", 0.5, 0.0)
    #: the ordinary link deviates at most this much from the partner's direction too (180: off) [deg]
    partner_angle_deg = Rule("refined", 90.0, 180.0)

    # With ``track_links`` (the paper and ``naive``: off).
    #: an end follows its pivot's track this far and links where it enters a node [m]
    track_search_m = Rule("track_links", 60.0, 0.0)
    #: ... also from ends that have a partner, where the map does not reach the landing anyway
    track_linked_ends = Rule("track_links", True, False)
    #: a track leaving node A through unmapped points for up to this far into B links A to B [m]
    track_bridge_m = Rule("track_links", 60.0, 0.0)
    #: ... leaving from a point up to this far beyond A's cross-section (a track's first point) [m]
    track_bridge_leave_margin_m = Rule("track_links", 2.0, 0.0)
    #: the walk passes over points where the pivot still turns onto the node's road [deg]
    track_settle_deg = Rule("track_links", 8.0, 0.0)
    #: no landing on a road that runs into what the end reaches within this path length [m]
    track_rejoin_m = Rule("track_links", 30.0, 0.0)
    #: ... looked for on both sides of the link (the split behind an end, the merge ahead)
    track_rejoin_both = Rule("track_links", True, False)
    #: tracks are the pivot's own corrected positions, not its steps' cut midpoints
    track_pose = Rule("track_links", True, False)

    def __post_init__(self) -> None:
        check_range(
            self, ("max_distance_m", "join_radius_m", "fill_spacing_m", "min_isolated_length_m"), low=0.0, finite=True
        )
        check_range(self, ("max_heading_diff_deg", "max_connection_angle_deg"), low=0.0, high=180.0, low_open=True)
