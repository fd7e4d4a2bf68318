"""segment_mapper: the drive store and the per-tile estimates (stages of Sec. III-IV, per tile).

Subscribes ``/hdmap/drives_accepted``. Each new drive is committed to the SQLite drive store
together with the tiles it covers (one transaction); from then on it is *acknowledged* (an ack is
published on ``/hdmap/drive_acks``) and survives any crash. A worker then re-maps the tiles the
new drives cover, each from all stored drives covering it (``hdmap_core.live.tiles.map_tile``),
when it is due (``LiveScheduler``: a new tile, new road in a mapped tile, or, without the fleet
model, a drive count grown by ``min_growth_fraction`` / ``min_growth_drives``). Each estimate is
committed (one transaction) and published on ``/hdmap/segments`` as hdmap_msgs/TileSegments with a
growing version per tile. When no drive came for ``settle_after_s``, every tile whose estimate
is older than its drive set is re-estimated once, so the settled map depends on the drives only.

Offsets (presets with the global adjustment, e.g. ``default``): an estimate made while drives come
is the tile's observation pass (``live.tiles.preview_tile``), and its step observations are stored
with it. When the input settles, (1) every tile's observations are brought up to its drive set
(``live.tiles.observe_tile``), (2) one fleet-wide offset model is estimated from the
observations of all tiles (``live.tiles.fleet_offsets``, the network-wide adjustment of
``hdmap bag2map``) and stored (``OffsetModel.to_dict``) with a signature of the drive sets it was
made from, and (3) every tile not yet made from all its drives with that model is re-estimated
with it (the final pass only). Each is a pure function of the stored drives, so the settled map
still depends on the drive set only, also across SIGKILL and restart. While the map has at most
``region_max_drives`` drives the settle is instead one job making every tile at once
(``live.region.map_region``: the passes of ``hdmap bag2map`` on the whole drives, cut into
tiles): the tiles' margins are not mapped again, and tiles still queued when the input settles
are not previewed first.

The schedule (queue, due test, order, settle phases) is ``hdmap_core.live.scheduler.LiveScheduler``;
this node feeds it drives and finished jobs, runs the jobs it hands out (``live.jobs.run_job``) on
``workers`` processes (0: every available CPU; 1: in this process, a time slice per turn), stores
and publishes their results. A tile is one job for all drives waiting on it; tiles no estimate
covers yet go first, then tiles with new road, so coverage grows while drives come.

The fast path (``fast_path``, presets with the fleet model): a drive whose tiles all hold settled
estimates and in which it drove no new road is fused into them at once (``live.fuse``: its offset
against the map, the gauge moved as the batch solve would, its samples into the matched line
points), and the fused estimates are published final, so the drive is listed within about a
second; the next settle re-makes every tile as before. A drive the fusion refuses goes the normal
way. A drive alone on new road (no drive covered its tiles) is mapped at once by one build of it
(``PART``), final as well.

Each tile estimate names, per drive it was made from, how many tiles that drive covers
(``drive_tile_counts``), and whether it is *final*: made as the settled map makes it (with the
fleet offset model where the preset has one). The stitcher lists a drive in ``Map.drive_ids``
only once every one of its tiles is in the map with it, final. The mapper's progress (drives
received and rejected, tiles pending, settled) goes out as hdmap_msgs/MapStatus on
``/hdmap/mapper_status`` (latched); the stitcher completes it on ``/hdmap/status``.

Restart: pending (acknowledged, unprocessed) drives are processed; with ``republish_on_start``
every stored tile estimate is published again (the stitcher ignores versions it has).
"""

from __future__ import annotations

import contextlib
import functools
import time
import traceback
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from concurrent.futures import Future, ProcessPoolExecutor

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from std_msgs.msg import String

from hdmap_core.errors import ConfigError, HdmapError, InvalidDriveError
from hdmap_core.live.jobs import JobResult, run_job, warm_up
from hdmap_core.live.progress import LiveStatus
from hdmap_core.live.scheduler import FUSE, FUSED, MAP, MODEL, OBSERVE, PART, REGION, REMAP, Job, LiveScheduler
from hdmap_core.live.tiles import TileConfig, TileKey, road_cells, tiles_of_drive
from hdmap_core.model import Drive, validate_drive
from hdmap_core.parallel import available_cpus, spawn_pool
from hdmap_core.pipeline.adjustment import OffsetModel
from hdmap_core.plausibility import check_plausible
from hdmap_core.segment_columns import SegmentColumns, segment_columns
from hdmap_ros.convert.messages import rclpy_status_class, rclpy_types, status_to_msg
from hdmap_ros.convert.tiles import rclpy_tile_types, tile_to_msg, tiles_to_batch
from hdmap_ros.nodes import qos
from hdmap_ros.nodes._common import (
    HealthMixin,
    declare,
    declare_pipeline_config,
    drive_from_wire,
    run_node,
    state_path,
)
from hdmap_ros.persistence.store import DriveStore, TileEstimate, blob_to_drive, read_drives

__all__ = ["SegmentMapper", "main"]

ACCEPTED_TOPIC = "hdmap/drives_accepted"  # relative: a namespace (-r __ns:=/ns2) moves every topic
REJECTED_TOPIC = "hdmap/drives_rejected"
SEGMENTS_TOPIC = "hdmap/segments"
BATCHES_TOPIC = "hdmap/segment_batches"
ACKS_TOPIC = "hdmap/drive_acks"
STATUS_TOPIC = "hdmap/mapper_status"
DRIVES_KEPT = 64  # RULE: stored drives the mapper keeps decoded (most recently used)


class _Inline:
    """An executor that runs each job at once, in this process (``workers`` = 1)."""

    def submit(self, fn, *args, **kwargs) -> Future:
        fut: Future = Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except BaseException as err:  # noqa: BLE001 - handed to the caller like a pool would
            fut.set_exception(err)
        return fut

    def shutdown(self, *_, **__) -> None:
        pass


class SegmentMapper(HealthMixin, Node):
    """Keeps the drive store and publishes tile estimates; see the module docstring."""

    def __init__(self, **kwargs) -> None:
        super().__init__("segment_mapper", **kwargs)
        db = declare(self, "db_path", "", "SQLite file of the drive store ('' = $ROS_HOME/hdmap/segment_mapper.db).")
        pipeline_config = declare_pipeline_config(self)  # a bad preset or override fails here, named
        self.tile_config = TileConfig(
            tile_size_m=declare(self, "tile_size_m", 256.0, "Edge of a map tile [m].", lo=32.0, hi=4096.0),
            margin_m=declare(
                self, "margin_m", 128.0, "Context mapped around a tile [m]; must be < tile_size_m.", lo=0.0, hi=1024.0
            ),
            min_growth_fraction=declare(
                self,
                "min_growth_fraction",
                0.10,
                "Without the fleet model: re-estimate a tile when its drive count grew by this fraction.",
                lo=0.0,
                hi=10.0,
            ),
            min_growth_drives=declare(
                self,
                "min_growth_drives",
                3,
                "Without the fleet model: ... and by at least this many drives.",
                lo=1,
                hi=10000,
            ),
            seed=declare(
                self, "seed", 0, "Base seed; each tile's seed derives from it and the tile key.", lo=0, hi=2**31 - 1
            ),
            pivot_margin_m=self._pivot_margin(),
        )
        self.settle_after_s = declare(
            self,
            "settle_after_s",
            2.0,
            "Idle time after which stale tiles are re-estimated [s].",
            lo=0.0,
            hi=3600.0,
            dynamic="settle_after_s",
        )
        depth = declare(
            self,
            "segments_history_depth",
            1000,
            "Tile estimates kept (TRANSIENT_LOCAL) for a restarting stitcher.",
            lo=1,
            hi=100000,
        )
        accepted_depth = declare(
            self,
            "accepted_history_depth",
            100,
            "History depth of /hdmap/drives_accepted (match the ingestor).",
            lo=1,
            hi=100000,
        )
        republish = declare(self, "republish_on_start", True, "Publish every stored tile estimate at start.")
        # RULE memory: the region is one build of every drive in one worker (paper_like, 134 drives:
        # peak 482 MB), so beyond a few hundred drives the settle goes tile by tile
        region_max_drives = declare(
            self,
            "region_max_drives",
            300,
            "With the fleet model: settle by one build of every tile while the map has at most this many "
            "drives (0 = tile by tile).",
            lo=0,
            hi=1000000,
        )
        self.work_slice_s = declare(
            self,
            "work_slice_s",
            0.5,
            "Mapping time per worker turn with workers=1 [s]; new drives are taken in between.",
            lo=0.0,
            hi=600.0,
            dynamic="work_slice_s",
        )
        fast_path = declare(
            self,
            "fast_path",
            True,
            "With the fleet model: fuse a drive on settled road into its tiles at once (listed before the settle).",
        )
        workers = declare(
            self, "workers", 0, "Processes mapping tiles: 0 = every available CPU, 1 = in this process.", lo=0, hi=256
        )
        self._init_health("segment_mapper")
        self.health.backlog_warn = 200

        self.pipeline_config = pipeline_config
        self.store = DriveStore(state_path(db, "segment_mapper.db"))
        self._check_tiling()
        self._types = rclpy_types()
        self._tile_types = rclpy_tile_types()
        self.use_fleet_model = self.pipeline_config.final_pass is not None
        self.scheduler = LiveScheduler(
            self.tile_config,
            use_fleet_model=self.use_fleet_model,
            settle_after_s=self.settle_after_s,
            region_max_drives=region_max_drives,
            fast_path=fast_path,
        )
        self._model: OffsetModel | None = None
        self._load_model()
        emptied = self._purge_implausible()  # before the schedule is made from the store
        self.scheduler.restore(
            self.store.tile_drive_sets(),
            self.store.estimates(),
            self.store.observation_sets(),
            self._model_sig,
            now=time.monotonic(),
        )
        self.store.mark_processed(self.store.pending())  # their tiles are in the restored schedule
        self.workers = workers or available_cpus()
        # one process per worker, so a tile's settle job can go to the process that keeps the
        # work of its observation pass (``live.jobs.TileWork``)
        self._pools: list[ProcessPoolExecutor | _Inline] = (
            [spawn_pool() for _ in range(self.workers)] if self.workers > 1 else [_Inline()]
        )
        self._running: dict[Future, tuple[Job, int]] = {}  # job in work -> (job, its worker)
        self._home: dict[TileKey, int] = {}  # tile -> the worker that made its observation pass last
        self._drive_cache: OrderedDict[str, Drive] = OrderedDict()  # decoded stored drives (_drives)
        self._seg_cache: dict[TileKey, tuple[int, list]] = {}  # final estimates stored, decoded (_keep_segments)
        self._input_done = False  # input_done() was called: handed to the schedule by work()
        self._last_taken = ("", 0.0)  # the last drive handed to the schedule and when (the fast path's log)
        self._here_cpu0 = 0.0  # this thread's CPU time when the last job run here began (the fast path's log)
        for pool in self._pools if self.workers > 1 else []:  # start the processes while nothing waits
            pool.submit(warm_up)
        self.tiles_published = 0
        self.fast_fused = 0  # drives fused into settled tiles (the fast path)
        self.fast_refused = 0  # ... refused by the fusion (they waited for the settle)
        self.received = 0
        self._rejected_ids: set[str] = set()
        self._status: LiveStatus | None = None
        self._status_cls = rclpy_status_class()

        self._seg_pub = self.create_publisher(self._tile_types.TileSegments, SEGMENTS_TOPIC, qos.replay(depth))
        self._batch_pub = self.create_publisher(self._tile_types.TileSegmentsBatch, BATCHES_TOPIC, qos.BATCHES)
        self._ack_pub = self.create_publisher(String, ACKS_TOPIC, qos.ACKS)
        self._status_pub = self.create_publisher(self._status_cls, STATUS_TOPIC, qos.LATCHED)
        # Receiving (commit + ack) stays quick and apart from the slow mapping worker.
        self._rx_group = MutuallyExclusiveCallbackGroup()
        self._work_group = MutuallyExclusiveCallbackGroup()
        self._sub = self.create_subscription(
            self._types.Drive,
            ACCEPTED_TOPIC,
            self.on_drive,
            qos.replay(accepted_depth),
            callback_group=self._rx_group,
            raw=True,  # CDR bytes, read vectorised (drive_from_wire)
        )
        self._rej_sub = self.create_subscription(
            String,
            REJECTED_TOPIC,
            lambda m: self._rejected_ids.add(str(m.data)),
            qos.ACKS,
            callback_group=self._rx_group,
        )
        self._timer = self.create_timer(0.05, self.work, callback_group=self._work_group)
        # a finished job wakes the worker turn at once: the next job starts without waiting for a tick
        self._wake = self.create_guard_condition(self.work, callback_group=self._work_group)
        for est in emptied:  # tiles no drive covers any more after the purge: an empty estimate
            self._publish(est)
        if republish:
            for est in self.store.tiles():
                self._publish(est)
        self.health.set("drives_stored", self.store.drive_count())
        self._update_status()
        self.get_logger().info(
            f"drive store {self.store.path}: {self.store.drive_count()} drive(s), "
            f"{self.scheduler.pending_tiles()} tile(s) pending, {len(self.store.tiles())} tile(s), "
            f"{self.workers} worker(s)"
        )

    @property
    def settle_after_s(self) -> float:
        """Idle time before settling [s] (the scheduler's; a run-time parameter)."""
        sched = self.__dict__.get("scheduler")
        return sched.settle_after_s if sched is not None else self.__dict__.get("_settle_after_s", 2.0)

    @settle_after_s.setter
    def settle_after_s(self, value: float) -> None:
        self.__dict__["_settle_after_s"] = float(value)
        sched = self.__dict__.get("scheduler")
        if sched is not None:
            sched.settle_after_s = float(value)

    def _pivot_margin(self) -> float | None:
        margin = float(self.get_parameter("margin_m").value)
        pm = declare(
            self,
            "pivot_margin_m",
            48.0,
            "Pivots walk their steps only this far around a tile [m] (the whole margin stays context); "
            ">= margin_m walks the whole grown tile.",
            lo=0.0,
            hi=1024.0,
        )
        return None if pm >= margin else pm

    def _check_tiling(self) -> None:
        """A store keeps the tiling it was made with: another one would mix incompatible tiles."""
        cfg = self.tile_config
        tiling = f"tile_size_m={cfg.tile_size_m!r} margin_m={cfg.margin_m!r} seed={cfg.seed!r}"
        if cfg.pivot_margin_m is not None:  # estimates made otherwise would differ
            tiling += f" pivot_margin_m={cfg.pivot_margin_m!r}"
        stored = self.store.get_meta("tiling")
        if stored is None:
            self.store.set_meta("tiling", tiling)
        elif stored != tiling:
            raise ConfigError(
                f"{self.store.path} was made with {stored}, not {tiling}: use that tiling or a new db_path"
            )

    def _purge_implausible(self) -> list[TileEstimate]:
        """Forget stored drives outside the physical bounds (stored by an older version or under
        other bounds): a bad drive never comes back from the store. Only drives not yet checked
        under the current bounds are read (their last arrival number is kept in the store).

        Returns:
            the empty estimates stored for tiles no drive covers any more (to publish).
        """
        bounds = self.pipeline_config.plausibility
        done = self.store.get_meta("plausible_upto") or ""
        key, _, upto = done.rpartition("|")
        start = int(upto) if key == repr(bounds) and upto.isdigit() else 0
        bad: list[str] = []
        for _seq, did, blob in self.store.drives_after(start):
            try:
                check_plausible(validate_drive(blob_to_drive(blob), expected_frame=""), bounds=bounds)
            except InvalidDriveError as err:
                bad.append(did)
                self.get_logger().warning(f"stored drive {did!r} removed: {err.reason} ({err.detail})")
            except (HdmapError, ValueError, KeyError, TypeError, OSError) as err:  # a damaged blob
                bad.append(did)
                self.get_logger().warning(f"stored drive {did!r} removed: unreadable ({type(err).__name__}: {err})")
        emptied: list[TileEstimate] = []
        if bad:
            for key_ in sorted(self.store.remove_drives(bad)):
                if self.store.tile_drive_count(key_) == 0 and self.store.tile(key_) is not None:
                    emptied.append(self.store.put_tile(key_, [], []))  # nothing left there
            for did in bad:
                self.health.reject("implausible_stored", did)
        self.store.set_meta("plausible_upto", f"{bounds!r}|{self.store.last_seq()}")
        return emptied

    # --- receiving -------------------------------------------------------------------------------

    def on_drive(self, msg) -> None:
        """Commit one drive (acknowledge it); mapping happens in :meth:`work`."""
        try:
            self._receive(msg)
        finally:
            self.received += 1  # counted once handled, so "received" means "stored or refused"

    def _receive(self, msg) -> None:
        did = str(getattr(msg, "drive_id", ""))
        try:
            drive = drive_from_wire(msg, self._types.Drive, expected_frame=None)
            did = drive.drive_id
            check_plausible(drive, bounds=self.pipeline_config.plausibility)
            tiles = tiles_of_drive(drive, config=self.tile_config)
        except InvalidDriveError as err:
            did = did or err.drive_id
            self.health.reject(err.reason, did)
            self._rejected_ids.add(did)
            self.get_logger().warning(f"drive {did!r} rejected: {err.reason} ({err.detail})")
            return
        except HdmapError as err:
            self.health.reject("invalid_message", f"{did!r}: {err}")
            self._rejected_ids.add(did)
            self.get_logger().warning(f"drive {did!r} rejected: {err}")
            return
        except (AttributeError, TypeError, ValueError, MemoryError) as err:  # a message unlike the contract
            self.health.reject("invalid_message", f"{did!r}: {type(err).__name__}: {err}")
            self._rejected_ids.add(did)
            self.get_logger().warning(f"drive {did!r} rejected: invalid_message ({type(err).__name__}: {err})")
            return
        if not self.store.add_drive(drive, tiles):
            self.health.duplicate()
            return
        self._ack_pub.publish(String(data=drive.drive_id))
        self.health.accept()
        self.health.backlog += 1
        self.health.set("drives_stored", self.store.drive_count())
        with contextlib.suppress(Exception):  # the node may be on its way down
            self._wake.trigger()  # scheduled at once (the fast path), not at the work timer's next tick

    def input_open(self) -> None:
        """More drives are on their way (``hdmap run``: its bag is being played): with the region
        settle nothing is previewed and no drive takes the fast path until :meth:`input_done`
        (``LiveScheduler.input_open``): the region settle makes every tile once the input is in."""
        self.scheduler.input_open()

    def input_done(self) -> None:
        """No more drives come (``hdmap run``: its bag is played and every drive received): settle
        without waiting ``settle_after_s`` (``LiveScheduler.input_done``), once the drives stored so
        far are scheduled. A drive that comes later makes the settle wait as usual."""
        self._input_done = True
        with contextlib.suppress(Exception):  # the node may be on its way down
            self._wake.trigger()

    # --- mapping ---------------------------------------------------------------------------------

    def work(self) -> None:
        """One worker turn: take new drives, collect finished jobs, start the next ones."""
        self._take_pending()
        if self._input_done and not self.store.pending():  # after the drives it covers are scheduled
            self._input_done = False
            self.scheduler.input_done()
        self._collect()
        if self.workers <= 1:
            deadline = time.monotonic() + self.work_slice_s
            while time.monotonic() < deadline and self._start(1):
                self._collect()
                self._take_pending()  # a drive that came meanwhile is scheduled before the next job
        else:
            self._start(self.workers - len(self._running))
        self.health.backlog = len(self.store.pending()) + self.scheduler.pending_tiles()
        self.health.set("tiles_pending", self.scheduler.pending_tiles())
        self.health.set("jobs_running", len(self._running))
        self.health.set("settled", self.is_settled())
        self.health.set("tile_versions", self.store.version_total())
        self._update_status()

    def _take_pending(self) -> None:
        """Hand acknowledged, unprocessed drives to the schedule (then they count as processed: at a
        restart the schedule follows from the store)."""
        pending = self.store.pending()
        if not pending:
            return
        per_drive = self.store.tiles_per_drive(pending)
        cells = {d.drive_id: road_cells(d, config=self.tile_config) for d in self._drives(pending)}
        now = time.monotonic()
        for d in pending:
            self.scheduler.add_drive(d, per_drive[d], now, cells.get(d))
            self._last_taken = (d, now)
        self.store.mark_processed(pending)

    def _start(self, free: int) -> int:
        """Start up to ``free`` jobs, one per idle worker; returns how many."""
        busy = {w for _, w in self._running.values()}
        idle = [w for w in range(len(self._pools)) if w not in busy][: max(0, free)]
        started = 0
        while idle:
            w = idle[0]
            # RULE: a settle job goes preferably to the worker holding its tile's observation pass
            jobs = self.scheduler.next_jobs(time.monotonic(), 1, prefer=functools.partial(self._at_home, worker=w))
            if not jobs:
                break
            self._submit(jobs[0], w)
            started += 1
            if jobs[0].kind != FUSE:  # a fusion ran here (_submit): the worker is still free
                idle.pop(0)
        return started

    def _drives(self, drive_ids: Sequence[str]) -> list[Drive]:
        """The stored drives of these ids, as ``DriveStore.drives`` (by id), the most recently
        used :data:`DRIVES_KEPT` kept decoded: a drive is in every job of the tiles it covers,
        and decoding its blob for each was ~40 % of the mapper's work turns (profiled, 30-drive
        ramps fleet). Stored drives never change while the node runs."""
        missing = [d for d in drive_ids if d not in self._drive_cache]
        for d in self.store.drives(missing) if missing else []:
            self._drive_cache[d.drive_id] = d
        out = []
        for did in sorted(set(drive_ids)):
            if did in self._drive_cache:
                self._drive_cache.move_to_end(did)
                out.append(self._drive_cache[did])
        while len(self._drive_cache) > max(DRIVES_KEPT, len(drive_ids)):
            self._drive_cache.popitem(last=False)
        return out

    def _segments(self, key: TileKey) -> list:
        """A tile's stored segments: kept decoded (:meth:`_keep_segments`) while that version is
        the stored one (its version read alone), else decoded from the store."""
        cached = self._seg_cache.get(key)
        if cached is not None and cached[0] == self.store.tile_version(key):
            return list(cached[1])
        est = self.store.tile(key)
        return est.segments() if est is not None else []

    def _keep_segments(self, est: TileEstimate, segments: Sequence) -> list:
        """The segments of a final estimate just stored, kept decoded (the fast path's next fusion
        into the tile takes them, and its message is made from them, without decoding the blob)."""
        segs = list(segments)
        self._seg_cache[est.key] = (est.version, segs)
        return segs

    def _at_home(self, key: TileKey, *, worker: int) -> bool:
        """The tile's observation pass was made on ``worker`` (or on none still known)."""
        return self._home.get(key, worker) == worker

    def _submit(self, job: Job, worker: int) -> None:
        """Run a job on a worker (``live.jobs.run_job``) with what it needs from the store."""
        if job.key is not None and (job.kind == OBSERVE or (job.kind == MAP and not job.final)):
            self._home[job.key] = worker  # that process keeps the work for the tile's final pass
        elif job.key is not None and job.kind == REMAP:
            self._home.pop(job.key, None)
        kw = {
            "tile_config": self.tile_config,
            "pipeline_config": self.pipeline_config,
            "use_fleet_model": self.use_fleet_model,
        }
        if job.kind == MODEL:
            kw["observations"] = self.store.observations()
        if job.kind == REMAP:
            kw["offset_model"] = self._model
        if job.kind == FUSE:
            kw["tile_segments"] = {key: self._segments(key) for key, _ in job.tiles}
        if job.kind == REGION:
            # forked children only from a worker process, never from this one (native threads)
            kw["region_workers"] = self.workers if self.workers > 1 else 1
            self._home.clear()
        if job.kind == REGION and self.workers > 1 and self.store.path != ":memory:":
            # RULE: the region's worker reads every drive from the store itself (read-only): not
            # decoded here and pickled over, in this process of every node, on the settle's path
            kw["load_drives"] = functools.partial(read_drives, self.store.path)
            drives: list[Drive] = []
        else:
            drives = self._drives(job.drive_ids) if job.kind != MODEL else []
        if job.kind == FUSE:
            # RULE: a fusion runs here, where its tiles' settled segments are kept decoded: on a
            # worker, the segments of its ~100 tiles and the fused ones were pickled there and back
            # (more CPU than the fusion itself, ``scripts/profile_fast_path.py``)
            self._run_here(job, drives, kw)
            return
        fut = self._pools[worker].submit(run_job, job, drives, **kw)
        self._running[fut] = (job, worker)
        if self.workers > 1:
            fut.add_done_callback(self._job_done)

    def _run_here(self, job: Job, drives: Sequence[Drive], kw: dict) -> None:
        """Run a job in this process and commit it at once (as :meth:`_collect` would)."""
        self._here_cpu0 = time.thread_time()  # the CPU of this thread for the job, its commit and message (log)
        try:
            result = run_job(job, drives, **kw)
        except Exception as err:  # noqa: BLE001 - a bug on one drive must not stop the live map; logged in full
            self._fail(job, err)
            return
        self._commit(job, result)

    def _job_done(self, _fut: Future) -> None:
        """(A pool's thread) a job ended: wake :meth:`work` to collect it and start the next."""
        with contextlib.suppress(Exception):  # the node may be on its way down
            self._wake.trigger()

    def _collect(self) -> None:
        for fut in [f for f in self._running if f.done()]:
            job, _ = self._running.pop(fut)
            try:
                result = fut.result()
            except Exception as err:  # noqa: BLE001 - a bug on one tile must not stop the live map; logged in full
                self._fail(job, err)
                continue
            self._commit(job, result)

    def _commit(self, job: Job, result: JobResult) -> None:
        if job.kind in (FUSE, PART):
            self._commit_fused(job, result)
            return
        if job.kind == MODEL:
            self.store.put_model(result.model.to_dict(), job.sig)
            self._load_model()
            self.health.set("offset_model_drives", len(result.model.drives))
            self.health.set("last_model_update_s", f"{result.seconds:.3f}")
        elif job.kind == OBSERVE:
            self.store.put_observations(job.key, result.observations, job.drive_ids)
        elif job.kind == REGION:
            # the status first: the stitcher then knows the burst is coming (its tile_versions)
            self._put_and_publish(job, result.tiles or {}, model_sig=job.sig, announce=True)
            self.health.set("last_tile_update_s", f"{result.seconds:.3f}")
            self.health.set("tiles", self.scheduler.tile_count)
            if result.model is not None:
                self.health.set("offset_model_drives", len(result.model.drives))
        else:
            est = self.store.put_tile(
                job.key,
                result.segments,
                job.drive_ids,
                model_sig=job.sig if job.kind == REMAP else "",
                observations=result.observations,
            )
            self._publish(est, final=job.final)
            self.health.updated()
            self.health.set("last_tile_update_s", f"{result.seconds:.3f}")
            self.health.set("tiles", self.scheduler.tile_count)
        self.scheduler.finished(job, ok=True, observed=job.kind == MAP and result.observations is not None)

    def _commit_fused(self, job: Job, result: JobResult) -> None:
        """A drive fused into its tiles: the estimates stored in one commit and published final
        (the drive is listed once the stitcher has them); refused: its tiles go the normal way."""
        did = job.drive_ids[0] if job.drive_ids else "?"
        self.health.set("last_fuse_s", f"{result.seconds:.3f}")
        if result.tiles is None:
            self.fast_refused += 1
            self.health.set("fast_refused", self.fast_refused)
            self.get_logger().info(f"drive {did!r} not fused ({result.refused}): it waits for the settle")
            self.scheduler.finished(job, ok=False)
            return
        n_tiles, store_s, batch_s = self._put_and_publish(job, result.tiles, model_sig=FUSED)
        self.fast_fused += 1
        self.health.set("fast_fused", self.fast_fused)
        how = "fused into" if job.kind == FUSE else "mapped alone (new road) into"
        taken = self._last_taken[1] if self._last_taken[0] == did else None
        since = f"{time.monotonic() - taken:.3f} s after it was scheduled: " if taken is not None else ""
        cpu = f", CPU of this thread {time.thread_time() - self._here_cpu0:.3f} s" if job.kind == FUSE else ""
        self.get_logger().info(
            f"drive {did!r} {how} {n_tiles} tile(s) ({since}job {result.seconds:.3f} s, store {store_s:.3f} s, "
            f"batch message {batch_s:.3f} s{cpu})"
        )
        self.scheduler.finished(job, ok=True)

    def _put_and_publish(
        self, job: Job, tiles: Mapping[TileKey, list], *, model_sig: str, announce: bool = False
    ) -> tuple[int, float, float]:
        """A job's tile estimates (``tiles`` by key; a tile of the job without any: no segments)
        stored in one commit and published as one batch; ``announce``: the status published
        between. Returns the number of tiles, the seconds storing and publishing took."""
        t0 = time.perf_counter()
        made = [(key, tiles.get(key, []), ids) for key, ids in job.tiles]
        cols = segment_columns([seg for _, segs, _ in made for seg in segs])  # made once: the blobs and the batch
        stored = self.store.put_tiles(made, model_sig=model_sig, columns=cols)
        t1 = time.perf_counter()
        if announce:
            self._update_status()
        self._publish_batch(stored, [segs for _, segs, _ in made], cols)
        return len(made), t1 - t0, time.perf_counter() - t1

    def _fail(self, job: Job, err: Exception) -> None:
        what = "fleet offset model" if job.kind == MODEL else f"tile {job.key} ({job.kind})"
        text = f"{what}: {type(err).__name__}: {err}"
        self.scheduler.finished(job, ok=False)
        self.health.error(text)
        detail = "" if isinstance(err, HdmapError) else "\n" + "".join(traceback.format_exception(err))
        self.get_logger().error(f"{text}; kept as it was{detail}")

    def _load_model(self) -> None:
        data, sig = self.store.model()
        # RULE: the model is always used as stored (JSON round trip), so a restarted mapper maps with
        # exactly the model an uninterrupted one would have used.
        self._model = OffsetModel.from_dict(data) if data is not None else None
        self._model_sig = sig if data is not None else ""

    def _publish(self, est: TileEstimate, *, final: bool | None = None, segments: Sequence | None = None) -> None:
        """Publish an estimate; ``final`` None (a stored one): final when made with the fleet model
        or when the preset has none. ``segments``: its segments when at hand (else decoded)."""
        msg = tile_to_msg(
            est.key,
            list(segments) if segments is not None else est.segments(),
            version=est.version,
            drive_ids=est.drive_ids,
            tile_size_m=self.tile_config.tile_size_m,
            stamp_ns=time.time_ns(),
            types=self._tile_types,
            drive_tile_counts=[self.scheduler.drive_tile_count(d) for d in est.drive_ids],
            final=(bool(est.model_sig) or not self.use_fleet_model) if final is None else final,
        )
        self._seg_pub.publish(msg)
        self.tiles_published += 1

    def _publish_batch(
        self, stored: Sequence[TileEstimate], segments: Sequence[Sequence], columns: SegmentColumns | None = None
    ) -> None:
        """Publish the final estimates one job made (``stored``, with their ``segments``, and these
        in ``columns`` when at hand) as one TileSegmentsBatch: one message the stitcher stores in one
        transaction, instead of one TileSegments per tile; their segments are kept decoded
        (:meth:`_keep_segments`)."""
        tiles = [
            (
                est.key,
                self._keep_segments(est, segs),
                est.version,
                est.drive_ids,
                [self.scheduler.drive_tile_count(d) for d in est.drive_ids],
                True,
            )
            for est, segs in zip(stored, segments, strict=True)
        ]
        msg = tiles_to_batch(
            tiles,
            tile_size_m=self.tile_config.tile_size_m,
            stamp_ns=time.time_ns(),
            types=self._tile_types,
            columns=columns,
        )
        self._batch_pub.publish(msg)
        self.tiles_published += len(tiles)
        for _ in tiles:
            self.health.updated()

    def _update_status(self) -> None:
        """Publish the mapper's part of MapStatus when it changed."""
        status = LiveStatus(
            drives_received=self.store.drive_count(),
            drives_rejected=len(self._rejected_ids),
            tiles_pending=self.scheduler.pending_tiles() + len(self.store.pending()),
            tile_versions=self.store.version_total(),
            settled=self.is_settled(),
            stamp_ns=time.time_ns(),
        )
        if status.same(self._status):
            return
        self._status = status
        self._status_pub.publish(status_to_msg(status, cls=self._status_cls, types=self._types))

    def is_settled(self) -> bool:
        """No pending drive and the schedule settled (``LiveScheduler.is_settled``)."""
        return not self.store.pending() and self.scheduler.is_settled()

    def destroy_node(self) -> None:
        for pool in self._pools:
            pool.shutdown(wait=True, cancel_futures=True)
        self.store.close()
        super().destroy_node()


def main(args=None) -> None:
    run_node(SegmentMapper, args)


if __name__ == "__main__":
    main()
