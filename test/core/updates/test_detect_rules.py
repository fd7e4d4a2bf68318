"""The rules of change detection (updates/detect.py) that keep a fleet without a change from
confirming one, each on a small in-memory fleet of per-place evidence (no map is built): every
test below confirms a change if its rule is taken out, and a real step is still confirmed."""

from __future__ import annotations

import numpy as np
import pytest
from place_rows import HOUR, place_row

from hdmap_core.model import Detection, Drive
from hdmap_core.pipeline.driver import PipelineConfig, build_map
from hdmap_core.simulation.changes import parse_change
from hdmap_core.simulation.config import SimConfig
from hdmap_core.simulation.fleet import simulate_fleet
from hdmap_core.simulation.synthetic import synthetic_highway
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.detect import change_point, detect_changes, drive_scatter, series_spread
from hdmap_core.updates.evidence import PlaceEvidence, fleet_evidence
from hdmap_core.updates.places import Places, places_of

N_PLACES = 11  # along a straight road: places (i, 0, 0), i = 0..10
PLACE = 5  # where the after-drives step
PLACES = Places(100.0, {(i, 0): 0.0 for i in range(N_PLACES)})
CONFIG = ChangeConfig()


def _evidence(values: np.ndarray, *, seen: dict[int, list[int]] | None = None) -> list[PlaceEvidence]:
    """Per drive (rows of ``values``, in time order) and place (columns, in the drive's order
    along the road) the markings' displacement against the borders [m]; no type or negative
    evidence (too few points: those shares are NaN). ``seen``: place -> the drives that passed it
    (default: every drive passes every place)."""
    out = []
    for d, row in enumerate(values):
        for i, v in enumerate(row):
            if seen is not None and i in seen and d not in seen[i]:
                continue
            out.append(place_row(d, i, float(v)))
    return out


def _calm(n_drives: int, seed: int = 0, sigma: float = 0.03) -> np.ndarray:
    """A fleet that agrees with the map everywhere: displacement ~ N(0, sigma)."""
    return np.random.default_rng(seed).normal(0.0, sigma, (n_drives, N_PLACES))


def _detect(values: np.ndarray, seen: dict[int, list[int]] | None = None) -> list:
    return detect_changes(_evidence(values, seen=seen), PLACES, config=CONFIG)


def _step(values: np.ndarray, noise: np.ndarray | None = None, fleet_spread: float = 0.0):
    """``change_point`` of one place's series with the default settings (ChangeConfig)."""
    return change_point(
        np.asarray(values, dtype=float),
        min_effect=CONFIG.min_shift_m,
        floor=CONFIG.displacement_floor_m,
        z_min=CONFIG.z_min,
        min_before=CONFIG.min_before,
        min_after=CONFIG.min_after,
        noise=noise,
        fleet_spread=fleet_spread,
    )


def test_a_real_shift_is_confirmed_after_three_drives():
    """The control of the rules below: 12 drives on the road as it was, 3 after its markings moved
    1.5 m over places 3-6 (drives scattering 0.03 m): one change of exactly those places, at the
    first drive after it, carried by the 3 drives."""
    v = _calm(15)
    v[12:, 3:7] += 1.5
    (change,) = _detect(v)
    assert change.kinds == ("geometry",)
    assert change.keys == {(i, 0, 0) for i in range(3, 7)}
    assert change.time_ns == 13 * HOUR
    assert change.drives_after == ("d12", "d13", "d14")
    assert all(abs(p.effect - 1.5) < 0.1 for p in change.places)
    # and so it is with the before-drives' own scatter as large as in the cases below
    v = _calm(15, sigma=0.1)
    v[12:, 3:7] += 1.5
    assert len(_detect(v)) == 1


def test_after_drives_among_the_before_drives_are_no_change():
    """Rule: every after-drive lies beyond the before-drives' nearest-rank 90th percentile. At one
    place 3 of 20 drives before were 1 m off already (they paired another line, say); 2 drives after
    at 0.9 m lie among them: the drives disagree there as they always did. With the rule out, the
    step from the before median (0.9 m on a spread of 0.1 m) is confirmed."""
    v = _calm(22)
    v[[2, 8, 14], PLACE] = 1.0
    v[20:, PLACE] = [0.9, 0.95]
    assert _detect(v) == []
    # the series of that place alone: the rule is what refuses it
    series = v[:, PLACE]
    assert _step(series) is None
    lifted = series.copy()
    lifted[[2, 8, 14]] = 0.0  # the same before-drives without their 1 m outliers: a change
    found = _step(lifted)
    assert found is not None and found[0] == 20


def _share_step(values: np.ndarray, *, min_each: float = 0.0):
    """``change_point`` of one place's share series (wrong type, say) with the default settings;
    ``detect`` runs it with ``min_each=CONFIG.min_share_drive``."""
    return change_point(
        np.asarray(values, dtype=float),
        min_effect=CONFIG.min_share,
        floor=CONFIG.share_floor,
        z_min=CONFIG.z_min,
        min_before=CONFIG.min_before,
        min_after=CONFIG.min_after_shares,
        heavy_tails=True,
        min_each=min_each,
    )


def test_a_later_drive_that_misses_the_changed_line_does_not_undo_it():
    """Tolerance (``DISSENT_SHARE``): 20 drives before (wrong-type share 0, one 0.1), 8 after a
    re-striping reading half the markings near them as the other type, the 4th of them reading
    none (it missed the changed line there): the split stays at the first drive after. Without
    it the true split fails, and every later one has changed drives among its before-drives:
    the change confirmed after 3 drives is gone after 8 (seed 2 of the bench lost its re-striping
    so after 5)."""
    each = CONFIG.min_share_drive  # as detect runs it
    series = np.r_[np.zeros(19), 0.1, np.full(8, 0.5)]
    series[23] = 0.0
    found = _share_step(series, min_each=each)
    assert found is not None and found[0] == 20 and abs(found[1] - 0.5) < 0.01
    assert (
        _share_step(series[:23], min_each=each) is not None and _share_step(series[:23], min_each=each)[0] == 20
    )  # after 3
    # the drive that misses it first: the change point is the next drive's
    first = series.copy()
    first[[20, 23]] = first[[23, 20]]
    found = _share_step(first, min_each=each)
    assert found is not None and found[0] == 21
    # two of 5 that miss it: more than one in DISSENT_SHARE = 4, no split at the first
    two = np.r_[series[:20], 0.5, 0.0, 0.5, 0.0, 0.5]
    assert _share_step(two, min_each=each) is None or _share_step(two, min_each=each)[0] != 20
    # the displacement allows none: a drive after a 1.5 m shift reading no move breaks the split
    moved = np.r_[np.zeros(20), np.full(8, 1.5)]
    moved[23] = 0.0
    assert _step(moved) is None or _step(moved)[0] != 20


def test_three_drives_before_with_one_far_off_are_too_few_to_tell():
    """Rule: with fewer than 10 drives before, their spread is at least their standard deviation.
    A place 3 drives passed before, one of them 0.45 m off the other two (0.00, 0.02 m): the
    median absolute deviation of three values is the smaller half-gap (0.02 m, floored to 0.1 m),
    which would make 2 drives at 1 m a step of z = 10.5; on their standard deviation (0.25 m) it is
    z = 4.1, below 5: no change."""
    v = _calm(14)
    v[:3, PLACE] = [0.0, 0.02, 0.45]
    v[12:, PLACE] = [0.95, 1.0]
    seen = {PLACE: [0, 1, 2, 12, 13]}  # the other drives took another road there
    assert _detect(v, seen=seen) == []
    series = np.array([0.0, 0.02, 0.45, 0.95, 1.0])
    assert _step(series) is None
    # the same step on 10 drives before that agree: confirmed (the rule costs nothing there)
    assert _step(np.r_[np.zeros(9), 0.02, 0.95, 1.0]) is not None


def test_a_fleet_that_scatters_everywhere_needs_a_larger_step():
    """Rule: the standard error uses at least the fleet's own per-place spread (``series_spread``).
    Drives whose displacement drifts along the road, each its own way (a map without offset
    correction: the fleet's spread is 0.36 m), happen to agree at one place; 2 drives after lie
    0.7 m off there. On that place's own spread (0.01 m, floored to 0.1 m) z = 9.1; on the fleet's
    z = 2.6: no change."""
    rng = np.random.default_rng(3)
    slope = rng.normal(0.0, 0.2, 14)  # per drive, m per place away from PLACE
    slope[12:] = [0.02, -0.02]  # the after-drives drift little: their own scatter is small
    v = slope[:, None] * (np.arange(N_PLACES) - PLACE)[None, :] + rng.normal(0.0, 0.01, (14, N_PLACES))
    v[12:, PLACE] += 0.7
    by_place: dict = {}
    for e in _evidence(v):
        by_place.setdefault(e.key, []).append(e)
    spread = series_spread(by_place, "displacement", CONFIG)
    assert spread > 0.3
    assert _detect(v) == []
    assert _step(v[:, PLACE]) is not None  # without the fleet's spread
    assert _step(v[:, PLACE], fleet_spread=spread) is None


def test_drives_that_scatter_from_place_to_place_are_no_change():
    """Rule: an after-drive must lie at least twice its own place-to-place scatter
    (``drive_scatter``) from the before median. Two badly localised drives whose markings and
    borders disagree differently in every place (+-0.4 m, alternating) both lie 0.6 m off at one
    place: that says nothing of the place (their scatter is 0.84 m: they would have to lie 1.7 m
    off). With the rule out, z = 8.1 there."""
    v = _calm(14)
    sign = np.where(np.arange(N_PLACES) % 2 == 0, 1.0, -1.0)
    v[12] = 0.4 * sign
    v[13] = -0.4 * sign
    v[12:, PLACE] = [0.6, 0.62]
    noise = drive_scatter(_evidence(v))
    assert noise["d12"] > 0.5 and noise["d13"] > 0.5 and noise["d00"] < 0.1
    assert _detect(v) == []
    assert _step(v[:, PLACE]) is not None  # without the drives' own scatter
    with_noise = np.array([noise[f"d{d:02d}"] for d in range(14)])
    assert _step(v[:, PLACE], noise=with_noise) is None


def test_no_geometry_change_where_the_map_lies_off_its_own_drives():
    """Rule (poor consensus): no geometry change at a place whose before-drives' median
    displacement is beyond the smallest shift (0.5 m): the map lies off its own drives there
    (a sparse or poorly aligned place), so a step against it is no evidence. Every drive before
    sees the map's markings 0.8 m off at one place, 2 drives after 1.5 m: a clean step of 0.7 m
    (z = 9.4), which change_point alone accepts, and no change is confirmed."""
    v = _calm(14)
    v[:12, PLACE] += 0.8
    v[12:, PLACE] += 1.5
    assert _detect(v) == []
    found = _step(v[:, PLACE])
    assert found is not None and found[0] == 12  # the step itself passes every other test
    # the same step from a map that agreed with its drives (median 0) is confirmed
    v[:12, PLACE] -= 0.8
    v[12:, PLACE] -= 0.8
    (change,) = _detect(v)
    assert change.keys == {(PLACE, 0, 0)}


def _typed(shares: np.ndarray) -> list[PlaceEvidence]:
    """Per drive (in time order) its share of wrong-type markings at place PLACE, of 20 typed
    points; every drive agrees with the map elsewhere (share 0) and no displacement (NaN)."""
    out = []
    for d, share in enumerate(shares):
        for i in range(N_PLACES):
            wrong = int(round(20 * share)) if i == PLACE else 0
            out.append(place_row(d, i, float("nan"), n_pairs=0, n_typed=20, n_wrong_type=wrong))
    return out


def test_share_after_drives_must_lie_beyond_every_before_drive():
    """Rule: for a share (wrong type, missed, extra) every after-drive lies beyond the before
    drives' maximum, not only their 90th percentile. Of 20 drives before, 18 read every type
    right at one place, one misread 20 % and one 60 % (the misreading drives of a share are its
    tail, and the 90th percentile, the second largest, is among them); the last 3 drives misread
    55, 55 and 50 %: as the one before did, so the road need not have changed (seen on
    carla_town04 seed 1, missed 0.48, 0.48, 0.35 after a before-drive's 0.49). With the 90th
    percentile the step of 0.53 is confirmed (z 6.3); the same 3 after one before-drive at 30 %
    instead of 60 % are confirmed with the rule too, and so are after-drives that tie with the
    largest before."""
    shares = np.zeros(23)
    shares[[4, 11]] = [0.2, 0.6]
    shares[20:] = [0.55, 0.55, 0.5]
    assert detect_changes(_typed(shares), PLACES, config=CONFIG) == []
    assert _share_step(shares) is None
    lower = shares.copy()
    lower[11] = 0.3  # below every after-drive: they lie beyond the drives before
    (change,) = detect_changes(_typed(lower), PLACES, config=CONFIG)
    assert change.kinds == ("type",)
    assert change.keys == {(PLACE, 0, 0)}
    assert change.drives_after == ("d20", "d21", "d22")
    found = _share_step(lower)
    assert found is not None and found[0] == 20
    # an after-drive at the largest before share is not among them (a share is often 1 of 2):
    # re-striping read as 0.5, 0.5, 0.75 after one drive before read 0.5 is confirmed
    tie = np.zeros(24)
    tie[11] = 0.5
    tie[21:] = [0.5, 0.5, 0.75]
    (change,) = detect_changes(_typed(tie), PLACES, config=CONFIG)
    assert change.drives_after == ("d21", "d22", "d23")


def test_every_share_after_drive_reads_about_half_its_markings_changed():
    """Rule (``min_share_drive``): every drive after a change point of a share reads at least 0.45
    of the markings near it wrong (or missed): a changed line is one of the two markings of the
    drive's lane, half of what it reads there. 11 drives before read every type right but one
    (14 %); the fleet's last 4 drives misread 59, 50, 41 and 40 % at that place, a chance run of
    partial misreads (seen on paper_like_134 seed 2: z 16.3, grown into 7 places). Every other
    test passes: with the rule out the step of 0.475 is confirmed. The same 4 drives reading half
    or more are a change."""
    shares = np.zeros(15)
    shares[9] = 0.15
    shares[11:] = [0.6, 0.5, 0.4, 0.4]
    assert detect_changes(_typed(shares), PLACES, config=CONFIG) == []
    assert _share_step(shares) is not None  # without the rule (min_each 0)
    restriped = shares.copy()
    restriped[11:] = [0.6, 0.5, 0.5, 0.5]
    (change,) = detect_changes(_typed(restriped), PLACES, config=CONFIG)
    assert change.kinds == ("type",)
    assert change.drives_after == ("d11", "d12", "d13", "d14")


# ------------------------------------------------------------------------------ on a simulated fleet


def _moved_left(drive: Drive, metres: float) -> Drive:
    """``drive`` localised ``metres`` too far left over its whole length, as a GNSS error would:
    trajectory and detections alike."""
    left = np.stack([-np.sin(drive.yaw), np.cos(drive.yaw)], axis=1)
    mean_left = left.mean(axis=0) / np.linalg.norm(left.mean(axis=0))
    dets = tuple(Detection(d.type, d.points + metres * mean_left) for d in drive.detections)
    return Drive(drive.drive_id, drive.xy + metres * left, drive.yaw, drive.stamps_ns, dets, drive.vehicle_id)


def _fleet_changes(drives: list[Drive]) -> list:
    hdmap = build_map(drives, config=PipelineConfig(), seed=0, workers=1).map
    places = places_of(drives, cell_m=CONFIG.cell_m)
    return detect_changes(fleet_evidence(drives, hdmap, places, config=CONFIG), places, config=CONFIG)


@pytest.mark.slow
def test_one_badly_localised_drive_on_a_simulated_fleet():
    """A 1.5 km motorway, 12 drives, then 3 more, the middle one of them localised 1.5 m too far
    left over its whole length: without a change of the road nothing is confirmed; after the lanes
    moved 1.5 m over 700 m, the change is confirmed with all 3 drives in evidence (the bad one too:
    its markings and borders are off alike, so its displacement is the road's). The anchor on the
    borders (updates/evidence.py) makes this so, not one of the rules above: with any one of them
    taken out this still passes."""
    road = synthetic_highway("motorway", length_m=1500.0)
    sim = SimConfig(n_drives=15, snippet_length_min_m=1300.0, snippet_length_max_m=1500.0, direction_bias=1.0)
    change = parse_change("shift:400-1100:1.5:fwd_lane2@12")
    plain = list(simulate_fleet(road, config=sim, seed=5).drives)
    plain[13] = _moved_left(plain[13], 1.5)
    assert _fleet_changes(plain) == []
    moved = list(simulate_fleet(road, config=sim, seed=5, changes=[change]).drives)
    moved[13] = _moved_left(moved[13], 1.5)
    (found,) = _fleet_changes(moved)
    assert "geometry" in found.kinds
    assert found.drives_after == tuple(sorted(d.drive_id for d in moved[12:]))
