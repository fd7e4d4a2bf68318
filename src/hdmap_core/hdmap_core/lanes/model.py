"""The lane-level view of a map: lanes (lanelet-sized pieces) and the boundary pieces they share.

A ``Boundary`` is one piece of one map feature (marking or road border) between two cross
sections; the lanes on both sides of it refer to the same piece, so a lane change crosses one
shared line. Consecutive pieces share their end nodes (``start_node`` / ``end_node``): lane B
follows lane A when B's boundaries start at the nodes where A's end (Lanelet2's rule). All
coordinates are map frame [m], ordered in driving direction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hdmap_core.model import FeatureType

__all__ = ["Boundary", "Lane", "LaneMap"]


@dataclass(frozen=True)
class Boundary:
    """One piece of a boundary line, shared by the lanes on its two sides.

    Attributes:
        id: stable id (hash of the feature id and the first cross section).
        feature_id: the map feature this piece follows.
        type: the feature's type (solid, dashed, road border).
        points: (N, 2) [m], N >= 2, in driving direction; the first and last point are the
            positions of ``start_node`` and ``end_node``.
        start_node, end_node: ids of the end nodes, shared with the preceding / following pieces.
        inferred: no map feature: a dashed line inferred in a strip of two or more lanes' width,
            or a divider continued through a taper (``feature_id`` 0).
    """

    id: int
    feature_id: int
    type: FeatureType
    points: np.ndarray
    start_node: int
    end_node: int
    inferred: bool = False


@dataclass(frozen=True)
class Lane:
    """One lane piece: the drivable strip between two adjacent boundaries.

    Attributes:
        id: stable id (hash of its two boundary feature ids and its first cross section).
        centerline: (N, 2) [m] in driving direction, midway between the boundaries.
        width: (N,) distance between the boundaries at the centerline points [m].
        left_boundary, right_boundary: ``Boundary.id`` of the two sides (seen in driving direction).
        left_feature, right_feature: the map feature ids of the two sides.
        left_type, right_type: their types; a lane change is allowed across a dashed side only.
        successors, predecessors: lane ids; several at splits and merges.
        left, right: the neighbour lane sharing the left / right boundary piece, or None.
    """

    id: int
    centerline: np.ndarray
    width: np.ndarray
    left_boundary: int
    right_boundary: int
    left_feature: int
    right_feature: int
    left_type: FeatureType
    right_type: FeatureType
    successors: tuple[int, ...] = ()
    predecessors: tuple[int, ...] = ()
    left: int | None = None
    right: int | None = None

    @property
    def length_m(self) -> float:
        """Length of the centerline [m]."""
        return float(np.linalg.norm(np.diff(self.centerline, axis=0), axis=1).sum())

    @property
    def change_left(self) -> bool:
        """A lane change to the left neighbour is allowed (left side dashed)."""
        return self.left is not None and self.left_type == FeatureType.DASHED

    @property
    def change_right(self) -> bool:
        """A lane change to the right neighbour is allowed (right side dashed)."""
        return self.right is not None and self.right_type == FeatureType.DASHED


@dataclass(frozen=True)
class LaneMap:
    """Lanes, the boundary pieces they share and the positions of the shared end nodes.

    Attributes:
        lanes: the lane pieces, sorted by id.
        boundaries: the boundary pieces, sorted by id.
        nodes: end node id -> (2,) position [m].
    """

    lanes: tuple[Lane, ...] = ()
    boundaries: tuple[Boundary, ...] = ()
    nodes: dict[int, np.ndarray] | None = None

    def lane(self, lane_id: int) -> Lane:
        """The lane of ``lane_id`` (KeyError if none)."""
        return self._lanes_by_id()[lane_id]

    def boundary(self, boundary_id: int) -> Boundary:
        """The boundary piece of ``boundary_id`` (KeyError if none)."""
        return {b.id: b for b in self.boundaries}[boundary_id]

    def polygon(self, lane: Lane) -> np.ndarray:
        """(M, 2) ring of ``lane``: its left boundary forward, then its right boundary backward [m]."""
        b = {x.id: x for x in self.boundaries}
        return np.concatenate([b[lane.left_boundary].points, b[lane.right_boundary].points[::-1]])

    def _lanes_by_id(self) -> dict[int, Lane]:
        return {lane.id: lane for lane in self.lanes}
