"""`hdmap simulate`: bag + ground truth + sim.json written, equal to the core's fleet; bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hdmap_core.groundtruth import load_ground_truth
from hdmap_core.simulation.fleet import SimConfig, load_map, simulate_fleet
from hdmap_ros import cli
from hdmap_ros.io.bagio import read_fleet_bag

ARGS = ["--map", "motorway", "--length-m", "1500", "--drives", "4", "--seed", "3", "--set", "snippet_length_max_m=600"]


def test_writes_bag_ground_truth_and_sim_json(tmp_path, capsys):
    out = tmp_path / "fleet"
    assert cli.main(["simulate", *ARGS, "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "4 drives" in printed and "detections" in printed

    bag = read_fleet_bag(out)
    assert bag.error is None and bag.rejected == []
    expected = simulate_fleet(
        load_map("motorway", length_m=1500.0), config=SimConfig(n_drives=4, snippet_length_max_m=600.0), seed=3
    )
    assert [d.drive_id for d in bag.drives] == [d.drive_id for d in expected.drives]
    for got, want in zip(bag.drives, expected.drives):
        np.testing.assert_allclose(got.xy, want.xy, atol=1e-9)
        assert len(got.detections) == len(want.detections)
        for a, b in zip(got.detections, want.detections):
            assert a.type == b.type
            np.testing.assert_allclose(a.points, b.points, atol=1e-9)
    assert bag.origin == expected.origin

    gt = load_ground_truth(tmp_path / "fleet.gt.json")
    assert set(gt.lanes) == set(load_map("motorway", length_m=1500.0).lanes)
    sim = json.loads((tmp_path / "fleet.sim.json").read_text())
    assert sim["config"]["n_drives"] == 4 and sim["config"]["snippet_length_max_m"] == 600.0
    assert sim["seed"] == 3
    first = expected.drives[0].drive_id
    assert sim["truth"][first]["bias_lateral_m"] == pytest.approx(expected.truth[first]["bias_lateral_m"])


def test_config_file_and_set_overrides(tmp_path):
    conf = tmp_path / "sim.json"
    conf.write_text(
        json.dumps(
            {"bias_lateral_sigma_m": 0.25, "n_drives": 2, "snippet_length_min_m": 200, "snippet_length_max_m": 400}
        )
    )
    out = tmp_path / "f"
    assert (
        cli.main(
            [
                "simulate",
                "--map",
                "motorway",
                "--length-m",
                "800",
                "--config",
                str(conf),
                "--set",
                "noise_sigma_m=0.02",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    sim = json.loads((tmp_path / "f.sim.json").read_text())
    assert sim["config"]["bias_lateral_sigma_m"] == 0.25
    assert sim["config"]["noise_sigma_m"] == 0.02
    assert len(sim["truth"]) == 2


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--set", "no_such=1"], "unknown SimConfig parameter"),
        (["--set", "bias_lateral_sigma_m"], "KEY=VALUE"),
        (["--set", "visibility_border=2"], "visibility_border"),
        (["--map", "autobahn"], "no map 'autobahn'"),
    ],
)
def test_bad_input_is_reported_not_raised(tmp_path, capsys, extra, message):
    assert cli.main(["simulate", *ARGS, *extra, "-o", str(tmp_path / "x")]) == 1
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_existing_output_needs_overwrite(tmp_path, capsys):
    out = tmp_path / "fleet"
    assert cli.main(["simulate", *ARGS, "-o", str(out)]) == 0
    assert cli.main(["simulate", *ARGS, "-o", str(out)]) == 1
    assert "exists" in capsys.readouterr().err
    assert cli.main(["simulate", *ARGS, "--overwrite", "-o", str(out)]) == 0


def test_bad_config_file(tmp_path, capsys):
    conf = tmp_path / "c.json"
    conf.write_text("[1, 2]")
    assert cli.main(["simulate", *ARGS, "--config", str(conf), "-o", str(tmp_path / "x")]) == 1
    assert "mapping" in capsys.readouterr().err


def test_yaml_config(tmp_path):
    pytest.importorskip("ruamel.yaml")
    conf = tmp_path / "sim.yaml"
    conf.write_text("n_drives: 2\nsnippet_length_min_m: 100\nsnippet_length_max_m: 300\nopposite_barrier: false\n")
    assert (
        cli.main(
            ["simulate", "--map", "motorway", "--length-m", "600", "--config", str(conf), "-o", str(tmp_path / "y")]
        )
        == 0
    )
    sim = json.loads((tmp_path / "y.sim.json").read_text())
    assert sim["config"]["opposite_barrier"] is False and len(sim["truth"]) == 2


def test_batch_drives_streams_the_same_bag_and_sim_json(tmp_path):
    from hdmap_ros.io.bagio import iter_bag

    whole, streamed = tmp_path / "whole", tmp_path / "streamed"
    assert cli.main(["simulate", *ARGS, "-o", str(whole)]) == 0
    assert cli.main(["simulate", *ARGS, "-o", str(streamed), "--batch-drives", "3"]) == 0

    def messages(bag):
        return [(m.topic, m.log_time_ns, m.data) for m in iter_bag(bag)]

    assert messages(streamed) == messages(whole) and len(messages(whole)) == 5  # origin + 4 drives
    assert json.loads((tmp_path / "streamed.sim.json").read_text()) == json.loads(
        (tmp_path / "whole.sim.json").read_text()
    )
    assert cli.main(["simulate", *ARGS, "-o", str(tmp_path / "x"), "--batch-drives", "0"]) == 1
