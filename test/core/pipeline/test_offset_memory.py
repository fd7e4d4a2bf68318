"""The offsets a drive had through earlier pivots (``pivot._OffsetMemory``)."""

from __future__ import annotations

import numpy as np

from hdmap_core.pipeline.pivot import _OffsetMemory


def test_lookup_finds_the_nearest_earlier_offset_within_reach():
    mem = _OffsetMemory(4, reach_m=50.0)
    # drives 0 and 2 seen by an earlier pivot (out of order, interleaved)
    mem.add(np.array([2, 0, 2, 0, 2]), np.array([300.0, 10.0, 100.0, 20.0, 200.0]), np.array([3.0, 0.1, 1.0, 0.2, 2.0]))
    uniq = np.array([0, 1, 2, 3])
    # the step's samples: drive code per sample (local) and their travelled distances
    local = np.array([2, 0, 1, 2, 0, 3, 2])
    s = np.array([190.0, 18.0, 5.0, 230.0, 26.0, 7.0, 180.0])
    got = mem.lookup(uniq, s, local, np.array([True, True, True, True]))
    # drive 0 at mean 22 m -> its offset at 20 m; drive 2 at mean 200 m -> 2.0; 1 and 3 unseen
    np.testing.assert_array_equal(got, [0.2, np.nan, 2.0, np.nan])
    # only where asked (the drives without a prior)
    got = mem.lookup(uniq, s, local, np.array([False, True, True, True]))
    np.testing.assert_array_equal(got, [np.nan, np.nan, 2.0, np.nan])
    # out of reach: nothing
    far = mem.lookup(np.array([2]), np.array([600.0]), np.array([0]), np.array([True]))
    assert np.isnan(far[0])


def test_later_marks_join_a_drives_history():
    mem = _OffsetMemory(2, reach_m=50.0)
    mem.add(np.array([1]), np.array([100.0]), np.array([0.5]))
    assert mem.lookup(np.array([1]), np.array([140.0]), np.array([0]), np.array([True]))[0] == 0.5
    mem.add(np.array([1, 1]), np.array([150.0, 400.0]), np.array([0.7, 0.9]))
    assert mem.lookup(np.array([1]), np.array([140.0]), np.array([0]), np.array([True]))[0] == 0.7
