"""QoS profiles of the node suite, built once here (one comment per policy).

Topic                  | profile        | why
---------------------- | -------------- | -----------------------------------------------------------
/fleet/drives          | DRIVES         | a burst of large drive messages must not be dropped
/hdmap/drives_accepted | ACCEPTED       | same, and a restarted mapper gets recent drives again
/hdmap/segments        | SEGMENTS       | a restarted stitcher gets the recent tile estimates again
/hdmap/segment_batches | BATCHES        | same, for the estimates one job made together (a few MB each)
/hdmap/map             | LATCHED        | a late subscriber gets the latest map at once
/hdmap/markers         | LATCHED        | RViz / Foxglove opened later still show the map
/hdmap/changes         | CHANGES        | every road change ever confirmed, for a late subscriber too
/fleet/origin          | LATCHED        | published once; late joiners need it (also subscribed ORIGIN_LIVE)
/hdmap/drive_acks      | ACKS           | one small message per acknowledged drive
/diagnostics           | DIAGNOSTICS    | the ROS convention (diagnostic_aggregator subscribes so)
"""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

__all__ = [
    "DRIVES",
    "ACCEPTED",
    "SEGMENTS",
    "BATCHES",
    "LATCHED",
    "CHANGES",
    "ORIGIN_LIVE",
    "ACKS",
    "DIAGNOSTICS",
    "replay",
]

# /fleet/drives: as the bag player and a fleet gateway publish.
DRIVES = QoSProfile(
    # KEEP_ALL: RELIABLE with KEEP_LAST 10 lost half of a burst of 20 large messages here
    # (shared notes ros-wheels.md); KEEP_ALL makes the writer block instead of overwrite.
    history=HistoryPolicy.KEEP_ALL,
    # RELIABLE: every drive counts; a lost drive is a lost piece of map.
    reliability=ReliabilityPolicy.RELIABLE,
    # VOLATILE: a mapper that starts late should not get a whole day of drives replayed at once;
    # `ros2 bag play` offers VOLATILE too, so it stays compatible.
    durability=DurabilityPolicy.VOLATILE,
)


def replay(depth: int) -> QoSProfile:
    """RELIABLE + TRANSIENT_LOCAL with the last ``depth`` messages kept for late (re)joiners."""
    return QoSProfile(
        # KEEP_LAST depth: bounded memory in the publisher; the depth is a node parameter.
        history=HistoryPolicy.KEEP_LAST,
        depth=max(1, int(depth)),
        # RELIABLE: the consumer must see every update.
        reliability=ReliabilityPolicy.RELIABLE,
        # TRANSIENT_LOCAL: a consumer restarted after a crash receives the kept messages again;
        # consumers are idempotent (drive ids, tile versions), so a repeat is harmless.
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


# Default profiles for the internal topics (the nodes build theirs from a depth parameter).
ACCEPTED = replay(100)
SEGMENTS = replay(1000)
# RULE memory: a batch holds every tile one job made (a region: all of them, a fused 10 km drive
# ~100 tiles, a few MB), so only the last few are kept for a restarting stitcher; the mapper's
# republish_on_start sends every stored estimate again.
BATCHES = replay(8)

# /hdmap/map, /hdmap/markers, /fleet/origin.
LATCHED = QoSProfile(
    # KEEP_LAST 1: only the newest map matters.
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    # RELIABLE: maps are large and must arrive whole.
    reliability=ReliabilityPolicy.RELIABLE,
    # TRANSIENT_LOCAL: "latched": a subscriber joining later gets the latest map at once.
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)

# /hdmap/changes: one MapChange per road change, the whole history latched.
CHANGES = QoSProfile(
    # KEEP_LAST 1000: every change, not only the newest (a late subscriber reads the history).
    history=HistoryPolicy.KEEP_LAST,
    depth=1000,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)

# /fleet/origin as the map publisher subscribes it, besides LATCHED (which gets the fix a
# TRANSIENT_LOCAL publisher sent before we joined): a second, VOLATILE subscription, which also
# matches a VOLATILE publisher (`ros2 bag play` of a bag without recorded QoS); LATCHED alone is
# incompatible with one and the origin never arrived. (BEST_AVAILABLE durability is decided once,
# when the subscription is made, from the publishers seen then: none, usually.)
ORIGIN_LIVE = QoSProfile(
    # KEEP_LAST 1, RELIABLE: one fix, needed whole.
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    # VOLATILE: compatible with every publisher.
    durability=DurabilityPolicy.VOLATILE,
)

# /hdmap/drive_acks.
ACKS = QoSProfile(
    # KEEP_ALL: a sender waiting for acks must see each one.
    history=HistoryPolicy.KEEP_ALL,
    # RELIABLE: an ack that is lost makes the sender resend (harmless, but wasteful).
    reliability=ReliabilityPolicy.RELIABLE,
    # VOLATILE: acks are about the present.
    durability=DurabilityPolicy.VOLATILE,
)

# /diagnostics.
DIAGNOSTICS = QoSProfile(
    # KEEP_LAST 10: diagnostics are periodic; old ones are superseded.
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    # RELIABLE, VOLATILE: what diagnostic_updater uses (the default profile).
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
