"""The map as it was before a change, where the consensus of every drive has taken the new road.

``follow_map`` compares every drive with the first map, the consensus of every drive, those
after a change too. Once enough drives after a change passed a place, that consensus holds the
new road there (or a blend of both: a 3 m move on 3.5 m lanes merged with the neighbour's old
line), and the drives before the change now disagree with the map while the drives after it
agree: the shares fall instead of growing, the map disagrees with its own drives before, or the
step is split between both sides below the smallest effect. ``detect`` refuses all of these by
design (a place where the map never agreed with its drives says nothing), so a change confirmed
after 3 drives through was lost again after 10 (re-striping and the 3 m shift, seed 2), and a
0.5 m shift read 0.43 m after 3 (the map already 0.07 m toward the new lines).

Here such places are found (``moved_consensus``: a step in time of a series, the place
evidence's or the edge line's move (an opened lane's new edge taken), between the medians of the
drives before and after, at least half the smallest effect, most drives after on its
side: no test of a change, only where one may hide), and the map is rebuilt there from the
drives before that step alone (``follow.follow_map``: cut as the follow cuts the drives after a
change, mapped with the margin of the local rebuild), aligned on the first map's borders and put
in (``as_before``). Detection then compares the drives with that map (again only those near
where it differs from the first map, ``follow.recompared``: the others' records are the same),
with all its rules: a badly localised drive confirms or refuses nothing it would not against the
first map, and where no change is confirmed the result is the first map as before.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Sequence, Set

import numpy as np

from hdmap_core.model import Drive, HDMap
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.detect import SERIES, series_value
from hdmap_core.updates.edges import MIN_EDGE_MOVE_M, EdgeEvidence
from hdmap_core.updates.evidence import PlaceEvidence
from hdmap_core.updates.places import PlaceKey, Places
from hdmap_core.updates.splice import border_shift, shifted

__all__ = ["moved_consensus", "consensus_step", "with_neighbours", "as_before"]

# Touching candidate places that count: a change the consensus took spans several (the bench's
# zones 7-10 places); a step at one or two places of a fleet without a change is the drives'
# scatter (4 places of 39 on esmini_e6mini_40_s1, one group of 2), and each costs a local build
# and a second comparison of the drives near it.
_MIN_GROUP = 3
# Of the drives after a step, at least this share lies on its side of the before median by a
# quarter of the smallest effect (a drive that missed the changed line may not).
_ON_SIDE = 0.75


def consensus_step(values: np.ndarray, *, min_effect: float, min_before: int, min_after: int) -> int | None:
    """Index of the first after-value of the earliest step of ``values`` (time ordered, no NaN),
    at least half of them before it (a map of fewer drives is a poorer consensus: it made false
    changes of its own), whose after median lies at least ``min_effect`` / 2 from the before
    median, with at least ``_ON_SIDE`` of the after-values on its side by ``min_effect`` / 4. The
    earliest: a step found late leaves drives of the new road in the map of the drives before it
    (a blend again), one found early only leaves out a few drives of the old road. None without
    one."""
    n = len(values)
    for k in range(max(min_before, (n + 1) // 2), n - min_after + 1):
        med = float(np.median(values[:k]))
        step = float(np.median(values[k:])) - med
        if abs(step) < min_effect / 2:
            continue
        shows = np.sign(step) * (values[k:] - med) >= min_effect / 4
        if np.count_nonzero(shows) >= math.ceil(_ON_SIDE * (n - k)):
            return k
    return None


def moved_consensus(
    evidence: Sequence[PlaceEvidence],
    config: ChangeConfig,
    *,
    skip: Set[PlaceKey] = frozenset(),
    edges: Sequence[EdgeEvidence] = (),
) -> dict[PlaceKey, int]:
    """Per place (not in ``skip``, e.g. already changed) where a series of the drives steps in
    time (``consensus_step``): the time of the first drive after its strongest step (over the
    series, by the step in units of the smallest effect). Candidates, not changes.

    The series: the place evidence's (``detect.SERIES``) and, with ``edges``, the edge line's move
    (``updates.edges``, smallest effect ``MIN_EDGE_MOVE_M``): once the consensus took an opened
    lane's new edge line at some places, the drives before the change read the old edge a lane
    inside it there and the drives after read none, and the lane opened was lost again (seed 1:
    confirmed after 3 drives through, not after 5)."""
    # per series its smallest effect and the drives it needs after a step; per place and series
    # the drives' (time, drive id, value)
    shares = (config.min_share, config.min_after_shares)
    params = [(config.min_shift_m, config.min_after) if name == "displacement" else shares for name in SERIES]
    params.append((MIN_EDGE_MOVE_M, config.min_after))
    rows: dict[PlaceKey, list[list[tuple[int, str, float]]]] = defaultdict(lambda: [[] for _ in params])
    for e in evidence:
        if e.key not in skip:
            for i, name in enumerate(SERIES):
                rows[e.key][i].append((e.time_ns, e.drive_id, series_value(e, name, config)))
    for x in edges:
        if x.key not in skip:
            rows[x.key][-1].append((x.time_ns, x.drive_id, x.move_m))
    out: dict[PlaceKey, int] = {}
    for key, per in rows.items():
        best: tuple[float, int] | None = None  # (step in smallest effects, time)
        for (smallest, min_after), series in zip(params, per):
            one = sorted((r for r in series if math.isfinite(r[2])), key=lambda r: (r[0], r[1]))
            vals = np.array([r[2] for r in one])
            k = consensus_step(vals, min_effect=smallest, min_before=config.min_before, min_after=min_after)
            if k is None:
                continue
            size = abs(float(np.median(vals[k:]) - np.median(vals[:k]))) / smallest
            if best is None or size > best[0]:
                best = (size, one[k][0])
        if best is not None:
            out[key] = best[1]
    return out


def with_neighbours(times: dict[PlaceKey, int], places: Places) -> dict[PlaceKey, int]:
    """``times`` as one time per group of at least ``_MIN_GROUP`` touching places (the lower
    median of theirs, as a change's time is that of its places: one place's step found late, past
    a drive that missed the changed line, would leave drives of the new road in its map), and the
    places next to each group along the road with it: the consensus there is a blend too, its step
    below half the smallest effect (the tapers, a place more drives of the old road passed).
    Smaller groups are left out."""
    out: dict[PlaceKey, int] = {}
    for group in places.components(times):
        if len(group) < _MIN_GROUP:
            continue
        ts = sorted(times[k] for k in group)
        t = ts[(len(ts) - 1) // 2]
        for k in group:
            out[k] = t
            for nb in places.neighbours(k):
                if nb not in times:
                    out[nb] = min(out.get(nb, t), t)
    return out


def as_before(
    first: HDMap,
    local: HDMap,
    drives: Sequence[Drive],
    places: Places,
    keys: set[PlaceKey],
    *,
    config: ChangeConfig = ChangeConfig(),
) -> HDMap:
    """``local`` (the map of the drives before the step in the places ``keys``) moved onto
    ``first``'s road borders along ``drives`` (those drives), as the rebuild of a changed place is
    (``updates.splice.border_shift``)."""
    return shifted(local, border_shift(local, first, drives, places, keys, config=config), places)
