"""Tests of hdmap_core.segment_columns: segments <-> columns exactly, and a slice of segments."""

from __future__ import annotations

import numpy as np

from hdmap_core.segment_columns import columns_to_segments, segment_columns, take_segments
from hdmap_core.steps import Segment, StepResult


def _step(pivot: str, i: int, k: int, *, judged: bool, pose: bool, ids: tuple[str, ...]) -> StepResult:
    return StepResult(
        pivot_id=pivot,
        index=i,
        s_m=2.0 * i + 0.125,
        midpoint=np.array([10.0 + i, -3.25]),
        heading=0.1 * i,
        width_m=12.5 - i,
        valid=i % 3 != 1,
        processed_before=i % 2 == 1,
        lateral_m=np.linspace(-6.0, 6.0, k) + 1e-9 * i,
        types=np.array([1, 2, 3, 1, 2, 3][:k], dtype=np.int64),
        counts=np.arange(k, dtype=np.int64) + i,
        std_m=np.full(k, 0.05 + i),
        drive_ids=ids,
        empty_m=np.array([[-3.25 + i, -1.0], [4.5, 6.0 + i]])[: i % 3] if judged else None,
        pose=np.array([10.25 + i, -4.5]) if pose else None,
    )


def _segments() -> list[Segment]:
    a = Segment(
        "a",
        tuple(_step("a", i, k, judged=i != 2, pose=i != 1, ids=("d1", "d2")[: i + 1]) for i, k in enumerate([5, 0, 3])),
    )
    b = Segment("b", ())
    c = Segment("c", (_step("c", 7, 6, judged=True, pose=True, ids=("d3", "d1")),))
    return [a, b, c]


def _assert_same(got: list[Segment], want: list[Segment]) -> None:
    assert [s.pivot_id for s in got] == [s.pivot_id for s in want]
    for sg, sw in zip(got, want, strict=True):
        assert len(sg.steps) == len(sw.steps)
        for a, b in zip(sg.steps, sw.steps, strict=True):
            for name in ("pivot_id", "index", "s_m", "heading", "width_m", "valid", "processed_before", "drive_ids"):
                assert getattr(a, name) == getattr(b, name), name
            for name in ("midpoint", "lateral_m", "types", "counts", "std_m", "empty_m", "pose"):
                x, y = getattr(a, name), getattr(b, name)
                assert (x is None) == (y is None), name
                if x is not None:
                    np.testing.assert_array_equal(x, y)
                    assert np.asarray(x).dtype == np.asarray(y).dtype, name


def test_columns_round_trip_is_exact():
    segs = _segments()
    c = segment_columns(segs)
    assert c.nsteps.tolist() == [3, 0, 1] and c.k.tolist() == [5, 0, 3, 6]
    assert c.drive_names == ("d1", "d2", "d3") and c.n_drives.tolist() == [1, 2, 2, 2]
    _assert_same(columns_to_segments(c), segs)
    assert columns_to_segments(segment_columns([])) == []


def test_a_slice_of_the_columns_is_the_columns_of_that_slice():
    segs = _segments()
    c = segment_columns(segs)
    for lo, hi in [(0, 1), (1, 2), (1, 3), (2, 3), (0, 3), (2, 2)]:
        _assert_same(columns_to_segments(take_segments(c, lo, hi)), segs[lo:hi])
