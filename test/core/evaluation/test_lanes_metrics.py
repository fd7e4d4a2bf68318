"""Lane metrics (evaluation/lanes.py) on the hand-made three-lane road of test/support/lane_samples.py."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hdmap_core.evaluation.lanes import evaluate_lanes, route_ends
from hdmap_core.groundtruth import GroundTruth, GTFeature, GTLane, GTRoute
from hdmap_core.lanes.derive import derive_lanes
from hdmap_core.model import HDMap

from lane_samples import three_lanes


def _truth(length_m: float = 800.0) -> GroundTruth:
    hd = three_lanes(length_m)
    x = np.arange(0.0, length_m + 1e-9, 1.0)
    lanes = {
        name: GTLane(name, np.stack([x, np.full_like(x, y)], axis=1), left=left, right=right)
        for name, y, left, right in (("l", 3.5, None, "m"), ("m", 0.0, "l", "r"), ("r", -3.5, "m", None))
    }
    feats = tuple(GTFeature(f.id, f.type, f.points) for f in hd.features)
    routes = (GTRoute("left", ("l",)), GTRoute("change", ("l", "m"), (0,)))
    return GroundTruth("three", feats, lanes, routes)


def _shifted(hdmap: HDMap, dy: float) -> HDMap:
    feats = tuple(dataclasses.replace(f, points=f.points + [0.0, dy]) for f in hdmap.features)
    nodes = tuple(dataclasses.replace(n, position=n.position + [0.0, dy]) for n in hdmap.topology)
    return HDMap(features=feats, topology=nodes)


def test_perfect_lanes_score_perfectly():
    rep = evaluate_lanes(derive_lanes(three_lanes()), _truth())
    assert rep.coverage == pytest.approx(1.0, abs=0.01) and rep.precision == pytest.approx(1.0, abs=0.01)
    assert rep.mean_error_m < 0.01
    assert rep.lane_count_accuracy == pytest.approx(1.0, abs=0.01) and rep.n_cuts > 300
    assert (rep.routes, rep.routes_routable, rep.unroutable) == (2, 2, ())
    assert rep.to_dict()["route_reachability"] == 1.0


def test_shift_shows_as_error_and_beyond_a_metre_as_lost_coverage():
    truth = _truth()
    near = evaluate_lanes(derive_lanes(_shifted(three_lanes(), 0.3)), truth)
    assert near.mean_error_m == pytest.approx(0.3, abs=0.02) and near.coverage > 0.99
    far = evaluate_lanes(derive_lanes(_shifted(three_lanes(), 1.75)), truth)
    # every map lane centerline lies 1.75 m from the truth: nothing within 1 m
    assert far.coverage < 0.01 and far.precision < 0.01


def test_missing_lane_costs_coverage_and_routes():
    hd = three_lanes()
    # without the left border and edge line the left lane has no left side: it is gone
    gone = HDMap(features=tuple(f for f in hd.features if f.id not in (1, 2)), topology=hd.topology)
    rep = evaluate_lanes(derive_lanes(gone), _truth())
    # coverage counts the lanes of the routes: "l" (gone) and "m"
    assert rep.coverage == pytest.approx(1 / 2, abs=0.02)
    assert rep.precision > 0.99
    assert "left" in rep.unroutable
    assert route_ends(derive_lanes(gone), _truth(), "left") is None
