"""The paper's map metric (Immel et al. 2023, Sec. VII): lateral error of a map against ground truth.

Along the ground truth's route centerlines a lateral cut line is placed every 2 m and limited to
the carriageway; map and ground-truth polylines are intersected with it; each map point is matched
to the nearest ground-truth point of the same type on that cut; the signed distance along the cut
is the lateral error. From these matches come the total and offset-corrected error, coverage,
recall, precision, type accuracy, fragmentation and the localization floor sigma/sqrt(n); with
the simulator's truth also the realized floor and recall over the ground truth the fleet observed.
``docs/evaluation.md`` defines every figure exactly.

Typical use::

    report = evaluate_map(hdmap, gt, drives=fleet.drives, sigma_loc_m=1.0)
    print(format_summary(report))                  # evaluation/summary.py
    json.dump(report.to_dict(), fp)                # EvalReport: evaluation/report.py
    plot_evaluation(report, hdmap, gt, "eval.png")  # evaluation/plot.py
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from hdmap_core.errors import ConfigError, HdmapError, NoUsableDataError
from hdmap_core.evaluation.config import EVAL_TYPES, EvalConfig
from hdmap_core.evaluation.cuts import (
    CutPoints,
    Cuts,
    configured_cuts,
    nearest_on_same_cut,
    nearest_same_type,
    points_on_cuts,
)
from hdmap_core.evaluation.links import LinkCheckConfig, LinkPrecision, check_topology_links
from hdmap_core.evaluation.report import CutProfile, EvalReport, TypeStats
from hdmap_core.evaluation.roads import (
    RoadBranchPoint,
    RoadCheckConfig,
    TopologyArrays,
    check_road_points,
    road_branch_points,
    topology_from_lanes,
)
from hdmap_core.evaluation.topology import (
    BranchPoint,
    check_branch_points,
    ground_truth_branch_points,
    inside_cuts,
    map_feature_graph,
    on_cuts,
)
from hdmap_core.geometry import turn_left, unit_tangents
from hdmap_core.groundtruth import GroundTruth
from hdmap_core.model import Drive, HDMap, MapFeature

__all__ = ["evaluate_map", "hdmap_from_ground_truth", "road_check_config"]


def _stats(values: np.ndarray) -> tuple[float, float, float]:
    if len(values) == 0:
        return math.nan, math.nan, math.nan
    return float(np.mean(values)), float(np.median(values)), float(np.percentile(values, 95))


def _share(num: int, den: int) -> float:
    return num / den if den else math.nan


# --------------------------------------------------------------------------------------------
# Input checks


def _valid_map_features(hdmap: HDMap, skipped: list[str]) -> list[MapFeature]:
    """Map features usable for evaluation; malformed ones are named in ``skipped``."""
    out = []
    for f in hdmap.features:
        pts = np.asarray(f.points, dtype=float) if f.points is not None else np.zeros((0, 2))
        if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 2:
            skipped.append(f"map feature {f.id}: points of shape {pts.shape}, need (N >= 2, 2)")
            continue
        if not np.all(np.isfinite(pts)):
            skipped.append(f"map feature {f.id}: non-finite coordinates")
            continue
        out.append(f)
    return out


def _finite_points(pts: object) -> np.ndarray | None:
    """(N, 2) float points with non-finite rows removed; None if not (N, 2) or fewer than 2 remain."""
    arr = np.asarray(pts, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 2:
        return None
    arr = arr[np.all(np.isfinite(arr), axis=1)]
    return arr if len(arr) >= 2 else None


def _usable_points(pts: np.ndarray, what: str, skipped: list[str]) -> np.ndarray | None:
    """``pts`` with non-finite rows dropped (``pts`` itself when all are finite), None when fewer
    than 2 remain; what was dropped is named in ``skipped``."""
    clean = _finite_points(pts)
    if clean is None:
        skipped.append(f"ground-truth {what}: fewer than 2 finite points, left out")
        return None
    if len(clean) == len(pts):
        return pts
    skipped.append(f"ground-truth {what}: {len(pts) - len(clean)} non-finite point(s) dropped")
    return clean


def _clean_ground_truth(gt: GroundTruth, skipped: list[str]) -> GroundTruth:
    """``gt`` with non-finite vertices dropped, unusable features/lanes and unknown route lanes left
    out (each named in ``skipped``); ``gt`` itself when nothing is wrong."""
    n_skipped = len(skipped)
    feats = []
    for f in gt.features:
        pts = _usable_points(f.points, f"feature {f.id}", skipped)
        if pts is not None:
            feats.append(f if pts is f.points else replace(f, points=pts))
    lanes = {}
    for lid, lane in gt.lanes.items():
        pts = _usable_points(lane.centerline, f"lane {lid}", skipped)
        if pts is not None:
            lanes[lid] = lane if pts is lane.centerline else replace(lane, centerline=pts)
    routes = []
    for r in gt.routes:
        known = tuple(lid for lid in r.lanes if lid in lanes)
        if len(known) != len(r.lanes):
            skipped.append(f"ground-truth route {r.id}: {len(r.lanes) - len(known)} unknown/unusable lane(s) left out")
            r = replace(r, lanes=known, lane_changes=())
        routes.append(r)
    if len(skipped) == n_skipped:
        return gt
    return replace(gt, features=tuple(feats), lanes=lanes, routes=tuple(routes))


def _per_point(f: MapFeature, name: str, skipped: list[str], *, missing: float) -> np.ndarray:
    """(N,) the feature's per-point attribute ``name`` (drive_count, lateral_std) as floats;
    ``missing`` everywhere when it has not one value per point (named in ``skipped``)."""
    raw = getattr(f, name)
    values = np.asarray(raw if raw is not None else (), dtype=float).reshape(-1)
    if len(values) != len(f.points):
        if len(values):
            skipped.append(f"map feature {f.id}: {name} has {len(values)} values for {len(f.points)} points, ignored")
        return np.full(len(f.points), missing)
    return values


def _valid_trajectories(drives: Sequence[Drive], skipped: list[str]) -> tuple[list[np.ndarray], list[str | None]]:
    """The usable trajectories and their drive ids (unusable ones are reported in ``skipped``)."""
    out, ids = [], []
    for i, d in enumerate(drives):
        xy = np.asarray(getattr(d, "xy", None), dtype=float)
        name = getattr(d, "drive_id", f"#{i}")
        if xy.ndim != 2 or xy.shape[1] != 2 or len(xy) < 2 or not np.all(np.isfinite(xy)):
            skipped.append(f"drive {name!r}: trajectory unusable (shape {xy.shape} or non-finite), not counted")
            continue
        out.append(xy)
        ids.append(getattr(d, "drive_id", None))
    return out, ids


@dataclass(frozen=True)
class _Crossings:
    """Which drive crosses which cut in its direction, each (cut, drive) pair once."""

    cut: np.ndarray
    owner: np.ndarray  # index into drive_ids
    drive_ids: list[str | None]


def _crossings(cuts: Cuts, drives: Sequence[Drive], cos_min: float, skipped: list[str]) -> _Crossings:
    trajs, ids = _valid_trajectories(drives, skipped)
    tp = points_on_cuts(cuts, trajs, cos_min=cos_min)
    pairs = np.unique(tp.cut * (len(trajs) + 1) + tp.owner)
    return _Crossings(pairs // (len(trajs) + 1), pairs % (len(trajs) + 1), ids)


# --------------------------------------------------------------------------------------------
# The metric


def evaluate_map(
    hdmap: HDMap,
    gt: GroundTruth,
    *,
    config: EvalConfig = EvalConfig(),
    drives: Sequence[Drive] | None = None,
    sigma_loc_m: float | None = None,
    drive_errors: Mapping[str, float] | None = None,
    seen_counts: Mapping[int, Sequence[int] | np.ndarray] | None = None,
) -> EvalReport:
    """Evaluate ``hdmap`` against ``gt`` with the paper's lateral metric (Sec. VII).

    Args:
        hdmap: the map to evaluate (features in the ground truth's frame).
        gt: the ground truth; its route centerlines are the reference lines.
        config: metric settings.
        drives: the fleet drives the map was built from; their trajectories give the drive count
            per cut for the floor. Without them the matched map points' ``drive_count`` is used.
        sigma_loc_m: localization sigma for the floor [m] (default ``config.default_sigma_loc_m``).
        drive_errors: per drive id, its mean lateral localization error [m, left of its heading]
            (the simulator's truth); with ``drives`` it gives the realized floor
            ``fleet_floor_mean_m``.
        seen_counts: per ground-truth feature id, (N_f,) for each of its points the number of
            drives that detected it (the simulator's ``Fleet.seen_count``); gives
            ``observed_share`` and ``recall_observed``. A feature missing here or with another
            number of points is left out of both (named in ``skipped``).

    Returns:
        The report. An empty map gives coverage 0 and NaN errors.

    Raises:
        HdmapError: ``hdmap`` / ``gt`` are not an HDMap / GroundTruth, or sigma_loc_m <= 0.
        NoUsableDataError: the ground truth yields no cut (no highway lane on any route; use
            ``highway_only=False``).
    """
    t0 = time.perf_counter()
    if not isinstance(hdmap, HDMap):
        raise HdmapError(f"evaluate_map: hdmap must be an HDMap, got {type(hdmap).__name__}")
    if not isinstance(gt, GroundTruth):
        raise HdmapError(f"evaluate_map: gt must be a GroundTruth, got {type(gt).__name__}")
    sigma = config.default_sigma_loc_m if sigma_loc_m is None else float(sigma_loc_m)
    if not (math.isfinite(sigma) and sigma > 0):
        raise ConfigError(f"evaluate_map: sigma_loc_m must be a finite number > 0, got {sigma_loc_m!r}")
    cos_feat = math.cos(math.radians(config.max_feature_angle_deg))
    skipped: list[str] = []
    gt = _clean_ground_truth(gt, skipped)
    cuts = configured_cuts(gt, config, cos_feature=cos_feat)
    if len(cuts) == 0:
        which = "highway lane" if config.highway_only else "lane"
        raise NoUsableDataError(
            f"ground truth {gt.name!r}: no {which} centerline of at least {config.step_m / 2} m on any route "
            "to evaluate along" + (" (try highway_only=False / --all-lanes)" if config.highway_only else "")
        )
    width = 4.0 * (config.max_half_length_m + config.border_margin_m) + 10.0

    # Ground-truth and map points on the cuts.
    gt_feats = list(gt.features)
    gp = points_on_cuts(cuts, [f.points for f in gt_feats], cos_min=cos_feat)
    g_type = np.array([int(f.type) for f in gt_feats], dtype=np.int64)[gp.owner] if gt_feats else gp.owner
    map_feats = _valid_map_features(hdmap, skipped)
    mp = points_on_cuts(cuts, [np.asarray(f.points, dtype=float) for f in map_feats], cos_min=cos_feat)
    m_type = np.array([int(f.type) for f in map_feats], dtype=np.int64)[mp.owner] if map_feats else mp.owner
    m_dc = _at_map_points([_per_point(f, "drive_count", skipped, missing=0.0) for f in map_feats], mp)
    m_dc = np.where(np.isfinite(m_dc), m_dc, 0.0)  # a non-finite count counts as none
    m_std = _at_map_points([_per_point(f, "lateral_std", skipped, missing=np.nan) for f in map_feats], mp)

    # RULE 1: a map point is matched to the nearest ground-truth point of its type on its cut,
    # within the gate; the signed difference along the cut is its lateral error.
    gi, gd = nearest_same_type(mp.cut, mp.s, m_type, gp.cut, gp.s, g_type, width=width)
    matched = gd <= config.gate_m
    err = np.where(matched, mp.s - gp.s[np.clip(gi, 0, None)] if len(gp.s) else 0.0, np.nan)

    # RULE 2: the cut's offset is the mean signed error of its matched points (least squares).
    k = len(cuts)
    n_match = np.bincount(mp.cut[matched], minlength=k)
    offset = np.full(k, np.nan)
    has = n_match > 0
    offset[has] = np.bincount(mp.cut[matched], weights=err[matched], minlength=k)[has] / n_match[has]
    corrected = np.where(matched, err - offset[mp.cut] if len(mp.cut) else 0.0, np.nan)

    # RULE 3: recall / precision within the recall radius, same type, same cut.
    _, g_to_m = nearest_same_type(gp.cut, gp.s, g_type, mp.cut, mp.s, m_type, width=width)
    gt_hit = g_to_m <= config.recall_radius_m
    map_hit = gd <= config.recall_radius_m
    observed = _observed_gt_points(gt_feats, gp, seen_counts, skipped) if seen_counts is not None else None

    # RULE 4: type accuracy over map points with any ground-truth point within the gate.
    _, any_d = nearest_on_same_cut(mp.cut, mp.s, gp.cut, gp.s, width=width)
    typed, type_ok = _typed_right(gd, any_d, config)
    # ... and on the positions less their cut's offset (RULE 2; a cut without one: as they are)
    s_cor = mp.s - np.nan_to_num(offset[mp.cut]) if len(mp.cut) else mp.s
    _, gd_cor = nearest_same_type(mp.cut, s_cor, m_type, gp.cut, gp.s, g_type, width=width)
    _, any_cor = nearest_on_same_cut(mp.cut, s_cor, gp.cut, gp.s, width=width)
    typed_cor, type_ok_cor = _typed_right(gd_cor, any_cor, config)

    per_cut_err = _per_cut_mean(mp.cut[matched], np.abs(err[matched]), k)
    per_cut_cor = _per_cut_mean(mp.cut[matched], np.abs(corrected[matched]), k)
    n_gt_cut = np.bincount(gp.cut, minlength=k)
    n_map_cut = np.bincount(mp.cut, minlength=k)

    crossings = _crossings(cuts, drives, cos_feat, skipped) if drives is not None else None
    drive_count, floor_source = _cut_drive_counts(k, crossings, mp, matched, m_dc)
    floor = np.where(drive_count >= 1, sigma / np.sqrt(np.maximum(drive_count, 1.0)), np.nan)
    fleet_err = _cut_fleet_error(k, crossings, drive_errors) if crossings is not None and drive_errors else None

    stats = functools.partial(
        _type_stats, gp=gp, mp=mp, err=err, corrected=corrected, matched=matched, gt_hit=gt_hit, map_hit=map_hit, k=k
    )
    per_type = {t.label: stats(g_mask=g_type == t, m_mask=m_type == t) for t in EVAL_TYPES}
    overall = stats(g_mask=np.ones(len(gp.cut), dtype=bool), m_mask=np.ones(len(mp.cut), dtype=bool))

    frag_mean, frag_max, n_frag = _fragmentation(gp, gi, matched, map_feats, mp)
    branch_points = _branch_points(gt_feats, cuts, gp, gi, gd, mp, map_feats, config, cos_feat)
    evaluable_bp = [b for b in branch_points if b.evaluable]
    topo = TopologyArrays.build(hdmap.topology, config.road_node_margin_m)
    road_points = _road_branch_points(gt, cuts, topo, config, cos_feat)
    links = _topology_links(gt, cuts, topo, config, cos_feat)
    evaluable_rp = [b for b in road_points if b.evaluable]
    evaluable = (n_match > 0) & (n_gt_cut > 0)
    floor_ok = evaluable & np.isfinite(floor)
    profile = CutProfile(
        station_m=cuts.station_m,
        center=cuts.center,
        heading_rad=np.arctan2(cuts.tangent[:, 1], cuts.tangent[:, 0]),
        lo_m=cuts.lo,
        hi_m=cuts.hi,
        n_gt=n_gt_cut,
        n_map=n_map_cut,
        n_matched=n_match,
        error_m=per_cut_err,
        corrected_m=per_cut_cor,
        offset_m=offset,
        drive_count=drive_count,
        floor_m=floor,
    )
    n_ref = int(np.count_nonzero(n_gt_cut > 0))
    n_eval = int(np.count_nonzero(evaluable))
    return EvalReport(
        gt_name=gt.name,
        config=config,
        overall=overall,
        per_type=per_type,
        type_accuracy=_share(int(np.count_nonzero(type_ok)), int(np.count_nonzero(typed))),
        n_typed=int(np.count_nonzero(typed)),
        type_accuracy_corrected=_share(int(np.count_nonzero(type_ok_cor)), int(np.count_nonzero(typed_cor))),
        **_std_calibration(err, m_std, matched),
        fragmentation_mean=frag_mean,
        fragmentation_max=frag_max,
        n_gt_features=n_frag,
        mean_abs_offset_m=float(np.mean(np.abs(offset[evaluable]))) if n_eval else math.nan,
        sigma_loc_m=sigma,
        floor_source=floor_source,
        floor_mean_m=float(np.mean(floor[floor_ok])) if floor_ok.any() else math.nan,
        drive_count_mean=float(np.mean(drive_count[floor_ok])) if floor_ok.any() else math.nan,
        fleet_floor_mean_m=_mean_abs(fleet_err, floor_ok),
        **_density_figures(drive_count, n_gt_cut > 0, config.density_drives, floor_source, evaluable),
        **_observed_figures(observed, gt_hit),
        n_cuts=k,
        n_reference_cuts=n_ref,
        n_evaluable_cuts=n_eval,
        reference_length_m=n_ref * config.step_m,
        evaluable_length_m=n_eval * config.step_m,
        gt_splits=sum(b.kind == "split" for b in evaluable_bp),
        gt_merges=sum(b.kind == "merge" for b in evaluable_bp),
        found_splits=sum(b.kind == "split" and b.found for b in evaluable_bp),
        found_merges=sum(b.kind == "merge" and b.found for b in evaluable_bp),
        branch_points=tuple(branch_points),
        gt_road_splits=sum(b.kind == "split" for b in evaluable_rp),
        gt_road_merges=sum(b.kind == "merge" for b in evaluable_rp),
        found_road_splits=sum(b.kind == "split" and b.found for b in evaluable_rp),
        found_road_merges=sum(b.kind == "merge" and b.found for b in evaluable_rp),
        road_branch_points=tuple(road_points),
        gt_lane_splits=sum(
            len(ln.successors) >= 2 and (ln.highway or not config.highway_only) for ln in gt.lanes.values()
        ),
        gt_lane_merges=sum(
            len(ln.predecessors) >= 2 and (ln.highway or not config.highway_only) for ln in gt.lanes.values()
        ),
        topology_link_precision=links.precision,
        n_topology_links=links.n_links,
        n_topology_links_evaluable=links.n_evaluable,
        n_topology_links_supported=links.n_supported,
        long_link_precision=links.long_precision,
        n_long_links=links.n_long,
        n_long_links_evaluable=links.n_long_evaluable,
        n_long_links_supported=links.n_long_supported,
        false_topology_links=links.false_links,
        unevaluable_long_links=links.unevaluable_long,
        cuts=profile,
        skipped=tuple(skipped),
        runtime_s=time.perf_counter() - t0,
    )


def _typed_right(same_d: np.ndarray, any_d: np.ndarray, config: EvalConfig) -> tuple[np.ndarray, np.ndarray]:
    """RULE 4 per map point, from its distances to the nearest ground-truth point of its type
    (``same_d``) and of any type (``any_d``) on its cut: (typed: one within the gate, typed and of
    the right type: the same-type point no farther than the nearest + ``type_tie_m``)."""
    typed = any_d <= config.gate_m
    return typed, typed & (same_d <= any_d + config.type_tie_m)


def _per_cut_mean(cut: np.ndarray, values: np.ndarray, k: int) -> np.ndarray:
    n = np.bincount(cut, minlength=k)
    out = np.full(k, np.nan)
    out[n > 0] = np.bincount(cut, weights=values, minlength=k)[n > 0] / n[n > 0]
    return out


def _at_map_points(values: list[np.ndarray], mp: CutPoints) -> np.ndarray:
    """(P,) a per-vertex value of the map features (one (N_i,) array each) at each map point on
    a cut: the value of the nearer segment end."""
    if not values:
        return np.zeros(0)
    offsets = np.concatenate([[0], np.cumsum([len(v) for v in values])])
    flat = np.concatenate(values)
    vertex = mp.vertex + (mp.u >= 0.5)
    return flat[offsets[mp.owner] + vertex]


def _std_calibration(err: np.ndarray, std: np.ndarray, matched: np.ndarray) -> dict:
    """How well the map's lateral_std describes its errors (EvalReport.std_within_share)."""
    ok = matched & np.isfinite(std) & (std > 0)
    n = int(np.count_nonzero(ok))
    if not n:
        return {"n_std_points": 0}
    z = err[ok] / std[ok]
    return {
        "std_within_share": float(np.mean(np.abs(z) <= 1.0)),
        "std_z_rms": float(np.sqrt(np.mean(z**2))),
        "n_std_points": n,
    }


def _cut_drive_counts(
    k: int,
    crossings: _Crossings | None,
    mp: CutPoints,
    matched: np.ndarray,
    m_dc: np.ndarray,
) -> tuple[np.ndarray, str]:
    """(K,) drives covering each cut (NaN unknown) and where the number comes from.

    With drives: trajectories crossing the cut in its direction, each drive once. Without: the
    largest drive_count among the cut's matched map points (0 -> unknown).
    """
    if crossings is not None:
        return np.bincount(crossings.cut, minlength=k).astype(float), "drives"
    dc = np.zeros(k)
    if matched.any():
        np.maximum.at(dc, mp.cut[matched], m_dc[matched])
    if not (dc > 0).any():
        return np.full(k, np.nan), "none"
    return np.where(dc > 0, dc, np.nan), "map"


def _density_figures(
    drive_count: np.ndarray, reference: np.ndarray, rng: tuple[int, int], source: str, evaluable: np.ndarray
) -> dict:
    """Median drive count over the ``reference`` cuts, the shares of them in ``rng``, below it and
    driven at all, and the coverage of the driven ones (only where the counts come from the
    drives' trajectories: map drive counts are not the fleet's density where the map has
    nothing)."""
    n = drive_count[reference]
    if source != "drives" or len(n) == 0:
        return {}
    lo, hi = rng
    driven = n >= 1
    return {
        "drive_count_median": float(np.median(n)),
        "density_share": float(np.mean((n >= lo) & (n <= hi))),
        "sparse_share": float(np.mean(n < lo)),
        "driven_share": float(np.mean(driven)),
        "coverage_driven": _share(int(np.count_nonzero(evaluable[reference] & driven)), int(np.count_nonzero(driven))),
    }


def _cut_fleet_error(k: int, crossings: _Crossings, drive_errors: Mapping[str, float]) -> np.ndarray:
    """(K,) mean of the known lateral errors of the drives crossing each cut in its direction
    (NaN where none is known). Crossing drives share the cut's left normal, so their errors add."""
    err = np.array([float(drive_errors.get(i, math.nan)) if i is not None else math.nan for i in crossings.drive_ids])
    e = err[crossings.owner] if len(err) else np.zeros(0)
    known = np.isfinite(e)
    n = np.bincount(crossings.cut[known], minlength=k).astype(float)
    total = np.bincount(crossings.cut[known], weights=e[known], minlength=k)
    return np.where(n > 0, total / np.maximum(n, 1.0), np.nan)


def _observed_gt_points(
    gt_feats: list, gp: CutPoints, seen_counts: Mapping[int, Sequence[int] | np.ndarray], skipped: list[str]
) -> np.ndarray:
    """(P,) per ground-truth point on a cut: the number of drives that saw the GT segment it lies on
    (the larger of its two ends' seen counts; > 0: "observed"), NaN when its feature's seen counts
    are missing or do not have one value per point."""
    on_cuts = set(np.unique(gp.owner).tolist())
    per_feature = []
    for i, f in enumerate(gt_feats):
        raw = seen_counts.get(int(f.id))
        try:
            seen = np.asarray(raw if raw is not None else [], dtype=float).reshape(-1)
            what = "no seen counts" if raw is None else f"{len(seen)} seen counts for {len(f.points)} points"
        except (TypeError, ValueError):
            seen, what = np.zeros(0), "seen counts that are not numbers"
        if len(seen) != len(f.points):
            if i in on_cuts:
                skipped.append(f"ground-truth feature {f.id}: {what}, left out of observed_share / recall_observed")
            seen = np.full(len(f.points), np.nan)
        per_feature.append(seen)
    flat = np.concatenate(per_feature) if per_feature else np.zeros(0)
    start = np.concatenate([[0], np.cumsum([len(a) for a in per_feature])]).astype(np.int64)
    a = flat[start[gp.owner] + gp.vertex] if len(gp.owner) else np.zeros(0)
    b = flat[start[gp.owner] + gp.vertex + 1] if len(gp.owner) else np.zeros(0)
    return np.where(np.isfinite(a) & np.isfinite(b), np.maximum(a, b), np.nan)


def _observed_figures(observed: np.ndarray | None, gt_hit: np.ndarray) -> dict[str, Any]:
    """``observed_share``, ``recall_observed`` and ``n_observed`` of the report (NaN, 0 without
    seen counts)."""
    if observed is None:
        return {"observed_share": math.nan, "recall_observed": math.nan, "n_observed": 0, "recall_by_seen": ()}
    known = np.isfinite(observed)
    obs = known & (observed > 0)
    n_obs = int(np.count_nonzero(obs))
    n_known = int(np.count_nonzero(known))
    by_seen = []
    for label, lo, hi in (("0", 0, 0), ("1", 1, 1), ("2", 2, 2), (">=3", 3, math.inf)):
        sel = known & (observed >= lo) & (observed <= hi)
        n = int(np.count_nonzero(sel))
        by_seen.append((label, _share(n, n_known), _share(int(np.count_nonzero(sel & gt_hit)), n)))
    return {
        "observed_share": _share(n_obs, n_known),
        "recall_observed": _share(int(np.count_nonzero(obs & gt_hit)), n_obs),
        "n_observed": n_obs,
        "recall_by_seen": tuple(by_seen) if n_known else (),
    }


def _mean_abs(values: np.ndarray | None, sel: np.ndarray) -> float:
    if values is None:
        return math.nan
    ok = sel & np.isfinite(values)
    return float(np.mean(np.abs(values[ok]))) if ok.any() else math.nan


def _type_stats(
    *,
    g_mask: np.ndarray,
    m_mask: np.ndarray,
    gp: CutPoints,
    mp: CutPoints,
    err: np.ndarray,
    corrected: np.ndarray,
    matched: np.ndarray,
    gt_hit: np.ndarray,
    map_hit: np.ndarray,
    k: int,
) -> TypeStats:
    sel = m_mask & matched
    abs_err = np.abs(err[sel])
    abs_cor = np.abs(corrected[sel])
    gt_cuts = np.unique(gp.cut[g_mask])
    covered = np.intersect1d(gt_cuts, np.unique(mp.cut[sel]))
    mean, med, p95 = _stats(abs_err)
    cmean, cmed, cp95 = _stats(abs_cor)
    n_g, n_m = int(np.count_nonzero(g_mask)), int(np.count_nonzero(m_mask))
    return TypeStats(
        n_gt_points=n_g,
        n_map_points=n_m,
        n_matched=int(np.count_nonzero(sel)),
        mean_m=mean,
        median_m=med,
        p95_m=p95,
        corrected_mean_m=cmean,
        corrected_median_m=cmed,
        corrected_p95_m=cp95,
        recall=_share(int(np.count_nonzero(gt_hit & g_mask)), n_g),
        precision=_share(int(np.count_nonzero(map_hit & m_mask)), n_m),
        coverage=_share(len(covered), len(gt_cuts)) if len(gt_cuts) else math.nan,
        n_cuts=len(gt_cuts),
    )


def _fragmentation(
    gp: CutPoints, gi: np.ndarray, matched: np.ndarray, map_feats: list[MapFeature], mp: CutPoints
) -> tuple[float, int, int]:
    """Distinct map features matched along each ground-truth feature: (mean, max, #GT features)."""
    if not matched.any():
        return math.nan, 0, 0
    gt_owner = gp.owner[gi[matched]]
    map_owner = mp.owner[matched]
    pairs = np.unique(np.stack([gt_owner, map_owner], axis=1), axis=0)
    _, per_gt = np.unique(pairs[:, 0], return_counts=True)
    return float(np.mean(per_gt)), int(np.max(per_gt)), len(per_gt)


def _branch_points(
    gt_feats: list,
    cuts: Cuts,
    gp: CutPoints,
    gi: np.ndarray,
    gd: np.ndarray,
    mp: CutPoints,
    map_feats: list[MapFeature],
    config: EvalConfig,
    cos_feat: float,
) -> list[BranchPoint]:
    """Ground-truth splits and merges in the evaluated area and whether the map has them connected."""
    nodes = on_cuts(
        ground_truth_branch_points(gt_feats, cos_min=cos_feat), cuts, half_step_m=config.step_m / 2, cos_min=cos_feat
    )
    if not nodes:
        return []
    near = gd <= config.recall_radius_m
    return check_branch_points(
        nodes,
        gt_feats,
        gp,
        gi[near],
        mp.owner[near],
        map_feature_graph(map_feats, attach_m=config.topology_attach_m, cos_min=cos_feat),
        separation_m=config.topology_separation_m,
        window_m=config.topology_window_m,
        reach_m=config.topology_reach_m,
    )


def road_check_config(config: EvalConfig) -> RoadCheckConfig:
    """The road-level check's settings from ``config``."""
    return RoadCheckConfig(
        follow_m=config.road_follow_m,
        apart_m=config.road_apart_m,
        cluster_m=config.road_cluster_m,
        node_margin_m=config.road_node_margin_m,
        path_m=config.road_path_m,
        cos_min=math.cos(math.radians(config.max_feature_angle_deg)),
    )


def _road_branch_points(
    gt: GroundTruth, cuts: Cuts, topo: TopologyArrays, config: EvalConfig, cos_feat: float
) -> list[RoadBranchPoint]:
    """Road splits and merges of the ground-truth lane graph in the evaluated area and whether the
    map's topology graph connects them (``hdmap_core.evaluation.roads``)."""
    cfg = road_check_config(config)
    points = road_branch_points(gt.lanes, highway_only=config.highway_only, cfg=cfg)
    if not points:
        return []
    xy = np.array([p.xy for p in points])
    heading = np.array([p.heading for p in points])
    # RULE R0: only points in the evaluated area (inside a cut running their way), as for features.
    inside = inside_cuts(xy, heading, cuts, half_step_m=config.step_m / 2, cos_min=cos_feat)
    points = [p for p, ok in zip(points, inside) if ok]
    if not points:
        return []
    return check_road_points(points, topo, cfg)


def _topology_links(
    gt: GroundTruth, cuts: Cuts, topo: TopologyArrays, config: EvalConfig, cos_feat: float
) -> LinkPrecision:
    """Each edge of the map's topology graph judged against the ground-truth lane graph
    (``hdmap_core.evaluation.links``); nodes count only in the evaluated area, as road points do."""
    cfg = LinkCheckConfig(
        node_margin_m=config.road_node_margin_m,
        cos_min=cos_feat,
        path_factor=config.link_path_factor,
        path_slack_m=config.link_path_slack_m,
        back_m=config.link_back_m,
        long_m=config.link_long_m,
    )
    heading = np.arctan2(topo.tangent[:, 1], topo.tangent[:, 0])
    in_area = inside_cuts(topo.xy, heading, cuts, half_step_m=config.step_m / 2, cos_min=cos_feat)
    return check_topology_links(gt.lanes, topo, in_area, cfg)


# --------------------------------------------------------------------------------------------
# Ground truth as a map; plotting


def hdmap_from_ground_truth(
    gt: GroundTruth, *, lateral_shift_m: float = 0.0, drive_count: int = 0, with_topology: bool = True
) -> HDMap:
    """The ground-truth features as an ``HDMap`` ("perfect map"), optionally shifted sideways.

    Args:
        gt: the ground truth.
        lateral_shift_m: every point moves this far along its feature's left normal (from central
            differences of the points) [m]; + = left of the feature's direction.
        drive_count: value of every point's ``drive_count``.
        with_topology: add a lane-level topology graph (``evaluate_roads.topology_from_lanes``: a
            node every 2 m along each lane centerline, 3.5 m wide, linked along the lane graph),
            so that the road-level splits/merges check has a perfect topology too.

    Returns:
        A map whose feature ids are the ground-truth ids; ``lateral_std`` is 0; features whose
        last point meets another's first point (within 5 cm) are linked as successor/predecessor.
    """
    feats = [f for f in gt.features if len(f.points) >= 2]
    starts = np.array([f.points[0] for f in feats]) if feats else np.zeros((0, 2))
    ends = np.array([f.points[-1] for f in feats]) if feats else np.zeros((0, 2))
    succ: dict[int, list[int]] = {i: [] for i in range(len(feats))}
    pred: dict[int, list[int]] = {i: [] for i in range(len(feats))}
    if feats:
        for i, js in enumerate(cKDTree(starts).query_ball_point(ends, r=0.05)):
            for j in js:
                if j != i:
                    succ[i].append(j)
                    pred[j].append(i)
    out = []
    for i, f in enumerate(feats):
        pts = np.asarray(f.points, dtype=float)
        if lateral_shift_m:
            pts = pts + lateral_shift_m * turn_left(unit_tangents(pts))
        out.append(
            MapFeature(
                id=int(f.id),
                type=f.type,
                points=pts,
                drive_count=np.full(len(pts), int(drive_count), dtype=np.int64),
                lateral_std=np.zeros(len(pts)),
                predecessors=tuple(int(feats[j].id) for j in sorted(pred[i])),
                successors=tuple(int(feats[j].id) for j in sorted(succ[i])),
            )
        )
    topology = topology_from_lanes(gt.lanes) if with_topology else ()
    return HDMap(
        features=tuple(out),
        topology=topology,
        extra={"source": f"ground truth {gt.name}", "lateral_shift_m": lateral_shift_m},
    )
