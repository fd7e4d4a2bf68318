"""The executor of a standalone node: rclpy's MultiThreadedExecutor without its busy loop.

A node's receiving callbacks have their own callback group, so that they stay responsive while
its worker callback maps or stitches (``run_node`` spins two threads). rclpy's
``MultiThreadedExecutor`` (Jazzy's, as the PyPI wheels ship it) spins in a loop whenever a
thread is slow to start a callback, which under the GIL is the rule, not the exception:

1. every ``spin_once`` first yields the tasks it listed as in progress that are "not executing
   and not done" and then skips the wait, so a task waiting in the thread pool's queue is
   yielded and submitted again and again (ros2/rclpy#1452, fixed upstream by ros2/rclpy#1547);
2. a callback group counts as busy only once a thread runs its callback, so until then the
   next wait set holds the group's other entities (the worker's guard condition beside its
   timer), which are yielded only to fail to start, each failure waking the executor again.

Both loops take the GIL from the callbacks they wait for. Here a task leaves the list when it is
handed to the pool, and ``spin_once`` returns once a thread has started it, so that the next
wait set sees its group busy. A task that comes back undone (a coroutine callback awaiting a
future) is listed again to be resumed, as rclpy does.
"""

from __future__ import annotations

import threading

from rclpy.executors import (
    ConditionReachedException,
    ExternalShutdownException,
    MultiThreadedExecutor,
    ShutdownException,
    TimeoutException,
)

__all__ = ["NodeExecutor"]


class NodeExecutor(MultiThreadedExecutor):
    """``MultiThreadedExecutor`` that hands each ready callback to its threads once."""

    def _spin_once_impl(self, timeout_sec=None, wait_condition=lambda: False) -> None:
        try:
            handler, entity, node = self.wait_for_ready_callbacks(timeout_sec, None, wait_condition)
        except (ExternalShutdownException, ShutdownException, TimeoutException, ConditionReachedException):
            return
        with self._tasks_lock:  # in the pool now: not to be yielded again while it waits for a thread
            self._tasks = [t for t in self._tasks if t[0] is not handler]
        started = threading.Event()
        self._executor.submit(self._run, handler, entity, node, started)
        self._futures.append(handler)
        while not started.wait(0.1) and not self._is_shutdown:  # the next wait set is built once
            pass  # its callback group is taken (all threads busy: waits for one, as nothing else could run)
        for future in self._futures[:]:
            if future.done():
                self._futures.remove(future)
                future.result()  # raise any exceptions, as rclpy does

    def _run(self, task, entity, node, started: threading.Event) -> None:
        started.set()
        task()
        if not task.done():  # a coroutine waiting for a future: listed again to be resumed
            with self._tasks_lock:
                self._tasks.append((task, entity, node))
            self._guard.trigger()
