"""Road changes followed by the live map: ``bag2map``'s code (``updates.follow.follow_map``) on the settled map.

The stitcher's map is the consensus of every drive, as ``bag2map``'s first build. Once the map has
settled (every drive mapped and stitched), :func:`follow_live` hands it with every stored drive to
``updates.follow.follow_map``, the function ``bag2map`` runs after its first build, with the same
settings: the drives are compared with the map place by place, the changes of the road confirmed
(markings moved, re-striped, gone or new, a lane closed or opened), the changed places (with their
tapers) mapped again from the drives after the change, aligned on the map's road borders and
spliced into it with their lane topology (``updates.splice``); the pieces they replace are retired
with the change's time as their valid-to.

What is live-specific is here: the result is a function of the drive set only, as the settled map
is, so a restart on the same store finds the same changes with the same ids (``DetectedChange.id``
hashes its places and time) and :func:`new_changes` tells the ones already announced (the
stitcher's history) from new ones. :class:`LiveChange` is what a ``hdmap_msgs/MapChange``
carries (:func:`live_changes`: its polygon and live tiles), with its JSON document for the history
store (:func:`change_to_dict`, :func:`change_from_dict`).
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull

from hdmap_core.model import Drive, HDMap
from hdmap_core.pipeline.config import PipelineConfig
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.detect import DetectedChange
from hdmap_core.updates.follow import FollowResult, RetiredFeature, follow_map
from hdmap_core.updates.places import PlaceKey

__all__ = [
    "LiveChange",
    "follow_live",
    "follow_loaded",
    "warm_up",
    "live_changes",
    "new_changes",
    "change_polygon",
    "change_to_dict",
    "change_from_dict",
]


@dataclass(frozen=True)
class LiveChange:
    """One confirmed change as announced (``hdmap_msgs/MapChange``) and kept in the history.

    Attributes:
        id: the change's stable id (``DetectedChange.id``).
        time_ns: the change point; the new road is valid from it, the retired pieces until it.
        kinds: geometry (markings moved), type (re-striped), marking_gone, marking_new.
        places: its places ``(ix, iy, side)`` of ``cell_m`` cells.
        cell_m: the places' cell size [m].
        polygon: (N, 2) convex hull of its places' cells [m], counter-clockwise.
        tiles: the live tiles ``(tx, ty)`` its cells touch.
        drive_ids: the drives in evidence (after the change).
        confidence: in (0, 1).
        retired_feature_ids: features of the map before it whose pieces inside it were retired.
        retired: the retired pieces (``RetiredFeature``).
        map_version: the first map version that follows it.
        confirmed_ns: wall time it was first confirmed.
    """

    id: int
    time_ns: int
    kinds: tuple[str, ...]
    places: tuple[PlaceKey, ...]
    cell_m: float
    polygon: np.ndarray
    tiles: tuple[tuple[int, int], ...]
    drive_ids: tuple[str, ...]
    confidence: float
    retired_feature_ids: tuple[int, ...]
    retired: tuple[RetiredFeature, ...]
    map_version: int
    confirmed_ns: int


def follow_live(
    consensus: HDMap,
    drives: Sequence[Drive],
    *,
    build: Callable[[Sequence[Drive]], HDMap],
    config: ChangeConfig = ChangeConfig(),
    workers: int = 1,
) -> FollowResult:
    """The live map as of the last of ``drives``: ``updates.follow.follow_map`` on ``consensus``.

    Args:
        consensus: the settled map of every drive (the stitcher's).
        drives: every stored drive (checked against the physical bounds by the mapper).
        build: drives -> map (the pipeline as the nodes are configured); called only when a
            change is confirmed, with the drives clipped to the changed places and their margin.
        config: change detection settings (as offline).
        workers: processes of the drives' comparison and the change tests (``follow_map``; forks:
            only from a process without native threads); the result is the same with any number.

    Returns:
        ``follow_map``'s result; its map is ``consensus`` itself when nothing changed (or there is
        nothing to compare: no drive, an empty map). The caller sets the map's version.
    """
    if not drives or not consensus.features:
        return FollowResult(consensus, (), (), consensus, None)
    return follow_map(consensus, drives, build=build, config=config, workers=workers)


def follow_loaded(
    consensus: HDMap,
    load: Callable[[], Sequence[Drive]],
    *,
    pipeline_config: PipelineConfig,
    workers: int = 1,
) -> FollowResult:
    """:func:`follow_live` on the drives ``load`` returns, the changed places rebuilt with
    ``build_map`` of ``pipeline_config``, both on ``workers`` processes as ``hdmap bag2map`` does:
    a job for a worker process (the stitcher's), which reads the drives itself."""
    drives = list(load())
    return follow_live(
        consensus, drives, build=functools.partial(_build, config=pipeline_config, workers=workers), workers=workers
    )


def warm_up() -> None:
    """Import what :func:`follow_loaded` needs (a worker process made before the map settles)."""
    import hdmap_core.pipeline.driver  # noqa: F401, PLC0415


def _build(drives: Sequence[Drive], *, config: PipelineConfig, workers: int) -> HDMap:
    from hdmap_core.pipeline.driver import build_map  # noqa: PLC0415

    return build_map(list(drives), config=config, workers=workers).map


def change_polygon(keys: Iterable[PlaceKey], cell_m: float) -> np.ndarray:
    """(N, 2) convex hull of the cells of ``keys``, counter-clockwise [m]."""
    ij = np.array(sorted({k[:2] for k in keys}), dtype=float).reshape(-1, 2)
    corners = np.concatenate([ij + d for d in ((0, 0), (1, 0), (1, 1), (0, 1))]) * cell_m
    if len(corners) < 3:
        return corners
    hull = ConvexHull(corners)
    return corners[hull.vertices]


def _tiles(keys: Iterable[PlaceKey], cell_m: float, tile_size_m: float) -> tuple[tuple[int, int], ...]:
    out = set()
    for ix, iy, _ in keys:
        x0, y0 = ix * cell_m, iy * cell_m
        for tx in range(int(np.floor(x0 / tile_size_m)), int(np.floor((x0 + cell_m - 1e-9) / tile_size_m)) + 1):
            for ty in range(int(np.floor(y0 / tile_size_m)), int(np.floor((y0 + cell_m - 1e-9) / tile_size_m)) + 1):
                out.add((tx, ty))
    return tuple(sorted(out))


def live_changes(result: FollowResult, *, tile_size_m: float, map_version: int, confirmed_ns: int) -> list[LiveChange]:
    """The changes of ``result`` as announced with map version ``map_version``."""
    cell_m = result.places.cell_m if result.places is not None else ChangeConfig().cell_m
    out = []
    for c in result.changes:
        keys = tuple(sorted(c.keys))
        retired = tuple(r for r in result.retired if r.change_id == c.id)
        out.append(
            LiveChange(
                id=int(c.id),
                time_ns=int(c.time_ns),
                kinds=tuple(c.kinds),
                places=keys,
                cell_m=float(cell_m),
                polygon=change_polygon(keys, cell_m),
                tiles=_tiles(keys, cell_m, tile_size_m),
                drive_ids=tuple(c.drives_after),
                confidence=float(c.confidence),
                retired_feature_ids=tuple(sorted({r.feature_id for r in retired})),
                retired=retired,
                map_version=int(map_version),
                confirmed_ns=int(confirmed_ns),
            )
        )
    return out


def new_changes(known: Iterable[int], changes: Sequence[DetectedChange]) -> list[DetectedChange]:
    """Those of ``changes`` not in the history ``known`` (ids)."""
    ids = set(known)
    return [c for c in changes if int(c.id) not in ids]


def change_to_dict(c: LiveChange) -> dict:
    """A JSON document of ``c`` (the stitcher's history store)."""
    return {
        "id": c.id,
        "time_ns": c.time_ns,
        "kinds": list(c.kinds),
        "places": [list(k) for k in c.places],
        "cell_m": c.cell_m,
        "polygon": np.asarray(c.polygon, dtype=float).tolist(),
        "tiles": [list(t) for t in c.tiles],
        "drive_ids": list(c.drive_ids),
        "confidence": c.confidence,
        "retired_feature_ids": list(c.retired_feature_ids),
        "retired": [
            {
                "feature_id": r.feature_id,
                "type": r.type,
                "points": np.asarray(r.points, dtype=float).tolist(),
                "change_id": r.change_id,
                "valid_from_ns": r.valid_from_ns,
                "valid_to_ns": r.valid_to_ns,
            }
            for r in c.retired
        ],
        "map_version": c.map_version,
        "confirmed_ns": c.confirmed_ns,
    }


def change_from_dict(d: dict) -> LiveChange:
    """The inverse of :func:`change_to_dict`."""
    return LiveChange(
        id=int(d["id"]),
        time_ns=int(d["time_ns"]),
        kinds=tuple(d["kinds"]),
        places=tuple((int(a), int(b), int(s)) for a, b, s in d["places"]),
        cell_m=float(d["cell_m"]),
        polygon=np.asarray(d["polygon"], dtype=float).reshape(-1, 2),
        tiles=tuple((int(a), int(b)) for a, b in d["tiles"]),
        drive_ids=tuple(d["drive_ids"]),
        confidence=float(d["confidence"]),
        retired_feature_ids=tuple(int(i) for i in d["retired_feature_ids"]),
        retired=tuple(
            RetiredFeature(
                int(r["feature_id"]),
                int(r["type"]),
                np.asarray(r["points"], dtype=float).reshape(-1, 2),
                int(r["change_id"]),
                int(r["valid_from_ns"]),
                int(r["valid_to_ns"]),
            )
            for r in d["retired"]
        ),
        map_version=int(d["map_version"]),
        confirmed_ns=int(d["confirmed_ns"]),
    )


def dumps(c: LiveChange) -> str:
    """``change_to_dict`` as a JSON string."""
    return json.dumps(change_to_dict(c))
