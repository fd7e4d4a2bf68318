"""Where the tile tasks run: in this process, or on a Dask cluster (``dask.distributed``).

``SerialRunner`` runs them one after the other here. ``DaskRunner`` submits them to a Dask
``Client``: of a ``LocalCluster`` it starts (``local(workers)``: one single-threaded worker process
per CPU asked for) or of a running cluster (``connect("tcp://HOST:8786")``, started with
``dask scheduler`` and ``dask worker`` as Dask documents). Results come back in input order
whatever the order the tasks finished in, so a build is the same with any number of workers.
At most ``in_flight`` tasks per worker are submitted at a time, so neither the client nor the
scheduler holds more than that many tasks' inputs and results in flight.
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from hdmap_core.errors import ConfigError
from hdmap_core.tiled.memory import cpu_seconds, peak_rss_mb

__all__ = ["Runner", "SerialRunner", "DaskRunner", "ProgressFn", "Parts", "LocalParts", "ActorParts"]

ProgressFn = Callable[[str, int, int], None]
_QUIET = {
    "distributed.worker.memory.monitor-interval": "2s",
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.admin.tick.interval": "200ms",
}
PerItem = Callable[[Any], tuple]


class Runner(Protocol):
    """Runs ``fn(*shared, item, *per_item(item))`` for every item; results in item order.

    ``run_grouped`` runs ``fn(*shared, item, *per_item(item))`` once for every item of the ``(label, items)``
    groups (groups may share items), then ``group_fn(label, results of the group's items,
    *group_shared)`` per group and ``reduce_fn(the groups' results in group order, *group_shared)``
    once, and returns the latter; on a cluster the items' and the groups' results stay on the
    workers (a block-wise reduction: the client receives only what ``reduce_fn`` returns).
    """

    workers: int

    def run(
        self,
        stage: str,
        fn: Callable,
        items: Sequence,
        shared: tuple = (),
        per_item: PerItem | None = None,
        progress: ProgressFn | None = None,
        weights: Sequence[float] | None = None,
    ) -> list: ...

    def run_grouped(
        self,
        stage: str,
        fn: Callable,
        groups: Sequence[tuple[Any, Sequence]],
        group_fn: Callable,
        reduce_fn: Callable,
        shared: tuple = (),
        group_shared: tuple = (),
        progress: ProgressFn | None = None,
        per_item: PerItem | None = None,
    ) -> Any: ...

    def run_parts(
        self,
        stage: str,
        fn: Callable,
        items: Sequence,
        groups: Sequence[Sequence[int]],
        factory: Callable,
        shared: tuple = (),
        progress: ProgressFn | None = None,
        weights: Sequence[float] | None = None,
    ) -> Parts: ...

    def peak_rss_mb(self) -> dict[str, float]: ...

    def cpu_seconds(self) -> dict[str, float]: ...

    def close(self) -> None: ...


class Parts(Protocol):
    """Objects held where they were built (``Runner.run_parts``): ``call(method, args)`` runs
    ``part.method(*args[b])`` on every part ``b`` (all at once on a cluster) and returns the
    results in part order; ``close()`` drops the parts."""

    def call(self, method: str, args: Sequence[tuple]) -> list: ...

    def close(self) -> None: ...


class LocalParts:
    """Parts in this process."""

    def __init__(self, parts: Sequence[Any]) -> None:
        self.parts = list(parts)

    def call(self, method: str, args: Sequence[tuple]) -> list:
        return [getattr(p, method)(*a) for p, a in zip(self.parts, args, strict=True)]

    def close(self) -> None:
        self.parts = []


class ActorParts:
    """Parts held as Dask actors on the workers: a call sends only its arguments and gets only its
    result back (no task through the scheduler); the parts on one worker run one at a time."""

    def __init__(self, actors: Sequence[Any], futures: Sequence[Any]) -> None:
        self.actors, self.futures = list(actors), list(futures)

    def call(self, method: str, args: Sequence[tuple]) -> list:
        pending = [getattr(a, method)(*arg) for a, arg in zip(self.actors, args, strict=True)]
        return [p.result() for p in pending]

    def close(self) -> None:
        for f in self.futures:
            f.release()
        self.actors, self.futures = [], []


class SerialRunner:
    """Every task in this process, in order."""

    workers = 1

    def run(
        self,
        stage: str,
        fn: Callable,
        items: Sequence,
        shared: tuple = (),
        per_item: PerItem | None = None,
        progress: ProgressFn | None = None,
        weights: Sequence[float] | None = None,
    ) -> list:
        out = []
        for i, item in enumerate(items):
            out.append(fn(*shared, item, *(per_item(item) if per_item else ())))
            if progress is not None:
                progress(stage, i + 1, len(items))
        return out

    def run_grouped(
        self,
        stage: str,
        fn: Callable,
        groups: Sequence[tuple[Any, Sequence]],
        group_fn: Callable,
        reduce_fn: Callable,
        shared: tuple = (),
        group_shared: tuple = (),
        progress: ProgressFn | None = None,
        per_item: PerItem | None = None,
    ) -> Any:
        last = {item: g for g, (_, items) in enumerate(groups) for item in items}  # last group using it
        total, done, out = len(last), 0, []
        cache: dict = {}
        for g, (label, items) in enumerate(groups):
            for item in items:
                if item not in cache:
                    cache[item] = fn(*shared, item, *(per_item(item) if per_item else ()))
                    done += 1
                    if progress is not None:
                        progress(stage, done, total)
            out.append(group_fn(label, [cache[i] for i in items], *group_shared))
            for item in items:
                if last[item] == g:
                    cache.pop(item, None)
        return reduce_fn(out, *group_shared)

    def run_parts(
        self,
        stage: str,
        fn: Callable,
        items: Sequence,
        groups: Sequence[Sequence[int]],
        factory: Callable,
        shared: tuple = (),
        progress: ProgressFn | None = None,
        weights: Sequence[float] | None = None,
    ) -> Parts:
        """``fn(*shared, item)`` for every item, then ``factory(*results of the group's items)``
        per group of item indices (each item's result dropped once its group is built)."""
        parts, done = [], 0
        for idx in groups:
            results = []
            for i in idx:
                results.append(fn(*shared, items[i]))
                done += 1
                if progress is not None:
                    progress(stage, done, len(items))
            parts.append(factory(*results))
            del results
        return LocalParts(parts)

    def peak_rss_mb(self) -> dict[str, float]:
        """{"main": peak RSS of this process} [MB]."""
        return {"main": peak_rss_mb()}

    def cpu_seconds(self) -> dict[str, float]:
        """{"main": CPU time of this process} [s]."""
        return {"main": cpu_seconds()}

    def close(self) -> None:
        pass


class DaskRunner:
    """The tasks on a ``dask.distributed`` cluster; see the module docstring."""

    def __init__(self, client: Any, *, cluster: Any = None, in_flight: int = 2) -> None:
        self.client = client
        self.cluster = cluster
        self.in_flight = max(1, int(in_flight))
        self.workers = max(1, len(client.scheduler_info().get("workers", {})))
        # every worker imports the pipeline now, not inside its first task
        client.run(importlib.import_module, "hdmap_core.tiled.tasks")

    @classmethod
    def local(cls, workers: int, *, in_flight: int = 2) -> DaskRunner:
        """Start a ``LocalCluster`` of ``workers`` single-threaded worker processes."""
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise ConfigError(f"workers must be an integer >= 1, got {workers!r}")
        import dask  # noqa: PLC0415 - only when asked for
        from distributed import Client, LocalCluster  # noqa: PLC0415

        # On loopback only; the scheduler's HTTP endpoint on a free port (8787 may be another
        # cluster's). Tasks take seconds: the monitors need not wake every 0.1-0.5 s (idle, a
        # worker used 3.1 % of a core with the defaults, 2.3-2.9 % with these; the client 4.3 %,
        # then 1.0-1.2 %).
        with dask.config.set(_QUIET):
            cluster = LocalCluster(
                n_workers=workers,
                threads_per_worker=1,
                processes=True,
                host="127.0.0.1",
                dashboard_address="127.0.0.1:0",
                silence_logs=logging.ERROR,
            )
        return cls(Client(cluster), cluster=cluster, in_flight=in_flight)

    @classmethod
    def connect(cls, address: str, *, timeout_s: float = 30.0, in_flight: int = 2) -> DaskRunner:
        """A client of the running cluster whose scheduler listens at ``address`` (tcp://HOST:8786).

        Raises:
            ConfigError: no scheduler answers there, or it has no worker.
        """
        from distributed import Client  # noqa: PLC0415

        try:
            client = Client(address, timeout=timeout_s)
        except (OSError, TimeoutError) as err:
            raise ConfigError(f"no Dask scheduler at {address}: {err}") from err
        try:
            client.wait_for_workers(1, timeout=timeout_s)
        except TimeoutError as err:
            client.close()
            raise ConfigError(f"the Dask scheduler at {address} has no worker after {timeout_s:.0f} s") from err
        return cls(client, in_flight=in_flight)

    def run(
        self,
        stage: str,
        fn: Callable,
        items: Sequence,
        shared: tuple = (),
        per_item: PerItem | None = None,
        progress: ProgressFn | None = None,
        weights: Sequence[float] | None = None,
    ) -> list:
        """``weights``: the expected cost of each item; the heaviest are submitted first, so that
        no worker is left with a heavy task at the end of the stage (results stay in item order)."""
        from distributed import as_completed  # noqa: PLC0415

        shared_f = [self.client.scatter(v, broadcast=True, hash=False) for v in shared]
        out: list = [None] * len(items)
        limit = self.in_flight * self.workers
        index: dict[str, int] = {}
        order = range(len(items)) if weights is None else sorted(range(len(items)), key=lambda i: -float(weights[i]))
        todo = iter((i, items[i]) for i in order)
        pending = as_completed()
        done = 0

        def submit() -> bool:
            nxt = next(todo, None)
            if nxt is None:
                return False
            i, item = nxt
            fut = self.client.submit(
                fn, *shared_f, item, *(per_item(item) if per_item else ()), pure=False, key=f"{stage}-{i}-{id(out):x}"
            )
            index[fut.key] = i
            pending.add(fut)
            return True

        for _ in range(limit):
            if not submit():
                break
        for fut in pending:
            out[index.pop(fut.key)] = fut.result()  # a task's error is raised here, named by Dask
            fut.release()
            done += 1
            if progress is not None:
                progress(stage, done, len(items))
            submit()
        for f in shared_f:
            f.release()
        return out

    def run_grouped(
        self,
        stage: str,
        fn: Callable,
        groups: Sequence[tuple[Any, Sequence]],
        group_fn: Callable,
        reduce_fn: Callable,
        shared: tuple = (),
        group_shared: tuple = (),
        progress: ProgressFn | None = None,
        per_item: PerItem | None = None,
    ) -> Any:
        """Groups submitted in the order given (put the heaviest first); a group's items (those
        not submitted before) and its group task together, at most ``in_flight`` x workers groups
        unfinished. An item's result is released once every group using it is submitted."""
        from distributed import as_completed  # noqa: PLC0415

        shared_f = [self.client.scatter(v, broadcast=True, hash=False) for v in shared]
        gshared_f = [self.client.scatter(v, broadcast=True, hash=False) for v in group_shared]
        tag = f"{id(groups):x}"
        last = {item: g for g, (_, items) in enumerate(groups) for item in items}
        total = len(last)
        done = 0
        futs: dict = {}  # item -> future, until its last group is submitted
        pending = as_completed()
        group_futs: list = []
        is_group: set = set()
        limit = self.in_flight * self.workers
        todo = iter(enumerate(groups))

        def submit() -> None:
            while sum(not f.done() for f in group_futs) < limit:
                nxt = next(todo, None)
                if nxt is None:
                    return
                g, (label, items) = nxt
                for item in items:
                    if item not in futs:
                        futs[item] = self.client.submit(
                            fn,
                            *shared_f,
                            item,
                            *(per_item(item) if per_item else ()),
                            pure=False,
                            key=f"{stage}-{len(futs)}-{g}-{tag}",
                        )
                        pending.add(futs[item])
                parts = [futs[i] for i in items]
                gfut = self.client.submit(
                    group_fn, label, parts, *gshared_f, pure=False, key=f"{stage}-group-{g}-{tag}"
                )
                group_futs.append(gfut)
                is_group.add(gfut.key)
                pending.add(gfut)
                for item in items:
                    if last[item] == g:
                        finished_with.add(futs[item].key)
                        if futs[item].key in completed:
                            futs[item].release()

        finished_with: set = set()  # items whose last group is submitted
        completed: set = set()
        submit()
        for fut in pending:
            if fut.status == "error":
                fut.result()  # a task's error is raised here, named by Dask
            if fut.key not in is_group:  # a group's result stays on its worker
                completed.add(fut.key)
                done += 1
                if progress is not None:
                    progress(stage, done, total)
            submit()
            if fut.key in finished_with:
                fut.release()
        reduced = self.client.submit(reduce_fn, group_futs, *gshared_f, pure=False, key=f"{stage}-reduce-{tag}")
        out = reduced.result()
        for f in [reduced, *group_futs, *shared_f, *gshared_f]:
            f.release()
        return out

    def run_parts(
        self,
        stage: str,
        fn: Callable,
        items: Sequence,
        groups: Sequence[Sequence[int]],
        factory: Callable,
        shared: tuple = (),
        progress: ProgressFn | None = None,
        weights: Sequence[float] | None = None,
    ) -> Parts:
        """The items' tasks (group by group, the heaviest groups first), then one actor
        ``factory(*results of the group's items)`` per group, the groups dealt to the workers in
        turn; the items' results go from their workers to their group's actor, never to this
        process."""
        from distributed import as_completed  # noqa: PLC0415

        shared_f = [self.client.scatter(v, broadcast=True, hash=False) for v in shared]
        tag = f"{id(groups):x}"
        # RULE a group's items one after the other: an item's result waits on a worker until its
        # group's last item is done (heaviest items first across groups kept every group open
        # until the end of the pass, their results beside the parts built so far)
        by_weight = sorted(groups, key=lambda idx: -sum(float(weights[i]) for i in idx)) if weights else groups
        order = [i for idx in by_weight for i in idx]
        futs = {i: self.client.submit(fn, *shared_f, items[i], pure=False, key=f"{stage}-{i}-{tag}") for i in order}
        addrs = sorted(self.client.scheduler_info().get("workers", {}))
        actor_futs = [
            self.client.submit(
                factory,
                *[futs[i] for i in idx],
                actor=True,
                pure=False,
                key=f"{stage}-part-{g}-{tag}",
                workers=[addrs[g % len(addrs)]] if addrs else None,
                allow_other_workers=not addrs,
            )
            for g, idx in enumerate(groups)
        ]
        done = 0
        pending = as_completed(list(futs.values()))
        futs.clear()
        for fut in pending:
            if fut.status == "error":
                fut.result()  # a task's error is raised here, named by Dask
            # RULE an item's result lives until its group's actor is built (the scheduler keeps a
            # dependency for its dependents), not until every item is done: else every worker
            # held all its tiles' observations beside the parts built from them
            fut.release()
            done += 1
            if progress is not None:
                progress(stage, done, len(items))
        actors = [f.result() for f in actor_futs]
        for f in shared_f:
            f.release()
        return ActorParts(actors, actor_futs)

    def peak_rss_mb(self) -> dict[str, float]:
        """Peak RSS [MB] of this process ("main"), of the scheduler and of each worker (by address).
        With a ``LocalCluster`` the scheduler runs in this process."""
        peaks = {"main": peak_rss_mb(), "scheduler": float(self.client.run_on_scheduler(peak_rss_mb))}
        for addr, mb in sorted(self.client.run(peak_rss_mb).items()):
            peaks[f"worker {addr}"] = float(mb)
        return peaks

    def cpu_seconds(self) -> dict[str, float]:
        """CPU time [s] of this process ("main", with a ``LocalCluster``'s scheduler) and of each
        worker since it started (by address)."""
        out = {"main": cpu_seconds()}
        for addr, sec in sorted(self.client.run(cpu_seconds).items()):
            out[f"worker {addr}"] = float(sec)
        return out

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()
