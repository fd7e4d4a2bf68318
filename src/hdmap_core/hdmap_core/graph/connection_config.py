"""Parameters of the connection stage (Sec. V): :class:`ConnectionConfig`.

Its own module so that ``assignment`` (the modified assignment) and ``connection`` (which calls it)
both read it without importing each other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from hdmap_core.checks import check_range

__all__ = ["ConnectionConfig"]


@dataclass(frozen=True)
class ConnectionConfig:
    """Parameters of the connection stage (the paper gives none of these numbers).

    Attributes:
        max_gap_m: steps without a result are bridged when the pivot travelled at most this far
            between two valid steps; a longer gap closes every polyline (RULE 3) [m].
        robust_angle: judge a step by the median connection angle instead of the mean, so that
            one feature leaving the cut while another enters does not reject a good step.
        mean_angle_slack: measure those connection angles with ``edge_slack_m`` taken off each
            connection's offset across the road, as the edge limit is: the maxima's own noise.
            On a tight curve the inner lines' maxima of consecutive steps lie < 1 m apart along
            the road, where 0.3 m of noise is 20 deg (carla_town06_30_s6's loop at y 148,
            radius ~13 m: 26 of its 33 steps rejected). False: the raw angles (the paper).
        max_edge_angle_deg: a single connection steeper than this is not made; 90 disables [deg].
        edge_slack_m: lateral slack added to the edge angle limit (noise of the maxima) [m].
        leftover_max_m: a leftover node is joined to its nearest neighbour only when that is at
            most this far across the cut; ``inf`` joins every leftover, as in the paper [m].
        leftover_same_type: join a leftover only to a node of its own type. At a gore the two
            lines resolve as one of their type first and split later (solid -> two solids), so
            real splits keep their leftover; a line that ends beside a line of the other marking
            type (solid beside dashed) no longer merges into it. False: the paper.
        fresh_first: assign the open ends of the last step first and let the ends bridged from
            earlier steps (``bridge_features``) take only the maxima left. One joint assignment
            minimises the summed distance, so a one-drive tip bridged from three steps back could
            take a well-supported line while the line it continues took its diverging neighbour
            (paper_like 4x: the through line of a gore continued a one-drive dashed maximum
            1.4 m beside it, and the exit lost its split; docs/pipeline.md "Fresh tips first").
            False: one assignment (the paper, the plain default).
        leftover_other_type_m: ... except when the marking of the other type is at most this far
            across: two markings that close are one place, so the leftover is a branch starting
            (ending) on the other line (an exit's dashed line starting on the solid edge line,
            0.2-0.5 m from it when first resolved; an entry's solid line ending on the dashed
            one). 0: same type only [m].
        bridge_features: keep a polyline whose feature is missing in a step open for ``max_gap_m``
            so that it continues when the feature reappears (per-feature gap bridging; the paper
            bridges whole steps only).
        min_separation_m: two lane markings (or two road borders) of one step closer than this
            are one feature seen twice (typically a misclassified cluster the overlap filter
            kept); only the one with more drives is used. 0 disables (the paper) [m].
        separation_count_ratio: ... only when the weaker one has at most this share of the
            stronger one's drives. 1.0 (default): always. (0.5 keeps two well supported lines
            about to diverge, but measured worse: they flicker and fragment more.)
        min_support_share: a maximum supported by fewer than this share of the step's drives
            (``counts < share * len(drive_ids)``) is noise (a false positive, a misclassified
            copy) and not used. 0 disables (the paper).
        support_window_m: when > 0, the share is taken of the best supported maximum of the step
            within this lateral distance (itself included) instead of all the step's drives: on a
            wide cut (a ramp beside the carriageway) the far lines are seen by only the drives
            near them, while a false positive or misclassified copy still sits beside a line many
            more drives saw [m].
        window_min_count: the window rule keeps only maxima of at least this many drives (a
            maximum of one drive flickers: one drive's false positive or misclassified stretch).
        lone_line_gap_m: when > 0, a maximum whose neighbours in its step (next inward and
            outward; none counts as far) are both at least this far away is kept with at least
            ``window_min_count`` drives, whatever the support share: a line seen only by the
            drives of the lane beside it lies a lane from the next line, while a misclassified
            copy or a false positive lies beside a line or inside a lane (carla_town04_50_s1:
            the inner edge line at a painted median, 3.5 m from a lane line of 7 drives, seen by
            the one drive in the lane between over 136 m; the right edge line 3.5 m inside the
            border, seen by one drive). 0 disables [m].
        lone_line_border_gap_m: for a marking, a road-border neighbour need only be this far
            away (the edge line lies 0.2-1.5 m inside the border, carla_town06_30_s1 x 326 ..
            476: 1.1 m, seen by one drive, the border by three; 0.5 m let one drive's solid
            lines 0.3-0.6 m from esmini_soderleden's border through). None: ``lone_line_gap_m``
            [m].
        lone_line_border_outer: the border neighbour of ``lone_line_border_gap_m`` counts only on
            the line's outer side (away from the cut's midpoint), where an edge line has its
            border. With 100 drives a lane line has one- or two-drive copies typed as border
            (the simulator's marking-to-border misclassification); taken as an edge line's
            border, such a copy let one drive's false line 2.3 m beside it through
            (esmini_soderleden_100_s4, precision 97.7 %).
        topo_pivot_lane_m: when > 0, the topology node of a step whose pivot's own position
            (``StepResult.pose``) lies beyond its refined cut gets a cross-section (midpoint,
            width) widened to reach this far beyond the pivot: the node describes the road the
            pivot drove. Where one side of a junction has no line, the cut sits on the side of
            the one border seen, its width carried from a step that ended at a stray line beside
            the pivot, and the node lay beside that road (carla_town04_30_s3's T-junction at x
            -388: a 4.5 m cut 1.15 m off the pivot, linked to its road 12 m back as if to the
            junction's side road). Only the topology node moves; the step's samples and
            features stay. 0: the cut as refined [m].
        tile_size_m: edge of the square tiles that key topology nodes by place [m].
        tip_frame_deg: a polyline end at least ``connection._TIP_FRAME_MIN_M`` (pivot travel) behind the new
            step (a bridged gap) whose own direction (from its node ~3 edges back, at least
            ``connection._TIP_FRAME_MIN_M`` away) differs from the new step's heading by more than this is
            paired in its own frame (along / across its direction) instead of the pivot's: where
            the pivot turns off (an exit ramp) the straight lines it still sees leave its
            heading, and in its frame the pairing shifted by one lane looked straight (Town04's
            cloverleaf: every line joined the next one 3.5 m over ~11 m). 0 disables [deg].
        bridge_edge_angle_deg: a connection longer than ``assignment._BRIDGE_EDGE_MIN_M`` along (across a
            bridged gap) steeper than this is not made (``edge_slack_m`` added): a 30 deg edge
            over 10 m is a line that ended joined to its neighbour 6 m over (an inner gore
            border to the outer border at an entry), not one line. 90 disables [deg].
        line_frame_deg: any open polyline end (also between consecutive steps, also on the
            identity fast path) whose own line direction (from its node at least 4 m back within
            6 edges, else the farthest at least ``connection._LINE_FRAME_MIN_M`` back) differs from the new
            step's heading by more than this (and at most ``connection._TIP_FRAME_MAX_DEG``) is paired in its
            own frame. Where a pivot comes in on an entry ramp at 17-25 deg to the carriageway, in
            its frame each carriageway line paired with the next lane's line (Town04: 3.2 m
            sideways over 6 m), or the step was rejected by the angle check (the true pairs
            looked 20 deg steep). An end without a direction of its own (a line the cut has just
            reached) keeps the pivot's frame: borrowing a neighbour's direction took a merging
            ramp line's at an entry (Town04 30 s3 fragmentation 1.541 -> 1.568). 0 disables (the
            paper) [deg].
        line_frame_max_deg: see ``line_frame_deg`` [deg].
        line_frame_check: a tip whose line leaves the heading by more than ``line_frame_max_deg``
            (and at most ``line_check_max_deg``) is paired in the pivot's frame, but an edge
            steeper than the edge limits (``max_edge_angle_deg``, ``bridge_edge_angle_deg``)
            against its own line direction, or not ahead along it, is not made: where the pivot
            turns off onto an exit the lines it leaves end in its segment instead of joining the
            next lane's line.
        line_check_max_deg: see ``line_frame_check``. 180 (default): any larger deviation. With
            90, a pivot turning off at a right angle across a bridged gap (an intersection, a
            T-junction joining the motorway) paired the lines it left in its new frame: on every
            CARLA fleet 1-4 lines turned a corner that no line has (Town04 50 s1: the median
            solid line continued 28 m across the carriageway into the side road) [deg].
        line_check_undirected: an end without a direction of its own (a line the cut has just
            reached) left behind where the pivot has since turned by more than
            ``line_frame_max_deg`` is checked against the pivot's heading at its step (the
            only direction known for it): at an intersection one node of a crossing line was
            joined across the turn to a line of the other road. Only with ``line_frame_deg`` and
            ``line_frame_check``.
        line_frame_bend_deg: ... both only for a line whose history is straight: the directions to
            its predecessors (at least ``connection._LINE_FRAME_MIN_M`` back, within 6 edges) all lie within
            this of the line's direction. Where the road curves (Town06's corners and junction
            turns) the lines curve with the pivot, a direction from 4 m back lags its heading by
            12-30 deg, and in that frame true continuations looked steep: steps were rejected
            and chord edges across a turn refused (Town06 30 s3 coverage 98.92 -> 98.13). 0: any
            history [deg].
    """

    max_gap_m: float = 20.0
    robust_angle: bool = True
    mean_angle_slack: bool = False
    max_edge_angle_deg: float = 35.0
    edge_slack_m: float = 0.3
    leftover_max_m: float = 2.0
    leftover_same_type: bool = True
    fresh_first: bool = False
    leftover_other_type_m: float = 1.0
    bridge_features: bool = True
    min_separation_m: float = 1.0
    separation_count_ratio: float = 1.0
    min_support_share: float = 0.25
    support_window_m: float = 0.0
    window_min_count: int = 1
    lone_line_gap_m: float = 0.0
    lone_line_border_gap_m: float | None = None
    lone_line_border_outer: bool = False
    topo_pivot_lane_m: float = 0.0
    tile_size_m: float = 256.0
    tip_frame_deg: float = 5.0
    bridge_edge_angle_deg: float = 15.0
    line_frame_deg: float = 0.0
    line_frame_max_deg: float = 30.0
    line_frame_check: bool = True
    line_check_max_deg: float = 180.0
    line_check_undirected: bool = True
    line_frame_bend_deg: float = 0.0

    def __post_init__(self) -> None:
        check_range(self, ("max_gap_m", "edge_slack_m", "min_separation_m", "leftover_max_m"), low=0.0)
        check_range(self, ("max_edge_angle_deg", "bridge_edge_angle_deg"), low=0.0, high=90.0, low_open=True)
        check_range(self, ("line_check_max_deg",), low=0.0, high=180.0, low_open=True)
        check_range(self, ("min_support_share",), low=0.0, high=1.0)
        check_range(
            self,
            (
                "support_window_m",
                "lone_line_gap_m",
                "topo_pivot_lane_m",
                "leftover_other_type_m",
                "tip_frame_deg",
                "line_frame_deg",
                "line_frame_max_deg",
                "line_frame_bend_deg",
            ),
            low=0.0,
            finite=True,
        )
        if self.lone_line_border_gap_m is not None:
            check_range(self, ("lone_line_border_gap_m",), low=0.0, finite=True)
        check_range(self, ("window_min_count",), low=1)
        check_range(self, ("tile_size_m",), low=0.0, low_open=True, finite=True)

    @classmethod
    def paper(cls) -> ConnectionConfig:
        """The paper's variant: every leftover joined, no per-edge limit, whole-step bridging only."""
        return cls(
            max_edge_angle_deg=90.0,
            leftover_max_m=math.inf,
            leftover_same_type=False,
            bridge_features=False,
            robust_angle=False,
            min_separation_m=0.0,
            min_support_share=0.0,
            tip_frame_deg=0.0,
            bridge_edge_angle_deg=90.0,
        )
