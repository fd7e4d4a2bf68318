"""Settings of the fleet simulator: ``SimConfig`` (every parameter, docs/simulator.md) and the
default geo origin of a simulated bag."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from typing import Any

import numpy as np

from hdmap_core.errors import ConfigError
from hdmap_core.model import GeoOrigin

__all__ = ["DEFAULT_ORIGIN", "ROUTE_WEIGHTINGS", "SimConfig"]

ROUTE_WEIGHTINGS = ("coverage", "length", "uniform")

# The paper's fleet data is from a motorway near Stuttgart; the shared maps' geo references are
# placeholders, so every simulated bag gets this fixed origin unless the config says otherwise.
DEFAULT_ORIGIN = GeoOrigin(latitude_deg=48.7758, longitude_deg=9.1829, altitude_m=250.0)

_PROBABILITIES = (
    "direction_bias",
    "visibility_ego_marking",
    "visibility_next_marking",
    "visibility_far_marking",
    "visibility_border",
    "misclass_rate",
    "marking_to_border_rate",
)


@dataclass(frozen=True)
class SimConfig:
    """Every parameter of the fleet simulator (docs/simulator.md explains each one).

    Lengths in metres, speeds in m/s, times as named; probabilities in [0, 1].
    """

    # --- fleet and routes
    n_drives: int = 134  # number of drive snippets (the paper's data set has 134)
    snippet_length_min_m: float = 500.0  # snippet length ~ U(min, max), capped by the route length
    snippet_length_max_m: float = 2500.0
    direction_bias: float = 0.7  # share of drives in the primary direction (paper: biased fleet)
    # "coverage": each drive takes, of ``coverage_candidates`` snippets drawn as for "length", the one
    # over the least-driven place so far, so every ramp gets driven (the paper's fleet has 5-25
    # drives at every place); "length": a route drawn in proportion to its length; "uniform": every
    # route of the direction equally likely.
    route_weighting: str = "coverage"
    coverage_candidates: int = 8  # snippets drawn per drive in "coverage" mode
    coverage_cell_m: float = 50.0  # size of a "place" (grid cell per direction) in "coverage" mode
    speed_min_mps: float = 25.0  # per-drive constant speed ~ U(min, max) -> time stamps
    speed_max_mps: float = 35.0
    pose_spacing_m: float = 1.0  # distance between consecutive poses
    start_time_ns: int = 1_685_606_400_000_000_000  # first drive's start, 2023-06-01T08:00:00Z
    drive_gap_min_s: float = 10.0  # time between consecutive drive starts ~ U(min, max)
    drive_gap_max_s: float = 300.0
    n_vehicles: int = 25  # vehicle ids veh000.. drawn uniformly per drive
    # --- lane keeping
    wander_sigma_m: float = 0.15  # in-lane lateral wander, Gauss-Markov std
    wander_corr_length_m: float = 150.0  # ... and correlation length
    lane_change_rate_per_km: float = 0.5  # Poisson rate of lane-change manoeuvres
    lane_change_length_min_m: float = 100.0  # length of one lateral transition ~ U(min, max)
    lane_change_length_max_m: float = 200.0
    lane_change_stay_min_m: float = 200.0  # time spent in the neighbour lane before returning
    lane_change_stay_max_m: float = 1000.0
    # --- localization error (per drive, vehicle frame)
    bias_lateral_sigma_m: float = 1.0  # constant lateral bias ~ N(0, sigma^2)
    bias_longitudinal_sigma_m: float = 1.0  # constant longitudinal bias ~ N(0, sigma^2)
    drift_sigma_m: float = 0.3  # Gauss-Markov drift (lateral and longitudinal), stationary std
    drift_corr_length_m: float = 1000.0  # ... and its correlation length along the drive
    # --- sensor: where features are seen
    range_ahead_m: float = 40.0  # detections reach this far beyond the last pose (0-40 m ahead)
    same_direction_cos_min: float = 0.7  # |cos| between feature and heading to count as (anti)parallel
    ego_marking_max_lateral_m: float = 3.0  # lateral band of the ego-lane markings
    next_marking_max_lateral_m: float = 6.5  # band of the next markings
    far_marking_max_lateral_m: float = 10.0  # band of farther markings; beyond: never seen
    border_max_lateral_m: float = 12.0  # road borders (incl. the opposite barrier) within this
    visibility_ego_marking: float = 0.95  # share of the ego-lane markings detected
    visibility_next_marking: float = 0.70
    visibility_far_marking: float = 0.25
    visibility_border: float = 0.60
    visibility_edge_m: float = 1.0  # width of the linear ramp between two bands' visibilities
    visibility_block_min_m: float = 10.0  # visibility is decided per block ~ U(min, max) along a
    visibility_block_max_m: float = 300.0  # feature: dropouts are on/off gaps of these lengths
    opposite_barrier: bool = True  # detect the opposite carriageway's median barrier
    # --- sensor: measurement noise (perpendicular to the feature)
    noise_sigma_m: float = 0.08  # std = noise_sigma_m + noise_growth_per_m * distance,
    noise_growth_per_m: float = 0.002  # distance = hypot(lateral, noise_ahead_m)
    noise_ahead_m: float = 15.0  # typical distance ahead at which a point is measured
    noise_corr_length_m: float = 5.0  # Gauss-Markov correlation along a polyline (0: white)
    # --- sensor: classification errors and false positives
    misclass_rate: float = 0.075  # share of marking stretches with dashed <-> solid swapped
    marking_to_border_rate: float = 0.01  # share of marking stretches reported as road border
    misclass_block_min_m: float = 20.0  # stretch length ~ U(min, max) for the two rates above
    misclass_block_max_m: float = 200.0
    false_positive_rate_per_km: float = 2.0  # short spurious polylines, Poisson per driven km
    false_positive_length_min_m: float = 1.0
    false_positive_length_max_m: float = 10.0
    false_positive_max_lateral_m: float = 8.0  # placed at U(-max, max) beside the trajectory
    # --- output
    detection_spacing_m: float = 1.5  # point spacing of the detection polylines
    min_detection_length_m: float = 0.5  # shorter visible pieces are not reported
    origin_latitude_deg: float = DEFAULT_ORIGIN.latitude_deg  # /fleet/origin of the bag
    origin_longitude_deg: float = DEFAULT_ORIGIN.longitude_deg
    origin_altitude_m: float = DEFAULT_ORIGIN.altitude_m

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise ``ConfigError`` naming the first parameter out of its range."""
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) and not np.isfinite(v):
                raise ConfigError(f"SimConfig.{f.name}={v!r} must be finite")
            # RULE: lengths, speeds, durations and rates are never negative.
            if f.name.endswith(("_m", "_mps", "_s", "_per_km", "_ns")) and f.name != "origin_altitude_m" and v < 0:
                raise ConfigError(f"SimConfig.{f.name}={v!r} must be >= 0")
            if f.name in _PROBABILITIES and not 0.0 <= v <= 1.0:
                raise ConfigError(f"SimConfig.{f.name}={v!r} must be in [0, 1]")
        if abs(self.origin_latitude_deg) > 90.0 or abs(self.origin_longitude_deg) > 180.0:
            raise ConfigError(
                f"SimConfig: origin {self.origin_latitude_deg}, {self.origin_longitude_deg} is not a WGS84 position"
            )
        pairs = [
            ("snippet_length", "_m"),
            ("speed", "_mps"),
            ("drive_gap", "_s"),
            ("lane_change_length", "_m"),
            ("lane_change_stay", "_m"),
            ("visibility_block", "_m"),
            ("misclass_block", "_m"),
            ("false_positive_length", "_m"),
        ]
        for stem, unit in pairs:
            lo, hi = getattr(self, f"{stem}_min{unit}"), getattr(self, f"{stem}_max{unit}")
            if lo > hi:
                raise ConfigError(f"SimConfig.{stem}_min{unit}={lo} exceeds {stem}_max{unit}={hi}")
        positive = (
            "pose_spacing_m",
            "detection_spacing_m",
            "speed_min_mps",
            "visibility_block_min_m",
            "misclass_block_min_m",
            "lane_change_length_min_m",
            "snippet_length_max_m",
        )
        for name in positive:
            if getattr(self, name) <= 0:
                raise ConfigError(f"SimConfig.{name}={getattr(self, name)!r} must be > 0")
        if self.n_drives < 0 or self.n_vehicles < 1:
            raise ConfigError(f"SimConfig: n_drives={self.n_drives} must be >= 0 and n_vehicles={self.n_vehicles} >= 1")
        if self.route_weighting not in ROUTE_WEIGHTINGS:
            raise ConfigError(
                f"SimConfig.route_weighting={self.route_weighting!r}: choose one of {', '.join(ROUTE_WEIGHTINGS)}"
            )
        if self.coverage_candidates < 1 or self.coverage_cell_m <= 0:
            raise ConfigError(
                f"SimConfig: coverage_candidates={self.coverage_candidates} must be >= 1 and "
                f"coverage_cell_m={self.coverage_cell_m} > 0"
            )
        if not 0.0 <= self.same_direction_cos_min < 1.0:
            raise ConfigError(f"SimConfig.same_direction_cos_min={self.same_direction_cos_min} must be in [0, 1)")
        if self.misclass_rate + self.marking_to_border_rate > 1.0:
            raise ConfigError("SimConfig: misclass_rate + marking_to_border_rate must not exceed 1")
        if not (self.ego_marking_max_lateral_m <= self.next_marking_max_lateral_m <= self.far_marking_max_lateral_m):
            raise ConfigError("SimConfig: marking bands must grow: ego <= next <= far max lateral")

    @property
    def origin(self) -> GeoOrigin:
        return GeoOrigin(self.origin_latitude_deg, self.origin_longitude_deg, self.origin_altitude_m)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict, *, base: SimConfig | None = None) -> SimConfig:
        """``base`` (default: defaults) with ``values`` overridden; strings are parsed.

        Raises:
            ConfigError: an unknown key or a value that does not parse / is out of range.
        """
        base = base if base is not None else cls()
        kinds = {f.name: type(getattr(base, f.name)) for f in fields(cls)}
        unknown = sorted(set(values) - set(kinds))
        if unknown:
            raise ConfigError(f"unknown SimConfig parameter(s) {unknown}; known: {', '.join(kinds)}")
        parsed: dict[str, Any] = {k: _coerce(k, v, kinds[k]) for k, v in values.items()}
        return replace(base, **parsed)

    @classmethod
    def noise_free(cls, **overrides: object) -> SimConfig:
        """Perfect sensing: no localization error, noise, wander, misclassification or false
        positives; every feature within the sensor bands is seen (visibility 1)."""
        clean: dict[str, object] = dict(
            wander_sigma_m=0.0,
            lane_change_rate_per_km=0.0,
            bias_lateral_sigma_m=0.0,
            bias_longitudinal_sigma_m=0.0,
            drift_sigma_m=0.0,
            visibility_ego_marking=1.0,
            visibility_next_marking=1.0,
            visibility_far_marking=1.0,
            visibility_border=1.0,
            noise_sigma_m=0.0,
            noise_growth_per_m=0.0,
            misclass_rate=0.0,
            marking_to_border_rate=0.0,
            false_positive_rate_per_km=0.0,
        )
        clean.update(overrides)
        return cls.from_dict(clean)


def _coerce(name: str, value: Any, kind: type) -> object:
    try:
        if kind is bool:
            if isinstance(value, str):
                if value.lower() in ("1", "true", "yes", "on"):
                    return True
                if value.lower() in ("0", "false", "no", "off"):
                    return False
                raise ValueError(value)
            return bool(value)
        if kind is int:
            f = float(value)
            if f != int(f):
                raise ValueError(value)
            return int(f)
        return kind(value)
    except (TypeError, ValueError):
        raise ConfigError(f"SimConfig.{name}: cannot use {value!r} as {kind.__name__}") from None
