"""Human-readable output of the evaluator: the text summary and the PNG figure.

matplotlib is imported only when a figure is drawn, with the non-interactive Agg backend.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hdmap_core.groundtruth import GroundTruth
from hdmap_core.model import FeatureType, HDMap

if TYPE_CHECKING:
    from hdmap_core.evaluation.evaluate import EvalReport

__all__ = ["format_summary", "plot_evaluation", "TYPE_COLORS"]

#: Colours per type (ground truth drawn light, map drawn strong).
TYPE_COLORS = {
    FeatureType.SOLID: "#2ca02c",
    FeatureType.DASHED: "#1f77b4",
    FeatureType.ROAD_BORDER: "#e8a100",
    FeatureType.UNKNOWN: "#7f7f7f",
}


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


def _branch_summary(head: str, points: Sequence[Any], missing: Sequence[Any], describe: Callable[[Any], str],
                    extra: str = "") -> str:
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


def _smooth(values: np.ndarray, window: int) -> np.ndarray:
    """Sliding-window mean ignoring NaN (NaN where the window holds no value)."""
    ok = np.isfinite(values)
    kernel = np.ones(window)
    num = np.convolve(np.where(ok, values, 0.0), kernel, mode="same")
    den = np.convolve(ok.astype(float), kernel, mode="same")
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.maximum(den, 1), np.nan)


_ZOOM_HALF_M = 40.0


def _draw_map(ax, report: EvalReport, hdmap: HDMap, gt: GroundTruth, *, gt_lw: float, map_lw: float,
              cut_every: int, lc: type) -> None:
    """Ground truth (light, wide) and map (strong, narrow) by type, cut lines, non-evaluable cuts."""
    for f in gt.features:
        p = np.asarray(f.points)
        ax.plot(p[:, 0], p[:, 1], color=TYPE_COLORS[f.type], lw=gt_lw, alpha=0.25, solid_capstyle="butt")
    for f in hdmap.features:
        p = np.asarray(f.points, dtype=float)
        if p.ndim == 2 and len(p) >= 2 and p.shape[1] == 2:
            ax.plot(p[:, 0], p[:, 1], color=TYPE_COLORS.get(f.type, "#7f7f7f"), lw=map_lw)
    cuts = report.cuts
    ref, ev = cuts.reference, cuts.evaluable
    normal = np.stack([-np.sin(cuts.heading_rad), np.cos(cuts.heading_rad)], axis=1)
    ends = np.stack([cuts.center + cuts.lo_m[:, None] * normal, cuts.center + cuts.hi_m[:, None] * normal], axis=1)
    ax.add_collection(lc(ends[ref][::cut_every], colors="0.6", linewidths=0.3, alpha=0.6, zorder=0))
    if (ref & ~ev).any():
        ax.scatter(*cuts.center[ref & ~ev].T, s=4, color="red", zorder=3)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def plot_evaluation(report: EvalReport, hdmap: HDMap, gt: GroundTruth, path: str | Path) -> Path:
    """Write the evaluation figure as PNG to ``path`` and return it.

    Top: ground truth (light, wide) with the map over it (strong, narrow), both coloured by type,
    and the evaluated cut positions. Bottom: mean absolute total and offset-corrected error per cut
    along the reference (sliding window of ~50 m, like the paper's Fig. of error over distance),
    the floor sigma/sqrt(n), and the drive count on a second axis; stretches without a matched map
    point are shaded.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D
    from matplotlib.patches import Rectangle

    path = Path(path)
    cuts = report.cuts
    ev = cuts.evaluable
    ref = cuts.reference
    km = cuts.station_m / 1000.0
    window = max(1, int(round(50.0 / report.config.step_m)))
    err_smooth = _smooth(cuts.error_m, window)
    zoom_k = int(np.nanargmax(err_smooth)) if np.isfinite(err_smooth).any() else int(np.argmax(ref))
    zc, half = cuts.center[zoom_k], _ZOOM_HALF_M

    fig = plt.figure(figsize=(13, 12), constrained_layout=True)
    grid = fig.add_gridspec(2, 2, height_ratios=[1.6, 1], width_ratios=[1.4, 1])
    ax_map, ax_zoom, ax_err = fig.add_subplot(grid[0, 0]), fig.add_subplot(grid[0, 1]), fig.add_subplot(grid[1, :])
    _draw_map(ax_map, report, hdmap, gt, gt_lw=3.5, map_lw=0.8, cut_every=5, lc=LineCollection)
    _draw_map(ax_zoom, report, hdmap, gt, gt_lw=7.0, map_lw=1.3, cut_every=1, lc=LineCollection)
    ax_map.set_aspect("equal", adjustable="datalim")
    ax_map.add_patch(Rectangle(zc - half, 2 * half, 2 * half, fill=False, ec="k", lw=1.0, zorder=4))
    fig.suptitle(
        f"map over ground truth {report.gt_name!r}: total {report.overall.mean_m:.3f} m, "
        f"offset-corrected {report.overall.corrected_mean_m:.3f} m, coverage {100 * report.coverage:.1f} %, "
        f"recall {100 * report.overall.recall:.1f} %"
        + (f" ({100 * report.recall_observed:.1f} % of the observed GT points)" if math.isfinite(report.recall_observed) else "")
        if math.isfinite(report.overall.mean_m)
        else f"map over ground truth {report.gt_name!r}: nothing evaluable"
    )
    ax_map.set_title("overview", fontsize=10)
    ax_zoom.set_xlim(zc[0] - half, zc[0] + half)
    ax_zoom.set_ylim(zc[1] - half, zc[1] + half)
    ax_zoom.set_aspect("equal", adjustable="box")
    where = "largest error" if np.isfinite(err_smooth).any() else "start of the reference (nothing evaluable)"
    ax_zoom.set_title(f"zoom (box at left): {where}, {km[zoom_k]:.2f} km along the reference", fontsize=10)
    handles = [Line2D([], [], color=TYPE_COLORS[t], lw=2, label=t.label) for t in TYPE_COLORS if t]
    handles += [
        Line2D([], [], color="k", lw=3.5, alpha=0.25, label="ground truth (light, wide)"),
        Line2D([], [], color="k", lw=0.8, label="map (strong, narrow)"),
        Line2D([], [], color="0.6", lw=0.5, label="cut lines (overview: every 5th)"),
        Line2D([], [], color="red", marker="o", ls="", ms=3, label="cut not evaluable"),
    ]
    ax_zoom.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=3, fontsize=8)

    ax_err.axvline(km[zoom_k], color="k", lw=0.6, ls=":")
    ax_err.plot(km, err_smooth, color="#1f77b4", lw=1.0, label="total error (50 m mean)")
    ax_err.plot(km, _smooth(cuts.corrected_m, window), color="#e07f2c", lw=1.0, label="offset-corrected error")
    if np.isfinite(cuts.floor_m).any():
        ax_err.plot(km, _smooth(cuts.floor_m, window), color="k", lw=0.8, ls="--", label="floor sigma/sqrt(n)")
    gaps = ref & ~ev
    if gaps.any():
        ax_err.fill_between(
            km, 0, 1, where=gaps, transform=ax_err.get_xaxis_transform(), color="red", alpha=0.12,
            lw=0, label="not evaluable",
        )
    ax_err.set_xlabel("distance along the de-duplicated reference [km]")
    ax_err.set_ylabel("mean absolute lateral error [m]")
    ax_err.set_ylim(bottom=0)
    ax_err.grid(alpha=0.3)
    lines, labels = ax_err.get_legend_handles_labels()
    if np.isfinite(cuts.drive_count).any():
        ax_n = ax_err.twinx()
        ax_n.plot(km, cuts.drive_count, color="#2ca02c", lw=0.6, alpha=0.7, label="drives per cut")
        ax_n.set_ylabel("drives covering the cut")
        ax_n.set_ylim(bottom=0)
        l2, lb2 = ax_n.get_legend_handles_labels()
        lines, labels = lines + l2, labels + lb2
    ax_err.legend(lines, labels, loc="upper right", fontsize=8)
    ax_err.set_title("lateral error and drive count along the reference")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
