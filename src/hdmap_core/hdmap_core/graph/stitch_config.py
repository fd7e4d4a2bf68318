"""Parameters of the inter-segment connection (``stitching.py``, Sec. VI of Immel et al. 2023)."""

from __future__ import annotations

from dataclasses import dataclass

from hdmap_core.checks import check_range
from hdmap_core.pipeline.evidence import EvidenceConfig

__all__ = ["StitchConfig"]


@dataclass(frozen=True)
class StitchConfig:
    """Parameters of the inter-segment connection (the paper gives no numbers).

    Attributes:
        max_distance_m: kd-tree search radius for a component end's neighbour [m].
        max_heading_diff_deg: the two topology nodes' headings differ at most this much [deg].
        max_connection_angle_deg: the link from one node to the other deviates at most this much
            from the driving direction (checked for links longer than ``links._ANGLE_FREE_M``) [deg].
        same_type_only: join features of the same type only (the paper; default). False: a solid
            and a dashed marking may be joined too (at ``type_mismatch_cost_m`` extra cost), since
            their types flicker with misclassification; a road border still joins only a border.
            The polyline closes there (RULE 1) unless ``min_type_run_m`` relabels the short run.
            (Measured on one motorway_ramps run: no gain, so the paper's rule stays default.)
        type_mismatch_cost_m: assignment cost added to a solid-dashed pair [m].
        trim_overlap: drop component end nodes that lie on a place already in the map.
        trim_keep_longer: ... but only where the other graph's piece there is at least as long
            (in topology nodes) as the trimmed one; a shorter piece is trimmed instead (a pivot
            that sees only the last metres of a road must not cut a long pivot's end off and
            then be dropped as an isolated piece). False: every overlap trims the new graph.
        trim_lookahead: a node does not give way to a node of a new graph not walked yet that
            will itself give way to a third graph's node (one look ahead): else both leave the
            place. esmini_soderleden_40_s7: a one-step piece at the road's start gave way to a
            one-step piece 0.85 m ahead, which then gave way to the long pivot 1.2 m further;
            the road's first 1.4 m were lost.
        overlap_search_m: ... as is one up to this far away (midpoints of two pivots differ with
            their cut lines) at most ``trim._OVERLAP_ALONG_M`` along the road, when at least
            ``trim._OVERLAP_SHARE`` of its maxima (and 2) have a same-type twin within
            ``trim._OVERLAP_FEATURE_M`` across the road [m].
        dedupe_loose_ends: drop dangling polyline ends/starts that run on top of another
            segment's polyline of the same class (``loose_ends._TWIN_LATERAL_M`` / ``loose_ends._TWIN_ALONG_M``) [see
            ``MapGraph._dedupe_loose_ends``].
        join_loose_ends: join polyline ends and starts of different segments that continue each
            other (same type, close across the cut) even where topology found no link.
        join_overlap_m: a loose start up to this far behind a loose end (the two overlap) is
            joined too, the end's overlapping nodes dropped [m].
        join_same_segment: also join loose ends of one segment (split there by a gap longer
            than the connection's ``max_gap_m``, RULE 3).
        join_radius_m: how far ahead of a loose end a loose start may begin [m].
        branch_lateral_m: a loose start (end) still unjoined then joins the nearest node of
            another segment's polyline of its type up to ``loose_ends._BRANCH_RADIUS_M`` behind (ahead) and
            this far across the road: a split (merge) across segments. 0 disables [m].
        join_line_heading_m: a loose end (start) is compared by its own polyline's direction,
            from the node at least this far back (on), instead of its topology node's heading (the
            pivot's, which leaves the lines where the pivot turns onto or off a ramp), when the
            two differ by more than ``join_line_heading_deg`` (a few metres of noisy nodes are a
            worse direction than the pivot's on an ordinary road). 0: the topology heading [m].
        join_line_heading_deg: see ``join_line_heading_m`` [deg].
        join_gap_check_m: a loose-end join longer than this is refused where drives passed
            through the gap but its neighbour lines were not mapped there either: some topology
            node (a pivot's step) lies in the middle half of the gap, within
            ``join_gap_lateral_m`` across the join and ``loose_ends._JOIN_GAP_HEADING_DEG`` of its direction,
            while drive-supported feature nodes of that direction within ``join_gap_lateral_m``
            cover less than ``loose_ends._JOIN_GAP_COVERAGE`` of the 2 m bins of the middle half. Every line of
            a road then ends at the same gap (a junction's mouth, where the steps failed): the
            straight fill across it is no drive's line. 0 disables (the paper) [m].
        join_gap_lateral_m: see ``join_gap_check_m`` [m].
        join_line_cross_deg: a join longer than ``join_gap_check_m`` that passes only in its
            lines' direction (``join_line_heading_m``: where the pivot turned) is refused when a
            topology node in the middle half of the gap, within ``loose_ends._JOIN_LINE_CROSS_LATERAL_M``
            across, heads more than this off the join: a pivot turning through a junction, whose
            lines all end at its mouth (carla_town06_30: three dashed lines filled straight
            across a junction, 30 false points each). 0 disables [deg].
        join_other_marking_m: with ``same_type_only``, a loose end and a loose start of the other
            lane-marking type (solid / dashed; a road border still joins only a border) are joined
            too when the start lies at most this far ahead (the other tests as for any join, at
            ``type_mismatch_cost_m`` extra cost): one line whose type flickered where a segment
            ended (a one-drive misclassified run at the end; the export's type runs relabel it).
            carla_town04_30_s1: a 3 km solid line, its end run dashed, the next segment's start
            solid 1.7 m ahead, stayed two polylines. Longer cross-type joins made a false 48 m
            fill there. 0 disables (the dataclass, ``paper``; 10 in the default preset) [m].
        fill_spacing_m: a polyline edge longer than 1.5 x this (a bridged gap or join) is filled
            with points on a cubic Hermite curve through the end tangents, this far apart; the
            filled points carry drive_count 0 (no drive saw them). 0 disables [m].
        min_isolated_length_m: polylines without any link and shorter than this are dropped
            (single-step specks, false positives) [m].
        refuted_piece_min_m: a polyline isolated only because fills were refuted (``fill_evidence``)
            is kept whatever its length (a short line between two junction mouths), unless it is
            shorter than this and seen by at most ``export._REFUTED_PIECE_MAX_DRIVES`` drives: one drive's
            2-3 steps left between refuted fills are a speck (carla_town04_50_s1: 1-3 m pieces
            of one drive at a gore and beside the ramps, each an extra piece of its line). 0
            keeps every such piece [m].
        inner_border_max_m: a road border polyline without any link, seen by at most
            ``inner_border_max_drives`` drives, is dropped when at most of its drive-supported
            nodes lane markings of its direction lie within this distance on both sides: a
            border has the road on one side only, and one drive's marking reported as a border
            (1 % of marking stretches in the simulator) lies between two lane lines
            (carla_town04_30_s2: three such borders of 44-104 m, 115 false map points). 0
            disables (5 in the default pipeline preset) [m].
        inner_border_max_drives: see ``inner_border_max_m`` (max drive count over its nodes).
        inner_border_dashed_drives: such an inner border of at most this many drives is kept as
            a dashed lane line instead of being dropped: the simulator's marking_to_border
            stretches are lane lines the only drive there saw (carla_town04_30_s3 x 260 .. 398:
            152 m of a dashed line one drive reported as a border), unless a marking lies
            within 1 m across at most of its nodes (the line is mapped already). 0: dropped
            (the dataclass default; 1 in the default pipeline preset).
        sparse_type_run_m: a flicker run (between two runs of one other type) seen by at most
            ``sparse_drive_count`` drives (median) is relabelled when shorter than this (with
            1-3 drives one drive's misclassification sets the type for tens of metres). 0
            disables [m].
        sparse_drive_count: see ``sparse_type_run_m``.
        sparse_minority_only: ... and such a run of two or more drives only when the better
            supported run beside it has more drives (median): on the 30-drive CARLA fleets
            solid runs of 3 drives between dashed runs of 2-3 drives were real and relabelling
            them cost precision. False: any run of <= ``sparse_drive_count`` (True in the
            default pipeline preset).
        single_drive_run_m: a flicker run seen by one drive (median) is relabelled when shorter
            than this: one drive's type is no evidence against the type the line has before
            and after it, and a misclassified stretch is 20-200 m long (the simulator's blocks;
            on carla_town04_30_s1 two one-drive solid runs of 160-175 m between dashed runs
            held 171 of the 642 false map points); not when the run is longer than both runs
            beside it (one drive's solid 78 m, dashed 145 m, solid 77 m: the short runs are the
            likelier misclassification). 0 disables (250 in the default pipeline preset) [m].
        single_drive_end_run_m: the same for a run at a polyline's end (one neighbour run): seen
            by one drive (median), shorter than this and not longer than its neighbour run, it
            takes the neighbour's type when that run was seen by more drives (median); judged
            once no other run is to be merged. A sparse line's last metres before a junction or
            a gap are often one drive's, and its misclassified stretch (or its flicker, merged
            into one run shortest first) was kept as a line of the other type
            (carla_town06_30_s3, docs/pipeline.md "One drive's type at a line's end"). 0
            disables (250 in the default pipeline preset) [m].
        single_drive_end_through_leftover: the ``single_drive_end_run_m`` rule judged once more
            after the other type rules, along chains that go on through edges made by the
            leftover assignment (a 1:1 edge, no split or merge): the smoothing's chains end at
            such an edge while the exported polyline goes on through it, so a one-drive run at
            a chain's end was compared with nothing (its better supported neighbour run lay in
            the next chain) and a chain's inner run looked like an end run. Only the end rule
            is judged along the longer chains (the flicker rules there relabelled a true 90 m
            dashed run on carla_town06_30_s1). False in the dataclass (True in the default
            pipeline preset; docs/pipeline.md "Type runs across leftover edges").
        edge_line_solid_m: a lane-marking node of at most ``export._EDGE_LINE_MAX_DRIVES`` drives (or of
            unknown type: drives that disagreed, ``AlignmentConfig.sparse_type_clash_keep``)
            within this distance across of a road border node of the same cross-section
            (topology node) is typed solid before the type runs are smoothed: the marking next to
            the road's edge is its edge line, solid on 97-100 % of such points in every map of
            the ground-truth maps (data/maps on the harden branch) (Town04 2570 of 2642, Town06
            11785 of 11795, e6mini all, soderleden 103 of 115), while one drive misclassifies a
            stretch 7.5 % of the time in the simulator (carla_town06_30_s3: one drive's 80 m
            dashed run of the right edge line, typed dashed against the other drive's solid).
            0 disables [m].
        end_stub_max_m: at a polyline's loose end (no edge beyond it), a run of drive-supported
            nodes up to this long that the rest of the line reaches only through an edge long
            enough to be filled, whose far end lies ``cleanup._END_STUB_SIDE_M`` (and ``cleanup._END_STUB_SLOPE`` of
            the edge's length) to the side of the rest's topology heading, is dropped with that
            edge: a loose-end join or bridged gap onto the neighbouring lane's line at a ramp or
            junction end, a stray piece of another line (docs/pipeline.md, "Town04's stray
            pieces"). Only where every stub node has another polyline's node within
            ``end_stub_cover_m`` across (and 2 m along): a stub that is the only map line on its
            cross-section stays. 0 disables (the dataclass default; 12 in the default pipeline
            preset) [m].
        end_stub_cover_m: see ``end_stub_max_m``; 0: no coverage check (every such stub is
            dropped) [m].
        spur_max_m: a polyline shorter than this that hangs off a split without successor (or
            runs into a merge without predecessor) is a spur and is dropped. 0 disables [m].
        bubble_max_m: of two branches from one split node to one merge node (or a branch beside
            a direct edge between them) the one with fewer drives is dropped when shorter than
            this: lanes do not split and rejoin within it [m].
        gore_max_m: a common piece at most this long between a type change and a split into two
            polylines of its type (a gore's lines before they are resolved) is given to both
            branches, so the split sits where the lane line ends (merges alike). 0 disables [m].
        min_type_run_m: along a polyline, a run of one marking type (solid/dashed) shorter than
            this takes its neighbours' type instead of closing the polyline twice (RULE 1 on
            misclassification flicker). 0 disables (the paper) [m].
        merge_continuations: at export, a polyline whose only successor has it as its only
            predecessor, of the same type, is one polyline with it (what closed them, e.g. a
            leftover edge whose sibling branch was pruned or a one-point piece between them, is
            gone). False: the paper.
        link_within_component: a component start (end) that finds no partner in *another* weakly
            connected component may take one in its own (same geometric tests), as a topology link
            only (no feature join), unless that closes a cycle of fewer than ``stitching_links._CYCLE_NODES``
            nodes. At a junction the main road's piece after a ramp is often joined to the map
            already through its other end, so its start stayed unlinked: the map's topology had
            no path from the incoming road to that branch (docs/evaluation.md, road-level splits
            and merges). On in the default preset only.
        path_search_m: a component start (end) still without a partner after every other
            component start/end had its turn follows its chain's own path backward (forward) up
            to this far: an arc from the node along its heading, turning at the chain's heading
            rate (over ``linking._PATH_CURVATURE_M`` of the chain). The first node whose cross-section
            (``topo_width`` / 2 across, one step along) the arc enters, with a heading within
            ``max_heading_diff_deg`` of the arc's there, in another component (or, with
            ``link_within_component``, in its own without closing a short cycle), is linked, as a
            topology link only (no feature join). A ramp's chain ends (an exit's starts) where
            its pivot's steps fail or reach a place mapped before, often still turning, 24-38 m
            from the gore: the main road within ``max_distance_m`` is 33-39 deg off the ramp's
            heading there, or the main road is beyond that radius (docs/graph.md). 0 disables
            (the paper; the plain default) [m].
        track_search_m: a component start (end) still without a partner after the ordinary
            links follows the path its own pivot drove (``SegmentGraph.track_xy``: every step's
            cut midpoint, rejected steps included) backward (forward) up to this far and links,
            topology only, to the first node whose cross-section (``topo_width`` / 2 across, one
            step along) a track point lies in, with a heading within ``max_heading_diff_deg`` of
            the track's there (another component, or with ``link_within_component`` its own
            without closing a short cycle). The link is drive-supported: the pivot went from the
            end to that node. Run before the arc search (``path_search_m``), whose extrapolated
            arc misses junction turns past ``path_max_turn_deg`` (Town04's exit, docs/graph.md
            "Track links"). The walk stops at a gap of more than ``tracks._TRACK_MAX_GAP_M`` between
            track points (a run processed before keeps only its first and last step). 0
            disables (the paper, the plain default) [m].
        track_linked_ends: the track search also runs from starts (ends) that have a partner
            already; it then links to a node its pivot's track enters only when the map does
            not reach that node from the start (end) within 2 * ``track_search_m`` + 30 m (the
            pivot took a turn at a junction that the ordinary link went straight through).
        track_rejoin_m: with ``track_linked_ends``, a node whose road runs on (for a start:
            back) within this path length into a node the map reaches from the start (end)
            is no landing either: the link would only be a side step between two roads that
            join anyway (esmini_soderleden_40_s5: a ramp end's pivot, on the strip beside the
            main road, landed 4.6 m sideways on the main road upstream of where the ramp's own
            continuation joins it; docs/graph.md "Side steps"). 0 disables (the paper, the
            plain default) [m].
        track_rejoin_both: with ``track_rejoin_m``, look on the other side of the link too: a
            node whose road came (for a start: runs on) within ``track_rejoin_m`` from (into)
            what reaches the end (what the start reaches) is no landing either, the side step
            across the split behind an end or the merge ahead of a start
            (carla_town04_100_s2 live: a merging ramp's linked start, its pivot's cut midpoints
            on the main road beside it, got a 12.9 m link from the main road 8 m before the
            merge; docs/graph.md "Side steps"). False: only the side named above.
        track_settle_deg: the track search (``track_search_m``) passes over a track point where
            the pivot is still turning onto the node's road: the track's heading there lies more
            than 2 x this off the node's and at the next track point of the walk (no gap)
            within this of it. The walk goes on and lands where the track has settled, or
            nowhere. A turn's track cuts the corner: on carla_town06_100_s1 an end's pivot,
            turning right onto a road, lay in the cross-section of a node 22 deg off its heading
            2 m before the turn lane joins that road (the node carries only the lanes from the
            south; a false 14.5 m link), 4.5 deg off one step later (docs/graph.md, "Track
            settling"). 0 disables (the paper, the plain
            default) [deg].
        track_bridge_m: where a pivot's track leaves a topology node A (a track point in its
            cross-section, heading within ``tracks._TRACK_BRIDGE_HEADING_DEG``), runs through at least one
            point in no node's cross-section for at most this far, and enters a node B, A is
            linked to B (topology only) unless the map reaches B from A within 2 * this + 30 m or
            the link closes a short cycle: the pivot drove from A to B. Needs no component
            start/end: at a junction turn whose steps failed while the roads on both sides were
            mapped by other pivots (the pivot's steps there processed before), no chain ends
            where the pivot turned, so the track search never starts (carla_town04_30_s1's exit,
            docs/graph.md "Track bridges"). 0 disables (the paper, the plain default) [m].
        track_bridge_leave_margin_m: see ``track_bridge_m``: where the walk has no road to leave
            yet (the track's first point, or the first after a gap: a run processed before keeps
            only its first and last step), a point up to this far beyond a node's cross-section
            (each side, heading within ``max_heading_diff_deg``) leaves that node. The last step
            of a run processed before, just before a junction's failed steps, has a cut midpoint
            already pulled off the road's middle: on carla_town04_50_s1 the only pivot through
            the exit's left turn at (-381, 12) lay 5.5-5.6 m across the exit road's last nodes
            (4.8-4.9 m half wide), so no bridge started and the exit's branch onto the road at
            y = -33 was not connected (docs/graph.md, "Track bridges").
            Only for leaving, and only there: a bridge still ends in a node's own cross-section,
            and a walk already off a road is not cut short. 0 disables (the paper, the plain
            default) [m].
        track_pose: the track search (``track_search_m``) and the track bridges
            (``track_bridge_m``) follow the pivot's own positions (``SegmentGraph.track_pose``:
            its trajectory point at each step, corrected like its samples by the offset model),
            not its steps' cut midpoints. A rejected step's midpoint is wherever its cut was
            refined to: at a junction, on a road the pivot never drove (carla_town04_30_s1: a
            pivot turning right from a side road had failed midpoints on the crossing road's
            through lanes, 8 m left of its turn, and the end was linked 18 m onto them, upstream
            of where the turn joins; docs/graph.md "Tracks of poses"). Graphs without poses
            (stored before) keep the midpoints. False: the midpoints (the plain default).
        fill_evidence: at export, a feature edge long enough to be filled is dropped when most of
            it runs where the drives that passed saw nothing (``hdmap_core.pipeline.evidence``, from the
            segments' ``StepResult.empty_m``, made by ``PipelineConfig.evidence``; the export's
            rules are that module's constants): its ends stay loose ends. None: off (the paper,
            the plain default).
        path_max_turn_deg: the arc search stops once the arc has turned this much from the
            node's heading: an arc still turning past it has left the road the chain was on
            (a chain start turning 92 deg in 30 m hit the opposite carriageway) [deg].
        side_link_angle_deg: a component start/end and a partner whose cross-sections lie apart
            (lateral offset > the sum of their half widths: two roads side by side) are linked
            only within this angle of the end's heading: esmini_soderleden's on-ramp, still a
            separate road 10 m beside the main road, was joined to it at 74 deg (under
            ``max_connection_angle_deg``). 90 = off (the paper, the plain default) [deg].
        side_link_overlap: with ``side_link_angle_deg``, two nodes whose half widths do reach
            each other still count as side by side when the lateral spans of their features
            overlap by less than this share of the narrower span (+ 1 m slack): the on-ramp of
            esmini_soderleden_40_s5, its features 4.5 m across, the shared edge 0.4 m inside the
            main road's lines, was linked 66 deg sideways to the main road. 0 = off (widths only:
            the paper, the plain default).
        partner_angle_deg: the ordinary link of a component start/end must also deviate at
            most this much from its partner's driving direction (links longer than
            ``links._ANGLE_FREE_M``), not only from the start's/end's own: a ramp node 20 deg off the
            main road was taken as the predecessor of a main-road start 8.4 m beside it, a link
            97 deg off the ramp's heading, backward for it (carla_town04_100_s1). 180 = off
            (the paper, the plain default) [deg].
        through_lines: at a split or merge whose node has exactly one continuing candidate of its
            own type, that edge continues the polyline through it (``segment_graph.chain_links``)
            instead of closing it there. False: the paper (every split and merge closes it).
    """

    max_distance_m: float = 12.0
    max_heading_diff_deg: float = 30.0
    max_connection_angle_deg: float = 80.0
    same_type_only: bool = True
    type_mismatch_cost_m: float = 0.3
    trim_overlap: bool = True
    trim_keep_longer: bool = True
    trim_lookahead: bool = True
    overlap_search_m: float = 8.0
    dedupe_loose_ends: bool = True
    join_loose_ends: bool = True
    join_same_segment: bool = True
    join_overlap_m: float = 8.0
    branch_lateral_m: float = 0.0
    join_radius_m: float = 60.0
    join_line_heading_m: float = 4.0
    join_line_heading_deg: float = 10.0
    join_gap_check_m: float = 20.0
    join_gap_lateral_m: float = 12.0
    join_line_cross_deg: float = 0.0
    join_other_marking_m: float = 0.0
    fill_spacing_m: float = 2.0
    min_isolated_length_m: float = 20.0
    refuted_piece_min_m: float = 6.0
    inner_border_max_m: float = 0.0
    inner_border_max_drives: int = 1
    inner_border_dashed_drives: int = 0
    min_type_run_m: float = 20.0
    sparse_type_run_m: float = 100.0
    sparse_drive_count: int = 5
    sparse_minority_only: bool = False
    single_drive_run_m: float = 0.0
    single_drive_end_run_m: float = 0.0
    single_drive_end_through_leftover: bool = False
    edge_line_solid_m: float = 0.0
    spur_max_m: float = 12.0
    end_stub_max_m: float = 0.0
    end_stub_cover_m: float = 8.0
    bubble_max_m: float = 60.0
    gore_max_m: float = 100.0
    merge_continuations: bool = True
    link_within_component: bool = False
    path_search_m: float = 0.0
    track_search_m: float = 0.0
    track_linked_ends: bool = False
    track_bridge_m: float = 0.0
    track_bridge_leave_margin_m: float = 0.0
    track_settle_deg: float = 0.0
    track_rejoin_m: float = 0.0
    track_rejoin_both: bool = False
    track_pose: bool = False
    fill_evidence: EvidenceConfig | None = None
    path_max_turn_deg: float = 180.0
    side_link_angle_deg: float = 90.0
    side_link_overlap: float = 0.0
    partner_angle_deg: float = 180.0
    through_lines: bool = True

    def __post_init__(self) -> None:
        check_range(self, (
            "max_distance_m", "type_mismatch_cost_m", "overlap_search_m", "join_radius_m", "join_overlap_m",
            "branch_lateral_m", "join_line_heading_m", "join_line_heading_deg", "join_gap_check_m",
            "join_gap_lateral_m", "join_line_cross_deg", "join_other_marking_m", "fill_spacing_m",
            "min_isolated_length_m", "refuted_piece_min_m", "inner_border_max_m", "min_type_run_m",
            "sparse_type_run_m", "single_drive_run_m", "single_drive_end_run_m", "edge_line_solid_m",
            "spur_max_m", "end_stub_max_m", "end_stub_cover_m", "bubble_max_m", "gore_max_m", "path_search_m",
            "track_search_m", "track_bridge_m", "track_bridge_leave_margin_m", "track_settle_deg",
            "track_rejoin_m",
        ), low=0.0, finite=True)
        check_range(self, (
            "max_heading_diff_deg", "max_connection_angle_deg", "path_max_turn_deg", "side_link_angle_deg",
            "partner_angle_deg",
        ), low=0.0, high=180.0, low_open=True)
        check_range(self, ("side_link_overlap",), low=0.0, high=1.0)
        check_range(self, ("inner_border_max_drives",), low=1)
        check_range(self, ("inner_border_dashed_drives",), low=0)

    @classmethod
    def paper(cls) -> StitchConfig:
        """The paper's variant: topology links and same-type unmodified assignment only."""
        return cls(
            same_type_only=True,
            trim_overlap=False,
            dedupe_loose_ends=False,
            join_loose_ends=False,
            min_isolated_length_m=0.0,
            refuted_piece_min_m=0.0,
            inner_border_max_m=0.0,
            fill_spacing_m=0.0,
            join_line_heading_m=0.0,
            join_gap_check_m=0.0,
            join_line_cross_deg=0.0,
            min_type_run_m=0.0,
            sparse_type_run_m=0.0,
            sparse_minority_only=False,
            single_drive_run_m=0.0,
            single_drive_end_run_m=0.0,
            spur_max_m=0.0,
            bubble_max_m=0.0,
            gore_max_m=0.0,
            merge_continuations=False,
            through_lines=False,
        )
