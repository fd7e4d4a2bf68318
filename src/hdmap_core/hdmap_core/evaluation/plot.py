"""The evaluator's figure: the map over the ground truth and the error along the road (PNG).

matplotlib is imported only when a figure is drawn, with the non-interactive Agg backend.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from hdmap_core.evaluation.report import EvalReport
from hdmap_core.geometry import left_normal
from hdmap_core.groundtruth import GroundTruth
from hdmap_core.model import FeatureType, HDMap

__all__ = ["TYPE_COLORS", "plot_evaluation"]

#: Colours per type (ground truth drawn light, map drawn strong).
TYPE_COLORS = {
    FeatureType.SOLID: "#2ca02c",
    FeatureType.DASHED: "#1f77b4",
    FeatureType.ROAD_BORDER: "#e8a100",
    FeatureType.UNKNOWN: "#7f7f7f",
}


def _smooth(values: np.ndarray, window: int) -> np.ndarray:
    """Sliding-window mean ignoring NaN (NaN where the window holds no value)."""
    ok = np.isfinite(values)
    kernel = np.ones(window)
    num = np.convolve(np.where(ok, values, 0.0), kernel, mode="same")
    den = np.convolve(ok.astype(float), kernel, mode="same")
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.maximum(den, 1), np.nan)


_ZOOM_HALF_M = 40.0


def _draw_map(
    ax, report: EvalReport, hdmap: HDMap, gt: GroundTruth, *, gt_lw: float, map_lw: float, cut_every: int, lc: type
) -> None:
    """Ground truth (light, wide) and map (strong, narrow) by type, cut lines, non-evaluable cuts."""
    for f in gt.features:
        p = np.asarray(f.points)
        ax.plot(p[:, 0], p[:, 1], color=TYPE_COLORS[f.type], lw=gt_lw, alpha=0.25, solid_capstyle="butt")
    for mf in hdmap.features:
        p = np.asarray(mf.points, dtype=float)
        if p.ndim == 2 and len(p) >= 2 and p.shape[1] == 2:
            ax.plot(p[:, 0], p[:, 1], color=TYPE_COLORS.get(mf.type, "#7f7f7f"), lw=map_lw)
    cuts = report.cuts
    ref, ev = cuts.reference, cuts.evaluable
    normal = left_normal(cuts.heading_rad).reshape(-1, 2)
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
        + (
            f" ({100 * report.recall_observed:.1f} % of the observed GT points)"
            if math.isfinite(report.recall_observed)
            else ""
        )
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
            km,
            0,
            1,
            where=gaps,
            transform=ax_err.get_xaxis_transform(),
            color="red",
            alpha=0.12,
            lw=0,
            label="not evaluable",
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
