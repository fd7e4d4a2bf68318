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


class _Flat:
    """The steps of one segment as arrays: per step (index, valid, processed before, s, midpoint,
    heading, width, number of maxima), per maximum (step index, slot, lateral, type, count, std)."""

    def __init__(self, seg: Segment) -> None:
        st = seg.steps
        self.index = np.array([int(s.index) for s in st], dtype=np.int64)
        self.flags = np.array([(bool(s.valid), bool(s.processed_before)) for s in st], dtype=bool).reshape(-1, 2)
        self.pose = np.array([(float(s.s_m), float(s.heading), float(s.width_m)) for s in st], dtype=float).reshape(
            -1, 3
        )
        self.mid = np.array([np.asarray(s.midpoint, dtype=float).reshape(2) for s in st]).reshape(-1, 2)
        self.k = np.array([np.asarray(s.lateral_m).size for s in st], dtype=np.int64)
        cat = np.concatenate
        self.lat = cat([np.asarray(s.lateral_m, dtype=float).reshape(-1) for s in st]) if st else np.zeros(0)
        self.typ = cat([np.asarray(s.types, dtype=np.int64).reshape(-1) for s in st]) if st else np.zeros(0, np.int64)
        self.cnt = cat([np.asarray(s.counts, dtype=np.int64).reshape(-1) for s in st]) if st else np.zeros(0, np.int64)
        self.std = cat([np.asarray(s.std_m, dtype=float).reshape(-1) for s in st]) if st else np.zeros(0)
        self.row = np.repeat(np.arange(len(st)), self.k)  # the step of each maximum
        self.slot = np.arange(len(self.lat)) - np.repeat(np.cumsum(self.k) - self.k, self.k)

    def same_maxima(self, other: _Flat) -> bool:
        """The same steps (cuts) with the same maxima (types; positions and counts may differ)."""
        return (
            np.array_equal(self.index, other.index)
            and np.array_equal(self.flags, other.flags)
            and np.array_equal(self.pose, other.pose, equal_nan=True)
            and np.array_equal(self.mid, other.mid, equal_nan=True)
            and np.array_equal(self.k, other.k)
            and len(self.typ) == len(other.typ)
            and np.array_equal(self.typ, other.typ)
            and np.array_equal(np.isfinite(self.lat), np.isfinite(other.lat))
        )


def same_structure(old: Sequence[Segment], new: Sequence[Segment]) -> bool:
    """Do two estimates of a tile hold the same segments, steps and maxima (types), so that the
    newer one only moved maxima and grew counts (a fusion)?"""
    if len(old) != len(new):
        return False
    for so, sn in zip(old, new, strict=True):
        if so.pivot_id != sn.pivot_id or len(so.steps) != len(sn.steps):
            return False
        if not _Flat(so).same_maxima(_Flat(sn)):
            return False
    return True


def _moved(g: SegmentGraph, seg: Segment, f: _Flat) -> SegmentGraph | None:
    """``g`` (connected from an earlier estimate of ``seg``) with its feature nodes at the
    maxima of ``seg`` (``f``: its arrays); None if a node is not found among them."""
    if g.n_nodes == 0:
        return g
    if len(f.lat) == 0:
        return None
    uid = stable_uid("feature:" + g.pivot_id, f.index[f.row], f.slot)
    order = np.argsort(uid, kind="stable")
    pos = np.minimum(np.searchsorted(uid[order], g.node_uid), len(uid) - 1)
    rows = order[pos]
    if not np.array_equal(uid[rows], g.node_uid) or not np.array_equal(f.typ[rows], g.node_type):
        return None
    step = f.row[rows]
    nrm = left_normal(f.pose[step, 1]).reshape(-1, 2)
    xy = f.mid[step] + f.lat[rows][:, None] * nrm
    if not np.isfinite(xy).all():
        return None
    used = set(np.unique(g.topo_step).tolist())
    drive_ids = sorted({d for st in seg.steps if int(st.index) in used for d in st.drive_ids} | set(g.drive_ids))
    return replace(g, node_xy=xy, node_count=f.cnt[rows], node_std=f.std[rows], drive_ids=tuple(drive_ids))


def moved_graphs(
    graphs: Sequence[SegmentGraph], old: Sequence[Segment], new: Sequence[Segment]
) -> list[SegmentGraph] | None:
    """A tile's segment graphs with their feature nodes moved to a newer estimate's maxima.

    Args:
        graphs: ``tiles.connect_tile`` of ``old`` (one graph per segment with steps, in order).
        old: the estimate the graphs were connected from.
        new: the newer estimate of the same tile.

    Returns:
        The graphs (same keys, nodes, edges) with node positions, counts and uncertainties of
        ``new``; None when ``new`` is not ``old`` with moved maxima (:func:`same_structure`):
        then the tile must be connected again.
    """
    if len(old) != len(new):
        return None
    pairs = []
    for so, sn in zip(old, new, strict=True):
        if so.pivot_id != sn.pivot_id or len(so.steps) != len(sn.steps):
            return None
        fn = _Flat(sn)
        if not _Flat(so).same_maxima(fn):
            return None
        if sn.steps:
            pairs.append((sn, fn))
    if len(pairs) != len(graphs):
        return None
    out = []
    for g, (seg, fn) in zip(graphs, pairs, strict=True):
        if (g.pivot_drive or g.pivot_id) != seg.pivot_id:
            return None
        m = _moved(g, seg, fn)
        if m is None:
            return None
        out.append(m)
    return out


def stitch_tiles(
    graphs: Sequence[SegmentGraph], *, pipeline_config: PipelineConfig, drive_ids: Iterable[str] = ()
) -> tuple[HDMap, MapGraph]:
    """``tiles.stitch_graphs`` (the same map), with the stitched graph kept for :func:`moved_map`."""
    mg = MapGraph(list(graphs), config=pipeline_config.stitching)
    return replace(mg.to_hdmap(), drive_ids=tuple(sorted(set(drive_ids)))), mg


def moved_map(mg: MapGraph, graphs: Sequence[SegmentGraph], *, drive_ids: Iterable[str] = ()) -> tuple[HDMap, MapGraph]:
    """The map of ``mg`` with ``graphs`` (:func:`moved_graphs`) in place of theirs, every stitch
    decision kept (``MapGraph.with_geometry``), and that map graph."""
    moved = mg.with_geometry(graphs)
    return replace(moved.to_hdmap(), drive_ids=tuple(sorted(set(drive_ids)))), moved


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
