"""Pivot passes on several processes: independent groups, exactly the one-process result."""

from __future__ import annotations

import logging
import os
import time

import numpy as np
import pytest

from hdmap_core.errors import ConfigError
from hdmap_core.parallel import ForkWorker, SpareWork, can_fork, split_order
from hdmap_core.pipeline import driver as pipeline
from hdmap_core.pipeline import presets
from hdmap_core.pipeline.driver import build_map, map_stretches, prepare_drives
from hdmap_core.pipeline.preprocess import preprocess
from hdmap_core.pipeline.sampling import pivot_groups, sample_pivot

from pipeline_fleet import make_drive

needs_fork = pytest.mark.skipif(not can_fork(), reason="no fork start method on this platform")


@pytest.fixture(scope="module")
def two_way_fleet():
    """A simulated two-carriageway motorway with ramps: drives both ways, exits and entries."""
    from hdmap_core.simulation.fleet import SimConfig, simulate_fleet
    from hdmap_core.simulation.synthetic import synthetic_highway

    gt = synthetic_highway("motorway_ramps", length_m=2000.0, seed=1)
    fleet = simulate_fleet(
        gt, config=SimConfig(n_drives=16, snippet_length_min_m=400.0, snippet_length_max_m=900.0), seed=3
    )
    drives, rejected = prepare_drives(fleet.drives)
    assert not rejected
    return drives


def test_opposite_directions_and_distant_stretches_are_separate_groups():
    drives = [
        make_drive("a", lane=0.0, bias=0.0, s0=0.0, s1=300.0),
        make_drive("b", lane=3.5, bias=0.3, s0=100.0, s1=400.0),  # overlaps a, same way
        make_drive("c", lane=0.0, bias=0.0, s0=0.0, s1=300.0, reverse=True),  # a's road, other way
        make_drive("d", lane=0.0, bias=0.0, s0=900.0, s1=1200.0),  # same way, 500 m further on
    ]
    cfg = presets.preset("default")
    group = pivot_groups(preprocess(drives, config=cfg.preprocess), drives, config=cfg.sampling)
    assert group[0] == group[1]
    assert len({group[0], group[2], group[3]}) == 3


def test_no_pivot_samples_a_drive_of_another_group(two_way_fleet):
    """The grouping is conservative: every drive a pivot's cut lines sample is in its group."""
    cfg = presets.preset("default")
    index = preprocess(two_way_fleet, config=cfg.preprocess)
    group = pivot_groups(index, two_way_fleet, config=cfg.sampling)
    assert group.max() >= 1  # the two carriageways at least
    for i, pivot in enumerate(two_way_fleet):
        ps = sample_pivot(index, pivot, config=cfg.sampling)
        assert len(ps.drive) > 0
        assert set(group[np.unique(ps.drive)].tolist()) == {group[i]}


def test_split_order_keeps_the_global_order_and_balances_whole_groups():
    order = np.array([5, 0, 3, 1, 4, 2])
    group = np.array([0, 1, 0, 2, 1, 2])
    weight = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 5.0])  # group 2 weighs 6, groups 0 and 1 two each
    shares = split_order(order, group, weight, 2)
    assert [s.tolist() for s in shares] == [[5, 3], [0, 1, 4, 2]]
    assert len(split_order(order, np.zeros(6, np.int64), weight, 2)) == 1  # one group: one share
    assert [s.tolist() for s in split_order(order, group, weight, 1)] == [order.tolist()]


def _same_segments(a, b):
    assert [s.pivot_id for s in a] == [s.pivot_id for s in b]
    for sa, sb in zip(a, b):
        assert len(sa.steps) == len(sb.steps)
        for x, y in zip(sa.steps, sb.steps):
            assert x.index == y.index and x.processed_before == y.processed_before
            np.testing.assert_array_equal(x.lateral_m, y.lateral_m)
            np.testing.assert_array_equal(x.types, y.types)


@pytest.mark.slow
@needs_fork
@pytest.mark.parametrize("preset", ["default", "naive"])  # two passes with the adjustment; one pass
def test_two_workers_give_exactly_the_one_process_result(two_way_fleet, preset):
    cfg = presets.preset(preset)
    group = pivot_groups(preprocess(two_way_fleet, config=cfg.preprocess), two_way_fleet, config=cfg.sampling)
    assert group.max() >= 1  # more than one group: the pivots really run in two processes
    one = map_stretches(two_way_fleet, config=cfg, seed=2, collect_observations=True, workers=1)
    two = map_stretches(two_way_fleet, config=cfg, seed=2, collect_observations=True, workers=2)
    assert "grouping" in two.stage_seconds and "grouping" not in one.stage_seconds
    _same_segments(one.segments, two.segments)
    assert one.counters == two.counters
    assert one.processed.intervals == two.processed.intervals
    assert [(o.pivot_id, o.index) for o in one.observations] == [(o.pivot_id, o.index) for o in two.observations]
    for x, y in zip(one.observations, two.observations):
        np.testing.assert_array_equal(x.offsets_m, y.offsets_m)
    m1 = build_map(two_way_fleet, config=cfg, seed=2, workers=1).map
    m2 = build_map(two_way_fleet, config=cfg, seed=2, workers=2).map
    assert [(f.id, f.type, f.predecessors, f.successors) for f in m1.features] == [
        (f.id, f.type, f.predecessors, f.successors) for f in m2.features
    ]
    for f1, f2 in zip(m1.features, m2.features):
        np.testing.assert_array_equal(f1.points, f2.points)
        np.testing.assert_array_equal(f1.lateral_std, f2.lateral_std)


@pytest.mark.slow
@needs_fork
def test_a_failing_worker_is_taken_over_with_the_same_result(two_way_fleet, monkeypatch, caplog):
    cfg = presets.preset("default")
    want = map_stretches(two_way_fleet, config=cfg, seed=2, workers=1)
    parent = os.getpid()
    real = pipeline.run_pass

    def fails_in_child(*args, **kwargs):
        if os.getpid() != parent:
            raise RuntimeError("boom in the worker")
        return real(*args, **kwargs)

    monkeypatch.setattr(pipeline, "run_pass", fails_in_child)
    with caplog.at_level(logging.WARNING, logger="hdmap_core.parallel"):
        got = map_stretches(two_way_fleet, config=cfg, seed=2, workers=2)
    assert "boom in the worker" in caplog.text and "in this process instead" in caplog.text
    _same_segments(want.segments, got.segments)
    assert want.counters == got.counters


def _same_model(a, b):
    assert list(a.drives) == list(b.drives) and a.drives
    for d, x in a.drives.items():
        y = b.drives[d]
        assert (x.k0, x.bias_m) == (y.k0, y.bias_m)
        np.testing.assert_array_equal(x.drift_m, y.drift_m)


@pytest.fixture(scope="module")
def one_process_run(two_way_fleet):
    return map_stretches(two_way_fleet, config=presets.preset("default"), seed=2, workers=1)


@pytest.mark.slow
@needs_fork
def test_the_adjustment_runs_over_the_workers_shares_with_the_one_process_offsets(two_way_fleet, one_process_run):
    """Without collect_observations each worker keeps its share's observations and holds a part
    of the one solve (adjustment_dist): the offsets are the one process's to the last bit."""
    got = map_stretches(two_way_fleet, config=presets.preset("default"), seed=2, workers=2)
    assert got.offset_model.stats["parts"] == 2 and "parts" not in one_process_run.offset_model.stats
    _same_model(one_process_run.offset_model, got.offset_model)
    _same_segments(one_process_run.segments, got.segments)
    assert got.observations == []  # they stayed in the workers


@pytest.mark.slow
@needs_fork
@pytest.mark.parametrize("method", ["set_fleet", "reweigh"])  # at its start; in the middle of a fit
def test_a_worker_lost_in_the_adjustment_is_taken_over_with_the_same_result(
    two_way_fleet, one_process_run, monkeypatch, caplog, method
):
    from hdmap_core.pipeline.adjustment_dist import AdjustPart

    parent = os.getpid()
    real = getattr(AdjustPart, method)

    def fails_in_child(self, *args):
        if os.getpid() != parent:
            os._exit(5)  # the worker dies
        return real(self, *args)

    monkeypatch.setattr(AdjustPart, method, fails_in_child)
    with caplog.at_level(logging.WARNING, logger="hdmap_core.parallel"):
        got = map_stretches(two_way_fleet, config=presets.preset("default"), seed=2, workers=2)
    assert "exit code 5" in caplog.text
    assert "parts" not in got.offset_model.stats  # the one solve, here
    _same_model(one_process_run.offset_model, got.offset_model)
    _same_segments(one_process_run.segments, got.segments)
    assert one_process_run.counters == got.counters


@needs_fork
def test_fork_worker_reports_a_dead_child_as_failed(caplog):
    def job(channel):
        os._exit(3)

    with caplog.at_level(logging.WARNING, logger="hdmap_core.parallel"), ForkWorker(job) as w:
        assert w.result() is None
    assert w.failed and "exit code 3" in caplog.text


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2"])
def test_workers_must_be_a_positive_integer(two_way_fleet, bad):
    with pytest.raises(ConfigError, match="workers"):
        map_stretches(two_way_fleet[:2], config=presets.preset("paper"), workers=bad)


@pytest.mark.slow
@needs_fork
def test_no_worker_process_possible_runs_everything_here(two_way_fleet, monkeypatch, caplog):
    """E.g. inside a daemonic multiprocessing worker, which may not start children."""
    import multiprocessing.context

    cfg = presets.preset("naive")
    want = build_map(two_way_fleet, config=cfg, seed=2, workers=1).map

    def refuse(self):
        raise AssertionError("daemonic processes are not allowed to have children")

    monkeypatch.setattr(multiprocessing.context.ForkProcess, "start", refuse)
    with caplog.at_level(logging.WARNING, logger="hdmap_core.parallel"):
        got = build_map(two_way_fleet, config=cfg, seed=2, workers=2).map
    assert "cannot start a worker process" in caplog.text
    assert [(f.id, f.predecessors, f.successors) for f in want.features] == [
        (f.id, f.predecessors, f.successors) for f in got.features
    ]
    for a, b in zip(want.features, got.features):
        np.testing.assert_array_equal(a.points, b.points)


def test_balance_gives_the_heaviest_first_to_the_least_loaded_share():
    from hdmap_core.parallel import balance

    assert balance(np.array([1.0, 5.0, 2.0, 2.0]), 2).tolist() == [1, 0, 1, 1]
    assert balance(np.array([3.0]), 4).tolist() == [0]


@needs_fork
def test_map_balanced_returns_results_in_item_order_from_two_processes():
    from hdmap_core.parallel import map_balanced

    got = map_balanced(lambda i: (i * i, os.getpid()), [1.0, 4.0, 1.0, 2.0, 3.0], 2)
    assert [v for v, _ in got] == [0, 1, 4, 9, 16]
    assert len({pid for _, pid in got}) == 2 and os.getpid() in {pid for _, pid in got}


# A parent that makes a spawn_pool, hands its worker a job that outlives it, prints the worker's
# pid and kills itself with SIGKILL (no clean-up runs).
# A parent that starts a worker (a spawn_pool's, or a ForkWorker waiting for the parent's next
# message), hands it work that outlives the parent, prints the worker's pid and kills itself with
# SIGKILL (no clean-up runs).
_KILLED_PARENT = """
import os, signal, sys, time
from hdmap_core.parallel import ForkWorker, spawn_pool

def busy():
    time.sleep(60)

def waits(channel):
    channel.send(os.getpid())
    channel.recv()

if __name__ == "__main__":
    if sys.argv[1] == "spawn_pool":
        pool = spawn_pool()
        pid = pool.submit(os.getpid).result()
        pool.submit(busy)
    else:
        pid = ForkWorker(waits).result()
    print(pid, flush=True)
    os.kill(os.getpid(), signal.SIGKILL)
"""


def _alive(pid: int) -> bool:
    """Running (not gone, not a zombie waiting for a reaper that never comes in a container)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            state = next(line for line in f if line.startswith("State:"))
    except (FileNotFoundError, ProcessLookupError, StopIteration):
        return False
    return "Z" not in state.split()[1]


@pytest.mark.slow
@pytest.mark.skipif(not (os.path.isdir("/proc") and can_fork()), reason="reads /proc, forks")
@pytest.mark.parametrize("kind", ["spawn_pool", "fork_worker"])
def test_a_worker_ends_when_its_parent_is_killed(tmp_path, kind):
    import subprocess  # noqa: PLC0415
    import sys  # noqa: PLC0415
    import time  # noqa: PLC0415

    script = tmp_path / "parent.py"
    script.write_text(_KILLED_PARENT)
    src = os.path.join(os.path.dirname(__file__), "..", "..", "src", "hdmap_core")
    env = {**os.environ, "PYTHONPATH": os.path.abspath(src)}
    # the worker inherits stdout: read the pid line, not to EOF
    with subprocess.Popen([sys.executable, str(script), kind], stdout=subprocess.PIPE, text=True, env=env) as parent:
        assert parent.stdout is not None
        worker = int(parent.stdout.readline())
        assert parent.wait(timeout=120) == -9
    try:
        deadline = time.monotonic() + 30  # a liveness bound, not a timing figure: it ends in ~0.5 s
        while _alive(worker) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _alive(worker), f"the {kind} worker outlived its killed parent"
    finally:
        if _alive(worker):
            os.kill(worker, 9)


@pytest.mark.skipif(not can_fork(), reason="needs fork")
def test_spare_work_gives_what_it_finished_computed_at_the_lowest_priority():
    def fn(i):
        return i, np.arange(i, dtype=float), os.nice(0)

    with SpareWork(fn, 5) as spare:
        done = spare.take(wait=True)
        assert spare.take() == {}  # taken once
    assert sorted(done) == list(range(5))
    for i, (j, values, niceness) in done.items():
        assert j == i and np.array_equal(values, np.arange(i, dtype=float))
        assert niceness == 19


@pytest.mark.skipif(not can_fork(), reason="needs fork")
def test_spare_work_stopped_early_gives_only_finished_items(tmp_path):
    started = tmp_path / "started_2"

    def fn(i):
        if i == 2:
            started.touch()  # items 0 and 1 are written by now
            time.sleep(3600)  # stopped here by take()
        return i * i

    spare = SpareWork(fn, 4)
    deadline = time.monotonic() + 30
    while not started.exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    t0 = time.monotonic()
    assert spare.take() == {0: 0, 1: 1}
    assert time.monotonic() - t0 < 5
