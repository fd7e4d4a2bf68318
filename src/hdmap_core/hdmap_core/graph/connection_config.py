"""Parameters of the connection stage (Sec. V): :class:`ConnectionConfig`.

Its own module so that ``assignment`` (the modified assignment) and ``connection`` (which calls it)
both read it without importing each other. ``ConnectionConfig()`` is the recommended stage; its
public fields are the gap and support limits and the two switches the presets flip, every other
rule a fixed :class:`~hdmap_core.checks.Rule` (or constant) of the class, with what it does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

from hdmap_core.checks import Rule, check_range

__all__ = ["ConnectionConfig"]


@dataclass(frozen=True)
class ConnectionConfig:
    """Parameters of the connection stage (the paper gives none of these numbers).

    Attributes:
        max_gap_m: steps without a result are bridged when the pivot travelled at most this far
            between two valid steps; a longer gap closes every polyline (RULE 3) [m].
        min_support_share: a maximum supported by fewer than this share of the step's drives
            (``counts < share * len(drive_ids)``) is noise (a false positive, a misclassified
            copy) and not used. 0 disables (the paper).
        cleanup: the rules of the first implementation (its fixed ``cleanup`` rules: median
            connection angle, per-edge angle limits, leftovers near and of their own type,
            per-feature gap bridging, one feature seen twice). False: the paper's assignment
            (every leftover joined, whole-step bridging only).
        refined: the rules measured and adopted on the simulated and CARLA fleets since (its
            fixed ``refined`` rules: fresh tips first, the support window, lone lines, line
            frames, the pivot's lane in its topology node). False: the paper (and ``naive``).
    """

    max_gap_m: float = 20.0
    min_support_share: float = 0.25
    cleanup: bool = True
    refined: bool = True

    # Fixed in every preset.
    #: lateral slack added to the edge angle limits (noise of the maxima) [m]
    edge_slack_m: ClassVar[float] = 0.3
    #: a leftover joins a marking of the other type this close across (a branch on it) [m]
    leftover_other_type_m: ClassVar[float] = 1.0
    #: the support window and lone-line rules keep only maxima of at least this many drives
    window_min_count: ClassVar[int] = 1
    #: edge of the square tiles that key topology nodes by place [m]
    tile_size_m: ClassVar[float] = 256.0
    #: a line leaving the pivot's heading by more than this is paired in the pivot's frame [deg]
    line_frame_max_deg: ClassVar[float] = 30.0
    #: ... but its edges are checked against its own direction
    line_frame_check: ClassVar[bool] = True
    #: ... up to this deviation [deg]
    line_check_max_deg: ClassVar[float] = 180.0
    #: an end without a direction of its own left behind a turn is checked against the pivot's
    line_check_undirected: ClassVar[bool] = True
    #: a lone marking's border neighbour need only be this far away (an edge line) [m]
    lone_line_border_gap_m: ClassVar[float] = 0.8
    #: ... and counts only on the line's outer side
    lone_line_border_outer: ClassVar[bool] = True

    # With ``cleanup`` (the paper: off).
    #: judge a step by the median connection angle instead of the mean
    robust_angle = Rule("cleanup", True, False)
    #: a single connection steeper than this is not made (90: off) [deg]
    max_edge_angle_deg = Rule("cleanup", 35.0, 90.0)
    #: a leftover node joins its nearest neighbour only this far across (inf: always) [m]
    leftover_max_m = Rule("cleanup", 2.0, math.inf)
    #: a leftover joins only a node of its own type
    leftover_same_type = Rule("cleanup", True, False)
    #: a polyline whose feature is missing in a step stays open for ``max_gap_m``
    bridge_features = Rule("cleanup", True, False)
    #: two markings (borders) of one step closer than this are one feature seen twice [m]
    min_separation_m = Rule("cleanup", 1.0, 0.0)
    #: a bridged tip whose own direction leaves the step's heading by more than this is paired
    #: in its own frame [deg]
    tip_frame_deg = Rule("cleanup", 5.0, 0.0)
    #: a connection across a bridged gap steeper than this is not made (90: off) [deg]
    bridge_edge_angle_deg = Rule("cleanup", 15.0, 90.0)

    # With ``refined`` (the paper and ``naive``: off).
    #: connection angles measured with ``edge_slack_m`` taken off (tight curves)
    mean_angle_slack = Rule("refined", True, False)
    #: the last step's open ends are assigned first, bridged ends take what is left
    fresh_first = Rule("refined", True, False)
    #: one of two features seen twice is dropped only with at most this share of the other's drives
    separation_count_ratio = Rule("refined", 0.5, 1.0)
    #: the support share is taken of the best maximum within this lateral distance [m]
    support_window_m = Rule("refined", 4.0, 0.0)
    #: a maximum a lane from both its neighbours is kept whatever its support [m]
    lone_line_gap_m = Rule("refined", 3.0, 0.0)
    #: a step's topology node reaches this far beyond its pivot when the pivot lies outside [m]
    topo_pivot_lane_m = Rule("refined", 0.5, 0.0)
    #: an open end whose straight line leaves the step's heading by more than this is paired in
    #: its line's frame (an entering pivot) [deg]
    line_frame_deg = Rule("refined", 12.0, 0.0)
    #: ... only when the line's history lies within this of its direction [deg]
    line_frame_bend_deg = Rule("refined", 5.0, 0.0)

    def __post_init__(self) -> None:
        check_range(self, ("max_gap_m",), low=0.0)
        check_range(self, ("min_support_share",), low=0.0, high=1.0)
