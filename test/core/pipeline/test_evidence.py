"""Negative evidence (hdmap_core.pipeline.evidence): empty stretches per step, and fills through them dropped."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hdmap_core.errors import ConfigError
from hdmap_core.model import Detection, Drive, FeatureType
from hdmap_core.pipeline import presets
from hdmap_core.pipeline.driver import build_map, map_stretches, prepare_drives
from hdmap_core.pipeline.evidence import EvidenceConfig, _in_intervals, refuted_edges, step_profiles

from former_configs import former, former_replace
from pipeline_fleet import LINES, offset_line

CFG = former(EvidenceConfig)


def _inside(intervals: np.ndarray, x: float) -> bool:
    return bool(((intervals[:, 0] <= x) & (x <= intervals[:, 1])).any()) if len(intervals) else False


def test_profile_empty_where_passing_drives_saw_nothing():
    """Six drives cross one cut, two in each lane (t = -3.5, 0, 3.5); all detect lines at
    t = -1.75 and 1.75, none at t = 5.25: expected there 2 x 0.9 + 2 x 0.6 + 2 x 0.2 = 3.4."""
    cross_t = np.array([-3.5, -3.5, 0.0, 0.0, 3.5, 3.5])
    drives = np.arange(6)
    hit_t = np.tile([-1.75, 1.75], 6)
    hit_d = np.repeat(drives, 2)
    (prof,) = step_profiles(1, np.zeros(6), cross_t, drives, np.zeros(12), hit_t, hit_d)
    assert _inside(prof, 5.25) and not _inside(prof, 1.75) and not _inside(prof, -1.75)
    assert not _inside(prof, 14.0)  # too far from every drive to expect anything
    # one drive of six seeing a line there (1 of 3.4 expected, > 20 %): not empty
    (prof,) = step_profiles(1, np.zeros(6), cross_t, drives, np.zeros(13), np.r_[hit_t, 5.3], np.r_[hit_d, 4])
    assert not _inside(prof, 5.25)
    # two drives passing expect too little to judge anything
    (prof,) = step_profiles(1, np.zeros(2), cross_t[4:], drives[4:], np.zeros(4), hit_t[8:], hit_d[8:])
    assert len(prof) == 0
    # a drive crossing twice counts once
    (prof,) = step_profiles(1, np.zeros(7), np.r_[cross_t, 3.4], np.r_[drives, 5], np.zeros(12), hit_t, hit_d)
    assert _inside(prof, 5.25)
    assert step_profiles(0, [], [], [], [], [], []) == []


def test_sparse_cut_judged_with_the_default_presets_min_expected():
    """Four drives cross one cut (t = -3.5, 0, 3.5, 3.5); all detect lines at t = -1.75 and
    1.75, none at t = 5.25: expected there 2 x 0.9 + 0.6 + 0.2 = 2.6 detections. The dataclass
    (min_expected 3) does not judge it; the default preset judges from 2 expected detections
    (the 30-drive fleets' junction mouths, docs/pipeline.md) and finds it empty."""
    cross_t = np.array([-3.5, 0.0, 3.5, 3.5])
    drives = np.arange(4)
    hit_t = np.tile([-1.75, 1.75], 4)
    hit_d = np.repeat(drives, 2)
    preset = presets.preset("default")
    assert preset.evidence.min_expected == 2.0 and preset.stitching.fill_evidence
    assert CFG.min_expected == 3.0
    (prof,) = step_profiles(1, np.zeros(4), cross_t, drives, np.zeros(8), hit_t, hit_d, config=preset.evidence)
    assert _inside(prof, 5.25) and not _inside(prof, 1.75)
    (prof,) = step_profiles(1, np.zeros(4), cross_t, drives, np.zeros(8), hit_t, hit_d, config=CFG)
    assert not _inside(prof, 5.25)


def test_profiles_of_many_steps_equal_those_of_each_step_alone():
    """Many steps at once (the matrices are built a chunk of steps at a time) give what each step
    gives alone."""
    rng = np.random.default_rng(4)
    n = 400
    cq = np.repeat(np.arange(n), 8)
    cd = np.tile(np.arange(8), n)
    ct = rng.uniform(-6, 6, len(cq))
    hq = np.repeat(np.arange(n), 24)
    hd = np.tile(np.repeat(np.arange(8), 3), n)
    ht = rng.choice([-5.25, -1.75, 1.75, 5.25], len(hq)) + rng.normal(0, 0.1, len(hq))
    ht[rng.random(len(hq)) < 0.5] = 20.0  # half the detections elsewhere: some bins go empty
    allp = step_profiles(n, cq, ct, cd, hq, ht, hd)
    assert sum(len(p) for p in allp) > 50
    for q in range(0, n, 37):
        c, h = cq == q, hq == q
        (one,) = step_profiles(1, cq[c] * 0, ct[c], cd[c], hq[h] * 0, ht[h], hd[h])
        np.testing.assert_array_equal(allp[q], one)


def test_edges_through_an_empty_stretch_refuted():
    """Steps every 2 m along x (heading 0) with the stretch y in [4, 6] empty for x in 20..40: a
    line node pair (18, 5) -> (42, 5) bridging it is refuted, one at y = 1.75 and a 2 m edge are not."""
    xs = np.arange(0.0, 61.0, 2.0)
    step_xy = np.stack([xs, np.zeros_like(xs)], axis=1)
    empty_rows = [np.array([[4.0, 6.0]]) if 20 <= x <= 40 else np.zeros((0, 2)) for x in xs]
    start = np.concatenate([[0], np.cumsum([len(e) for e in empty_rows])])
    empty = np.concatenate(empty_rows)
    nodes = np.array([[18.0, 5.0], [42.0, 5.0], [18.0, 1.75], [42.0, 1.75], [10.0, 5.0], [12.0, 5.0]])
    edges = np.array([[0, 1], [2, 3], [4, 5]])
    out = refuted_edges(nodes, edges, step_xy, np.zeros(len(xs)), start, empty)
    assert out.tolist() == [True, False, False]
    # steps heading the other way do not judge it; with half the gap empty, the share decides
    assert not refuted_edges(nodes, edges, step_xy, np.full(len(xs), np.pi), start, empty).any()
    nodes2 = nodes.copy()
    nodes2[1] = [66.0, 5.0]  # 48 m edge, 20 m of it empty (~42 %)
    assert refuted_edges(nodes2, edges, step_xy, np.zeros(len(xs)), start, empty).tolist() == [False, False, False]
    assert (
        refuted_edges(nodes, edges, np.zeros((0, 2)), np.zeros(0), np.zeros(1, np.int64), np.zeros((0, 2))).tolist()
        == [False] * 3
    )


def test_interval_lookup_matches_a_scan_of_each_steps_intervals():
    """Several disjoint intervals per step, steps without any, points on the bounds, between
    intervals and on another step's interval: the sorted lookup answers as a per-step scan."""
    rng = np.random.default_rng(3)
    rows = []
    for _ in range(40):
        cuts = np.sort(rng.choice(np.arange(-15.0, 15.5, 0.5), size=2 * rng.integers(0, 4), replace=False))
        rows.append(cuts.reshape(-1, 2)[::-1])  # out of order within a step on purpose
    start = np.concatenate([[0], np.cumsum([len(r) for r in rows])])
    empty = np.concatenate(rows)
    step = rng.integers(0, 40, size=2000)
    lat = np.concatenate([rng.uniform(-16, 16, 1500), empty[rng.integers(0, len(empty), 500)].ravel()[:500]])
    got = _in_intervals(step, lat, start, empty)
    want = [bool(((rows[q][:, 0] <= t) & (t <= rows[q][:, 1])).any()) for q, t in zip(step.tolist(), lat.tolist())]
    assert got.tolist() == want
    assert 100 < sum(want) < 1900
    assert _in_intervals(step[:0], lat[:0], start, empty).tolist() == []


def _drive(i: int, lane: float, gap: tuple[float, ...] | None) -> Drive:
    """A drive on the tiny fleet's road (pipeline_fleet); the solid line at +5.25 is not
    detected over ``gap`` (pairs of s from, to), every other line everywhere."""
    s = np.arange(0.0, 300.0 + 1e-9, 1.0)
    xy, h = offset_line(s, lane)
    dets = []
    for lat, ftype in LINES:
        p, _ = offset_line(s, lat)
        if gap is not None and lat == 5.25:
            seen = np.ones(len(s), dtype=bool)
            for a, b in zip(gap[::2], gap[1::2]):
                seen &= (s <= a) | (s >= b)
            cut = np.flatnonzero(np.diff(seen.astype(np.int8))) + 1
            dets += [Detection(type=ftype, points=p[idx]) for idx in np.split(np.arange(len(s)), cut) if seen[idx[0]]]
        else:
            dets.append(Detection(type=ftype, points=p))
    return Drive(
        drive_id=f"d{i}",
        xy=xy,
        yaw=h,
        stamps_ns=(np.arange(len(s)) * 50_000_000).astype(np.int64),
        detections=tuple(dets),
    )


def _solid_left(hdmap) -> list[np.ndarray]:
    """The map's solid-line points near lateral +5.25 (the road's centre runs near y = 0)."""
    out = []
    for f in hdmap.features:
        if f.type == FeatureType.SOLID and np.median(f.points[:, 1] - offset_line(f.points[:, 0], 0.0)[0][:, 1]) > 3:
            out.append(f)
    return out


def _gap_points(feats, lo: float, hi: float) -> int:
    return sum(int(((f.points[:, 0] > lo) & (f.points[:, 0] < hi)).sum()) for f in feats)


@pytest.mark.parametrize("n_missing", [pytest.param(6, marks=pytest.mark.slow), 1])
def test_fill_dropped_only_where_every_passing_drive_missed_the_line(n_missing):
    """A 16 m stretch of the left solid line (s 120..136) is missing for ``n_missing`` of six drives.
    Missing for all (a junction mouth): the connection bridges the gap with filled points, and the
    evidence drops them (two pieces). Missing for one (a dropout): the others map it, no gap."""
    lanes = (-3.5, -3.5, 0.0, 0.0, 3.5, 3.5)
    drives = [_drive(i, lane, (120.0, 136.0) if i < n_missing else None) for i, lane in enumerate(lanes)]
    default = presets.preset("default")
    off = dataclasses.replace(
        default, evidence=None, stitching=dataclasses.replace(default.stitching, fill_evidence=None)
    )
    with_ev, without = build_map(drives, config=default), build_map(drives, config=off)
    a, b = _solid_left(with_ev.map), _solid_left(without.map)
    if n_missing == 6:
        assert _gap_points(b, 124.0, 132.0) >= 3 and all(
            (f.drive_count[(f.points[:, 0] > 124) & (f.points[:, 0] < 132)] == 0).all() for f in b
        )
        assert _gap_points(a, 124.0, 132.0) == 0 and len(a) == 2
        assert with_ev.map.extra["fills_refuted"] >= 1
    else:
        assert _gap_points(a, 124.0, 132.0) >= 3 and len(a) == 1
        assert with_ev.map.extra["fills_refuted"] == 0
    # the rest of the map is the same
    assert len(with_ev.map.features) - len(a) == len(without.map.features) - len(b)


def test_piece_between_two_refuted_fills_is_kept():
    """Two 16 m stretches missing for every drive (s 120..136 and 150..166) leave a 14 m piece of
    the line between them, seen by all: shorter than the speck rule's 20 m, but drive-supported
    and only isolated by the refuted fills, so it stays (three pieces, none in the gaps)."""
    lanes = (-3.5, -3.5, 0.0, 0.0, 3.5, 3.5)
    drives = [_drive(i, lane, (120.0, 136.0, 150.0, 166.0)) for i, lane in enumerate(lanes)]
    res = build_map(drives, config=presets.preset("default"))
    solid = _solid_left(res.map)
    assert len(solid) == 3 and res.map.extra["fills_refuted"] >= 2
    assert _gap_points(solid, 124.0, 132.0) == 0 and _gap_points(solid, 154.0, 162.0) == 0
    assert _gap_points(solid, 138.0, 148.0) >= 4


@pytest.mark.slow
def test_steps_of_the_returned_pass_carry_profiles():
    drives, _ = prepare_drives([_drive(i, lane, (120.0, 136.0)) for i, lane in enumerate((-3.5, 0.0, 3.5) * 2)])
    res = map_stretches(drives, config=presets.preset("default"))
    judged = [st for seg in res.segments for st in seg.steps if st.empty_m is not None]
    assert judged and all(st.empty_m.shape[1] == 2 for st in judged)
    at_gap = [st for st in judged if 122.0 < st.s_m < 134.0 and not st.processed_before]
    assert at_gap and all(_inside(st.empty_m, 5.25) for st in at_gap)  # from the midpoint, the road's centre
    for name in ("paper", "naive"):
        res = map_stretches(drives, config=presets.preset(name))
        steps = [st for seg in res.segments for st in seg.steps]
        assert steps and all(st.empty_m is None for st in steps)


def test_evidence_config_checked():
    for bad in (
        dict(max_seen_ratio=0.0),
        dict(max_seen_ratio=1.5),
        dict(min_expected=-1.0),
        dict(min_expected=float("inf")),
    ):
        with pytest.raises(ConfigError):
            former(EvidenceConfig, **bad)


@pytest.mark.parametrize("seen_by", ["one", "all"])
def test_one_drives_speck_between_refuted_fills_is_dropped(seen_by):
    """Four drives; the solid line is missing for all of them over s 120..166 except a 4 m piece
    (136..140) that one drive (or every drive) saw. Both fills beside the piece are refuted; the
    piece of one drive is a speck (refuted_piece_min_m) and goes, the piece every drive saw
    stays."""
    lanes = (3.5, 3.5, 0.0, 0.0)
    gaps = [(120.0, 136.0, 140.0, 166.0) if seen_by == "all" or i == 0 else (120.0, 166.0) for i in range(4)]
    drives = [_drive(i, lane, gap) for i, (lane, gap) in enumerate(zip(lanes, gaps))]
    default = presets.preset("default")
    res = build_map(drives, config=default)
    solid = _solid_left(res.map)
    assert res.map.extra["fills_refuted"] == 2
    assert _gap_points(solid, 124.0, 132.0) == 0 and _gap_points(solid, 144.0, 162.0) == 0
    kept = former_replace(default, stitching=former_replace(default.stitching, refuted_piece_min_m=0.0))
    assert _gap_points(_solid_left(build_map(drives, config=kept).map), 134.0, 142.0) >= 2  # the piece exists
    if seen_by == "one":
        assert len(solid) == 2 and _gap_points(solid, 134.0, 142.0) == 0
    else:
        assert len(solid) == 3 and _gap_points(solid, 134.0, 142.0) >= 2
    assert presets.preset("paper").stitching.refuted_piece_min_m == 0.0
