"""segment_mapper: the drive store and the per-tile estimates (stages of Sec. III-IV, per tile).

Subscribes ``/hdmap/drives_accepted``. Each new drive is committed to the SQLite drive store
together with the tiles it covers (one transaction); from then on it is *acknowledged* (an ack is
published on ``/hdmap/drive_acks``) and survives any crash. A worker then re-maps the tiles the
new drives cover, each from all stored drives covering it (``hdmap_core.live.tiles.map_tile``),
but only when the tile's drive count grew enough for the estimate to improve (parameters
``min_growth_fraction`` / ``min_growth_drives``; a new tile is always mapped). Each estimate is
committed (one transaction) and published on ``/hdmap/segments`` as hdmap_msgs/TileSegments with a
growing version per tile. When no drive came for ``settle_after_s``, every tile whose estimate
is older than its drive set is re-estimated once, so the settled map depends on the drives only.

Offsets (presets with the global adjustment, e.g. ``default``): an estimate made while drives come
adjusts offsets over the tile and its margin only, and its step observations are stored with it.
When the input settles, (1) every tile's observations are brought up to its drive set
(``incremental.observe_tile``), (2) one fleet-wide offset model is estimated from the
observations of all tiles (``incremental.fleet_offsets``, the network-wide adjustment of
``hdmap bag2map``) and stored (``OffsetModel.to_dict``) with a signature of the drive sets it was
made from, and (3) every tile not yet made from all its drives with that model is re-estimated
with it (the final pass only). Each is a pure function of the stored drives, so the settled map
still depends on the drive set only, also across SIGKILL and restart.

An update is: the drive committed and acknowledged, the tiles it adds (no estimate yet) mapped and
published. Re-estimates of mapped tiles are background work: the worker takes them one tile at a
time and only when no new drive waits and no new tile is queued, so a new drive waits at most for
the one re-estimate in progress.

Restart: pending (acknowledged, unprocessed) drives are processed; with ``republish_on_start``
every stored tile estimate is published again (the stitcher ignores versions it has).
"""

from __future__ import annotations

import os
import time
import traceback

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from std_msgs.msg import String

from hdmap_core.errors import ConfigError, HdmapError, InvalidDriveError
from hdmap_core.live.tiles import (
    TileConfig,
    TileKey,
    fleet_offsets,
    map_tile,
    map_tile_observed,
    needs_update,
    observations_signature,
    observe_tile,
    tiles_of_drive,
)
from hdmap_core.model import validate_drive
from hdmap_core.pipeline.adjustment import OffsetModel
from hdmap_ros.convert.messages import msg_to_drive, rclpy_types
from hdmap_ros.convert.tiles import rclpy_tile_types, tile_to_msg
from hdmap_ros.nodes import qos
from hdmap_ros.nodes._common import HealthMixin, declare, declare_pipeline_config, run_node
from hdmap_ros.persistence.store import DriveStore, TileEstimate

__all__ = ["SegmentMapper", "main"]

ACCEPTED_TOPIC = "/hdmap/drives_accepted"
SEGMENTS_TOPIC = "/hdmap/segments"
ACKS_TOPIC = "/hdmap/drive_acks"


class SegmentMapper(HealthMixin, Node):
    """Keeps the drive store and publishes tile estimates; see the module docstring."""

    def __init__(self, **kwargs) -> None:
        super().__init__("segment_mapper", **kwargs)
        db = declare(self, "db_path", "~/.ros/hdmap/segment_mapper.db", "SQLite file of the drive store.")
        pipeline_config = declare_pipeline_config(self)  # a bad preset or override fails here, named
        self.tile_config = TileConfig(
            tile_size_m=declare(self, "tile_size_m", 256.0, "Edge of a map tile [m].", lo=32.0, hi=4096.0),
            margin_m=declare(
                self, "margin_m", 128.0, "Context mapped around a tile [m]; must be < tile_size_m.", lo=0.0, hi=1024.0
            ),
            min_growth_fraction=declare(
                self, "min_growth_fraction", 0.10,
                "Re-estimate a tile when its drive count grew by this fraction (and min_growth_drives).",
                lo=0.0, hi=10.0,
            ),
            min_growth_drives=declare(
                self, "min_growth_drives", 3, "Re-estimate a tile when at least this many drives were added.",
                lo=1, hi=10000,
            ),
            seed=declare(self, "seed", 0, "Base seed; each tile's seed derives from it and the tile key.", lo=0, hi=2**31 - 1),
            pivot_margin_m=self._pivot_margin(),
        )
        self.settle_after_s = declare(
            self, "settle_after_s", 2.0, "Idle time after which stale tiles are re-estimated [s].", lo=0.0, hi=3600.0
        )
        depth = declare(
            self, "segments_history_depth", 1000, "Tile estimates kept (TRANSIENT_LOCAL) for a restarting stitcher.",
            lo=1, hi=100000,
        )
        accepted_depth = declare(
            self, "accepted_history_depth", 100, "History depth of /hdmap/drives_accepted (match the ingestor).",
            lo=1, hi=100000,
        )
        republish = declare(self, "republish_on_start", True, "Publish every stored tile estimate at start.")
        self.work_slice_s = declare(
            self, "work_slice_s", 0.5, "Mapping time per worker turn [s]; new drives are taken in between.",
            lo=0.0, hi=600.0,
        )
        self._init_health("segment_mapper")
        self.health.backlog_warn = 200

        self.pipeline_config = pipeline_config
        self.store = DriveStore(os.path.expanduser(db))
        self._check_tiling()
        self._types = rclpy_types()
        self._tile_types = rclpy_tile_types()
        self._last_input = time.monotonic()
        self._failed: dict[TileKey, int] = {}  # tile -> drive count at which mapping failed
        # fleet-wide offset model (presets with the global adjustment only)
        self.use_fleet_model = self.pipeline_config.final_pass is not None
        self._obs_failed: dict[TileKey, int] = {}  # tile -> drive count at which its observation pass failed
        self._model_failed_sig = ""  # observations whose fleet adjustment failed
        self._obs_sig: str | None = None  # signature of the stored observations (None: recompute)
        self._model: OffsetModel | None = None
        self._model_sig = ""
        self._model_cursor: TileKey | None = None  # last tile re-estimated with the model (round robin)
        self._load_model()
        self.tiles_published = 0
        self.received = 0

        self._seg_pub = self.create_publisher(self._tile_types.TileSegments, SEGMENTS_TOPIC, qos.replay(depth))
        self._ack_pub = self.create_publisher(String, ACKS_TOPIC, qos.ACKS)
        # Receiving (commit + ack) stays quick and apart from the slow mapping worker.
        self._rx_group = MutuallyExclusiveCallbackGroup()
        self._work_group = MutuallyExclusiveCallbackGroup()
        self._sub = self.create_subscription(
            self._types.Drive, ACCEPTED_TOPIC, self.on_drive, qos.replay(accepted_depth), callback_group=self._rx_group
        )
        self._timer = self.create_timer(0.05, self.work, callback_group=self._work_group)
        if republish:
            for est in self.store.tiles():
                self._publish(est)
        # drive count of each tile's latest estimate (the store's, cached: the worker asks per tile)
        self._est_count: dict[TileKey, int] = {t.key: t.drive_count for t in self.store.tiles()}
        # the due tiles of before a restart (the queue is not stored; it follows from the store)
        self._queue: set[TileKey] = {k for k in self.store.stale_tiles() if self._due(k)[0]}
        self.health.backlog = len(self.store.pending()) + len(self._queue)
        self.health.set("drives_stored", self.store.drive_count())
        self.get_logger().info(
            f"drive store {self.store.path}: {self.store.drive_count()} drive(s), {self.health.backlog} pending, "
            f"{len(self.store.tiles())} tile(s)"
        )

    def _pivot_margin(self) -> float | None:
        margin = float(self.get_parameter("margin_m").value)
        pm = declare(
            self, "pivot_margin_m", 48.0,
            "Pivots walk their steps only this far around a tile [m] (the whole margin stays context); "
            ">= margin_m walks the whole grown tile.",
            lo=0.0, hi=1024.0,
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

    # --- receiving -------------------------------------------------------------------------------

    def on_drive(self, msg) -> None:
        """Commit one drive (acknowledge it); mapping happens in :meth:`work`."""
        try:
            self._receive(msg)
        finally:
            self.received += 1  # counted once handled, so "received" means "stored or refused"

    def _receive(self, msg) -> None:
        did = str(msg.drive_id)
        try:
            drive = validate_drive(msg_to_drive(msg, expected_frame=None), expected_frame="")
        except InvalidDriveError as err:
            self.health.reject(err.reason, did)
            self.get_logger().warning(f"drive {did!r} rejected: {err.reason} ({err.detail})")
            return
        except HdmapError as err:
            self.health.reject("invalid_message", f"{did!r}: {err}")
            self.get_logger().warning(f"drive {did!r} rejected: {err}")
            return
        self._last_input = time.monotonic()
        if not self.store.add_drive(drive, tiles_of_drive(drive, config=self.tile_config)):
            self.health.duplicate()
            return
        self._ack_pub.publish(String(data=drive.drive_id))
        self.health.accept()
        self.health.backlog += 1
        self.health.set("drives_stored", self.store.drive_count())

    # --- mapping ---------------------------------------------------------------------------------

    def work(self) -> None:
        """One worker turn: queue the tiles of new drives, map due tiles for a time slice, settle."""
        self._work()
        self.health.backlog = len(self._queue) + len(self.store.pending())
        self.health.set("tiles_due", len(self._queue))
        self.health.set("settled", self.is_settled())
        self.health.set("tile_versions", self.store.version_total())

    def _due(self, key: TileKey) -> tuple[bool, int]:
        count = self.store.tile_drive_count(key)
        due = needs_update(self._est_count.get(key, 0), count, config=self.tile_config)
        return due and self._failed.get(key) != count, count

    def _next_tile(self) -> TileKey:
        # RULE: stretches no estimate covers yet go first (a new road is on the map at once);
        # re-estimates of mapped stretches follow, in key order.
        fresh = [k for k in self._queue if k not in self._est_count]
        return min(fresh) if fresh else min(self._queue)

    def _take_pending(self) -> bool:
        """Queue the tiles of acknowledged, unprocessed drives; True when there were any."""
        pending = self.store.pending()
        if pending:
            # A drive is processed once its tiles are queued; the queue itself need not be stored:
            # at start it is rebuilt from the store (every tile that is due).
            self._queue.update(self.store.tiles_of(pending))
            self.store.mark_processed(pending)
        return bool(pending)

    def _work(self) -> None:
        pending = self._take_pending()
        deadline = time.monotonic() + self.work_slice_s
        while self._queue and time.monotonic() < deadline:
            key = self._next_tile()
            if key in self._est_count and self._take_pending():
                continue  # a re-estimate is background work: a drive that came meanwhile goes first
            self._queue.discard(key)
            due, count = self._due(key)
            if due:
                self._estimate(key, count)
        if self._queue or pending or time.monotonic() - self._last_input < self.settle_after_s:
            return
        if self.use_fleet_model and self._model_failed_sig != self._observations_sig():
            self._settle_with_model(deadline)
            return
        for key in self.store.stale_tiles():  # settle: every estimate made from all its drives
            count = self.store.tile_drive_count(key)
            if self._failed.get(key) != count:
                self._estimate(key, count)
            if time.monotonic() >= deadline or self.store.pending():
                return

    # --- the fleet-wide offset model -------------------------------------------------------------

    def _load_model(self) -> None:
        data, sig = self.store.model()
        # RULE: the model is always used as stored (JSON round trip), so a restarted mapper maps with
        # exactly the model an uninterrupted one would have used.
        self._model = OffsetModel.from_dict(data) if data is not None else None
        self._model_sig = sig if data is not None else ""

    def _observations_sig(self) -> str:
        if self._obs_sig is None:
            sets = self.store.observation_sets()
            self._obs_sig = observations_signature(sets) if sets else ""  # nothing observed: no model needed
        return self._obs_sig

    def _settle_with_model(self, deadline: float) -> None:
        """Settle in three phases (module docstring); returns at the deadline or when a drive waits."""

        def out_of_time() -> bool:
            return time.monotonic() >= deadline or bool(self.store.pending())

        for key in self.store.stale_observations():  # 1. observations of every tile's drive set
            count = self.store.tile_drive_count(key)
            if self._obs_failed.get(key) != count:
                self._observe(key)
            if out_of_time():
                return
        if any(self._obs_failed.get(k) != self.store.tile_drive_count(k) for k in self.store.stale_observations()):
            return
        sig = self._observations_sig()
        if sig != self._model_sig:  # 2. the fleet-wide model of those observations
            if not self._estimate_model(sig) or out_of_time():
                return
        keys = self._tiles_off_model()
        if self._model_cursor is not None:  # round robin: a settle cut short goes on where it stopped
            keys = [k for k in keys if k > self._model_cursor] + [k for k in keys if k <= self._model_cursor]
        for key in keys:  # 3. every tile made from all its drives with that model
            count = self.store.tile_drive_count(key)
            if self._failed.get(key) != count:
                self._estimate(key, count, model=True)
            self._model_cursor = key
            if out_of_time():
                return

    def _tiles_off_model(self) -> list[TileKey]:
        off = set(self.store.tiles_off_model(self._model_sig)) | set(self.store.stale_tiles())
        return sorted(off)

    def _observe(self, key: TileKey) -> None:
        drives = self.store.drives_covering(key)
        try:
            obs = observe_tile(drives, key, tile_config=self.tile_config, pipeline_config=self.pipeline_config)
        except Exception as err:  # noqa: BLE001 - logged in full; the tile keeps its observations
            self._obs_failed[key] = len(drives)
            self.health.error(f"tile {key} observations: {type(err).__name__}: {err}")
            self.get_logger().error(f"observation pass failed for tile {key}: {traceback.format_exc()}")
            return
        self.store.put_observations(key, obs, [d.drive_id for d in drives])
        self._obs_sig = None
        self._obs_failed.pop(key, None)

    def _estimate_model(self, sig: str) -> bool:
        t0 = time.perf_counter()
        try:
            model = fleet_offsets(self.store.observations(), pipeline_config=self.pipeline_config)
        except Exception as err:  # noqa: BLE001 - logged; tiles keep their own adjustment
            self._model_failed_sig = sig
            self.health.error(f"fleet offset model: {type(err).__name__}: {err}")
            self.get_logger().error(f"fleet offset adjustment failed, tiles keep their own: {traceback.format_exc()}")
            return False
        self.store.put_model(model.to_dict(), sig)
        self._load_model()
        self.health.set("offset_model_drives", len(model.drives))
        self.health.set("last_model_update_s", f"{time.perf_counter() - t0:.3f}")
        return True

    def _estimate(self, key: TileKey, count: int, *, model: bool = False) -> None:
        drives = self.store.drives_covering(key)
        t0 = time.perf_counter()
        obs = None
        try:
            if model:
                segments = map_tile(drives, key, tile_config=self.tile_config, pipeline_config=self.pipeline_config,
                                    offset_model=self._model)
            elif self.use_fleet_model:
                segments, obs = map_tile_observed(
                    drives, key, tile_config=self.tile_config, pipeline_config=self.pipeline_config
                )
            else:
                segments = map_tile(drives, key, tile_config=self.tile_config, pipeline_config=self.pipeline_config)
        except HdmapError as err:
            self._fail(key, count, f"tile {key}: {err}")
            return
        except Exception as err:  # noqa: BLE001 - a bug on one tile must not stop the live map; logged in full
            self._fail(key, count, f"tile {key}: {type(err).__name__}: {err}\n{traceback.format_exc()}")
            return
        est = self.store.put_tile(key, segments, [d.drive_id for d in drives],
                                  model_sig=self._model_sig if model else "", observations=obs)
        if obs is not None:
            self._obs_sig = None
        self._est_count[key] = est.drive_count
        self._failed.pop(key, None)
        self._publish(est)
        self.health.updated()
        self.health.set("last_tile_update_s", f"{time.perf_counter() - t0:.3f}")
        self.health.set("tiles", len(self.store.tiles()))

    def _fail(self, key: TileKey, count: int, text: str) -> None:
        self._failed[key] = count
        self.health.error(text.splitlines()[0])
        self.get_logger().error(f"mapping failed, tile kept as it was: {text}")

    def _publish(self, est: TileEstimate) -> None:
        msg = tile_to_msg(
            est.key, est.segments(), version=est.version, drive_ids=est.drive_ids,
            tile_size_m=self.tile_config.tile_size_m, stamp_ns=time.time_ns(), types=self._tile_types,
        )
        self._seg_pub.publish(msg)
        self.tiles_published += 1

    def is_settled(self) -> bool:
        """No pending drive, no tile due and no stale tile (that did not fail at its current count);
        with the fleet model also: every tile observed, the model current, every tile made with it."""
        if self._queue or self.store.pending():
            return False
        if self.use_fleet_model and self._model_failed_sig != self._observations_sig():
            if any(self._obs_failed.get(k) != self.store.tile_drive_count(k) for k in self.store.stale_observations()):
                return False
            if self._model_sig != self._observations_sig():
                return False
            stale = self._tiles_off_model()
        else:
            stale = self.store.stale_tiles()
        return all(self._failed.get(k) == self.store.tile_drive_count(k) for k in stale)

    def destroy_node(self) -> None:
        self.store.close()
        super().destroy_node()


def main(args=None) -> None:
    run_node(SegmentMapper, args)


if __name__ == "__main__":
    main()
