"""Tests of hdmap_core.live.tiles: tiles, clipping, step selection, debounce, id carry-over."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from hdmap_core.errors import ConfigError
from hdmap_core.live.tiles import (
    TileConfig,
    carry_over_ids,
    clip_drive,
    needs_update,
    select_steps,
    tile_bounds,
    tile_seed,
    tiles_of_drive,
)
from hdmap_core.model import Detection, Drive, FeatureType, HDMap, MapFeature, TopologyNode
from hdmap_core.steps import Segment

from segment_samples import point_step


def _drive(xy, drive_id="d", dets=()):
    xy = np.asarray(xy, dtype=float)
    return Drive(
        drive_id=drive_id,
        xy=xy,
        yaw=np.zeros(len(xy)),
        stamps_ns=np.arange(len(xy), dtype=np.int64),
        detections=tuple(dets),
    )


def _line(x0, x1, y=0.0, n=None):
    n = n or int(abs(x1 - x0)) + 1
    return np.stack([np.linspace(x0, x1, n), np.full(n, y)], axis=1)


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(tile_size_m=0),
        dict(margin_m=-1),
        dict(margin_m=256.0),
        dict(min_growth_fraction=-0.1),
        dict(min_growth_drives=0),
    ],
)
def test_tile_config_rejects_bad_values(kwargs):
    with pytest.raises(ConfigError):
        TileConfig(**kwargs)


def test_tiles_of_drive_straight_line_with_margin():
    #   tiles of 100 m, margin 10 m; drive along y=50 from x=5 to x=195
    #   |  (0,0)  |  (1,0)  |
    #   x=5 ................ x=195 -> also within 10 m of tile (-1,0) (x<10) and (2,0) (x>190)
    cfg = TileConfig(tile_size_m=100.0, margin_m=10.0)
    keys = tiles_of_drive(_drive(_line(5, 195, y=50)), config=cfg)
    assert keys == {(-1, 0), (0, 0), (1, 0), (2, 0)}


def test_tiles_of_drive_densifies_long_pose_gaps():
    # two poses 1 km apart: every tile in between is covered
    cfg = TileConfig(tile_size_m=100.0, margin_m=0.0)
    keys = tiles_of_drive(_drive([[50, 50], [1050, 50]]), config=cfg)
    assert {(i, 0) for i in range(11)} == keys


def test_tile_bounds_and_seed_are_deterministic():
    assert tile_bounds((1, -2), tile_size_m=256.0, margin_m=10.0) == (246.0, -522.0, 522.0, -246.0)
    # the same tile draws the same seed in another process with another hash seed (a restart)
    code = "from hdmap_core.live.tiles import tile_seed; print(tile_seed((3, 4), seed=1))"
    env = {**os.environ, "PYTHONHASHSEED": "12345", "PYTHONPATH": os.pathsep.join(sys.path)}
    other = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert int(other.stdout) == tile_seed((3, 4), seed=1)
    assert tile_seed((3, 4), seed=1) != tile_seed((4, 3), seed=1)
    assert tile_seed((3, 4), seed=1) != tile_seed((3, 4), seed=2)


def test_clip_drive_cuts_trajectory_and_detection_runs():
    #        box x in [0, 100)
    #  traj  -20 ....................... 130
    #  det   -10 ..... 40      60 .. 99.5  (second run inside), 120..125 outside
    det_a = Detection(FeatureType.SOLID, _line(-10, 40, y=2))
    det_b = Detection(FeatureType.DASHED, _line(60, 125, y=-2, n=66))
    d = _drive(_line(-20, 130, n=151), dets=[det_a, det_b])
    c = clip_drive(d, (0.0, -50.0, 100.0, 50.0))
    assert c is not None and c.drive_id == d.drive_id
    np.testing.assert_allclose(c.xy[[0, -1], 0], [0.0, 99.0])
    assert len(c.yaw) == len(c.xy) == len(c.stamps_ns)
    assert [det.type for det in c.detections] == [FeatureType.SOLID, FeatureType.DASHED]
    np.testing.assert_allclose(c.detections[0].points[[0, -1], 0], [0.0, 40.0])
    assert c.detections[1].points[:, 0].max() < 100.0
    # input untouched
    assert len(d.xy) == 151 and len(d.detections[0].points) == 51


def test_clip_drive_outside_returns_none():
    assert clip_drive(_drive(_line(200, 300)), (0.0, 0.0, 100.0, 100.0)) is None


def test_select_steps_keeps_inside_and_splits_runs():
    # steps at x = -4, -2, 0, 2, 4, 200, 6 (pivot leaves and comes back) ; box x in [0, 100)
    xs = [-4, -2, 0, 2, 4, 200, 6]
    seg = Segment("p", tuple(point_step("p", i, x) for i, x in enumerate(xs)))
    out = select_steps([seg, Segment("q", ())], (0.0, -10.0, 100.0, 10.0))
    assert [[s.index for s in o.steps] for o in out] == [[2, 3, 4], [6]]
    assert all(o.pivot_id == "p" for o in out)


@pytest.mark.parametrize(
    "old,now,due",
    [
        (0, 0, False),
        (0, 1, True),
        (5, 5, False),
        (5, 6, True),
        (20, 21, False),
        (20, 22, True),
        (100, 109, False),
        (100, 110, True),
    ],
)
def test_needs_update_debounce(old, now, due):
    assert needs_update(old, now, config=TileConfig(min_growth_fraction=0.10, min_growth_drives=1)) is due


def _feat(fid, pts, ftype=FeatureType.SOLID, succ=()):
    pts = np.asarray(pts, dtype=float)
    return MapFeature(
        id=fid,
        type=ftype,
        points=pts,
        drive_count=np.ones(len(pts), int),
        lateral_std=np.zeros(len(pts)),
        successors=tuple(succ),
    )


def test_carry_over_ids_keeps_ids_of_persisting_features():
    old = HDMap(features=(_feat(11, _line(0, 100, 0)), _feat(12, _line(0, 100, 3.5), FeatureType.DASHED)))
    # new version: same lines slightly moved and longer, plus one new line; stitcher ids differ
    new = HDMap(
        features=(
            _feat(7, _line(0, 150, 3.6), FeatureType.DASHED, succ=(8,)),
            _feat(8, _line(0, 120, 0.1)),
            _feat(11, _line(0, 100, 7.0)),  # new feature whose stitcher id collides with a carried one
        ),
        topology=(TopologyNode(id=1, position=np.zeros(2), heading=0.0, width=7.0, features=(7, 8, 11)),),
    )
    out = carry_over_ids(new, old)
    ids = [f.id for f in out.features]
    assert ids[0] == 12 and ids[1] == 11
    assert ids[2] not in (11, 12) and len(set(ids)) == 3
    assert out.features[0].successors == (11,)
    assert out.topology[0].features == (12, 11, ids[2])
    np.testing.assert_array_equal(out.features[2].points, new.features[2].points)


@pytest.mark.parametrize("start", [1.0, 3.0, -1.0])
def test_carry_over_ids_keeps_the_id_of_a_line_begun_elsewhere(start):
    # the same line begun 1 or 3 m later (or earlier): resampled every 2 m its points fall between
    # the old line's points (1 m off at start 1.0), yet it lies on the old line; 0.8 m to the side
    # it is another line
    old = HDMap(features=(_feat(11, _line(0, 100, 0, n=11)),))
    on = HDMap(features=(_feat(7, _line(start, start + 100, 0.0, n=11)),))
    beside = HDMap(features=(_feat(7, _line(start, start + 100, 0.8, n=11)),))
    assert carry_over_ids(on, old).features[0].id == 11
    assert carry_over_ids(beside, old).features[0].id != 11


def test_carry_over_ids_never_gives_a_new_line_the_id_of_a_vanished_one():
    # the stitcher names features by pivot/step/slot: a new line far from the old one can come out
    # with the vanished line's id, which a consumer diffing versions would read as the same line
    old = HDMap(features=(_feat(11, _line(0, 100, 0)), _feat(12, _line(0, 100, 3.5))))
    new = HDMap(features=(_feat(11, _line(0, 100, 20.0)), _feat(12, _line(0, 100, 3.6))))
    out = carry_over_ids(new, old)
    assert out.features[1].id == 12  # continues the old line 12
    assert out.features[0].id not in (11, 12)  # line 11 vanished; its id is not reused


def test_carry_over_ids_type_must_match_and_no_old_map():
    old = HDMap(features=(_feat(5, _line(0, 100, 0), FeatureType.ROAD_BORDER),))
    new = HDMap(features=(_feat(9, _line(0, 100, 0)),))
    assert carry_over_ids(new, old).features[0].id == 9
    assert carry_over_ids(new, None) is new


def test_needs_update_default_one_drive_never_makes_a_mapped_tile_due():
    # the default debounce: one more drive never re-estimates a mapped tile, however few drives it
    # has; 3 more drives do on sparse tiles, 10 % more on dense ones
    cfg = TileConfig()
    for n in range(1, 300):
        assert not needs_update(n, n + 1, config=cfg)
        need = max(3, -(-n // 10))
        assert not needs_update(n, n + need - 1, config=cfg)
        assert needs_update(n, n + need, config=cfg)
    assert needs_update(0, 1, config=cfg)  # a new tile is always mapped


@pytest.mark.parametrize("pm", [-1.0, 129.0])
def test_tile_config_rejects_pivot_margin_outside_the_margin(pm):
    with pytest.raises(ConfigError, match="pivot_margin_m"):
        TileConfig(margin_m=128.0, pivot_margin_m=pm)


def test_steps_outside_marks_exactly_the_pivot_steps_outside_the_box():
    from hdmap_core.live.tiles import steps_outside
    from hdmap_core.pipeline.sampling import pivot_walk

    d = _drive(_line(-100, 300, n=81), drive_id="a")  # poses every 5 m, steps every 2 m
    bounds = (0.0, -10.0, 100.0, 10.0)
    store = steps_outside([d, _drive(_line(10, 90), drive_id="b")], bounds, step_m=2.0)
    s, pts, _ = pivot_walk(d, step_m=2.0)
    inside = (pts[:, 0] >= 0) & (pts[:, 0] < 100)
    np.testing.assert_array_equal(store.contains("a", s), ~inside)
    assert "b" not in store.intervals  # a drive wholly inside is not marked at all


def _sim_tile():
    from hdmap_core.pipeline import presets
    from hdmap_core.simulation.fleet import SimConfig, simulate_fleet
    from hdmap_core.simulation.synthetic import synthetic_highway

    gt = synthetic_highway("motorway", length_m=700.0, seed=3)
    fleet = simulate_fleet(gt, config=SimConfig(n_drives=4, snippet_length_min_m=500, snippet_length_max_m=600), seed=3)
    cfg = TileConfig(tile_size_m=128.0, margin_m=64.0)
    cover: dict = {}
    for d in fleet.drives:
        for k in tiles_of_drive(d, config=cfg):
            cover.setdefault(k, []).append(d)
    mid = np.asarray(fleet.drives[0].xy)[len(fleet.drives[0].xy) // 2]
    key = (int(np.floor(mid[0] / cfg.tile_size_m)), int(np.floor(mid[1] / cfg.tile_size_m)))
    return cover[key], key, cfg, presets.preset("default")


@pytest.mark.slow
def test_map_tile_pivot_margin_keeps_the_tile_and_equals_the_full_walk_at_the_margin():
    from dataclasses import replace

    from hdmap_core.live.tiles import map_tile

    drives, key, cfg, pc = _sim_tile()
    full = map_tile(drives, key, tile_config=cfg, pipeline_config=pc)
    same = map_tile(drives, key, tile_config=replace(cfg, pivot_margin_m=cfg.margin_m), pipeline_config=pc)
    near = map_tile(drives, key, tile_config=replace(cfg, pivot_margin_m=16.0), pipeline_config=pc)

    def mids(segs):
        return np.array([st.midpoint for sg in segs for st in sg.steps], dtype=float).reshape(-1, 2)

    assert len(mids(full)) > 0
    # walking the whole grown tile through the store path changes nothing
    np.testing.assert_array_equal(mids(same), mids(full))
    # walking only 16 m around the tile still maps the tile proper, and nothing outside it
    xmin, ymin, xmax, ymax = tile_bounds(key, tile_size_m=cfg.tile_size_m)
    m = mids(near)
    assert len(m) >= 0.8 * len(mids(full))
    assert ((m[:, 0] >= xmin) & (m[:, 0] < xmax) & (m[:, 1] >= ymin) & (m[:, 1] < ymax)).all()


# --- the fleet-wide offset model ------------------------------------------------------------------


def test_clip_reports_where_on_the_full_drive_the_clip_starts():
    from hdmap_core.live.tiles import _clip

    d = _drive(_line(-500, 500))  # poses every 1 m along y=0
    clipped, s0 = _clip(d, (-128.0, -10.0, 384.0, 10.0))
    assert clipped is not None and clipped.xy[0, 0] == -128.0
    assert s0 == pytest.approx(372.0)
    assert _clip(d, (600.0, 0.0, 700.0, 1.0)) == (None, 0.0)


def _positions(drive, s):
    from hdmap_core.geometry import arc_length

    xy = np.asarray(drive.xy, dtype=float)
    st = arc_length(xy)
    return np.stack([np.interp(s, st, xy[:, 0]), np.interp(s, st, xy[:, 1])], axis=1)


@pytest.mark.slow
def test_observe_tile_equals_the_tiles_own_first_pass_in_full_drive_distances():
    from hdmap_core.live.tiles import map_tile_observed, observe_tile

    drives, key, cfg, pc = _sim_tile()
    obs = observe_tile(drives, key, tile_config=cfg, pipeline_config=pc)
    _, obs2 = map_tile_observed(drives, key, tile_config=cfg, pipeline_config=pc)
    assert len(obs) > 10 and len(obs) == len(obs2)
    for a, b in zip(obs, obs2):  # the settle's observation pass and the streaming estimate agree exactly
        assert (a.pivot_id, a.index, a.drive_ids) == (b.pivot_id, b.index, b.drive_ids)
        for f in ("midpoint", "drive_s_m", "lateral_m", "types", "cluster"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    xmin, ymin, xmax, ymax = tile_bounds(key, tile_size_m=cfg.tile_size_m)
    mids = np.array([o.midpoint for o in obs], dtype=float)
    assert ((mids[:, 0] >= xmin) & (mids[:, 0] < xmax) & (mids[:, 1] >= ymin) & (mids[:, 1] < ymax)).all()
    by_id = {d.drive_id: d for d in drives}
    # the tile starts well into some drive: clip-relative distances would land far away
    assert (
        max(
            clip_drive(d, (xmin, ymin, xmax, ymax)) is not None
            and float(np.hypot(*(np.asarray(d.xy[0]) - mids.mean(axis=0))))
            for d in drives
        )
        > 150
    )
    for o in obs:
        for did in set(o.drive_ids):
            sel = np.array([x == did for x in o.drive_ids])
            pos = _positions(by_id[did], o.drive_s_m[sel])
            # a sample projected onto its own full trajectory lies beside the cut, not hundreds of m off
            assert np.hypot(*(pos - o.midpoint).T).max() < 30.0


@pytest.mark.slow
def test_preview_tile_observes_as_the_settle_does_and_maps_the_tile():
    from hdmap_core.live.tiles import observe_tile, preview_tile

    drives, key, cfg, pc = _sim_tile()
    segments, obs = preview_tile(drives, key, tile_config=cfg, pipeline_config=pc)
    obs2 = observe_tile(drives, key, tile_config=cfg, pipeline_config=pc)
    assert len(obs) > 10 and len(obs) == len(obs2)
    for a, b in zip(obs, obs2):  # the preview's observations are the settle's, exactly
        assert (a.pivot_id, a.index, a.drive_ids) == (b.pivot_id, b.index, b.drive_ids)
        for f in ("midpoint", "drive_s_m", "lateral_m", "types", "cluster"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    xmin, ymin, xmax, ymax = tile_bounds(key, tile_size_m=cfg.tile_size_m)
    mids = np.array([st.midpoint for sg in segments for st in sg.steps if st.valid], dtype=float)
    assert len(mids) > 10  # a map of the tile, its steps inside the tile proper
    assert ((mids[:, 0] >= xmin) & (mids[:, 0] < xmax) & (mids[:, 1] >= ymin) & (mids[:, 1] < ymax)).all()


@pytest.mark.slow
def test_map_tile_with_a_fleet_model_shifts_by_it_at_full_drive_distances():
    from dataclasses import replace

    from hdmap_core.live.tiles import fleet_offsets, map_tile, observe_tile
    from hdmap_core.pipeline.adjustment import DriveOffset

    drives, key, cfg, pc = _sim_tile()
    model = fleet_offsets(observe_tile(drives, key, tile_config=cfg, pipeline_config=pc), pipeline_config=pc)
    assert set(model.drives) == {d.drive_id for d in drives}

    asked = []

    class Spy:
        def offset(self, drive_id, s_m):
            asked.append((drive_id, np.asarray(s_m, dtype=float).copy()))
            return model.offset(drive_id, s_m)

        def table(self, drive_ids):
            return None  # asked drive by drive, so that every distance is seen

    base = map_tile(drives, key, tile_config=cfg, pipeline_config=pc, offset_model=Spy())
    assert base and asked
    grown = tile_bounds(key, tile_size_m=cfg.tile_size_m, margin_m=cfg.margin_m + 30.0)
    by_id = {d.drive_id: d for d in drives}
    for did, s in asked:  # the model is asked at the tile's place on the full drives
        pos = _positions(by_id[did], s)
        assert (
            (pos[:, 0] >= grown[0]) & (pos[:, 0] < grown[2]) & (pos[:, 1] >= grown[1]) & (pos[:, 1] < grown[3])
        ).all()
    # a model 1 m further left for every drive moves the tile's features by 1 m along the cuts
    plus = replace(model, drives={k: replace(v, bias_m=v.bias_m + 1.0) for k, v in model.drives.items()})
    moved = map_tile(drives, key, tile_config=cfg, pipeline_config=pc, offset_model=plus)
    from hdmap_core.steps import left_normal

    # (cuts are re-centred on the shifted samples: compare positions across the pivot's walk)
    after = {(st.pivot_id, st.index): st for sg in moved for st in sg.steps if st.valid}
    pairs = [
        (a, after[(a.pivot_id, a.index)])
        for sg in base
        for a in sg.steps
        if a.valid
        and (a.pivot_id, a.index) in after
        and len(after[(a.pivot_id, a.index)].lateral_m) == len(a.lateral_m)
    ]
    shifts = [
        float(np.dot(np.asarray(b.midpoint) - a.midpoint, np.ravel(left_normal(a.heading))))
        + np.median(b.lateral_m)
        - np.median(a.lateral_m)
        for a, b in pairs
    ]
    assert len(shifts) > 10 and abs(np.median(shifts) - 1.0) < 0.05
    assert isinstance(next(iter(model.drives.values())), DriveOffset)


def test_observations_signature_depends_on_the_drive_sets_only():
    from hdmap_core.live.tiles import observations_signature

    a = observations_signature([((0, 0), ["b", "a"]), ((1, 0), ["c"])])
    assert a == observations_signature([((1, 0), ["c"]), ((0, 0), ["a", "b"])])
    assert a != observations_signature([((0, 0), ["a", "b"]), ((1, 0), ["c", "d"])])


@pytest.mark.slow
def test_the_tiles_final_pass_is_the_pipelines_final_pass():
    # the fleet-model path runs the pipeline's passes apart (map_stretches with offset_model); given the model
    # the pipeline estimated itself, its final pass must give exactly the pipeline's segments
    from hdmap_core.live.tiles import _final_pass, _tile_input
    from hdmap_core.pipeline.driver import map_stretches

    drives, key, cfg, pc = _sim_tile()
    inp = _tile_input(drives, key, cfg, pc)
    res = map_stretches(inp.clipped, config=pc, seed=inp.seed, processed=inp.processed, validated=True)
    mine = _final_pass(inp, pc, res.offset_model)
    assert len(mine) == len(res.segments) and sum(len(s.steps) for s in mine) > 10
    for a, b in zip(mine, res.segments):
        assert a.pivot_id == b.pivot_id and len(a.steps) == len(b.steps)
        for x, y in zip(a.steps, b.steps):
            assert (x.index, x.valid, x.drive_ids) == (y.index, y.valid, y.drive_ids)
            np.testing.assert_array_equal(x.lateral_m, y.lateral_m)
            np.testing.assert_array_equal(x.midpoint, y.midpoint)
            # the negative evidence too (the live stitcher drops fills by it as offline)
            assert (x.empty_m is None) == (y.empty_m is None)
            if x.empty_m is not None:
                np.testing.assert_array_equal(x.empty_m, y.empty_m)
    assert any(st.empty_m is not None for sg in mine for st in sg.steps)


def _same_segments(a, b):
    assert len(a) == len(b)
    for sa, sb in zip(a, b):
        assert sa.pivot_id == sb.pivot_id and len(sa.steps) == len(sb.steps)
        for x, y in zip(sa.steps, sb.steps):
            assert (x.index, x.s_m, x.valid, x.drive_ids) == (y.index, y.s_m, y.valid, y.drive_ids)
            for f in ("lateral_m", "types", "counts", "midpoint", "pose"):
                np.testing.assert_array_equal(getattr(x, f), getattr(y, f))
            assert (x.empty_m is None) == (y.empty_m is None)
            if x.empty_m is not None:
                np.testing.assert_array_equal(x.empty_m, y.empty_m)


@pytest.mark.slow
def test_tile_work_gives_the_preview_and_the_final_pass_of_the_tile_functions():
    # the settle's final pass reuses the observation pass's preprocessing and cut intersections
    # (TileWork); the segments must be exactly those of the tile made afresh with the model
    from hdmap_core.live.tiles import TileWork, fleet_offsets, map_tile, preview_tile

    drives, key, cfg, pc = _sim_tile()
    work = TileWork(drives, key, tile_config=cfg, pipeline_config=pc)
    segs, obs = work.preview()
    segs0, obs0 = preview_tile(drives, key, tile_config=cfg, pipeline_config=pc)
    _same_segments(segs, segs0)
    assert len(obs) == len(obs0) > 10
    for a, b in zip(obs, obs0):
        assert (a.pivot_id, a.index, a.drive_ids) == (b.pivot_id, b.index, b.drive_ids)
        np.testing.assert_array_equal(a.drive_s_m, b.drive_s_m)
    assert work.preview() is work.preview()  # made once
    model = fleet_offsets(obs, pipeline_config=pc)
    final = work.final(model)
    assert sum(st.valid for sg in final for st in sg.steps) > 10
    _same_segments(final, map_tile(drives, key, tile_config=cfg, pipeline_config=pc, offset_model=model))


def test_tile_work_of_a_tile_no_drive_reaches_is_empty():
    from hdmap_core.live.tiles import TileWork
    from hdmap_core.pipeline import presets

    d = _drive(_line(0.0, 100.0), "a")
    work = TileWork([d], (50, 50), tile_config=TileConfig(), pipeline_config=presets.preset("default"))
    assert work.preview() == ([], [])
    assert work.final(None) == []  # type: ignore[arg-type]
