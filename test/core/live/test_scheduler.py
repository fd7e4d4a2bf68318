"""Tests of hdmap_core.live.scheduler: the live mapper's schedule without DDS, store or clock."""

from __future__ import annotations

import random
from dataclasses import replace

from hdmap_core.live.scheduler import FUSE, MAP, MODEL, OBSERVE, PART, REGION, REMAP, Job, LiveScheduler
from hdmap_core.live.tiles import TileConfig

CFG = TileConfig(min_growth_fraction=0.10, min_growth_drives=3)
A, B, C = (0, 0), (1, 0), (2, 0)


def _sched(model: bool = False, settle: float = 2.0) -> LiveScheduler:
    return LiveScheduler(CFG, use_fleet_model=model, settle_after_s=settle)


def _run(s: LiveScheduler, now: float, limit: int = 1, *, observed: bool = False) -> list[Job]:
    """Start up to ``limit`` jobs and finish them all successfully; return them."""
    jobs = s.next_jobs(now, limit)
    for j in jobs:
        s.finished(j, ok=True, observed=observed and j.kind == MAP)
    return jobs


def _drain(s: LiveScheduler, now: float, *, observed: bool = False) -> list[Job]:
    done: list[Job] = []
    while jobs := _run(s, now, 4, observed=observed):
        done.extend(jobs)
    return done


def test_a_tile_is_one_job_for_all_drives_waiting_on_it():
    s = _sched()
    for i in range(5):
        s.add_drive(f"d{i}", [A, B], now=0.0)
    jobs = s.next_jobs(0.0, limit=10)
    assert sorted(j.key for j in jobs) == [A, B]
    assert all(j.kind == MAP and j.drive_ids == ("d0", "d1", "d2", "d3", "d4") for j in jobs)
    assert s.next_jobs(0.0, limit=10) == []  # nothing more: both are in work
    assert s.add_drive("d0", [C], now=0.0) is False  # a known drive changes nothing


def test_new_road_goes_before_re_estimates_and_the_most_grown_first():
    s = _sched()
    for i in range(3):
        s.add_drive(f"a{i}", [A, B], now=0.0)
    _drain(s, 0.0)
    for i in range(2):
        s.add_drive(f"b{i}", [A], now=1.0)  # A: 3 -> 5
    for i in range(4):
        s.add_drive(f"c{i}", [B], now=1.0)  # B: 3 -> 7 (x2.3)
    s.add_drive("n", [C, A], now=1.0)  # C: new road; A: 3 -> 6 (x2) now
    order = [j.key for j in _drain(s, 1.0)]
    assert order == [C, B, A]


def test_due_test_waits_for_enough_new_drives():
    s = _sched()
    for i in range(10):
        s.add_drive(f"d{i:02d}", [A], now=0.0)
    _drain(s, 0.0)
    s.add_drive("x1", [A], now=1.0)
    s.add_drive("x2", [A], now=1.0)
    assert s.next_jobs(1.0) == []  # 10 -> 12: below min_growth_drives
    assert s.pending_tiles() == 1 and not s.is_settled()
    s.add_drive("x3", [A], now=1.0)
    (job,) = _run(s, 1.0)
    assert job.kind == MAP and len(job.drive_ids) == 13


def test_a_tile_in_work_is_queued_again_behind_its_job():
    s = _sched()
    s.add_drive("d0", [A], now=0.0)
    (job,) = s.next_jobs(0.0)
    for i in range(1, 4):
        s.add_drive(f"d{i}", [A], now=0.1)
    assert s.next_jobs(0.1) == []  # A is in work
    s.finished(job, ok=True)
    (again,) = s.next_jobs(0.2)
    assert again.key == A and again.drive_ids == ("d0", "d1", "d2", "d3")


def test_settle_without_model_re_estimates_stale_tiles_after_the_idle_time():
    s = _sched(settle=2.0)
    for i in range(10):
        s.add_drive(f"d{i}", [A, B], now=0.0)
    _drain(s, 0.0)
    s.add_drive("late", [A], now=5.0)  # 10 -> 11: not due
    assert s.next_jobs(6.0) == [] and not s.idle(6.0)
    assert s.idle(7.0)
    jobs = _drain(s, 7.0)
    assert [(j.kind, j.key, len(j.drive_ids)) for j in jobs] == [(MAP, A, 11)]
    assert s.is_settled() and s.pending_tiles() == 0


def test_settle_with_model_runs_three_phases_with_a_barrier_before_the_model():
    s = _sched(model=True, settle=1.0)
    for i in range(4):
        s.add_drive(f"d{i}", [A, B], now=0.0)
    _drain(s, 0.0, observed=True)  # arrival: both tiles mapped with their own adjustment, observed
    s.add_drive("e", [B, C], now=0.5)
    _drain(s, 0.5, observed=True)  # C is new (mapped); B: 4 -> 5 not due
    assert not s.is_settled()
    jobs = s.next_jobs(2.0, limit=4)
    assert [(j.kind, j.key) for j in jobs] == [(OBSERVE, B)]  # 1. B's observations are behind its drives
    assert s.next_jobs(2.0, limit=4) == []  # 2. the model waits for the observation in work
    s.finished(jobs[0], ok=True)
    (model,) = s.next_jobs(2.0, limit=4)
    assert model.kind == MODEL and model.sig == s.observations_sig() != ""
    assert s.next_jobs(2.0, limit=4) == []  # nothing beside the model
    s.finished(model, ok=True)
    remaps = _drain(s, 2.0)  # 3. every tile with the model, from all its drives
    assert sorted((j.kind, j.key, len(j.drive_ids), j.sig) for j in remaps) == [
        (REMAP, A, 4, model.sig),
        (REMAP, B, 5, model.sig),
        (REMAP, C, 1, model.sig),
    ]
    assert s.is_settled() and s.pending_tiles() == 0
    s.add_drive("f", [A], now=3.0)  # new input: not settled until it went through all phases again
    assert not s.is_settled()


def test_failed_jobs_are_not_retried_until_the_drive_set_changes():
    s = _sched(settle=0.0)
    s.add_drive("d0", [A], now=0.0)
    (job,) = s.next_jobs(0.0)
    s.finished(job, ok=False)
    assert s.next_jobs(1.0) == [] and s.is_settled()  # failed at its count: nobody waits for it
    s.add_drive("d1", [A], now=1.0)
    (again,) = s.next_jobs(1.0)
    assert again.key == A and again.drive_ids == ("d0", "d1")


def test_a_failed_model_falls_back_to_the_tiles_own_adjustment():
    s = _sched(model=True, settle=1.0)
    s.add_drive("d0", [A], now=0.0)
    _drain(s, 0.0, observed=True)
    (model,) = s.next_jobs(1.0)
    assert model.kind == MODEL
    s.finished(model, ok=False)
    assert s.next_jobs(1.0) == [] and s.is_settled()


def test_restore_queues_the_due_tiles_and_keeps_a_settled_state():
    from hdmap_core.live.tiles import observations_signature

    obs = [(A, ["d0", "d1"]), (B, ["d1"])]
    sig = observations_signature(obs)
    s = _sched(model=True)
    s.restore(
        {A: ["d0", "d1"], B: ["d1"]},
        estimates=[(A, ["d0", "d1"], sig), (B, ["d1"], sig)],
        observations=obs,
        model_sig=sig,
        now=0.0,
    )
    assert s.drive_tile_count("d1") == 2 and s.drive_count == 2
    assert s.is_settled() and s.next_jobs(10.0) == []
    s2 = _sched(model=True)
    s2.restore(
        {A: ["d0", "d1"], B: ["d1"]},
        estimates=[(A, ["d0", "d1"], "old"), (B, ["d1"], "old")],
        observations=obs,
        model_sig=sig,
        now=0.0,
    )
    assert not s2.is_settled()
    assert [(j.kind, j.key) for j in s2.next_jobs(10.0, limit=4)] == [(REMAP, A), (REMAP, B)]  # another model
    s3 = _sched()
    s3.restore({A: ["d0", "d1"], B: ["d1"]}, estimates=[(A, ["d0"], "")], now=0.0)
    assert [j.key for j in s3.next_jobs(0.0, limit=4)] == [B]  # A (1 -> 2) is not due; B was never mapped
    assert [(j.key, j.drive_ids) for j in s3.next_jobs(2.0, limit=4)] == [(A, ("d0", "d1"))]  # settling


def test_any_arrival_and_completion_order_settles_to_jobs_of_the_full_drive_sets():
    rng = random.Random(1)
    tiles = [(i, 0) for i in range(6)]
    drives = {f"d{i:02d}": rng.sample(tiles, rng.randint(1, 4)) for i in range(25)}
    for model in (False, True):
        s = _sched(model=model, settle=1.0)
        last: dict = {}
        in_work: list[Job] = []
        now = 0.0
        pending = list(drives.items())
        while pending or in_work or not s.is_settled():
            now += 0.3
            if pending and rng.random() < 0.6:
                did, keys = pending.pop(0)
                s.add_drive(did, keys, now)
            in_work += s.next_jobs(now, limit=2 - len(in_work))
            if in_work and rng.random() < 0.7:
                job = in_work.pop(rng.randrange(len(in_work)))
                s.finished(job, ok=True, observed=model and job.kind == MAP)
                if job.key is not None and job.kind in (MAP, REMAP):
                    last[job.key] = job
            assert now < 1000, "no progress"
        for key in tiles:
            want = tuple(sorted(d for d, ks in drives.items() if key in ks))
            if want:
                assert last[key].drive_ids == want
                assert last[key].kind == (REMAP if model else MAP)
        assert s.pending_tiles() == 0


def test_a_drive_is_integrated_once_every_tile_it_touches_is_mapped_with_it():
    from hdmap_core.live.progress import integrated_drives

    # a covers 2 tiles, b 1, c 3 (one of c's tiles has no estimate yet)
    tiles = [(("a", "b", "c"), (2, 1, 3)), (("a", "c"), (2, 3))]
    assert integrated_drives(tiles) == {"a", "b"}
    assert integrated_drives(tiles + [(("c",), (3,))]) == {"a", "b", "c"}
    assert integrated_drives([(("a",), (2,)), (("b",), ())]) == {"b"}  # no counts: vouches for itself
    assert integrated_drives([]) == set()


def test_only_estimates_made_as_the_settled_map_makes_them_are_final():
    s = _sched(model=False)
    s.add_drive("d0", [A], now=0.0)
    assert all(j.final for j in _drain(s, 0.0))  # without the fleet model every estimate is final
    s = _sched(model=True, settle=1.0)
    s.add_drive("d0", [A], now=0.0)
    arrival = _drain(s, 0.0, observed=True)
    assert [(j.kind, j.final) for j in arrival] == [(MAP, False)]  # its own adjustment: not final
    settle = _drain(s, 2.0)
    assert [(j.kind, j.final) for j in settle] == [(MODEL, False), (REMAP, True)]


def test_the_maps_status_completes_the_mappers_and_settles_only_when_every_estimate_is_stitched():
    from hdmap_core.live.progress import LiveStatus, map_status

    mapper = LiveStatus(drives_received=10, drives_rejected=1, tiles_pending=0, tile_versions=40, settled=True)
    st = map_status(mapper, map_version=3, drives_integrated=10, tile_versions=38, tiles_unstitched=2, stitched=True)
    assert (st.drives_received, st.drives_integrated, st.drives_rejected, st.tiles_pending) == (10, 10, 1, 2)
    assert not st.settled  # two estimates of the mapper are not in the stitcher's store yet
    st = map_status(mapper, map_version=4, drives_integrated=10, tile_versions=40, tiles_unstitched=0, stitched=True)
    assert st.settled and st.map_version == 4 and st.same(replace(st, stamp_ns=5)) and not st.same(None)
    busy = replace(mapper, settled=False, tiles_pending=3)
    assert not map_status(
        busy, map_version=4, drives_integrated=9, tile_versions=40, tiles_unstitched=0, stitched=True
    ).settled


def _cells(key, xs):
    return {key: {(x, 0) for x in xs}}


def test_new_road_in_a_mapped_tile_is_due_at_once_mapped_road_waits_for_the_settle():
    s = _sched(model=True, settle=5.0)
    for i in range(3):
        s.add_drive(f"d{i}", [A], now=0.0, cells=_cells(A, range(0, 10)))
    assert [len(j.drive_ids) for j in _drain(s, 0.0, observed=True)] == [3]
    for i in range(5):  # more drives on the same road: nothing until the settle re-makes the tile
        s.add_drive(f"e{i}", [A], now=1.0, cells=_cells(A, range(0, 10)))
    assert s.next_jobs(1.0) == [] and s.pending_tiles() == 1
    s.add_drive("ramp", [A], now=2.0, cells=_cells(A, range(8, 12)))  # 2 cells of new road
    (job,) = _run(s, 2.0, observed=True)
    assert job.kind == MAP and len(job.drive_ids) == 9 and not job.final
    s.add_drive("wiggle", [A], now=3.0, cells=_cells(A, [12]))  # one new cell: not new road
    assert s.next_jobs(3.0) == []
    settle = _drain(s, 9.0)
    assert [j.kind for j in settle] == [OBSERVE, MODEL, REMAP] and len(settle[-1].drive_ids) == 10


def test_without_the_model_new_road_is_due_at_once_beside_the_growth_rule():
    s = _sched(model=False)
    for i in range(10):
        s.add_drive(f"d{i}", [A, B], now=0.0, cells={**_cells(A, range(5)), **_cells(B, range(5))})
    _drain(s, 0.0)
    s.add_drive("x", [A, B], now=1.0, cells={**_cells(A, range(5)), **_cells(B, range(5, 8))})
    assert [(j.key, len(j.drive_ids)) for j in s.next_jobs(1.0, limit=4)] == [(B, 11)]  # A: one drive, old road


def test_prefer_picks_the_settle_job_a_worker_holds_the_observations_of():
    s = _sched(model=True, settle=1.0)
    for i in range(3):
        s.add_drive(f"d{i}", [A, B, C], now=0.0)
    _drain(s, 0.0, observed=True)
    (model,) = s.next_jobs(2.0)
    s.finished(model, ok=True)
    # the worker asking holds C's and B's observation pass: C first, then B, then whatever is left
    first = s.next_jobs(2.0, prefer=lambda k: k in (B, C))
    second = s.next_jobs(2.0, prefer=lambda k: k in (B, C))
    third = s.next_jobs(2.0, prefer=lambda k: k in (B, C))
    assert [(j.kind, j.key) for j in first + second + third] == [(REMAP, B), (REMAP, C), (REMAP, A)]
    for j in first + second + third:
        s.finished(j, ok=True)
    assert s.is_settled()
    # before the settle, prefer changes nothing: new tiles go first in key order
    s.add_drive("n", [(5, 0), (4, 0)], now=3.0)
    assert [j.key for j in s.next_jobs(3.0, prefer=lambda k: k == (5, 0))] == [(4, 0)]


def test_the_region_settle_is_one_job_of_every_tile_and_drops_the_previews_it_makes_anyway():
    s = LiveScheduler(CFG, use_fleet_model=True, settle_after_s=1.0, region_max_drives=10)
    for i in range(3):
        s.add_drive(f"d{i}", [A, B], now=0.0)
    assert s.next_jobs(0.0) == [] and s.next_jobs(0.49) == []  # a burst: no preview until it pauses
    (first,) = s.next_jobs(0.5)  # while drives come: a new tile's preview
    assert first.kind == MAP and not first.final
    s.add_drive("e", [B, C], now=0.5)
    (second,) = s.next_jobs(1.0)  # not idle yet: previews go on
    assert second.kind == MAP and s.queued() == {A, B, C}
    s.finished(first, ok=True, observed=True)
    s.finished(second, ok=True, observed=True)
    assert s.queued() == {C}
    # idle: B and C are not previewed any more, the region makes them; it waits for no job in work
    (region,) = s.next_jobs(1.5, limit=4)
    assert region.kind == REGION and region.key is None and region.final
    assert region.tiles == ((A, ("d0", "d1", "d2")), (B, ("d0", "d1", "d2", "e")), (C, ("e",)))
    assert region.drive_ids == ("d0", "d1", "d2", "e") and region.sig == s.region_sig() != ""
    assert s.next_jobs(1.5, limit=4) == [] and not s.is_settled()
    s.add_drive("f", [C, (3, 0)], now=1.6)  # a drive during the region: its new tile goes at once,
    (new,) = s.next_jobs(1.6, limit=4)  # C waits behind the region
    assert (new.kind, new.key) == (MAP, (3, 0))
    s.finished(new, ok=True, observed=True)
    s.finished(region, ok=True)
    assert not s.is_settled() and s.queued() == {C}  # C is behind its drives, (3, 0) not made by a region
    (again,) = s.next_jobs(3.0, limit=4)
    assert again.kind == REGION and dict(again.tiles)[C] == ("e", "f") and again.sig != region.sig
    s.finished(again, ok=True)
    assert s.is_settled() and s.pending_tiles() == 0 and s.next_jobs(10.0, limit=4) == []


def test_a_failed_region_falls_back_to_the_three_phases_and_too_many_drives_never_use_it():
    s = LiveScheduler(CFG, use_fleet_model=True, settle_after_s=1.0, region_max_drives=10)
    s.add_drive("d0", [A, B], now=0.0)
    _drain(s, 0.0, observed=True)
    (region,) = s.next_jobs(1.0, limit=4)
    assert region.kind == REGION
    s.finished(region, ok=False)
    (model,) = s.next_jobs(1.0, limit=4)
    assert model.kind == MODEL
    s.finished(model, ok=True)
    assert sorted(j.kind for j in _drain(s, 1.0)) == [REMAP, REMAP] and s.is_settled()
    big = LiveScheduler(CFG, use_fleet_model=True, settle_after_s=1.0, region_max_drives=1)
    for d in ("d0", "d1"):
        big.add_drive(d, [A], now=0.0)
    _drain(big, 0.0, observed=True)
    assert [j.kind for j in big.next_jobs(1.0, limit=4)] == [MODEL]


def test_restore_of_a_settled_region_is_settled_and_other_drive_sets_are_not():
    s = LiveScheduler(CFG, use_fleet_model=True, settle_after_s=1.0, region_max_drives=10)
    for d in ("d0", "d1"):
        s.add_drive(d, [A, B], now=0.0)
    _drain(s, 0.0, observed=True)
    (region,) = _run(s, 1.0)
    assert region.kind == REGION and s.is_settled()
    t = LiveScheduler(CFG, use_fleet_model=True, settle_after_s=1.0, region_max_drives=10)
    t.restore({A: ["d0", "d1"], B: ["d0", "d1"]}, [(k, ids, region.sig) for k, ids in region.tiles], now=0.0)
    assert t.is_settled() and t.next_jobs(5.0, limit=4) == []
    u = LiveScheduler(CFG, use_fleet_model=True, settle_after_s=1.0, region_max_drives=10)
    u.restore({A: ["d0", "d1"], B: ["d0", "d1", "d2"]}, [(k, ids, region.sig) for k, ids in region.tiles], now=0.0)
    assert not u.is_settled() and [j.kind for j in u.next_jobs(5.0, limit=4)] == [REGION]


def _settled_region(n: int, keys=(A, B)) -> LiveScheduler:
    s = LiveScheduler(CFG, use_fleet_model=True, settle_after_s=1.0, region_max_drives=100, fast_path=True)
    for i in range(n):
        s.add_drive(f"d{i:02d}", keys, now=0.0, cells={k: {(0, 0)} for k in keys})
    _drain(s, 0.0, observed=True)
    (region,) = s.next_jobs(1.0, limit=4)
    s.finished(region, ok=True)
    assert s.is_settled()
    return s


def test_fast_path_a_drive_on_settled_road_is_one_fuse_job_then_the_settle_re_makes_every_tile():
    s = _settled_region(12)
    s.add_drive("new", [A, B], now=2.0, cells={A: {(0, 0)}, B: {(0, 0)}})
    assert s.queued() == set() and s.fast_pending() == 1 and not s.is_settled()
    (fuse,) = s.next_jobs(2.0, limit=4)  # at once, not after settle_after_s
    assert fuse.kind == FUSE and fuse.drive_ids == ("new",) and fuse.final
    assert dict(fuse.tiles)[A] == tuple(sorted([f"d{i:02d}" for i in range(12)] + ["new"]))
    assert s.next_jobs(2.0, limit=4) == []  # its tiles are in work
    s.finished(fuse, ok=True)
    assert not s.is_settled() and s.pending_tiles() == 0  # listed (final), not the settle's
    (region,) = s.next_jobs(3.5, limit=4)  # idle: the settle re-makes every tile as before
    assert region.kind == REGION and "new" in region.drive_ids
    s.finished(region, ok=True)
    assert s.is_settled()


def test_fast_path_is_refused_on_new_road_thin_support_too_many_fused_or_changed_tiles():
    s = _settled_region(12)
    s.add_drive("ramp", [A, B], now=2.0, cells={A: {(0, 0), (5, 5), (5, 6)}, B: {(0, 0)}})  # new road in A
    assert s.fast_pending() == 0 and s.queued() == {A, B}
    thin = _settled_region(3)  # FAST_MAX_SHARE of 3 drives: still one
    for x in ("x", "y"):
        thin.add_drive(x, [A], now=2.0, cells={A: {(0, 0)}})
    assert thin.fast_pending() == 1
    s = _settled_region(12)  # at most FAST_MAX_SHARE of 12 = 3 per tile between two settles
    for i in range(4):
        s.add_drive(f"f{i}", [A], now=2.0, cells={A: {(0, 0)}})
    assert s.fast_pending() == 3 and s.queued() == {A}
    s = _settled_region(12)
    s.add_drive("f", [A, C], now=2.0, cells={A: {(0, 0)}, C: {(0, 0)}})  # C never mapped
    assert s.fast_pending() == 0
    s.add_drive("g", [B], now=2.0, cells={B: {(0, 0)}})
    (fuse,) = s.next_jobs(2.0, limit=1)
    assert fuse.kind == FUSE and fuse.drive_ids == ("g",)
    s.finished(fuse, ok=False)  # refused by the fusion: the normal way
    assert B in s.queued() and s.fast_pending() == 0


def test_fast_path_a_drive_alone_on_new_road_is_one_part_job_of_its_tiles():
    s = _settled_region(12)
    s.add_drive("far", [(9, 9), (9, 10)], now=2.0, cells={(9, 9): {(1, 1)}})
    (part,) = s.next_jobs(2.0, limit=4)
    assert part.kind == PART and part.final and part.tiles == (((9, 9), ("far",)), ((9, 10), ("far",)))
    s.finished(part, ok=True)
    assert s.pending_tiles() == 0 and not s.is_settled()  # listed; the settle re-makes every tile
    (region,) = s.next_jobs(3.5, limit=4)
    assert region.kind == REGION and "far" in region.drive_ids
    # two drives on the same new road before the first is made: the normal way (previews)
    s.add_drive("n1", [(7, 7)], now=4.0, cells={(7, 7): {(1, 1)}})
    s.add_drive("n2", [(7, 7)], now=4.0, cells={(7, 7): {(1, 1)}})
    assert s.next_jobs(4.0, limit=1) == []  # a burst (the region settle): previewed once it pauses
    (job,) = s.next_jobs(4.5, limit=1)
    assert job.kind == MAP and not job.final and job.drive_ids == ("n1", "n2")


def test_input_done_settles_at_once_and_a_later_drive_waits_settle_after_s_again():
    s = LiveScheduler(CFG, use_fleet_model=True, settle_after_s=5.0, region_max_drives=10)
    for i in range(3):
        s.add_drive(f"d{i}", [A, B], now=0.0)
    s.add_drive("e", [B, C], now=0.1)
    assert s.next_jobs(0.2) == []  # a burst
    (first,) = s.next_jobs(0.7)  # input paused: a new tile's preview
    assert first.kind == MAP and not first.final
    assert not s.idle(0.7)
    s.input_done()  # the sender's input is in: the queued previews are dropped, the region comes
    assert s.next_jobs(0.7, limit=4) == []  # ... once the preview in work is done
    s.finished(first, ok=True, observed=True)
    assert s.idle(0.7)
    (region,) = s.next_jobs(0.7, limit=4)
    assert region.kind == REGION and [k for k, _ in region.tiles] == [A, B, C]
    s.finished(region, ok=True)
    assert s.is_settled()
    # a drive after all: its new tile is previewed, and the settle waits settle_after_s as usual
    s.add_drive("f", [C, (3, 0)], now=1.0)
    (new,) = s.next_jobs(1.0, limit=4)
    assert (new.kind, new.key, new.final) == (MAP, (3, 0), False)
    s.finished(new, ok=True, observed=True)
    assert s.next_jobs(5.9, limit=4) == [] and not s.idle(5.9)
    (again,) = s.next_jobs(6.0, limit=4)
    assert again.kind == REGION
    # without the fleet model: input_done settles (every stale tile final) at once too
    p = _sched(model=False, settle=5.0)
    p.add_drive("a", [A], now=0.0)
    _drain(p, 0.0)
    p.add_drive("b", [A], now=1.0)  # a mapped tile, grown too little to be due before the settle
    assert p.next_jobs(1.0) == []
    p.input_done()
    (settle,) = p.next_jobs(1.0)
    assert settle.kind == MAP and settle.final and settle.drive_ids == ("a", "b")


def test_a_burst_of_drives_is_not_previewed_with_the_region_settle_but_a_drive_alone_at_once():
    s = LiveScheduler(CFG, use_fleet_model=True, settle_after_s=5.0, region_max_drives=10)
    s.add_drive("a", [A], now=0.0)  # alone: at once
    (first,) = s.next_jobs(0.0)
    assert (first.kind, first.key, first.final) == (MAP, A, False)
    s.finished(first, ok=True, observed=True)
    s.add_drive("b0", [B, (3, 0)], now=10.0)  # the first of a burst looks alone: at once
    _drain(s, 10.0, observed=True)
    for i, t in enumerate((10.2, 10.4), start=1):  # the rest 0.2 s apart: a burst
        s.add_drive(f"b{i}", [B, (3 + i, 0)], now=t)
        assert s.next_jobs(t, limit=4) == []
    assert s.next_jobs(10.89, limit=4) == []
    jobs = s.next_jobs(10.9, limit=4)  # paused for BURST_GAP_S: the previews go on
    assert {j.key for j in jobs} == {(4, 0), (5, 0)} and not any(j.final for j in jobs)
    # without the region settle (too many drives, or no fleet model) a burst is mapped as it comes
    t = LiveScheduler(CFG, use_fleet_model=True, settle_after_s=5.0, region_max_drives=1)
    p = _sched(model=False)
    for sched in (t, p):
        sched.add_drive("x", [A], now=0.0)
        sched.add_drive("y", [B], now=0.1)
        assert {j.key for j in sched.next_jobs(0.1, limit=4)} == {A, B}


def test_while_the_input_is_open_nothing_is_previewed_and_no_drive_takes_the_fast_path():
    s = _settled_region(12)  # a settled map with the fast path on
    s.input_open()  # e.g. hdmap run playing a bag: more drives are on their way
    s.add_drive("on", [A, B], now=2.0, cells={A: {(0, 0)}, B: {(0, 0)}})  # settled road: would be fused
    s.add_drive("far", [(9, 9)], now=9.0, cells={(9, 9): {(1, 1)}})  # alone on new road: would be a PART
    assert s.fast_pending() == 0 and s.queued() == {A, B, (9, 9)}
    assert s.next_jobs(9.0, limit=4) == [] and s.next_jobs(9.9, limit=4) == []  # paused, still open: no preview
    s.input_done()  # the input is in: one region job makes every tile, previews dropped
    (region,) = s.next_jobs(9.9, limit=4)
    assert region.kind == REGION and {"on", "far"} <= set(region.drive_ids)
    s.finished(region, ok=True)
    assert s.is_settled()
    # the hold is for the region settle only: beyond region_max_drives drives, previews go on
    t = LiveScheduler(CFG, use_fleet_model=True, settle_after_s=5.0, region_max_drives=1)
    t.input_open()
    t.add_drive("x", [A], now=0.0)
    t.add_drive("y", [B], now=0.6)
    assert {j.key for j in t.next_jobs(2.0, limit=4)} == {A, B}
