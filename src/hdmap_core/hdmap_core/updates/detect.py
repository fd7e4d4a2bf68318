"""Confirming a change of the road per place, with a change point in time.

Per place, the drives' evidence (``updates.evidence``) in time order gives four series: the
markings' displacement against the borders, and the shares of wrong-type, missed and extra
markings. For each series, a change point is the earliest split into "before" (>= ``min_before``
drives) and "after" (>= ``min_after`` drives) such that

* every after-drive lies on the same side of the before median, at least half the smallest
  effect away, and within 3 before-spreads (or half the smallest effect) of the after mean (one
  odd drive cannot hide among them, nor can one stray drive make a change); for the shares
  up to one in ``DISSENT_SHARE`` after-drives (not the first) may fall short of that side and
  are left out of the tests below: else one later drive that missed or misread the changed line
  at the place breaks the true split, and the later splits have the changed drives among their
  before drives (a re-striping confirmed after 3 drives was lost after 5, seed 2). Not for the
  displacement, which does not depend on the drive's localisation (markings against borders):
  allowing it there moved the split of a 1.5 m shift and cost its zone 4 points of recall
  after 10;
* for the shares (type, missed, extra): at least ``min_after_shares`` after-drives, the share
  grows, every after-drive lies beyond the before drives' 90th percentile and none below their
  maximum (a share is 0 for most drives and large for the few that misread a line: its 90th
  percentile is 0 or one of those few, so after-drives that misread as one before did are no
  change), every after-drive's share is at least ``min_share_drive`` above the before median (a
  changed line is one of the two markings near a drive in its lane: about half its points or all
  of them; a drive misreading a few pieces of a line reads less), the spread is their standard
  deviation,
  and the before median is below ``max_share_before`` (where the map disagrees with its
  own drives already, e.g. sparse ramps, a share says nothing of a change);
* the after mean is at least the smallest effect (``min_shift_m`` / ``min_share``) away from the
  before median, and that is at least ``z_min`` standard errors (the before spread, robust,
  with a floor, over both groups' sizes).

A drive that is badly localised is off in its markings and borders alike: its displacement stays
near 0, so it confirms nothing. Confirmed places of one direction that touch are one change; it
grows along the road into neighbouring places where the drives after its time (even one) show the
same effect: the tapers and the stretches fewer drives passed (carried by the drives in evidence:
one of them must show the effect there, and no drive after the change the opposite).

The places of one change agree on its time (the median change point of its places of the kind
most of them show, unless, for a share's kind, another of their change points is the split at
which more of them show the change: a drive of the old road that missed the line at some places
is no drive after it).
A place of another kind whose own change point lies before that time stays only if its series
also shows its change with the split at that time; else it is left out, with
the places grown from it: its drives after include drives that passed before the change, and as
one of the change's kinds it would make a shift something else (a one-place wrong-type step of
two drives a day before a 1.0 m shift and one after it made the shift a `geometry` and `type`
change, for which ``updates.unseen`` does not model the lines no drive after it saw).
"""

from __future__ import annotations

import hashlib
import math
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from hdmap_core.parallel import map_balanced
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.evidence import PlaceEvidence
from hdmap_core.updates.places import PlaceKey, Places

__all__ = [
    "PlaceChange",
    "DetectedChange",
    "change_point",
    "detect_changes",
    "grow_changes",
    "drive_scatter",
    "series_spread",
    "SERIES",
    "series_value",
    "DISSENT_SHARE",
]

#: Of the shares (wrong type, missed, extra), at most one in this many drives after a change
#: point may not show the change (a drive that missed or misread the changed line there): with
#: fewer than this many after it, every one must. The displacement allows none.
DISSENT_SHARE = 4

#: The evidence series tested, with the kind of change each reveals.
SERIES = {"displacement": "geometry", "wrong_type": "type", "missed": "marking_gone", "extra": "marking_new"}
_SERIES_OF = {kind: name for name, kind in SERIES.items()}  # a change kind's series


@dataclass(frozen=True)
class PlaceChange:
    """A change confirmed at one place.

    Attributes:
        key: the place.
        kind: ``geometry``, ``type``, ``marking_gone`` or ``marking_new``.
        time_ns: start of the first drive after the change point (the road had changed by then).
        last_before_ns: start of the last drive before it.
        effect: after mean - before median of the series (m or share).
        z: that in standard errors.
        drives_before, drives_after: the drives on each side.
        extended: True for a place joined along the road, not confirmed on its own.
    """

    key: PlaceKey
    kind: str
    time_ns: int
    last_before_ns: int
    effect: float
    z: float
    drives_before: tuple[str, ...]
    drives_after: tuple[str, ...]
    extended: bool = False


@dataclass(frozen=True)
class DetectedChange:
    """Touching changed places of one direction: one change of the road.

    Attributes:
        id: stable (a hash of its places and time).
        time_ns: the change point: the (lower) median of the change points of its places of the
            kind most of them show (one place's early change point does not move it), or for a
            share's kind the one of them at which more of those places show the change
            (``_main_kind_time``).
        kinds: the kinds seen.
        places: its places.
        drives_after: drives in evidence (after the change).
        confidence: in (0, 1): 1 - 1/z of the strongest confirmed place.
    """

    id: int
    time_ns: int
    kinds: tuple[str, ...]
    places: tuple[PlaceChange, ...]
    drives_after: tuple[str, ...]
    confidence: float

    @property
    def keys(self) -> set[PlaceKey]:
        return {p.key for p in self.places}


def series_value(e: PlaceEvidence, name: str, config: ChangeConfig) -> float:
    """The value of series ``name`` (``SERIES``) of one drive at one place; NaN: too few points."""
    if name == "displacement":
        return e.displacement_m
    if name == "wrong_type":
        return e.n_wrong_type / e.n_typed if e.n_typed >= config.min_points else math.nan
    if name == "missed":
        return e.n_missed / e.n_map_near if e.n_map_near >= config.min_points else math.nan
    return e.n_extra / e.n_drive_near if e.n_drive_near >= config.min_points else math.nan


def change_point(
    values: np.ndarray,
    *,
    min_effect: float,
    floor: float,
    z_min: float,
    min_before: int,
    min_after: int,
    heavy_tails: bool = False,
    noise: np.ndarray | None = None,
    fleet_spread: float = 0.0,
    min_each: float = 0.0,
    split: int | None = None,
) -> tuple[int, float, float] | None:
    """(index of the first after-value, effect, z) of the earliest change point of ``values``
    (time ordered, no NaN), or None (module docstring).

    ``floor`` is the smallest spread assumed. ``fleet_spread``: the fleet's own spread of the
    series (``series_spread``), the least spread the standard error is computed with, so that a
    map or a fleet whose drives scatter widely everywhere (a map without offset correction)
    needs a larger step. Every after-value must lie beyond
    the before values' 90th (10th) percentile: the drives after disagree with the drives before
    themselves, not only with the map. ``heavy_tails``: and none below their maximum (above their
    minimum; a tie counts, a share of 1 of 2 points is common), and the before spread is the
    standard deviation, not the median absolute deviation (a share of wrong types is 0 for most
    drives and large for the few that misread a line: a robust spread would call those few a
    change, and the 90th percentile is one of them or 0), and up to one in ``DISSENT_SHARE``
    after-values (not the first) may fall short of the step and are left out; with
    fewer than 10 before-values the larger of that and their standard deviation (the median
    absolute deviation of 3 values is the smaller half-gap). ``noise`` (per value): each drive's
    own scatter over the road (``drive_scatter``); an after-drive must lie at least twice its
    own scatter from the before median (a drive off everywhere says nothing of this place).
    ``min_each``: every after-value lies at least this far from the before median (a share: a
    changed line is at least half the markings near a drive). ``split``: only the split with
    that many values before it is tested."""
    n = len(values)
    splits = range(min_before, n - min_after + 1)
    for k in splits if split is None else [split] if split in splits else []:
        before, after = values[:k], values[k:]
        med = float(np.median(before))
        dev = after - med
        need = max(min_effect / 2, min_each) if noise is None else np.maximum(min_effect / 2, 2.0 * noise[k:])
        if not (np.all(dev >= need) or np.all(dev <= -need)):
            if not heavy_tails:
                continue
            # a share: up to one in DISSENT_SHARE after-drives may fall short (a drive that
            # missed or misread the changed line there), never the first; the rest are tested
            side = 1.0 if dev[0] > 0 else -1.0
            shows = side * dev >= need
            if not shows[0] or np.count_nonzero(~shows) > len(after) // DISSENT_SHARE:
                continue
            after = after[shows]
        effect = float(np.mean(after)) - med
        # the before values' 90th / 10th percentile by nearest rank: with fewer than 10 before,
        # their largest / smallest (an interpolated percentile of 3 values lies inside them); never
        # inside the interpolated percentile
        ranked = np.sort(before)
        skip = (k - 1) // 10
        hi, lo = float(ranked[k - 1 - skip]), float(ranked[skip])
        beyond = bool(np.all(after > hi) if effect > 0 else np.all(after < lo))
        if heavy_tails:  # a share: and none below the largest before (a tie counts: 1 of 2 points)
            beyond = beyond and bool(np.all(after >= ranked[-1]) if effect > 0 else np.all(after <= ranked[0]))
        if not beyond:
            continue  # an after-drive lies among the before-drives: their own scatter
        if heavy_tails:
            spread = max(floor, float(np.std(before)))
        else:
            spread = max(floor, 1.4826 * float(np.median(np.abs(before - med))))
            if k < 10:
                spread = max(spread, float(np.std(before, ddof=1)))
        if np.any(np.abs(after - np.mean(after)) > max(3.0 * spread, min_effect / 2)):
            continue  # the after-drives disagree: a drive of the old road among them, or noise
        z = abs(effect) / (max(spread, fleet_spread) * math.sqrt(1.0 / k + 1.0 / len(after)))
        if abs(effect) >= min_effect and z >= z_min:
            return k, effect, z
    return None


def series_spread(by_place: dict[PlaceKey, list[PlaceEvidence]], name: str, config: ChangeConfig) -> float:
    """The fleet's own per-drive spread of series ``name``: the median over places (with at least
    ``2 * min_before`` drives) of the robust spread (1.4826 MAD) of all drives there. A change
    touches few places and few drives, so it barely moves this; a poor map or a badly localised
    fleet raises it everywhere. 0 when no place has enough drives."""
    spreads = []
    for rows in by_place.values():
        v = np.array([series_value(e, name, config) for e in rows])
        v = v[np.isfinite(v)]
        if len(v) >= 2 * config.min_before:
            spreads.append(1.4826 * float(np.median(np.abs(v - np.median(v)))))
    return float(np.median(spreads)) if spreads else 0.0


def drive_scatter(evidence: Sequence[PlaceEvidence]) -> dict[str, float]:
    """Per drive, the scatter of its displacement from place to place along it: the robust spread
    (1.4826 MAD / sqrt 2) of the differences between consecutive places it gave one in. A
    badly localised drive whose markings and borders disagree differently in every place scatters;
    a change of the road moves a block of consecutive places, which adds two steps (its ends)
    and leaves the rest. ``evidence`` of one drive must come in its order along the drive (as
    ``drive_evidence`` gives it). 0 for a drive with fewer than 5 places."""
    vals: dict[str, list[float]] = defaultdict(list)
    for e in evidence:
        if math.isfinite(e.displacement_m):
            vals[e.drive_id].append(e.displacement_m)
    out = {}
    for d, v in vals.items():
        steps = np.diff(np.asarray(v))
        out[d] = 1.4826 * float(np.median(np.abs(steps))) / math.sqrt(2.0) if len(v) >= 5 else 0.0
    return out


def _series_change(
    rows: list[PlaceEvidence],
    key: PlaceKey,
    name: str,
    config: ChangeConfig,
    spreads: dict[str, float],
    scatter: dict[str, float],
    at_ns: int | None = None,
) -> PlaceChange | None:
    """The change of series ``name`` at one place (its evidence in time order), if any: at its
    earliest change point, or with ``at_ns`` at the split there only (the drives before that
    time before it)."""
    vals = np.array([series_value(e, name, config) for e in rows])
    ok = np.isfinite(vals)
    used = [e for e, good in zip(rows, ok) if good]
    geometric = name == "displacement"
    found = change_point(
        vals[ok],
        min_effect=config.min_shift_m if geometric else config.min_share,
        floor=config.displacement_floor_m if geometric else config.share_floor,
        z_min=config.z_min,
        min_before=config.min_before,
        min_after=config.min_after if geometric else config.min_after_shares,
        heavy_tails=not geometric,
        noise=np.array([scatter.get(e.drive_id, 0.0) for e in used]) if geometric else None,
        fleet_spread=spreads.get(name, 0.0),
        min_each=0.0 if geometric else config.min_share_drive,
        split=None if at_ns is None else sum(e.time_ns < at_ns for e in used),
    )
    if found is None:
        return None
    k, effect, z = found
    before_med = float(np.median(vals[ok][:k]))
    if not geometric and (effect <= 0 or before_med > config.max_share_before):
        return None  # fewer wrong / missed / extra, or a place the map never agreed on
    if geometric and abs(before_med) > config.min_shift_m:
        return None  # the map lies off its own drives before: a poor consensus there, no evidence
    return PlaceChange(
        key,
        SERIES[name],
        used[k].time_ns,
        used[k - 1].time_ns,
        effect,
        z,
        tuple(e.drive_id for e in used[:k]),
        tuple(e.drive_id for e in used[k:]),
    )


def _confirm(
    rows: list[PlaceEvidence],
    key: PlaceKey,
    config: ChangeConfig,
    spreads: dict[str, float],
    scatter: dict[str, float],
) -> PlaceChange | None:
    """The strongest series' change at one place (its evidence in time order), if any;
    ``spreads``: the fleet's spread per series (``series_spread``); ``scatter``: each drive's
    own (``drive_scatter``), for the displacement."""
    best: PlaceChange | None = None
    for name in SERIES:
        cand = _series_change(rows, key, name, config, spreads, scatter)
        if cand is not None and (best is None or cand.z > best.z):
            best = cand
    return best


def _extends(rows: list[PlaceEvidence], key: PlaceKey, change: PlaceChange, config: ChangeConfig) -> PlaceChange | None:
    """``key`` joined to a neighbouring ``change`` when a drive in evidence of it (one is enough)
    shows the same kind of effect here, at least half the smallest, against this place's drives
    before, and no drive after shows the opposite."""
    name = _SERIES_OF[change.kind]
    vals = np.array([series_value(e, name, config) for e in rows])
    t = np.array([e.time_ns for e in rows])
    ok = np.isfinite(vals)
    before = vals[ok & (t < change.time_ns)]
    if len(before) < config.min_before:
        return None
    med = float(np.median(before))
    need = (config.min_shift_m if name == "displacement" else config.min_share) / 2
    sign = 1.0 if change.effect > 0 else -1.0
    carriers = set(change.drives_after)
    showing, after_ids = [], []
    for e, v, good in zip(rows, vals, ok):
        if not good or e.time_ns < change.time_ns:
            continue
        after_ids.append(e.drive_id)
        dev = (v - med) * sign
        if dev <= -need:
            return None
        if dev >= need and e.drive_id in carriers:
            showing.append((e.drive_id, v - med))
    if not showing:
        return None
    return PlaceChange(
        key,
        change.kind,
        change.time_ns,
        change.last_before_ns,
        float(np.mean([d for _, d in showing])),
        math.nan,
        tuple(e.drive_id for e, good in zip(rows, ok) if good and e.time_ns < change.time_ns),
        tuple(d for d, _ in showing),
        extended=True,
    )


def grow_changes(
    confirmed: dict[PlaceKey, PlaceChange],
    places: Places,
    extend: Callable[[PlaceKey, PlaceChange], PlaceChange | None],
) -> dict[PlaceKey, PlaceChange]:
    """``confirmed`` grown along the road, breadth first: a neighbouring place (same driving
    direction) joins with ``extend(neighbour, change of the place it neighbours)`` unless that
    is None (the displacement and shares here, the edge line's move in ``updates.edges``)."""
    changed = dict(confirmed)
    frontier = sorted(confirmed)
    while frontier:
        nxt = []
        for key in frontier:
            for nb in places.neighbours(key):
                if nb in changed:
                    continue
                ext = extend(nb, changed[key])
                if ext is not None:
                    changed[nb] = ext
                    nxt.append(nb)
        frontier = sorted(nxt)
    return changed


def _components(changed: dict[PlaceKey, PlaceChange], places: Places) -> list[list[PlaceChange]]:
    """Touching places of ``changed`` (connected components along the road) that hold a place
    confirmed on its own, each sorted by key."""
    own = [k for k, c in changed.items() if not c.extended]
    return [[changed[k] for k in sorted(comp)] for comp in places.components(changed, seeds=own)]


def _main_kind_time(
    comp: Sequence[PlaceChange],
    by_place: dict[PlaceKey, list[PlaceEvidence]],
    config: ChangeConfig,
    spreads: dict[str, float],
    scatter: dict[str, float],
) -> tuple[str, int]:
    """The kind most of ``comp``'s own places show (geometry on a tie) and the change's time: the
    (lower) median change point of those places, unless they are of a share's kind (type,
    marking gone or new) and another of their change points is the split at which more of them
    show the change (``_series_change`` with the split forced there; the earliest such).

    RULE: a drive of the old road that missed the line at one place (a dropout) puts that place's
    change point before it; taken as the change's time, it counts among the drives after the
    change and its old lines are rebuilt into the changed places (a removed dashed divider kept
    over the whole zone after 3 drives, seed 1: precision 65 %). At the time most places agree
    on, it is a drive before the change. Not for a shift: a dropout fakes no displacement, and
    the displacement allows no dissenting drive after a split, so a drive after the shift that
    read less of it at some places moved the time past it (1.5 m shift after 10, seed 0: zone
    recall 97.3 -> 94.0 %)."""
    own = [p for p in comp if not p.extended]
    kinds = [p.kind for p in own]
    main = max(set(kinds), key=lambda k: (kinds.count(k), k == "geometry"))
    mains = [p for p in own if p.kind == main]
    times = sorted(p.time_ns for p in mains)
    t = times[(len(times) - 1) // 2]
    candidates = sorted(set(times))
    if len(candidates) > 1 and main != "geometry":
        name = _SERIES_OF[main]

        def shown(at: int) -> int:
            return sum(
                p.time_ns == at
                or _series_change(by_place[p.key], p.key, name, config, spreads, scatter, at_ns=at) is not None
                for p in mains
            )

        counts = {c: shown(c) for c in candidates}
        best = max(counts.values())
        if counts[t] < best:
            t = min(c for c in candidates if counts[c] == best)
    return main, t


def detect_changes(
    evidence: Sequence[PlaceEvidence], places: Places, *, config: ChangeConfig = ChangeConfig(), workers: int = 1
) -> list[DetectedChange]:
    """The changes of the road the ``evidence`` confirms (module docstring), in time order.

    ``workers``: processes the places' change-point tests are shared out over
    (``parallel.map_balanced``, by the square of their drives: each test tries every split of
    the place's series); each place is tested on its own, so the changes are the one-process ones."""
    by_place: dict[PlaceKey, list[PlaceEvidence]] = defaultdict(list)
    for e in evidence:
        by_place[e.key].append(e)
    for rows in by_place.values():
        rows.sort(key=lambda e: (e.time_ns, e.drive_id))
    spreads = {name: series_spread(by_place, name, config) for name in SERIES}
    scatter = drive_scatter(evidence)
    keys = sorted(by_place)
    tested = map_balanced(
        lambda i: _confirm(by_place[keys[i]], keys[i], config, spreads, scatter),
        [float(len(by_place[k])) ** 2 for k in keys],
        workers,
    )
    confirmed = {key: got for key, got in zip(keys, tested) if got is not None}
    # Grow along the road from the confirmed places.
    changed = grow_changes(
        confirmed, places, lambda nb, c: _extends(by_place[nb], nb, c, config) if nb in by_place else None
    )
    # Touching places of one change: connected components (the drives in evidence). Its places
    # agree on its time: a place of another kind whose change point lies before it stays only
    # if its series shows the change with the split at that time too (module docstring)
    comps: list[tuple[list[PlaceChange], int]] = []  # each change's places and time
    for comp in _components(changed, places):
        main, t = _main_kind_time(comp, by_place, config, spreads, scatter)
        early = {
            (p.kind, p.time_ns)
            for p in comp
            if not p.extended
            and p.kind != main
            and p.time_ns < t
            and _series_change(by_place[p.key], p.key, _SERIES_OF[p.kind], config, spreads, scatter, at_ns=t) is None
        }
        if not early:
            comps.append((comp, t))
            continue
        # left out with the places grown from them (their kind and time)
        for sub in _components({p.key: p for p in comp if (p.kind, p.time_ns) not in early}, places):
            comps.append((sub, _main_kind_time(sub, by_place, config, spreads, scatter)[1]))
    out: list[DetectedChange] = []
    for comp, t in comps:
        own = [p for p in comp if not p.extended]
        z = max(p.z for p in own)
        after_t = {e.drive_id for p in comp for e in by_place[p.key] if e.time_ns >= t}
        digest = hashlib.sha1(repr(([p.key for p in comp], t)).encode()).digest()
        out.append(
            DetectedChange(
                id=int.from_bytes(digest[:8], "little") & ((1 << 63) - 1),
                time_ns=t,
                kinds=tuple(sorted({p.kind for p in comp})),
                places=tuple(comp),
                drives_after=tuple(sorted({d for p in comp for d in p.drives_after} & after_t)),
                confidence=1.0 - 1.0 / z,
            )
        )
    return sorted(out, key=lambda c: (c.time_ns, c.id))
