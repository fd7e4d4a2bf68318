"""`hdmap simulate --change` writes the road before and after and the changes; `hdmap evaluate
--changes` scores the changed zone apart, `--as-of` picks the road of a time."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hdmap_core.groundtruth import load_ground_truth
from hdmap_ros import cli

ARGS = ["--map", "motorway", "--length-m", "1500", "--drives", "4", "--seed", "3", "--set", "snippet_length_max_m=600"]


@pytest.mark.slow
def test_simulate_with_a_change_and_evaluate_the_zone(tmp_path, capsys):
    out = tmp_path / "fleet"
    assert cli.main(["simulate", *ARGS, "--change", "shift:400-1100:1.5:fwd_lane2@2", "-o", str(out)]) == 0
    assert "change shift:400-1100:1.5:fwd_lane2@2" in capsys.readouterr().out
    after = load_ground_truth(tmp_path / "fleet.gt.json")
    before = load_ground_truth(tmp_path / "fleet.gt_before.json")
    moved = [np.abs(a.points - b.points).max() for a, b in zip(after.features, before.features)]
    assert max(moved) > 1.4 and min(moved) == 0.0
    doc = json.loads((tmp_path / "fleet.changes.json").read_text())
    assert doc["gt_before"] == "fleet.gt_before.json"
    (change,) = doc["changes"]
    assert change["kind"] == "shift" and change["time_ns"] > 0 and len(change["zone"]["line"]) > 10

    # The old road used as map: whole-road figures, then the zone: ghosts, nothing of the new road.
    gt_old, gt_new = str(tmp_path / "fleet.gt_before.json"), str(tmp_path / "fleet.gt.json")
    report = tmp_path / "eval.json"
    assert (
        cli.main(["evaluate", gt_old, gt_new, "--changes", str(tmp_path / "fleet.changes.json"), "--json", str(report)])
        == 0
    )
    zone = json.loads(report.read_text())["changed_zone"]
    assert zone["ghost_share"] > 0.3 and zone["old_recall"] > 0.99 and zone["recall"] < 0.7
    # As of before the change, the old road is the road: no ghost.
    t = change["time_ns"] - 1
    assert (
        cli.main(
            [
                "evaluate",
                gt_old,
                gt_old,
                "--changes",
                str(tmp_path / "fleet.changes.json"),
                "--as-of",
                str(t),
                "--json",
                str(report),
            ]
        )
        == 0
    )
    zone = json.loads(report.read_text())["changed_zone"]
    assert zone["ghost_share"] == 0.0 and zone["recall"] > 0.99
    printed = capsys.readouterr().out
    assert "0 of 1 change(s) made" in printed and "changed zone" in printed


def test_as_of_without_changes_is_refused(tmp_path, capsys):
    gt = tmp_path / "m.gt.json"
    assert (
        cli.main(["simulate", "--map", "motorway", "--length-m", "500", "--drives", "1", "-o", str(tmp_path / "m")])
        == 0
    )
    assert cli.main(["evaluate", str(gt), str(gt), "--as-of", "5"]) == 2
    assert "--as-of needs --changes" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.parametrize("name", ["e6mini_20", "ramps_20"])
def test_follow_changes_leaves_the_sample_maps_byte_identical(tmp_path, sample_bags, name, capsys):
    """The sample roads did not change: following changes (the default) finds nothing and writes the
    same bag as without."""
    for sub, extra in (("plain", ["--no-follow-changes"]), ("follow", [])):
        (tmp_path / sub).mkdir()
        assert (
            cli.main(["bag2map", str(sample_bags / name), "-o", str(tmp_path / sub / "map"), "--workers", "1", *extra])
            == 0
        )
    assert "follow changes: 0 change(s)" in capsys.readouterr().out
    plain = (tmp_path / "plain" / "map" / "map.mcap").read_bytes()
    assert plain == (tmp_path / "follow" / "map" / "map.mcap").read_bytes()
    assert json.loads((tmp_path / "follow" / "map.history.json").read_text()) == {
        "changes": [],
        "retired": [],
        "modelled": [],
    }


@pytest.mark.slow
@pytest.mark.parametrize("preset", ["paper", "naive"])
def test_paper_and_naive_map_the_consensus_unless_asked(tmp_path, sample_bags, preset, capsys):
    """``paper`` and ``naive`` do not follow changes by default (FOLLOWS_CHANGES): the naive map,
    without offset correction, is too far off for change detection (false changes on the CARLA
    bench fleets, docs/updates.md "How `bag2map` follows a change"); ``--follow-changes`` still turns it on."""
    bag = str(sample_bags / "e6mini_20")
    args = ["bag2map", bag, "--preset", preset, "--workers", "1"]
    assert cli.main([*args, "-o", str(tmp_path / "plain")]) == 0
    assert "follow changes" not in capsys.readouterr().out
    assert not (tmp_path / "plain.history.json").exists()
    assert cli.main([*args, "-o", str(tmp_path / "asked"), "--follow-changes"]) == 0
    assert "follow changes:" in capsys.readouterr().out
    assert (tmp_path / "asked.history.json").exists()


@pytest.mark.slow
def test_a_closed_lane_is_scored_by_lane_count_in_the_zone(tmp_path, capsys):
    out = tmp_path / "fleet"
    assert cli.main(["simulate", *ARGS, "--change", "close:400-1100:fwd_lane2@2", "-o", str(out)]) == 0
    gt_old, gt_new = str(tmp_path / "fleet.gt_before.json"), str(tmp_path / "fleet.gt.json")
    changes = str(tmp_path / "fleet.changes.json")
    report = tmp_path / "eval.json"
    assert cli.main(["evaluate", gt_old, gt_new, "--changes", changes, "--lanes", "--json", str(report)]) == 0
    zone = json.loads(report.read_text())["changed_zone_lanes"]
    assert "changed zone lanes" in capsys.readouterr().out
    # the old road as map shows the closed lane: one lane too many along the zone but where the
    # closing lane still runs apart from its neighbour in the tapers (18 % of the cuts)
    assert zone["n_cuts"] > 100 and zone["count_accuracy"] < 0.3
    assert zone["mean_map_lanes"] > zone["mean_gt_lanes"] + 0.6


def test_an_opening_wider_than_the_shoulder_is_refused_without_a_traceback(tmp_path, capsys):
    """The motorway's 2.5 m shoulder: ``open`` of 3 m would put the edge beyond the road border."""
    out = tmp_path / "fleet"
    assert cli.main(["simulate", *ARGS, "--change", "open:400-1100:3.0:fwd_lane2@2", "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert "beyond the road border" in err and "at most SIZE 2.50 m" in err and "Traceback" not in err
    assert not list(tmp_path.iterdir())  # refused before any drive is written
