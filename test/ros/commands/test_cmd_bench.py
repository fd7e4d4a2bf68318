"""`hdmap bench`: scenario handling, figures wiring and the table (pipeline faked; real run is slow)."""

from __future__ import annotations

import json
import math
import types
from dataclasses import dataclass
from pathlib import Path

import pytest

from hdmap_core.evaluation.evaluate import hdmap_from_ground_truth
from hdmap_core.groundtruth import load_ground_truth
from hdmap_ros import cli
from hdmap_ros.commands.bench import format_table, summarize_seeds

from bag_samples import install_fake_pipeline


@pytest.fixture
def gt_pipeline(monkeypatch, tmp_path):
    """build_map stand-in returning the ground truth of the scenario as the map (a perfect map)."""

    @dataclass(frozen=True)
    class Result:
        map: object
        report: object

    def build_map(drives, *, config, seed=0, progress=None, workers=1):
        assert workers >= 1
        gt = sorted(tmp_path.glob("*.gt.json"))[0]  # every scenario here is of one map
        return Result(hdmap_from_ground_truth(load_ground_truth(gt)), types.SimpleNamespace(stage_seconds={"x": 0.0}))

    install_fake_pipeline(monkeypatch, build_map)
    return tmp_path


@pytest.mark.slow
def test_inline_bench_on_a_simulated_scenario(gt_pipeline, capsys):
    work = gt_pipeline
    out_json, out_md = work / "bench.json", work / "bench.md"
    code = cli.main(
        [
            "bench",
            "motorway:3",
            "--presets",
            "naive,paper",
            "--inline",
            "--work-dir",
            str(work),
            "--json",
            str(out_json),
            "--markdown",
            str(out_md),
        ]
    )
    assert code == 0
    rows = json.loads(out_json.read_text())
    assert [(r["scenario"], r["preset"]) for r in rows] == [("motorway_3_s0", "naive"), ("motorway_3_s0", "paper")]
    for r in rows:
        assert r["drives"] == 3 and r["drive_km"] > 0
        assert r["mean_m"] < 0.01 and r["coverage"] > 0.9  # the ground truth scored against itself
        assert r["floor_m"] > 0 and r["peak_rss_mb"] > 10
        # 3 short drives see part of the road; the ground truth as map has all of that
        assert 0.05 < r["observed_share"] < 0.9 and r["recall_observed"] == 1.0
        assert r["type_accuracy"] == r["type_accuracy_corrected"] == 1.0
    table = capsys.readouterr().out
    assert "motorway_3_s0" in table and "mean/floor" in table and "recall obs." in table
    assert out_md.read_text().count("\n") == 4  # header, rule, two rows


@pytest.mark.slow
def test_seed_range_runs_each_seed_and_adds_the_mean_over_seeds(gt_pipeline, capsys):
    work = gt_pipeline
    out_json, out_md = work / "bench.json", work / "bench.md"
    assert (
        cli.main(
            [
                "bench",
                "motorway:3:1-2",
                "--presets",
                "naive",
                "--inline",
                "--work-dir",
                str(work),
                "--json",
                str(out_json),
                "--markdown",
                str(out_md),
            ]
        )
        == 0
    )
    rows = json.loads(out_json.read_text())
    runs = [r for r in rows if not r.get("summary")]
    (mean,) = [r for r in rows if r.get("summary")]
    assert [r["scenario"] for r in runs] == ["motorway_3_s1", "motorway_3_s2"]
    assert mean["scenario"] == "motorway_3" and mean["seeds"] == "1,2" and mean["preset"] == "naive"
    assert mean["floor_m"] == pytest.approx((runs[0]["floor_m"] + runs[1]["floor_m"]) / 2)
    assert "mean over seeds" in capsys.readouterr().out
    assert "Mean over seeds" in out_md.read_text()


@pytest.mark.slow
def test_set_changes_every_preset_run_and_names_the_rows(monkeypatch, tmp_path, capsys):
    seen = []

    @dataclass(frozen=True)
    class Result:
        map: object
        report: object

    def build_map(drives, *, config, seed=0, progress=None, workers=1):
        seen.append(config)
        gt = sorted(tmp_path.glob("*.gt.json"))[0]
        return Result(hdmap_from_ground_truth(load_ground_truth(gt)), types.SimpleNamespace(stage_seconds={}))

    install_fake_pipeline(monkeypatch, build_map)
    out_json = tmp_path / "bench.json"
    assert (
        cli.main(
            [
                "bench",
                "motorway:3",
                "--presets",
                "naive,default",
                "--inline",
                "--work-dir",
                str(tmp_path),
                "--set",
                "stitching.max_distance_m=8",
                "--set",
                "alignment.robust_loss=false",
                "--json",
                str(out_json),
            ]
        )
        == 0
    )
    changes = (("stitching.max_distance_m", 8), ("alignment.robust_loss", False))
    assert [(c.name, c.overrides) for c in seen] == [("naive+", changes), ("default+", changes)]
    rows = json.loads(out_json.read_text())
    assert [r["preset"] for r in rows] == ["naive+", "default+"]
    assert rows[1]["overrides"] == {"stitching.max_distance_m": 8, "alignment.robust_loss": False}
    assert "default+" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ("alignment.nope=1", "AlignmentConfig has no field 'nope'"),
        # the final pass is off in paper and naive: the message names where it fits
        ("final_pass.sparse_step_max_drives=2", "(preset paper); it fits default: choose the presets with --presets"),
    ],
)
def test_set_that_does_not_fit_a_preset_is_named_before_anything_is_simulated(change, message, tmp_path, capsys):
    assert cli.main(["bench", "motorway:3", "--set", change, "--work-dir", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert message in err and change.partition("=")[0] in err
    assert not any(tmp_path.iterdir())  # no fleet was simulated


def test_summarize_seeds_means_and_ratios_of_means():
    rows = [
        {
            "scenario": "m_40_s1",
            "preset": "default",
            "mean_m": 0.4,
            "floor_m": 0.2,
            "fleet_floor_m": 0.4,
            "coverage": 1.0,
        },
        {
            "scenario": "m_40_s2",
            "preset": "default",
            "mean_m": 0.1,
            "floor_m": 0.2,
            "fleet_floor_m": 0.1,
            "coverage": 0.9,
        },
        {"scenario": "m_40_s1", "preset": "naive", "mean_m": 0.5, "floor_m": 0.2, "fleet_floor_m": math.nan},
        {"scenario": "other_30_s1", "preset": "default", "mean_m": 0.3, "floor_m": 0.3},
    ]
    (row,) = summarize_seeds(rows)  # one seed of naive / of "other": no mean row
    assert (row["scenario"], row["preset"], row["seeds"]) == ("m_40", "default", "1,2")
    assert row["mean_m"] == pytest.approx(0.25) and row["coverage"] == pytest.approx(0.95)
    assert row["mean_over_floor"] == pytest.approx(1.25)  # 0.25 / 0.2, not the mean of 2.0 and 0.5
    assert row["mean_over_floor_max"] == pytest.approx(2.0)
    assert row["mean_over_fleet"] == pytest.approx(1.0)
    assert math.isnan(row["recall"])


def test_table_prints_missing_figures_as_dash():
    text = format_table([{"scenario": "s", "preset": "p", "drives": 2, "mean_m": math.nan, "coverage": 0.5}])
    assert "50.0%" in text and " -" in text


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["bench", "motorway:3", "--presets", "fancy"], "--presets"),
        (["bench", "no/such/bag"], "neither an existing bag"),
        (["bench", "motorway:x"], "integers"),
        (["bench", "motorway:3:5-2"], "integers"),
        (["bench", "motorway:3:1,1"], "distinct"),
        (["bench", "motorway:0"], "DRIVES must be >= 1, got 0"),
        (["bench", "motorway:-2:1"], "DRIVES must be >= 1, got -2"),
        (["bench", "motorway:3", "--scale", "0"], "--scale"),
        (["bench", "motorway:3", "--workers", "0"], "--workers"),
    ],
)
def test_bad_arguments(argv, message, capsys, tmp_path):
    assert cli.main(argv + ["--work-dir", str(tmp_path)]) == 1
    assert message in capsys.readouterr().err


@pytest.mark.slow
def test_real_bench_in_a_subprocess(tmp_path, capsys):
    assert cli.main(["bench", "motorway:4", "--presets", "naive", "--work-dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "motorway_4_s0" in out and "naive" in out


@pytest.mark.slow
def test_named_paper_like_scenario_is_simulated_with_its_overrides(tmp_path):
    from hdmap_ros.commands.bench import NAMED_SCENARIOS, prepare_scenarios

    scenarios = prepare_scenarios(["paper_like:6:3"], scales=[1.0, 0.5], work_dir=tmp_path)
    assert [s.name for s in scenarios] == ["paper_like_6_s3", "paper_like_3_s3"]
    sim = json.loads((tmp_path / "paper_like_6_s3.sim.json").read_text())
    named = NAMED_SCENARIOS["paper_like"]
    for key, value in named["sim"].items():
        assert sim["config"][key] == value
    gt = json.loads(Path(scenarios[0].gt_path).read_text())
    # the layout is the long synthetic motorway with ramps, not the 3 km default
    xs = [p[0] for f in gt["features"] for p in f["points"]]
    ys = [p[1] for f in gt["features"] for p in f["points"]]
    assert max(max(xs) - min(xs), max(ys) - min(ys)) > 0.6 * named["length_m"]


@pytest.mark.slow
def test_simulated_fleet_is_reused_only_when_made_with_the_same_config(tmp_path):
    from hdmap_core.simulation.fleet import simulator_fingerprint
    from hdmap_ros.commands.bench import prepare_scenarios

    (first,) = prepare_scenarios(["motorway:3:2"], scales=[1.0], work_dir=tmp_path)
    sim = Path(first.bag).with_name("motorway_3_s2.sim.json")
    stamp = sim.stat().st_mtime_ns
    prepare_scenarios(["motorway:3:2"], scales=[1.0], work_dir=tmp_path)
    assert sim.stat().st_mtime_ns == stamp  # same config and seed: the bag is reused
    doc = json.loads(sim.read_text())
    doc["config"]["route_weighting"] = "length"  # as if simulated by an older simulator default
    sim.write_text(json.dumps(doc))
    prepare_scenarios(["motorway:3:2"], scales=[1.0], work_dir=tmp_path)
    assert json.loads(sim.read_text())["config"]["route_weighting"] == "coverage"  # simulated anew
    doc = json.loads(sim.read_text())
    del doc["seen_count"]  # as written before the simulator recorded seen counts
    sim.write_text(json.dumps(doc))
    prepare_scenarios(["motorway:3:2"], scales=[1.0], work_dir=tmp_path)
    assert "seen_count" in json.loads(sim.read_text())  # simulated anew
    doc = json.loads(sim.read_text())
    assert doc["simulator"] == simulator_fingerprint()
    doc["simulator"] = "0123456789abcdef"  # as if made by other simulator code, same config
    sim.write_text(json.dumps(doc))
    stamp = sim.stat().st_mtime_ns
    prepare_scenarios(["motorway:3:2"], scales=[1.0], work_dir=tmp_path)
    assert json.loads(sim.read_text())["simulator"] == simulator_fingerprint()  # simulated anew
    assert sim.stat().st_mtime_ns != stamp


@pytest.mark.slow
def test_tiled_bench_prints_the_scale_table(sample_bags, tmp_path, capsys):
    pytest.importorskip("distributed")
    out_json = tmp_path / "bench.json"
    assert (
        cli.main(
            [
                "bench",
                str(sample_bags / "ramps_20"),
                "--presets",
                "default",
                "--inline",
                "--tiled",
                "--workers",
                "2",
                "--json",
                str(out_json),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "default tiled" in out and "drive-km/s per worker" in out and "scheduler" in out
    (row,) = json.loads(out_json.read_text())
    assert row["tiled"] and row["workers"] == 2 and row["tiles"] > 0 and row["km_per_s_worker"] > 0
    peaks = row["peak_rss_by_process"]
    assert sum(k.startswith("worker") for k in peaks) == 2 and row["peak_rss_mb"] == max(peaks.values())
    assert row["mean_m"] < 0.5 and row["coverage"] > 0.5


def test_lane_figures_use_the_drives_connectors(tmp_path):
    """The bench's lane figures are those of the exports: a turn without lines is routable once
    the drives' trajectories add its connector (the map's lanes alone end before the turn)."""
    import numpy as np

    from hdmap_core.groundtruth import GroundTruth, GTLane, GTRoute, save_ground_truth
    from hdmap_ros.commands.bench import Scenario, _lane_figures

    from lane_samples import TURN_RADIUS_M, turn_drives, turn_without_lines

    a = np.linspace(np.pi / 2, 0.0, 48)
    lanes = {
        "east": GTLane("east", np.stack([np.arange(0.0, 301.0), np.zeros(301)], axis=1), successors=("turn",)),
        "turn": GTLane(
            "turn",
            np.stack([300.0 + TURN_RADIUS_M * np.cos(a), -30.0 + TURN_RADIUS_M * np.sin(a)], axis=1),
            successors=("south",),
            predecessors=("east",),
        ),
        "south": GTLane(
            "south", np.stack([np.full(270, 330.0), np.arange(-30.0, -300.0, -1.0)], axis=1), predecessors=("turn",)
        ),
    }
    save_ground_truth(
        GroundTruth("turn", (), lanes, (GTRoute("r", ("east", "turn", "south")),)), tmp_path / "t.gt.json"
    )
    scenario = Scenario("turn", str(tmp_path / "none"), str(tmp_path / "t.gt.json"))
    alone, _ = _lane_figures(scenario, turn_without_lines())
    driven, _ = _lane_figures(scenario, turn_without_lines(), turn_drives(4, seed=3))
    assert alone["routes"] == "0/1" and driven["routes"] == "1/1"
    assert driven["n_lanes"] == alone["n_lanes"] + 1 and driven["lane_coverage"] > alone["lane_coverage"]


def test_the_map_updating_benchmark_is_a_section_of_hdmap_bench(sample_bags, tmp_path, capsys):
    # a sample bag without a change, followed with the default preset: no change, the first map
    out = tmp_path / "changes.json"
    argv = ["bench", "--changes", "--change-section", "nochange", "--change-fleets", "e6mini_20"]
    argv += ["--change-bags", str(sample_bags), "--presets", "default", "--json", str(out)]
    assert cli.main(argv) == 0
    (row,) = json.loads(out.read_text())["nochange"]
    assert row["fleet"] == "e6mini_20" and row["preset"] == "default" and row["drives"] == 20
    assert row["changes"] == 0 and row["same_map"]
    assert row["plain"] == row["follow"]
    assert "| e6mini_20 | default | 20 |" in capsys.readouterr().out
    # no scenario with it, nor an unknown fleet
    assert cli.main(["bench", "motorway:3", "--changes"]) == 1
    assert cli.main(["bench", "--changes", "--change-fleets", "nowhere", "--change-bags", str(sample_bags)]) == 1
