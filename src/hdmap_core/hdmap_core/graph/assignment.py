"""The modified rectangular assignment between consecutive steps (Sec. V of Immel et al. 2023).

Open polyline ends (tips) of one step are paired with the maxima of the next by a rectangular
linear assignment (``scipy.optimize.linear_sum_assignment``, Karp 1980) on their distance across
the cut, with an angle plausibility check and no road border paired with another type; nodes left
over at splits and merges are then joined to their nearest neighbour on the other side (the
paper's modification). Used by ``connection.connect_segment``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import linear_sum_assignment

from hdmap_core.model import FeatureType

if TYPE_CHECKING:
    from hdmap_core.graph.connection_config import ConnectionConfig

__all__ = ["Assignment", "assign"]

# Rules measured and adopted with this stage (docs/graph.md); no preset changes them, so they are
# constants, not settings
#: a bridged connection longer than this along is held to ``bridge_edge_angle_deg``; shorter ones
#: (one step's gap) keep the ordinary edge limit [m]
_BRIDGE_EDGE_MIN_M = 3.0

_BORDER = int(FeatureType.ROAD_BORDER)
_BIG = 1.0e9
_GATE = 1.0e4  # cost added to a pair beyond the edge limits: taken only when nothing else is left
_GATE_TIE = 1.0e-3  # weight of the distance of such a pair (ties among them only)


def _median(v: np.ndarray) -> float:
    w = np.sort(v)
    h = len(w) // 2
    return float(w[h]) if len(w) % 2 else 0.5 * float(w[h - 1] + w[h])


@dataclass
class Assignment:
    """Pairs (tip index, new maximum index) of one step: ``regular`` from the assignment,
    ``leftover`` joined at splits/merges; ``mean_angle_deg`` of the solved pairs (plausibility)."""

    regular: list[tuple[int, int]]
    leftover: list[tuple[int, int]]
    mean_angle_deg: float


def _plausible(along: np.ndarray, lat: np.ndarray, config: ConnectionConfig) -> np.ndarray:
    """Edges (``along`` / ``lat`` [m] from tip to maximum in some frame) within the edge angle
    limits: ahead, at most ``max_edge_angle_deg`` steep (plus ``edge_slack_m``), and beyond
    ``_BRIDGE_EDGE_MIN_M`` at most ``bridge_edge_angle_deg``."""
    tan_max = math.tan(math.radians(min(config.max_edge_angle_deg, 89.999)))
    ok = (along > 0.0) & (lat <= config.edge_slack_m + np.maximum(along, 0.0) * tan_max)
    if config.bridge_edge_angle_deg < 90.0:
        # across a bridged gap a steep edge is a line joined to its neighbour, not the line
        tan_b = math.tan(math.radians(config.bridge_edge_angle_deg))
        ok &= (along <= _BRIDGE_EDGE_MIN_M) | (lat <= config.edge_slack_m + along * tan_b)
    return ok


def assign(
    tip_xy: np.ndarray,
    tip_type: np.ndarray,
    tip_fresh: np.ndarray,
    new_xy: np.ndarray,
    new_type: np.ndarray,
    heading: float,
    config: ConnectionConfig,
    tip_dir: np.ndarray | None = None,
    tip_check: np.ndarray | None = None,
) -> Assignment:
    """Modified rectangular assignment between open polyline ends (tips) and a step's maxima.

    The cost is the point distance across the cut of the new step (for consecutive steps it ranks
    pairs as the Euclidean distance does, and it stays comparable across bridged gaps).
    ``tip_dir`` (n, 2): unit direction of each tip's own line, NaN where the new step's heading
    is used; a tip with a direction is measured along / across its line instead.
    ``tip_check`` (n, 2): unit direction of a tip's own line against which its edges must be
    plausible too (the edge limits measured in that direction; NaN: no such check).
    """
    d = new_xy[None, :, :] - tip_xy[:, None, :]
    c, s_ = math.cos(heading), math.sin(heading)
    u, nrm = np.array([c, s_]), np.array([-s_, c])
    own = np.zeros(len(tip_xy), dtype=bool) if tip_dir is None else np.isfinite(tip_dir[:, 0])
    if tip_dir is not None and own.any():
        uu = np.where(own[:, None], tip_dir, u[None, :])
        nn = np.stack([-uu[:, 1], uu[:, 0]], axis=1)
        along = np.einsum("ijk,ik->ij", d, uu)
        lat = np.abs(np.einsum("ijk,ik->ij", d, nn))
    else:
        along = d @ u
        lat = np.abs(d @ nrm)
    # never connect a road border to another type
    forbidden = (tip_type[:, None] == _BORDER) != (new_type[None, :] == _BORDER)
    plausible = _plausible(along, lat, config)
    if tip_check is not None and np.isfinite(tip_check[:, 0]).any():
        # the same limits measured along / across the tip's own line too
        chk = np.isfinite(tip_check[:, 0])
        cu = tip_check[chk]
        dc = d[chk]
        al_c = np.einsum("ijk,ik->ij", dc, cu)
        la_c = np.abs(np.einsum("ijk,ik->ij", dc, np.stack([-cu[:, 1], cu[:, 0]], axis=1)))
        plausible[chk] &= _plausible(al_c, la_c, config)
    ok = plausible & ~forbidden

    n, m = lat.shape
    rows = cols = np.zeros(0, dtype=np.int64)
    if config.max_edge_angle_deg < 90.0:
        # an implausible pair is dropped after solving, so its distance only breaks ties among
        # such pairs (x 1e-3): with the full distance a chain of plausible but wrong pairs (a
        # bridged tip taking the next line 3.5 m across) could cost less than one far
        # implausible pair that is dropped anyway
        cost = np.where(forbidden, _BIG, np.where(plausible, lat, _GATE + _GATE_TIE * lat))
    else:  # the paper's variant: plain point distances
        cost = np.where(forbidden, _BIG, lat)
    if n and m:
        if n == m and bool(tip_fresh.all()) and not own.any():
            # In 1-D the sorted pairing is the exact optimum of the assignment for |a - b| costs.
            lt = tip_xy @ nrm
            ln = new_xy @ nrm
            rows, cols = np.argsort(lt, kind="stable"), np.argsort(ln, kind="stable")
            if not ok[rows, cols].all():
                rows, cols = linear_sum_assignment(cost)
        elif config.fresh_first and tip_fresh.any() and not tip_fresh.all():
            # the tips of the last step first; tips bridged from earlier steps take what is left
            fr, st = np.flatnonzero(tip_fresh), np.flatnonzero(~tip_fresh)
            r1, c1 = linear_sum_assignment(cost[fr])
            r1 = fr[r1]
            taken = np.zeros(m, dtype=bool)
            taken[c1[ok[r1, c1]]] = True
            free = np.flatnonzero(~taken)
            if len(free):
                r2, c2 = linear_sum_assignment(cost[np.ix_(st, free)])
                r2, c2 = st[r2], free[c2]
            else:
                r2 = c2 = np.zeros(0, dtype=np.int64)
            keep1 = ok[r1, c1] | ~np.isin(c1, c2)
            rows, cols = np.concatenate([r1[keep1], r2]), np.concatenate([c1[keep1], c2])
        else:
            rows, cols = linear_sum_assignment(cost)
    # the plausibility of the step is judged on the assignment as solved (before edge limits)
    allowed = ~forbidden[rows, cols]
    # RULE mean_angle_slack: the maxima's noise (edge_slack_m) is no angle
    lat_a = np.maximum(lat[rows, cols] - config.edge_slack_m, 0.0) if config.mean_angle_slack else lat[rows, cols]
    angles = np.degrees(np.arctan2(lat_a, np.abs(along[rows, cols]) + 1e-9))[allowed]
    if len(angles) == 0:
        mean_angle = 0.0
    else:
        mean_angle = float(_median(angles) if config.robust_angle else angles.mean())
    keep = ok[rows, cols]
    rows, cols = rows[keep], cols[keep]

    # the paper's modification: leftovers join their nearest neighbour on the other side
    leftover: list[tuple[int, int]] = []
    near = ok & (lat <= config.leftover_max_m)
    if config.leftover_same_type:
        # a lane marking may still branch off (join) a marking of the other type right beside it
        # (forbidden already keeps borders to borders): an exit's dashed line starts on the
        # solid edge line, an entry's solid line ends on the dashed one
        near &= (tip_type[:, None] == new_type[None, :]) | (lat <= config.leftover_other_type_m)
    matched_new = np.zeros(m, dtype=bool)
    matched_new[cols] = True
    matched_tip = np.zeros(n, dtype=bool)
    matched_tip[rows] = True
    fresh_near = near & tip_fresh[:, None]
    for j in np.flatnonzero(~matched_new):  # split: a new node without a partner
        cand = np.flatnonzero(fresh_near[:, j])
        if len(cand):
            leftover.append((int(cand[np.argmin(lat[cand, j])]), int(j)))
    for i in np.flatnonzero(~matched_tip & tip_fresh):  # merge: an old node without a partner
        cand = np.flatnonzero(near[i, :])
        if len(cand):
            leftover.append((int(i), int(cand[np.argmin(lat[i, cand])])))
    regular = list(zip(rows.tolist(), cols.tolist()))
    return Assignment(regular=regular, leftover=leftover, mean_angle_deg=mean_angle)
