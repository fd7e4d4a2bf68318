"""Tests of hdmap_core.live.fuse and the fast path through the live schedule (no DDS).

A fleet on a synthetic motorway is settled (the region job: the offline build cut into tiles);
one more drive on that road is fused into the settled estimates, listed, and the settle after it
gives the offline map of every drive again.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from fuse_fleet import fuse_fleet

from hdmap_core.live.fuse import _greedy, fuse_drive
from hdmap_core.live.jobs import run_job
from hdmap_core.live.progress import integrated_drives
from hdmap_core.live.region import map_region
from hdmap_core.live.scheduler import FUSE, REGION, LiveScheduler
from hdmap_core.live.tiles import TileConfig, road_cells, tiles_of_drive
from hdmap_core.model import Detection, Drive
from hdmap_core.pipeline import presets

TC = TileConfig(tile_size_m=256.0, margin_m=128.0, seed=0)


@pytest.fixture(scope="module")
def fleet():
    drives = fuse_fleet()
    pc = presets.preset("default")
    return drives, pc


def _keys(drives):
    return sorted(set().union(*[tiles_of_drive(d, config=TC) for d in drives]))


def _shifted(drive: Drive, by_m: float) -> Drive:
    """The whole drive moved by ``by_m`` to the left of its mean heading (a localisation offset)."""
    h = float(np.arctan2(np.sin(drive.yaw).mean(), np.cos(drive.yaw).mean()))
    v = by_m * np.array([-np.sin(h), np.cos(h)])
    dets = tuple(Detection(d.type, np.asarray(d.points) + v) for d in drive.detections)
    return replace(drive, xy=np.asarray(drive.xy) + v, detections=dets)


def test_fuse_names_the_drive_holds_the_map_as_gauge_and_refuses_a_drive_off_the_map(fleet):
    drives, pc = fleet
    base, new = drives[:-1], drives[-1]
    keys = _keys(base)
    tiles = map_region(base, keys, tile_config=TC, pipeline_config=pc).segments
    mine = {k: tiles[k] for k in tiles_of_drive(new, config=TC)}
    res = fuse_drive(new, mine)
    assert res.tiles is not None, res.reason
    assert res.passed_share >= 0.9 and res.matched > 0.5 * res.samples
    before = sum(int(np.sum(st.counts)) for k in mine for seg in mine[k] for st in seg.steps)
    after = sum(int(np.sum(st.counts)) for k in res.tiles for seg in res.tiles[k] for st in seg.steps)
    assert after - before == res.matched  # each matched maximum carries one drive more
    named = [new.drive_id in st.drive_ids for k in res.tiles for seg in res.tiles[k] for st in seg.steps]
    assert sum(named) == res.steps_passed > 0
    # the same drive 0.8 m off: its offset takes the 0.8 m; against the map held fixed the lines do
    # not move by it, with the gauge they move as the batch solve's would: by -0.8 / (n + 1)
    moved = fuse_drive(_shifted(new, 0.8), mine)
    assert moved.tiles is not None
    d_off = np.interp(moved.offset_knots[0], *res.offset_knots) - moved.offset_knots[1]
    assert np.allclose(d_off, 0.8, atol=0.1)

    def lines(tiles):
        return np.concatenate([st.lateral_m for k in sorted(tiles) for seg in tiles[k] for st in seg.steps])

    fixed, fixed_m = fuse_drive(new, mine, gauge=False), fuse_drive(_shifted(new, 0.8), mine, gauge=False)
    assert np.mean(np.abs(lines(fixed.tiles) - lines(fixed_m.tiles))) < 0.02
    passed = [st for k in sorted(res.tiles) for seg in res.tiles[k] for st in seg.steps if new.drive_id in st.drive_ids]
    want = np.mean([0.8 / len(st.drive_ids) for st in passed])  # n + 1 drives once it is named
    moved_by = lines(moved.tiles) - lines(res.tiles)
    assert abs(np.sum(moved_by) / sum(len(st.lateral_m) for st in passed) - want) < 0.03
    # a drive 300 m beside the road passes none of its steps: refused (the normal way)
    off = fuse_drive(_shifted(new, 300.0), mine)
    assert off.tiles is None and off.reason
    # a map of 3 drives is no gauge: refused
    same = [d for d in base if np.cos(np.mean(d.yaw) - np.mean(new.yaw)) > 0][:3]
    thin = map_region(same, keys, tile_config=TC, pipeline_config=pc).segments
    res2 = fuse_drive(new, {k: thin.get(k, []) for k in mine})
    assert res2.tiles is None and "stand on" in res2.reason


def test_fast_path_lists_a_drive_with_its_evidence_and_the_settle_gives_the_offline_map(fleet):
    drives, pc = fleet
    base, new = drives[:-1], drives[-1]
    kw = {"tile_config": TC, "pipeline_config": pc, "use_fleet_model": True}
    s = LiveScheduler(TC, use_fleet_model=True, settle_after_s=1.0, region_max_drives=100, fast_path=True)
    store: dict = {}  # tile -> (segments, drive ids, tile counts of its drives, final)
    by_id = {d.drive_id: d for d in drives}

    def run(now: float) -> list:
        done = []
        while jobs := s.next_jobs(now, 1):
            (job,) = jobs
            if job.kind == FUSE:
                res = run_job(
                    job, [by_id[job.drive_ids[0]]], tile_segments={k: store[k][0] for k, _ in job.tiles}, **kw
                )
                tiles = res.tiles
            else:
                res = run_job(job, [by_id[d] for d in job.drive_ids], **kw)
                tiles = res.tiles if job.kind == REGION else {job.key: res.segments}
            for k, ids in job.tiles or ((job.key, job.drive_ids),):
                if tiles is not None:
                    store[k] = (tiles[k], ids, [s.drive_tile_count(d) for d in ids], job.final)
            s.finished(job, ok=tiles is not None, observed=res.observations is not None)
            done.append(job)
        return done

    def listed() -> set[str]:
        return integrated_drives((ids, counts) for _, ids, counts, final in store.values() if final)

    for d in base:
        s.add_drive(d.drive_id, tiles_of_drive(d, config=TC), 0.0, road_cells(d, config=TC))
    run(0.0)
    assert [j.kind for j in run(1.0)] == [REGION] and s.is_settled()
    assert listed() == {d.drive_id for d in base}
    s.add_drive(new.drive_id, tiles_of_drive(new, config=TC), 2.0, road_cells(new, config=TC))
    assert [j.kind for j in run(2.0)] == [FUSE]  # at once, before settle_after_s
    assert new.drive_id in listed()  # listed: every tile of it is final with it
    assert any(new.drive_id in st.drive_ids for seg, *_ in store.values() for sg in seg for st in sg.steps)
    assert not s.is_settled()
    assert [j.kind for j in run(3.5)] == [REGION] and s.is_settled()  # the settle re-makes every tile
    offline = map_region(drives, _keys(drives), tile_config=TC, pipeline_config=pc).segments
    for k, (segs, *_rest) in store.items():
        assert [(g.pivot_id, [st.lateral_m.tolist() for st in g.steps]) for g in segs] == [
            (g.pivot_id, [st.lateral_m.tolist() for st in g.steps]) for g in offline[k]
        ]


def test_greedy_matching_in_rounds_is_the_greedy_pass():
    """``fuse._greedy`` (rounds of pairs first for their sample and their maximum) takes exactly the
    pairs the greedy pass over the pairs in order takes (one per sample, one per maximum)."""
    rng = np.random.default_rng(3)
    for n in (0, 1, 7, 200, 2000):
        sample, maximum = rng.integers(0, max(1, n // 3), n), rng.integers(0, max(1, n // 4), n)
        used_s, used_m, want = set(), set(), []
        for j, (i, k) in enumerate(zip(sample.tolist(), maximum.tolist(), strict=True)):
            if i not in used_s and k not in used_m:
                used_s.add(i)
                used_m.add(k)
                want.append(j)
        assert _greedy(sample, maximum).tolist() == want
