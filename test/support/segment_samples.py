"""Segments of a road running east (heading 0), for the connection and stitching tests (not a
test module): a maximum's lateral position is its world y (plus the midpoint's y)."""

from __future__ import annotations

import numpy as np

from hdmap_core.graph.connection import connect_segment
from hdmap_core.graph.connection_config import ConnectionConfig
from hdmap_core.model import FeatureType
from hdmap_core.steps import Segment, StepResult

from former_configs import former

B, S, D = int(FeatureType.ROAD_BORDER), int(FeatureType.SOLID), int(FeatureType.DASHED)
LINES = ([-3.5, 0.0, 3.5], [S, D, B])


def step(pivot: str, i: int, x: float, lateral, types, *, y_mid: float = 0.0, processed_before=False, counts=None):
    k = len(lateral)
    return StepResult(
        pivot_id=pivot,
        index=i,
        s_m=2.0 * i,
        midpoint=np.array([x, y_mid]),
        heading=0.0,
        width_m=10.0,
        valid=True,
        processed_before=processed_before,
        lateral_m=np.asarray(lateral, float) - y_mid,
        types=np.asarray(types),
        counts=np.asarray(counts if counts is not None else [4] * k),
        std_m=np.full(k, 0.15),
        drive_ids=(pivot, f"{pivot}-other"),
    )


def road(pivot: str, x0: float, n: int, lines=LINES, *, y_mid: float = 0.0, processed=()) -> Segment:
    """n steps from x0 eastwards, 2 m apart; ``processed``: step indices marked processed_before."""
    return Segment(
        pivot,
        tuple(
            step(pivot, i, x0 + 2.0 * i, lines[0], lines[1], y_mid=y_mid, processed_before=i in processed)
            for i in range(n)
        ),
    )


def conn(seg: Segment):
    """The segment's graph with the connection's first implementation (``former``: the rules
    these samples were drawn for)."""
    return connect_segment(seg, config=former(ConnectionConfig))


def point_step(pivot: str, i: int, x: float, y: float = 0.0) -> StepResult:
    """A valid step with its midpoint at (x, y) (two maxima 1 m either side, drive "a"): for the
    tests of which steps a tile keeps (``select_steps``, ``cut_into_tiles``), where only the
    position counts."""
    return StepResult(
        pivot_id=pivot,
        index=i,
        s_m=2.0 * i,
        midpoint=np.array([x, y]),
        heading=0.0,
        width_m=10.0,
        valid=True,
        processed_before=False,
        lateral_m=np.array([-1.0, 1.0]),
        types=np.array([1, 2]),
        counts=np.array([3, 3]),
        std_m=np.array([0.1, 0.1]),
        drive_ids=("a",),
    )


def step_runs(segments) -> list[tuple[str, list[int]]]:
    """(pivot id, step indices) of each segment: what a selection of steps kept, comparable."""
    return [(s.pivot_id, [st.index for st in s.steps]) for s in segments]


def assert_same_steps(want, got) -> None:
    """Two sequences of steps equal field for field, arrays exactly (a round trip through a blob,
    a message or the columns)."""
    want, got = list(want), list(got)
    assert len(want) == len(got)
    for a, b in zip(want, got, strict=True):
        fields = ("pivot_id", "index", "s_m", "heading", "width_m", "valid", "processed_before", "drive_ids")
        assert tuple(getattr(a, f) for f in fields) == tuple(getattr(b, f) for f in fields)
        for attr in ("midpoint", "lateral_m", "types", "counts", "std_m"):
            np.testing.assert_array_equal(getattr(a, attr), getattr(b, attr))
        for attr in ("empty_m", "pose"):  # optional arrays
            assert (getattr(a, attr) is None) == (getattr(b, attr) is None)
            if getattr(a, attr) is not None:
                np.testing.assert_array_equal(getattr(a, attr), getattr(b, attr))
