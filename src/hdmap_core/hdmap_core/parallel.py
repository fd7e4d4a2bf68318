"""Pivot passes on more than one core, with the same result as one core.

A pivot changes the state later pivots see only through the drives that have samples on its cut
lines (their processed-stretch marks and remembered offsets). Two drives can only ever meet that
way where one of them, as pivot, has a cut line that crosses a detection segment of the other
going the same way. ``pivot_groups`` unites drives that may meet (a conservative test on a coarse
grid of place and heading) into independent groups; the pivots of different groups never share
a drive, so the groups can run in separate processes, each in the global pivot order, and the
merged result is exactly the one-process result (a highway's two carriageways are two groups).

``ForkWorker`` runs one share of the groups in a forked child process (Linux/Unix ``fork``: the
child inherits the detection index and the drives, nothing is pickled on the way in; results come
back through a pipe). A child that fails for any reason is reported by ``result()`` returning
None, and the caller then runs that share itself: the result stays the same, only slower.
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import os
import traceback
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from hdmap_core.model import Drive
from hdmap_core.pipeline.preprocess import DetectionIndex
from hdmap_core.pipeline.sampling import SamplingConfig, pivot_walk

__all__ = ["ForkWorker", "available_cpus", "balance", "can_fork", "map_balanced", "pivot_groups", "run_shares", "split_order"]

_LOG = logging.getLogger(__name__)
_HEADING_BINS = 12  # 30 deg each
_OFF = 1 << 20  # cell index offset: keys stay non-negative for maps within +-2^20 cells
_SPAN = 1 << 22


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover (not Linux)
        return max(1, os.cpu_count() or 1)


def can_fork() -> bool:
    return "fork" in multiprocessing.get_all_start_methods()


def pivot_groups(index: DetectionIndex, drives: Sequence[Drive], *, config: SamplingConfig) -> np.ndarray:
    """(N,) group label per drive (0..G-1): drives in different groups never meet on a cut line.

    Drive j's detection segment can be sampled on pivot i's cut at step point p only if the
    crossing lies within ``initial_half_length_m`` of p and j's heading there (``seg_yaw``) is
    within ``max_heading_diff_deg`` of the pivot's step heading. So the segment's midpoint lies
    within R = half length + half the longest segment of p. Place is binned in square cells of
    side > R (a point within R of p is in p's cell or one of its 8 neighbours) and heading in 30
    degree bins (two headings within D degrees are at most ceil(D / 30) bins apart): a drive is
    linked to every drive with a segment in a neighbouring (cell, heading bin) of one of its
    steps. The test can only unite too much, never too little.
    """
    n = len(drives)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    seg_len = np.hypot(*(index.seg_b - index.seg_a).T) if index.n_segments else np.zeros(1)
    reach = config.initial_half_length_m + 0.5 * float(seg_len.max())
    cell = reach * (1.0 + 1e-6) + 1e-6
    bin_w = 2.0 * math.pi / _HEADING_BINS
    d_bins = math.ceil(math.radians(config.max_heading_diff_deg) / bin_w + 1e-9)

    def place(xy: np.ndarray, yaw: np.ndarray) -> np.ndarray:
        c = np.floor(np.asarray(xy, dtype=float) / cell).astype(np.int64) + _OFF
        b = np.floor(np.mod(yaw, 2.0 * math.pi) / bin_w).astype(np.int64) % _HEADING_BINS
        return (c[:, 0] * _SPAN + c[:, 1]) * _HEADING_BINS + b

    # Where each drive's detections are: its distinct place keys (segments come drive by drive).
    seg_key = place(0.5 * (index.seg_a + index.seg_b), index.seg_yaw)
    seg_drive = index.seg_drive.astype(np.int64)
    if np.any(np.diff(seg_drive) < 0):
        by_drive = np.argsort(seg_drive, kind="stable")
        seg_key, seg_drive = seg_key[by_drive], seg_drive[by_drive]
    bounds = np.searchsorted(seg_drive, np.arange(n + 1), side="left")
    det_key: list[np.ndarray] = []
    det_drive: list[np.ndarray] = []
    for i in np.flatnonzero(np.diff(bounds)):
        k = np.unique(seg_key[bounds[i] : bounds[i + 1]])
        det_key.append(k)
        det_drive.append(np.full(len(k), i, dtype=np.int64))
    det_k = np.concatenate(det_key) if det_key else np.zeros(0, np.int64)
    det_d = np.concatenate(det_drive) if det_drive else np.zeros(0, np.int64)
    keys, det_node = np.unique(det_k, return_inverse=True)
    # Where each drive's cut lines may reach: its steps' keys grown by one cell and d_bins.
    shifts = sorted({s % _HEADING_BINS for s in range(-d_bins, d_bins + 1)})
    reach_node: list[np.ndarray] = []
    reach_drive: list[np.ndarray] = []
    for i, d in enumerate(drives):
        _, pts, heading = pivot_walk(d, step_m=config.step_m)
        k = np.unique(place(pts, heading))
        b, c = k % _HEADING_BINS, k // _HEADING_BINS
        grown = np.concatenate([
            (c + dx * _SPAN + dy) * _HEADING_BINS + (b + db) % _HEADING_BINS
            for dx in (-1, 0, 1) for dy in (-1, 0, 1) for db in shifts
        ])
        pos = np.minimum(np.searchsorted(keys, grown), max(len(keys) - 1, 0))
        hit = keys[pos] == grown if len(keys) else np.zeros(len(grown), dtype=bool)
        reach_node.append(pos[hit])
        reach_drive.append(np.full(int(hit.sum()), i, dtype=np.int64))
    # Bipartite graph drives -- place keys; its components are the groups.
    rows = np.concatenate([det_d, *reach_drive])
    cols = n + np.concatenate([det_node, *reach_node])
    m = len(keys)
    g = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n + m, n + m))
    _, label = connected_components(g, directed=False)
    _, group = np.unique(label[:n], return_inverse=True)
    return group.astype(np.int64)


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

    workers = [ForkWorker(lambda ch, sh=sh: job(ch, sh)) for sh in shares[1:]]
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
        self._proc = ctx.Process(target=_child_main, args=(job, child_conn), daemon=True)
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
            self._proc.join(timeout=1)
            self._fail(f"the worker process ended without a result (exit code {self._proc.exitcode}): {err!r}")
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


def _child_main(job: Callable[[Any], None], conn: Any) -> None:
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
