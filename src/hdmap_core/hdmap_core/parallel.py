"""Work on more than one core, with the same result as one core: generic execution only.

This module knows nothing of the pipeline. What may run apart is decided by the caller: for the
pivot passes, ``pipeline.sampling.pivot_groups`` unites drives that may meet on a cut line into
independent groups; ``split_order`` cuts the global pivot order into shares of whole groups, and
each share runs in its own process in that order, so the merged result is the one-process result.

``SpareWork`` computes items ahead in a forked child at the lowest priority, on the CPU time the
other processes leave idle (e.g. the second core while a 2-core run does serial work); the caller
takes what it finished and computes the rest itself: the same results either way.

``ForkWorker`` runs one share of the groups in a forked child process (Linux/Unix ``fork``: the
child inherits the detection index and the drives, nothing is pickled on the way in; results come
back through a pipe). A child that fails for any reason is reported by ``result()`` returning
None, and the caller then runs that share itself: the result stays the same, only slower.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import multiprocessing
import os
import pickle
import struct
import tempfile
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np

try:  # threadpoolctl comes with scikit-learn
    from threadpoolctl import threadpool_limits
except ImportError:  # pragma: no cover
    threadpool_limits = None

__all__ = [
    "ForkWorker",
    "SpareWork",
    "available_cpus",
    "balance",
    "can_fork",
    "exit_with_parent",
    "map_balanced",
    "one_blas_thread",
    "run_shares",
    "spawn_pool",
    "split_order",
]

_LOG = logging.getLogger(__name__)


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover (not Linux)
        return max(1, os.cpu_count() or 1)


def one_blas_thread() -> contextlib.AbstractContextManager:
    """BLAS on one thread inside the ``with``: small dense solves only pay multithreaded BLAS's
    sync overhead, and on a small shared machine its threads thrash (measured: 3.6 ms per 55 x 55
    solve with 2 threads on a loaded 2-core machine; a dense inverse 20x slower)."""
    return threadpool_limits(limits=1, user_api="blas") if threadpool_limits is not None else contextlib.nullcontext()


def can_fork() -> bool:
    return "fork" in multiprocessing.get_all_start_methods()


def balance(weight: np.ndarray, parts: int) -> np.ndarray:
    """(N,) share (0..parts-1) per item: heaviest item first, each to the least loaded share
    (ties: the lower share). Share 0 carries the heaviest first item."""
    weight = np.asarray(weight, dtype=float)
    load = np.zeros(max(1, min(parts, len(weight))))
    share = np.zeros(len(weight), dtype=np.int64)
    for i in np.argsort(-weight, kind="stable"):
        k = int(np.argmin(load))
        share[i] = k
        load[k] += weight[i]
    return share


def split_order(order: np.ndarray, group: np.ndarray, weight: np.ndarray, parts: int) -> list[np.ndarray]:
    """The pivot order split into at most ``parts`` shares of whole groups, each in global order.

    Groups are ``balance``d by their summed weight (e.g. the drives' lengths). Empty shares are
    dropped; the first share is the heaviest.
    """
    order = np.asarray(order, dtype=np.int64)
    n_groups = int(group.max()) + 1 if len(group) else 0
    gw = np.bincount(group, weights=weight, minlength=n_groups)
    share_of = balance(gw, parts)
    load = np.bincount(share_of, weights=gw, minlength=int(share_of.max()) + 1 if n_groups else 0)
    shares = [order[share_of[group[order]] == p] for p in np.argsort(-load, kind="stable")]
    return [s for s in shares if len(s)]


def map_balanced(fn: Callable[[int], Any], weight: Sequence[float], workers: int) -> list[Any]:
    """``[fn(i) for i in range(len(weight))]``, the items ``balance``d by ``weight`` over
    ``workers`` processes (``run_shares``); the results in item order."""
    n = len(weight)
    if workers < 2 or n < 2:
        return [fn(i) for i in range(n)]
    share_of = balance(np.asarray(weight, dtype=float), workers)
    shares = [np.flatnonzero(share_of == k) for k in range(int(share_of.max()) + 1)]
    out: list[Any] = [None] * n
    for items, results in zip(shares, run_shares(lambda items: [fn(int(i)) for i in items], shares)):
        for i, r in zip(items, results):
            out[int(i)] = r
    return out


def run_shares(fn: Callable[[Any], Any], shares: Sequence[Any]) -> list[Any]:
    """``[fn(share) for share in shares]``, the first share here, the others in forked workers
    (where ``fork`` exists); a failed worker's share is computed here instead."""
    if len(shares) < 2 or not can_fork():
        return [fn(share) for share in shares]

    def job(channel: Any, share: Any) -> None:
        channel.send(fn(share))

    workers = [ForkWorker(functools.partial(job, share=sh)) for sh in shares[1:]]
    try:
        out = [fn(shares[0])]
        for w, share in zip(workers, shares[1:]):
            got = w.result()
            out.append(fn(share) if w.failed else got)
        return out
    finally:
        for w in workers:
            w.close()


class ForkWorker:
    """A forked child process that runs ``job(channel)`` and sends its results back.

    ``job`` runs in the child with a ``channel`` that has ``send(obj)`` (to the parent) and
    ``recv()`` (from the parent). The parent reads with ``result()`` and writes with ``send()``.
    ``result()`` returns None when the child failed (exception, death, closed pipe): the caller
    then does the work itself.
    """

    def __init__(self, job: Callable[[Any], None]) -> None:
        ctx = multiprocessing.get_context("fork")
        self._conn, child_conn = ctx.Pipe(duplex=True)
        self.failed = False
        self._proc: multiprocessing.process.BaseProcess | None = ctx.Process(
            target=_child_main, args=(job, child_conn, self._conn, os.getpid()), daemon=True
        )
        try:
            self._proc.start()
        except (AssertionError, OSError) as err:  # e.g. a daemonic process may not have children
            self._proc = None
            self._fail(f"cannot start a worker process: {err!r}")
        finally:
            child_conn.close()

    def send(self, obj: Any) -> None:
        if self.failed:
            return
        try:
            self._conn.send(obj)
        except (OSError, ValueError) as err:
            self._fail(f"cannot send to the worker: {err}")

    def result(self) -> Any:
        """The child's next message, or None if it failed (logged with the reason)."""
        if self.failed:
            return None
        try:
            kind, payload = self._conn.recv()
        except (EOFError, OSError) as err:
            code = None
            if self._proc is not None:
                self._proc.join(timeout=1)
                code = self._proc.exitcode
            self._fail(f"the worker process ended without a result (exit code {code}): {err!r}")
            return None
        if kind == "error":
            self._fail(f"the worker process failed:\n{payload}")
            return None
        return payload

    def close(self) -> None:
        """Close the pipe and reap the child (killed if it has not ended within 2 s, e.g. when
        the parent gave up on it after an error of its own)."""
        try:
            self._conn.close()
        finally:
            if self._proc is not None:
                self._proc.join(timeout=2)
                if self._proc.is_alive():
                    self._proc.kill()
                    self._proc.join()

    def __enter__(self) -> ForkWorker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _fail(self, why: str) -> None:
        self.failed = True
        _LOG.warning("%s; running its share in this process instead", why)


def _child_main(job: Callable[[Any], None], conn: Any, parent_end: Any, parent_pid: int) -> None:
    # The parent's end came along with the fork: closed here, a recv() sees the parent go (EOF)
    # instead of waiting on a pipe this process holds open itself; and the child ends with a
    # killed parent while it computes (``exit_with_parent``).
    parent_end.close()
    exit_with_parent(parent_pid)

    class _Channel:
        def send(self, obj: Any) -> None:
            conn.send(("ok", obj))

        def recv(self) -> Any:
            return conn.recv()

    try:
        job(_Channel())
    except BaseException:  # noqa: BLE001 - everything goes back to the parent, which takes over
        try:
            conn.send(("error", traceback.format_exc()))
        except Exception:  # noqa: BLE001
            pass
    finally:
        conn.close()


# How often a pool's worker looks whether the process that started it is still there [s].
PARENT_POLL_S = 0.5


def spawn_pool(max_workers: int = 1, *, nice: int = 0) -> ProcessPoolExecutor:
    """A ``ProcessPoolExecutor`` of freshly spawned processes that end with the process that made
    them (``exit_with_parent``): a node killed with SIGKILL, which runs no clean-up, leaves no
    worker behind, busy or idle (a spawned worker holds both ends of its call queue, so it would
    never see the parent go and would wait for work forever). ``nice``: added to the workers'
    niceness (background work that must not slow the node's own)."""
    return ProcessPoolExecutor(
        max_workers,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_pool_worker_init,
        initargs=(os.getpid(), nice),
    )


def _pool_worker_init(parent_pid: int, nice: int) -> None:
    if nice:
        os.nice(nice)
    exit_with_parent(parent_pid)


def exit_with_parent(parent_pid: int) -> None:
    """Pool initializer: a daemon thread ends this process (``os._exit``, nothing left to clean
    up that the parent still wants) once ``parent_pid`` is no longer its parent, i.e. the parent
    died and the process was re-parented. Polls every ``PARENT_POLL_S`` seconds; portable POSIX
    (``prctl(PR_SET_PDEATHSIG)`` would fire when the *thread* that spawned the pool ends)."""

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(PARENT_POLL_S)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


class SpareWork:
    """``fn(i)`` for ``i`` in ``range(n)``, computed ahead in a forked child at the lowest
    priority (nice 19): it runs on CPU time the other processes leave idle and gives way to them
    everywhere else. :meth:`take` stops it and returns what it finished, ``{i: fn(i)}``; the
    caller computes the rest itself (the same results: ``fn`` is the same function on the same
    data, inherited by the fork).

    Results go to an anonymous temporary file (one record per item: index, size, pickle), not
    a pipe: a starved child need not run again to hand them over, it is killed and its complete
    records read. Nothing is started where ``fork`` is missing (``take`` then returns ``{}``).
    """

    _HEAD = struct.Struct("<qq")

    def __init__(self, fn: Callable[[int], Any], n: int) -> None:
        self._file = tempfile.TemporaryFile()
        self._proc: multiprocessing.process.BaseProcess | None = None
        if n < 1 or not can_fork():
            return
        ctx = multiprocessing.get_context("fork")
        proc = ctx.Process(
            target=_spare_main, args=(fn, n, self._file.fileno(), os.getpid()), name="spare-work", daemon=True
        )
        try:
            proc.start()
        except (AssertionError, OSError) as err:  # e.g. a daemonic process may not have children
            _LOG.debug("no spare worker: %r", err)
            return
        self._proc = proc

    def take(self, *, wait: bool = False) -> dict[int, Any]:
        """Stop the child (``wait``: let it finish every item first); the items it finished
        (none after the first call)."""
        if self._proc is not None:
            if wait:
                self._proc.join()
            self._proc.kill()
            self._proc.join()
            self._proc = None
        if self._file.closed:
            return {}
        self._file.seek(0)
        data = memoryview(self._file.read())
        self._file.close()
        out: dict[int, Any] = {}
        pos, head = 0, self._HEAD.size
        while pos + head <= len(data):
            i, size = self._HEAD.unpack_from(data, pos)
            if pos + head + size > len(data):
                break  # the record being written when the child was stopped
            out[i] = pickle.loads(data[pos + head : pos + head + size])
            pos += head + size
        return out

    def __enter__(self) -> SpareWork:
        return self

    def __exit__(self, *exc: object) -> None:
        self.take()


def _spare_main(fn: Callable[[int], Any], n: int, fd: int, parent_pid: int) -> None:
    os.nice(19)
    exit_with_parent(parent_pid)
    try:
        for i in range(n):
            blob = pickle.dumps(fn(i), protocol=pickle.HIGHEST_PROTOCOL)
            record = memoryview(SpareWork._HEAD.pack(i, len(blob)) + blob)
            while len(record):
                record = record[os.write(fd, record) :]
    except Exception:  # noqa: BLE001 - the caller computes what is missing
        _LOG.debug("spare work stopped:\n%s", traceback.format_exc())
