"""Places and a map's markings along them (``updates.places``)."""

from __future__ import annotations

import numpy as np
from carriageway_samples import BORDER, CHANGED, DASHED, PLACES, SOLID, carriageway_lines, line_feature

from hdmap_core.model import HDMap
from hdmap_core.updates.places import markings_in


def test_markings_in_gives_the_markings_with_a_point_in_the_places():
    # the carriageway's markings and barriers (x 0-600), a dashed piece in place 0 only (x 10-90)
    # and a one-point solid in place 2:
    #
    #   place     0       1       2       3       4       5
    #   lines  |=======|=======|=======|=======|=======|=======|   ids 1-4 (markings), 5-6 (borders)
    #   piece   |--|                                               id 7
    #   dot                     *                                  id 8
    dot = line_feature(8, SOLID, 55.0, 250.0, 250.0)
    hdmap = HDMap(features=(*carriageway_lines(), line_feature(7, DASHED, 52.0, 10.0, 90.0), dot))
    got = markings_in(hdmap, PLACES, set(CHANGED))
    # the four markings cross places 2-3; not the borders, the piece elsewhere, nor one point
    assert [m.feature.id for m in got] == [1, 2, 3, 4]
    assert [m.feature_index for m in got] == [0, 1, 2, 3]
    for m in got:
        assert m.keys == PLACES.keys_along(m.points)
        x = m.points[:, 0]
        np.testing.assert_array_equal(m.inside, (x >= 200.0) & (x < 400.0))
    assert not any(int(m.feature.type) == int(BORDER) for m in got)
    assert markings_in(hdmap, PLACES, set()) == []
    # in place 0: the four markings and the piece
    (piece,) = markings_in(hdmap, PLACES, {(0, 0, 0)})[4:]
    assert piece.feature.id == 7 and piece.inside.all()
