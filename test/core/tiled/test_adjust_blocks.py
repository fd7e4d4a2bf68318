"""The block-wise offset adjustment (``hdmap_core.tiled.adjust``): the coarse solve undoes the
blocks' gauges, one block is the single solve, and a tiled build with it is the same map on one
process and on two Dask workers."""

from __future__ import annotations

import numpy as np
import pytest
from tiled_fleet import same_map, small_fleet

from hdmap_core.live.tiles import TileConfig
from hdmap_core.pipeline import presets
from hdmap_core.pipeline.adjustment import AdjustConfig, DriveOffset, OffsetModel
from hdmap_core.tiled import tasks
from hdmap_core.tiled.adjust import (
    adjust_blockwise,
    block_of,
    coarse_shifts,
    group_tiles,
    merge_blocks,
    solve_block,
)
from hdmap_core.tiled.build import build_tiled
from hdmap_core.tiled.clips import MemorySource
from hdmap_core.tiled.cluster import SerialRunner


def _model(curves: dict[str, tuple[int, float, list[float]]]) -> OffsetModel:
    cfg = AdjustConfig()
    drives = {d: DriveOffset(k0=k0, bias_m=b, drift_m=np.array(g, dtype=float)) for d, (k0, b, g) in curves.items()}
    return OffsetModel(cfg.knot_spacing_m, cfg.correlation_length_m, cfg.drift_sigma_m, cfg.bias_sigma_m, drives)


def test_blocks_group_tiles_by_floor_division():
    assert block_of((-1, 4), 4) == (-1, 1) and block_of((3, -4), 4) == (0, -1)
    groups = group_tiles([(5, 0), (0, 0), (-1, 0), (1, 1)], 2)
    assert groups == {(-1, 0): [(-1, 0)], (0, 0): [(0, 0), (1, 1)], (2, 0): [(5, 0)]}


def test_coarse_solve_removes_a_block_gauge_and_merge_joins_the_curves():
    true = {"a": (0, 0.2, [0.0, 0.1, 0.2, 0.1, 0.0, -0.1]), "b": (1, -0.3, [0.05, 0.0, -0.05, 0.0, 0.05])}
    gauge = 0.4  # block 1 sees every drive shifted by this (the shift its priors cannot see)

    def part(lo: int, hi: int, shift: float) -> OffsetModel:
        out = {}
        for d, (k0, b, g) in true.items():
            a, z = max(lo, k0), min(hi, k0 + len(g))
            out[d] = (a, b + shift, g[a - k0 : z - k0])
        return _model(out)

    models = {(0, 0): part(0, 4, 0.0), (1, 0): part(3, 9, gauge)}  # they share knot 3
    shifts = coarse_shifts(models, AdjustConfig())
    assert shifts[(1, 0)] - shifts[(0, 0)] == pytest.approx(-gauge, abs=2e-3)  # the priors pull a little
    merged = merge_blocks(models, shifts)
    common = shifts[(0, 0)]
    for d, (k0, b, g) in true.items():
        s = (k0 + np.arange(len(g))) * AdjustConfig().knot_spacing_m
        np.testing.assert_allclose(merged.offset(d, s), b + np.array(g) + common, atol=2e-3)
    # the network's gauge stays near zero: the shifts split the difference
    assert abs(common) < gauge


def test_merge_interpolates_knots_between_blocks():
    models = {(0, 0): _model({"a": (0, 0.0, [1.0, 1.0])}), (2, 0): _model({"a": (4, 0.0, [3.0, 3.0])})}
    merged = merge_blocks(models, {(0, 0): 0.0, (2, 0): 0.0})
    cur = merged.drives["a"]
    assert cur.k0 == 0 and cur.drift_m.size == 6
    np.testing.assert_allclose(cur.bias_m + cur.drift_m, [1.0, 1.0, 5 / 3, 7 / 3, 3.0, 3.0])


@pytest.mark.slow
def test_one_block_is_the_single_solve_and_blocks_stay_close_to_it():
    drives = small_fleet(n=10, length_m=2000.0)
    pc = presets.preset("default")
    src = MemorySource(drives, TileConfig(tile_size_m=384.0, margin_m=96.0, pivot_margin_m=32.0))
    by_tile = {k: tasks.observe(src, pc, k) for k in src.tiles()}
    single = solve_block([o for k in sorted(by_tile) for o in by_tile[k]], pc.adjustment)
    one = merge_blocks({(0, 0): single}, coarse_shifts({(0, 0): single}, pc.adjustment))
    blocks = adjust_blockwise(by_tile, pc.adjustment, block_tiles=2)
    assert blocks.stats["blocks"] > 1
    diff_one, diff_blocks = [], []
    for d in single.drives:
        s = np.linspace(0.0, 1200.0, 25)
        diff_one.append(one.offset(d, s) - single.offset(d, s))
        diff_blocks.append(blocks.offset(d, s) - single.offset(d, s))
    assert np.max(np.abs(np.concatenate(diff_one))) < 1e-9
    assert set(blocks.drives) == set(single.drives)
    assert np.sqrt(np.mean(np.concatenate(diff_blocks) ** 2)) < 0.08  # 0.044 measured (0.077 without the halo)


@pytest.mark.slow
def test_blockwise_tiled_build_is_the_same_map_on_one_process_and_on_two_dask_workers():
    pytest.importorskip("distributed")
    from hdmap_core.tiled.cluster import DaskRunner

    drives = small_fleet()
    src = MemorySource(drives, TileConfig(tile_size_m=384.0, margin_m=96.0))
    pc = presets.preset("default")
    one = build_tiled(src, config=pc, runner=SerialRunner(), block_tiles=2)
    runner = DaskRunner.local(2)
    try:
        two = build_tiled(src, config=pc, runner=runner, block_tiles=2)
    finally:
        runner.close()
    same_map(one.map, two.map)
    assert one.report.observations == two.report.observations > 0
    with pytest.raises(Exception, match="block_tiles"):
        build_tiled(src, config=pc, block_tiles=0)
