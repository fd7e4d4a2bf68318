"""Physical plausibility of drives: every bound names its reason; good drives pass unchanged."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hdmap_core.errors import ConfigError, InvalidDriveError
from hdmap_core.model import Detection, FeatureType
from hdmap_core.pipeline.driver import prepare_drives
from hdmap_core.plausibility import REASONS, PhysicalBounds, check_plausible, check_quaternions

from bag_samples import make_drive


def _pose_moved(drive, i, dxy):
    xy = np.array(drive.xy, dtype=float)
    xy[i] += dxy
    return replace(drive, xy=xy)


def _stamps(drive, fn):
    s = np.array(drive.stamps_ns, dtype=np.int64)
    return replace(drive, stamps_ns=fn(s))


def _zigzag(drive):
    xy = np.array(drive.xy, dtype=float)
    xy[1::2, 1] += 50.0
    return replace(drive, xy=xy)


def _far_detection(drive, where):
    pts = np.array(drive.detections[0].points, dtype=float)
    pts[len(pts) // 2] = where
    return replace(drive, detections=(Detection(FeatureType.SOLID, pts), *drive.detections[1:]))


def _standing(drive):
    n = len(drive.xy)
    rng = np.random.default_rng(1)
    return replace(drive, xy=np.full((n, 2), 10.0) + rng.normal(0, 0.3, (n, 2)), detections=())


# A drive of 50 poses 1 m and 0.1 s apart along +x (bag_samples.make_drive), spoiled one way each.
CASES = {
    "pose at 1e9 m": (lambda d: _pose_moved(d, 20, (1e9, 0.0)), "coordinate_out_of_bounds"),
    "pose at 1e200 m": (lambda d: _pose_moved(d, 20, (0.0, 1e200)), "coordinate_out_of_bounds"),
    "detection at 1e60 m": (lambda d: _far_detection(d, (1e60, 0.0)), "coordinate_out_of_bounds"),
    "detection 5 km away": (lambda d: _far_detection(d, (20.0, 5000.0)), "detection_out_of_range"),
    "reversed stamps": (lambda d: _stamps(d, lambda s: s[::-1].copy()), "stamps_not_increasing"),
    "repeated stamp": (lambda d: _stamps(d, lambda s: np.concatenate([s[:10], s[9:-1]])), "stamps_not_increasing"),
    "stamps jump an hour": (
        lambda d: _stamps(d, lambda s: s + (np.arange(len(s)) >= 25) * 3_600_000_000_000),
        "stamp_gap",
    ),
    "pose 200 m off": (lambda d: _pose_moved(d, 20, (0.0, 200.0)), "pose_jump"),
    "50 m glitch": (lambda d: _pose_moved(d, 20, (0.0, 50.0)), "too_fast"),
    "zigzag +50 m": (_zigzag, "too_fast"),
    "standing still": (_standing, "standing_still"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_each_bound_rejects_with_its_reason(case):
    spoil, reason = CASES[case]
    good = make_drive("d1")
    assert check_plausible(good) is good
    with pytest.raises(InvalidDriveError) as err:
        check_plausible(spoil(good))
    assert err.value.reason == reason and reason in REASONS
    assert err.value.drive_id == "d1" and err.value.detail


def test_glitch_at_a_slow_pose_rate():
    # poses 1 s apart: a 12 m glitch is below the speed bound, caught by the glitch bound
    d = _stamps(make_drive("g"), lambda s: s[0] + np.arange(len(s), dtype=np.int64) * 1_000_000_000)
    with pytest.raises(InvalidDriveError) as err:
        check_plausible(_pose_moved(d, 20, (0.0, 12.0)))
    assert err.value.reason == "pose_glitch"
    check_plausible(_pose_moved(d, 20, (0.0, 8.0)))  # within the bound: kept


def test_bounds_are_settings():
    d = _pose_moved(make_drive("d"), 20, (0.0, 50.0))
    check_plausible(d, bounds=PhysicalBounds(max_speed_mps=1000.0, max_glitch_m=60.0))
    with pytest.raises(ConfigError, match="max_speed_mps"):
        PhysicalBounds(max_speed_mps=0.0)


@pytest.mark.parametrize(
    "q, ok",
    [
        ((0.0, 0.0, 0.0, 1.0), True),
        ((0.0, 0.0, 0.6, 0.8), True),
        ((0.0, 0.0, 0.0, 0.0), False),
        ((0.0, 0.0, 0.0, 2.0), False),
        ((0.0, 0.0, np.nan, 1.0), False),
    ],
)
def test_quaternion_norm(q, ok):
    quat = np.tile(np.asarray(q, dtype=float), (3, 1))
    if ok:
        check_quaternions("q", quat)
    else:
        with pytest.raises(InvalidDriveError, match="bad_quaternion"):
            check_quaternions("q", quat)


def test_prepare_drives_reports_implausible_and_skips_bounds_when_asked():
    good, bad = make_drive("a"), _zigzag(make_drive("b", seed=1))
    usable, rejected = prepare_drives([good, bad])
    assert [d.drive_id for d in usable] == ["a"]
    assert rejected[0][0] == "b" and rejected[0][1].startswith("too_fast")
    usable, rejected = prepare_drives([good, bad], bounds=None)
    assert len(usable) == 2 and not rejected


def test_prepare_drives_on_several_processes_gives_the_serial_verdicts():
    bad = [spoil(make_drive(f"bad{i}", seed=i)) for i, (spoil, _) in enumerate(CASES.values())]
    drives = [make_drive("a"), *bad, make_drive("b", seed=7), make_drive("a", seed=8)]  # the last: a repeated id
    serial = prepare_drives(drives)
    assert [d.drive_id for d in serial[0]] == ["a", "b"] and len(serial[1]) == len(CASES) + 1
    for workers in (2, 3):
        usable, rejected = prepare_drives(drives, workers=workers)
        assert [id(d) for d in usable] == [id(d) for d in serial[0]] and rejected == serial[1]
