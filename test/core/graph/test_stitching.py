"""Inter-segment connection (Sec. VI): hierarchical graph, stitching, ids, incremental updates.

Roads run east (heading 0): a maximum's lateral position is its world y (plus the midpoint's y).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from hdmap_core.errors import ConfigError, HdmapError
from hdmap_core.graph.connection import connect_segment
from hdmap_core.graph.connection_config import ConnectionConfig
from hdmap_core.graph.from_hdmap import graph_from_hdmap
from hdmap_core.graph.map_graph import MapGraph, to_hdmap
from hdmap_core.graph.map_graph import stitch as _stitch
from hdmap_core.graph.stitch_config import StitchConfig
from hdmap_core.model import FeatureType, HDMap
from hdmap_core.pipeline import presets
from hdmap_core.steps import Segment, StepResult

from former_configs import former, former_paper, former_replace
from segment_samples import LINES, B, D, S, conn, road, step


def stitch(graphs, *, config: StitchConfig | None = None, **kw):
    """``map_graph.stitch`` with the stitcher's first implementation (``former``) unless a config
    is given: the rules these tests were drawn for."""
    return _stitch(graphs, config=former(StitchConfig) if config is None else config, **kw)


DEFAULT = presets.preset("default").stitching  # the default preset's stitching options


def by_type(m: HDMap, t: int):
    return [f for f in m.features if f.type == t]


def assert_one_continuous(m: HDMap, x_from: float, x_to: float) -> None:
    """Exactly one polyline per line, spanning x_from..x_to with ~2 m spacing, no duplicates."""
    for t, y in ((S, -3.5), (D, 0.0), (B, 3.5)):
        fs = by_type(m, t)
        assert len(fs) == 1, f"type {t}: {len(fs)} polylines"
        p = fs[0].points
        np.testing.assert_allclose(p[:, 1], y, atol=1e-9)
        assert p[0, 0] == pytest.approx(x_from) and p[-1, 0] == pytest.approx(x_to)
        dx = np.diff(p[:, 0])
        assert np.all(dx > 0) and dx.max() <= 2.0 + 1e-9


def test_consecutive_segments_make_one_polyline_per_line():
    r"""a: x 0..98 | b: x 100..198   ->  one feature per line, 0..198."""
    m = stitch([conn(road("a", 0.0, 50)), conn(road("b", 100.0, 50))])
    assert_one_continuous(m, 0.0, 198.0)
    assert len(m.topology) == 100
    # the topology chain runs through: one node without successor
    assert sum(1 for t in m.topology if not t.successors) == 1


def test_feature_fields_filled_from_step_results():
    seg = Segment("a", tuple(step("a", i, 2.0 * i, [0.0], [D], counts=[i + 3]) for i in range(20)))
    m = stitch([conn(seg)])
    (f,) = m.features
    np.testing.assert_array_equal(f.drive_count, np.arange(3, 23))
    np.testing.assert_allclose(f.lateral_std, 0.15)
    assert f.points.shape == (20, 2) and f.drive_count.shape == (20,) and f.lateral_std.shape == (20,)
    assert m.drive_ids == ("a", "a-other")
    for t in m.topology:
        assert t.features == (f.id,)
        assert t.width == pytest.approx(10.0)


def test_overlap_marked_processed_before_stitched_without_duplicates():
    r"""a: x 0..98
    b: x 60..158, its steps at x 60..98 processed_before (RULE 4) -> joined at x 98 -> 100."""
    b = road("b", 60.0, 50, y_mid=0.4, processed=set(range(20)))
    m = stitch([conn(road("a", 0.0, 50)), conn(b)])
    assert_one_continuous(m, 0.0, 158.0)


@pytest.mark.parametrize("order", ["together", "a_then_b", "b_then_a"])
def test_unmarked_overlap_is_trimmed_to_one_copy(order):
    """Two pivots map x 60..98 twice (no processed_before): one copy survives, lines continuous."""
    ga, gb = conn(road("a", 0.0, 50)), conn(road("b", 60.0, 50, y_mid=0.4))
    if order == "together":
        m = stitch([ga, gb])
    else:
        first, second = (ga, gb) if order == "a_then_b" else (gb, ga)
        mg = MapGraph([first])
        mg.integrate([second])
        m = mg.to_hdmap()
    assert_one_continuous(m, 0.0, 158.0)


@pytest.mark.parametrize("order", ["together", "long_then_short", "short_then_long"])
def test_trim_keeps_the_longer_piece_at_an_overlap(order):
    r"""a: x 0..98 (50 steps)      b: x 97 (one step: the last metres a second pivot saw)
    RULE trim_keep_longer: b gives way, so every line still reaches x 98; trimming a's end for b
    instead leaves b as a one-step speck (no polyline), and the lines end short of the road's end."""
    ga, gb = conn(road("a", 0.0, 50)), conn(road("b", 97.0, 1, y_mid=0.4))
    if order == "together":
        m = stitch([ga, gb])
    else:
        first, second = (ga, gb) if order == "long_then_short" else (gb, ga)
        mg = MapGraph([first])
        mg.integrate([second])
        m = mg.to_hdmap()
    assert_one_continuous(m, 0.0, 98.0)
    old = stitch([ga, gb], config=former(StitchConfig, trim_keep_longer=False))
    assert max(f.points[-1, 0] for f in old.features) < 98.0


def test_trim_does_not_give_way_to_a_place_trimmed_later():
    r"""b: x -2 (one step)   c: x -1.1 (one step)   a: x 0..98 (50 steps)
    c lies on a's first place and b on c's, but b is 2 m before a: the map starts at x -2 only if
    b is not trimmed for c, which gives way to a itself when its turn comes (RULE
    trim_lookahead). Without the look ahead b gives way to c, then c to a, and x -2..0 is lost
    (esmini_soderleden_40_s7's first cut)."""
    gb, gc, ga = conn(road("b", -2.0, 1)), conn(road("c", -1.1, 1, y_mid=0.1)), conn(road("a", 0.0, 50))
    for graphs in ([gb, gc, ga], [ga, gc, gb], [gc, gb, ga]):
        m = stitch(graphs, config=DEFAULT)
        assert_one_continuous(m, -2.0, 98.0)
    old = stitch([gb, gc, ga], config=former_replace(DEFAULT, trim_lookahead=False))
    assert min(f.points[0, 0] for f in old.features) == pytest.approx(0.0)


def test_stitch_joins_same_type_only():
    """a ends with a dashed line, b starts with a solid one at the same place: not joined; the
    border and the solid line continue."""
    a = road("a", 0.0, 20, ([-3.5, 0.0, 3.5], [S, D, B]))
    b = road("b", 40.0, 20, ([-3.5, 0.0, 3.5], [S, S, B]))
    m = stitch([conn(a), conn(b)], config=former(StitchConfig, join_loose_ends=False))
    assert len(by_type(m, S)) == 2  # the through solid line and the new solid centre line
    assert len(by_type(m, B)) == 1 and len(by_type(m, D)) == 1
    d = by_type(m, D)[0]
    assert d.successors == () and d.points[-1, 0] == pytest.approx(38.0)
    centre = next(f for f in by_type(m, S) if abs(f.points[0, 1]) < 1e-9)
    assert centre.predecessors == ()


def test_road_border_never_joined_to_marking_across_segments():
    a = road("a", 0.0, 20, ([0.0], [B]))
    b = road("b", 40.0, 20, ([0.0], [S]))
    m = stitch([conn(a), conn(b)])
    assert len(m.features) == 2
    assert all(f.successors == () and f.predecessors == () for f in m.features)


def _ramp(pivot: str, x0: float, n: int, *, converging: bool) -> Segment:
    """A one-lane ramp right of the main road: its left solid line approaches the main road's
    solid line (y=-3.5) at the merge end (converging) or leaves it from the split start."""
    steps = []
    for i in range(n):
        k = (n - 1 - i) if converging else i
        gap = 0.5 + 0.3 * k
        left, right = -3.5 - gap, -3.5 - gap - 3.5
        steps.append(step(pivot, i, x0 + 2.0 * i, [left, right], [S, B], y_mid=(left + right) / 2))
    return Segment(pivot, tuple(steps))


def test_merge_across_segments_gives_two_predecessors():
    r"""main: x 0..198 (S at y=-3.5);  ramp: x 20..58 converging, ends beside the main road.

    ======================== S y=-3.5 ======>
                     ____/  ramp S
    """
    m = stitch([conn(road("main", 0.0, 100)), conn(_ramp("ramp", 20.0, 20, converging=True))])
    merging = [f for f in m.features if len(f.predecessors) == 2]
    assert len(merging) == 1 and merging[0].type == S
    ramp_line = next(f for f in by_type(m, S) if f.points[0, 0] == pytest.approx(20.0))
    assert ramp_line.successors == (merging[0].id,)
    np.testing.assert_allclose(ramp_line.points[-1], merging[0].points[0])  # meets at the merge point
    # the topology has a node with two predecessors
    preds = {}
    for t in m.topology:
        for s_ in t.successors:
            preds[s_] = preds.get(s_, 0) + 1
    assert max(preds.values()) == 2


def test_split_across_segments_gives_two_successors():
    m = stitch([conn(road("main", 0.0, 100)), conn(_ramp("ramp", 100.0, 20, converging=False))])
    splitting = [f for f in m.features if len(f.successors) == 2]
    assert len(splitting) == 1 and splitting[0].type == S
    assert max(len(t.successors) for t in m.topology) == 2
    for sid in splitting[0].successors:
        succ = next(f for f in m.features if f.id == sid)
        np.testing.assert_allclose(succ.points[0], splitting[0].points[-1])  # branches start at the split
    # no road border joined to anything else
    ids = {f.id: f for f in m.features}
    for f in m.features:
        for s_ in f.successors:
            assert (f.type == B) == (ids[s_].type == B)


def test_ids_stable_and_independent_of_unrelated_segments_and_order():
    ga, gb = conn(road("a", 0.0, 50)), conn(road("b", 100.0, 50))
    gc = conn(road("c", 0.0, 50, ([500.0, 503.5], [D, S]), y_mid=501.75))  # an unrelated road far away
    m1, m2 = stitch([ga, gb]), stitch([gb, ga])
    ids1 = sorted(f.id for f in m1.features)
    assert ids1 == sorted(f.id for f in m2.features)
    assert ids1 == sorted(f.id for f in stitch([conn(road("a", 0.0, 50)), conn(road("b", 100.0, 50))]).features)
    m3 = stitch([ga, gb, gc])
    assert set(ids1) < {f.id for f in m3.features}
    assert {t.id for t in m1.topology} < {t.id for t in m3.topology}
    assert all(0 < f.id < 2**63 for f in m3.features) and len({f.id for f in m3.features}) == len(m3.features)


def test_topology_nodes_reference_crossing_features():
    m = stitch([conn(road("a", 0.0, 30)), conn(_ramp("r", 60.0, 10, converging=False))])
    feats = {f.id: f for f in m.features}
    for t in m.topology:
        assert t.features, "every step carries features"
        for fid in t.features:
            d = np.min(np.abs(feats[fid].points[:, 0] - t.position[0]))
            assert d < 1e-6  # the feature has a point on this step
    nodes = {t.id for t in m.topology}
    assert all(s_ in nodes for t in m.topology for s_ in t.successors)


def test_integrate_replaces_reestimated_segment_and_keeps_other_ids():
    mg = MapGraph([conn(road("a", 0.0, 50)), conn(road("b", 100.0, 50))])
    v0 = mg.version
    before = mg.to_hdmap()
    # b re-estimated: same key, lines moved by 0.1 m
    b2 = conn(road("b", 100.0, 50, ([-3.4, 0.1, 3.6], [S, D, B])))
    rep = mg.integrate([b2])
    assert rep.removed == 1 and rep.added == 1 and mg.version == v0 + 1
    after = mg.to_hdmap()
    assert sorted(f.id for f in after.features) == sorted(f.id for f in before.features)
    solid = by_type(after, S)[0]
    assert solid.points[-1, 1] == pytest.approx(-3.4) and solid.points[0, 1] == pytest.approx(-3.5)
    # replacement by place: the tiles of b
    keys = mg.keys_in_tiles([(0, 0)])
    assert keys == {"a@0", "b@0"}
    mg.integrate([], replace=["b@0"])
    assert mg.keys == ["a@0"]
    assert len(mg.to_hdmap().features) == 3


def test_base_map_roundtrip_and_update():
    base = stitch(
        [conn(road("main", 0.0, 100)), conn(_ramp("ramp", 100.0, 20, converging=False))], config=former(StitchConfig)
    )
    same = stitch([], base=base)
    assert sorted(f.id for f in same.features) == sorted(f.id for f in base.features)
    for f in base.features:
        g = next(x for x in same.features if x.id == f.id)
        np.testing.assert_allclose(g.points, f.points)
        assert g.successors == f.successors and g.predecessors == f.predecessors
        np.testing.assert_array_equal(g.drive_count, f.drive_count)
    # update: a new section continuing the ramp is stitched onto the base map
    ext = Segment(
        "ext", tuple(step("ext", i, 140.0 + 2.0 * i, [-10.0, -13.5], [S, B], y_mid=-11.75) for i in range(10))
    )
    upd = stitch([conn(ext)], base=base)
    assert upd.version == base.version + 1
    ramp_s = [f for f in by_type(upd, S) if f.points[-1, 0] == pytest.approx(158.0)]
    assert len(ramp_s) == 1 and len(ramp_s[0].predecessors) == 1
    assert set(base.drive_ids) < set(upd.drive_ids)


def test_graph_from_hdmap_without_topology():
    base = stitch([conn(road("a", 0.0, 10))])
    bare = HDMap(features=base.features, drive_ids=base.drive_ids)
    g = graph_from_hdmap(bare)
    assert g.n_nodes == sum(len(f.points) for f in base.features)
    assert sorted(f.id for f in to_hdmap(g).features) == sorted(f.id for f in base.features)


def test_isolated_speck_dropped_and_bad_config():
    speck = Segment("s", (step("s", 0, 0.0, [0.0], [D]), step("s", 1, 2.0, [0.0], [D])))
    assert stitch([conn(speck)]).features == ()  # 2 m < min_isolated_length_m
    assert len(stitch([conn(speck)], config=former_paper(StitchConfig)).features) == 1
    single = Segment("s", (step("s", 0, 0.0, [0.0], [D]),))
    assert stitch([conn(single)], config=former_paper(StitchConfig)).features == ()  # one point is no polyline
    with pytest.raises(ConfigError):
        former(StitchConfig, max_distance_m=-1.0)
    g = conn(road("a", 0.0, 5))
    with pytest.raises(HdmapError, match="same key"):
        MapGraph([g, g])


def test_segment_split_by_long_gap_rejoined_only_when_asked():
    """RULE 3 breaks a segment at a 42 m gap: topology stitching does not bridge it (beyond
    max_distance_m); the loose-end join of one segment does (and fills the gap with drive_count 0)."""
    steps = [step("a", i, 2.0 * i, *LINES) for i in range(20)] + [step("a", i, 2.0 * i, *LINES) for i in range(40, 60)]
    g = connect_segment(Segment("a", tuple(steps)), config=former(ConnectionConfig))
    assert g.stats.gaps_closed == 1 and len(g.polylines()) == 6
    assert len(stitch([g], config=former(StitchConfig, join_same_segment=False)).features) == 6
    m = stitch([g])
    assert len(m.features) == 3
    for f in m.features:
        assert f.points[0, 0] == pytest.approx(0.0) and f.points[-1, 0] == pytest.approx(118.0)
        assert (f.drive_count == 0).sum() == 20  # x 40..78 filled


def test_one_point_feature_dropped_and_linked_past():
    r"""Two dashed lines touch in one step and part again (an X):

    \__/      the one-point piece at the touch is no polyline: dropped, and
    /  \      both inflows link straight to both outflows; every feature has >= 2 points.
    """

    def lat(i: int) -> list[float]:
        return [0.0] if i == 15 else [-0.1 * abs(i - 15), 0.1 * abs(i - 15)]

    seg = Segment("a", tuple(step("a", i, 2.0 * i, lat(i), [D] * len(lat(i))) for i in range(31)))
    m = stitch(
        [connect_segment(seg, config=former(ConnectionConfig, min_separation_m=0.0))],
        config=former(StitchConfig, through_lines=False),
    )
    assert all(len(f.points) >= 2 for f in m.features)
    assert len(m.features) == 4
    ins = [f for f in m.features if f.points[0, 0] == 0.0]
    outs = [f for f in m.features if f.points[0, 0] > 0.0]
    assert len(ins) == 2 and len(outs) == 2
    for f in ins:
        assert sorted(f.successors) == sorted(g.id for g in outs)
    for g in outs:
        assert sorted(g.predecessors) == sorted(f.id for f in ins)


def _arc_segment(pivot: str, i0: int, n: int, radius: float = 300.0) -> Segment:
    """Steps i0..i0+n-1 along a left curve of the given radius (centre (0, radius)), 2 m apart,
    one dashed line on the road midpoint."""
    steps = []
    for i in range(i0, i0 + n):
        th = 2.0 * i / radius
        mid = np.array([radius * math.sin(th), radius - radius * math.cos(th)])
        st = step(pivot, i, 0.0, [0.0], [D])
        steps.append(StepResult(**{**st.__dict__, "midpoint": mid, "heading": th}))
    return Segment(pivot, tuple(steps))


def test_loose_ends_joined_across_a_gap_with_curved_fill():
    r"""Two pivots map one curved line with a 30 m hole between them (no topology link: beyond
    max_distance_m): the loose ends are joined, the hole filled on the arc with drive_count 0."""
    a, b = conn(_arc_segment("a", 0, 40)), conn(_arc_segment("b", 55, 40))
    m = stitch([a, b])
    assert len(m.features) == 1
    f = m.features[0]
    r = np.linalg.norm(f.points - [0.0, 300.0], axis=1)
    assert np.abs(r - 300.0).max() < 0.05  # the filled points lie on the arc, not on the chord
    assert np.diff(np.hypot(*np.diff(f.points, axis=0).T)).max() < 0.5  # ~even spacing
    filled = f.drive_count == 0
    assert 10 <= filled.sum() <= 16  # 30 m hole at ~2 m spacing
    m_off = stitch([a, b], config=former(StitchConfig, join_loose_ends=False))
    assert len(m_off.features) == 2


def test_overlap_with_shifted_midpoints_trimmed_by_features():
    """Pivot b's cut also spans an extra lane, so its midpoint lies 3.5 m beside a's: the places
    overlap by their features, not their midpoints; one copy of each shared line survives."""
    wide = ([-7.0, -3.5, 0.0, 3.5], [B, S, D, B])
    b = road("b", 60.0, 50, wide, y_mid=-1.75)
    m = stitch([conn(road("a", 0.0, 50, ([-3.5, 0.0, 3.5], [B, D, B]))), conn(b)])
    for y, t in ((0.0, D), (3.5, B)):
        fs = [f for f in m.features if f.type == t and abs(f.points[0, 1] - y) < 1e-6]
        assert len(fs) == 1 and fs[0].points[-1, 0] == pytest.approx(158.0)
    # without the feature test both copies of x 60..98 stay
    m2 = stitch(
        [conn(road("a", 0.0, 50, ([-3.5, 0.0, 3.5], [B, D, B]))), conn(b)],
        config=former(StitchConfig, overlap_search_m=0.0, dedupe_loose_ends=False),
    )
    assert sum(len(f.points) for f in m2.features) > sum(len(f.points) for f in m.features) + 40


def test_short_type_flicker_smoothed_long_change_kept():
    """dashed 40 m, solid 6 m (misclassified), dashed 40 m, solid 40 m (a real change): two
    polylines, dashed then solid; without smoothing four."""
    types = [D] * 20 + [S] * 3 + [D] * 20 + [S] * 20
    seg = Segment("a", tuple(step("a", i, 2.0 * i, [0.0], [t]) for i, t in enumerate(types)))
    m = stitch([conn(seg)])
    assert [f.type for f in sorted(m.features, key=lambda f: f.points[0, 0])] == [FeatureType.DASHED, FeatureType.SOLID]
    assert len(stitch([conn(seg)], config=former(StitchConfig, min_type_run_m=0.0)).features) == 4


def test_sparse_flicker_between_one_type_relabelled_up_to_100_m():
    """dashed 60 m, solid 40 m, dashed 60 m, solid 40 m (to the end). Seen by 2 drives where the
    dashed runs have 3, the inner solid run (between two dashed runs) is one drive's
    misclassification and takes the dashed type; the last solid run (no dashed after it) stays.
    Seen by 10 drives (or with sparse_type_run_m 0) the inner run stays: three type changes,
    four polylines."""
    types = [D] * 30 + [S] * 20 + [D] * 30 + [S] * 20

    def seg(count: int, inner: int | None = None) -> Segment:
        cnt = [inner if (inner is not None and 30 <= i < 50) else count for i in range(len(types))]
        return Segment(
            "a", tuple(step("a", i, 2.0 * i, [0.0], [t], counts=[c]) for i, (t, c) in enumerate(zip(types, cnt)))
        )

    for cfg in (former(StitchConfig), DEFAULT):
        m = stitch([conn(seg(3, inner=2))], config=cfg)
        assert [f.type for f in sorted(m.features, key=lambda f: f.points[0, 0])] == [
            FeatureType.DASHED,
            FeatureType.SOLID,
        ]
        assert len(stitch([conn(seg(10))], config=cfg).features) == 4
        assert len(stitch([conn(seg(3, inner=2))], config=former_replace(cfg, sparse_type_run_m=0.0)).features) == 4


def test_sparse_flicker_of_as_many_drives_as_its_neighbours_kept():
    """dashed 60 m, solid 40 m, dashed 60 m, all seen by 3 drives: the solid run is not a
    minority (its drives saw solid where as many saw dashed beside it) and stays: three
    polylines. Without sparse_minority_only (the old rule: any run of <= 5 drives) it is
    relabelled; seen by one drive throughout it is relabelled too (one drive's type). Options of
    the default pipeline preset (the dataclass defaults keep the old rule)."""
    types = [D] * 30 + [S] * 20 + [D] * 30

    def seg(count: int) -> Segment:
        return Segment("a", tuple(step("a", i, 2.0 * i, [0.0], [t], counts=[count]) for i, t in enumerate(types)))

    assert DEFAULT.sparse_minority_only and not former(StitchConfig).sparse_minority_only
    assert [f.type for f in sorted(stitch([conn(seg(3))], config=DEFAULT).features, key=lambda f: f.points[0, 0])] == [
        FeatureType.DASHED,
        FeatureType.SOLID,
        FeatureType.DASHED,
    ]
    old = former_replace(DEFAULT, sparse_minority_only=False)
    assert [f.type for f in stitch([conn(seg(3))], config=old).features] == [FeatureType.DASHED]
    assert [f.type for f in stitch([conn(seg(1))], config=DEFAULT).features] == [FeatureType.DASHED]


def test_run_of_four_drives_between_better_supported_runs_kept():
    """dashed 60 m, solid 40 m, dashed 60 m; the dashed runs seen by 7 drives. A solid run that 4
    drives agree on is a real stretch (a solid line before a gore; four independent
    misclassifications at the simulator's 7.5 % are ~3e-5) and stays in the default preset
    (sparse_drive_count 3): three polylines. Of 3 drives it is relabelled, as it was of 4 with the
    dataclass's 5."""
    types = [D] * 30 + [S] * 20 + [D] * 30

    def seg(solid_count: int) -> Segment:
        cnt = [solid_count if t == S else 7 for t in types]
        return Segment(
            "a", tuple(step("a", i, 2.0 * i, [0.0], [t], counts=[c]) for i, (t, c) in enumerate(zip(types, cnt)))
        )

    assert DEFAULT.sparse_drive_count == 3 and former(StitchConfig).sparse_drive_count == 5
    assert [f.type for f in sorted(stitch([conn(seg(4))], config=DEFAULT).features, key=lambda f: f.points[0, 0])] == [
        FeatureType.DASHED,
        FeatureType.SOLID,
        FeatureType.DASHED,
    ]
    assert [f.type for f in stitch([conn(seg(3))], config=DEFAULT).features] == [FeatureType.DASHED]
    five = former_replace(DEFAULT, sparse_drive_count=5)
    assert [f.type for f in stitch([conn(seg(4))], config=five).features] == [FeatureType.DASHED]


def test_one_drive_flicker_relabelled_up_to_250_m():
    """One drive: dashed 200 m, solid 160 m (its misclassified stretch), dashed 200 m: one dashed
    polyline (the 100 m sparse limit alone would keep the solid run). A 300 m solid run, or
    single_drive_run_m 0, stays: three polylines. Two drives on the solid run (the dashed runs
    have 3): the single-drive rule does not apply, the 100 m limit does: three polylines. A run
    longer than both of its neighbours stays.
    Options of the default pipeline preset; the dataclass default (0, off) keeps the run."""

    def seg(n_solid: int, solid_count: int = 1, count: int = 1) -> Segment:
        types = [D] * 100 + [S] * n_solid + [D] * 100
        cnt = [solid_count if t == S else count for t in types]
        return Segment(
            "a", tuple(step("a", i, 2.0 * i, [0.0], [t], counts=[c]) for i, (t, c) in enumerate(zip(types, cnt)))
        )

    assert DEFAULT.single_drive_run_m == 250.0
    assert [f.type for f in stitch([conn(seg(80))], config=DEFAULT).features] == [FeatureType.DASHED]
    assert len(stitch([conn(seg(150))], config=DEFAULT).features) == 3
    assert len(stitch([conn(seg(80))], config=former(StitchConfig)).features) == 3
    assert len(stitch([conn(seg(80, solid_count=2, count=3))], config=DEFAULT).features) == 3
    # One drive, solid 78 m, dashed 146 m, solid 78 m: the dashed run is longer than both solid
    # runs beside it, so it is not taken for the misclassified one: three polylines S, D, S.
    types = [S] * 40 + [D] * 73 + [S] * 40
    m = stitch(
        [conn(Segment("a", tuple(step("a", i, 2.0 * i, [0.0], [t], counts=[1]) for i, t in enumerate(types))))],
        config=DEFAULT,
    )
    assert [f.type for f in sorted(m.features, key=lambda f: f.points[0, 0])] == [
        FeatureType.SOLID,
        FeatureType.DASHED,
        FeatureType.SOLID,
    ]


def test_line_of_unknown_type_takes_the_type_of_the_line_it_continues():
    """Two drives disagreed on solid/dashed over 40 m of a dashed line (a type clash kept as a
    line of type UNKNOWN, ``AlignmentConfig.sparse_type_clash_keep``): the run takes the type of
    the runs beside it, one dashed polyline without a hole; at the line's end it takes its one
    neighbour's type. A polyline of unknown type alone, continuing no typed line, is dropped.
    The same in the dataclass and the default preset (no option: UNKNOWN only comes from that
    rule)."""
    U = int(FeatureType.UNKNOWN)

    def seg(types: list[int]) -> Segment:
        return Segment("a", tuple(step("a", i, 2.0 * i, [0.0], [t], counts=[2]) for i, t in enumerate(types)))

    for cfg in (former(StitchConfig), DEFAULT):
        m = stitch([conn(seg([D] * 30 + [U] * 20 + [D] * 30))], config=cfg)
        assert [f.type for f in m.features] == [FeatureType.DASHED]
        assert len(m.features[0].points) == 80 and np.all(m.features[0].drive_count == 2)
        m = stitch([conn(seg([S] * 30 + [U] * 20))], config=cfg)
        assert [f.type for f in m.features] == [FeatureType.SOLID] and len(m.features[0].points) == 50
        assert stitch([conn(seg([U] * 30))], config=cfg).features == ()
        # beside a border line: the unknown line alone goes, the border stays
        both = Segment("a", tuple(step("a", i, 2.0 * i, [0.0, 3.5], [U, B], counts=[2, 2]) for i in range(30)))
        assert [f.type for f in stitch([conn(both)], config=cfg).features] == [FeatureType.ROAD_BORDER]


def test_one_drive_end_run_takes_the_better_supported_type():
    """Solid 200 m seen by 2 drives, then the line's last 80 m seen by one drive as dashed (its
    misclassified stretch; no run after it, so the flicker rules do not apply): one solid
    polyline. Kept (two polylines) when the end run has 2 drives too, when its neighbour has only
    one drive, when it is longer than its neighbour, or with single_drive_end_run_m 0 (the
    dataclass default). At the line's start alike (the end run first)."""

    def seg(types: list[int], counts: list[int]) -> Segment:
        return Segment(
            "a", tuple(step("a", i, 2.0 * i, [0.0], [t], counts=[c]) for i, (t, c) in enumerate(zip(types, counts)))
        )

    def kinds(m) -> list:
        return [f.type for f in sorted(m.features, key=lambda f: f.points[0, 0])]

    assert DEFAULT.single_drive_end_run_m == 250.0 and former(StitchConfig).single_drive_end_run_m == 0.0
    types, counts = [S] * 100 + [D] * 40, [2] * 100 + [1] * 40
    assert kinds(stitch([conn(seg(types, counts))], config=DEFAULT)) == [FeatureType.SOLID]
    assert kinds(stitch([conn(seg(types[::-1], counts[::-1]))], config=DEFAULT)) == [FeatureType.SOLID]
    assert len(stitch([conn(seg(types, counts))], config=former(StitchConfig)).features) == 2
    assert (
        len(stitch([conn(seg(types, counts))], config=former_replace(DEFAULT, single_drive_end_run_m=0.0)).features)
        == 2
    )
    assert len(stitch([conn(seg(types, [2] * 140))], config=DEFAULT).features) == 2  # 2 drives: kept
    assert len(stitch([conn(seg(types, [1] * 140))], config=DEFAULT).features) == 2  # neighbour 1 drive
    long_end = [S] * 40 + [D] * 60
    assert len(stitch([conn(seg(long_end, [2] * 40 + [1] * 60))], config=DEFAULT).features) == 2  # longer


def test_one_drive_end_run_judged_across_a_leftover_edge():
    """Solid 200 m seen by 2 drives, then the line's last 80 m seen by one drive as dashed, with
    a leftover edge (1:1) 60 m before the dashed run: the smoothing's chain ends there while the
    exported polyline goes on, so the end run's neighbour in its chain is only 60 m long and the
    end rule (not longer than its neighbour) kept it (two polylines). Judged along chains that go
    on through leftover edges (single_drive_end_through_leftover, default preset) it takes the
    solid type: one polyline. Off in the dataclass."""
    types, counts = [S] * 100 + [D] * 40, [2] * 100 + [1] * 40
    seg = Segment(
        "a", tuple(step("a", i, 2.0 * i, [0.0], [t], counts=[c]) for i, (t, c) in enumerate(zip(types, counts)))
    )
    g = conn(seg)
    (k,) = np.flatnonzero(np.abs(g.node_xy[g.edges[:, 0], 0] - 138.0) < 0.5)  # the edge 138 -> 140 m
    g.edge_leftover[k] = True

    def kinds(cfg) -> list:
        return [f.type for f in sorted(stitch([g], config=cfg).features, key=lambda f: f.points[0, 0])]

    assert DEFAULT.single_drive_end_through_leftover and not former(StitchConfig).single_drive_end_through_leftover
    assert kinds(DEFAULT) == [FeatureType.SOLID]
    assert kinds(former_replace(DEFAULT, single_drive_end_through_leftover=False)) == [
        FeatureType.SOLID,
        FeatureType.DASHED,
    ]


def test_spur_at_a_flicker_split_pruned():
    """A second line appears for 3 steps 1 m beside the dashed line (a leftover split) and dies:
    the spur is dropped, the dashed line stays one polyline."""

    def lat(i: int) -> list[float]:
        return [0.0, -1.2] if 20 <= i < 23 else [0.0]

    seg = Segment("a", tuple(step("a", i, 2.0 * i, lat(i), [D] * len(lat(i))) for i in range(50)))
    g = conn(seg)
    assert g.stats.splits == 1
    m = stitch([g])
    assert len(m.features) == 1 and len(m.features[0].points) == 50
    assert (
        len(stitch([g], config=former(StitchConfig, spur_max_m=0.0, bubble_max_m=0.0, through_lines=False)).features)
        == 4
    )
    # through lines: the unpruned spur starts on the dashed line, which stays whole
    kept = stitch([g], config=former(StitchConfig, spur_max_m=0.0, bubble_max_m=0.0)).features
    assert sorted(len(f.points) for f in kept) == [5, 50]


def test_loose_end_running_on_another_line_deduplicated():
    """b's dashed line starts on top of a's for 20 m (no topology overlap: b's other lines and
    midpoint are elsewhere, trimming disabled): the duplicate start is dropped and the rest joins
    a's line into one polyline."""
    a = road("a", 0.0, 50, ([0.0], [D]))
    b = road("b", 60.0, 50, ([0.0, -30.0], [D, S]), y_mid=-30.0)
    cfg = former(StitchConfig, trim_overlap=False)
    m = stitch([conn(a), conn(b)], config=cfg)
    dashed = by_type(m, D)
    assert len(dashed) == 1 and dashed[0].points[-1, 0] == pytest.approx(158.0)
    assert np.all(np.diff(dashed[0].points[:, 0]) > 0)  # no doubling back
    m0 = stitch([conn(a), conn(b)], config=former(StitchConfig, trim_overlap=False, dedupe_loose_ends=False))
    assert len(by_type(m0, D)) == 2


def test_loose_end_is_no_twin_of_the_link_into_itself():
    r"""a: x 0..98      b: one step at x 99.5 (the last metres of the road another pivot saw)
    The stitcher links a's end to b's node; b's lines then end there, and the edge into that end
    is no other line running on top of it: the lines reach x 99.5 (they stopped at 98 when the
    de-duplication took the link for a twin)."""
    m = stitch([conn(road("a", 0.0, 50)), conn(road("b", 99.5, 1))])
    assert_one_continuous(m, 0.0, 99.5)


def test_rebuild_makes_the_map_independent_of_integration_order():
    ga, gb = conn(road("a", 0.0, 50)), conn(road("b", 60.0, 50, y_mid=0.4))
    gc = conn(_ramp("c", 100.0, 20, converging=False))
    maps = []
    for order in ([ga, gb, gc], [gc, gb, ga]):
        mg = MapGraph()
        for g in order:
            mg.integrate([g])
        mg.rebuild()
        maps.append(mg.to_hdmap(version=0))
    a, b = maps
    assert [f.id for f in a.features] == [f.id for f in b.features]
    for fa, fb in zip(a.features, b.features):
        np.testing.assert_array_equal(fa.points, fb.points)
        assert fa.successors == fb.successors and fa.predecessors == fb.predecessors
    assert [t.id for t in a.topology] == [t.id for t in b.topology]
    assert a.extra["last_integrate"]["added"] == 3


def test_gore_split_placed_where_the_lane_line_ends():
    r"""A dashed lane line ends at x=40; two solid gore lines start there and diverge by 3 cm/m.
    The aggregation resolves them as two only from 1 m apart (x >= 74), so the connection yields
    dashed -> one solid -> split. The map gives the common piece to both branches: the dashed line
    has the two solid lines as successors, both starting at its end (as in the ground truth).

        D D D D D *======------   solid A
                   \====------    solid B
    """

    def lat(i):
        x = 2.0 * i
        if x < 40:
            return [0.0], [D]
        sep = 0.03 * (x - 40)
        return ([0.0], [S]) if sep < 1.0 else ([-sep / 2, sep / 2], [S, S])

    seg = Segment("a", tuple(step("a", i, 2.0 * i, *lat(i)) for i in range(80)))
    m = stitch([conn(seg)])
    (dashed,) = by_type(m, D)
    assert len(dashed.successors) == 2
    ids = {f.id: f for f in m.features}
    for sid in dashed.successors:
        b = ids[sid]
        assert b.type == FeatureType.SOLID and b.predecessors == (dashed.id,)
        np.testing.assert_allclose(b.points[0], dashed.points[-1])
        assert b.points[-1, 0] == pytest.approx(158.0)
    assert len(m.features) == 3
    # over the common piece (the two lines' one maximum at their middle) the two lines part
    # again: at x=60 (truly +-0.3 m) they lie on opposite sides, each at most 0.3 m out
    ys = [float(np.interp(60.0, ids[sid].points[:, 0], ids[sid].points[:, 1])) for sid in dashed.successors]
    assert min(ys) < -0.05 and max(ys) > 0.05 and max(abs(y) for y in ys) <= 0.3
    plain = stitch([conn(seg)], config=former(StitchConfig, gore_max_m=0.0, through_lines=False))
    assert len(plain.features) == 4 and len(by_type(plain, D)[0].successors) == 1


def test_branch_starting_beside_a_line_joins_it_as_a_split():
    """A ramp line of another pivot starts 1 m beside the main road's solid line and diverges: it
    is joined as a branch (the main line gets two successors). A copy running parallel 1.5 m
    beside the line for 40 m (no divergence) is not joined. (Topology stitching is switched off
    here, max_distance_m=0, so that only the feature-level branch join acts.)"""
    main = road("m", 0.0, 60, ([-3.5, 0.0], [S, D]))
    ramp = Segment("r", tuple(step("r", i, 50.0 + 2.0 * i, [-4.5 - 0.3 * i], [S], y_mid=-8.0) for i in range(30)))
    cfg = former(StitchConfig, trim_overlap=False, max_distance_m=0.0, branch_lateral_m=2.0, through_lines=False)
    m = stitch([conn(main), conn(ramp)], config=cfg)
    splitting = [f for f in m.features if len(f.successors) == 2]
    assert len(splitting) == 1 and splitting[0].type == FeatureType.SOLID
    # through lines (default): the main solid line stays whole, the ramp line starts on its interior
    m_thr = stitch([conn(main), conn(ramp)], config=former_replace(cfg, through_lines=True))
    solid = [f for f in m_thr.features if f.type == FeatureType.SOLID]
    main_solid = max(solid, key=lambda f: len(f.points))
    branch = [f for f in solid if f is not main_solid]
    assert len(solid) == 2 and main_solid.points[0, 0] == 0.0 and main_solid.points[-1, 0] == pytest.approx(118.0)
    d = np.hypot(*(main_solid.points - branch[0].points[0]).T)
    assert d.min() < 1e-9 and 0 < int(np.argmin(d)) < len(main_solid.points) - 1
    par = Segment("p", tuple(step("p", i, 50.0 + 2.0 * i, [-5.0], [S], y_mid=-8.0) for i in range(20)))
    m2 = stitch([conn(main), conn(par)], config=cfg)
    assert all(len(f.successors) < 2 and len(f.predecessors) < 2 for f in m2.features)
    m3 = stitch(
        [conn(main), conn(ramp)],
        config=former(StitchConfig, trim_overlap=False, max_distance_m=0.0, branch_lateral_m=0.0),
    )
    assert all(len(f.successors) < 2 for f in m3.features)


def test_stitch_rejects_non_graphs_and_handles_empty():
    with pytest.raises(HdmapError, match="SegmentGraph"):
        stitch([object()])
    m = stitch([])
    assert m.features == () and m.topology == ()
    m = stitch([conn(Segment("e", ()))])
    assert m.features == () and m.topology == ()


def test_overlapping_loose_end_and_start_joined_without_doubling_back():
    """a's line ends at x=98, b's starts 5 m behind it at x=93 (0.3 m aside): joined into one
    polyline whose points keep going forward (a's overlapping nodes are dropped)."""
    a = road("a", 0.0, 50, ([0.0], [D]))
    b = road("b", 93.0, 40, ([0.3], [D]))
    cfg = former(StitchConfig, trim_overlap=False, dedupe_loose_ends=False, max_distance_m=0.0)
    m = stitch([conn(a), conn(b)], config=cfg)
    assert len(m.features) == 1
    x = m.features[0].points[:, 0]
    assert np.all(np.diff(x) > 0) and x[0] == 0.0 and x[-1] == pytest.approx(171.0)
    cfg0 = former(StitchConfig, trim_overlap=False, dedupe_loose_ends=False, max_distance_m=0.0, join_overlap_m=0.0)
    assert len(stitch([conn(a), conn(b)], config=cfg0).features) == 2


def test_duplicate_inside_a_bridged_gap_deduplicated_against_the_edge():
    r"""a's dashed line has no result for 16 m (x 40..54, bridged by one edge); b maps a short
    copy of it inside that hole (0.2 m aside). The copy has no twin node, only a twin edge: it is
    dropped, and a's line stays one polyline.

        a:  - - - - - - -*- - - - - - - - - -*- - - - - - -
        b:                  - - - - - -                     (0.2 m aside)
    """
    a_steps = [step("a", i, 2.0 * i, [0.0], [D]) for i in range(50) if not 20 <= i < 27]
    a = Segment("a", tuple(a_steps))
    b = Segment("b", tuple(step("b", i, 41.0 + 2.0 * i, [0.2, -30.0], [D, S], y_mid=-30.0) for i in range(6)))
    cfg = former(StitchConfig, trim_overlap=False, min_isolated_length_m=0.0, max_distance_m=0.0)
    m = stitch([conn(a), conn(b)], config=cfg)
    assert len(by_type(m, D)) == 1
    assert by_type(m, D)[0].points[0, 0] == 0.0 and by_type(m, D)[0].points[-1, 0] == pytest.approx(98.0)


@pytest.mark.parametrize("merge", [True, False])
def test_continuations_merge_across_a_lone_leftover_edge(merge):
    """A leftover edge whose split partner is gone (e.g. its nodes were dropped as twins of
    another segment) still closes the polyline by RULE 2, though nothing splits or merges there.
    With merge_continuations (or through_lines, which continue a lone leftover edge of one type)
    the two pieces are one polyline; without both (the paper), two linked ones."""
    g = conn(road("a", 0.0, 50))
    solid_edges = np.flatnonzero((g.node_type[g.edges[:, 0]] == S) & (g.node_xy[g.edges[:, 0], 0] == 48.0))
    assert len(solid_edges) == 1
    lo = g.edge_leftover.copy()
    lo[solid_edges] = True
    g = dataclasses.replace(g, edge_leftover=lo)
    m = stitch([g], config=former(StitchConfig, merge_continuations=merge, through_lines=merge))
    solids = by_type(m, S)
    if merge:
        assert len(solids) == 1
        f = solids[0]
        assert f.points[0, 0] == pytest.approx(0.0) and f.points[-1, 0] == pytest.approx(98.0)
        assert np.all(np.diff(f.points[:, 0]) > 0) and np.diff(f.points[:, 0]).max() <= 2.0 + 1e-9
        assert len(f.drive_count) == len(f.points) == len(f.lateral_std)
        assert f.predecessors == () and f.successors == ()
    else:
        assert len(solids) == 2
        a, b = sorted(solids, key=lambda f: f.points[0, 0])
        assert a.successors == (b.id,) and b.predecessors == (a.id,)
    # Every topology node names a solid feature of the map.
    ids = {f.id for f in solids}
    assert all(any(fid in ids for fid in t.features) for t in m.topology)


def _exit_road() -> Segment:
    """Solid edge line at y=0 bending right by 3 cm/m from x=40; from x=50 a dashed line runs on
    straight 0.3 m beside it (an exit's deceleration lane line starting on the edge line)."""
    steps = []
    for i in range(60):
        x = 2.0 * i
        y = -0.03 * max(x - 40.0, 0.0)
        steps.append(step("e", i, x, [y] if x < 50 else [y, -0.0], [S] if x < 50 else [S, D]))
    return Segment("e", tuple(steps))


def test_exit_line_starts_on_the_interior_of_the_whole_edge_line():
    """Through lines: the solid edge line stays one feature across the split, and the dashed
    branch's first point is one of its interior points (no link: a link joins a last point to a
    first point). The paper's export breaks the edge line there and links three pieces."""
    g = connect_segment(_exit_road(), config=former(ConnectionConfig, min_separation_m=0.0))
    m = stitch([g])
    (solid,) = by_type(m, S)
    (dashed,) = by_type(m, D)
    assert solid.points[0, 0] == 0.0 and solid.points[-1, 0] == pytest.approx(118.0)
    assert not solid.successors and not dashed.predecessors
    k = int(np.argmin(np.hypot(*(solid.points - dashed.points[0]).T)))
    np.testing.assert_allclose(solid.points[k], dashed.points[0])
    assert solid.points[k, 0] == pytest.approx(48.0)
    paper = stitch([g], config=former(StitchConfig, through_lines=False))
    assert len(paper.features) == 3
    (head,) = [f for f in paper.features if len(f.successors) == 2]
    assert head.type == FeatureType.SOLID


def test_attached_branch_survives_a_base_map_round_trip():
    """graph_from_hdmap turns a branch drawn on a through line back into a leftover edge, so
    re-exporting the base map gives the same features (ids, points, links)."""
    m = stitch([connect_segment(_exit_road(), config=former(ConnectionConfig, min_separation_m=0.0))])
    g = graph_from_hdmap(m)
    assert int(g.edge_leftover.sum()) == 1
    again = stitch([], base=m)
    assert sorted(f.id for f in again.features) == sorted(f.id for f in m.features)
    for f in m.features:
        (h,) = [x for x in again.features if x.id == f.id]
        np.testing.assert_allclose(h.points, f.points)
        assert h.predecessors == f.predecessors and h.successors == f.successors


def test_loose_ends_joined_where_the_pivot_heading_leaves_the_line():
    """One dashed line along x, mapped by pivot a (x 0..40) and pivot b (x 48..100). b's pivot
    comes in on an entry ramp: the heading of its first topology nodes is its own (40 deg, then
    turning in), not the line's. Compared by those headings the end and the start differ by
    more than max_heading_diff_deg and stayed apart (Town04's cloverleaf); compared by their
    lines' own directions they continue each other and are joined across the 8 m gap."""
    a = conn(road("a", 0.0, 21, ([0.0], [D])))
    b = conn(road("b", 48.0, 27, ([0.0], [D])))
    h = b.topo_heading.copy()
    h[:8] = np.radians(np.linspace(40.0, 5.0, 8))
    b = dataclasses.replace(b, topo_heading=h)
    m = stitch([a, b])
    assert len(m.features) == 1
    p = m.features[0].points
    assert p[0, 0] == pytest.approx(0.0) and p[-1, 0] == pytest.approx(100.0)
    np.testing.assert_allclose(p[:, 1], 0.0, atol=1e-6)
    assert len(stitch([a, b], config=former(StitchConfig, join_line_heading_m=0.0)).features) == 2


def _turning_pivots(cross: bool):
    """One dashed line along x, mapped by pivots a (x 0..40) and b (x 72..120) with a 32 m gap;
    both pivots head 6 deg off the line (topology heading 0.1 rad), so compared by their
    topology headings the start lies 3.2 m beside the end and the join fails; compared by the
    line's own direction it passes (from ``join_line_heading_deg`` 3, the default preset's).
    ``cross``: pivot c drives north through the middle of the gap (x 56), as a pivot turning
    through a junction."""

    def seg(name: str, x0: float, n: int) -> Segment:
        return Segment(
            name, tuple(dataclasses.replace(step(name, i, x0 + 2.0 * i, [0.0], [D]), heading=0.1) for i in range(n))
        )

    graphs = [conn(seg("a", 0.0, 21)), conn(seg("b", 72.0, 25))]
    if cross:
        c = Segment(
            "c",
            tuple(
                dataclasses.replace(step("c", i, 56.0, [-6.0, 6.0], [B, B], y_mid=-20.0 + 2.0 * i), heading=math.pi / 2)
                for i in range(21)
            ),
        )
        graphs.append(conn(c))
    return graphs


def test_join_in_the_lines_frame_refused_where_a_pivot_turned_through_the_gap():
    """The loose end and start of one line, 32 m apart, pass the join only in the line's own
    frame. With no other drive in the gap they are joined (default preset); where another
    pivot's topology nodes cross the gap's middle (heading 90 deg off, > join_line_cross_deg),
    the join is refused: the pivots turned through a junction and the lines end at its mouths
    (Town06). With the dataclass defaults (line frame from 10 deg only, the check off) the
    line stays in two pieces either way."""

    def pieces(m: HDMap) -> list:
        return [f for f in m.features if f.type == FeatureType.DASHED]

    assert DEFAULT.join_line_cross_deg == 30.0 and DEFAULT.join_line_heading_deg == 3.0
    joined = pieces(stitch(_turning_pivots(cross=False), config=DEFAULT))
    assert len(joined) == 1 and joined[0].points[-1, 0] == pytest.approx(120.0)
    assert len(pieces(stitch(_turning_pivots(cross=True), config=DEFAULT))) == 2
    off = former_replace(DEFAULT, join_line_cross_deg=0.0)
    assert len(pieces(stitch(_turning_pivots(cross=True), config=off))) == 1
    assert len(pieces(stitch(_turning_pivots(cross=False), config=former(StitchConfig)))) == 2


def test_one_drive_border_between_lane_lines_dropped():
    """Pivot a maps a road (solid -3.5, dashed 0, solid 3.5 m, 4 drives); pivot b (its cuts
    centred 3 m over, so it is no overlap to trim) alone reports
    a road border at 1.75 m over 60 m (a marking taken for a border) and another
    at 5.5 m, beyond the outer line. The inner one has lane markings on both sides within 5 m:
    with inner_border_max_m (default preset) it is no border, the outer one stays; one drive's
    is kept as a dashed lane line (inner_border_dashed_drives 1), two drives' is dropped, and so
    is one drive's border lying on a mapped line (0.3 m from the dashed line at 0). With 3 drives
    on b (above inner_border_max_drives 2), or with the dataclass default (0, off), both stay."""
    a = conn(road("a", 0.0, 50, ([-3.5, 0.0, 3.5], [S, D, S])))

    def b(count: int, inner: float = 1.75):
        steps = [
            step("b", i, 20.0 + 2.0 * i, [inner, 5.5], [B, B], y_mid=3.0, counts=[count, count]) for i in range(30)
        ]
        return conn(Segment("b", tuple(steps)))

    def lines(m: HDMap, t: FeatureType) -> list[float]:
        return sorted(round(float(f.points[0, 1]), 2) for f in m.features if f.type == t)

    assert DEFAULT.inner_border_max_m == 5.0 and DEFAULT.inner_border_dashed_drives == 1
    one = stitch([a, b(1)], config=DEFAULT)
    assert lines(one, B) == [5.5]
    assert lines(one, D) == [0.0, 1.75]
    two = stitch([a, b(2)], config=DEFAULT)
    assert lines(two, B) == [5.5] and lines(two, D) == [0.0]
    on_line = stitch([a, b(1, inner=0.3)], config=DEFAULT)
    assert lines(on_line, B) == [5.5] and lines(on_line, D) == [0.0]
    assert lines(stitch([a, b(1)], config=former_replace(DEFAULT, inner_border_dashed_drives=0)), D) == [0.0]
    assert lines(stitch([a, b(3)], config=DEFAULT), B) == [1.75, 5.5]
    assert lines(stitch([a, b(1)], config=former(StitchConfig)), B) == [1.75, 5.5]


def _gap_roads(through_lines):
    """Pivots a (x 0..40) and b (x 80..120) map the three lines of one road, which all end at
    the same 40 m gap; pivot c drove through the gap (x 42..78) mapping ``through_lines``
    there (lateral positions; a pivot's step needs a line to have a topology node)."""
    a = conn(road("a", 0.0, 21))
    b = conn(road("b", 80.0, 21))
    k = len(through_lines)
    c = conn(Segment("c", tuple(step("c", i, 42.0 + 2.0 * i, through_lines, [D] * k) for i in range(19))))
    return a, b, c


def test_long_join_refused_across_a_gap_drives_passed_with_no_line_mapped():
    """Every line of a road ends at one 40 m gap that drives went through (c's topology nodes
    lie in it) but where no line was mapped beside the join (c saw only a line 20 m over, beyond
    join_gap_lateral_m, as at a junction's mouth): a straight join across it would
    be a filled line no drive saw (Town06's junction mouths), so it is refused; with the check
    off (the paper's loose-end joins have none; 0 disables) the three lines are joined."""
    a, b, c = _gap_roads([20.0])
    m = stitch([a, b, c])
    road_ = [f for f in m.features if abs(f.points[0, 1]) < 5.0]
    assert len(road_) == 6
    assert all(f.points[-1, 0] <= 40.0 or f.points[0, 0] >= 80.0 for f in road_)
    off = stitch([a, b, c], config=former(StitchConfig, join_gap_check_m=0.0))
    road_ = [f for f in off.features if abs(f.points[0, 1]) < 5.0]
    assert len(road_) == 3
    for f in road_:
        assert f.points[0, 0] == pytest.approx(0.0) and f.points[-1, 0] == pytest.approx(120.0)
    assert len(stitch([a, b, c], config=former_paper(StitchConfig)).features) == 7


def test_long_join_made_where_neighbour_lines_are_mapped_through_the_gap():
    """The same gap, but c mapped two other lines (7 m and -7 m over, within
    join_gap_lateral_m) all through it: the road's lines are only unseen there, so the joins are
    made; without c (no drive in the gap) they are made too. With a 5 m band the middle line
    (y 0, c's lines 7 m over) is refused again, the outer ones (3.5 m from c's) still joined."""
    a, b, c = _gap_roads([-7.0, 7.0])
    m = stitch([a, b, c])
    long_ = [f for f in m.features if f.points[0, 0] == pytest.approx(0.0)]
    assert len(long_) == 3 and all(f.points[-1, 0] == pytest.approx(120.0) for f in long_)
    assert len(stitch([a, b]).features) == 3
    narrow = stitch([a, b, c], config=former(StitchConfig, join_gap_lateral_m=5.0))
    for f in narrow.features:
        if f.points[0, 0] == pytest.approx(0.0):
            assert f.points[-1, 0] == pytest.approx(40.0 if f.points[0, 1] == 0.0 else 120.0)


def _topo_chain(first_id: int, xs: np.ndarray, ys: np.ndarray, nxt: int | None = None) -> list:
    from hdmap_core.model import TopologyNode  # noqa: PLC0415

    return [
        TopologyNode(
            id=first_id + k,
            position=np.array([x, y]),
            heading=0.0,
            width=10.0,
            successors=(first_id + k + 1,) if k + 1 < len(xs) else (() if nxt is None else (nxt,)),
        )
        for k, (x, y) in enumerate(zip(xs, ys))
    ]


def _successor_positions(m: HDMap, xy) -> list:
    pos = {t.id: t.position for t in m.topology}
    (node,) = [t for t in m.topology if np.allclose(t.position, xy)]
    return [pos[s].tolist() for s in node.successors]


def test_end_linked_inside_its_own_component_when_asked():
    r"""Main road piece P (x 0..98) and Q (x 104..298), already joined through a bypass R that leaves
    P at x 48 and enters Q at x 152: P's end and Q's start are in one weakly connected component, so
    the paper's rule leaves the 6 m gap unlinked (no path P -> Q along the main road)."""
    p = _topo_chain(1, np.arange(0, 99, 2.0), np.zeros(50))
    q = _topo_chain(100, np.arange(104, 300, 2.0), np.zeros(98))
    xr = np.arange(50, 151, 2.0)
    r = _topo_chain(300, xr, -4 - 26 * np.sin(np.pi * (xr - 50) / 100), nxt=124)
    p[24] = dataclasses.replace(p[24], successors=(p[25].id, 300))
    base = HDMap(topology=tuple(p + q + r))
    assert _successor_positions(stitch([], base=base, config=former(StitchConfig)), [98, 0]) == []
    m = stitch([], base=base, config=former(StitchConfig, link_within_component=True))
    assert _successor_positions(m, [98, 0]) == [[104.0, 0.0]]
    assert _successor_positions(m, [48, 0]) == [[50.0, 0.0], [50.0, -4.0]]  # nothing else changed


def test_link_inside_a_component_never_closes_a_short_cycle():
    """Chain A (x 10..98) continues into chain B whose last nodes lie just behind A's start: linking
    B's end to A's start would make a 100-node loop, so it is not made."""
    a = _topo_chain(1, np.arange(10, 99, 2.0), np.zeros(45), nxt=100)
    b = _topo_chain(100, np.concatenate([np.arange(100, 200, 2.0), np.arange(0, 9, 2.0)]), np.zeros(55))
    m = stitch([], base=HDMap(topology=tuple(a + b)), config=former(StitchConfig, link_within_component=True))
    assert _successor_positions(m, [8, 0]) == []


def test_link_within_component_only_in_the_default_preset():
    from hdmap_core.pipeline import presets  # noqa: PLC0415

    assert presets.preset("default").stitching.link_within_component
    for name in ("naive", "paper"):
        assert not presets.preset(name).stitching.link_within_component
    assert not former_paper(StitchConfig).link_within_component and not former(StitchConfig).link_within_component


def _arc_chain(first_id: int, center, radius: float, headings: np.ndarray, *, left: bool, width: float = 7.0) -> list:
    """Topology nodes on a circle around ``center`` with the given headings (driving order),
    turning left (centre on the left) or right, as ``_topo_chain``."""
    from hdmap_core.model import TopologyNode  # noqa: PLC0415

    cx, cy = center
    side = 1.0 if left else -1.0
    out = []
    for k, h in enumerate(headings):
        xy = np.array([cx + side * radius * math.sin(h), cy - side * radius * math.cos(h)])
        out.append(
            TopologyNode(
                id=first_id + k,
                position=xy,
                heading=float(h),
                width=width,
                successors=(first_id + k + 1,) if k + 1 < len(headings) else (),
            )
        )
    return out


def _main_road(first_id: int = 1) -> list:
    """A straight road along +x, x 0..298, midpoints at y 0, 14 m wide (four lanes)."""
    return [dataclasses.replace(t, width=14.0) for t in _topo_chain(first_id, np.arange(0, 299, 2.0), np.zeros(150))]


def _predecessors(m: HDMap, node_id: int) -> list:
    return [t for t in m.topology if node_id in t.successors]


def test_ramp_end_turning_onto_the_road_follows_its_arc():
    r"""An entry ramp (radius 50 m, turning right) meets the main road's right lanes tangentially at
    x 100 but its chain ends 30 m before, heading 35 deg: the main-road nodes within 12 m run 35 deg
    off it (over ``max_heading_diff_deg``), so the ordinary rule leaves it unlinked. Its own arc,
    turning at its heading rate, enters the main road's cross-section: linked there."""
    main = _main_road()
    heads = np.arange(1.2, 0.60, -0.04)  # heading 69 -> 35 deg, turning right, ending 30 m before x 100
    ramp = _arc_chain(1000, (100.0, -52.0), 50.0, heads, left=False)
    end = ramp[-1]
    assert 10.0 < -end.position[1] < 12.0 and math.degrees(end.heading) > 34.0
    base = HDMap(topology=tuple(main + ramp))
    assert _successor_positions(stitch([], base=base, config=former(StitchConfig)), end.position) == []
    m = stitch([], base=base, config=former(StitchConfig, path_search_m=40.0))
    ((x, y),) = _successor_positions(m, end.position)
    assert y == 0.0 and end.position[0] < x < 100.0
    assert _successor_positions(m, [50.0, 0.0]) == [[52.0, 0.0]]  # nothing else changed
    # too short a search, or a chain turning away from the road: no link
    assert (
        _successor_positions(stitch([], base=base, config=former(StitchConfig, path_search_m=6.0)), end.position) == []
    )
    # the arc turns ~8 deg before it enters the road's cross-section: a 4 deg cap stops it short
    capped = former(StitchConfig, path_search_m=40.0, path_max_turn_deg=4.0)
    assert _successor_positions(stitch([], base=base, config=capped), end.position) == []
    assert _successor_positions(
        stitch([], base=base, config=former_replace(capped, path_max_turn_deg=60.0)), end.position
    ) == [[x, y]]
    he, (ex, ey) = end.heading, end.position  # the same end, reached turning left
    away = _arc_chain(
        1000, (ex - 50.0 * math.sin(he), ey + 50.0 * math.cos(he)), 50.0, he - np.arange(0.8, -1e-9, -0.04), left=True
    )
    assert np.allclose(away[-1].position, end.position)
    m = stitch([], base=HDMap(topology=tuple(main + away)), config=former(StitchConfig, path_search_m=40.0))
    assert _successor_positions(m, away[-1].position) == []


def test_exit_start_beyond_the_stitch_radius_follows_its_arc_back():
    r"""An exit (radius 80 m, turning left) leaves the main road's left lanes at x 100; its chain
    starts 36 m later, 13 m from the main road's midpoints (beyond ``max_distance_m``). Followed
    back along its arc it enters the main road's cross-section: a main-road node behind gets it as
    a second successor (the split)."""
    main = _main_road()
    exit_ = _arc_chain(1000, (100.0, 85.0), 80.0, np.arange(0.45, 1.2, 0.025), left=True)
    start = exit_[0]
    assert 12.0 < start.position[1] < 14.0
    base = HDMap(topology=tuple(main + exit_))
    assert _predecessors(stitch([], base=base, config=former(StitchConfig)), start.id) == []
    m = stitch([], base=base, config=former(StitchConfig, path_search_m=40.0))
    (pred,) = _predecessors(m, start.id)
    assert pred.position[1] == 0.0 and 100.0 < pred.position[0] < start.position[0]
    assert len(pred.successors) == 2


def test_path_search_only_in_the_default_preset():
    from hdmap_core.pipeline import presets  # noqa: PLC0415

    assert presets.preset("default").stitching.path_search_m > 0
    for name in ("naive", "paper"):
        assert presets.preset(name).stitching.path_search_m == 0.0
    assert former_paper(StitchConfig).path_search_m == 0.0 and former(StitchConfig).path_search_m == 0.0


def test_roads_side_by_side_join_only_at_a_shallow_angle():
    r"""a: x 0..98 at y 0     b: x 100..198 at y 11 (10 m wide each: their cross-sections lie
    apart). a's end and b's start are 11.2 m apart at 80 deg to a's heading, inside
    ``max_connection_angle_deg`` (80.5 deg here): linked by default, not with a 30 deg
    ``side_link_angle_deg``; the same pair 1 m apart across (one road) is linked either way."""
    a = _topo_chain(1, np.arange(0, 99, 2.0), np.zeros(50))
    b = _topo_chain(100, np.arange(100, 199, 2.0), np.full(50, 11.0))
    cfg = former(StitchConfig, max_connection_angle_deg=80.5)
    base = HDMap(topology=tuple(a + b))
    assert _successor_positions(stitch([], base=base, config=cfg), [98.0, 0.0]) == [[100.0, 11.0]]
    side = former_replace(cfg, side_link_angle_deg=30.0)
    assert _successor_positions(stitch([], base=base, config=side), [98.0, 0.0]) == []
    near = HDMap(topology=tuple(a + _topo_chain(100, np.arange(100, 199, 2.0), np.full(50, 1.0))))
    assert _successor_positions(stitch([], base=near, config=side), [98.0, 0.0]) == [[100.0, 1.0]]


def test_roads_whose_lines_barely_overlap_are_side_by_side():
    r"""a: x 0..98, lines at y -3.5 .. 3.5      b: x 100..198, lines at y 4.5 .. 8.5 (mid 6.5)
    Both cuts are 10 m wide, so their half widths reach each other (6.5 m across < 10 m) and the
    30 deg ``side_link_angle_deg`` does not apply to a's end and b's start (73 deg apart, inside
    ``max_connection_angle_deg``): a ramp beside its main road (esmini_soderleden_40_s5). Their
    lines overlap by -1 m across, under half the narrower span (4 m, + 1 m slack): with
    ``side_link_overlap`` 0.5 they are side by side and not linked. b 2 m further in, its lines at
    2.5 .. 6.5 overlapping a's by 1 m, is the same road: linked either way."""
    lines_a = ([-3.5, 0.0, 3.5], [S, D, B])
    cfg = former(StitchConfig, max_connection_angle_deg=80.0, side_link_angle_deg=30.0, join_loose_ends=False)
    for y_mid, linked_by_default in ((6.5, False), (4.5, True)):
        b_lines = ([y_mid - 2.0, y_mid, y_mid + 2.0], [B, D, B])
        graphs = [conn(road("a", 0.0, 50, lines_a)), conn(road("b", 100.0, 50, b_lines, y_mid=y_mid))]
        on = _successor_positions(stitch(graphs, config=former_replace(cfg, side_link_overlap=0.5)), [98.0, 0.0])
        off = _successor_positions(stitch(graphs, config=cfg), [98.0, 0.0])
        assert off == [[100.0, y_mid]]
        assert on == ([[100.0, y_mid]] if linked_by_default else [])
    assert presets.preset("default").stitching.side_link_overlap == 0.5
    assert former(StitchConfig).side_link_overlap == 0.0 and former_paper(StitchConfig).side_link_overlap == 0.0


def test_side_link_angle_only_in_the_default_preset():
    from hdmap_core.pipeline import presets  # noqa: PLC0415

    assert presets.preset("default").stitching.side_link_angle_deg == 30.0
    assert former(StitchConfig).side_link_angle_deg == 90.0 and former_paper(StitchConfig).side_link_angle_deg == 90.0


def test_link_runs_within_the_partners_heading_too():
    r"""carla_town04_100_s1: the last node of a ramp piece A (heading -20 deg, leaving the road)
    lies at (98, -8.4); the main road's piece B starts at (100, 0), heading 0. Seen from B's
    start, A's end lies 2 m behind and 8.4 m aside (77 deg off B's heading, inside
    ``max_connection_angle_deg``), so the plain rule links A -> B. The link runs 97 deg off A's
    own heading, backward for A: with ``partner_angle_deg`` 90 it is refused, while a
    predecessor heading along the link's way (A turned to heading +20 deg, 57 deg off the link)
    is still taken."""
    from hdmap_core.model import TopologyNode  # noqa: PLC0415

    def ramp(heading_deg: float) -> list:
        """A's one node (id 500): its end, without successor."""
        return [TopologyNode(id=500, position=np.array([98.0, -8.4]), heading=math.radians(heading_deg), width=9.0)]

    b = _topo_chain(100, np.arange(100, 199, 2.0), np.zeros(50))
    start = b[0]
    away = HDMap(topology=tuple(ramp(-20.0) + b))
    assert [t.id for t in _predecessors(stitch([], base=away, config=former(StitchConfig)), start.id)] == [500]
    strict = former(StitchConfig, partner_angle_deg=90.0)
    assert _predecessors(stitch([], base=away, config=strict), start.id) == []
    toward = HDMap(topology=tuple(ramp(20.0) + b))
    assert [t.id for t in _predecessors(stitch([], base=toward, config=strict), start.id)] == [500]


def test_partner_angle_only_in_the_default_preset():
    assert presets.preset("default").stitching.partner_angle_deg == 90.0
    assert former(StitchConfig).partner_angle_deg == 180.0 and former_paper(StitchConfig).partner_angle_deg == 180.0


def _pose_step(pivot: str, i: int, xy, heading: float, *, valid: bool = True, processed_before: bool = False):
    """Step i of ``pivot`` at midpoint ``xy`` heading ``heading``, 10 m wide, with the lines
    ``LINES`` (lateral from the midpoint) when valid, else a geometry-only placeholder."""
    lat, typ = LINES if valid and not processed_before else ([], [])
    return StepResult(
        pivot_id=pivot,
        index=i,
        s_m=2.0 * i,
        midpoint=np.asarray(xy, float),
        heading=float(heading),
        width_m=10.0,
        valid=valid,
        processed_before=processed_before,
        lateral_m=np.asarray(lat, float),
        types=np.asarray(typ, int),
        counts=np.full(len(lat), 4),
        std_m=np.full(len(lat), 0.15),
        drive_ids=(pivot, f"{pivot}-other"),
    )


def _junction(turn: bool) -> list:
    r"""Pivot p drives south on x = 0 (y 100 -> 30), then (``turn``) left through a 20 m-radius
    junction whose steps all failed onto the road q maps eastwards at y = 10 (x 20 -> 118; p's
    steps there were processed before through q), or (not ``turn``) straight on with failed steps.

        p |
          |
          (0, 30)  end of p's chain, heading -90 deg
           \_ _ _ q ->  (20, 10), heading 0
    """
    south = -math.pi / 2
    steps = [_pose_step("p", i, (0.0, 100.0 - 2.0 * i), south) for i in range(36)]
    if turn:
        thetas = math.pi + 0.1 * np.arange(1, 16)  # centre (20, 30), 2 m steps, to heading 0
        steps += [
            _pose_step(
                "p", 35 + k, (20.0 + 20.0 * math.cos(t), 30.0 + 20.0 * math.sin(t)), t + math.pi / 2, valid=False
            )
            for k, t in enumerate(thetas, start=1)
        ]
        steps += [
            _pose_step("p", 51, (22.0, 10.0), 0.0, processed_before=True),
            _pose_step("p", 70, (60.0, 10.0), 0.0, processed_before=True),
        ]
    else:
        steps += [_pose_step("p", 35 + k, (0.0, 30.0 - 2.0 * k), south, valid=False) for k in range(1, 16)]
    q = Segment("q", tuple(_pose_step("q", i, (20.0 + 2.0 * i, 10.0), 0.0) for i in range(50)))
    return [connect_segment(Segment("p", tuple(steps))), connect_segment(q)]


def test_segment_graph_keeps_the_pivots_whole_track():
    p, _ = _junction(turn=True)
    used = set(p.topo_step.tolist())
    assert used == set(range(36))  # the turn failed, the rest was processed through q
    assert p.track_step.tolist() == list(range(52)) + [70]  # every step with a pose, in order
    assert np.allclose(p.track_xy[36], [20.0 + 20.0 * math.cos(math.pi + 0.1), 30.0 + 20.0 * math.sin(math.pi + 0.1)])
    assert math.isclose(p.track_heading[-1], 0.0)
    # a step without a finite pose is left out of the track (and reported as before, not a crash)
    bad = dataclasses.replace(_pose_step("p", 36, (0.0, 28.0), 0.0, valid=False), midpoint=np.array([np.nan, 0.0]))
    g = connect_segment(Segment("p", (_pose_step("p", 35, (0.0, 30.0), 0.0), bad)))
    assert g.track_step.tolist() == [35]


def test_end_follows_its_pivots_track_through_a_junction_turn():
    """p's chain ends heading south 28 m from q's start heading east: too far and too far turned for
    the ordinary link, and its own (straight) arc runs south past q. The path p drove (its failed
    steps' midpoints) enters q's cross-section: a topology link p -> q."""
    graphs = _junction(turn=True)
    end = [0.0, 30.0]
    for cfg in (former(StitchConfig), former(StitchConfig, path_search_m=36.0, path_max_turn_deg=60.0)):
        assert _successor_positions(stitch(graphs, config=cfg), end) == []
    m = stitch(graphs, config=former(StitchConfig, track_search_m=60.0))
    ((x, y),) = _successor_positions(m, end)
    assert y == 10.0 and 20.0 <= x <= 24.0
    assert m.extra["last_integrate"]["track_links"] == 1
    # the turn is ~31 m of track: a shorter search, or a pivot that drove straight on, links nothing
    assert _successor_positions(stitch(graphs, config=former(StitchConfig, track_search_m=20.0)), end) == []
    assert (
        _successor_positions(stitch(_junction(turn=False), config=former(StitchConfig, track_search_m=60.0)), end) == []
    )


@pytest.mark.parametrize("across_m, linked", [(0.0, True), (4.5, True), (7.0, False)])
def test_track_walk_passes_failed_midpoints_thrown_across_the_road(across_m: float, linked: bool):
    """As above, with two failed steps' cut midpoints thrown across the road (refined to other
    borders), +across_m and -across_m off the pivot's arc: 2 * across_m apart, 2 m along. The
    pivot drove on: up to ``tracks._TRACK_MAX_JUMP_M`` (12 m) the walk goes on, beyond it that is no path."""
    p, q = _junction(turn=True)
    xy = p.track_xy.copy()
    for k, sign in ((37, 1.0), (38, -1.0)):
        h = p.track_heading[k]
        xy[k] += sign * across_m * np.array([-math.sin(h), math.cos(h)])
    p = dataclasses.replace(p, track_xy=xy)
    end = [0.0, 30.0]
    succ = _successor_positions(stitch([p, q], config=former(StitchConfig, track_search_m=60.0)), end)
    assert (len(succ) == 1 and succ[0][1] == 10.0) if linked else succ == []


def test_linked_end_gets_the_turn_its_pivot_took_as_a_second_successor():
    """As above, with a road c going on south from p's end: the ordinary link takes c. With
    ``track_linked_ends`` the end also gets q (the split p's pivot drove); c keeps its link."""
    c = connect_segment(Segment("c", tuple(_pose_step("c", i, (0.0, 28.0 - 2.0 * i), -math.pi / 2) for i in range(40))))
    graphs = _junction(turn=True) + [c]
    end = [0.0, 30.0]
    assert _successor_positions(stitch(graphs, config=former(StitchConfig, track_search_m=60.0)), end) == [[0.0, 28.0]]
    m = stitch(graphs, config=former(StitchConfig, track_search_m=60.0, track_linked_ends=True))
    succ = _successor_positions(m, end)
    assert len(succ) == 2 and [0.0, 28.0] in succ
    ((x, y),) = [s for s in succ if s != [0.0, 28.0]]
    assert y == 10.0 and 20.0 <= x <= 24.0
    # a pivot that drove on south along c adds nothing: c is reached from the end already
    graphs = _junction(turn=False) + [c]
    m = stitch(graphs, config=former(StitchConfig, track_search_m=60.0, track_linked_ends=True))
    assert _successor_positions(m, end) == [[0.0, 28.0]]


def _beside_a_road_joining_later() -> list:
    """soderleden s5's ramp (docs/graph.md): pivot p drives east on y = 0; its chain ends at x = 0
    (the steps after it failed, its track runs on at y = 0) and is linked to c, the ramp going on
    to x = 10, whose end links to the main road m 4.5 m beside it (y = 4.5, x -60 -> 60). p's
    track after the end lies in m's cross-section (10 m wide) from x = 2 on."""
    east = 0.0
    p = [_pose_step("p", i, (-60.0 + 2.0 * i, 0.0), east) for i in range(31)]
    p += [_pose_step("p", i, (-60.0 + 2.0 * i, 0.0), east, valid=False) for i in range(31, 46)]
    c = [_pose_step("c", i, (2.0 + 2.0 * i, 0.0), east) for i in range(5)]
    m = [_pose_step("m", i, (-60.0 + 2.0 * i, 4.5), east) for i in range(61)]
    return [connect_segment(Segment(k, tuple(v))) for k, v in (("p", p), ("c", c), ("m", m))]


@pytest.mark.parametrize("rejoin_m, fan", [(0.0, True), (10.0, False), (30.0, False)])
def test_linked_end_gets_no_side_step_onto_a_road_it_joins_anyway(rejoin_m: float, fan: bool):
    """p's end is linked to c, and through c the map reaches m from x = 12 on. p's track enters
    m's node at x = 2, which the map does not reach from the end: ``track_linked_ends`` alone
    links it (a 4.9 m side step). With ``track_rejoin_m`` that node's road runs into what the end
    reaches within 10 m (at x 12): no link; the turn of a pivot onto a road that does not join
    again is still linked (below)."""
    graphs = _beside_a_road_joining_later()
    cfg = former(StitchConfig, track_search_m=60.0, track_linked_ends=True, track_rejoin_m=rejoin_m)
    m = stitch(graphs, config=cfg)
    assert _successor_positions(m, [10.0, 0.0]) == [[12.0, 4.5]]  # c's end joins m
    succ = sorted(_successor_positions(m, [0.0, 0.0]))
    assert succ == ([[2.0, 0.0], [2.0, 4.5]] if fan else [[2.0, 0.0]])
    assert m.extra["last_integrate"]["track_links"] == (1 if fan else 0)


def _merging_beside_a_road() -> list:
    """carla_town04_100_s2's live false link (docs/graph.md "Side steps"): pivot p drives east on
    y = 0; its steps before x = 0 failed (its track runs on y = 0 from x = -16), its chain runs
    x 0 -> 8 and merges into the main road m (y = 4.5, x -60 -> 60) at x = 10. c, mapped by
    another pivot on y = 0 (x -20 -> -2), links into p's start. Walked back from p's start, p's
    track lies in m's cross-section (10 m wide) from x = -2 back to x = -16, all within 30 m of
    path from where m and p join."""
    east = 0.0
    p = [_pose_step("p", i, (-60.0 + 2.0 * i, 0.0), east, valid=False) for i in range(22, 30)]
    p += [_pose_step("p", i, (-60.0 + 2.0 * i, 0.0), east) for i in range(30, 35)]
    c = [_pose_step("c", i, (-20.0 + 2.0 * i, 0.0), east) for i in range(10)]
    m = [_pose_step("m", i, (-60.0 + 2.0 * i, 4.5), east) for i in range(61)]
    return [connect_segment(Segment(k, tuple(v))) for k, v in (("p", p), ("c", c), ("m", m))]


@pytest.mark.parametrize("rejoin_m, both, side_step", [(0.0, True, True), (30.0, False, True), (30.0, True, False)])
def test_linked_start_gets_no_side_step_from_a_road_it_merges_into(rejoin_m: float, both: bool, side_step: bool):
    """p's start is linked from c, and p's end merges into m at x = 10. p's track, walked back,
    enters m's node at x = -2, which does not reach p's start: ``track_linked_ends`` links
    m(-2) -> p(0), a 4.9 m side step between two roads that join 10 m on. The one-sided
    ``track_rejoin_m`` looks only behind a start (m and c share no road upstream) and keeps it;
    with ``track_rejoin_both`` it also sees that m runs into what p's start reaches (m at x 10):
    no link."""
    cfg = former(
        StitchConfig, track_search_m=60.0, track_linked_ends=True, track_rejoin_m=rejoin_m, track_rejoin_both=both
    )
    m = stitch(_merging_beside_a_road(), config=cfg)
    assert _successor_positions(m, [-2.0, 0.0]) == [[0.0, 0.0]]  # c's end joins p's start
    assert _successor_positions(m, [8.0, 0.0]) == [[10.0, 4.5]]  # p merges into m
    assert sorted(_successor_positions(m, [-2.0, 4.5])) == ([[0.0, 0.0], [0.0, 4.5]] if side_step else [[0.0, 4.5]])
    assert m.extra["last_integrate"]["track_links"] == (1 if side_step else 0)


def test_track_rejoin_keeps_the_turn_a_linked_pivot_took():
    c = connect_segment(Segment("c", tuple(_pose_step("c", i, (0.0, 28.0 - 2.0 * i), -math.pi / 2) for i in range(40))))
    cfg = former(StitchConfig, track_search_m=60.0, track_linked_ends=True, track_rejoin_m=30.0)
    succ = _successor_positions(stitch(_junction(turn=True) + [c], config=cfg), [0.0, 30.0])
    assert len(succ) == 2 and [0.0, 28.0] in succ


@pytest.mark.parametrize(
    "landing_deg, next_deg, settle_deg, x_linked",
    [(-25.0, 0.0, 0.0, 20.0), (-25.0, 0.0, 8.0, 22.0), (-25.0, -20.0, 8.0, 20.0), (-12.0, 0.0, 8.0, 20.0)],
)
def test_track_link_lands_where_the_pivot_has_settled_onto_the_road(
    landing_deg: float, next_deg: float, settle_deg: float, x_linked: float
):
    """carla_town06_100_s1's false link (docs/graph.md): p's track first lies in q's cross-section
    at (18.6, 10.05), in the node at x = 20, heading ``landing_deg`` (within the 30 deg limit), and
    one step on at (22, 10) heading ``next_deg``. With ``track_settle_deg`` (8) a point more than
    16 deg off the node's heading whose next point is within 8 deg of it is still turning onto
    the road: the link lands on the node at x = 22, where the track has settled. A track still
    turning at the next point (-20 deg) or landing only 12 deg off keeps the node at x = 20."""
    p, q = _junction(turn=True)
    (row,) = np.flatnonzero(p.track_step == 50)
    assert np.allclose(p.track_xy[row], [20.0 + 20.0 * math.cos(math.pi + 1.5), 30.0 + 20.0 * math.sin(math.pi + 1.5)])
    assert p.track_step[row + 1] == 51 and np.allclose(p.track_xy[row + 1], [22.0, 10.0])
    heading = p.track_heading.copy()
    heading[row], heading[row + 1] = math.radians(landing_deg), math.radians(next_deg)
    p = dataclasses.replace(p, track_heading=heading)
    m = stitch([p, q], config=former(StitchConfig, track_search_m=60.0, track_settle_deg=settle_deg))
    assert _successor_positions(m, [0.0, 30.0]) == [[x_linked, 10.0]]
    assert m.extra["last_integrate"]["track_links"] == 1


def test_track_settle_only_in_the_default_preset():
    assert presets.preset("default").stitching.track_settle_deg == 8.0
    for name in ("naive", "paper"):
        assert presets.preset(name).stitching.track_settle_deg == 0.0
    assert former(StitchConfig).track_settle_deg == 0.0 and former_paper(StitchConfig).track_settle_deg == 0.0


def test_track_links_only_in_the_default_preset():
    d = presets.preset("default").stitching
    assert d.track_search_m > 0 and d.track_linked_ends and d.track_rejoin_m == 30.0
    for name in ("naive", "paper"):
        assert presets.preset(name).stitching.track_search_m == 0.0
    assert former(StitchConfig).track_search_m == 0.0 and former_paper(StitchConfig).track_search_m == 0.0
    assert former(StitchConfig).track_rejoin_m == 0.0 and former_paper(StitchConfig).track_rejoin_m == 0.0
    assert (
        d.track_rejoin_both
        and not former(StitchConfig).track_rejoin_both
        and not former_paper(StitchConfig).track_rejoin_both
    )


def _bridged_turn(turn: bool = True, landing_deg: float = 0.0) -> list:
    r"""Road e mapped southwards on x = 0 (y 100 -> -38) and road q eastwards on y = 10 (x -60 ->
    118), by their own pivots; both go on through the junction (no chain ends there), crossing at
    90 deg (no link). Pivot p drove south on e (processed before through e), then (``turn``) left
    through a 20 m-radius turn whose steps all failed, onto q (processed before through q; the
    first such step heading ``landing_deg``), or straight on with failed steps. p has no chain of
    its own: no start or end for the track search to walk from.

        e |   p
          |  (0, 30)
          |   \_ _ _ q -> (22, 10)
    """
    south = -math.pi / 2
    steps = [
        _pose_step("p", 0, (0.0, 100.0), south, valid=False, processed_before=True),
        _pose_step("p", 35, (0.0, 30.0), south, valid=False, processed_before=True),
    ]
    if turn:
        thetas = math.pi + 0.1 * np.arange(1, 16)  # centre (20, 30), 2 m steps, to heading 0
        steps += [
            _pose_step(
                "p", 35 + k, (20.0 + 20.0 * math.cos(t), 30.0 + 20.0 * math.sin(t)), t + math.pi / 2, valid=False
            )
            for k, t in enumerate(thetas, start=1)
        ]
        steps += [
            _pose_step("p", 51, (22.0, 10.0), math.radians(landing_deg), valid=False, processed_before=True),
            _pose_step("p", 70, (60.0, 10.0), 0.0, valid=False, processed_before=True),
        ]
    else:
        steps += [_pose_step("p", 35 + k, (0.0, 30.0 - 2.0 * k), south, valid=False) for k in range(1, 16)]
    e = Segment("e", tuple(_pose_step("e", i, (0.0, 100.0 - 2.0 * i), south) for i in range(70)))
    q = Segment("q", tuple(_pose_step("q", i, (-60.0 + 2.0 * i, 10.0), 0.0) for i in range(90)))
    return [connect_segment(Segment("p", tuple(steps))), connect_segment(e), connect_segment(q)]


def _reaches(m: HDMap, src, dst, limit: int = 200) -> bool:
    """Does topology node at ``src`` reach the node at ``dst`` along successors (BFS, ``limit`` nodes)?"""
    by_id = {t.id: t for t in m.topology}
    (a,) = [t.id for t in m.topology if np.allclose(t.position, src)]
    (b,) = [t.id for t in m.topology if np.allclose(t.position, dst)]
    seen, todo = {a}, [a]
    while todo and len(seen) < limit:
        for s in by_id[todo.pop()].successors:
            if s == b:
                return True
            if s not in seen:
                seen.add(s)
                todo.append(s)
    return False


def test_track_bridge_links_two_mapped_roads_a_pivot_turned_between():
    """carla_town04_30_s1's missed exit (docs/graph.md, "Track bridges"): the pivot's track leaves
    e, runs through failed steps and enters q, but no chain ends there, so the ordinary links,
    the arc search and the track search (default preset) give no path e -> q. The bridge links
    the node of e the track left to the node of q it entered."""
    graphs = _bridged_turn()
    assert graphs[0].n_topo == 0 and len(graphs[0].track_step) == 19
    d = presets.preset("default").stitching
    without = former_replace(d, track_bridge_m=0.0)
    assert not _reaches(stitch(graphs, config=without), [0.0, 30.0], [40.0, 10.0])
    m = stitch(graphs, config=d)
    assert m.extra["last_integrate"]["bridge_links"] == 1
    (src,) = [t for t in m.topology if len(t.successors) == 2]  # e's node that got the turn
    assert src.position[0] == 0.0 and 18.0 <= src.position[1] <= 30.0  # where the track still ran along e
    assert _reaches(m, [0.0, 30.0], [40.0, 10.0])
    # a pivot that drove straight on along e bridges nothing
    assert stitch(_bridged_turn(turn=False), config=d).extra["last_integrate"]["bridge_links"] == 0


@pytest.mark.parametrize("landing_deg, linked", [(-35.0, True), (-50.0, False)])
def test_track_bridge_enters_a_road_at_a_merge_angle(landing_deg: float, linked: bool):
    """The track enters q's cross-section while still turning: its last failed steps lie outside
    it, the step processed through q heads ``landing_deg``. Entering is accepted within
    ``tracks._TRACK_BRIDGE_HEADING_DEG`` (45 deg), wider than the 30 deg of leaving a road."""
    graphs = _bridged_turn(landing_deg=landing_deg)
    # the arc's last points lie in q's cross-section already: move them out (the pivot cut the corner)
    p = graphs[0]
    xy = p.track_xy.copy()
    late = (xy[:, 1] < 15.1) & (np.arange(len(xy)) < len(xy) - 2)
    xy[late, 1] = 15.1  # q's cross-section reaches 5 m across
    xy[-2] = [20.0, 11.0]  # the step processed through q
    graphs[0] = dataclasses.replace(p, track_xy=xy)
    m = stitch(graphs, config=presets.preset("default").stitching)
    assert (m.extra["last_integrate"]["bridge_links"] == 1) is linked


@pytest.mark.parametrize("margin_m, linked", [(0.0, False), (2.0, True)])
def test_track_bridge_leaves_a_road_its_first_point_after_a_gap_just_misses(margin_m: float, linked: bool):
    """carla_town04_50_s1's missed exit (docs/graph.md, "Track bridges"):
    the last step of p's run processed before through e (the track's first point after the run's
    gap) has a cut midpoint pulled 5.6 m across e, whose cross-section reaches 5 m; the failed
    turn lies beside e too. Without a road to leave no bridge starts; with
    ``track_bridge_leave_margin_m`` (2 m in the default preset) that point leaves e."""
    graphs = _bridged_turn()
    p = graphs[0]
    graphs[0] = dataclasses.replace(p, track_xy=p.track_xy + np.array([5.6, 0.0]))
    d = former_replace(presets.preset("default").stitching, track_bridge_leave_margin_m=margin_m)
    m = stitch(graphs, config=d)
    assert (m.extra["last_integrate"]["bridge_links"] == 1) is linked
    assert _reaches(m, [0.0, 30.0], [40.0, 10.0]) is linked
    if linked:
        (src,) = [t for t in m.topology if len(t.successors) == 2]
        assert src.position[0] == 0.0 and 28.0 <= src.position[1] <= 32.0  # the node beside that point
    # 7.5 m across: beyond the margin too, no bridge
    graphs[0] = dataclasses.replace(p, track_xy=p.track_xy + np.array([7.5, 0.0]))
    assert stitch(graphs, config=d).extra["last_integrate"]["bridge_links"] == 0


def test_track_bridge_leave_margin_only_in_the_default_preset():
    assert presets.preset("default").stitching.track_bridge_leave_margin_m == 2.0
    for name in ("naive", "paper"):
        assert presets.preset(name).stitching.track_bridge_leave_margin_m == 0.0
    assert (
        former(StitchConfig).track_bridge_leave_margin_m == 0.0
        and former_paper(StitchConfig).track_bridge_leave_margin_m == 0.0
    )


def test_track_bridges_only_in_the_default_preset():
    assert presets.preset("default").stitching.track_bridge_m == 60.0
    for name in ("naive", "paper"):
        assert presets.preset(name).stitching.track_bridge_m == 0.0
    assert former(StitchConfig).track_bridge_m == 0.0 and former_paper(StitchConfig).track_bridge_m == 0.0


def _junction_turn_split() -> tuple[list, list]:
    """``_junction(turn=True)``'s pivot p in two pieces, as two tiles hold it live: its chain
    (steps 0-35) and its failed turn with the step processed through q."""
    steps = [_pose_step("p", i, (0.0, 100.0 - 2.0 * i), -math.pi / 2) for i in range(36)]
    thetas = math.pi + 0.1 * np.arange(1, 16)
    turn = [
        _pose_step("p", 35 + k, (20.0 + 20.0 * math.cos(t), 30.0 + 20.0 * math.sin(t)), t + math.pi / 2, valid=False)
        for k, t in enumerate(thetas, start=1)
    ]
    turn += [_pose_step("p", 51, (22.0, 10.0), 0.0, processed_before=True)]
    return steps, turn


def test_track_of_a_pivot_split_over_tiles_is_followed_across_them():
    """Live, one pivot's steps come in one segment per tile: p's chain (steps 0-35) in one, its
    failed turn and the steps processed through q in the next. The end still follows the pivot's
    whole track onto q."""
    p, q = _junction(turn=True)
    steps, turn = _junction_turn_split()
    tile_a, tile_b = connect_segment(Segment("p", tuple(steps))), connect_segment(Segment("p", tuple(turn)))
    assert tile_a.key != tile_b.key and tile_a.track_step.max() == 35
    m = stitch([tile_a, tile_b, q], config=former(StitchConfig, track_search_m=60.0))
    ((x, y),) = _successor_positions(m, [0.0, 30.0])
    assert y == 10.0 and 20.0 <= x <= 24.0


def test_track_of_a_pivot_is_followed_across_live_tiles():
    """Live (``incremental.connect_tile``) each tile's graph of p has its own pivot id
    (``p#ix,iy``) and counts its steps from the tile's clip of the drive: p's chain (steps 0-35)
    in tile (0, 0); its failed turn and the steps processed through q in tile (0, -1), steps
    counted from 0 again, ``s_m`` the travelled distance of the whole drive (``map_tile``). The
    end still follows p's whole track onto q: the pieces are one track by drive and ``s_m``."""
    from hdmap_core.live.tiles import connect_tile  # noqa: PLC0415

    p, q = _junction(turn=True)
    steps, turn = _junction_turn_split()
    clip = [dataclasses.replace(st, index=st.index - 30) for st in turn]  # the tile's clip starts 60 m on
    cfg = presets.preset("default")
    (tile_a,) = connect_tile([Segment("p", tuple(steps))], (0, 0), pipeline_config=cfg)
    (tile_b,) = connect_tile([Segment("p", tuple(clip))], (0, -1), pipeline_config=cfg)
    assert tile_a.pivot_id != tile_b.pivot_id and tile_a.pivot_drive == tile_b.pivot_drive == "p"
    assert set(tile_a.track_step.tolist()) & set(tile_b.track_step.tolist())  # the step numbers overlap
    m = stitch([tile_a, tile_b, q], config=former(StitchConfig, track_search_m=60.0))
    ((x, y),) = _successor_positions(m, [0.0, 30.0])
    assert y == 10.0 and 20.0 <= x <= 24.0


def _junction_thrown_west() -> tuple[list, Segment]:
    """``_junction(turn=True)`` where the failed turn's cut midpoints were refined onto a road r
    10 m west of the pivot, which runs south from y 20 (a road the pivot never drove on): each
    step keeps the pivot's own position on the turn as its ``pose``."""
    steps = [dataclasses.replace(st, pose=st.midpoint) for st in _junction_turn_split()[0]]
    for k, t in enumerate(math.pi + 0.1 * np.arange(1, 16), start=1):
        pose = np.array([20.0 + 20.0 * math.cos(t), 30.0 + 20.0 * math.sin(t)])
        st = _pose_step("p", 35 + k, (-10.0, pose[1]), t + math.pi / 2, valid=False)
        steps.append(dataclasses.replace(st, pose=pose))
    steps += [
        dataclasses.replace(_pose_step("p", i, xy, 0.0, processed_before=True), pose=np.asarray(xy, float))
        for i, xy in ((51, (22.0, 10.0)), (70, (60.0, 10.0)))
    ]
    r = Segment("r", tuple(_pose_step("r", i, (-10.0, 20.0 - 2.0 * i), -math.pi / 2) for i in range(30)))
    return steps, r


def test_track_pose_follows_where_the_pivot_drove_not_its_failed_midpoints():
    """With ``track_pose`` (default preset) the track search follows the pivot's own positions:
    p's end links to q, where it turned. On its failed steps' midpoints (the plain default) it
    lands on r, 10 m west, where the midpoints were thrown; steps without poses (stored before)
    keep the midpoints."""
    steps, r = _junction_thrown_west()
    _, q = _junction(turn=True)
    p = connect_segment(Segment("p", tuple(steps)))
    assert len(p.track_pose) == len(p.track_step) and np.allclose(p.track_pose[-1], [60.0, 10.0])
    graphs = [p, q, connect_segment(r)]
    end = [0.0, 30.0]
    base = former(StitchConfig, track_search_m=60.0)
    assert _successor_positions(stitch(graphs, config=former(StitchConfig)), end) == []  # 14 m: no ordinary partner
    ((x, y),) = _successor_positions(stitch(graphs, config=base), end)
    assert x == -10.0  # on r: where the midpoints went
    ((x, y),) = _successor_positions(stitch(graphs, config=former_replace(base, track_pose=True)), end)
    assert y == 10.0 and 20.0 <= x <= 24.0
    assert DEFAULT.track_pose and not former(StitchConfig).track_pose and not former_paper(StitchConfig).track_pose
    no_pose = connect_segment(Segment("p", tuple(dataclasses.replace(st, pose=None) for st in steps)))
    assert len(no_pose.track_pose) == 0
    ((x, y),) = _successor_positions(
        stitch([no_pose, q, connect_segment(r)], config=former_replace(base, track_pose=True)), end
    )
    assert x == -10.0


def _stub_road(others_on: bool):
    """One pivot: solid -3.5 and border 7 m (through x 0..98 if ``others_on``, else up to x 58),
    a dashed line at 0 m up to x 58, another at 3.5 m up to x 40, and two steps of a dashed line
    at 3.5 m at x 74-76 (the neighbouring lane's line past a junction mouth)."""

    def lines(i: int):
        ys, ts = ([-3.5, 7.0], [S, B]) if others_on or i <= 29 else ([], [])
        if i <= 29:
            ys, ts = ys + [0.0], ts + [D]
        if i <= 20 or i in (37, 38):
            ys, ts = ys + [3.5], ts + [D]
        o = np.argsort(ys)
        return [ys[k] for k in o], [ts[k] for k in o]

    steps = [step("a", i, 2.0 * i, *lines(i)) for i in range(50) if lines(i)[0]]
    return conn(Segment("a", tuple(steps)))


def test_end_stub_reached_by_a_sideways_fill_dropped_where_other_lines_map_the_place():
    """The dashed line at 0 m ends at x 58; the connection bridges it 3.5 m sideways onto the
    two-step stub of the neighbouring line at x 74-76 (a filled edge, no drive's line). With
    end_stub_max_m (default preset) the stub and the fill are dropped: the line ends at x 58.
    Where no other map line lies on the stub's cross-section (the solid line and the border end
    at x 58 too), the stub is the only map point there and stays; with the dataclass default
    (0, off) it stays too."""
    g = _stub_road(others_on=True)

    def dashed_ends(m: HDMap) -> list[tuple[float, float]]:
        return sorted((round(float(f.points[-1, 0]), 1), round(float(f.points[-1, 1]), 1)) for f in by_type(m, D))

    assert DEFAULT.end_stub_max_m == 12.0 and former(StitchConfig).end_stub_max_m == 0.0
    assert dashed_ends(stitch([g], config=former_replace(DEFAULT, end_stub_max_m=0.0))) == [(40.0, 3.5), (76.0, 3.5)]
    assert dashed_ends(stitch([g], config=DEFAULT)) == [(40.0, 3.5), (58.0, 0.0)]
    lone = _stub_road(others_on=False)
    assert (76.0, 3.5) in dashed_ends(stitch([lone], config=DEFAULT))
    assert (76.0, 3.5) not in dashed_ends(stitch([lone], config=former_replace(DEFAULT, end_stub_cover_m=0.0)))


def _flicker_end(pivot: str, n: int, tail_type: int, tail: int = 5) -> Segment:
    """A solid line x 0..2(n-1) whose last ``tail`` steps were classified ``tail_type``."""
    return Segment(pivot, tuple(step(pivot, i, 2.0 * i, [0.0], [S if i < n - tail else tail_type]) for i in range(n)))


@pytest.mark.parametrize("gap_m, joined", [(2.0, True), (9.0, True), (16.0, False)])
def test_loose_ends_of_the_other_marking_type_joined_up_to_the_limit(gap_m, joined):
    """a's solid line ends in a 10 m dashed run (type flicker), b's solid line starts gap_m ahead
    (no topology link: max_distance_m 0). With join_other_marking_m 10 the end and the start are
    joined and the export's type runs make one solid polyline; without it (the dataclass, the
    paper) or beyond the limit, two polylines."""
    a = _flicker_end("a", 50, D)
    b = road("b", 98.0 + gap_m, 40, ([0.0], [S]))
    base = former(StitchConfig, max_distance_m=0.0)
    m = stitch([conn(a), conn(b)], config=former_replace(base, join_other_marking_m=10.0))
    if joined:
        assert len(m.features) == 1
        f = m.features[0]
        assert f.type == FeatureType.SOLID
        assert f.points[0, 0] == 0.0 and f.points[-1, 0] == pytest.approx(98.0 + gap_m + 78.0)
    else:
        assert len(m.features) == 2
    assert len(stitch([conn(a), conn(b)], config=base).features) == 2
    assert former_paper(StitchConfig).join_other_marking_m == 0.0 and DEFAULT.join_other_marking_m == 10.0


def test_loose_end_of_a_marking_not_joined_to_a_border_start():
    """The other-marking join is for solid / dashed only: a marking's end and a road border's
    start 2 m ahead stay apart."""
    a = _flicker_end("a", 50, D)
    b = road("b", 100.0, 40, ([0.0], [B]))
    m = stitch([conn(a), conn(b)], config=former(StitchConfig, max_distance_m=0.0, join_other_marking_m=10.0))
    assert len(m.features) == 2
    assert sum(int(f.type) == B for f in m.features) == 1


def test_cross_section_lookup_with_several_margins_equals_separate_lookups():
    """``entered_by_points`` with one margin per heading limit answers as one call per limit
    (one tree query instead of several): random nodes and track points."""
    from types import SimpleNamespace

    from scipy.spatial import cKDTree

    from hdmap_core.graph.tracks import entered_by_points

    rng = np.random.default_rng(7)
    n = 300
    t_xy = rng.uniform(0, 200, (n, 2))
    flat = SimpleNamespace(
        n_topo=n,
        t_xy=t_xy,
        t_heading=rng.uniform(-np.pi, np.pi, n),
        t_width=np.where(rng.random(n) < 0.1, np.nan, rng.uniform(4, 14, n)),
    )
    tree = cKDTree(t_xy)
    xy = rng.uniform(0, 200, (500, 2))
    heading = rng.uniform(-np.pi, np.pi, 500)
    lims, margins = (0.9, 0.5, 0.9), (0.0, 0.0, 2.0)
    together = entered_by_points(flat, tree, xy, heading, lims, 12.0, margins)
    for out, lim, mg in zip(together, lims, margins):
        (alone,) = entered_by_points(flat, tree, xy, heading, (lim,), 12.0, mg)
        np.testing.assert_array_equal(out, alone)
    assert (together[2] >= 0).sum() > (together[0] >= 0).sum() > 0  # the margin widens
    with pytest.raises(ValueError):
        entered_by_points(flat, tree, xy, heading, lims, 12.0, (0.0, 1.0))


def test_one_drive_marking_beside_the_border_is_the_solid_edge_line():
    """A line 1.2 m inside the border seen by one drive, which reports it dashed over 120 m
    between solid runs of 30 m (its misclassified stretch, longer than the runs beside it, so
    the flicker rules keep it): with ``edge_line_solid_m`` (1.5 m in the default preset) the
    marking beside the border is the road's solid edge line, one solid polyline. Seen by two
    drives, or 2 m from the border (a lane line's place), or with the option off (the
    dataclass), the drives' type stays: three polylines."""
    types = [S] * 15 + [D] * 60 + [S] * 15
    assert DEFAULT.edge_line_solid_m == 1.5 and former(StitchConfig).edge_line_solid_m == 0.0

    def edge_types(cfg: StitchConfig, count: int = 1, gap: float = 1.2) -> list[FeatureType]:
        segment = Segment(
            "a",
            tuple(
                step("a", i, 2.0 * i, [-3.5 - gap, -3.5, 0.0], [B, t, D], counts=[3, count, 3])
                for i, t in enumerate(types)
            ),
        )
        m = stitch([conn(segment)], config=cfg)
        return [
            f.type
            for f in sorted(m.features, key=lambda f: f.points[0, 0])
            if f.type != FeatureType.ROAD_BORDER and abs(f.points[0, 1] + 3.5) < 0.1
        ]

    three = [FeatureType.SOLID, FeatureType.DASHED, FeatureType.SOLID]
    assert edge_types(former_replace(DEFAULT, edge_line_solid_m=0.0)) == three
    assert edge_types(DEFAULT) == [FeatureType.SOLID]
    assert edge_types(DEFAULT, count=2) == three
    assert edge_types(DEFAULT, gap=2.0) == three
