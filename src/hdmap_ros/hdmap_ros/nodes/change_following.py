"""map_stitcher's road-change following, on the settled map (docs/updates.md, "Live").

Once the map has settled (the mapper settled, every estimate stitched), the stitcher reads every
drive from the mapper's store (``drive_db_path``, read-only) and follows the changes of the road
with ``bag2map``'s code (``live.changes.follow_loaded``: ``updates.follow.follow_map`` on the
settled map) in a process of its own: the changed places are rebuilt from the drives after the
change, aligned and spliced in with their topology, their old pieces retired. Each change not yet
in the history is published on ``hdmap/changes`` (hdmap_msgs/MapChange) and stored with the
followed map in one transaction; the map's version grows by the number of new changes. A restart
publishes the stored history again (same ids) and finds the same changes, which are not new.

``ChangeFollowing`` is a part of ``MapStitcher`` (a mixin): it uses the stitcher's store, map,
health and publishing; the stitcher calls ``_follow`` on each work turn.
"""

from __future__ import annotations

import functools
import json
import time
import traceback
from concurrent.futures import BrokenExecutor, Executor, Future
from dataclasses import replace

from hdmap_core.errors import ConfigError, HdmapError
from hdmap_core.live.changes import (
    LiveChange,
    change_from_dict,
    dumps,
    follow_loaded,
    live_changes,
    new_changes,
    warm_up,
)
from hdmap_core.model import HDMap
from hdmap_core.parallel import available_cpus, spawn_pool
from hdmap_core.pipeline.presets import FOLLOWS_CHANGES
from hdmap_ros.convert.messages import change_to_msg, rclpy_change_class
from hdmap_ros.nodes import qos
from hdmap_ros.nodes._common import declare, state_path
from hdmap_ros.persistence.store import read_drives

__all__ = ["ChangeFollowing", "CHANGES_TOPIC", "CHANGES_QOS", "FOLLOW_NICE"]

CHANGES_TOPIC = "hdmap/changes"  # relative: a namespace (-r __ns:=/ns2) moves every topic
# RULE: the change following is background work (it reads every drive and rebuilds on every CPU
# for seconds once the map settled); its process runs this much nicer, so that a drive arriving
# meanwhile (the fast path: mapper and stitcher in their own processes) is not slowed by it
FOLLOW_NICE = 10
CHANGES_QOS = qos.CHANGES  # the whole history latched (a restart publishes it again)


class ChangeFollowing:
    """The road-change following of ``MapStitcher`` (module docstring)."""

    def _declare_change_following(self) -> None:
        """Its parameters (declared in the stitcher's order: its YAML lists them so)."""
        follow = declare(
            self,
            "follow_changes",
            "auto",
            "Follow road changes once the map settled: on, off, or auto (as bag2map: on with the default preset).",
        )
        if follow not in ("auto", "on", "off"):
            raise ConfigError(f"follow_changes: {follow!r} is not one of auto, on, off")
        preset_name = self.get_parameter("preset").value
        self.follow_changes = follow == "on" or (follow == "auto" and FOLLOWS_CHANGES.get(preset_name, False))
        drive_db = declare(
            self,
            "drive_db_path",
            "",
            "The mapper's SQLite drive store, read for change detection ('' = $ROS_HOME/hdmap/segment_mapper.db).",
        )
        self.drive_db = state_path(drive_db, "segment_mapper.db")
        self.tile_size_m = declare(
            self,
            "tile_size_m",
            256.0,
            "Edge of a map tile [m], as the mapper's (names the tiles of a change on hdmap/changes).",
            lo=32.0,
            hi=4096.0,
        )

    def _init_change_following(self, sig: str) -> None:
        """The stored history published again, the follow's state from the store (``sig``: the
        tile versions the stored map was made from)."""
        self._change_cls = rclpy_change_class()
        self._changes_pub = self.create_publisher(self._change_cls, CHANGES_TOPIC, CHANGES_QOS)
        self.history: dict[int, LiveChange] = {}
        for doc in self.store.changes():
            c = change_from_dict(json.loads(doc))
            self.history[c.id] = c
        self.changes_new = 0  # changes first confirmed by this process
        self._follow_executor: Executor | None = None
        self._follow_fut: tuple[str, Future] | None = None  # (map signature, the follow in work)
        self._follow_t0 = 0.0
        self._follow_workers = available_cpus()
        self._followed_sig = self.store.get_meta("followed_sig", "") or ""
        # the consensus map (of every drive) the changes are followed on: the stored map unless
        # it is already the followed one
        self._consensus = self.map if self._followed_sig != sig else None
        for c in self.history.values():  # latched: the history again, same ids (not new)
            self._changes_pub.publish(change_to_msg(c, cls=self._change_cls, types=self._types))
        self._changes_health()

    def changes_followed(self) -> bool:
        """The current map follows the road changes of every stored drive (or following is off)."""
        return not self.follow_changes or self.map is None or self._followed_sig == self._map_sig

    def _follow(self) -> None:
        """Follow the road changes on the settled map (module docstring)."""
        if self.changes_followed() or not self._mapper_status.settled or not self.is_settled():
            return
        if self.store.version_total() < self._mapper_status.tile_versions:
            return  # RULE: estimates the settled mapper made are on their way: this is not its map yet
        sig = self._map_sig
        consensus = self._consensus
        if consensus is None:  # the stored map is the followed one of an older signature: rebuild
            self._first_dirty = time.monotonic()
            return
        fut = self._follow_fut
        if fut is not None and fut[0] != sig:  # the map changed while its changes were followed
            fut[1].cancel()
            self._follow_fut = fut = None
        if fut is None:
            self._follow_t0 = time.perf_counter()
            load = functools.partial(read_drives, self.drive_db)
            job = self._follow_pool().submit(
                follow_loaded, consensus, load, pipeline_config=self.pipeline_config, workers=self._follow_workers
            )
            self._follow_fut = (sig, job)
            return
        if not fut[1].done():
            return
        self._follow_fut = None
        t0 = self._follow_t0
        try:
            result = fut[1].result()
        except BrokenExecutor as err:  # the process died (killed, out of memory): a new one next time
            self._follow_executor = None
            self._follow_failed(sig, f"{type(err).__name__}: {err}")
            return
        except HdmapError as err:
            self._follow_failed(sig, str(err))
            return
        except Exception as err:  # noqa: BLE001 - a bug must not stop the live map; logged in full
            self._follow_failed(sig, f"{type(err).__name__}: {err}\n{''.join(traceback.format_exception(err))}")
            return
        fresh = new_changes(self.history, result.changes)
        if not result.changes:  # nothing changed: the consensus map is the map
            self.store.set_meta("followed_sig", sig)
            self._followed_sig = sig
        else:
            version = self.map.version + max(1, len(fresh))
            new = replace(result.map, version=version, stamp_ns=time.time_ns())
            announced = [
                c
                for c in live_changes(
                    result, tile_size_m=self.tile_size_m, map_version=version, confirmed_ns=new.stamp_ns
                )
                if c.id not in self.history
            ]
            self._put_followed(new, sig, announced)
            for c in announced:
                self.history[c.id] = c
                self.changes_new += 1
                self._changes_pub.publish(change_to_msg(c, cls=self._change_cls, types=self._types))
                self.get_logger().info(
                    f"road change {c.id}: {', '.join(c.kinds)} at {c.time_ns} ns, {len(c.places)} place(s), "
                    f"{len(c.drive_ids)} drive(s) in evidence, confidence {c.confidence:.3f}, map version {version}"
                )
            self._map_health()
        self._changes_health()
        self.health.set("changes_in_map", len(result.changes))
        seconds = time.perf_counter() - t0
        self.health.set("last_follow_s", f"{seconds:.3f}")
        self.get_logger().info(
            f"road changes followed on map version {self.map.version} in {seconds:.1f} s: "
            f"{len(result.changes)} in the map, {len(fresh)} new, {len(self.history)} in the history"
        )

    def _put_followed(self, new: HDMap, sig: str, announced: list[LiveChange]) -> None:
        """Store, take and publish ``new``, the map of the tiles ``sig`` with road changes followed."""
        self.store.put_followed(new, sig, [(c.id, c.time_ns, dumps(c)) for c in announced])
        self.map = new
        self._mg = None  # no map graph made this map: no fast update on it (the rebuild, then the follow)
        self._followed_sig = sig
        self._publish()

    def _follow_pool(self) -> Executor:
        """The process the change following runs in (``live.changes.follow_loaded``: it reads the
        drives and compares them on every CPU, as ``bag2map`` does, away from this process's
        executor; forks only from there, never from this process with its native threads). Made
        when the first tile estimates come (a stitcher that never gets one never starts it)."""
        if self._follow_executor is None:
            self._follow_executor = spawn_pool(nice=FOLLOW_NICE)
            self._follow_executor.submit(warm_up)
        return self._follow_executor

    def _follow_failed(self, sig: str, text: str) -> None:
        self._followed_sig = sig  # not again on the same inputs
        self.health.error(text.splitlines()[0])
        self.get_logger().error(f"following road changes failed, the map of every drive kept: {text}")

    def _changes_health(self) -> None:
        """The history's size and the changes this process confirmed, on /diagnostics."""
        self.health.set("changes_known", len(self.history))
        self.health.set("changes_new", self.changes_new)

    def _close_change_following(self) -> None:
        if self._follow_executor is not None:
            self._follow_executor.shutdown(wait=False, cancel_futures=True)
