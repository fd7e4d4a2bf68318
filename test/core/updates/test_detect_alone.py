"""A change whose only place confirmed on its own is a share's change point that left a
dissenting drive out is no change (updates/detect.py): the tolerance of one drive in
``DISSENT_SHARE`` is for a drive that missed a changed line somewhere along a change, which spans
places (re-striping, bench_changes seed 2: three and four such places after 4 and 5 drives
through); a step at one place alone that not every drive after it shows is a run of misreads (a
wrong-type step of 3 drives at a ramp place, 270 m before a 1.0 m shift, bench shift1.0 seed 0;
the false `marking_new` of the sample bag ramps_20 followed with the `naive` preset)."""

from __future__ import annotations

from place_rows import place_row

from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.detect import detect_changes
from hdmap_core.updates.evidence import PlaceEvidence
from hdmap_core.updates.places import Places

N_PLACES = 11  # along a straight road: places (i, 0, 0), i = 0..10
PLACES = Places(100.0, {(i, 0): 0.0 for i in range(N_PLACES)})
N_DRIVES = 15  # drives 0..10 before, 11..14 after
DISSENT = 12  # the drive after that misses the changed line where it dissents


def _evidence(shares: dict[int, list[float]], moved: dict[int, float] | None = None) -> list[PlaceEvidence]:
    """Per drive and place: at each place of ``shares`` the drives after (11..14) read those shares
    of 20 typed points as the other type, every drive before none; no type evidence elsewhere
    (NaN). Displacement 0, but ``moved[i]`` at place ``i`` for the drives after."""
    moved = moved or {}
    out = []
    for d in range(N_DRIVES):
        for i in range(N_PLACES):
            wrong = shares[i][d - 11] if i in shares and d >= 11 else 0.0
            typed = 20 if i in shares else 0
            shift = moved.get(i, 0.0) if d >= 11 else 0.0
            out.append(place_row(d, i, shift, n_typed=typed, n_wrong_type=int(round(20 * wrong))))
    return out


SHOWS = [0.5, 0.5, 0.5, 0.5]
MISSES = [0.5, 0.05, 0.5, 0.5]  # DISSENT reads 5 %: one in 4, not the first


def test_a_lone_share_step_with_a_dissent_is_no_change():
    """Place 5 alone: 3 of the 4 drives after read half the markings as the other type, one 5 %.
    Its change point (drive 11, the dissent left out) passes every test, but no touching place
    confirms a type change on its own: no change. Before this rule: a `type` change at place 5."""
    assert detect_changes(_evidence({5: MISSES}), PLACES, config=ChangeConfig()) == []


def test_the_same_step_shown_by_every_drive_after_stays_a_change():
    """The rule costs nothing where no drive dissents: place 5 alone, all 4 drives after at 0.5."""
    (change,) = detect_changes(_evidence({5: SHOWS}), PLACES, config=ChangeConfig())
    assert change.kinds == ("type",) and change.keys == {(5, 0, 0)}


def test_two_places_with_a_dissent_are_a_change():
    """Places 5 and 6, the same drive missing the changed line at both (as the 2nd drive through
    the re-striping of seed 2): a change of two places confirmed on their own; so is place 5
    beside a place 6 every drive after shows."""
    for six in (MISSES, SHOWS):
        (change,) = detect_changes(_evidence({5: MISSES, 6: six}), PLACES, config=ChangeConfig())
        assert change.kinds == ("type",) and change.keys == {(5, 0, 0), (6, 0, 0)}
        assert change.places[0].dissent == 1 and change.places[1].dissent == (1 if six is MISSES else 0)
        assert change.drives_after == ("d11", "d12", "d13", "d14")


def test_places_grown_from_a_lone_dissenting_step_do_not_make_it_a_change():
    """Place 5's dissenting step, and at places 4 and 6 each drive after reading 0.3 wrong (too
    little to confirm there, enough to grow into: a drive in evidence shows half the smallest
    effect): still one place confirmed on its own, no change. Before this rule: a `type` change
    over places 4-6."""
    grown = [0.3, 0.3, 0.3, 0.3]
    assert detect_changes(_evidence({4: grown, 5: MISSES, 6: grown}), PLACES, config=ChangeConfig()) == []
    (change,) = detect_changes(_evidence({4: grown, 5: SHOWS, 6: grown}), PLACES, config=ChangeConfig())
    assert change.keys == {(4, 0, 0), (5, 0, 0), (6, 0, 0)}
    assert [p.extended for p in change.places] == [True, False, True]
