"""Places for change detection: square cells of the plane, each split by driving direction.

A place is ``(ix, iy, side)``: the cell ``ix = floor(x / cell_m)``, ``iy = floor(y / cell_m)``
and the side of the cell's road axis a drive runs along (0: with it, 1: against it). The axis of
a cell is the mean direction of every pose in it, as an axis (headings taken modulo pi), so the
two carriageways of a divided road are two places and every drive of one carriageway falls in
the same one, whatever the road's heading.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from hdmap_core.geometry import point_headings
from hdmap_core.model import Drive, FeatureType, HDMap, MapFeature

__all__ = ["PlaceKey", "Places", "places_of", "PlacedMarking", "markings_in"]

PlaceKey = tuple[int, int, int]


@dataclass(frozen=True)
class Places:
    """The cells' road axes.

    Attributes:
        cell_m: cell size [m].
        axis: per cell ``(ix, iy)``, the road axis angle [rad] (modulo pi).
    """

    cell_m: float
    axis: dict[tuple[int, int], float]

    def keys(self, xy: np.ndarray, yaw: np.ndarray) -> list[PlaceKey]:
        """The place of each pose ``xy`` (N, 2) heading ``yaw`` (N,)."""
        ij = np.floor(np.asarray(xy, dtype=float) / self.cell_m).astype(np.int64).reshape(-1, 2)
        if len(ij) == 0:
            return []
        cells, inv = np.unique(ij, axis=0, return_inverse=True)
        ax = np.array([self.axis.get((int(i), int(j)), 0.0) for i, j in cells])[inv.reshape(-1)]
        side = (np.cos(np.asarray(yaw, dtype=float) - ax) < 0).astype(np.int64)
        return list(zip(ij[:, 0].tolist(), ij[:, 1].tolist(), side.tolist()))

    def keys_along(self, pts: np.ndarray) -> list[PlaceKey]:
        """The place of each point of a polyline ``pts`` (N >= 2, 2), heading along its tangent."""
        return self.keys(pts, point_headings(pts))

    def neighbours(self, key: PlaceKey) -> list[PlaceKey]:
        """The places of the 8 cells around ``key``'s cell, on the side of the same direction.

        The side flips where the axes of two cells point opposite ways (cos < 0)."""
        ix, iy, side = key
        a = self.axis.get((ix, iy), 0.0)
        out = []
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                c = (ix + dx, iy + dy)
                if (dx or dy) and c in self.axis:
                    flip = int(np.cos(self.axis[c] - a) < 0)
                    out.append((c[0], c[1], side ^ flip))
        return out

    def components(
        self,
        keys: Collection[PlaceKey],
        *,
        seeds: Iterable[PlaceKey] | None = None,
        joins: Callable[[PlaceKey, PlaceKey], bool] | None = None,
    ) -> list[list[PlaceKey]]:
        """The touching places of ``keys`` (connected along the road by :meth:`neighbours`), one
        list per component in the order found: grown from each of ``seeds`` (default: every key),
        in sorted order, that no earlier component holds. ``joins(seed, nb)``: whether neighbour
        ``nb`` may join the component grown from ``seed`` (default: any)."""
        out: list[list[PlaceKey]] = []
        seen: set[PlaceKey] = set()
        for key in sorted(keys if seeds is None else seeds):
            if key in seen:
                continue
            comp, stack = [], [key]
            seen.add(key)
            while stack:
                k = stack.pop()
                comp.append(k)
                for nb in self.neighbours(k):
                    if nb in keys and nb not in seen and (joins is None or joins(key, nb)):
                        seen.add(nb)
                        stack.append(nb)
            out.append(comp)
        return out


def places_of(drives: Iterable[Drive], *, cell_m: float) -> Places:
    """The road axis of every cell some pose of ``drives`` falls in."""
    sums: dict[tuple[int, int], np.ndarray] = {}
    for d in drives:
        xy = np.asarray(d.xy, dtype=float)
        if len(xy) == 0:
            continue
        ij = np.floor(xy / cell_m).astype(np.int64)
        yaw = np.asarray(d.yaw, dtype=float)
        c2, s2 = np.cos(2 * yaw), np.sin(2 * yaw)
        uniq, inv = np.unique(ij, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        cs = np.bincount(inv, weights=c2, minlength=len(uniq))
        ss = np.bincount(inv, weights=s2, minlength=len(uniq))
        for (i, j), c, s in zip(uniq, cs, ss):
            key = (int(i), int(j))
            acc = sums.setdefault(key, np.zeros(2))
            acc += (c, s)
    return Places(cell_m, {k: float(np.arctan2(v[1], v[0]) / 2.0) for k, v in sums.items()})


class PlacedMarking(NamedTuple):
    """A map's marking along the places: its ``feature_index`` in the map's features, the
    ``feature``, its ``points`` (N, 2), each point's place ``keys`` (``Places.keys_along``) and
    ``inside`` (N,): the point lies in one of the places asked for."""

    feature_index: int
    feature: MapFeature
    points: np.ndarray
    keys: list[PlaceKey]
    inside: np.ndarray


_MARKINGS = (int(FeatureType.SOLID), int(FeatureType.DASHED))


def markings_in(hdmap: HDMap, places: Places, keys: Collection[PlaceKey]) -> list[PlacedMarking]:
    """The markings (solid, dashed; >= 2 points) of ``hdmap`` with a point in the places ``keys``,
    in the map's order."""
    out = []
    for i, f in enumerate(hdmap.features):
        if int(f.type) not in _MARKINGS or len(f.points) < 2:
            continue
        pts = np.asarray(f.points, dtype=float)
        along = places.keys_along(pts)
        inside = np.array([k in keys for k in along], dtype=bool)
        if inside.any():
            out.append(PlacedMarking(i, f, pts, along, inside))
    return out
