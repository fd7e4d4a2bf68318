"""scripts/compare_fleets.py (a rule measured on many fleets) and scripts/restitch_state.py (the
live map rebuilt from its stores)."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

from hdmap_core.pipeline import PipelineConfig
from hdmap_ros.commands.bench import SCORE_COLUMNS

REPO = Path(__file__).resolve().parents[2]


def _load(name: str) -> ModuleType:
    """scripts/<name>.py as a module."""
    spec = importlib.util.spec_from_file_location(f"_scripts_{name}", REPO / "scripts" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _script() -> ModuleType:
    return _load("compare_fleets")


def test_scores_a_sample_bag_and_rejects_an_unknown_key(capsys, tmp_path):
    cf = _script()
    assert cf.main([str(REPO / "bags" / "ramps_20"), "--workers", "1", "--save", str(tmp_path)]) == 0
    header, line = capsys.readouterr().out.strip().splitlines()
    assert header == SCORE_COLUMNS
    fields = line.split()
    assert fields[0] == "ramps_20" and len(fields) == len(header.split())
    mean, precision = float(fields[1]), float(fields[7])
    assert 0.0 < mean < 0.5 and precision > 90.0  # a real map of the bag, scored against its GT
    assert (tmp_path / "ramps_20.pkl").exists()
    assert cf.main([str(REPO / "bags" / "ramps_20"), "--set", "stitching.nope=1"]) == 2
    assert "--set stitching.nope: StitchConfig has no field 'nope'" in capsys.readouterr().err
    assert cf.main(["no_such_map:3"]) == 2  # a bad scenario is named as such, not as a --set
    err = capsys.readouterr().err
    assert "no_such_map" in err and "--set" not in err


def test_a_bag_that_cannot_be_used_is_named_and_the_rest_goes_on(capsys, tmp_path):
    cf = _script()
    bad = tmp_path / "broken.mcap"
    bad.write_bytes(b"not an mcap file")
    (tmp_path / "broken.mcap.gt.json").write_text((REPO / "bags" / "ramps_20.gt.json").read_text())
    assert cf.main([str(bad), str(REPO / "bags" / "ramps_20"), "--workers", "1"]) == 1
    out, err = capsys.readouterr()
    assert "compare_fleets: broken" in err
    assert out.strip().splitlines()[-1].startswith("ramps_20 ")


def test_restitch_state_rebuilds_the_map_of_a_stored_tile(capsys, tmp_path):
    """A map_stitcher store holding one tile's segments (those of bags/ramps_20) is connected and
    stitched as the node does it: the same map as connect_tile + stitch_graphs, scored."""
    from hdmap_core.incremental import connect_tile, stitch_graphs
    from hdmap_core.pipeline import build_map
    from hdmap_ros.bagio import read_fleet_bag
    from hdmap_ros.store import MapStore, segments_to_blob

    rs = _load("restitch_state")
    fleet = read_fleet_bag(REPO / "bags" / "ramps_20")
    config = PipelineConfig.preset("default")
    segments = build_map(fleet.drives, config=config).segments
    state = tmp_path / "state"
    state.mkdir()
    MapStore(state / "map_stitcher.db").put_tile((0, 0), 1, segments_to_blob(segments), [d.drive_id for d in fleet.drives])
    direct = stitch_graphs(connect_tile(segments, (0, 0), pipeline_config=config), pipeline_config=config)
    hdmap, n_tiles = rs.restitch(state, config)
    assert n_tiles == 1 and len(hdmap.features) == len(direct.features) > 0
    assert [f.id for f in hdmap.features] == [f.id for f in direct.features]
    assert rs.main([str(state), "--gt", str(REPO / "bags" / "ramps_20.gt.json")]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("1 tiles -> ") and out[2].split()[0] == "state" and float(out[2].split()[7]) > 90.0
    assert rs.main([str(tmp_path / "nowhere")]) == 2
    assert "no map_stitcher store" in capsys.readouterr().err
    assert rs.main([str(state), "--set", "stitching.track_rejoin_m=0"]) == 0  # changes go through bag2map's parser
