"""`hdmap evaluate`: map bag or .gt.json against ground truth, fleet bag for the floor, outputs."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from hdmap_core.evaluation.evaluate import hdmap_from_ground_truth
from hdmap_core.groundtruth import GroundTruth, GTFeature, GTLane, GTRoute, save_ground_truth
from hdmap_core.model import Drive, FeatureType, GeoOrigin
from hdmap_ros import cli
from hdmap_ros.commands.evaluate import resolve_ground_truth, seen_counts_from_sim_json, sigma_from_sim_json
from hdmap_ros.io.bagio import write_fleet_bag, write_map_bag

ORIGIN = GeoOrigin(48.78, 9.18, 250.0)


def _line(y: float, x1: float = 120.0) -> np.ndarray:
    x = np.arange(0.0, x1 + 1e-9, 1.0)
    return np.stack([x, np.full_like(x, y)], axis=1)


@pytest.fixture
def road_path(tmp_path: Path) -> Path:
    """One carriageway (+x), two lanes, 120 m: borders, solid edges, a dashed centre line."""
    feats = tuple(
        GTFeature(i + 1, t, _line(y))
        for i, (t, y) in enumerate(
            [
                (FeatureType.ROAD_BORDER, -0.5),
                (FeatureType.SOLID, 0.0),
                (FeatureType.DASHED, 3.5),
                (FeatureType.SOLID, 7.0),
                (FeatureType.ROAD_BORDER, 7.5),
            ]
        )
    )
    lanes = {"A": GTLane("A", _line(1.75), left="B"), "B": GTLane("B", _line(5.25), right="A")}
    gt = GroundTruth("cli_road", feats, lanes, (GTRoute("rA", ("A",)), GTRoute("rB", ("B",))))
    path = tmp_path / "cli_road.gt.json"
    save_ground_truth(gt, path)
    return path


def _gt(road_path: Path) -> GroundTruth:
    return resolve_ground_truth(str(road_path))


@pytest.mark.slow
def test_ground_truth_as_map_scores_zero(road_path: Path, tmp_path: Path, capsys) -> None:
    out_json, out_png = tmp_path / "r.json", tmp_path / "r.png"
    rc = cli.main(["evaluate", str(road_path), str(road_path), "--json", str(out_json), "--plot", str(out_png)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "coverage 100.0%" in text and "type accuracy" in text
    doc = json.loads(out_json.read_text())
    assert doc["overall"]["mean_m"] == pytest.approx(0.0, abs=1e-9)
    assert doc["overall"]["recall"] == 1.0
    assert len(doc["cuts"]["station_m"]) == doc["n_cuts"] == 60
    assert doc["inputs"]["sigma_loc_source"] == "default"
    assert out_png.read_bytes()[:4] == b"\x89PNG"


def test_map_bag_with_fleet_and_sim_json(road_path: Path, tmp_path: Path, capsys) -> None:
    gt = _gt(road_path)
    map_bag = write_map_bag(tmp_path / "map", hdmap_from_ground_truth(gt, lateral_shift_m=0.3, drive_count=3), ORIGIN)
    drives = [
        Drive(f"d{i}", _line(1.75), np.zeros(121), (np.arange(121) * 10**8 + i * 10**12).astype(np.int64))
        for i in range(4)
    ]
    fleet = write_fleet_bag(tmp_path / "fleet", drives, ORIGIN)
    # As hdmap simulate writes it: sigma_loc = hypot(bias 0.3, drift 0.4) = 0.5.
    sim = {"config": {"bias_lateral_sigma_m": 0.3, "drift_sigma_m": 0.4, "noise_sigma_m": 0.08}, "truth": {}}
    (tmp_path / "fleet.sim.json").write_text(json.dumps(sim))
    out_json = tmp_path / "r.json"
    rc = cli.main(["evaluate", str(map_bag), str(road_path), "--fleet", str(fleet), "--json", str(out_json)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "fleet: 4 drives" in text and "fleet.sim.json" in text
    doc = json.loads(out_json.read_text())
    assert doc["overall"]["mean_m"] == pytest.approx(0.3, abs=0.02)
    assert doc["floor_source"] == "drives"
    assert doc["floor_mean_m"] == pytest.approx(0.5 / math.sqrt(4))
    # --sigma-loc wins over the sim.json.
    rc = cli.main(
        ["evaluate", str(map_bag), str(road_path), "--fleet", str(fleet), "--sigma-loc", "2", "--json", str(out_json)]
    )
    assert rc == 0 and json.loads(out_json.read_text())["floor_mean_m"] == pytest.approx(1.0)


def test_seen_counts_in_the_sim_json_give_recall_over_the_observed_ground_truth(
    road_path: Path, tmp_path: Path, capsys
) -> None:
    gt = _gt(road_path)
    perfect = hdmap_from_ground_truth(gt)
    without_outer_border = replace(perfect, features=tuple(f for f in perfect.features if f.id != 5))
    map_bag = write_map_bag(tmp_path / "map", without_outer_border, ORIGIN)
    drives = [Drive("d0", _line(1.75), np.zeros(121), (np.arange(121) * 10**8).astype(np.int64))]
    fleet = write_fleet_bag(tmp_path / "fleet", drives, ORIGIN)
    # as hdmap simulate writes it: run-length coded per feature id; the outer border never seen
    seen = {str(i): [2, 121] for i in (1, 2, 3, 4)} | {"5": [0, 121]}
    sim = {"config": {"bias_lateral_sigma_m": 0.3}, "truth": {"d0": {"lateral_error_mean_m": 0.1}}, "seen_count": seen}
    (tmp_path / "fleet.sim.json").write_text(json.dumps(sim))
    out_json = tmp_path / "r.json"
    assert cli.main(["evaluate", str(map_bag), str(road_path), "--fleet", str(fleet), "--json", str(out_json)]) == 0
    assert "observed GT points" in capsys.readouterr().out
    doc = json.loads(out_json.read_text())
    assert doc["overall"]["recall"] == pytest.approx(0.8)
    assert doc["observed_share"] == pytest.approx(0.8) and doc["recall_observed"] == 1.0
    assert doc["fleet_floor_mean_m"] == pytest.approx(0.1)


@pytest.mark.slow
def test_sim_json_from_before_the_seen_count_still_evaluates(tmp_path: Path, capsys, sample_bags: Path) -> None:
    # bags/e6mini_20.sim.json was written by the simulator before it recorded seen counts.
    assert "seen_count" not in json.loads((sample_bags / "e6mini_20.sim.json").read_text())
    gt = str(sample_bags / "e6mini_20.gt.json")
    out_json = tmp_path / "r.json"
    assert cli.main(["evaluate", gt, gt, "--fleet", str(sample_bags / "e6mini_20"), "--json", str(out_json)]) == 0
    text = capsys.readouterr().out
    assert "realized floor" in text and "observed GT points" not in text
    doc = json.loads(out_json.read_text())
    assert doc["overall"]["recall"] == 1.0 and doc["fleet_floor_mean_m"] > 0
    assert doc["observed_share"] is None and doc["recall_observed"] is None and doc["n_observed"] == 0


def test_seen_counts_from_sim_json(tmp_path: Path) -> None:
    path = tmp_path / "x.sim.json"
    path.write_text(json.dumps({"seen_count": {"7": [0, 2, 3, 1], "8": [1, 2, 3], "x": [1, 1], "9": []}}))
    got = seen_counts_from_sim_json(path)
    assert set(got) == {7, 9}
    assert got[7].tolist() == [0, 0, 3] and got[9].tolist() == []
    path.write_text(json.dumps({"truth": {}}))
    assert seen_counts_from_sim_json(path) is None
    path.write_text("{not json")
    assert seen_counts_from_sim_json(path) is None
    assert seen_counts_from_sim_json(None) is None


def test_unknown_ground_truth_and_missing_map_are_clear_errors(road_path: Path, tmp_path: Path, capsys) -> None:
    assert cli.main(["evaluate", str(road_path), "no_such_map_name"]) == 1
    assert "no_such_map_name" in capsys.readouterr().err
    assert cli.main(["evaluate", str(tmp_path / "no_bag"), str(road_path)]) == 1
    assert "no_bag" in capsys.readouterr().err


def test_all_lanes_flag_and_bad_numbers(road_path: Path, capsys) -> None:
    assert cli.main(["evaluate", str(road_path), str(road_path), "--all-lanes"]) == 0
    with pytest.raises(SystemExit):
        cli.main(["evaluate", str(road_path), str(road_path), "--sigma-loc", "-1"])


def test_shared_and_synthetic_names_resolve(monkeypatch, road_path: Path, tmp_path: Path) -> None:
    monkeypatch.setenv("HDMAP_MAPS_DIR", str(road_path.parent))
    monkeypatch.chdir(tmp_path.parent)
    assert resolve_ground_truth("cli_road").name == "cli_road"
    assert resolve_ground_truth("cli_road.gt.json").name == "cli_road"
    assert resolve_ground_truth(str(road_path)).name == "cli_road"
    assert resolve_ground_truth("motorway").features


@pytest.mark.parametrize(
    ("doc", "want"),
    [
        ({"config": {"bias_lateral_sigma_m": 0.7}}, 0.7),
        ({"config": {"bias_lateral_sigma_m": 0.0, "drift_sigma_m": 0.0}}, None),
        ({"config": {"lateral_bias_sigma_m": 0.7}}, 0.7),
        ({"sigma_loc_m": 1.2, "config": {"lateral_bias_sigma_m": 0.7}}, 1.2),
        ({"config": {"loc": {"bias_lat_sigma_m": 0.9}}}, 0.9),
        ({"config": {"noise_m": 0.1}}, None),
        ([1, 2], None),
    ],
)
def test_sigma_from_sim_json(tmp_path: Path, doc: object, want: float | None) -> None:
    path = tmp_path / "x.sim.json"
    path.write_text(json.dumps(doc))
    assert sigma_from_sim_json(path) == (pytest.approx(want) if want is not None else None)
    path.write_text("{not json")
    assert sigma_from_sim_json(path) is None
