"""Tests of the shared array math (geometry.py)."""

from __future__ import annotations

import numpy as np
import pytest

from hdmap_core.geometry import (
    arc_length,
    cut_segment_intersections,
    dense_points,
    left_normal,
    point_headings,
    rdp_mask_many,
    resample_by_distance,
    resample_evenly,
    split_long_segments,
    true_runs,
    turn_left,
    unit_tangents,
    wrap_angle,
)


def _rdp_reference(pts: np.ndarray, eps: float) -> list[int]:
    """Textbook recursive RDP, indices kept."""

    def rec(i: int, j: int) -> list[int]:
        if j - i < 2:
            return [i, j]
        a, b = pts[i], pts[j]
        ab = b - a
        lab = np.hypot(*ab)
        d = np.abs(ab[0] * (pts[i + 1 : j, 1] - a[1]) - ab[1] * (pts[i + 1 : j, 0] - a[0])) / lab
        k = int(np.argmax(d))
        if d[k] <= eps:
            return [i, j]
        m = i + 1 + k
        return rec(i, m)[:-1] + rec(m, j)

    return rec(0, len(pts) - 1)


def test_rdp_drops_collinear_points_keeps_corner():
    #   (0,0) ---- (5,0) ---- (10,0)
    #                           \
    #                            (10,-5)
    pts = np.array([[0, 0], [2.5, 0.01], [5, 0], [7.5, -0.01], [10, 0], [10, -2.5], [10, -5]], float)
    keep = rdp_mask_many(pts, np.array([0]), 0.05)
    np.testing.assert_array_equal(np.flatnonzero(keep), [0, 4, 6])


@pytest.mark.parametrize("eps", [0.01, 0.1, 0.5])
def test_rdp_many_polylines_equal_reference(eps):
    rng = np.random.default_rng(3)
    polys = [np.cumsum(rng.normal(0, 1, (n, 2)), axis=0) for n in (2, 3, 7, 25, 60)]
    starts = np.cumsum([0] + [len(p) for p in polys[:-1]])
    keep = rdp_mask_many(np.concatenate(polys), starts, eps)
    for p, s0 in zip(polys, starts):
        got = np.flatnonzero(keep[s0 : s0 + len(p)])
        np.testing.assert_array_equal(got, _rdp_reference(p, eps))


def test_split_long_segments_limits_length_and_keeps_shape():
    xy = np.array([[0, 0], [25, 0], [25, 3], [0, 0], [0, 9]], float)
    starts = np.array([0, 3])
    out, new_starts = split_long_segments(xy, starts, 10.0)
    ends = np.concatenate([new_starts[1:], [len(out)]])
    for a, b in zip(new_starts, ends):
        seg = np.hypot(*np.diff(out[a:b], axis=0).T)
        assert seg.max() <= 10.0 + 1e-9
    np.testing.assert_allclose(out[new_starts], xy[starts])
    assert arc_length(out[new_starts[0] : new_starts[1]])[-1] == pytest.approx(28.0)


def test_cut_intersections_match_brute_force():
    rng = np.random.default_rng(1)
    n = 4000
    o = rng.uniform(-10, 10, (n, 2))
    ang = rng.uniform(-np.pi, np.pi, n)
    d = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    h = rng.uniform(1, 10, n)
    a = rng.uniform(-10, 10, (n, 2))
    b = a + rng.normal(0, 4, (n, 2))
    hit, t, u = cut_segment_intersections(o, d, h, a, b)
    assert 0 < hit.sum() < n  # both outcomes occur
    # Brute force: solve the 2x2 system per pair.
    for i in range(0, n, 37):
        m = np.array([d[i], -(b[i] - a[i])]).T
        tt, uu = np.linalg.solve(m, a[i] - o[i])
        expect = 0 <= uu < 1 and abs(tt) <= h[i]
        assert hit[i] == expect
        if expect:
            np.testing.assert_allclose(o[i] + t[i] * d[i], a[i] + u[i] * (b[i] - a[i]), atol=1e-9)
            assert t[i] == pytest.approx(tt)


def test_resample_and_wrap():
    pts, s = resample_by_distance(np.array([[0, 0], [0, 0], [5, 0]], float), 2.0)
    np.testing.assert_allclose(s, [0, 2, 4])
    np.testing.assert_allclose(pts[:, 0], [0, 2, 4])
    np.testing.assert_allclose(wrap_angle(np.array([3 * np.pi, -np.pi / 2])), [-np.pi, -np.pi / 2])


def test_resample_evenly_keeps_both_ends():
    # 5 m with at most 2 m steps: 3 steps of 5/3 m, the end point kept (resample_by_distance
    # stops at 4 m); the duplicate point does not disturb the interpolation
    pts = resample_evenly(np.array([[0, 0], [0, 0], [3, 0], [3, 2]], float), 2.0)
    np.testing.assert_allclose(pts, [[0, 0], [5 / 3, 0], [3, 1 / 3], [3, 2]], atol=1e-12)
    np.testing.assert_allclose(resample_evenly(np.array([[0, 0], [1, 0]], float), 2.0), [[0, 0], [1, 0]])
    # degenerate lines: their first point alone
    np.testing.assert_allclose(resample_evenly(np.array([[1, 2], [1, 2]], float), 2.0), [[1, 2]])
    np.testing.assert_allclose(resample_evenly(np.array([[1, 2]], float), 2.0), [[1, 2]])
    assert resample_evenly(np.zeros((0, 2)), 2.0).shape == (0, 2)


def test_dense_points_joins_the_lines_resampled_and_leaves_out_those_of_no_length():
    a = np.array([[0, 0], [3, 0]], float)
    b = [[10, 0], [10, 1]]  # a list, as map features' points may come
    got = dense_points([a, np.array([[5, 5], [5, 5]], float), np.array([[7, 7]], float), b], 1.0)
    np.testing.assert_allclose(got, np.concatenate([resample_evenly(a, 1.0), [[10, 0], [10, 1]]]))
    assert dense_points([], 1.0).shape == (0, 2)


def test_rdp_closed_polyline_measures_from_the_end_point():
    # start == end: the chord has length 0, so distances are to that point; the far corner stays
    pts = np.array([[0, 0], [4, 0.01], [4, 4], [0, 4], [0, 0]], float)
    keep = rdp_mask_many(pts, np.array([0]), 0.05)
    assert keep[0] and keep[-1] and keep[2]
    assert keep.sum() >= 4  # a square needs its corners


def test_split_long_segments_is_bounded_by_max_pieces():
    from hdmap_core.geometry import split_long_segments

    xy = np.array([[0.0, 0.0], [1e12, 0.0], [1e12, 1e200], [1e12, 1e200 + 25.0]])
    out, starts = split_long_segments(xy, np.array([0]), 10.0, max_pieces=1000)
    assert len(out) <= 1 + 1000 + 1 + 1000 + 1 and np.all(np.isfinite(out))
    np.testing.assert_array_equal(starts, [0])
    np.testing.assert_array_equal(out[-1], xy[-1])
    # segments within the cap are split as before: 25 m at 10 m -> 3 pieces
    near, _ = split_long_segments(np.array([[0.0, 0.0], [25.0, 0.0]]), np.array([0]), 10.0, max_pieces=1000)
    np.testing.assert_allclose(near[:, 0], [0.0, 25 / 3, 50 / 3, 25.0])


def test_point_headings_follow_the_tangent_of_an_arc():
    """On a circle of radius 50 m run anticlockwise, the heading at each point is its polar
    angle + 90 degrees (central differences of even points are exact in direction), and a
    straight line's ends take the segment's heading."""
    phi = np.linspace(0.2, 1.2, 11)
    arc = 50.0 * np.stack([np.cos(phi), np.sin(phi)], axis=1)
    yaw = point_headings(arc)
    assert np.allclose(yaw[1:-1], phi[1:-1] + np.pi / 2, atol=1e-12)
    assert np.allclose(point_headings(np.array([[0.0, 0.0], [1.0, 1.0]])), np.pi / 4)


def test_true_runs_are_the_half_open_ranges_of_the_true_values():
    mask = np.array([True, True, False, False, True, False, True])
    assert true_runs(mask) == [(0, 2), (4, 5), (6, 7)]
    assert true_runs(np.zeros(3, dtype=bool)) == [] and true_runs(np.zeros(0, dtype=bool)) == []


def test_unit_tangents_and_normals_of_an_arc():
    """The circle of radius 50 m run anticlockwise: the unit tangent at each point is along its
    heading, the left normal points to the centre; turning a tangent left is the left normal of
    its heading. A polyline standing still has zero tangents, a single point one zero.

        y
        |   . <- normal (to the centre)
        | .'  ^ tangent
        o-----------> x
    """
    phi = np.linspace(0.2, 1.2, 11)
    arc = 50.0 * np.stack([np.cos(phi), np.sin(phi)], axis=1)
    t = unit_tangents(arc)
    yaw = point_headings(arc)
    np.testing.assert_allclose(np.linalg.norm(t, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(t, np.stack([np.cos(yaw), np.sin(yaw)], axis=1), atol=1e-12)
    left = turn_left(t)
    np.testing.assert_allclose(left, left_normal(yaw), atol=1e-12)
    np.testing.assert_allclose(left[1:-1], -arc[1:-1] / 50.0, atol=1e-12)  # to the centre
    assert left_normal(0.0).shape == (2,) and np.allclose(left_normal(0.0), [0.0, 1.0])
    np.testing.assert_array_equal(unit_tangents(np.zeros((3, 2))), np.zeros((3, 2)))
    np.testing.assert_array_equal(unit_tangents(np.ones((1, 2))), np.zeros((1, 2)))
