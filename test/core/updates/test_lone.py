"""One drive's misclassified copy of a line, dropped from the rebuilt places (``updates.lone``)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from carriageway_samples import BORDER, DASHED, PLACES, REBUILT, SOLID, carriageway_lines, line_feature

from hdmap_core.model import HDMap, TopologyNode
from hdmap_core.updates.lone import lone_copies_dropped


def _one_drive(f):
    return replace(f, drive_count=np.ones(len(f.points), dtype=int))


def _map(*extra):
    lines = carriageway_lines()  # 20 drives each
    node = TopologyNode(1, np.array([250.0, 55.0]), 0.0, 12.5, (), tuple(f.id for f in (*lines, *extra)))
    linked = replace(lines[1], successors=tuple(f.id for f in extra))
    return HDMap(features=(lines[0], linked, *lines[2:], *extra), topology=(node,))


def test_a_one_drive_border_along_a_divider_in_the_rebuilt_places_is_dropped_with_its_links():
    copy = _one_drive(line_feature(20, BORDER, 53.7, 220.0, 380.0))  # 0.2 m beside the divider at 53.5
    got, dropped = lone_copies_dropped(_map(copy), PLACES, REBUILT)
    assert dropped == (20,)
    assert 20 not in {f.id for f in got.features}
    assert all(20 not in f.successors and 20 not in f.predecessors for f in got.features)
    assert 20 not in got.topology[0].features and 2 in got.topology[0].features


def test_what_stays():
    cases = {
        # a line of the same type beside it: not a copy of another type (the aggregation's case)
        "same type": _one_drive(line_feature(20, DASHED, 53.7, 220.0, 380.0)),
        # nothing of another type along it: maybe what the other drives missed
        "alone": _one_drive(line_feature(20, SOLID, 55.2, 220.0, 380.0)),
        # two drives saw it
        "two drives": replace(line_feature(20, BORDER, 53.7, 220.0, 380.0), drive_count=np.full(161, 2)),
        # modelled (no drive saw it: count 0)
        "modelled": replace(line_feature(20, BORDER, 53.7, 220.0, 380.0), drive_count=np.zeros(161, dtype=int)),
        # a marking along a border: an edge line at its curb (here 0.3 m in from the barrier at 49)
        "edge line at a curb": _one_drive(line_feature(20, SOLID, 49.3, 220.0, 380.0)),
        # reaching out of the rebuilt places (x 100-500): the first map's, not the rebuild's
        "beyond the rebuilt places": _one_drive(line_feature(20, BORDER, 53.7, 420.0, 560.0)),
        # along the divider over less than 80 % of its length
        "mostly apart": _one_drive(
            line_feature(20, BORDER, 53.7, 220.0, 380.0, shift=lambda x: np.where(x < 260.0, 0.0, 1.5))
        ),
    }
    for name, extra in cases.items():
        hdmap = _map(extra)
        got, dropped = lone_copies_dropped(hdmap, PLACES, REBUILT)
        assert dropped == () and got is hdmap, name
