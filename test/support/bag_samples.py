"""Small synthetic drives and maps shared by the bag / conversion tests (not a test module)."""

from __future__ import annotations

import numpy as np

from hdmap_core.model import Detection, Drive, FeatureType, HDMap, MapFeature, TopologyNode

T0_NS = 1_700_000_000_123_456_789


def make_drive(drive_id: str = "d000", *, n: int = 50, seed: int = 0, start_ns: int = T0_NS) -> Drive:
    """A gently curving drive along +x with one solid and one dashed detection."""
    rng = np.random.default_rng(seed)
    s = np.arange(n, dtype=np.float64)
    xy = np.stack([s, 0.002 * s**2 + rng.normal(0.0, 0.05, n)], axis=1)
    yaw = np.arctan2(0.004 * s, 1.0)
    stamps = start_ns + np.arange(n, dtype=np.int64) * 100_000_000
    m = max(n // 2, 2)
    dets = (
        Detection(FeatureType.SOLID, xy[:m] + np.array([0.0, 1.8])),
        Detection(FeatureType.DASHED, xy[n - m :] - np.array([0.0, 1.7])),
        Detection(FeatureType.ROAD_BORDER, xy[:3] + np.array([0.0, 5.0])),
    )
    return Drive(drive_id, xy, yaw, stamps, dets, vehicle_id=f"veh-{seed}")


def make_map(*, n_features: int = 4, n_points: int = 30, seed: int = 0) -> HDMap:
    """A map with features of every type, large uint64 ids and a topology chain."""
    rng = np.random.default_rng(seed)
    feats = []
    for i in range(n_features):
        pts = np.stack([np.arange(n_points, dtype=float), np.full(n_points, 3.5 * i)], 1) + rng.normal(
            0, 0.01, (n_points, 2)
        )
        feats.append(
            MapFeature(
                id=2**63 + 17 * i,
                type=FeatureType(1 + i % 3),
                points=pts,
                drive_count=rng.integers(1, 40, n_points),
                lateral_std=rng.uniform(0.05, 0.5, n_points),
                predecessors=(2**64 - 1 - i,) if i else (),
                successors=(i + 1, i + 2),
            )
        )
    nodes = tuple(
        TopologyNode(
            id=10_000 + k,
            position=np.array([2.0 * k, 5.0 + 0.1 * k]),
            heading=0.01 * k,
            width=10.5 + 0.25 * k,
            successors=(10_001 + k,) if k < 9 else (),
            features=tuple(f.id for f in feats[: 1 + k % n_features]),
        )
        for k in range(10)
    )
    return HDMap(features=tuple(feats), topology=nodes, drive_ids=("a", "b", "c"), version=7, stamp_ns=T0_NS + 5)


def assert_drives_equal(a: Drive, b: Drive) -> None:
    assert a.drive_id == b.drive_id and a.vehicle_id == b.vehicle_id and a.frame_id == b.frame_id
    np.testing.assert_array_equal(a.xy, b.xy)
    np.testing.assert_allclose(a.yaw, b.yaw, atol=1e-12)
    np.testing.assert_array_equal(a.stamps_ns, b.stamps_ns)
    assert len(a.detections) == len(b.detections)
    for da, db in zip(a.detections, b.detections):
        assert da.type == db.type
        np.testing.assert_array_equal(da.points, db.points)


def assert_maps_equal(a: HDMap, b: HDMap) -> None:
    assert (a.version, a.frame_id, a.stamp_ns, a.drive_ids) == (b.version, b.frame_id, b.stamp_ns, b.drive_ids)
    assert len(a.features) == len(b.features) and len(a.topology) == len(b.topology)
    for fa, fb in zip(a.features, b.features):
        assert (fa.id, fa.type, fa.predecessors, fa.successors) == (fb.id, fb.type, fb.predecessors, fb.successors)
        np.testing.assert_array_equal(fa.points, fb.points)
        np.testing.assert_array_equal(fa.drive_count, fb.drive_count)
        # float32 in the message
        np.testing.assert_allclose(fa.lateral_std, fb.lateral_std, rtol=1e-6)
    for na, nb in zip(a.topology, b.topology):
        assert (na.id, na.successors, na.features) == (nb.id, nb.successors, nb.features)
        np.testing.assert_array_equal(na.position, nb.position)
        assert na.heading == nb.heading
        np.testing.assert_allclose(na.width, nb.width, rtol=1e-6)


def install_fake_pipeline(monkeypatch, build_map) -> None:
    """Replace ``hdmap_core.pipeline.driver`` and ``overrides`` by stand-ins with the contract's API:
    ``build_map`` as given and a ``config_from(preset, overrides)`` whose config keeps only the
    preset's name and records the overrides (the CLI tests check the glue, not the algorithms)."""
    import sys  # noqa: PLC0415
    import types  # noqa: PLC0415
    from dataclasses import dataclass  # noqa: PLC0415

    import hdmap_core.pipeline  # noqa: PLC0415
    from hdmap_core.pipeline.overrides import parse_override  # noqa: PLC0415 - the real text format of --set

    @dataclass(frozen=True)
    class PipelineConfig:
        name: str
        overrides: tuple = ()
        plausibility: object = None  # bag2map hands it to change detection (None: the form only)

    def config_from(preset: str, overrides: dict) -> PipelineConfig:
        return PipelineConfig(preset + ("+" if overrides else ""), tuple(dict(overrides).items()))

    driver = types.ModuleType("hdmap_core.pipeline.driver")
    driver.build_map = build_map
    overrides = types.ModuleType("hdmap_core.pipeline.overrides")
    overrides.config_from, overrides.parse_override = config_from, parse_override
    for name, mod in (("driver", driver), ("overrides", overrides)):
        monkeypatch.setitem(sys.modules, f"hdmap_core.pipeline.{name}", mod)
        monkeypatch.setattr(hdmap_core.pipeline, name, mod, raising=False)
