"""The evaluator's text summary: what ``hdmap evaluate`` prints for an ``EvalReport``."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

from hdmap_core.evaluation.report import EvalReport

__all__ = ["format_summary"]


def _m(v: float) -> str:
    return "   n/a" if not math.isfinite(v) else f"{v:6.3f}"


def _pct(v: float) -> str:
    return "   n/a" if not math.isfinite(v) else f"{100 * v:5.1f}%"


def format_summary(report: EvalReport) -> str:
    """The multi-line text summary of a report."""
    cfg = report.config
    lanes = "highway lanes" if cfg.highway_only else "all lanes"
    lines = [
        f"Evaluation against ground truth {report.gt_name!r} ({lanes}, a cut every {cfg.step_m:g} m, "
        f"match gate {cfg.gate_m:g} m, recall radius {cfg.recall_radius_m:g} m)",
        f"reference {report.reference_length_m / 1000:.2f} km ({report.n_reference_cuts} cuts), "
        f"evaluable {report.evaluable_length_m / 1000:.2f} km: coverage {_pct(report.coverage).strip()}",
        "",
        "lateral error [m]       total:  mean median    p95 | offset-corrected:  mean median    p95"
        " | recall precision coverage |  GT pts map pts matched",
    ]
    rows = [("all", report.overall)] + list(report.per_type.items())
    for name, st in rows:
        lines.append(
            f"  {name:<12s}         {_m(st.mean_m)} {_m(st.median_m)} {_m(st.p95_m)} |"
            f"                  {_m(st.corrected_mean_m)} {_m(st.corrected_median_m)} {_m(st.corrected_p95_m)} |"
            f" {_pct(st.recall)}    {_pct(st.precision)}   {_pct(st.coverage)} |"
            f" {st.n_gt_points:7d} {st.n_map_points:7d} {st.n_matched:7d}"
        )
    lines += [
        "",
        f"mean |offset| per cut {_m(report.mean_abs_offset_m).strip()} m; type accuracy "
        f"{_pct(report.type_accuracy).strip()} of {report.n_typed} map points "
        f"({_pct(report.type_accuracy_corrected).strip()} offset-corrected); fragmentation "
        + (
            f"{report.fragmentation_mean:.2f} map features per GT feature (max {report.fragmentation_max}, "
            f"{report.n_gt_features} GT features)"
            if report.n_gt_features
            else "n/a"
        ),
    ]
    if report.n_std_points:
        lines.append(
            f"lateral_std as 1-sigma: {_pct(report.std_within_share).strip()} of {report.n_std_points} matched map "
            f"points lie within it of the truth (68.3% if calibrated); rms error / lateral_std {report.std_z_rms:.2f}"
        )
    lines.append(_topology_line(report))
    lines.append(_road_line(report))
    lines.append(_link_line(report))
    if report.floor_source == "none":
        lines.append(f"floor sigma/sqrt(n): n/a (no drive counts; sigma_loc {report.sigma_loc_m:g} m)")
    else:
        src = "drive trajectories" if report.floor_source == "drives" else "map drive_count"
        lines.append(
            f"floor sigma/sqrt(n): {_m(report.floor_mean_m).strip()} m mean over evaluable cuts "
            f"(sigma_loc {report.sigma_loc_m:g} m, n from {src}: mean {report.drive_count_mean:.1f} drives)"
        )
    if math.isfinite(report.density_share):
        lo, hi = report.config.density_drives
        lines.append(
            f"fleet density over the reference cuts: median {report.drive_count_median:.0f} drives; "
            f"{_pct(report.density_share).strip()} at {lo}-{hi} drives (the paper's data), "
            f"{_pct(report.sparse_share).strip()} below {lo}"
        )
    if math.isfinite(report.driven_share):
        lines.append(
            f"driven reference cuts (crossed by >= 1 drive in their direction): {_pct(report.driven_share).strip()}; "
            f"coverage over them {_pct(report.coverage_driven).strip()} (over all {_pct(report.coverage).strip()})"
        )
    if math.isfinite(report.fleet_floor_mean_m):
        lines.append(
            f"realized floor |mean error of the crossing drives|: {report.fleet_floor_mean_m:.3f} m mean over "
            "evaluable cuts (the fleet's own common error, from its simulator truth)"
        )
    if math.isfinite(report.observed_share):
        lines.append(
            f"observed GT points (an end of their GT segment detected by >= 1 drive, simulator truth): "
            f"{_pct(report.observed_share).strip()}; recall over them {_pct(report.recall_observed).strip()} "
            f"of {report.n_observed} (recall over all {_pct(report.overall.recall).strip()})"
        )
    if report.recall_by_seen:
        parts = [
            f"{label}: {_pct(share).strip()} of the points, recall {_pct(rec).strip() if math.isfinite(rec) else '-'}"
            for label, share, rec in report.recall_by_seen
        ]
        lines.append("GT points by drives that saw them: " + "; ".join(parts))
    if report.skipped:
        lines.append(f"skipped {len(report.skipped)} input part(s):")
        lines += [f"  {s}" for s in report.skipped[:10]]
        if len(report.skipped) > 10:
            lines.append(f"  ... and {len(report.skipped) - 10} more")
    lines.append(f"evaluated in {report.runtime_s:.2f} s")
    return "\n".join(lines)


def _branch_summary(
    head: str, points: Sequence[Any], missing: Sequence[Any], describe: Callable[[Any], str], extra: str = ""
) -> str:
    """``head``, how many ``points`` were not evaluable, ``extra``, then the ``missing`` ones (at most 5)."""
    n_unevaluable = sum(not b.evaluable for b in points)
    line = head + (f" ({n_unevaluable} more not evaluable)" if n_unevaluable else "") + extra
    for b in missing[:5]:
        line += f"\n  {describe(b)}"
    if len(missing) > 5:
        line += f"\n  ... and {len(missing) - 5} more"
    return line


def _topology_line(report: EvalReport) -> str:
    """Splits and merges found, and the missing ones with their positions (at most 5 listed)."""
    return _branch_summary(
        f"splits/merges connected in the map: splits {report.found_splits}/{report.gt_splits}, "
        f"merges {report.found_merges}/{report.gt_merges}",
        report.branch_points,
        report.missing_branch_points,
        lambda b: f"missing {b.kind} at ({b.x:.1f}, {b.y:.1f}): {b.reason}",
        extra=f"; GT lane graph: {report.gt_lane_splits} lane splits, {report.gt_lane_merges} lane merges",
    )


def _road_line(report: EvalReport) -> str:
    """Road-level splits and merges (GT lane graph vs the map's topology), the missing ones listed."""
    return _branch_summary(
        f"road splits/merges connected in the map's topology: splits {report.found_road_splits}/"
        f"{report.gt_road_splits}, merges {report.found_road_merges}/{report.gt_road_merges}",
        report.road_branch_points,
        report.missing_road_branch_points,
        lambda b: f"missing road {b.kind} at ({b.x:.1f}, {b.y:.1f}), GT lanes {', '.join(b.gt_lanes)}: {b.reason}",
    )


def _link_line(report: EvalReport) -> str:
    """Topology link precision against the GT lane graph, the false long links listed (at most 5)."""
    cfg = report.config
    line = (
        f"topology links supported by the GT lane graph: {report.n_topology_links_supported}/"
        f"{report.n_topology_links_evaluable} ({_pct(report.topology_link_precision).strip()}), long (> "
        f"{cfg.link_long_m:g} m) {report.n_long_links_supported}/{report.n_long_links_evaluable} "
        f"({_pct(report.long_link_precision).strip()}); not evaluable "
        f"{report.n_topology_links - report.n_topology_links_evaluable} of {report.n_topology_links} "
        f"({report.n_long_links - report.n_long_links_evaluable} long)"
    )
    false_long = [t for t in report.false_topology_links if t.length_m > cfg.link_long_m]
    for t in false_long[:5]:
        line += (
            f"\n  false link {t.length_m:.1f} m from ({t.x:.1f}, {t.y:.1f}) to ({t.to_x:.1f}, {t.to_y:.1f}): {t.reason}"
        )
    if len(false_long) > 5:
        line += f"\n  ... and {len(false_long) - 5} more long"
    return line
