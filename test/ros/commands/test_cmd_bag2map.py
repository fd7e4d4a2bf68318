"""`hdmap bag2map`: argument handling, bad input, and the wiring around build_map (faked here)."""

from __future__ import annotations

import json
from dataclasses import dataclass, replace

import numpy as np
import pytest

from hdmap_core.model import GeoOrigin
from hdmap_ros import cli
from hdmap_ros.io.bagio import read_fleet_bag, read_map_bag, write_fleet_bag

from bag_samples import T0_NS, assert_maps_equal, install_fake_pipeline, make_drive, make_map

ORIGIN = GeoOrigin(57.7, 11.97, 5.0)


@pytest.fixture
def fake_pipeline(monkeypatch):
    """A stand-in for hdmap_core.pipeline.driver with the contract's API; records its calls."""
    calls = {}

    @dataclass(frozen=True)
    class BuildReport:
        n_drives_used: int

        def summary(self):
            return f"drives used {self.n_drives_used}"

    @dataclass(frozen=True)
    class BuildResult:
        map: object
        report: BuildReport
        drives: list  # the drives the map was built from

    def build_map(drives, *, config, seed=0, progress=None, workers=1):
        calls.update(drives=list(drives), config=config, seed=seed, workers=workers)
        if progress is not None:
            progress("pivots", 1, 2)
            progress("pivots", 2, 2)
        return BuildResult(make_map(n_features=3), BuildReport(len(drives)), list(drives))

    install_fake_pipeline(monkeypatch, build_map)
    return calls


def _fleet(tmp_path, drives, origin=ORIGIN):
    return write_fleet_bag(tmp_path / "fleet", drives, origin)


def test_wiring_writes_map_bag_and_geojson(tmp_path, fake_pipeline, capsys):
    good = [make_drive(f"d{i}", n=20, seed=i, start_ns=T0_NS + i * 10**9) for i in range(3)]
    bad = replace(make_drive("broken", n=20, start_ns=T0_NS + 9 * 10**9), frame_id="odom")
    bag = _fleet(tmp_path, good + [bad])
    out, gj = tmp_path / "map", tmp_path / "map.geojson"
    rep = tmp_path / "report.json"
    code = cli.main(
        [
            "bag2map",
            str(bag),
            "-o",
            str(out),
            "--geojson",
            str(gj),
            "--preset",
            "paper",
            "--seed",
            "7",
            "--report",
            str(rep),
            "--workers",
            "3",
        ]
    )
    assert code == 0
    assert fake_pipeline["workers"] == 3
    doc = json.loads(rep.read_text())
    assert doc["drives"] == 3 and doc["rejected"][0]["drive_id"] == "broken" and doc["build"]["n_drives_used"] == 3
    assert [d.drive_id for d in fake_pipeline["drives"]] == ["d0", "d1", "d2"]
    assert fake_pipeline["config"].name == "paper" and fake_pipeline["seed"] == 7
    got = read_map_bag(out)
    assert_maps_equal(make_map(n_features=3), got)
    assert got.extra["origin"] == ORIGIN
    kinds = [f["properties"]["kind"] for f in json.loads(gj.read_text())["features"]]
    assert kinds.count("road_feature") == 3 and set(kinds) <= {"road_feature", "lane"}
    captured = capsys.readouterr()
    assert "broken" in captured.err and "wrong_frame" in captured.err
    assert "drives used 3" in captured.out and "rejected 1" in captured.out


def test_graphml_writes_the_topology_graph(tmp_path, fake_pipeline, capsys):
    """``--graphml`` writes the map's topology nodes and successor links, read back by networkx."""
    nx = pytest.importorskip("networkx")
    bag = _fleet(tmp_path, [make_drive("a", n=10)])
    gml = tmp_path / "map.graphml"
    assert cli.main(["bag2map", str(bag), "-o", str(tmp_path / "map"), "--graphml", str(gml)]) == 0
    want = make_map(n_features=3)
    g = nx.read_graphml(gml, node_type=int)
    assert sorted(g.nodes) == sorted(t.id for t in want.topology)
    assert sorted(g.edges) == sorted((t.id, s) for t in want.topology for s in t.successors)
    last = want.topology[-1]
    assert g.nodes[last.id]["width"] == pytest.approx(last.width)
    assert [int(f) for f in g.nodes[last.id]["features"].split()] == list(last.features)
    assert "10 nodes, 9 links" in capsys.readouterr().out


def test_graphml_into_a_directory_is_refused(tmp_path, capsys):
    code = cli.main(["bag2map", str(tmp_path / "nope"), "-o", str(tmp_path / "map"), "--graphml", str(tmp_path)])
    assert code == 2 and "--graphml" in capsys.readouterr().err


def test_set_changes_preset_parameters_and_the_report_names_them(tmp_path, fake_pipeline, capsys):
    bag = _fleet(tmp_path, [make_drive("a", n=10)])
    rep = tmp_path / "report.json"
    code = cli.main(
        [
            "bag2map",
            str(bag),
            "-o",
            str(tmp_path / "map"),
            "--report",
            str(rep),
            "--set",
            "stitching.max_distance_m=8",
            "--set",
            "alignment.clustering=auto",
        ]
    )
    assert code == 0
    config = fake_pipeline["config"]
    assert config.name == "default+"
    assert config.overrides == (("stitching.max_distance_m", 8), ("alignment.clustering", "auto"))
    assert json.loads(rep.read_text())["overrides"] == {"stitching.max_distance_m": 8, "alignment.clustering": "auto"}
    assert 'changed: stitching.max_distance_m=8, alignment.clustering="auto"' in capsys.readouterr().out


@pytest.mark.parametrize(
    "item, message",
    [
        ("stitching.nope=1", "stitching.nope: StitchConfig has no field 'nope'"),
        ("stitching.max_distance_m=-1", "stitching.max_distance_m"),
        ("stitching.max_distance_m=far", "not a valid value"),
    ],
)
def test_a_bad_set_is_named_before_the_bag_is_read(tmp_path, capsys, item, message):
    """The real PipelineConfig checks the change; the bag (missing here) is not read at all."""
    code = cli.main(["bag2map", str(tmp_path / "nope"), "-o", str(tmp_path / "map"), "--set", item])
    err = capsys.readouterr().err
    assert code == 2 and "--set" in err and message in err and "no such bag" not in err


def test_no_usable_drive_exits_nonzero_with_reasons(tmp_path, fake_pipeline, capsys):
    nan = make_drive("nan", n=10)
    nan.xy[0, 1] = np.inf
    bag = _fleet(tmp_path, [nan, replace(make_drive("odom", n=10), frame_id="odom")])
    code = cli.main(["bag2map", str(bag), "-o", str(tmp_path / "map")])
    err = capsys.readouterr().err
    assert code == 1
    assert "no usable drive" in err and "non_finite_coordinates" in err and "wrong_frame" in err
    assert not (tmp_path / "map").exists() and "drives" not in fake_pipeline


def test_missing_input_is_a_clear_error(tmp_path, capsys):
    code = cli.main(["bag2map", str(tmp_path / "nope"), "-o", str(tmp_path / "map")])
    err = capsys.readouterr().err
    assert code == 1 and "no such bag" in err
    # one error that names the fault; no "going on with 0 drives" before it
    assert "going on" not in err and len(err.strip().splitlines()) == 1


def test_existing_output_is_refused_before_reading(tmp_path, capsys):
    (tmp_path / "map").mkdir()
    code = cli.main(["bag2map", str(tmp_path / "nope"), "-o", str(tmp_path / "map")])
    assert code == 2 and "exists already" in capsys.readouterr().err
    code = cli.main(["bag2map", str(tmp_path / "nope"), "-o", str(tmp_path / "map"), "--overwrite"])
    assert code == 2 and "not a rosbag2 directory" in capsys.readouterr().err


def test_geojson_without_origin(tmp_path, fake_pipeline, capsys):
    bag = _fleet(tmp_path, [make_drive("a", n=10)], origin=None)
    args = ["bag2map", str(bag), "-o", str(tmp_path / "map"), "--geojson", str(tmp_path / "m.geojson")]
    assert cli.main(args) == 2 and "--origin" in capsys.readouterr().err
    assert cli.main(args + ["--origin", "57.7,11.97"]) == 0
    assert (tmp_path / "m.geojson").exists()


@pytest.mark.parametrize(
    "argv",
    [
        ["bag2map", "in"],  # -o missing
        ["bag2map", "in", "-o", "out", "--preset", "fancy"],
        ["bag2map", "in", "-o", "out", "--seed", "x"],
        ["bag2map", "in", "-o", "out", "--origin", "95,1"],
        ["bag2map", "in", "-o", "out", "--workers", "0"],
        ["bag2map", "in", "-o", "out", "--workers", "two"],
        ["bag2map", "in", "-o", "out", "--set", "track_rejoin_m"],  # no =VALUE
        ["bag2map", "in", "-o", "out", "--set", "=1"],
    ],
)
def test_bad_arguments_are_usage_errors(argv, capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(argv)
    assert info.value.code == 2


def test_progress_bar_follows_stages(capsys):
    from hdmap_ros.commands.bag2map import _Progress

    with _Progress(enabled=True) as progress:
        progress("pivots", 1, 4)
        progress("pivots", 4, 4)
        progress("final", 2, 3)
        assert progress.stage == "final" and progress.bar.total == 3 and progress.bar.n == 2
    assert "pivots" in capsys.readouterr().err


@pytest.mark.slow
def test_end_to_end_on_sample_bag(tmp_path, capsys, sample_bags):
    """The real pipeline on bags/e6mini_20: a map bag and GeoJSON come out, consistent with each other."""
    bag = sample_bags / "e6mini_20"
    out, gj = tmp_path / "map", tmp_path / "map.geojson"
    assert cli.main(["bag2map", str(bag), "-o", str(out), "--geojson", str(gj), "--no-progress"]) == 0
    hdmap = read_map_bag(out)
    origin = hdmap.extra["origin"]
    assert hdmap.features and hdmap.topology
    assert set(hdmap.drive_ids) <= {d.drive_id for d in read_fleet_bag(bag).drives}
    everything = json.loads(gj.read_text())["features"]
    features = [f for f in everything if f["properties"]["kind"] == "road_feature"]
    lanes = [f for f in everything if f["properties"]["kind"] == "lane"]
    assert len(features) == sum(len(f.points) >= 2 for f in hdmap.features)
    assert lanes and all(f["geometry"]["type"] == "Polygon" for f in lanes)
    lon, lat = np.array([c for f in features for c in f["geometry"]["coordinates"]]).T
    # the e6mini map spans < 2 km: every point within ~0.03 deg of the origin
    assert np.all(np.abs(lat - origin.latitude_deg) < 0.03) and np.all(np.abs(lon - origin.longitude_deg) < 0.05)
    assert "pipeline report:" in capsys.readouterr().out
    # one process builds the very same map (the default uses every CPU available)
    assert cli.main(["bag2map", str(bag), "-o", str(tmp_path / "map1"), "--workers", "1", "--no-progress"]) == 0
    assert_maps_equal(hdmap, read_map_bag(tmp_path / "map1"))


@pytest.mark.slow
def test_sample_bag_map_scores_within_thresholds(tmp_path, capsys, sample_bags):
    """bag2map on bags/e6mini_20 (20 drives, 4.9 per place), scored by `hdmap evaluate` against
    its ground truth: the default preset's map is accurate and beats the naive peer's
    (measured 2026-12-01: default 0.106 m / 0.051 m corrected / precision 99.1 % / coverage
    81.3 %; naive 0.668 m / 0.454 m / 74.3 % / 81.2 %)."""
    bags = sample_bags
    figures = {}
    for preset in ("default", "naive"):
        out, ev = tmp_path / f"map_{preset}", tmp_path / f"{preset}.json"
        assert cli.main(["bag2map", str(bags / "e6mini_20"), "-o", str(out), "--preset", preset, "--no-progress"]) == 0
        assert (
            cli.main(
                [
                    "evaluate",
                    str(out),
                    str(bags / "e6mini_20.gt.json"),
                    "--fleet",
                    str(bags / "e6mini_20"),
                    "--json",
                    str(ev),
                ]
            )
            == 0
        )
        figures[preset] = json.loads(ev.read_text())
    capsys.readouterr()
    good, naive = figures["default"]["overall"], figures["naive"]["overall"]
    assert figures["default"]["floor_source"] == "drives"
    assert good["mean_m"] <= 0.30 and good["corrected_mean_m"] <= 0.12
    assert good["precision"] >= 0.97 and good["coverage"] >= 0.75
    assert good["mean_m"] < 0.5 * naive["mean_m"] and good["corrected_mean_m"] < 0.5 * naive["corrected_mean_m"]
    assert good["recall"] > naive["recall"] and good["precision"] > naive["precision"]


def test_damaged_bag_goes_on_with_intact_drives(tmp_path, fake_pipeline, capsys, sample_bags):
    bags = sample_bags
    code = cli.main(["bag2map", str(bags / "bad_inputs_truncated.mcap"), "-o", str(tmp_path / "map")])
    captured = capsys.readouterr()
    assert code == 0 and len(fake_pipeline["drives"]) == 2
    assert "truncated" in captured.err and "DAMAGED" in captured.out
