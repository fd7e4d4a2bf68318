"""Tests of Sec. III preprocessing and the segment index (preprocess.py)."""

from __future__ import annotations

import numpy as np
import pytest

from hdmap_core.errors import ConfigError
from hdmap_core.geometry import cut_segment_intersections
from hdmap_core.model import Detection, Drive, FeatureType
from hdmap_core.pipeline.preprocess import PreprocessConfig, preprocess

from former_configs import former


def _drive(dets, drive_id="a", length_m=100.0):
    x = np.arange(0.0, length_m + 1e-9, 1.0)
    xy = np.stack([x, np.zeros_like(x)], axis=1)
    return Drive(drive_id, xy, np.zeros(len(x)), np.arange(len(x), dtype=np.int64), tuple(dets))


def test_short_polylines_dropped_and_rdp_thins():
    straight = np.stack([np.linspace(0, 50, 51), np.full(51, 2.0)], axis=1)  # 50 m, collinear
    short = np.array([[10.0, -2.0], [11.0, -2.0], [12.9, -2.0]])  # 2.9 m < 3 m
    just = np.array([[10.0, -4.0], [13.0, -4.0]])  # exactly 3 m: kept
    unknown = Detection(FeatureType.UNKNOWN, straight + [0, 5])
    idx = preprocess(
        [
            _drive(
                [
                    Detection(FeatureType.SOLID, straight),
                    Detection(FeatureType.DASHED, short),
                    Detection(FeatureType.DASHED, just),
                    unknown,
                ]
            )
        ],
        config=former(PreprocessConfig, max_segment_m=100.0),
    )
    assert idx.n_polylines_in == 4
    assert idx.n_polylines_kept == 2
    # The collinear 51-point line is reduced to its two end points: one segment.
    assert idx.n_segments == 2
    assert sorted(idx.seg_type.tolist()) == [FeatureType.SOLID, FeatureType.DASHED]


def test_travelled_distance_and_heading_of_segments():
    line = np.stack([np.linspace(5, 45, 41), np.full(41, 3.0)], axis=1)
    line[:, 1] += 0.3 * np.sin(line[:, 0])  # wiggly, so RDP keeps vertices
    idx = preprocess(
        [_drive([Detection(FeatureType.SOLID, line)])], config=former(PreprocessConfig, rdp_epsilon_m=0.01)
    )
    # Trajectory runs along x from 0 with s = x, so s of a vertex equals its x.
    np.testing.assert_allclose(idx.seg_s_a, idx.seg_a[:, 0], atol=1e-6)
    np.testing.assert_allclose(idx.seg_s_b, idx.seg_b[:, 0], atol=1e-6)
    np.testing.assert_allclose(idx.seg_yaw, 0.0, atol=1e-9)


def test_index_query_equals_brute_force():
    rng = np.random.default_rng(7)
    dets = []
    for _ in range(60):
        start = rng.uniform(-80, 80, 2)
        steps = rng.normal(0, 3.0, (rng.integers(2, 30), 2))
        dets.append(Detection(FeatureType(int(rng.integers(1, 4))), start + np.cumsum(steps, axis=0)))
    drive = _drive(dets, length_m=10)
    cfg = former(PreprocessConfig, min_length_m=0.0, rdp_epsilon_m=1e-9, max_segment_m=7.0, grid_cell_m=4.0)
    idx = preprocess([drive], config=cfg)
    q = 300
    origin = rng.uniform(-90, 90, (q, 2))
    ang = rng.uniform(-np.pi, np.pi, q)
    direction = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    half = rng.uniform(2, 40, q)
    hits = idx.intersect(origin, direction, half)
    got = set(zip(hits.cut.tolist(), np.round(hits.t_m, 9).tolist()))
    # Brute force: every cut against every segment.
    s = idx.n_segments
    qq = np.repeat(np.arange(q), s)
    ss = np.tile(np.arange(s), q)
    hit, t, _ = cut_segment_intersections(origin[qq], direction[qq], half[qq], idx.seg_a[ss], idx.seg_b[ss])
    want = set(zip(qq[hit].tolist(), np.round(t[hit], 9).tolist()))
    assert len(want) > 100
    assert got == want


def test_intersect_in_chunks_of_cuts_is_the_one_call_result(monkeypatch):
    """The crossing test runs in chunks of cuts (bounded memory): same hits, same order."""
    import hdmap_core.pipeline.preprocess as pre  # noqa: PLC0415

    rng = np.random.default_rng(3)
    dets = [
        Detection(
            FeatureType(int(rng.integers(1, 4))), rng.uniform(-60, 60, 2) + np.cumsum(rng.normal(0, 3, (20, 2)), 0)
        )
        for _ in range(80)
    ]
    idx = preprocess([_drive(dets, length_m=10)])
    q = 500
    origin = rng.uniform(-70, 70, (q, 2))
    ang = rng.uniform(-np.pi, np.pi, q)
    direction = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    half = rng.uniform(2, 40, q)
    monkeypatch.setattr(pre, "INTERSECT_CHUNK_CUTS", q)
    one = idx.intersect(origin, direction, half)
    monkeypatch.setattr(pre, "INTERSECT_CHUNK_CUTS", 7)
    chunked = idx.intersect(origin, direction, half)
    assert one.cut.size > 200 and np.unique(one.cut).size > 50  # hits in many chunks
    for name in ("cut", "t_m", "types", "drive", "drive_s_m", "drive_yaw"):
        a, b = getattr(one, name), getattr(chunked, name)
        assert a.dtype == b.dtype and np.array_equal(a, b), name


def test_config_rejects_bad_values():
    with pytest.raises(ConfigError):
        former(PreprocessConfig, min_length_m=-1.0)


def _random_fleet(n_drives: int, seed: int) -> list[Drive]:
    rng = np.random.default_rng(seed)
    drives = []
    for i in range(n_drives):
        dets = []
        for _ in range(int(rng.integers(0, 8))):
            start = rng.uniform(-80, 80, 2)
            steps = rng.normal(0, 2.0, (rng.integers(2, 60), 2))
            dets.append(Detection(FeatureType(int(rng.integers(1, 4))), start + np.cumsum(steps, axis=0)))
        drives.append(_drive(dets, drive_id=f"d{i}", length_m=float(rng.uniform(20, 150))))
    return drives


@pytest.mark.parametrize("workers", [1, 2])
def test_index_is_the_same_in_chunks_and_processes(monkeypatch, workers):
    """Drives are thinned in chunks (and on several processes): every step is per polyline and
    the chunks are joined in drive order, so the index equals the one made in one piece."""
    import hdmap_core.pipeline.preprocess as pre

    drives = _random_fleet(40, seed=3)
    cfg = former(PreprocessConfig, max_segment_m=6.0)
    whole = preprocess(drives, config=cfg)
    monkeypatch.setattr(pre, "_CHUNK_POINTS", 300)
    assert len(pre._drive_chunks(drives)) > 4
    chunked = preprocess(drives, config=cfg, workers=workers)
    for f in ("seg_a", "seg_b", "seg_type", "seg_drive", "seg_s_a", "seg_s_b", "seg_yaw", "cell_keys", "cell_start"):
        np.testing.assert_array_equal(getattr(whole, f), getattr(chunked, f), err_msg=f)
    assert (whole.n_polylines_in, whole.n_polylines_kept, whole.n_points_in, whole.n_points_kept) == (
        chunked.n_polylines_in,
        chunked.n_polylines_kept,
        chunked.n_points_in,
        chunked.n_points_kept,
    )
    for c in range(len(whole.cell_keys)):  # the same segments in every cell (their order is free)
        lo, hi = whole.cell_start[c], whole.cell_start[c + 1]
        assert sorted(whole.cell_segs[lo:hi]) == sorted(chunked.cell_segs[lo:hi])


def test_no_drives_no_segments():
    idx = preprocess([])
    assert idx.n_segments == 0 and len(idx.cell_keys) == 0 and idx.n_polylines_in == 0


def test_clean_drive_drops_short_and_unknown_and_thins_as_preprocess():
    from hdmap_core.pipeline.preprocess import clean_drive

    def line(x0, x1, y):
        n = int(abs(x1 - x0)) + 1
        return np.stack([np.linspace(x0, x1, n), np.full(n, float(y))], axis=1)

    straight = Detection(FeatureType.SOLID, line(0, 50, 1))  # 51 collinear points
    short = Detection(FeatureType.DASHED, line(0, 2, 2))  # 2 m < 3 m
    unknown = Detection(FeatureType.UNKNOWN, line(0, 50, 3))
    bend = Detection(FeatureType.ROAD_BORDER, np.array([[0.0, 0], [10, 0], [20, 5], [30, 10]]))
    d = _drive([straight, short, unknown, bend])
    c = clean_drive(d)
    assert [x.type for x in c.detections] == [FeatureType.SOLID, FeatureType.ROAD_BORDER]
    np.testing.assert_allclose(c.detections[0].points, [[0, 1], [50, 1]])
    np.testing.assert_allclose(c.detections[1].points, [[0, 0], [10, 0], [30, 10]])
    assert len(d.detections) == 4  # input untouched
    assert clean_drive(d, config=PreprocessConfig(min_length_m=1.0)).detections[1].type == FeatureType.DASHED
    # the same segments in the index, cleaned or not
    assert preprocess([c]).n_segments == preprocess([d]).n_segments


@pytest.mark.parametrize("far", [1e9, 1e12, 1e200])
def test_a_far_detection_point_neither_crashes_nor_sizes_the_index(far):
    """Drives normally pass the physical bounds first; the index must still not blow up without them
    (issue 32: 'repeats may not contain negative values', terabytes asked)."""
    from hdmap_core.live.tiles import TileConfig, tiles_of_drive
    from hdmap_core.model import Detection, Drive, FeatureType
    from hdmap_core.pipeline.preprocess import preprocess

    s = np.arange(0.0, 100.0, 1.0)
    xy = np.stack([s, np.zeros_like(s)], axis=1)
    line = xy + [0.0, 1.75]
    bad = line.copy()
    bad[50, 1] = far
    drive = Drive(
        "d",
        xy,
        np.zeros(len(s)),
        np.arange(len(s), dtype=np.int64) * 10**8,
        (Detection(FeatureType.SOLID, line), Detection(FeatureType.DASHED, bad)),
    )
    index = preprocess([drive])
    assert index.n_segments < 10_000 and len(index.cell_segs) < 100_000
    hits = index.intersect(np.array([[30.0, 0.0]]), np.array([[0.0, 1.0]]), np.array([10.0]))
    assert sorted(hits.types.tolist()) == [FeatureType.SOLID, FeatureType.DASHED]  # the good parts stay indexed
    far_pose = Drive("p", np.where(np.arange(len(s))[:, None] == 50, [50.0, far], xy), drive.yaw, drive.stamps_ns)
    assert len(tiles_of_drive(far_pose, config=TileConfig())) < 100_000
