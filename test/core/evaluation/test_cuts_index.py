"""intersect_indexed (the segments indexed once, the cuts querying them) finds what intersect_cuts
finds, ordered by cut, then segment."""

import numpy as np

from hdmap_core.evaluation.cuts import index_segments, intersect_cuts, intersect_indexed, segments_of


def _random_lines(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    out = []
    for _ in range(n):
        start = rng.uniform(0, 200, 2)
        steps = rng.normal(0, 3, (int(rng.integers(2, 30)), 2)) + rng.uniform(-4, 4, 2)
        out.append(np.vstack([start, start + np.cumsum(steps, axis=0)]))
    # a line through a vertex on a cut and one along it: the half-open rule and the parallel case
    out.append(np.array([[50.0, 40.0], [50.0, 50.0], [50.0, 60.0]]))
    out.append(np.array([[40.0, 50.0], [60.0, 50.0]]))
    return out


def test_indexed_intersections_are_those_of_intersect_cuts_sorted_by_cut() -> None:
    rng = np.random.default_rng(3)
    segs = segments_of(_random_lines(rng, 60))
    k = 400
    center = rng.uniform(0, 200, (k, 2))
    center[0] = (45.0, 50.0)
    ang = rng.uniform(-np.pi, np.pi, k)
    ang[0] = 0.0
    normal = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    lo, hi = -rng.uniform(1, 15, k), rng.uniform(1, 15, k)
    ci, si, s, u = intersect_cuts(center, normal, lo, hi, segs)
    order = np.lexsort((si, ci))
    ci2, si2, s2, u2 = intersect_indexed(center, normal, lo, hi, index_segments(segs))
    assert len(ci) > 100
    assert np.array_equal(ci[order], ci2) and np.array_equal(si[order], si2)
    assert np.array_equal(s[order], s2) and np.array_equal(u[order], u2)


def test_indexed_with_nothing_to_cut() -> None:
    empty = index_segments(segments_of([]))
    ci, si, s, u = intersect_indexed(np.zeros((2, 2)), np.ones((2, 2)), -np.ones(2), np.ones(2), empty)
    assert len(ci) == len(si) == len(s) == len(u) == 0
    segs = index_segments(segments_of([np.array([[0.0, -1.0], [0.0, 1.0]])]))
    ci, *_ = intersect_indexed(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0), segs)
    assert len(ci) == 0
