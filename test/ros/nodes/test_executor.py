"""nodes/executor.NodeExecutor: every ready callback handed to the threads once, callbacks of two
groups still concurrent, a coroutine callback still resumed."""

from __future__ import annotations

import threading
import time

import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.task import Future  # noqa: E402

from hdmap_ros.nodes.executor import NodeExecutor  # noqa: E402


class _Counting(NodeExecutor):
    """Counts what ``spin_once`` hands to the threads."""

    handed = 0

    def wait_for_ready_callbacks(self, *args, **kwargs):
        got = super().wait_for_ready_callbacks(*args, **kwargs)
        self.handed += 1
        return got


@pytest.fixture
def node(ros):
    """A node in the harness's context, spun by the executor under test (not by the harness's)."""
    n = Node("executor_probe", context=ros.context)
    yield n
    n.destroy_node()


def _spin(node, until, executor_cls=NodeExecutor, timeout=10.0):
    """Spin ``node`` on a new two-thread ``executor_cls`` until ``until()`` (or ``timeout``); the
    executor, shut down."""
    executor = executor_cls(num_threads=2, context=node.context)
    executor.add_node(node)
    end = time.monotonic() + timeout
    try:
        while not until() and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
    finally:
        executor.shutdown()
    return executor


def test_a_busy_group_is_not_handed_out_again_and_again(node):
    """A worker that holds the GIL (as mapping in Python does) in a group with a timer and a guard
    condition: rclpy's MultiThreadedExecutor hands the waiting work out hundreds of times a second
    while a thread is slow to start it (24 hand-outs for 8 runs when tested); once each here."""
    group = MutuallyExclusiveCallbackGroup()
    runs, ended = [], []

    def work():
        runs.append(time.monotonic())
        end = time.monotonic() + 0.1
        while time.monotonic() < end:  # pure Python: holds the GIL but for the switch interval
            sum(range(1000))
        if len(runs) < 8:
            wake.trigger()  # as the mapper's collect wakes the next turn
        else:
            timer.cancel()
        ended.append(1)

    timer = node.create_timer(0.05, work, callback_group=group)
    wake = node.create_guard_condition(work, callback_group=group)
    executor = _spin(node, lambda: len(ended) >= 8, _Counting)
    assert len(runs) >= 8
    # each run was handed out once; the last hand-out may still wait for its thread
    assert executor.handed <= len(runs) + 2, (executor.handed, len(runs))


def test_callbacks_of_two_groups_still_run_at_once(node):
    """The receiving group stays responsive while the worker's callback runs: the worker waits
    for an event only the other group's callback sets."""
    released = threading.Event()
    done = []

    def worker():
        done.append(released.wait(5.0))

    node.create_timer(0.01, worker, callback_group=MutuallyExclusiveCallbackGroup())
    node.create_timer(0.05, released.set, callback_group=MutuallyExclusiveCallbackGroup())
    _spin(node, lambda: bool(done))
    assert done and done[0] is True


def test_a_coroutine_callback_is_resumed_when_its_future_is_done(node):
    future = Future()
    finished = []

    async def waiter():
        if not finished:
            finished.append(await future)

    def setter():
        if not future.done():
            future.set_result("set")

    t = node.create_timer(0.01, waiter, callback_group=MutuallyExclusiveCallbackGroup())
    node.create_timer(0.2, setter, callback_group=MutuallyExclusiveCallbackGroup())
    try:
        _spin(node, lambda: bool(finished))
    finally:
        t.cancel()
    assert finished == ["set"]
