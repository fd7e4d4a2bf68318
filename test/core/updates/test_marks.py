"""The lines a re-striping or a removed marking left alone, kept from the first map (``updates.marks``)."""

from __future__ import annotations

import numpy as np
from carriageway_samples import CHANGED, DASHED, PLACES, REBUILT, SOLID, carriageway_lines, line_feature

from hdmap_core.model import Detection, Drive, HDMap
from hdmap_core.updates.detect import DetectedChange, PlaceChange
from hdmap_core.updates.marks import share_places, unchanged_marks
from hdmap_core.updates.splice import Reach, splice

# The carriageway of carriageway_samples, places 2 and 3 (x 200-400) changed; the drives after the
# change keep to the left lane (y = 58.75), so the right edge line lies 8.75 m from them: within
# the sensors' reach (12 m), rarely seen.
LANE_Y = 58.75
FIRST = HDMap(features=(*carriageway_lines(),))


def _after(y=LANE_Y, seen=()):
    """Two drives after the change along the left lane; ``seen``: (type, y) of lines the first of
    them detected over the whole carriageway."""
    x = np.arange(0.0, 600.0, 2.0)
    xy = np.stack([x, np.full(len(x), y)], axis=1)
    stamps = 10**12 + np.arange(len(x), dtype=np.int64) * 10**8
    dets = tuple(Detection(t, np.stack([x, np.full(len(x), float(ly))], axis=1)) for t, ly in seen)
    return [Drive(f"a{i}", xy, np.zeros(len(x)), stamps, dets if i == 1 else ()) for i in (1, 2)]


def _local(*lines):
    """The aligned rebuild of places 1-4 from the drives after the change: the lines they saw."""
    return HDMap(features=tuple(line_feature(100 + i, t, y, 100.0, 499.0) for i, (t, y) in enumerate(lines)))


def _change(kind):
    places = tuple(PlaceChange(k, kind, 10, 5, 0.5, 9.0, ("b1", "b2", "b3"), ("a1", "a2")) for k in CHANGED)
    return DetectedChange(7, 10, (kind,), places, ("a1", "a2"), 0.9)


def _followed(local, change, *, keep_unchanged=True, seen=()):
    after = _after(seen=seen)
    kept = unchanged_marks(FIRST, local, PLACES, [change], after, REBUILT) if keep_unchanged else np.zeros((0, 2))
    reach = Reach(np.concatenate([d.xy for d in after]), 12.0, keep=kept)
    return splice(FIRST, local, PLACES, REBUILT, reach=reach)


def _lines_at(hdmap, x=300.0):
    """(type, y) of the markings crossing x, sorted by y."""
    out = []
    for f in hdmap.features:
        if int(f.type) not in (int(SOLID), int(DASHED)):
            continue
        sel = np.abs(f.points[:, 0] - x) < 0.5
        out += [(int(f.type), round(float(y), 2)) for y in f.points[sel, 1]]
    return sorted(set(out), key=lambda t: t[1])


def test_re_striping_keeps_the_lines_the_drives_after_it_did_not_see():
    # the divider 57 painted solid; the drives after it saw their own lane's lines only
    local = _local((SOLID, 57.0), (SOLID, 60.5))
    got = _lines_at(_followed(local, _change("type")))
    assert got == [(int(SOLID), 50.0), (int(DASHED), 53.5), (int(SOLID), 57.0), (int(SOLID), 60.5)]
    # without it the rebuilt place had only what those drives saw: the far lines were lost
    plain = _lines_at(_followed(local, _change("type"), keep_unchanged=False))
    assert plain == [(int(SOLID), 57.0), (int(SOLID), 60.5)]


def test_a_marking_gone_next_to_the_drives_goes_and_a_far_line_stays():
    # both dividers removed: the drives see only the left edge; the right edge line lies 8.75 m
    # away, beyond their lane and the next
    local = _local((SOLID, 60.5))
    got = _lines_at(_followed(local, _change("marking_gone")))
    assert got == [(int(SOLID), 50.0), (int(SOLID), 60.5)]


def test_a_line_in_the_next_band_goes_only_with_its_type():
    # both dividers removed; the drives after the change keep to the middle lane (55.25): the
    # dividers lie in their own lane (1.75 m), the edge lines in the next band (5.25 m), which
    # they saw the left one of only. The solid right edge did not go: no solid went in a drive's
    # own lane
    local = _local((SOLID, 60.5))
    after = _after(y=55.25)
    kept = unchanged_marks(FIRST, local, PLACES, [_change("marking_gone")], after, REBUILT)
    reach = Reach(np.concatenate([d.xy for d in after]), 12.0, keep=kept)
    got = _lines_at(splice(FIRST, local, PLACES, REBUILT, reach=reach))
    assert got == [(int(SOLID), 50.0), (int(SOLID), 60.5)]
    # a solid that went in their own lane (the right one of it, 53.5 here taken as solid) takes
    # the solid of the next band with it
    first = HDMap(
        features=tuple(
            f if abs(f.points[0, 1] - 53.5) > 0.1 else line_feature(f.id, SOLID, 53.5, 0.0, 600.0)
            for f in FIRST.features
        )
    )
    kept = unchanged_marks(first, local, PLACES, [_change("marking_gone")], after, REBUILT)
    assert not np.any(np.abs(kept[:, 1] - 50.0) < 0.1)


def test_a_line_one_drive_after_the_change_detected_is_no_gone_line():
    # only the divider 57 was removed; one drive saw the divider 53.5 in the next lane, too few
    # for the local map
    local = _local((SOLID, 60.5))
    got = _lines_at(_followed(local, _change("marking_gone"), seen=((DASHED, 53.3), (SOLID, 60.5))))
    assert got == [(int(SOLID), 50.0), (int(DASHED), 53.5), (int(SOLID), 60.5)]


def test_a_line_the_local_map_saw_is_taken_from_it():
    local = _local((SOLID, 57.3), (SOLID, 60.5), (SOLID, 50.2))
    kept = unchanged_marks(FIRST, local, PLACES, [_change("type")], _after(), REBUILT)
    # of the first map's markings in the rebuilt places only the dashed 53.5 stays
    assert len(kept) and np.allclose(kept[:, 1], 53.5)


def test_a_geometry_change_keeps_nothing_here():
    change = _change("geometry")
    assert share_places([change], PLACES, REBUILT) == set()
    kept = unchanged_marks(FIRST, _local((SOLID, 60.5)), PLACES, [change], _after(), REBUILT)
    assert len(kept) == 0
    # a re-striping beside a shift: the shifted places and their neighbours are not its
    mixed = DetectedChange(8, 10, ("geometry", "type"), _change("type").places, ("a1", "a2"), 0.9)
    assert share_places([mixed], PLACES, REBUILT) == set()
