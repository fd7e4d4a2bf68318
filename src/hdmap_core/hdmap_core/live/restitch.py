"""The live map moved in place after a fusion: the stitch's decisions kept, the geometry updated.

A drive fused into settled tiles (``live.fuse``) changes its tiles' estimates in three ways only:
matched maxima move laterally (``lateral_m``), their drive counts grow (``counts``), the passed
steps name the drive (``drive_ids``). Steps, cuts, maxima and their types stay. Re-connecting
those tiles (Sec. V) and re-stitching the whole map (Sec. VI) for that took most of the time from
the drive's arrival to its listing. Here the connection's and the stitch's decisions (which maxima
are feature nodes, their edges, trims, links, de-duplications, joins) are kept and only the feature
nodes move to the fused maxima: :func:`moved_graphs` per tile, then
``MapGraph.with_geometry`` and its export.

RULE: this is an approximation of the full re-stitch: a count or a lateral that moved can change
which maxima the connection keeps (support, separation) or a stitch decision (distance gates).
The fusion moves a maximum by ``(sample - x) / (n + 1)`` on lines of at least ``fuse.MIN_SUPPORT``
drives, a few centimetres, so the decisions rarely change; the stitcher makes the exact map of
the same tiles right after (a full rebuild) and the settle re-makes every tile, so the
approximation lives for one map version. ``test/core/live/test_restitch.py`` bounds the
difference to the full re-stitch of the same tiles (``MOVED_TOLERANCE_M``).

Pure numpy; no ROS.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from hdmap_core.graph.map_graph import MapGraph
from hdmap_core.graph.segment_graph import SegmentGraph, stable_uid
from hdmap_core.model import HDMap
from hdmap_core.segment_columns import SegmentColumns, segment_columns
from hdmap_core.steps import Segment, left_normal

if TYPE_CHECKING:
    from hdmap_core.pipeline.config import PipelineConfig

__all__ = [
    "moved_graphs",
    "same_structure",
    "stitch_tiles",
    "moved_map",
    "remap_ids",
    "raw_id_map",
    "MOVED_TOLERANCE_M",
]

# the moved map against the full re-stitch of the same tiles: mean distance of its feature points
# to the full map's lines of the same type [m] (what test_restitch asserts on fused fleets)
MOVED_TOLERANCE_M = 0.01


Estimate = Sequence[Segment] | SegmentColumns  # a tile's estimate: its segments, or these in columns


def _columns(est: Estimate) -> SegmentColumns:
    return est if isinstance(est, SegmentColumns) else segment_columns(est)


def _same_maxima(o: SegmentColumns, n: SegmentColumns) -> bool:
    """The same segments, steps (cuts) and maxima (types); positions and counts may differ."""
    return (
        o.pivots == n.pivots
        and np.array_equal(o.nsteps, n.nsteps)
        and np.array_equal(o.index, n.index)
        and np.array_equal(o.valid, n.valid)
        and np.array_equal(o.processed_before, n.processed_before)
        and all(np.array_equal(a, b, equal_nan=True) for a, b in ((o.s_m, n.s_m), (o.heading, n.heading)))
        and np.array_equal(o.width_m, n.width_m, equal_nan=True)
        and np.array_equal(o.midpoint, n.midpoint, equal_nan=True)
        and np.array_equal(o.k, n.k)
        and np.array_equal(o.types, n.types)
        and np.array_equal(np.isfinite(o.lateral_m), np.isfinite(n.lateral_m))
    )


def same_structure(old: Estimate, new: Estimate) -> bool:
    """Do two estimates of a tile hold the same segments, steps and maxima (types), so that the
    newer one only moved maxima and grew counts (a fusion)?"""
    return _same_maxima(_columns(old), _columns(new))


def _moved(g: SegmentGraph, c: SegmentColumns, a: int, b: int, ma: int) -> SegmentGraph | None:
    """``g`` (connected from an earlier estimate of its segment) with its feature nodes at the
    maxima of that segment in ``c`` (its steps ``a:b``, their maxima from ``ma``); None if a node
    is not found among them."""
    if g.n_nodes == 0:
        return g
    k = c.k[a:b]
    n_max = int(k.sum())
    if n_max == 0:
        return None
    row = np.repeat(np.arange(b - a), k)  # the step of each maximum
    slot = np.arange(n_max) - np.repeat(np.cumsum(k) - k, k)
    uid = stable_uid("feature:" + g.pivot_id, c.index[a:b][row], slot)
    order = np.argsort(uid, kind="stable")
    pos = np.minimum(np.searchsorted(uid[order], g.node_uid), len(uid) - 1)
    rows = order[pos]
    mx = slice(ma, ma + n_max)
    if not np.array_equal(uid[rows], g.node_uid) or not np.array_equal(c.types[mx][rows], g.node_type):
        return None
    step = row[rows]
    nrm = left_normal(c.heading[a:b][step]).reshape(-1, 2)
    xy = c.midpoint[a:b][step] + c.lateral_m[mx][rows][:, None] * nrm
    if not np.isfinite(xy).all():
        return None
    used = np.isin(c.index[a:b], g.topo_step)  # the steps of the graph's topology nodes
    d0 = int(c.n_drives[:a].sum())
    entry_step = np.repeat(np.arange(b - a), c.n_drives[a:b])
    picked = c.drive_index[d0 : d0 + len(entry_step)][used[entry_step]]
    drive_ids = sorted({c.drive_names[i] for i in picked.tolist()} | set(g.drive_ids))
    return replace(g, node_xy=xy, node_count=c.counts[mx][rows], node_std=c.std_m[mx][rows], drive_ids=tuple(drive_ids))


def moved_graphs(graphs: Sequence[SegmentGraph], old: Estimate, new: Estimate) -> list[SegmentGraph] | None:
    """A tile's segment graphs with their feature nodes moved to a newer estimate's maxima.

    Args:
        graphs: ``tiles.connect_tile`` of ``old`` (one graph per segment with steps, in order).
        old: the estimate the graphs were connected from (segments, or in columns).
        new: the newer estimate of the same tile (segments, or in columns: a batch message's).

    Returns:
        The graphs (same keys, nodes, edges) with node positions, counts and uncertainties of
        ``new``; None when ``new`` is not ``old`` with moved maxima (:func:`same_structure`):
        then the tile must be connected again.
    """
    o, c = _columns(old), _columns(new)
    if not _same_maxima(o, c):
        return None
    with_steps = np.flatnonzero(c.nsteps > 0).tolist()
    if len(with_steps) != len(graphs):
        return None
    step0 = np.concatenate([[0], np.cumsum(c.nsteps)]).tolist()
    max0 = np.concatenate([[0], np.cumsum(c.k)]).tolist()
    out = []
    for g, j in zip(graphs, with_steps, strict=True):
        if (g.pivot_drive or g.pivot_id) != c.pivots[j]:
            return None
        a, b = step0[j], step0[j + 1]
        m = _moved(g, c, a, b, max0[a])
        if m is None:
            return None
        out.append(m)
    return out


def stitch_tiles(
    graphs: Sequence[SegmentGraph], *, pipeline_config: PipelineConfig, drive_ids: Iterable[str] = ()
) -> tuple[HDMap, MapGraph]:
    """``tiles.stitch_graphs`` (the same map), with the stitched graph kept for :func:`moved_map`."""
    mg = MapGraph(list(graphs), config=pipeline_config.stitching)
    return replace(mg.to_hdmap(keep_plan=True), drive_ids=tuple(sorted(set(drive_ids)))), mg


def moved_map(mg: MapGraph, graphs: Sequence[SegmentGraph], *, drive_ids: Iterable[str] = ()) -> tuple[HDMap, MapGraph]:
    """The map of ``mg`` with ``graphs`` (:func:`moved_graphs`) in place of theirs, every stitch
    decision kept (``MapGraph.with_geometry``), and that map graph. RULE: the export's decisions
    are kept too (``MapGraph.to_hdmap_planned``: the same polylines of the same nodes, moved) when
    ``mg`` was exported with its plan (:func:`stitch_tiles`): the export of the whole map was the
    largest part of a fast update's CPU; a decision of it that the moved lines would flip (a length
    or count threshold) is made again by the full rebuild that follows."""
    moved = mg.with_geometry(graphs)
    hd = moved.to_hdmap_planned() if moved.export_plan is not None else moved.to_hdmap(keep_plan=True)
    return replace(hd, drive_ids=tuple(sorted(set(drive_ids)))), moved


def raw_id_map(raw: HDMap, published: HDMap) -> dict[int, int]:
    """The ids a stitched map's features got when published (``tiles.carry_over_ids`` keeps the
    order): raw feature id -> published id."""
    return {int(a.id): int(b.id) for a, b in zip(raw.features, published.features, strict=True)}


def remap_ids(raw: HDMap, ids: Mapping[int, int]) -> HDMap | None:
    """The features of ``raw`` renamed by ``ids`` (raw id -> id, :func:`raw_id_map` of the
    previous version made from the same stitch decisions), references too; None when a feature
    is not in ``ids`` (then carry the ids over by shape)."""
    if any(int(f.id) not in ids for f in raw.features):
        return None
    if len(set(ids[int(f.id)] for f in raw.features)) != len(raw.features):
        return None
    if all(ids[int(f.id)] == int(f.id) for f in raw.features):
        return raw  # every id kept: nothing to rename

    def _r(seq) -> tuple[int, ...]:
        return tuple(ids.get(int(i), int(i)) for i in seq)

    features = tuple(
        replace(f, id=ids[int(f.id)], predecessors=_r(f.predecessors), successors=_r(f.successors))
        for f in raw.features
    )
    changed = {k for k, v in ids.items() if k != v}
    topology = tuple(
        replace(t, features=_r(t.features)) if any(int(i) in changed for i in t.features) else t for t in raw.topology
    )
    return replace(raw, features=features, topology=topology)
