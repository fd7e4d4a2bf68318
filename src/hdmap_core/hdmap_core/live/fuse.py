"""The live fast path: one drive on mapped, settled road fused into the tiles' estimates.

A drive is listed in ``Map.drive_ids`` only once every tile it touches is in the map with it,
made as the settled map makes it. Re-making the tiles (the settle: every tile with the fleet
offset model, or the region build) takes seconds to minutes; a drive on road the map already
holds carries little new: its samples on the map's cuts, one more drive per step. So such a drive
is fused into the settled estimates at once (:func:`fuse_drive`), and the next settle re-makes
every tile exactly as before (the settled map is still a function of the drive set only):

1. **Where the drive passed.** Every step of the tiles' segments is a cut (midpoint, heading,
   width); the drive's trajectory crossing the cut within its width, running with it, means the
   drive passed the step (at its travelled distance there).
2. **Its samples.** The drive's detection polylines crossing the cuts it passed, running with it
   (``evaluation.cuts``: the evaluator's vectorised intersection).
3. **Its offset, against the map held fixed.** The lateral difference map - sample of same-type
   pairs: their density mode over the whole drive (``updates.evidence.density_mode``), then per
   ``WINDOW_M`` of the drive near that mode, interpolated along the drive.
4. **Consistency** (the drive shows the road the map holds, else it goes the normal way and
   waits for the settle, where road changes are followed): the passed steps cover at least
   ``MIN_PASSED`` of the drive's trajectory in the tiles, at least ``MIN_MATCHED`` of its
   marking samples lie within ``GATE_M`` of a map maximum of their type after the offset, and the
   maxima it matched stand on ``MIN_SUPPORT`` drives or more (median): the map is a gauge.
5. **Fusion.** Each matched maximum moves to the recursive weighted mean of its drives and the
   sample (``lateral + (sample - lateral) / (count + 1)``), its count grows by one; every passed
   step names the drive. Steps it did not pass are kept as they were.
6. **The gauge** (``gauge``): the batch solve of the same drives keeps the fleet's offsets at zero
   mean with the new drive in it, which moves the lines where it drove by -offset / (n + 1) (n:
   the step's drives). So every maximum of a passed step moves by that much. Held fixed instead,
   the map keeps the settled map's gauge, as a local offset update (``pipeline.adjustment_local``)
   does, which is what kept that one 0.13-0.16 m from the global solve.

Pure (numpy, shapely through ``evaluation.cuts``); a function of the estimates and the drive.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from hdmap_core.evaluation.cuts import index_segments, intersect_indexed, segments_of
from hdmap_core.geometry import arc_length
from hdmap_core.live.tiles import TileKey
from hdmap_core.model import Drive, FeatureType
from hdmap_core.steps import Segment, StepResult, left_normal
from hdmap_core.updates.evidence import density_mode

__all__ = ["FuseResult", "fuse_drive", "GATE_M", "WINDOW_M", "MIN_PASSED", "MIN_MATCHED", "MIN_SUPPORT"]

GATE_M = 0.5  # RULE: a sample joins a map maximum of its type this close, after the drive's offset [m]
SEARCH_M = 2.0  # RULE: the drive's offset against the map is searched within +- this [m]
KERNEL_M = 0.1  # kernel of the offset's density mode [m]
WINDOW_M = 100.0  # RULE: the drive's offset curve: one value per this much of the drive [m]
MIN_WINDOW_PAIRS = 20  # a window with fewer pairs near the drive's mode takes the drive's mode
CUT_MARGIN_M = 2.0  # a cut reaches this far beyond the step's half width [m]
COS_MIN = 0.7  # the drive (and a detection) runs with a step when cos(angle) >= this
PASS_BIN_M = 10.0  # the share passed is counted in bins of this much of the drive [m]
MIN_PASSED = 0.9  # RULE: consistency: share of the drive's trajectory in the tiles on steps it passed
MIN_MATCHED = 0.6  # RULE: consistency: share of its marking samples matching a map maximum
# RULE: the map is the gauge only where it stands on enough drives: the median drive count of the
# maxima the drive matched (one drive more moves a batch solve of n drives by about 1/n of its offset)
MIN_SUPPORT = 5
_MARKINGS = (int(FeatureType.SOLID), int(FeatureType.DASHED))


@dataclass
class FuseResult:
    """What :func:`fuse_drive` made.

    Attributes:
        tiles: per tile, its segments with the drive fused in (None: refused, see ``reason``).
        reason: why the drive was refused ('' when fused).
        offset_knots: (s along the drive [m], offset [m]) of the drive's offset curve (added to
            its samples).
        steps_passed, samples, matched: steps the drive passed, its samples on them, those
            fused into a map maximum.
        passed_share, matched_share: the consistency figures (step 4 of the module docstring).
    """

    tiles: dict[TileKey, list[Segment]] | None
    reason: str = ""
    offset_knots: tuple[np.ndarray, np.ndarray] = field(default_factory=lambda: (np.zeros(0), np.zeros(0)))
    steps_passed: int = 0
    samples: int = 0
    matched: int = 0
    passed_share: float = 0.0
    matched_share: float = 0.0


def _steps(tiles: Mapping[TileKey, Sequence[Segment]]) -> tuple[list[tuple[TileKey, int, int]], list[StepResult]]:
    """Every step with maxima: (tile, segment index, step index) and the step."""
    where = [
        (key, si, ti) for key in sorted(tiles) for si, seg in enumerate(tiles[key]) for ti in range(len(seg.steps))
    ]
    every = [st for key in sorted(tiles) for seg in tiles[key] for st in seg.steps]
    if not every:
        return [], []
    try:  # the midpoints at once (one shape, the usual case)
        finite = np.isfinite(np.array([st.midpoint for st in every], dtype=float)).reshape(len(every), -1).all(axis=1)
    except ValueError:
        finite = np.array([bool(np.all(np.isfinite(np.asarray(st.midpoint, dtype=float)))) for st in every])
    ok = finite & np.array([bool(st.valid) and np.size(st.lateral_m) > 0 for st in every], dtype=bool)
    keep = np.flatnonzero(ok).tolist()
    return [where[j] for j in keep], [every[j] for j in keep]


def _passed(drive: Drive, center: np.ndarray, tangent: np.ndarray, normal: np.ndarray, half: np.ndarray):
    """(cut index, travelled distance) of the cuts the drive's trajectory crosses within their
    width while running with them; the crossing nearest the midpoint per cut."""
    xy = np.asarray(drive.xy, dtype=float)
    traj = segments_of([xy])
    if not len(traj):
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    ci, si, s, u = intersect_indexed(center, normal, -half, half, index_segments(traj))
    d = traj.b[si] - traj.a[si]
    ok = (d * tangent[ci]).sum(axis=1) >= COS_MIN * np.linalg.norm(d, axis=1)
    ci, si, s, u = ci[ok], si[ok], s[ok], u[ok]
    order = np.lexsort((np.abs(s), ci))
    ci, si, u = ci[order], si[order], u[order]
    first = np.ones(len(ci), dtype=bool)
    first[1:] = ci[1:] != ci[:-1]
    ci, si, u = ci[first], si[first], u[first]
    arc = arc_length(xy)
    v = traj.vertex[si]
    seg_len = np.linalg.norm(traj.b[si] - traj.a[si], axis=1)
    return ci, arc[v] + u * seg_len


def _samples(drive: Drive, center: np.ndarray, tangent: np.ndarray, normal: np.ndarray, half: np.ndarray):
    """(cut index, lateral [m], type) of the drive's detections crossing the cuts, running with them."""
    polys = [np.asarray(d.points, dtype=float) for d in drive.detections if len(d.points) >= 2]
    types = np.array([int(d.type) for d in drive.detections if len(d.points) >= 2], dtype=np.int64)
    segs = segments_of(polys) if polys else None
    if segs is None or not len(segs) or not len(center):
        return np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0, dtype=np.int64)
    ci, si, s, _ = intersect_indexed(center, normal, -half, half, index_segments(segs))
    d = segs.b[si] - segs.a[si]
    ok = (d * tangent[ci]).sum(axis=1) >= COS_MIN * np.linalg.norm(d, axis=1)
    return ci[ok], s[ok], types[segs.owner[si[ok]]]


def _maxima(steps: Sequence[StepResult]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The maxima of ``steps`` flat: per step its first maximum and count of maxima; per maximum its
    lateral [m] (float64), type and drive count (the steps' dtype)."""
    lat = [np.asarray(st.lateral_m, dtype=float).reshape(-1) for st in steps]
    k = np.array([len(x) for x in lat], dtype=np.int64)
    start = np.cumsum(k) - k
    cat = np.concatenate
    typ = cat([np.asarray(st.types).reshape(-1) for st in steps]).astype(np.int64) if steps else np.zeros(0, np.int64)
    cnt = cat([np.asarray(st.counts).reshape(-1) for st in steps]) if steps else np.zeros(0, np.int64)
    return start, k, (cat(lat) if steps else np.zeros(0)), typ, cnt


def _pairs(cut: np.ndarray, lat: np.ndarray, typ: np.ndarray, start: np.ndarray, k: np.ndarray, m_lat, m_typ):
    """(sample index, maximum index within its step, map - sample) of every same-type pair: the
    samples in (stable) cut order, each with the maxima of its cut's step in order (``_maxima``:
    ``start``, ``k``, ``m_lat``, ``m_typ`` per step of the cuts)."""
    order = np.argsort(cut, kind="stable")
    n = k[cut[order]]
    i = np.repeat(order, n)
    slot = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
    m = start[cut[i]] + slot
    same = typ[i] == m_typ[m]
    i, slot, m = i[same], slot[same], m[same]
    return i, slot, m_lat[m] - lat[i]


def _greedy(sample: np.ndarray, maximum: np.ndarray) -> np.ndarray:
    """Indices of the pairs a greedy pass in the given order accepts, one pair per sample and per
    maximum (nearest first when ordered by residual), in that order. In rounds: a pair first among
    the remaining ones for both its sample and its maximum is what the greedy pass takes; the pairs
    sharing a sample or a maximum with it are then out."""
    alive = np.arange(len(sample))
    taken = []
    while len(alive):
        s, m = sample[alive], maximum[alive]
        first_s = np.zeros(len(alive), dtype=bool)
        first_s[np.unique(s, return_index=True)[1]] = True
        first_m = np.zeros(len(alive), dtype=bool)
        first_m[np.unique(m, return_index=True)[1]] = True
        win = first_s & first_m
        taken.append(alive[win])
        out = np.isin(s, s[win]) | np.isin(m, m[win])
        alive = alive[~out]
    return np.sort(np.concatenate(taken)) if taken else np.zeros(0, dtype=np.int64)


def _offset_curve(s_pair: np.ndarray, diff: np.ndarray, length_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The drive's offset against the map: (knots along the drive, values); empty: no mode."""
    mode, n = density_mode(diff, reach_m=SEARCH_M, kernel_m=KERNEL_M)
    if n == 0 or not np.isfinite(mode):
        return np.zeros(0), np.zeros(0)
    edges = np.arange(0.0, max(length_m, WINDOW_M) + WINDOW_M, WINDOW_M)
    knots, values = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        w = (s_pair >= lo - 0.5 * WINDOW_M) & (s_pair < hi + 0.5 * WINDOW_M)  # windows overlap by half
        m, k = density_mode(diff[w], reach_m=GATE_M, kernel_m=KERNEL_M, center=mode) if w.any() else (mode, 0)
        knots.append(0.5 * (lo + hi))
        values.append(m if k >= MIN_WINDOW_PAIRS and np.isfinite(m) else mode)
    return np.asarray(knots), np.asarray(values)


def fuse_drive(drive: Drive, tiles: Mapping[TileKey, Sequence[Segment]], *, gauge: bool = True) -> FuseResult:
    """Fuse one drive into the settled estimates of the tiles it touches (module docstring).

    Args:
        drive: the new drive (cleaned as stored by the mapper).
        tiles: every tile the drive touches -> its current (settled) segments.
        gauge: move the lines of the passed steps as the batch solve would (step 6); False: the
            map held fixed.

    Returns:
        The fused segments per tile, or the reason the drive goes the normal way.
    """
    where, steps = _steps(tiles)
    if not steps:
        return FuseResult(None, "no mapped step")
    center = np.array([np.asarray(st.midpoint, dtype=float).reshape(-1)[:2] for st in steps]).reshape(-1, 2)
    heading = np.array([float(st.heading) for st in steps])
    normal = left_normal(heading).reshape(-1, 2)
    tangent = np.stack([np.cos(heading), np.sin(heading)], axis=1)
    half = np.maximum(np.array([float(st.width_m) for st in steps]), 0.0) * 0.5 + CUT_MARGIN_M

    cut_p, s_p = _passed(drive, center, tangent, normal, half)
    res = FuseResult(None, steps_passed=len(cut_p))
    if not len(cut_p):
        res.reason = "passed no mapped step"
        return res
    # consistency 1: the drive runs on mapped steps along (nearly) all its way through the tiles
    bins = np.unique(np.floor(s_p / PASS_BIN_M))
    res.passed_share = float(min(1.0, bins.size * PASS_BIN_M / max(drive.length_m, PASS_BIN_M)))
    if res.passed_share < MIN_PASSED:
        res.reason = f"passed mapped steps on {res.passed_share:.0%} of its way (< {MIN_PASSED:.0%})"
        return res

    sub = cut_p  # the passed cuts only
    ci, lat, typ = _samples(drive, center[sub], tangent[sub], normal[sub], half[sub])
    res.samples = len(ci)
    if not len(ci):
        res.reason = "no detection on the passed steps"
        return res
    s_of_sample = s_p[ci]
    steps_p = [steps[int(j)] for j in sub]
    start, k_max, m_lat, m_typ, m_cnt = _maxima(steps_p)  # the passed steps' maxima, flat
    pi, pk, pd = _pairs(ci, lat, typ, start, k_max, m_lat, m_typ)
    knots, values = _offset_curve(s_of_sample[pi], pd, drive.length_m)
    if not len(knots):
        res.reason = "no offset against the map"
        return res
    res.offset_knots = (knots, values)
    off = np.interp(s_of_sample, knots, values)
    resid = np.abs(pd - off[pi])
    ok = resid <= GATE_M
    pi, pk, resid = pi[ok], pk[ok], resid[ok]
    # one sample per maximum and one maximum per sample: nearest first
    order = np.argsort(resid, kind="stable")
    pi, pk = pi[order], pk[order]
    m_of = start[ci[pi]] + pk  # the pair's maximum, flat
    won = _greedy(pi, m_of)
    mi, mm = pi[won], m_of[won]  # the matches: sample, maximum (flat)
    marking = np.isin(typ, _MARKINGS)
    matched_mark = int(marking[mi].sum())
    res.matched = len(mi)
    res.matched_share = float(matched_mark / marking.sum()) if marking.any() else float(len(mi) / len(ci))
    if res.matched_share < MIN_MATCHED:
        res.reason = f"{res.matched_share:.0%} of its markings on the map's lines (< {MIN_MATCHED:.0%})"
        return res
    support = float(np.median(m_cnt[mm]))
    if support < MIN_SUPPORT:
        res.reason = f"the map's lines stand on {support:g} drives there (< {MIN_SUPPORT})"
        return res

    # fusion: the matched maxima move to the weighted mean, counts + 1 (one sample per maximum)
    x = lat + off  # the samples with the drive's offset: in the map's frame
    new_lat = m_lat.copy()
    new_cnt = m_cnt.copy()
    n = np.maximum(m_cnt[mm], 1).astype(float)
    new_lat[mm] += (x[mi] - new_lat[mm]) / (n + 1.0)
    new_cnt[mm] = new_cnt[mm] + 1
    if gauge:  # the step's drives' offsets keep zero mean with the new one: all move by -off / (n + 1)
        off_p = np.interp(s_p, knots, values)
        most = np.maximum.reduceat(m_cnt, start) if len(m_cnt) else np.zeros(0, m_cnt.dtype)
        n_step = np.maximum(np.array([len(st.drive_ids) for st in steps_p]), np.maximum(most, 1))
        step_of = np.repeat(np.arange(len(steps_p)), k_max)
        new_lat += -off_p[step_of] / (n_step[step_of] + 1.0)
    lat_parts = np.split(new_lat, start[1:])
    cnt_parts = np.split(new_cnt, start[1:])
    new_steps: dict[tuple[TileKey, int], dict[int, StepResult]] = {}
    did = drive.drive_id
    for c, st in enumerate(steps_p):
        ids = st.drive_ids if did in st.drive_ids else (*st.drive_ids, did)
        key, si, ti = where[int(sub[c])]
        new_steps.setdefault((key, si), {})[ti] = _with(st, lat_parts[c], cnt_parts[c], tuple(ids))
    out: dict[TileKey, list[Segment]] = {}
    for key in tiles:
        segs = list(tiles[key])
        for si, seg in enumerate(segs):
            moved = new_steps.get((key, si))
            if moved:
                segs[si] = replace(seg, steps=tuple(moved.get(ti, st) for ti, st in enumerate(seg.steps)))
        out[key] = segs
    res.tiles = out
    return res


def _with(st: StepResult, lateral_m: np.ndarray, counts: np.ndarray, drive_ids: tuple[str, ...]) -> StepResult:
    """``st`` with these maxima and drives (``dataclasses.replace``, without its per-call field walk)."""
    return StepResult(
        st.pivot_id,
        st.index,
        st.s_m,
        st.midpoint,
        st.heading,
        st.width_m,
        st.valid,
        st.processed_before,
        lateral_m,
        st.types,
        counts,
        st.std_m,
        drive_ids,
        st.empty_m,
        st.pose,
    )
