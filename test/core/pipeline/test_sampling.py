"""Tests of Sec. IV-A lateral sampling and cut-line refinement (sampling.py)."""

from __future__ import annotations

import numpy as np
import pytest

from hdmap_core.model import Detection, Drive, FeatureType
from hdmap_core.pipeline.preprocess import preprocess
from hdmap_core.pipeline.sampling import SamplingConfig, pivot_walk, refine_cuts, sample_pivot

from former_configs import former
from pipeline_fleet import make_drive, offset_line


def _opposite_drive(drive_id: str) -> Drive:
    """A drive on the other carriageway, 20 m to the right, going the other way.

    ------>  ego carriageway (lines at +-1.75, +-5.25, borders +-6.5)
    <------  opposite carriageway centred at -20 m (lines at -20 +- 1.75)
    """
    s = np.arange(0.0, 301.0, 1.0)
    xy, h = offset_line(s, -20.0)
    dets = []
    for lat in (-18.25, -21.75):
        p, _ = offset_line(s, lat)
        dets.append(Detection(FeatureType.DASHED, p[::-1].copy()))
    yaw = (h[::-1] + 2 * np.pi) % (2 * np.pi) - np.pi
    return Drive(drive_id, xy[::-1].copy(), yaw, np.arange(len(s), dtype=np.int64), tuple(dets))


def test_pivot_walk_steps_every_2m():
    d = make_drive("p", lane=0.0, bias=0.0, s1=101.0)  # chords of the arc: just over 100 m
    s, pts, heading = pivot_walk(d, step_m=2.0)
    assert len(s) == 51
    np.testing.assert_allclose(np.hypot(*np.diff(pts, axis=0).T), 2.0, atol=1e-3)
    np.testing.assert_allclose(heading, s / 2000.0, atol=1e-4)  # arc of radius 2000 m


def test_opposite_direction_samples_dropped():
    pivot = make_drive("p", lane=0.0, bias=0.0)
    drives = [pivot, _opposite_drive("o")]
    idx = preprocess(drives)
    cfg = former(SamplingConfig, initial_half_length_m=30.0, min_border_support=1)
    ps = sample_pivot(idx, pivot, config=cfg)
    assert ps.n_steps > 100
    assert len(ps.drive) > 0
    assert set(ps.drive.tolist()) == {0}  # nothing of the opposite drive survives
    # ... although its lines do cross the initial cut: with the filter off they are sampled.
    wide = former(
        SamplingConfig,
        initial_half_length_m=30.0,
        max_heading_diff_deg=180.0,
        min_border_support=1,
        max_width_m=60.0,
        margin_m=20.0,
    )
    ps2 = sample_pivot(idx, pivot, config=wide)
    assert 1 in set(ps2.drive.tolist())


@pytest.mark.parametrize("lane", [-3.5, 0.0, 3.5])
def test_refinement_finds_borders(lane):
    pivot = make_drive("p", lane=lane, bias=0.0)
    others = [make_drive(f"d{i}", lane=0.0, bias=b) for i, b in enumerate([0.2, -0.2, 0.1])]
    # A parallel road 12 m to the left (its border at +12 m) must be cut away.
    extra = make_drive("x", lane=0.0, bias=0.0, lines=((12.0, FeatureType.ROAD_BORDER), (15.0, FeatureType.SOLID)))
    idx = preprocess([pivot, *others, extra])
    cfg = former(SamplingConfig, margin_m=0.5, spread_factor=2.0)
    ps = sample_pivot(idx, pivot, config=cfg)
    q = ps.n_steps // 2
    lat = ps.lateral_m[ps.ptr[q] : ps.ptr[q + 1]]
    types = ps.types[ps.ptr[q] : ps.ptr[q + 1]]
    # Midpoint on the road centre, width = border to border + spread and constant margins.
    _, h = offset_line(np.array([ps.s_m[q]]), 0.0)
    centre, _ = offset_line(np.array([ps.s_m[q]]), 0.0)
    off = np.dot(ps.midpoint[q] - centre[0], [-np.sin(h[0]), np.cos(h[0])])
    assert off == pytest.approx(0.0, abs=0.05)
    assert 13.0 + 2 * 0.5 <= ps.width_m[q] <= 13.0 + 2 * (0.5 + 2.0 * 0.2) + 0.05
    assert lat.max() < 8.0 and lat.min() > -8.0
    assert (types == FeatureType.ROAD_BORDER).sum() == 8  # 4 drives x 2 borders
    assert not np.any(np.isclose(lat, 12.0, atol=1.0))


def test_refinement_smooths_over_missing_borders():
    # Steps 0..19 see borders at +-6.5; steps 20..39 see none: the width is carried over.
    q = np.repeat(np.arange(20), 4)
    t = np.tile([6.5, 6.5, -6.5, -6.5], 20)
    types = np.full(len(q), FeatureType.ROAD_BORDER)
    mid, width = refine_cuts(q, t, types, 40, config=former(SamplingConfig, margin_m=0.5, spread_factor=0.0))
    np.testing.assert_allclose(width, 14.0)
    np.testing.assert_allclose(mid, 0.0, atol=1e-12)


def test_skip_mask_skips_steps():
    pivot = make_drive("p", lane=0.0, bias=0.0, s1=100.0)
    idx = preprocess([pivot])
    s, _, _ = pivot_walk(pivot, step_m=2.0)
    skip = s < 50.0
    ps = sample_pivot(idx, pivot, config=former(SamplingConfig, min_border_support=1), skip=skip)
    counts = np.diff(ps.ptr)
    assert np.all(counts[skip] == 0)
    assert np.all(counts[~skip] == 6)


def test_cache_gives_the_same_samples():
    pivot = make_drive("p", lane=0.0, bias=0.0, s1=120.0)
    others = [make_drive(f"d{i}", lane=3.5, bias=b) for i, b in enumerate([0.3, -0.2])]
    idx = preprocess([pivot, *others])
    cfg = former(SamplingConfig, min_border_support=1)
    s, _, _ = pivot_walk(pivot, step_m=2.0)
    cache: dict = {}
    first = sample_pivot(idx, pivot, config=cfg, skip=s > 60.0, cache=cache)  # fills half
    again = sample_pivot(idx, pivot, config=cfg, cache=cache)  # computes the rest only
    plain = sample_pivot(idx, pivot, config=cfg)
    assert first.ptr[-1] < plain.ptr[-1]
    for name in ("ptr", "lateral_m", "types", "drive", "drive_s_m", "width_m"):
        np.testing.assert_array_equal(getattr(again, name), getattr(plain, name))


def test_border_support_fraction_ignores_a_few_inner_border_samples():
    # 20 drives see the borders at +-6.5; two misclassify a dashed line at +1.75 as border.
    q = np.zeros(44, dtype=np.int64)
    t = np.concatenate([np.full(20, 6.5), np.full(20, -6.5), [1.75, 1.75, 1.8, 1.7]])
    types = np.full(44, FeatureType.ROAD_BORDER)
    drive = np.concatenate([np.arange(20), np.arange(20), [0, 1, 2, 3]])
    cfg = former(SamplingConfig, spread_factor=0.0, margin_m=0.5)
    _, w_plain = refine_cuts(q, t, types, 1, config=cfg, drive=drive)
    _, w_frac = refine_cuts(
        q,
        t,
        types,
        1,
        config=former(SamplingConfig, spread_factor=0.0, margin_m=0.5, min_border_support_fraction=0.25),
        drive=drive,
    )
    assert w_plain[0] < 10.0  # cut short at the misclassified line
    assert w_frac[0] == pytest.approx(14.0)


def test_open_side_reaches_the_last_line_before_the_median():
    """A border on the right only (a median without a barrier on the left): the lines of our four
    lanes reach +9.5 m, the opposite carriageway's inner line (seen by our drives, so kept by
    heading) lies 7 m further. The default width (16 m) clips the +9.5 m line; the open-side
    chain ends the cut just after it and stops at the median."""
    lines = [
        (-7.0, FeatureType.ROAD_BORDER),
        (-4.0, FeatureType.SOLID),
        (-0.5, FeatureType.DASHED),
        (3.0, FeatureType.DASHED),
        (6.5, FeatureType.DASHED),
        (9.5, FeatureType.SOLID),
        (16.5, FeatureType.SOLID),
    ]
    n_steps, n_drives = 30, 5
    q = np.repeat(np.arange(n_steps), n_drives * len(lines))
    t = np.tile(np.repeat([lat for lat, _ in lines], n_drives), n_steps).astype(float)
    types = np.tile(np.repeat([int(ty) for _, ty in lines], n_drives), n_steps)
    drive = np.tile(np.arange(n_drives), n_steps * len(lines))
    cfg = former(SamplingConfig, spread_factor=0.0, margin_m=0.5)
    mid, width = refine_cuts(q, t, types, n_steps, config=cfg, drive=drive)
    assert np.all(mid + 0.5 * width < 9.5)  # paper: the default width cuts the edge line off
    mid, width = refine_cuts(
        q,
        t,
        types,
        n_steps,
        config=former(SamplingConfig, spread_factor=0.0, margin_m=0.5, open_side_gap_m=4.0),
        drive=drive,
    )
    np.testing.assert_allclose(mid + 0.5 * width, 10.0)  # the edge line + margin
    np.testing.assert_allclose(mid - 0.5 * width, -7.5)  # the border side is unchanged
    # A border seen on a side sets that side as before (here beyond the chain's gap).
    types2 = np.where(t == 16.5, int(FeatureType.ROAD_BORDER), types)
    mid, width = refine_cuts(
        q,
        t,
        types2,
        n_steps,
        config=former(SamplingConfig, spread_factor=0.0, margin_m=0.5, open_side_gap_m=4.0),
        drive=drive,
    )
    np.testing.assert_allclose(mid + 0.5 * width, 17.0)


def test_far_border_one_drive_saw_kept_with_outer_border_reach():
    """Two drives (carla_town06_30_s2, y -135): both see the right border and the lines near
    them; only drive b sees the far left border at +8 m, and nobody the solid line at +5.25 m
    before it. One border sample cannot be the first border (support 2), and the open side's
    chain stops at the 6 m gap after +1.75 m: the border is cut away. With
    ``outer_border_reach`` the side keeps its samples up to that border (nothing lies beyond
    it); the refined cut itself (midpoint, width: the topology) is unchanged."""
    B, S, D = FeatureType.ROAD_BORDER, FeatureType.SOLID, FeatureType.DASHED
    a = make_drive("a", lane=-3.5, bias=0.0, lines=((-6.5, B), (-5.25, S), (-1.75, D), (1.75, D)))
    b = make_drive("b", lane=0.0, bias=0.0, lines=((-6.5, B), (-1.75, D), (1.75, D), (8.0, B)))
    idx = preprocess([a, b])
    base = former(SamplingConfig, open_side_gap_m=4.0, spread_factor=0.0, margin_m=0.5)
    q = 40
    plain = sample_pivot(idx, a, config=base)
    reach = sample_pivot(
        idx,
        a,
        config=former(SamplingConfig, open_side_gap_m=4.0, spread_factor=0.0, margin_m=0.5, outer_border_reach=True),
    )
    lat0, lat1 = (ps.lateral_m[ps.ptr[q] : ps.ptr[q + 1]] for ps in (plain, reach))
    ty1 = reach.types[reach.ptr[q] : reach.ptr[q + 1]]
    centre, h = offset_line(np.array([plain.s_m[q]]), 0.0)
    n = np.array([-np.sin(h[0]), np.cos(h[0])])
    far0 = lat0 + (plain.midpoint[q] - centre[0]) @ n  # positions from the road centre
    far1 = lat1 + (reach.midpoint[q] - centre[0]) @ n
    assert not np.any(np.isclose(far0, 8.0, atol=0.3))
    assert np.sum(np.isclose(far1, 8.0, atol=0.3) & (ty1 == B)) == 1
    assert len(lat1) == len(lat0) + 1
    np.testing.assert_array_equal(reach.width_m, plain.width_m)
    np.testing.assert_array_equal(reach.midpoint, plain.midpoint)
    # A sample beyond the lone border (a parallel road's line): it is no road edge, nothing added.
    c = make_drive("c", lane=0.0, bias=0.0, lines=((12.0, S),))
    idx3 = preprocess([a, b, c])
    beyond = sample_pivot(
        idx3,
        a,
        config=former(SamplingConfig, open_side_gap_m=4.0, spread_factor=0.0, margin_m=0.5, outer_border_reach=True),
    )
    lat3 = beyond.lateral_m[beyond.ptr[q] : beyond.ptr[q + 1]] + (beyond.midpoint[q] - centre[0]) @ n
    assert not np.any(np.isclose(lat3, 8.0, atol=0.3)) and not np.any(np.isclose(lat3, 12.0, atol=0.3))
    # With a border of two drives on that side, the first border ends the cut as before.
    d = make_drive("d", lane=0.0, bias=0.0, lines=((4.0, B),))
    e = make_drive("e", lane=0.0, bias=0.0, lines=((4.0, B),))
    idx4 = preprocess([a, b, d, e])
    first = sample_pivot(
        idx4,
        a,
        config=former(SamplingConfig, open_side_gap_m=4.0, spread_factor=0.0, margin_m=0.5, outer_border_reach=True),
    )
    lat4 = first.lateral_m[first.ptr[q] : first.ptr[q + 1]] + (first.midpoint[q] - centre[0]) @ n
    assert not np.any(np.isclose(lat4, 8.0, atol=0.3)) and np.sum(np.isclose(lat4, 4.0, atol=0.3)) == 2


def test_pivot_beyond_its_one_sided_cut_is_off_cut():
    """carla_town06_30_s1, a junction: the only supported border is one 20 m to the left of the
    pivot, the right side has none, so the one-sided midpoint (border minus half the default
    width) puts the cut 12.5 m left of the pivot, which lies 4.5 m beyond its right end. With
    ``max_pivot_outside_m`` such a step is off its pivot's road; a road bordered on both sides
    (the pivot inside its cut) never is."""
    B, D = FeatureType.ROAD_BORDER, FeatureType.DASHED
    far = [make_drive(k, lane=0.0, bias=0.0, lines=((20.0, B), (16.5, D))) for k in "ab"]
    ps = sample_pivot(preprocess(far), far[0], config=former(SamplingConfig, spread_factor=0.0, margin_m=0.5))
    q = ps.n_steps // 2
    centre, h = offset_line(np.array([ps.s_m[q]]), 0.0)
    mid = (ps.midpoint[q] - centre[0]) @ np.array([-np.sin(h[0]), np.cos(h[0])])
    assert mid == pytest.approx(20.5 - 8.0, abs=0.05) and ps.width_m[q] == pytest.approx(16.0)
    assert not ps.off_cut.any()  # the paper's reading: no check
    checked = sample_pivot(
        preprocess(far), far[0], config=former(SamplingConfig, spread_factor=0.0, margin_m=0.5, max_pivot_outside_m=2.0)
    )
    assert checked.off_cut[q] and checked.off_cut.mean() > 0.9
    assert not sample_pivot(
        preprocess(far), far[0], config=former(SamplingConfig, spread_factor=0.0, margin_m=0.5, max_pivot_outside_m=5.0)
    ).off_cut.any()
    # the check is made where the pivot is in the frame of its samples: an offset that moves
    # every drive, the pivot too, 3 m to the left moves the road and the pivot together
    for margin in (2.0, 5.0):
        cfg = former(SamplingConfig, spread_factor=0.0, margin_m=0.5, max_pivot_outside_m=margin)
        moved = sample_pivot(preprocess(far), far[0], config=cfg, shift=lambda d, s_m: np.full(len(d), 3.0))
        np.testing.assert_array_equal(moved.off_cut, sample_pivot(preprocess(far), far[0], config=cfg).off_cut)
    both = [make_drive(k, lane=3.5, bias=0.0) for k in "ab"]  # borders at +-6.5, pivot in the left lane
    assert not sample_pivot(
        preprocess(both), both[0], config=former(SamplingConfig, max_pivot_outside_m=0.0)
    ).off_cut.any()


def test_pivot_pose_is_corrected_like_its_samples():
    """``PivotSamples.pose``: the pivot point moved along the cut by the offset the ``shift``
    gives the pivot drive at its own travelled distance (the samples get the same); without a
    shift it is the point itself."""
    pivot = make_drive("p", lane=0.0, bias=0.0, s1=100.0)
    other = make_drive("o", lane=3.5, bias=0.0, s1=100.0)
    idx = preprocess([other, pivot])  # the pivot is drive 1
    cfg = former(SamplingConfig, min_border_support=1)
    plain = sample_pivot(idx, pivot, config=cfg)
    np.testing.assert_array_equal(plain.pose, plain.point)
    calls = []

    def shift(drive, s_m):
        calls.append(drive.copy())
        return np.where(drive == 1, 0.7 + 0.001 * s_m, -0.2)

    moved = sample_pivot(idx, pivot, config=cfg, shift=shift)
    normal = np.stack([-np.sin(moved.heading), np.cos(moved.heading)], axis=1)
    np.testing.assert_allclose(moved.pose, moved.point + (0.7 + 0.001 * moved.s_m)[:, None] * normal)
    assert any(np.all(c == 1) and len(c) == moved.n_steps for c in calls)
