"""What ``evaluate_map`` measured: ``EvalReport`` with its per-type figures (``TypeStats``) and the
per-cut profile (``CutProfile``), plain data with a JSON form. ``summary.format_summary`` turns a
report into text, ``plot.plot_evaluation`` into a figure; docs/evaluation.md defines every figure.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hdmap_core.evaluation.config import EvalConfig
from hdmap_core.evaluation.links import TopologyLink
from hdmap_core.evaluation.roads import RoadBranchPoint
from hdmap_core.evaluation.topology import BranchPoint

__all__ = ["CutProfile", "EvalReport", "TypeStats", "jsonable"]


@dataclass(frozen=True)
class TypeStats:
    """Figures of one feature type (or of all types together). Errors in metres; NaN when empty.

    Attributes:
        n_gt_points: ground-truth points on the cuts.
        n_map_points: map points on the cuts.
        n_matched: map points matched (same type, within the gate) -> errors measured.
        mean_m, median_m, p95_m: of the absolute lateral error of matched map points.
        corrected_mean_m, corrected_median_m, corrected_p95_m: the same after removing each cut's
            offset (mean signed error of its matched points, all types).
        recall: share of ground-truth points with a same-type map point within recall_radius_m.
        precision: share of map points with a same-type ground-truth point within recall_radius_m.
        coverage: share of the cuts holding a ground-truth point of this type where at least one
            map point of this type is matched.
        n_cuts: cuts holding a ground-truth point of this type.
    """

    n_gt_points: int
    n_map_points: int
    n_matched: int
    mean_m: float
    median_m: float
    p95_m: float
    corrected_mean_m: float
    corrected_median_m: float
    corrected_p95_m: float
    recall: float
    precision: float
    coverage: float
    n_cuts: int


@dataclass(frozen=True)
class CutProfile:
    """Per-cut results along the reference, K cuts in evaluation order (for plots and analysis).

    Attributes:
        station_m: (K,) distance along the de-duplicated reference [m].
        center: (K, 2) cut reference point [m]; heading_rad: (K,) ENU yaw of the reference lane.
        lo_m, hi_m: (K,) cut extent to the right (<= 0) and left (>= 0) [m].
        n_gt, n_map, n_matched: (K,) ground-truth points, map points, matched map points.
        error_m: (K,) mean absolute total error of the cut's matched points (NaN if none).
        corrected_m: (K,) mean absolute offset-corrected error (NaN if none).
        offset_m: (K,) the cut's offset, mean signed error, + = map left of truth (NaN if none).
        drive_count: (K,) drives covering the cut (NaN if unknown).
        floor_m: (K,) sigma_loc / sqrt(drive_count) (NaN if unknown or 0 drives).
    """

    station_m: np.ndarray
    center: np.ndarray
    heading_rad: np.ndarray
    lo_m: np.ndarray
    hi_m: np.ndarray
    n_gt: np.ndarray
    n_map: np.ndarray
    n_matched: np.ndarray
    error_m: np.ndarray
    corrected_m: np.ndarray
    offset_m: np.ndarray
    drive_count: np.ndarray
    floor_m: np.ndarray

    @property
    def reference(self) -> np.ndarray:
        """(K,) bool: the cut holds at least one ground-truth point (part of the reference)."""
        return self.n_gt > 0

    @property
    def evaluable(self) -> np.ndarray:
        """(K,) bool: at least one map point is matched on the cut."""
        return self.n_matched > 0

    def to_dict(self) -> dict:
        return {k: jsonable(getattr(self, k)) for k in self.__dataclass_fields__}


@dataclass(frozen=True)
class EvalReport:
    """Everything ``evaluate_map`` measured. See docs/evaluation.md for the definitions.

    Attributes:
        gt_name: name of the ground truth.
        config: the settings used.
        overall: figures over all types; per_type: the same per type label ("solid", ...).
        type_accuracy: share of map points (with a ground-truth point of any type within the gate)
            whose nearest ground-truth point has their type; n_typed: that denominator.
        type_accuracy_corrected: the same with each map point moved by its cut's offset (as the
            offset-corrected error): where two lines of different type lie close (an edge line
            0.5-1 m inside its border), the fleet's common error, which no map without an
            absolute reference can remove, moves a right-typed line nearer the other one.
        fragmentation_mean, fragmentation_max: distinct map features matched along each
            ground-truth feature, over the n_gt_features ground-truth features with a match.
        mean_abs_offset_m: mean over evaluable cuts of |offset| (the paper's offset error).
        sigma_loc_m: localization sigma used for the floor.
        floor_source: "drives" (trajectories crossing each cut), "map" (the matched map points'
            drive_count) or "none" (no drive information).
        floor_mean_m: mean over evaluable cuts with a known drive count of sigma_loc / sqrt(n).
        drive_count_mean: mean drive count over the same cuts.
        drive_count_median: median drive count over the reference cuts (cuts holding a
            ground-truth point, mapped or not), from the drives' trajectories; NaN without drives.
        density_share: share of those reference cuts whose drive count lies in
            ``config.density_drives`` (the paper's 5-25 drives per place); NaN without drives.
        sparse_share: share of them crossed by fewer than ``config.density_drives[0]`` drives.
        driven_share: share of the reference cuts crossed by >= 1 drive in their direction (from
            the drives' trajectories); NaN without drives. A lane no drive of the fleet drove
            cannot be in a map made from it: the realized ceiling of ``coverage``.
        coverage_driven: coverage over the driven reference cuts only (evaluable and driven /
            driven); NaN without drives.
        fleet_floor_mean_m: mean over the same cuts of |mean lateral error of the drives crossing
            the cut| when their errors are known (simulated fleets): the realized floor. Any map
            made from these drives alone (no absolute reference) inherits their common error, so a
            fleet whose mean error is unluckily large bounds the mean from below, whatever sigma/sqrt(n)
            says. NaN when the drive errors are not given.
        observed_share: with seen counts (the simulator's per-point count of drives that detected
            each ground-truth feature point): share of the ground-truth points on the cuts whose
            ground-truth segment has an end seen by >= 1 drive ("observed"); over the points whose
            feature has seen counts. NaN without seen counts.
        recall_observed: recall (RULE 3) over the observed ground-truth points only; 1 when the
            map has everything the fleet saw. NaN without seen counts.
        n_observed: the observed ground-truth points (the denominator of recall_observed).
        recall_by_seen: with seen counts, per number of drives that saw a ground-truth point
            (the larger count of its segment's two ends; buckets "0", "1", "2", ">=3"): (bucket,
            share of the points with seen counts, recall over them); recall NaN for an empty
            bucket. Empty without seen counts. Tells a line no drive saw from one the map lost.
        n_cuts, n_reference_cuts, n_evaluable_cuts: all cuts, cuts holding a ground-truth point,
            cuts with a matched map point.
        reference_length_m, evaluable_length_m: the latter two times step_m.
        cuts: the per-cut profile.
        skipped: messages about input parts that were left out (malformed map features, drives).
        gt_splits, gt_merges: evaluable ground-truth splits / merges in the evaluated area
            (branch points of the ground-truth features, see docs/evaluation.md).
        found_splits, found_merges: those connected in the map.
        branch_points: every ground-truth branch point in the evaluated area, evaluable or not,
            with its verdict.
        gt_road_splits, gt_road_merges: evaluable road splits / merges of the ground-truth lane graph
            in the evaluated area (lane branch points whose branches part into different roads).
        found_road_splits, found_road_merges: those the map's topology graph connects.
        road_branch_points: every ground-truth road split / merge in the evaluated area, evaluable
            or not, with its verdict.
        topology_link_precision: map topology edges (A -> successor B) that the ground-truth lane
            graph supports (both nodes on ground-truth lanes running their way, a lane path from A
            to B within link_path_factor * |AB| + link_path_slack_m) / evaluable edges (both nodes
            on ground-truth lanes in the evaluated area). NaN when none is evaluable.
        n_topology_links, n_topology_links_evaluable, n_topology_links_supported: the edge counts.
        long_link_precision, n_long_links, n_long_links_evaluable, n_long_links_supported: the same
            for edges longer than link_long_m (the stitcher's links).
        false_topology_links: every unsupported evaluable edge, longest first.
        unevaluable_long_links: the long edges with a node on no ground-truth lane, longest first.
        gt_lane_splits, gt_lane_merges: for context, ground-truth lanes (highway lanes unless
            highway_only is False) with >= 2 successors / >= 2 predecessors. Where the ground-truth
            markings stop at junctions these have no branch point of the features.
        runtime_s: wall time of the evaluation.
        std_within_share: share of the matched map points (RULE 1) with a lateral_std > 0 whose
            |total error| is at most their lateral_std (interpolated like drive_count: the value
            of the nearer segment end). The message calls lateral_std a 1-sigma lateral
            uncertainty: calibrated, this is 0.683. NaN when no matched point carries one.
        std_z_rms: over the same points, the rms of total error / lateral_std (1 when calibrated;
            above 1 the map claims more accuracy than it has).
        n_std_points: those points.
    """

    gt_name: str
    config: EvalConfig
    overall: TypeStats
    per_type: dict[str, TypeStats]
    type_accuracy: float
    n_typed: int
    fragmentation_mean: float
    fragmentation_max: int
    n_gt_features: int
    mean_abs_offset_m: float
    sigma_loc_m: float
    floor_source: str
    floor_mean_m: float
    drive_count_mean: float
    n_cuts: int
    n_reference_cuts: int
    n_evaluable_cuts: int
    reference_length_m: float
    evaluable_length_m: float
    gt_splits: int
    gt_merges: int
    found_splits: int
    found_merges: int
    branch_points: tuple[BranchPoint, ...]
    gt_road_splits: int
    gt_road_merges: int
    found_road_splits: int
    found_road_merges: int
    road_branch_points: tuple[RoadBranchPoint, ...]
    gt_lane_splits: int
    gt_lane_merges: int
    cuts: CutProfile = field(repr=False)
    skipped: tuple[str, ...] = ()
    runtime_s: float = 0.0
    fleet_floor_mean_m: float = math.nan
    observed_share: float = math.nan
    recall_observed: float = math.nan
    n_observed: int = 0
    recall_by_seen: tuple[tuple[str, float, float], ...] = ()
    drive_count_median: float = math.nan
    density_share: float = math.nan
    sparse_share: float = math.nan
    driven_share: float = math.nan
    coverage_driven: float = math.nan
    topology_link_precision: float = math.nan
    n_topology_links: int = 0
    n_topology_links_evaluable: int = 0
    n_topology_links_supported: int = 0
    long_link_precision: float = math.nan
    n_long_links: int = 0
    n_long_links_evaluable: int = 0
    n_long_links_supported: int = 0
    false_topology_links: tuple[TopologyLink, ...] = ()
    unevaluable_long_links: tuple[TopologyLink, ...] = ()
    type_accuracy_corrected: float = math.nan
    std_within_share: float = math.nan
    std_z_rms: float = math.nan
    n_std_points: int = 0

    @property
    def coverage(self) -> float:
        """Share of the reference that could be evaluated (== overall.coverage)."""
        return self.overall.coverage

    @property
    def missing_branch_points(self) -> tuple[BranchPoint, ...]:
        """Evaluable ground-truth splits and merges that the map does not have connected."""
        return tuple(b for b in self.branch_points if b.evaluable and not b.found)

    @property
    def missing_road_branch_points(self) -> tuple[RoadBranchPoint, ...]:
        """Evaluable ground-truth road splits and merges that the map's topology does not connect."""
        return tuple(b for b in self.road_branch_points if b.evaluable and not b.found)

    def to_dict(self, *, include_cuts: bool = False) -> dict:
        """A JSON-able dict (NaN -> None); ``include_cuts`` adds the per-cut profile arrays."""
        out = {
            "gt_name": self.gt_name,
            "config": dict(self.config.__dict__),
            "overall": jsonable(self.overall.__dict__),
            "per_type": {k: jsonable(v.__dict__) for k, v in self.per_type.items()},
        }
        for name in self.__dataclass_fields__:
            if name in (
                "gt_name",
                "config",
                "overall",
                "per_type",
                "cuts",
                "branch_points",
                "road_branch_points",
                "false_topology_links",
                "unevaluable_long_links",
            ):
                continue
            out[name] = jsonable(getattr(self, name))
        out["missing_branch_points"] = [b.to_dict() for b in self.missing_branch_points]
        out["branch_points"] = [b.to_dict() for b in self.branch_points]
        out["missing_road_branch_points"] = [b.to_dict() for b in self.missing_road_branch_points]
        out["road_branch_points"] = [b.to_dict() for b in self.road_branch_points]
        out["false_topology_links"] = [jsonable(t.to_dict()) for t in self.false_topology_links]
        out["unevaluable_long_links"] = [jsonable(t.to_dict()) for t in self.unevaluable_long_links]
        out["coverage"] = jsonable(self.coverage)
        if include_cuts:
            out["cuts"] = self.cuts.to_dict()
        return out


def jsonable(value: object) -> object:
    """``value`` with numpy arrays and scalars as lists and numbers, NaN and inf as None (for JSON)."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        if value.dtype.kind == "f":
            return [jsonable(v) for v in value.tolist()] if value.ndim == 1 else jsonable(value.tolist())
        return value.tolist()
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return v if math.isfinite(v) else None
    return value
