"""The lanes of a map bag around a place, drawn over its features (the picture of docs/lanes.md);
turned so that the road at the place runs to the right.

    .venv/bin/python scripts/lanes_figure.py MAP_BAG X Y [--radius M] [-o OUT.png]
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Polygon  # noqa: E402

from hdmap_core.evaluation.plot import TYPE_COLORS  # noqa: E402
from hdmap_core.lanes.derive import derive_lanes  # noqa: E402
from hdmap_core.model import FeatureType  # noqa: E402
from hdmap_ros.io.bagio import read_map_bag  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("map")
    ap.add_argument("x", type=float)
    ap.add_argument("y", type=float)
    ap.add_argument("--radius", type=float, default=150.0)
    ap.add_argument("-o", "--output", default="lanes.png")
    args = ap.parse_args(argv)
    hdmap = read_map_bag(args.map)
    lanes = derive_lanes(hdmap)
    c = np.array([args.x, args.y])
    near = min(lanes.lanes, key=lambda ln: float(np.min(np.hypot(*(ln.centerline - c).T))))
    k = int(np.argmin(np.hypot(*(near.centerline - c).T)))
    d = near.centerline[min(k + 1, len(near.centerline) - 1)] - near.centerline[max(k - 1, 0)]
    yaw = float(np.arctan2(d[1], d[0]))
    rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])  # (p - c) @ rot: road along +x

    def local(p: np.ndarray) -> np.ndarray:
        return (np.asarray(p) - c) @ rot

    fig, ax = plt.subplots(figsize=(11, 3.6), dpi=110)
    colors = ["#a6cee3", "#b2df8a", "#fdbf6f", "#cab2d6"]
    for i, ln in enumerate(lanes.lanes):
        ring = lanes.polygon(ln)
        if np.min(np.hypot(*(ring - c).T)) > args.radius:
            continue
        virtual = ln.left_type == FeatureType.UNKNOWN
        ax.add_patch(
            Polygon(
                local(ring),
                closed=True,
                alpha=0.55,
                lw=0.3,
                ec="k",
                fc="#dddddd" if virtual else colors[i % len(colors)],
            )
        )
        ax.plot(*local(ln.centerline).T, "-", color="#1f5f1f", lw=0.6)
        ax.annotate(
            "",
            xy=local(ln.centerline[-1]),
            xytext=local(ln.centerline[-2]),
            arrowprops=dict(arrowstyle="->", color="#1f5f1f", lw=0.6),
        )
    for f in hdmap.features:
        if np.min(np.hypot(*(f.points - c).T)) <= args.radius:
            ax.plot(
                *local(f.points).T, "--" if f.type == FeatureType.DASHED else "-", color=TYPE_COLORS[f.type], lw=1.0
            )
    ax.set_xlim(-args.radius, args.radius)
    ax.set_ylim(-args.radius / 4, args.radius / 4)
    ax.set_aspect("equal")
    ax.set_xlabel("along the road [m]")
    ax.set_ylabel("across [m]")
    ax.set_title("lanes (filled, centerline arrows) between the map's features (lines)")
    fig.tight_layout()
    fig.savefig(args.output)
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
