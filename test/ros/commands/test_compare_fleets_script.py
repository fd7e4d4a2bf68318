"""scripts/compare_fleets.py (a rule measured on many fleets), scripts/restitch_state.py (the
live map rebuilt from its stores) and scripts/targets.py (the mapping targets checked on bench
results)."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

from hdmap_core.pipeline import presets
from hdmap_core.pipeline.overrides import config_from
from hdmap_ros.commands.bench import SCORE_COLUMNS

REPO = Path(__file__).resolve().parents[3]


def _load(name: str) -> ModuleType:
    """scripts/<name>.py as a module."""
    spec = importlib.util.spec_from_file_location(f"_scripts_{name}", REPO / "scripts" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _script() -> ModuleType:
    return _load("compare_fleets")


@pytest.mark.slow
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


@pytest.mark.slow
def test_a_bag_that_cannot_be_used_is_named_and_the_rest_goes_on(capsys, tmp_path):
    cf = _script()
    bad = tmp_path / "broken.mcap"
    bad.write_bytes(b"not an mcap file")
    (tmp_path / "broken.mcap.gt.json").write_text((REPO / "bags" / "ramps_20.gt.json").read_text())
    assert cf.main([str(bad), str(REPO / "bags" / "ramps_20"), "--workers", "1"]) == 1
    out, err = capsys.readouterr()
    assert "compare_fleets: broken" in err
    assert out.strip().splitlines()[-1].startswith("ramps_20 ")


@pytest.mark.slow
def test_restitch_state_rebuilds_the_map_of_a_stored_tile(capsys, tmp_path):
    """A map_stitcher store holding one tile's segments (those of bags/ramps_20) is connected and
    stitched as the node does it: the same map as connect_tile + stitch_graphs, scored."""
    from hdmap_core.live.tiles import connect_tile, stitch_graphs
    from hdmap_core.pipeline.driver import build_map
    from hdmap_ros.io.bagio import read_fleet_bag
    from hdmap_ros.persistence.store import MapStore, segments_to_blob

    rs = _load("restitch_state")
    fleet = read_fleet_bag(REPO / "bags" / "ramps_20")
    config = presets.preset("default")
    segments = build_map(fleet.drives, config=config).segments
    state = tmp_path / "state"
    state.mkdir()
    MapStore(state / "map_stitcher.db").put_tile(
        (0, 0), 1, segments_to_blob(segments), [d.drive_id for d in fleet.drives]
    )
    direct = stitch_graphs(connect_tile(segments, (0, 0), pipeline_config=config), pipeline_config=config)
    hdmap, n_tiles = rs.restitch(state, config)
    assert n_tiles == 1 and len(hdmap.features) == len(direct.features) > 0
    assert [f.id for f in hdmap.features] == [f.id for f in direct.features]
    assert rs.main([str(state), "--gt", str(REPO / "bags" / "ramps_20.gt.json")]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("1 tiles -> ") and out[2].split()[0] == "state" and float(out[2].split()[7]) > 90.0
    assert rs.main([str(tmp_path / "nowhere")]) == 2
    assert "no map_stitcher store" in capsys.readouterr().err
    assert rs.main([str(state), "--set", "stitching.max_distance_m=8"]) == 0  # changes go through bag2map's parser


def _run(scenario: str, preset: str = "default", **figures) -> dict:
    """A bench JSON run meeting every target, with ``figures`` changed."""
    run = {
        "scenario": scenario,
        "preset": preset,
        "drives": 40,
        "mean_m": 0.2,
        "p95_m": 0.4,
        "corrected_mean_m": 0.05,
        "floor_m": 0.2,
        "fleet_floor_m": 0.18,
        "coverage": 0.99,
        "driven_share": 1.0,
        "recall": 0.98,
        "observed_share": 0.99,
        "recall_observed": 0.99,
        "precision": 0.99,
        "type_accuracy": 0.99,
        "fragmentation": 1.1,
        "splits_merges": "1/1 1/1",
        "gt_splits": 1,
        "gt_merges": 1,
        "found_splits": 1,
        "found_merges": 1,
        "road_splits_merges": "2/2 2/2",
        "gt_road_splits": 2,
        "gt_road_merges": 2,
        "found_road_splits": 2,
        "found_road_merges": 2,
        "long_links": "100.0% 5/5",
        "long_link_precision": 1.0,
    }
    run.update(figures)
    return run


def test_targets_names_each_miss_and_what_bounds_it(tmp_path, capsys):
    tg = _load("targets")
    assert tg.misses(_run("a_s1")) == []
    missed = tg.misses(_run("a_s1", recall=0.9, observed_share=0.92, recall_observed=0.97))
    assert missed == ["recall 90.0 % (observed 92.0 %, recall obs. 97.0 %)"]
    missed = tg.misses(_run("a_s1", mean_m=0.41, fleet_floor_m=0.40, fragmentation=1.6, found_road_merges=1))
    assert missed[0] == "mean 0.410 m > 0.30 (fleet's own error 0.400 m)" and "2.05 x floor" in missed[1]
    assert missed[2:] == ["fragm. 1.60", "road splits/merges 2/2 2/2"]
    assert tg.misses(_run("a_s1", recall=0.9, observed_share=0.99)) == ["recall 90.0 %"]  # nothing bounds it
    # bound by the fleet only where the map meets the target over what the fleet allows
    assert tg.own_misses(_run("a_s1", recall=0.9, observed_share=0.92, recall_observed=0.97)) == []
    assert tg.own_misses(_run("a_s1", recall=0.9, observed_share=0.92, recall_observed=0.94)) == [
        "recall 90.0 % (observed 92.0 %, recall obs. 94.0 %)"
    ]
    assert tg.own_misses(_run("a_s1", mean_m=0.41, fleet_floor_m=0.40)) == []  # 1.03 x the fleet's own error
    assert len(tg.own_misses(_run("a_s1", mean_m=0.47, fleet_floor_m=0.40))) == 2  # 1.18 x: the map's own
    assert tg.own_misses(_run("a_s1", coverage=0.9, driven_share=0.92, coverage_driven=0.98)) == []
    assert tg.own_misses(_run("a_s1", coverage=0.9, driven_share=0.92, coverage_driven=0.95)) != []
    # a peer preset better on one figure (ties are no loss)
    lost = tg.losses(_run("a_s1"), [_run("a_s1", "naive", long_link_precision=1.0, precision=0.995, recall=0.98)])
    assert lost == ["precision vs naive"]
    runs = [
        _run("a_s1"),
        _run("a_s1", "naive", mean_m=0.5),
        _run("a"),
        _run("b_s2", coverage=0.9, driven_share=0.95),
        _run("c_s3", recall=0.9, observed_share=0.92, recall_observed=0.97),
    ]
    path = tmp_path / "bench.json"
    path.write_text(__import__("json").dumps(runs))
    assert tg.main([str(path)]) == 0
    out = capsys.readouterr().out
    assert "| a_s1 | 40 | none | none | naive |" in out and "| a |" not in out  # means over seeds left out
    assert "| b_s2 | 40 | coverage 90.0 % (driven 95.0 %) | none | - |" in out
    assert "1 of 3 fleets meet every target and" in out
    assert "2 of 3 fleets meet every target their fleet allows" in out  # c_s3: recall bound by the fleet
    assert tg.main([str(path), "--misses-only"]) == 0
    out = capsys.readouterr().out
    assert "| a_s1 |" not in out and "| b_s2 |" in out and "1 of 3 fleets meet every target" in out
    # a bench --set run's rows (default+) checked against the shipped presets, the default among them
    changed = tmp_path / "changed.json"
    changed.write_text(__import__("json").dumps([_run("a_s1", "default+", precision=0.985)]))
    assert tg.main([str(path), str(changed), "--preset", "default+"]) == 0
    out = capsys.readouterr().out
    (row,) = [line for line in out.splitlines() if line.startswith("| a_s1 |")]
    assert row.startswith("| a_s1 | 40 | none | ") and row.endswith(" | default, naive |")
    assert "precision vs default" in row and "precision vs naive" in row  # both at 99 %
    assert "0 of 1 fleets meet every target" in out
    assert tg.main([str(path), "--preset", "default+"]) == 2  # not in these runs: named, not "0 of 0"
    assert "no run of preset 'default+'" in capsys.readouterr().err


def test_ablation_switches_each_change_the_default_and_the_table_lists_them_per_fleet():
    ab = _load("ablation")
    default = presets.preset("default")
    changed = set()
    for label, sets in ab.SWITCHES:
        config = config_from(default, list(sets))
        assert config != default, label  # a switch that changes nothing would measure nothing
        changed.add(config)
    assert len(changed) == len(ab.SWITCHES)  # no two switches are the same change
    base = [_run("a_s1"), _run("b_s2", mean_m=0.25)]
    variants = [("no x", [_run("b_s2", "default+", mean_m=0.4), _run("a_s1", "default+", mean_m=0.3)])]
    lines = ab.table(base, variants).splitlines()
    assert len(lines) == 2 + 4
    assert lines[2].startswith("| a_s1 | default | 0.200 |") and lines[3].startswith("| a_s1 | no x | 0.300 |")
    assert lines[4].startswith("| b_s2 | default | 0.250 |") and lines[5].startswith("| b_s2 | no x | 0.400 |")
    assert "| 99.0% |" in lines[2] and lines[2].endswith("| - |")  # no build time in the run: a dash
