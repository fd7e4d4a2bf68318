"""The live mapper's schedule: which tile job runs next. Pure: no DDS, no store, no clock of its own.

The segment mapper feeds it what happened (:meth:`LiveScheduler.add_drive`, :meth:`finished`) and
asks it what to run (:meth:`next_jobs`); it runs the jobs (:mod:`hdmap_core.live.tiles`), stores
and publishes their results. The rules:

- **Coalescing.** A drive queues the tiles it covers; a queued tile is one job however many drives
  wait on it, made from every drive covering the tile when the job starts. A tile in work when new
  drives come is queued again and runs after its current job.
- **Due test.** A tile without an estimate is due. A mapped tile is due at once when its drives
  drove new road in it (at least ``NEW_ROAD_CELLS`` cells of the ``road_cells`` grid its estimate
  has not seen: a ramp, the other carriageway), so coverage grows while a fleet arrives. Otherwise,
  with the fleet-wide model, a mapped tile waits for the settle (which re-makes every tile with
  the model anyway: a re-estimate before it is work thrown away, and the map keeps its final
  estimates meanwhile); without it, it is due when its drive count grew enough
  (:func:`~hdmap_core.live.tiles.needs_update`). A tile whose job failed is not retried until its
  drive set changes.
- **Bursts.** With the region settle, while drives come less than ``BURST_GAP_S`` apart (a fast
  replay) nothing is previewed: the settle after the burst makes every tile anyway. A drive alone
  is previewed at once. While the sender says more drives are on their way
  (:meth:`LiveScheduler.input_open`, e.g. ``hdmap run`` playing its bag) nothing is previewed and
  no drive takes the fast path either: every tile is made by the region settle once the input is
  in, so a preview or a one-drive map (and its map version) would be work thrown away.
- **Order.** Tiles no estimate covers yet go first, then tiles with new road, then re-estimates,
  the most grown (relative to the estimate) first.
- **Settling**, after ``settle_after_s`` without input (at once after :meth:`LiveScheduler.input_done`:
  the sender said no more drives come, e.g. ``hdmap run`` at the end of its bag) and with nothing
  queued or in work: without
  the fleet-wide offset model every tile not made from all its drives is re-estimated once. With
  it (presets with a final pass), in three phases: (1) every tile's observations brought up to its
  drive set, (2) one fleet-wide offset model from all observations, (3) every tile re-made from
  all its drives with that model. Phase 2 waits until no job is in work (a barrier); the jobs of
  phases 1 and 3 run side by side.
- **The fast path** (``fast_path``, with the fleet model): a drive every tile of which holds a
  settled estimate (made by the settle, or fused) and in which it drove no new road is not queued
  tile by tile: one :data:`FUSE` job fuses it into those estimates (:mod:`hdmap_core.live.fuse`:
  its offset against the map, the gauge moved as the batch solve would, its samples into the
  matched maxima). Its estimates are final but not the settle's (:data:`FUSED`), so the settle
  re-makes every tile as before. A drive alone on new road (no drive covered any of its tiles before
  it) is one :data:`PART` job: its tiles made by one build of it
  (:func:`~hdmap_core.live.region.map_region`), final, also :data:`FUSED`. At most
  ``FAST_MAX_SHARE`` of a tile's settled drives (at least one) are fused into it between two
  settles. A drive whose tiles changed meanwhile (a job on them, another drive's settle), or whose
  fusion is refused (it does not show the road the map holds), goes the normal way: its tiles
  queued.
- **The region settle** (with the fleet model and at most ``region_max_drives`` drives): instead
  of the three phases, one :data:`REGION` job makes every tile of the map at once
  (:func:`~hdmap_core.live.region.map_region`: the offline build's passes on the whole drives, cut
  into tiles), once no job is in work. Tiles queued when the settle comes are not previewed any
  more (the region makes them anyway). A region that fails falls back to the three phases.

Each job's result is a function of the tile's drive set (and the model), so the settled map
depends on the drives only, whatever the order, the number of workers or a restart in between.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

from hdmap_core.live.tiles import TileConfig, TileKey, needs_update, observations_signature

__all__ = [
    "Job",
    "LiveScheduler",
    "MAP",
    "OBSERVE",
    "MODEL",
    "REMAP",
    "REGION",
    "FUSE",
    "PART",
    "FUSED",
    "NEW_ROAD_CELLS",
    "BURST_GAP_S",
]

# RULE: with the region settle, drives arriving less than this apart are a burst (a fast replay):
# their tiles are not previewed until the input pauses this long (previews are thrown away by the
# settle after the burst; 30-drive ramps fleet at --rate 0, py-spy: ~40 % of the region's samples)
BURST_GAP_S = 0.5
NEW_ROAD_CELLS = 2  # RULE: new road in a mapped tile: this many road cells (16 m) its estimate has not seen

MAP = "map"  # the tile with its own offset adjustment (and its observations, with the fleet model)
OBSERVE = "observe"  # the tile's observation pass only (settle phase 1)
MODEL = "model"  # the fleet-wide offset model over every tile's observations (settle phase 2)
REMAP = "remap"  # the tile's final pass with the fleet-wide model (settle phase 3)
REGION = "region"  # every tile of the map in one build (the region settle)
FUSE = "fuse"  # one drive on settled road fused into its tiles' estimates (the fast path)
PART = "part"  # a drive alone on new road: its tiles made by one build of it (the fast path there)
FUSED = "fused"  # the model signature of a fused (or PART) estimate: final, never the settle's own
# RULE fast path: the fused map holds the settled map as its gauge, while the batch map of the same
# drives re-solves the offsets with them; each drive moves that solve by about 1/n of its offset, so
# at most FAST_MAX_SHARE of a tile's settled drives (at least one) are fused into it between two
# settles (the rest wait for the settle; the support a drive needs where it drives, the drives per
# line point, is checked by the fusion: a tile the drive only touches with its margin may hold few)
FAST_MAX_SHARE = 0.25


@dataclass(frozen=True)
class Job:
    """One unit of work.

    Attributes:
        kind: :data:`MAP`, :data:`OBSERVE`, :data:`MODEL`, :data:`REMAP` or :data:`REGION`.
        key: the tile (None for :data:`MODEL` and :data:`REGION`).
        drive_ids: the drives covering the tile when the job was made, sorted (its input); a
            :data:`REGION`: every drive of its tiles.
        sig: :data:`MODEL`: the signature of the observations it is made from; :data:`REMAP`: that
            of the model it uses; :data:`REGION`: that of the drive sets of its tiles; else ''.
        tiles: :data:`REGION`: every tile and its drives; :data:`FUSE`: the drive's tiles and their
            drives (the drive included).
        final: its estimate is made as the settled map makes it (a REMAP; a MAP when no fleet model
            is used, or when the model of these observations failed): only then do the drives it is
            made from count as mapped on this tile (``Map.drive_ids``).
    """

    kind: str
    key: TileKey | None
    drive_ids: tuple[str, ...] = ()
    sig: str = ""
    final: bool = False
    tiles: tuple[tuple[TileKey, tuple[str, ...]], ...] = ()  # REGION: every tile and its drives


class LiveScheduler:
    """Queue, due test, settle phases and jobs in work of the live mapper; see the module docstring.

    Args:
        tile_config: the tiling (its growth thresholds make the due test).
        use_fleet_model: settle with the fleet-wide offset model (a pipeline with a final pass).
        settle_after_s: idle time after the last drive before settling [s].
        region_max_drives: with the fleet model, settle with one :data:`REGION` job while the map
            has at most this many drives (0: never; the three phases).
        fast_path: with the fleet model, a drive on settled road is fused into its tiles
            (:data:`FUSE`) instead of waiting for the settle.
    """

    def __init__(
        self,
        tile_config: TileConfig,
        *,
        use_fleet_model: bool,
        settle_after_s: float,
        region_max_drives: int = 0,
        fast_path: bool = False,
    ) -> None:
        self.tile_config = tile_config
        self.use_fleet_model = use_fleet_model
        self.settle_after_s = float(settle_after_s)
        self.region_max_drives = int(region_max_drives)
        self.fast_path = bool(fast_path) and use_fleet_model
        self._fast: dict[str, tuple[TileKey, ...]] = {}  # drives waiting for the fast path (arrival order)
        self._part: dict[str, tuple[TileKey, ...]] = {}  # drives alone on new road waiting for their PART job
        self._fused: dict[TileKey, int] = {}  # drives fused into the tile's estimate since it was made
        self._region_sig: str | None = None  # cache of the tiles' drive sets' signature
        self._region_failed_sig = ""  # drive sets whose region job failed
        self._tiles: dict[TileKey, set[str]] = {}  # tile -> drives covering it
        self._drive_tiles: dict[str, int] = {}  # drive -> number of tiles it covers
        self._est: dict[TileKey, tuple[int, str]] = {}  # tile -> (drive count, model sig) of its estimate
        self._obs: dict[TileKey, tuple[str, ...]] = {}  # tile -> drives its observations were made from
        self._failed: dict[TileKey, int] = {}  # tile -> drive count at which its job failed
        self._obs_failed: dict[TileKey, int] = {}
        self._model_sig = ""  # observations the current model was made from
        self._model_failed_sig = ""  # observations whose model failed
        self._obs_sig: str | None = None  # cache of the observations' signature
        self._queue: set[TileKey] = set()
        self._busy: dict[TileKey | None, Job] = {}  # jobs in work (None: the model)
        self._cursor: TileKey | None = None  # phase 3 round robin: where the last turn stopped
        self._last_input = float("-inf")
        self._prev_input = float("-inf")  # the drive before the last one came then (a burst)
        self._input_done = False  # the sender said no more input comes (until the next drive)
        self._input_open = False  # the sender said more input is on its way (until input_done)
        self._cells: dict[TileKey, set[tuple[int, int]]] = {}  # road cells the tile's drives drove
        self._cells_est: dict[TileKey, frozenset[tuple[int, int]]] = {}  # ... those of its estimate's drives
        self._cells_job: dict[TileKey, frozenset[tuple[int, int]]] = {}  # ... those of its job in work
        self._cells_unknown: set[TileKey] = set()  # estimates restored from a store: their cells are not known
        # RULE: is_settled and pending_tiles are asked several times per worker turn (mapper,
        # status, hdmap run's end check; paper_like: ~15000 calls, each over every tile) and only
        # change with the state: their answers are kept until a method that changes it is called
        self._memo: dict[str, int] = {}

    # --- inputs ----------------------------------------------------------------------------------

    def restore(
        self,
        tile_drives: dict[TileKey, Iterable[str]],
        estimates: Iterable[tuple[TileKey, Sequence[str], str]],
        observations: Iterable[tuple[TileKey, Sequence[str]]] = (),
        model_sig: str = "",
        *,
        now: float,
    ) -> None:
        """The state of a store (a restart): drives per tile, (tile, drives, model sig) of each
        estimate, (tile, drives) of each tile's observations, the stored model's signature; ``now``
        counts as the last input. Every
        tile that is due is queued (the queue itself is not stored: it follows from the rest)."""
        self._memo.clear()
        for key, ids in tile_drives.items():
            self._tiles.setdefault(key, set()).update(ids)
        counts: dict[str, int] = {}
        for ids in self._tiles.values():
            for d in ids:
                counts[d] = counts.get(d, 0) + 1
        self._drive_tiles.update(counts)
        for key, ids, sig in estimates:
            self._est[key] = (len(ids), sig)
            self._cells_unknown.add(key)  # new road is told from the tile's next estimate on
        for key, ids in observations:
            self._obs[key] = tuple(sorted(ids))
        self._obs_sig = None
        self._region_sig = None
        self._model_sig = model_sig
        self._last_input = now  # settling waits as after a drive
        self._queue.update(k for k in self._tiles if self._due(k))

    def add_drive(
        self,
        drive_id: str,
        tiles: Iterable[TileKey],
        now: float,
        cells: Mapping[TileKey, Iterable[tuple[int, int]]] | None = None,
    ) -> bool:
        """A new drive covering ``tiles`` (False, nothing changed, for a known drive); ``cells``:
        where it drove, per tile (:func:`~hdmap_core.live.tiles.road_cells`; None: not known)."""
        self._memo.clear()
        if drive_id in self._drive_tiles:
            return False
        keys = set(tiles)
        # RULE: while the input is open (more drives on their way) and the region settle will make
        # every tile, no drive takes the fast path: its map would be made again at once
        hold = self._holding(extra=1)
        fast = not hold and self.fast_path and cells is not None and self._on_settled_road(keys, cells)
        alone = not hold and self.fast_path and bool(keys) and all(self._alone_new(k) for k in keys)
        for key, cs in (cells or {}).items():
            self._cells.setdefault(key, set()).update(cs)
        self._drive_tiles[drive_id] = len(keys)
        for key in keys:
            self._tiles.setdefault(key, set()).add(drive_id)
        if fast:
            self._fast[drive_id] = tuple(sorted(keys))
        elif alone:
            self._part[drive_id] = tuple(sorted(keys))
        else:
            self._queue.update(keys)
        self._region_sig = None
        self._prev_input, self._last_input = self._last_input, now
        self._input_done = False  # more input came after all: settle_after_s again
        return True

    def _alone_new(self, key: TileKey) -> bool:
        """No drive covers the tile yet (before the one being added) and nothing is made or queued there."""
        return not self._tiles.get(key) and key not in self._est and key not in self._queue and key not in self._busy

    def _on_settled_road(self, keys: set[TileKey], cells: Mapping[TileKey, Iterable[tuple[int, int]]]) -> bool:
        """Every tile holds a settled (or fused) estimate whose road cells are known and the drive
        drove no new road in any of them."""
        waiting: dict[TileKey, int] = {}
        for ks in self._fast.values():
            for k in ks:
                waiting[k] = waiting.get(k, 0) + 1
        for key in keys:
            est = self._est.get(key)
            if est is None or est[1] == "" or key in self._cells_unknown or key in self._queue:
                return False
            fused = self._fused.get(key, 0)
            base = est[0] - fused
            if fused + waiting.get(key, 0) + 1 > max(1.0, FAST_MAX_SHARE * base):
                return False
            if len(set(cells.get(key, ())) - self._cells_est.get(key, frozenset())) >= NEW_ROAD_CELLS:
                return False
        return bool(keys)

    def input_done(self) -> None:
        """No more drives come (the sender knows, e.g. its bag is played): settle without waiting
        ``settle_after_s``. A drive added afterwards makes the settle wait again as usual."""
        self._memo.clear()
        self._input_done = True
        self._input_open = False

    def input_open(self) -> None:
        """More drives are on their way (the sender knows, e.g. it is playing a bag): with the
        region settle, nothing is previewed and no drive takes the fast path until
        :meth:`input_done` (module docstring, "Bursts")."""
        self._memo.clear()
        self._input_open = True
        self._input_done = False

    def _holding(self, extra: int = 0) -> bool:
        """The input is open and the region settle will make every tile (``extra``: drives about
        to be added)."""
        return (
            self._input_open
            and self.use_fleet_model
            and 0 < self.drive_count + extra <= self.region_max_drives
            and (not self._region_failed_sig or self._region_failed_sig != self.region_sig())
        )

    def _burst(self, now: float) -> bool:
        """Drives are coming in a burst: the last two came less than :data:`BURST_GAP_S` apart and
        the last one less than that ago (a drive alone is previewed at once)."""
        return self._last_input - self._prev_input < BURST_GAP_S and now - self._last_input < BURST_GAP_S

    def _quiet(self, now: float) -> bool:
        """No input for ``settle_after_s``, or none to come (:meth:`input_done`)."""
        return self._input_done or now - self._last_input >= self.settle_after_s

    def finished(self, job: Job, *, ok: bool, observed: bool = False) -> None:
        """A job ended. ``observed``: a :data:`MAP` job also stored the tile's observations."""
        self._memo.clear()
        if job.kind == PART:
            self._part_finished(job, ok)
            return
        if job.kind == FUSE:
            self._fuse_finished(job, ok)
            return
        self._busy.pop(job.key if job.kind != MODEL else None, None)
        if job.kind == REGION:
            self._region_finished(job, ok)
            return
        n = len(job.drive_ids)
        if job.kind == MODEL:
            if ok:
                self._model_sig = job.sig
            else:
                self._model_failed_sig = job.sig
            return
        key = job.key
        if key is None:  # only a MODEL job has no tile
            return
        if job.kind == OBSERVE:
            if ok:
                self._obs[key] = job.drive_ids
                self._obs_sig = None
                self._obs_failed.pop(key, None)
            else:
                self._obs_failed[key] = n
            return
        cells = self._cells_job.pop(key, frozenset())
        if not ok:
            self._failed[key] = n
            return
        self._est[key] = (n, job.sig if job.kind == REMAP else "")
        self._fused.pop(key, None)
        self._cells_est[key] = cells
        self._cells_unknown.discard(key)
        self._failed.pop(key, None)
        if observed:
            self._obs[key] = job.drive_ids
            self._obs_sig = None

    def _fuse_finished(self, job: Job, ok: bool) -> None:
        for key, _ in job.tiles:
            self._busy.pop(key, None)
            cells = self._cells_job.pop(key, frozenset())
            if ok and key in self._est:
                self._est[key] = (self._est[key][0] + 1, FUSED)
                self._fused[key] = self._fused.get(key, 0) + 1
                self._cells_est[key] = self._cells_est.get(key, frozenset()) | cells
        if not ok:  # the normal way: its tiles wait for the settle (or are due, with new road)
            self._queue.update(k for k, _ in job.tiles)

    def _part_finished(self, job: Job, ok: bool) -> None:
        for key, ids in job.tiles:
            self._busy.pop(key, None)
            cells = self._cells_job.pop(key, frozenset())
            if ok:
                self._est[key] = (len(ids), FUSED)
                self._cells_est[key] = cells
                self._fused.pop(key, None)
        if not ok:
            self._queue.update(k for k, _ in job.tiles)

    def _region_finished(self, job: Job, ok: bool) -> None:
        for key, _ in job.tiles:
            self._busy.pop(key, None)
        if not ok:
            self._region_failed_sig = job.sig
            for key, _ in job.tiles:
                self._cells_job.pop(key, None)
            return
        for key, ids in job.tiles:
            self._est[key] = (len(ids), job.sig)
            self._fused.pop(key, None)
            self._cells_est[key] = self._cells_job.pop(key, frozenset())
            self._cells_unknown.discard(key)
            self._failed.pop(key, None)
        for d in set(job.drive_ids) & set(self._fast):  # made by the region: nothing left to fuse
            del self._fast[d]
        for d in set(job.drive_ids) & set(self._part):
            del self._part[d]

    # --- queries ---------------------------------------------------------------------------------

    def drive_tile_count(self, drive_id: str) -> int:
        """How many tiles a drive covers (0: unknown drive)."""
        return self._drive_tiles.get(drive_id, 0)

    def tile_drives(self, key: TileKey) -> tuple[str, ...]:
        """The drives covering a tile, sorted."""
        return tuple(sorted(self._tiles.get(key, ())))

    def queued(self) -> set[TileKey]:
        """Tiles queued or in work."""
        return set(self._queue) | {k for k in self._busy if k is not None}

    def is_mapped(self, key: TileKey) -> bool:
        """The tile has an estimate."""
        return key in self._est

    @property
    def drive_count(self) -> int:
        return len(self._drive_tiles)

    @property
    def tile_count(self) -> int:
        return len(self._tiles)

    @property
    def busy(self) -> int:
        """Jobs in work."""
        return len(self._busy)

    @property
    def model_sig(self) -> str:
        return self._model_sig

    def fast_pending(self) -> int:
        """Drives waiting for the fast path (on settled road or alone on new road)."""
        return len(self._fast) + len(self._part)

    def pending_tiles(self) -> int:
        """Tiles queued, in work, or not yet made from all their drives (failed ones excepted)."""
        if "pending" not in self._memo:
            self._memo["pending"] = self._pending_tiles()
        return int(self._memo["pending"])

    def _pending_tiles(self) -> int:
        waiting = set(self._queue) | {k for k in self._busy if k is not None}
        waiting.update(k for k in self._tiles if self._stale(k) and not self._failed_at_count(k))
        return len(waiting)

    def observations_sig(self) -> str:
        """Signature of the drive sets every tile's observations were made from ('' = none)."""
        if self._obs_sig is None:
            self._obs_sig = observations_signature(self._obs.items()) if self._obs else ""
        return self._obs_sig

    def region_sig(self) -> str:
        """Signature of every tile's drive set: what a :data:`REGION` job made from them is named by."""
        if self._region_sig is None:
            self._region_sig = (
                "region:" + observations_signature((k, tuple(v)) for k, v in self._tiles.items()) if self._tiles else ""
            )
        return self._region_sig

    def idle(self, now: float) -> bool:
        """Nothing queued or in work and no drive for ``settle_after_s`` (or none to come): time to settle."""
        return not self._queue and not self._busy and not self._fast and not self._part and self._quiet(now)

    def is_settled(self) -> bool:
        """Nothing queued or in work and every tile made from all its drives (with the fleet model:
        every tile observed, the model current, every tile made with it), failed tiles excepted."""
        if "settled" not in self._memo:
            self._memo["settled"] = int(self._is_settled())
        return bool(self._memo["settled"])

    def _is_settled(self) -> bool:
        if self._queue or self._busy or self._fast or self._part:
            return False
        if self._region_phase():
            return not self._off_region()
        if self._model_phase():
            if self._stale_observations():
                return False
            if self._model_sig != self.observations_sig():
                return False
            return not self._off_model()
        return not any(self._stale(k) and not self._failed_at_count(k) for k in self._tiles)

    # --- the schedule ----------------------------------------------------------------------------

    def next_jobs(self, now: float, limit: int = 1, *, prefer: Callable[[TileKey], bool] | None = None) -> list[Job]:
        """Up to ``limit`` jobs to start now (marked as in work), in the order to start them.

        ``prefer``: of the settle's final jobs (phase 3, any order gives the same map), a tile it
        holds true for goes first (the mapper: the worker asking holds that tile's observation pass).
        """
        self._memo.clear()
        jobs: list[Job] = []
        while len(jobs) < limit:
            job = self._next(now, prefer)
            if job is None:
                break
            if job.kind not in (FUSE, PART):  # these hold their tiles only (several may run side by side)
                self._busy[job.key if job.kind != MODEL else None] = job
            if job.key is not None and job.kind in (MAP, REMAP):
                self._cells_job[job.key] = frozenset(self._cells.get(job.key, ()))
            for key, _ in job.tiles:  # a REGION, a FUSE: its tiles are in work (new drives wait behind it)
                self._busy[key] = job
                self._cells_job[key] = frozenset(self._cells.get(key, ()))
            jobs.append(job)
        return jobs

    def _next(self, now: float, prefer: Callable[[TileKey], bool] | None = None) -> Job | None:
        fuse = self._fuse_job() or self._part_job()
        if fuse is not None:
            return fuse
        if self._quiet(now) and self._region_phase():
            # RULE coalescing: once the input settles, the region job makes every tile; a preview
            # of a tile still queued would be thrown away with it
            self._queue.clear()
        if self._queue and self._holding():
            return None  # RULE: the input is open: the region settle after it makes every tile
        if self._queue and self._burst(now) and self._region_phase():
            # RULE: drives come faster than previews are made: a preview now is thrown away by the
            # region settle after the burst (and costs a map version while drives come); wait for a pause
            return None
        while self._queue:
            ready = [k for k in self._queue if k not in self._busy]
            if not ready:
                return None  # every queued tile is in work: it is queued again behind its job
            key = self._pick(ready)
            self._queue.discard(key)
            if self._due(key):
                failed = self._model_failed_sig != "" and self._model_failed_sig == self.observations_sig()
                return Job(MAP, key, self.tile_drives(key), final=not self.use_fleet_model or failed)
        if not self._quiet(now):
            return None
        return self._settle_job(prefer)

    def _fuse_job(self) -> Job | None:
        """The first drive waiting for the fast path whose tiles are free: its :data:`FUSE` job
        if its tiles still hold settled estimates of all their other drives, else its tiles are
        queued (the normal way)."""
        waiting: dict[TileKey, int] = {}
        for keys in self._fast.values():
            for key in keys:
                waiting[key] = waiting.get(key, 0) + 1
        for did, keys in list(self._fast.items()):
            if any(k in self._busy for k in keys):
                continue
            del self._fast[did]
            ok = all(
                k in self._est and self._est[k][1] != "" and self._est[k][0] + waiting[k] == self._count(k)
                for k in keys
            )
            if ok:
                return Job(FUSE, None, (did,), final=True, tiles=tuple((k, self.tile_drives(k)) for k in keys))
            self._queue.update(keys)  # RULE: tiles changed meanwhile: the normal way
        return None

    def _part_job(self) -> Job | None:
        """The first drive alone on new road whose tiles are free: its :data:`PART` job while it is
        still the only drive on every tile of it, else its tiles are queued (the normal way)."""
        for did, keys in list(self._part.items()):
            if any(k in self._busy for k in keys):
                continue
            del self._part[did]
            if all(self._count(k) == 1 and k not in self._est for k in keys):
                return Job(PART, None, (did,), final=True, tiles=tuple((k, (did,)) for k in keys))
            self._queue.update(keys)
        return None

    def _pick(self, ready: list[TileKey]) -> TileKey:
        fresh = [k for k in ready if k not in self._est]
        if fresh:
            return min(fresh)
        road = [k for k in ready if self._new_road(k)]
        if road:
            return min(road)
        # RULE: the most grown estimate first (relative to its drive count), ties by key
        return min(ready, key=lambda k: (-len(self._tiles.get(k, ())) / max(1, self._est[k][0]), k))

    def _settle_job(self, prefer: Callable[[TileKey], bool] | None = None) -> Job | None:
        if self._region_phase():
            if self._busy or not self._off_region():
                return None  # the region waits for the jobs in work: it makes their tiles too
            tiles = tuple((k, self.tile_drives(k)) for k in sorted(self._tiles))
            ids = tuple(sorted({d for _, ds in tiles for d in ds}))
            return Job(REGION, None, ids, self.region_sig(), final=True, tiles=tiles)
        if not self._model_phase():
            for key in sorted(self._tiles):
                if key not in self._busy and self._stale(key) and not self._failed_at_count(key):
                    return Job(MAP, key, self.tile_drives(key), final=True)
            return None
        stale_obs = self._stale_observations()
        for key in stale_obs:  # 1. observations of every tile's drive set
            if key not in self._busy:
                return Job(OBSERVE, key, self.tile_drives(key))
        if stale_obs:
            return None  # the model waits for every observation
        sig = self.observations_sig()
        if sig != self._model_sig:  # 2. the fleet-wide model of those observations, once no job is in work
            return None if self._busy else Job(MODEL, None, (), sig)
        keys = [k for k in self._off_model() if k not in self._busy]
        if not keys:
            return None
        if self._cursor is not None:  # round robin: a settle cut short goes on where it stopped
            after = [k for k in keys if k > self._cursor]
            keys = after + [k for k in keys if k <= self._cursor]
        key = next((k for k in keys if prefer(k)), keys[0]) if prefer is not None else keys[0]
        self._cursor = key
        return Job(REMAP, key, self.tile_drives(key), self._model_sig, final=True)  # 3. every tile with the model

    # --- tile state ------------------------------------------------------------------------------

    def _count(self, key: TileKey) -> int:
        return len(self._tiles.get(key, ()))

    def _due(self, key: TileKey) -> bool:
        count = self._count(key)
        est = self._est.get(key, (0, ""))[0]
        if self._failed.get(key) == count or count <= 0:
            return False
        if est <= 0 or self._new_road(key):
            return True
        if self.use_fleet_model:
            return False  # mapped road waits for the settle: it re-makes every tile with the model
        return needs_update(est, count, config=self.tile_config)

    def _new_road(self, key: TileKey) -> bool:
        """The tile's drives drove road in it that its estimate has not seen."""
        if key not in self._est or key in self._cells_unknown:
            return False
        return len(self._cells.get(key, set()) - self._cells_est.get(key, frozenset())) >= NEW_ROAD_CELLS

    def _stale(self, key: TileKey) -> bool:
        return self._est.get(key, (0, ""))[0] < self._count(key)

    def _failed_at_count(self, key: TileKey) -> bool:
        return self._failed.get(key) == self._count(key)

    def _model_phase(self) -> bool:
        """Settling goes through the fleet model (unless the model of these observations failed)."""
        return self.use_fleet_model and self._model_failed_sig != self.observations_sig()

    def _region_phase(self) -> bool:
        """Settling is one region job (the fleet model, not too many drives, its region not failed)."""
        return (
            self.use_fleet_model
            and 0 < self.drive_count <= self.region_max_drives
            and self._region_failed_sig != self.region_sig()
        )

    def _off_region(self) -> bool:
        """Some tile is not made from all its drives by the region job of the current drive sets."""
        sig = self.region_sig()
        return any(self._est.get(k, (0, ""))[1] != sig or self._stale(k) for k in self._tiles)

    def _stale_observations(self) -> list[TileKey]:
        """Tiles whose observations are older than their drive set (and did not fail at it), by key."""
        return sorted(
            k
            for k in self._tiles
            if len(self._obs.get(k, ())) < self._count(k) and self._obs_failed.get(k) != self._count(k)
        )

    def _off_model(self) -> list[TileKey]:
        """Tiles not made from all their drives with the current model (failed ones excepted), by key."""
        return sorted(
            k
            for k in self._tiles
            if (self._stale(k) or self._est[k][1] != self._model_sig) and not self._failed_at_count(k)
        )
