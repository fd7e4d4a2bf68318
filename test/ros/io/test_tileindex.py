"""The tile index: one pass over a bag, the clips of the in-memory tiling read back per tile; the
tiled bag2map gives the same map with one and two workers."""

from __future__ import annotations

import pickle
from dataclasses import replace

import numpy as np
import pytest

from hdmap_core.errors import BagError, ConfigError
from hdmap_core.geometry import resample_evenly
from hdmap_core.live.tiles import TileConfig
from hdmap_core.tiled.clips import MemorySource
from hdmap_ros.io.bagio import read_fleet_bag, write_fleet_bag
from hdmap_ros.io.tileindex import POSE_STEP_M, TileIndex, build_tile_index

from bag_samples import T0_NS, make_drive


def test_index_holds_the_clips_of_the_in_memory_tiling(tmp_path, sample_bags):
    tc = TileConfig(tile_size_m=256.0, margin_m=64.0, seed=4)
    index = build_tile_index(sample_bags / "e6mini_20", tmp_path / "t.sqlite", tile_config=tc)
    fleet = read_fleet_bag(sample_bags / "e6mini_20")
    mem = MemorySource(fleet.drives, tc)
    assert index.tile_config == tc and index.drive_count == len(fleet.drives) == 20
    assert index.drive_km == pytest.approx(sum(d.length_m for d in fleet.drives) / 1000.0)
    assert index.origin == fleet.origin
    keys = index.tiles()
    assert keys == sorted(keys) and len(keys) > 3
    assert set(keys) <= set(mem.tiles())
    for key in keys:
        got, want = index.clips(key), sorted(mem.clips(key), key=lambda c: c[0].drive_id)
        assert [(c.drive_id, s0) for c, s0 in got] == [(c.drive_id, s0) for c, s0 in want]
        assert index.drive_ids(key) == [c.drive_id for c, _ in want]
        for (a, _), (b, _) in zip(got, want):
            np.testing.assert_array_equal(a.xy, b.xy)
            assert [len(d.points) for d in a.detections] == [len(d.points) for d in b.detections]
    # the poses alone, every metre, in bag order: the drives' trajectories for the lanes' connectors
    trajs = list(index.trajectories())
    assert len(trajs) == len(fleet.drives)
    for t, d in zip(trajs, fleet.drives):
        np.testing.assert_allclose(t, resample_evenly(d.xy, POSE_STEP_M), atol=1e-9)
        assert np.hypot(*np.diff(t, axis=0).T).max() <= POSE_STEP_M + 1e-9
    # a task carries the index as its path and reads it anew
    again = pickle.loads(pickle.dumps(index))
    assert len(pickle.dumps(index)) < 200 + len(str(index.path))
    assert again.drive_ids(keys[0]) == index.drive_ids(keys[0])


def test_index_keeps_what_the_reader_rejected_and_refuses_to_overwrite(tmp_path):
    good = [make_drive(f"d{i}", n=30, seed=i, start_ns=T0_NS + i * 10**9) for i in range(2)]
    bad = replace(make_drive("odd", n=30, start_ns=T0_NS + 5 * 10**9), frame_id="odom")
    bag = write_fleet_bag(tmp_path / "fleet", good + [bad], None)
    index = build_tile_index(bag, tmp_path / "t.sqlite")
    assert index.drive_count == 2 and index.origin is None
    assert [(d, r) for d, r, _ in index.rejected()] == [("odd", "wrong_frame")]
    with pytest.raises(ConfigError, match="exists"):
        build_tile_index(bag, tmp_path / "t.sqlite")
    with pytest.raises(BagError):
        build_tile_index(tmp_path / "nope", tmp_path / "u.sqlite")
    assert not (tmp_path / "u.sqlite").exists()
    (tmp_path / "junk.sqlite").write_text("not sqlite")
    with pytest.raises(BagError, match="not a tile index"):
        TileIndex(tmp_path / "junk.sqlite")


@pytest.mark.slow
def test_bag2map_tiled_is_the_same_map_with_one_and_two_workers(tmp_path, sample_bags, capsys):
    pytest.importorskip("distributed")
    import json

    from hdmap_ros import cli
    from hdmap_ros.io.bagio import read_map_bag

    maps = []
    for n in (1, 2):
        out, rep = tmp_path / f"map{n}", tmp_path / f"rep{n}.json"
        code = cli.main(
            [
                "bag2map",
                str(sample_bags / "ramps_20"),
                "-o",
                str(out),
                "--tiled",
                "--workers",
                str(n),
                "--tile-size-m",
                "384",
                "--report",
                str(rep),
                "--no-progress",
            ]
        )
        assert code == 0
        doc = json.loads(rep.read_text())
        assert doc["tiled"] and doc["drives"] == 20 and doc["build"]["workers"] == n
        maps.append(read_map_bag(out))
    assert "summary (tiled)" in capsys.readouterr().out
    a, b = maps
    assert len(a.features) == len(b.features) > 0
    for f, g in zip(a.features, b.features):
        assert f.id == g.id and tuple(f.successors) == tuple(g.successors)
        np.testing.assert_array_equal(np.asarray(f.points), np.asarray(g.points))
    assert [t.id for t in a.topology] == [t.id for t in b.topology]
    assert (
        cli.main(
            ["bag2map", str(sample_bags / "ramps_20"), "-o", str(tmp_path / "m3"), "--tiled", "--margin-m", "2000"]
        )
        == 2
    )


@pytest.mark.slow
def test_tiled_bag2map_exports_lanes_with_the_drives_poses(tmp_path, sample_bags):
    """bag2map --tiled --lanelet2 reads the drives' poses back from the index for the lanes'
    connectors: its export is the one of ``export MAP --fleet BAG`` (the drives in memory)."""
    from hdmap_core.pipeline.presets import preset
    from hdmap_ros import cli
    from hdmap_ros.io.lanelet2 import MAP_FILE
    from hdmap_ros.tiled import build_from_bag

    bag = sample_bags / "e6mini_20"
    out, ll, ll2 = tmp_path / "map", tmp_path / "ll", tmp_path / "ll2"
    argv = ["bag2map", str(bag), "-o", str(out), "--tiled", "--tile-size-m", "384", "--no-progress"]
    assert cli.main([*argv, "--lanelet2", str(ll), "--geojson", str(tmp_path / "m.geojson")]) == 0
    assert cli.main(["export", str(out), "--lanelet2", str(ll2), "--fleet", str(bag)]) == 0
    assert (ll / MAP_FILE).read_bytes() == (ll2 / MAP_FILE).read_bytes()

    got = build_from_bag(
        bag, config=preset("default"), tile_config=TileConfig(tile_size_m=384.0, margin_m=128.0), trajectories=True
    )
    fleet = read_fleet_bag(bag)
    assert len(got.trajectories) == len(fleet.drives) == 20
    for t, d in zip(got.trajectories, fleet.drives):
        np.testing.assert_allclose(t, resample_evenly(d.xy, POSE_STEP_M), atol=1e-9)
