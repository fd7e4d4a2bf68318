"""The places of one change agree on its time (updates/detect.py): a touching place of another
kind whose own change point lies before the change's, and whose series shows no change at the
change's time, is left out of it (as one of its kinds it took the shift's model of its unseen
lines away: ``updates.unseen``; bench_changes shift1.0, seed 0, after 3 drives)."""

from __future__ import annotations

import numpy as np
from place_rows import HOUR, place_row

from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.detect import detect_changes
from hdmap_core.updates.evidence import PlaceEvidence
from hdmap_core.updates.places import Places

N_PLACES = 11  # along a straight road: places (i, 0, 0), i = 0..10
PLACES = Places(100.0, {(i, 0): 0.0 for i in range(N_PLACES)})
TYPED = 2  # the place with type evidence, touching the shifted places 3-6


def _evidence(moved: np.ndarray, wrong: dict[int, float]) -> list[PlaceEvidence]:
    """Per drive (rows of ``moved``, time order) and place its displacement [m]; at place TYPED
    the drives in ``wrong`` read that share of 20 typed points as the other type (the others too
    few typed points there: NaN), every other place no type evidence."""
    out = []
    for d, row in enumerate(moved):
        for i, v in enumerate(row):
            typed = 20 if i == TYPED and d in wrong else 0
            n_wrong = int(round(20 * wrong.get(d, 0.0))) if typed else 0
            out.append(place_row(d, i, float(v), n_typed=typed, n_wrong_type=n_wrong))
    return out


def _shifted() -> np.ndarray:
    """15 drives, the last 3 after the markings of places 3-6 moved 1.0 m (drives scatter 0.03 m)."""
    v = np.random.default_rng(0).normal(0.0, 0.03, (15, N_PLACES))
    v[12:, 3:7] += 1.0
    return v


def test_a_touching_type_step_of_drives_before_the_change_is_left_out():
    """At place 2, beside the shifted places 3-6, drives 7 and 9 (before the shift) and 13 (after
    it) read half the markings as the other type, drive 8 reads 5 % (one in 4 after a share's
    change point may dissent); 7 drives before read none. Its own change point is drive 7's.
    With the split at the shift's time (drive 12) only drive 13 is after it: no change then. So
    the shift is a shift (kinds `geometry` only), the same change as without place 2's type
    evidence. Before this rule it was one change of kinds `geometry` and `type`, with place 2."""
    wrong = {**{d: 0.0 for d in range(7)}, 7: 0.5, 8: 0.05, 9: 0.5, 13: 0.5}
    (shift,) = detect_changes(_evidence(_shifted(), wrong), PLACES, config=ChangeConfig())
    assert shift.kinds == ("geometry",)
    assert shift.keys == {(i, 0, 0) for i in range(3, 7)}
    assert shift.time_ns == 13 * HOUR
    assert shift.drives_after == ("d12", "d13", "d14")
    (alone,) = detect_changes(_evidence(_shifted(), {}), PLACES, config=ChangeConfig())
    assert alone == shift
    # the place's own series is a change (drive 7 on): what leaves it out is the shift's time
    typed_only = _shifted()
    typed_only[12:, 3:7] -= 1.0
    (typed,) = detect_changes(_evidence(typed_only, wrong), PLACES, config=ChangeConfig())
    assert typed.kinds == ("type",) and typed.keys == {(TYPED, 0, 0)} and typed.time_ns == 8 * HOUR


def test_a_touching_type_step_at_the_change_time_is_part_of_it():
    """The same place 2 read half wrong by the 3 drives after the shift and by none of 9 before
    (a re-striping that came with it): its change point is the shift's, and it is one change of
    both kinds."""
    wrong = {**{d: 0.0 for d in range(9)}, 12: 0.5, 13: 0.5, 14: 0.5}
    (change,) = detect_changes(_evidence(_shifted(), wrong), PLACES, config=ChangeConfig())
    assert change.kinds == ("geometry", "type")
    assert change.keys == {(i, 0, 0) for i in range(2, 7)}
    assert change.time_ns == 13 * HOUR


def _gone(missed: dict[tuple[int, int], float]) -> list[PlaceEvidence]:
    """15 drives over places 0-10, each seeing 40 map marking points near it per place; the share
    ``missed[(drive, place)]`` of them it did not see (else none); displacement noise 0.03 m."""
    from dataclasses import replace

    v = np.random.default_rng(1).normal(0.0, 0.03, (15, N_PLACES))
    return [
        replace(place_row(d, i, float(v[d, i])), n_map_near=40, n_missed=int(round(40 * missed.get((d, i), 0.0))))
        for d in range(15)
        for i in range(N_PLACES)
    ]


def test_a_drive_of_the_old_road_that_missed_the_line_in_some_places_is_no_drive_after_the_change():
    """A divider removed over places 3-6 after drive 12: drives 12-14 miss half the markings
    there. Drive 11, before the removal, missed the line at places 3 and 4 (a dropout) but saw it
    at 5 and 6. Places 3 and 4 put their change point at drive 11, places 5 and 6 at drive 12:
    the lower median of the four is drive 11's, and taken as the change's time drive 11 was a
    drive after the change, its old line rebuilt into the zone. With the split at drive 11 places
    5 and 6 show no change (drive 11, the first after it, saw the line); with the split at drive 12
    all four do: the change's time is drive 12's."""
    missed = {(d, i): 0.5 for d in (12, 13, 14) for i in range(3, 7)}
    missed |= {(11, 3): 0.5, (11, 4): 0.5}
    (gone,) = detect_changes(_gone(missed), PLACES, config=ChangeConfig())
    assert gone.kinds == ("marking_gone",)
    assert {p.key for p in gone.places if not p.extended} == {(i, 0, 0) for i in range(3, 7)}
    assert {p.time_ns for p in gone.places if not p.extended} == {12 * HOUR, 13 * HOUR}  # drive 11's, 12's
    assert gone.time_ns == 13 * HOUR
    assert "d11" not in gone.drives_after
    # the dropout at one place of four: the median was drive 12's already
    (one,) = detect_changes(_gone(missed | {(11, 4): 0.0}), PLACES, config=ChangeConfig())
    assert one.time_ns == 13 * HOUR
