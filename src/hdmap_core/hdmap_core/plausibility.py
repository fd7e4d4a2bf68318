"""Physical plausibility of a drive: bounds no real vehicle or sensor leaves.

``model.validate_drive`` checks the form of a drive (shapes, finite numbers, known types); this
module checks that it could have happened: coordinates near the map origin, poses in time order
that move at a possible speed without glitches, a vehicle that moved at all, and detections within
sensor range of the vehicle. A drive that fails is rejected as a whole with a named reason
(``InvalidDriveError.reason``), never repaired:

- a pose fault (glitch, jump, reversed stamps) also misplaces the detections near it, which are
  placed in the map frame through the poses;
- a detection far beyond sensor range shows that the drive's transform or perception output was
  broken, so its other detections are not trusted either;
- the alignment (Sec. IV-B) estimates one offset curve per drive, so a partly repaired drive
  could still bias its neighbours, while dropping one drive of a fleet costs little.

Every entry point of drives applies it: the pipeline's ``prepare_drives`` (``bag2map``,
``build_map``), the live ``drive_ingestor`` and ``segment_mapper``. The message conversion checks
the pose quaternions (:func:`check_quaternions`), which the data model no longer carries.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hdmap_core.checks import check_range
from hdmap_core.errors import InvalidDriveError
from hdmap_core.model import Drive, validate_drive
from hdmap_core.parallel import map_balanced

__all__ = [
    "PhysicalBounds",
    "check_plausible",
    "prepare_drives",
    "check_quaternions",
    "QUATERNION_NORM_TOLERANCE",
    "REASONS",
]

# A pose orientation is a unit quaternion; writers normalise in float64 (float32 at worst, 1e-7),
# so a norm off by more than 1 % is a defect (e.g. an all-zero quaternion: no heading at all).
QUATERNION_NORM_TOLERANCE = 0.01

# reason key -> what it means (docs and tests name them)
REASONS = {
    "coordinate_out_of_bounds": "a pose or detection point farther from the map origin than max_coordinate_m",
    "stamps_not_increasing": "pose stamps not strictly increasing",
    "stamp_gap": "consecutive poses farther apart in time than max_pose_gap_s",
    "pose_jump": "consecutive poses farther apart than max_pose_step_m",
    "too_fast": "speed between consecutive poses above max_speed_mps",
    "pose_glitch": "a pose farther than max_glitch_m from the midpoint of its neighbours",
    "standing_still": "the trajectory stays within min_extent_m",
    "bad_quaternion": "a pose orientation whose norm is not 1",
    "detection_out_of_range": "a detection point farther than max_detection_range_m from every pose",
}


@dataclass(frozen=True)
class PhysicalBounds:
    """Bounds a real drive stays within (defaults generous: several times what a car does).

    Attributes:
        max_coordinate_m: largest |x| or |y| of a pose or detection point [m]; the map frame is a
            local tangent plane, whose height error is already ~20 km at 500 km from its origin.
        max_pose_step_m: longest distance between consecutive poses [m].
        max_pose_gap_s: longest time between consecutive poses [s].
        max_speed_mps: highest speed between consecutive poses [m/s] (100 m/s = 360 km/h).
        max_glitch_m: largest distance of a pose from the midpoint of its two neighbours [m]
            (a smooth path at a 40 m pose spacing and a 200 m curve radius: 4 m).
        min_extent_m: a drive whose poses all lie within a box of this diagonal stood still [m].
        max_detection_range_m: largest distance of a detection point from the nearest pose [m].
    """

    max_coordinate_m: float = 500_000.0
    max_pose_step_m: float = 100.0
    max_pose_gap_s: float = 10.0
    max_speed_mps: float = 100.0
    max_glitch_m: float = 10.0
    min_extent_m: float = 5.0
    max_detection_range_m: float = 150.0

    def __post_init__(self) -> None:
        check_range(
            self,
            (
                "max_coordinate_m",
                "max_pose_step_m",
                "max_pose_gap_s",
                "max_speed_mps",
                "max_glitch_m",
                "max_detection_range_m",
            ),
            low=0.0,
            low_open=True,
        )
        check_range(self, ("min_extent_m",), low=0.0, finite=True)


def check_quaternions(drive_id: str, quaternions: np.ndarray) -> None:
    """Raise ``InvalidDriveError("bad_quaternion")`` unless every (x, y, z, w) row has norm 1.

    Args:
        quaternions: (N, 4) pose orientations.
    """
    q = np.asarray(quaternions, dtype=float).reshape(-1, 4)
    with np.errstate(over="ignore", invalid="ignore"):
        norm = np.sqrt(np.einsum("ij,ij->i", q, q))
        bad = ~(np.abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InvalidDriveError(drive_id, "bad_quaternion", f"pose {i} orientation has norm {norm[i]:.6g}, want 1")


def check_plausible(drive: Drive, *, bounds: PhysicalBounds = PhysicalBounds()) -> Drive:
    """Return ``drive`` unchanged when it is physically plausible, else raise.

    Args:
        drive: a drive that passed ``model.validate_drive`` (finite, of consistent shapes).
        bounds: the physical bounds.

    Raises:
        InvalidDriveError: ``reason`` one of :data:`REASONS`, ``detail`` names the pose or point.
    """
    did = drive.drive_id
    xy = np.asarray(drive.xy, dtype=float).reshape(-1, 2)
    _check_magnitude(did, "pose", xy, bounds.max_coordinate_m)
    for i, det in enumerate(drive.detections):
        _check_magnitude(
            did, f"detection {i} point", np.asarray(det.points, dtype=float).reshape(-1, 2), bounds.max_coordinate_m
        )
    _check_stamps(did, np.asarray(drive.stamps_ns, dtype=np.int64).reshape(-1), bounds)
    _check_motion(did, xy, np.asarray(drive.stamps_ns, dtype=np.int64).reshape(-1), bounds)
    _check_range(drive, xy, bounds)
    return drive


def _first(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def _check_magnitude(did: str, what: str, pts: np.ndarray, limit: float) -> None:
    far = np.abs(pts).max(axis=1) > limit if len(pts) else np.zeros(0, bool)
    if far.any():
        i = _first(far)
        raise InvalidDriveError(
            did, "coordinate_out_of_bounds", f"{what} {i} at ({pts[i, 0]:.6g}, {pts[i, 1]:.6g}) m, limit {limit:g} m"
        )


def _check_stamps(did: str, stamps: np.ndarray, bounds: PhysicalBounds) -> None:
    # int64 differences of valid stamps cannot overflow in practice; compare as Python ints where they might
    dt = np.diff(stamps.astype(np.float64))
    back = ~(dt > 0)
    if back.any():
        i = _first(back)
        raise InvalidDriveError(
            did, "stamps_not_increasing", f"pose {i + 1} stamp {int(stamps[i + 1])} after {int(stamps[i])}"
        )
    gap = dt > bounds.max_pose_gap_s * 1e9
    if gap.any():
        i = _first(gap)
        raise InvalidDriveError(
            did, "stamp_gap", f"{dt[i] / 1e9:.6g} s between poses {i} and {i + 1}, limit {bounds.max_pose_gap_s:g} s"
        )


def _check_motion(did: str, xy: np.ndarray, stamps: np.ndarray, bounds: PhysicalBounds) -> None:
    step = np.hypot(*np.diff(xy, axis=0).T)
    jump = step > bounds.max_pose_step_m
    if jump.any():
        i = _first(jump)
        raise InvalidDriveError(
            did, "pose_jump", f"{step[i]:.6g} m between poses {i} and {i + 1}, limit {bounds.max_pose_step_m:g} m"
        )
    speed = step / (np.diff(stamps.astype(np.float64)) / 1e9)
    fast = speed > bounds.max_speed_mps
    if fast.any():
        i = _first(fast)
        raise InvalidDriveError(
            did, "too_fast", f"{speed[i]:.6g} m/s between poses {i} and {i + 1}, limit {bounds.max_speed_mps:g} m/s"
        )
    if len(xy) >= 3:
        dev = np.hypot(*(xy[1:-1] - 0.5 * (xy[:-2] + xy[2:])).T)
        glitch = dev > bounds.max_glitch_m
        if glitch.any():
            i = _first(glitch)
            raise InvalidDriveError(
                did,
                "pose_glitch",
                f"pose {i + 1} lies {dev[i]:.6g} m off its neighbours, limit {bounds.max_glitch_m:g} m",
            )
    extent = float(np.hypot(*np.ptp(xy, axis=0)))
    if extent < bounds.min_extent_m:
        raise InvalidDriveError(
            did, "standing_still", f"all poses within {extent:.3g} m, need {bounds.min_extent_m:g} m"
        )


def _check_range(drive: Drive, xy: np.ndarray, bounds: PhysicalBounds) -> None:
    if not drive.detections:
        return
    from scipy.spatial import cKDTree  # noqa: PLC0415 - only drives with detections need it

    pts = np.concatenate([np.asarray(d.points, dtype=float).reshape(-1, 2) for d in drive.detections])
    lens = np.array([len(np.asarray(d.points).reshape(-1, 2)) for d in drive.detections])
    dist = cKDTree(xy).query(pts, distance_upper_bound=bounds.max_detection_range_m)[0]
    far = ~np.isfinite(dist)  # beyond the bound: inf
    if far.any():
        k = _first(far)
        det = int(np.searchsorted(np.cumsum(lens), k, side="right"))
        raise InvalidDriveError(
            drive.drive_id,
            "detection_out_of_range",
            f"detection {det} has a point over {bounds.max_detection_range_m:g} m from every pose",
        )


_BOUNDS = PhysicalBounds()


def prepare_drives(
    drives: Sequence[Drive], *, bounds: PhysicalBounds | None = _BOUNDS, workers: int = 1
) -> tuple[list[Drive], list[tuple[str, str]]]:
    """Validate drives; invalid, implausible and duplicate ones are rejected with a reason, never raised.

    Args:
        drives: the drives.
        bounds: the physical bounds every drive must keep (``hdmap_core.plausibility``); None:
            only the form is checked (``model.validate_drive``), e.g. for clips of drives that
            passed the bounds when they came in.
        workers: processes the drives' checks are shared out over (``parallel.map_balanced``,
            by their points); the verdicts are put back in drive order, so the result is the
            one-process result.

    Returns:
        (usable drives in input order, [(drive_id, reason), ...]).
    """
    drives = list(drives)
    if workers > 1 and len(drives) > 1:
        weight = [np.size(d.xy) + sum(np.size(det.points) for det in d.detections) for d in drives]
        verdicts = map_balanced(lambda i: _verdict(drives[i], bounds), weight, workers)
    else:
        verdicts = [_verdict(d, bounds) for d in drives]
    ok: list[Drive] = []
    rejected: list[tuple[str, str]] = []
    seen: set[str] = set()
    for d, bad in zip(drives, verdicts):
        if bad is not None:
            rejected.append(bad)
            continue
        if d.drive_id in seen:
            rejected.append((d.drive_id, "duplicate_drive_id"))
            continue
        seen.add(d.drive_id)
        ok.append(d)
    return ok, rejected


def _verdict(drive: Drive, bounds: PhysicalBounds | None) -> tuple[str, str] | None:
    """None when ``drive`` keeps the form and ``bounds``, else (drive_id, reason[: detail])."""
    try:
        validate_drive(drive)
        if bounds is not None:
            check_plausible(drive, bounds=bounds)
    except InvalidDriveError as err:
        return err.drive_id, f"{err.reason}" + (f": {err.detail}" if err.detail else "")
    return None
