"""Settings of the map metric (Sec. VII): ``EvalConfig`` and the feature types reported apart."""

from __future__ import annotations

import math
from dataclasses import dataclass

from hdmap_core.errors import ConfigError
from hdmap_core.model import FeatureType

__all__ = ["EVAL_TYPES", "EvalConfig"]

#: The feature types reported separately, in report order.
EVAL_TYPES = (FeatureType.SOLID, FeatureType.DASHED, FeatureType.ROAD_BORDER)


@dataclass(frozen=True)
class EvalConfig:
    """Settings of the metric. Defaults follow the paper where it gives a value (2 m steps).

    Attributes:
        step_m: distance between cut lines along each reference line (paper: 2 m).
        recall_radius_m: a point counts for recall / precision when its partner of the same type on
            the same cut is at most this far away.
        gate_m: a map point farther than this from every ground-truth point of its type on its cut
            is unmatched (no error is measured for it).
        border_margin_m: the cut reaches this far beyond the first ground-truth road border on each
            side, so that a map border displaced outwards is still seen.
        max_half_length_m: the longest a cut may reach to each side (used where no border is found).
        highway_only: reference lines only along lanes with ``highway`` True.
        max_feature_angle_deg: a polyline segment counts at a cut only when its direction is within
            this angle of the cut's driving direction (excludes the opposite carriageway, crossing
            roads, overpasses). Also used for drives crossing a cut (floor) and for the borders that
            limit the cut (there in either direction).
        dedup_heading_deg: candidate cuts closer than step_m / 2 along, and within the extent across,
            an earlier cut whose heading differs by less than this are the same cross section.
        type_tie_m: for type accuracy, the same-type ground-truth point may be this much farther
            than the nearest ground-truth point of any type (coincident lines, e.g. a border on
            a solid edge line).
        default_sigma_loc_m: localization sigma for the floor when none is given.
        topology_separation_m: splits/merges: each branch is sampled only on cuts where it is at
            least this far from the other branches of its side.
        topology_window_m: splits/merges: length of each branch's sample [m].
        topology_reach_m: splits/merges: a branch's sample must start within this distance (along
            the branch) of the point; map joints count within reach + window of it [m].
        topology_attach_m: splits/merges: a map feature starting (ending) within this distance of
            another map feature running the same way counts as connected to it without a link.
        road_follow_m: road splits/merges: length of the ground-truth lane paths followed from a
            lane branch point on each side [m].
        road_apart_m: road splits/merges: two successor (predecessor) paths that part by more than
            this are different roads; closer ones are lanes of one carriageway [m].
        road_cluster_m: road splits/merges: lane branch points of one kind closer than this are one
            road point (the lanes of one junction) [m].
        road_node_margin_m: road splits/merges: a map topology node's cross-section reaches this
            far beyond half its width to each side [m].
        road_path_m: road splits/merges: longest path along the map's topology successors from the
            single side to a branch [m].
        link_path_factor: topology link precision: a map topology edge A -> B is supported when a
            ground-truth lane path from A to B is at most this times |AB| ...
        link_path_slack_m: ... plus this long [m] (cross-sections as for road_node_margin_m).
        link_back_m: topology link precision: on one lane, B up to this far behind A counts [m].
        link_long_m: topology link precision: edges longer than this are the "long" ones (the
            stitcher's links; consecutive steps are 2 m apart) [m].
        density_drives: (lo, hi) drives per place of the paper's data set (Sec. VII: 5-25); the
            report gives the share of the reference cuts whose drive count lies in this range,
            so a fleet can be placed against the density the paper's figures hold for.
    """

    step_m: float = 2.0
    recall_radius_m: float = 1.0
    gate_m: float = 2.5
    border_margin_m: float = 1.0
    max_half_length_m: float = 25.0
    highway_only: bool = True
    max_feature_angle_deg: float = 60.0
    dedup_heading_deg: float = 30.0
    type_tie_m: float = 0.1
    default_sigma_loc_m: float = 1.0
    topology_separation_m: float = 2.0
    topology_window_m: float = 20.0
    topology_reach_m: float = 100.0
    topology_attach_m: float = 0.1
    road_follow_m: float = 600.0
    road_apart_m: float = 10.0
    road_cluster_m: float = 30.0
    road_node_margin_m: float = 1.0
    road_path_m: float = 1300.0
    link_path_factor: float = 2.0
    link_path_slack_m: float = 20.0
    link_back_m: float = 2.0
    link_long_m: float = 3.0
    density_drives: tuple[int, int] = (5, 25)

    def __post_init__(self) -> None:
        lo, hi = self.density_drives
        if not (0 <= lo <= hi):
            raise ConfigError(
                f"EvalConfig.density_drives must be (lo, hi) with 0 <= lo <= hi, got {self.density_drives!r}"
            )
        positive = (
            "step_m",
            "recall_radius_m",
            "gate_m",
            "max_half_length_m",
            "default_sigma_loc_m",
            "topology_separation_m",
            "topology_window_m",
            "topology_reach_m",
            "topology_attach_m",
            "road_follow_m",
            "road_apart_m",
            "road_cluster_m",
            "road_path_m",
            "link_path_factor",
            "link_long_m",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"EvalConfig.{name} must be a finite number > 0, got {value!r}")
        for name in ("border_margin_m", "type_tie_m", "road_node_margin_m", "link_path_slack_m", "link_back_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"EvalConfig.{name} must be a finite number >= 0, got {value!r}")
        for name in ("max_feature_angle_deg", "dedup_heading_deg"):
            value = getattr(self, name)
            if not (0 < value < 90):
                raise ConfigError(f"EvalConfig.{name} must be in (0, 90) degrees, got {value!r}")
        if self.recall_radius_m > self.gate_m:
            raise ConfigError(
                f"EvalConfig.recall_radius_m ({self.recall_radius_m}) must not exceed gate_m ({self.gate_m})"
            )
