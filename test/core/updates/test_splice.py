"""The changed places rebuilt alone and spliced into the first map (``updates.splice``)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from hdmap_core.model import FeatureType, HDMap, MapFeature, TopologyNode
from hdmap_core.updates.detect import DetectedChange, PlaceChange
from hdmap_core.updates.follow import retired_features
from hdmap_core.updates.places import Places
from hdmap_core.updates.splice import Reach, grow, shifted, splice

PLACES = Places(100.0, {(i, 0): 0.0 for i in range(-1, 7)})
CORE = {(2, 0, 0)}  # x in [200, 300), running +x


def _line(fid: int, x0: float, x1: float, y: float, ftype=FeatureType.DASHED, reverse=False) -> MapFeature:
    x = np.arange(x0, x1 + 1e-9, 2.0)
    pts = np.stack([x, np.full_like(x, y)], axis=1)
    pts = pts[::-1].copy() if reverse else pts
    return MapFeature(fid, ftype, pts, np.full(len(pts), 5), np.full(len(pts), 0.1))


def _nodes(first_id: int, x0: float, x1: float, y: float, feature_ids) -> tuple[TopologyNode, ...]:
    xs = np.arange(x0, x1 + 1e-9, 10.0)
    return tuple(
        TopologyNode(
            first_id + i, np.array([x, y]), 0.0, 7.0, (first_id + i + 1,) if i + 1 < len(xs) else (), feature_ids
        )
        for i, x in enumerate(xs)
    )


def test_splice_takes_the_changed_places_from_the_local_map_and_keeps_the_rest():
    first = HDMap(
        features=(
            _line(1, 0.0, 500.0, 10.0, FeatureType.SOLID),
            _line(2, 0.0, 500.0, 13.5),
            _line(3, 0.0, 500.0, 5.0, FeatureType.SOLID, reverse=True),  # the other carriageway
            _line(4, 400.0, 500.0, 17.0),  # never enters the changed place
        ),
        topology=_nodes(0, 0.0, 500.0, 12.0, (1, 2)),
        drive_ids=("a",),
    )
    local = HDMap(
        features=(_line(1, 150.0, 350.0, 11.0, FeatureType.SOLID), _line(7, 150.0, 350.0, 14.5)),
        topology=_nodes(0, 150.0, 350.0, 13.0, (1, 7)),
        drive_ids=("a/0", "b"),
    )
    out = splice(first, local, PLACES, CORE)
    by_id = {f.id: f for f in out.features}
    # untouched: the other carriageway and the line that never enters the place, as they were
    assert by_id[3] is first.features[2] and by_id[4] is first.features[3]
    # every point in the changed place comes from the local map, every other one from the first
    for f in out.features:
        inside = (f.points[:, 0] >= 200.0) & (f.points[:, 0] < 300.0) & (f.points[:, 1] > 8.0)
        assert np.all(np.isin(f.points[inside, 1], [11.0, 14.5]))
        assert np.all(np.isin(f.points[~inside, 1], [5.0, 10.0, 13.5, 17.0]))
    solid = sorted((f for f in out.features if f.type == FeatureType.SOLID and f.id != 3), key=lambda f: f.points[0, 0])
    assert [round(f.points[0, 0]) for f in solid] == [0, 200, 300]
    assert solid[0].id == 1  # the first piece keeps the feature's id
    assert len({f.id for f in out.features}) == len(out.features)
    # linked across both seams
    assert solid[1].id in solid[0].successors and solid[2].id in solid[1].successors
    assert solid[0].id in solid[1].predecessors
    # topology: local nodes inside, first nodes outside, successors across the seams
    pos = {n.id: n.position for n in out.topology}
    core_nodes = [n for n in out.topology if 200.0 <= n.position[0] < 300.0]
    assert core_nodes and all(n.position[1] == 13.0 for n in core_nodes)
    assert all(n.position[1] == 12.0 for n in out.topology if not 200.0 <= n.position[0] < 300.0)
    before_seam = next(n for n in out.topology if n.position[0] == 190.0)
    assert [pos[s][0] for s in before_seam.successors] == [200.0]
    last_inside = max(core_nodes, key=lambda n: n.position[0])
    assert [pos[s][0] for s in last_inside.successors] == [300.0]
    assert all(s in pos for n in out.topology for s in n.successors)
    assert set(out.drive_ids) == {"a", "a/0", "b"}


def test_shifted_moves_features_left_by_their_place_and_grow_adds_neighbours():
    hdmap = HDMap(features=(_line(1, 0.0, 500.0, 10.0),))
    out = shifted(hdmap, {(k, 0, 0): 0.5 for k in range(5)}, PLACES)
    np.testing.assert_allclose(out.features[0].points[:, 1], 10.5)
    np.testing.assert_allclose(out.features[0].points[:, 0], hdmap.features[0].points[:, 0])
    assert shifted(hdmap, {}, PLACES) is hdmap
    assert grow(PLACES, CORE, 1) == {(1, 0, 0), (2, 0, 0), (3, 0, 0)}
    assert grow(PLACES, CORE, 0) == CORE


def _solid(fid: int, x0: float, x1: float, y: float, pred=(), succ=()) -> MapFeature:
    return replace(_line(fid, x0, x1, y, FeatureType.SOLID), predecessors=tuple(pred), successors=tuple(succ))


def test_splice_keeps_the_links_of_the_ends_it_keeps():
    # the live map of motorway_ramps had lost a lane split's connection outside the zone: a feature
    # cut by the changed place must keep the links at its ends outside it, on the pieces holding them
    inlet = _solid(3, 0.0, 100.0, 10.0, succ=(1,))  # ends where line 1 starts
    line = _solid(1, 100.0, 400.0, 10.0, pred=(3,), succ=(4,))  # crosses the changed place
    outlet = _solid(4, 400.0, 500.0, 10.0, pred=(1,))
    into = _solid(5, 0.0, 198.0, 30.0, succ=(6,))  # ends just before the changed place ...
    onward = _solid(6, 200.0, 500.0, 30.0, pred=(5,))  # ... where 6 starts; 6 leaves it at 300
    first = HDMap(features=(inlet, line, outlet, into, onward))
    out = splice(first, HDMap(), PLACES, CORE)
    by_id = {f.id: f for f in out.features}
    assert len(by_id) == len(out.features)
    head = by_id[1]  # the piece that starts where line 1 started keeps its id and predecessor
    assert (head.points[0, 0], head.points[-1, 0]) == (100.0, 198.0)
    assert head.predecessors == (3,) and head.successors == ()
    (tail,) = [f for f in out.features if f.id not in (1, 3, 4, 5, 6) and f.points[0, 1] == 10.0]
    assert (tail.points[0, 0], tail.points[-1, 0]) == (300.0, 400.0)  # holds its last point: its links
    assert tail.predecessors == () and tail.successors == (4,)
    assert by_id[3].successors == (1,) and by_id[4].predecessors == (tail.id,)
    # a link to an end the changed place took is dropped, not moved to a piece 100 m on
    assert by_id[5].points.shape == into.points.shape and by_id[5].successors == ()
    (rest,) = [f for f in out.features if f.points[0, 1] == 30.0 and f.points[0, 0] >= 300.0]
    assert rest.id == 6 and rest.predecessors == ()  # 6's only piece, from the changed place's end


def test_splice_keeps_what_no_drive_after_the_change_could_see():
    # motorway_ramps, shift of one carriageway: the drives after the change kept to the
    # carriageway, the ramp's far border in the same places (18 m off) was left to nobody; the
    # first map must keep it there, not leave a 100 m gap (nor take a stray local line there)
    border = _line(4, 0.0, 500.0, 30.0, FeatureType.ROAD_BORDER)
    first = HDMap(features=(_line(1, 0.0, 500.0, 10.0, FeatureType.SOLID), border))
    local = HDMap(
        features=(
            _line(1, 150.0, 350.0, 11.0, FeatureType.SOLID),
            _line(2, 150.0, 350.0, 30.5, FeatureType.ROAD_BORDER),  # beyond reach: not taken
        )
    )
    poses = np.stack([np.arange(200.0, 300.0, 1.0), np.full(100, 12.0)], axis=1)
    out = splice(first, local, PLACES, CORE, reach=Reach(poses, 12.0))
    assert any(f is border for f in out.features)  # kept whole, as it was
    far = [f for f in out.features if f.type == FeatureType.ROAD_BORDER]
    assert len(far) == 1
    solid_in = np.concatenate([f.points for f in out.features if f.type == FeatureType.SOLID])
    solid_in = solid_in[(solid_in[:, 0] >= 200.0) & (solid_in[:, 0] < 300.0)]
    assert len(solid_in) and np.all(solid_in[:, 1] == 11.0)  # within reach: the local map's
    # without reach every point of the place is replaced: the border loses its piece there
    cut = splice(first, local, PLACES, CORE)
    gone = np.concatenate([f.points for f in cut.features if f.type == FeatureType.ROAD_BORDER])
    assert not np.any((gone[:, 0] >= 200.0) & (gone[:, 0] < 300.0) & (gone[:, 1] == 30.0))
    # and the history retires only what was replaced
    change = DetectedChange(1, 5, ("geometry",), (PlaceChange((2, 0, 0), "geometry", 5, 1, 1.5, 9.0, (), ()),), (), 0.9)
    retired = retired_features(first, PLACES, [change], valid_from_ns=0, reach=Reach(poses, 12.0))
    assert [r.feature_id for r in retired] == [1]
    assert {r.feature_id for r in retired_features(first, PLACES, [change], valid_from_ns=0)} == {1, 4}


def test_splice_keeps_the_first_maps_borders_the_local_map_lacks_but_not_inside_the_road():
    # seeds 0-2 of shift10: the drives after the change saw the shoulder border once at most
    # (visibility 0.6) and the rebuild dropped it; a change leaves the borders in place (the
    # local map is aligned on them), so the first map's border stays where the local map has
    # none within border_m -- but not a "border" with local markings on both sides (a first-map
    # artefact across the lanes)
    shoulder = _line(5, 0.0, 500.0, 4.0, FeatureType.ROAD_BORDER)
    across = _line(6, 150.0, 350.0, 12.5, FeatureType.ROAD_BORDER)  # between lines 10 and 14.5
    first = HDMap(features=(_line(1, 0.0, 500.0, 10.0, FeatureType.SOLID), shoulder, across))
    local = HDMap(
        features=(_line(1, 150.0, 350.0, 11.0, FeatureType.SOLID), _line(7, 150.0, 350.0, 14.5, FeatureType.DASHED))
    )
    poses = np.stack([np.arange(200.0, 300.0, 1.0), np.full(100, 12.0)], axis=1)
    marks = np.concatenate([f.points for f in local.features])
    reach = Reach(poses, 12.0, np.zeros((0, 2)), 3.0, marks)
    out = splice(first, local, PLACES, CORE, reach=reach)
    assert any(f is shoulder for f in out.features)
    pts = np.concatenate([f.points for f in out.features if f.type == FeatureType.ROAD_BORDER])
    assert not np.any((pts[:, 0] >= 200.0) & (pts[:, 0] < 300.0) & (pts[:, 1] == 12.5))
    # a local border within border_m replaces it as before
    local_b = replace(local, features=(*local.features, _line(8, 150.0, 350.0, 5.0, FeatureType.ROAD_BORDER)))
    reach_b = Reach(poses, 12.0, local_b.features[-1].points, 3.0, marks)
    out_b = splice(first, local_b, PLACES, CORE, reach=reach_b)
    pts = np.concatenate([f.points for f in out_b.features if f.type == FeatureType.ROAD_BORDER])
    inside = (pts[:, 0] >= 200.0) & (pts[:, 0] < 300.0)
    assert np.all(np.isin(pts[inside, 1], [5.0]))
