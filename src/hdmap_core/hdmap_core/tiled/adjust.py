"""The network-wide offset adjustment block-wise over tiles, with a global coarse solve.

``pipeline.adjustment.adjust_offsets`` solves one sparse system over every drive's knots: its
input (the step observations of all tiles) and its unknowns grow with the fleet's drive-km, so in
one process it is the limit of a country-sized build (docs/scale.md). Here the tiles are grouped
into square blocks of ``block_tiles`` x ``block_tiles`` tiles and:

1. **Block solves** (one task per block, independent): ``adjust_offsets`` over the observations of
   the block's tiles and of a halo of ``halo_tiles`` tiles around them only (association,
   lane-shift search, coarse rejection and robust IRLS, all as in the single solve). A drive
   crossing several blocks gets one curve per block, on the same global knot grid
   (``k * knot_spacing_m`` of its travelled distance).
2. **Coarse solve** (one small task): each block's solution carries its own gauge, the shift
   common to all its drives that the data cannot see and that the zero-mean bias prior sets within
   the block. One unknown shift ``c_b`` per block ties the blocks together: every drive seen by two
   blocks whose knot ranges share knots gives ``c_b - c_a = o_a(k) - o_b(k)`` at those knots
   (weighted least squares), and the single solve's gauge prior, ``bias_d ~ N(0, bias_sigma^2)``
   once per drive on its merged bias (the mean over its blocks of its bias there plus ``c_b``),
   puts the network's gauge where the single solve puts it.
3. **Merge**: every drive's curve is the mean, at each knot, of its shifted block curves (knots no
   block covers interpolated between those that are), split into a bias (the mean of the blocks'
   shifted biases) and a drift.

Each block needs only its tiles' observations (on a worker), the coarse solve only the blocks'
curves at their shared knots (about the size of the final offset model). Deterministic for the
same observations: blocks in key order, drives in sorted order. Accuracy against the single
solve: docs/scale.md. With ``block_tiles`` so large that one block holds every tile the result is
the single solve's.

API (shared with other callers, e.g. an incremental live adjustment):

- ``block_of(key, block_tiles)``: the block of a tile.
- ``group_tiles(keys, block_tiles, halo_tiles)``: {block: its tiles and its halo's}, sorted.
- ``solve_block(observations, config)``: one block's ``OffsetModel``.
- ``coarse_shifts(models, config)``: {block: shift c_b [m]} from the block models.
- ``merge_blocks(models, shifts)``: the fleet's ``OffsetModel``.
- ``adjust_blockwise(observations_by_tile, config, block_tiles, halo_tiles)``: all three, here.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from hdmap_core.pipeline.adjustment import AdjustConfig, DriveOffset, OffsetModel, adjust_offsets

__all__ = [
    "BlockKey",
    "HALO_TILES",
    "block_of",
    "group_tiles",
    "solve_block",
    "coarse_shifts",
    "merge_blocks",
    "adjust_blockwise",
]

BlockKey = tuple[int, int]
#: each block solves its tiles and those within this many tiles around them: neighbouring blocks
#: then fit the same observations along their border, so a drive's curves of two blocks share
#: knots fitted from the same data (the coarse solve's links), and a block's border knots are
#: not extrapolated from one side
HALO_TILES = 1
#: sigma of the difference of two blocks' curves of one drive at one shared knot [m] (each is
#: estimated from one side's data only; about the drift's change over a knot)
LINK_SIGMA_M = 0.05


def block_of(key: Sequence[int], block_tiles: int) -> BlockKey:
    """The block of tile ``key``: tiles grouped ``block_tiles`` x ``block_tiles``."""
    return (int(key[0]) // block_tiles, int(key[1]) // block_tiles)


def group_tiles(
    keys: Iterable[Sequence[int]], block_tiles: int, halo_tiles: int = 0
) -> dict[BlockKey, list[tuple[int, int]]]:
    """{block: its tiles and those within ``halo_tiles`` tiles of it}, blocks and tiles sorted."""
    tiles = sorted({(int(k[0]), int(k[1])) for k in keys})
    out: dict[BlockKey, list[tuple[int, int]]] = {}
    for key in tiles:
        out.setdefault(block_of(key, block_tiles), [])
    for key in tiles:
        near = {
            block_of((key[0] + dx, key[1] + dy), block_tiles)
            for dx in range(-halo_tiles, halo_tiles + 1)
            for dy in range(-halo_tiles, halo_tiles + 1)
        }
        for b in sorted(near):
            if b in out:
                out[b].append(key)
    return dict(sorted(out.items()))


def solve_block(observations: Sequence[Any], config: AdjustConfig) -> OffsetModel:
    """The adjustment of one block's observations (no posterior std: unused by the mapping)."""
    return adjust_offsets(list(observations), config=replace(config, compute_std=False))


def _totals(cur: DriveOffset) -> np.ndarray:
    """A curve's offset at its knots (bias + drift; the bias alone without drift)."""
    return cur.bias_m + cur.drift_m if cur.drift_m.size else np.array([cur.bias_m])


def coarse_shifts(models: Mapping[BlockKey, OffsetModel], config: AdjustConfig) -> dict[BlockKey, float]:
    """One shift per block (added to all its curves) making the blocks agree (module docstring, 2.)."""
    blocks = sorted(models)
    col = {b: i for i, b in enumerate(blocks)}
    n = len(blocks)
    # per drive, the blocks that fitted it
    seen: dict[str, list[BlockKey]] = {}
    for b in blocks:
        for d in models[b].drives:
            seen.setdefault(d, []).append(b)
    rows_i: list[int] = []
    rows_j: list[int] = []
    delta: list[float] = []
    weight: list[float] = []
    for d in sorted(seen):
        bs = seen[d]
        for x in range(len(bs)):
            for y in range(x + 1, len(bs)):
                ca, cb = models[bs[x]].drives[d], models[bs[y]].drives[d]
                ta, tb = _totals(ca), _totals(cb)
                if ca.drift_m.size == 0 or cb.drift_m.size == 0:  # constant offsets: the biases
                    shared_a, shared_b = ta[:1], tb[:1]
                else:
                    lo, hi = max(ca.k0, cb.k0), min(ca.k0 + ca.drift_m.size, cb.k0 + cb.drift_m.size)
                    if hi <= lo:
                        continue  # the drive left the road between the blocks: no shared knot
                    shared_a, shared_b = ta[lo - ca.k0 : hi - ca.k0], tb[lo - cb.k0 : hi - cb.k0]
                rows_i.append(col[bs[x]])
                rows_j.append(col[bs[y]])
                delta.append(float(np.mean(shared_a - shared_b)))  # c_y - c_x
                weight.append(shared_a.size / LINK_SIGMA_M**2)
    # the single solve's gauge prior, bias_d ~ N(0, bias_sigma^2) once per drive: here on each
    # drive's merged bias, the mean over its blocks of (its bias there + c_b)
    h = sp.diags(np.full(n, 1e-9)).tolil()  # a block no drive links stays at 0
    rhs = np.zeros(n)
    prior = config.bias_sigma_m**-2
    for d in sorted(seen):
        idx = [col[b] for b in seen[d]]
        m = len(idx)
        mean_bias = float(np.mean([models[b].drives[d].bias_m for b in seen[d]]))
        for i in idx:
            rhs[i] -= prior * mean_bias / m
            for j in idx:
                h[i, j] += prior / m**2
    for i, j, dl, w in zip(rows_i, rows_j, delta, weight, strict=True):
        h[i, i] += w
        h[j, j] += w
        h[i, j] -= w
        h[j, i] -= w
        rhs[j] += w * dl
        rhs[i] -= w * dl
    c = spla.spsolve(h.tocsc(), rhs) if n > 1 else np.zeros(n)
    return {b: float(v) for b, v in zip(blocks, np.atleast_1d(c), strict=True)}


def merge_blocks(models: Mapping[BlockKey, OffsetModel], shifts: Mapping[BlockKey, float]) -> OffsetModel:
    """Every drive's curve from its shifted block curves (module docstring, 3.)."""
    blocks = sorted(models)
    if not blocks:
        cfg = AdjustConfig()
        return OffsetModel(cfg.knot_spacing_m, cfg.correlation_length_m, cfg.drift_sigma_m, cfg.bias_sigma_m)
    first = models[blocks[0]]
    parts: dict[str, list[tuple[DriveOffset, float]]] = {}
    for b in blocks:
        for d, cur in models[b].drives.items():
            parts.setdefault(d, []).append((cur, shifts.get(b, 0.0)))
    out: dict[str, DriveOffset] = {}
    for d in sorted(parts):
        curves = parts[d]
        if all(c.drift_m.size == 0 for c, _ in curves):
            bias = float(np.mean([c.bias_m + s for c, s in curves]))
            out[d] = _offset(0, bias, np.zeros(0))
            continue
        curves = [(c, s) for c, s in curves if c.drift_m.size]
        k0 = min(c.k0 for c, _ in curves)
        k1 = max(c.k0 + c.drift_m.size for c, _ in curves)
        total = np.zeros(k1 - k0)
        count = np.zeros(k1 - k0)
        for c, s in curves:
            sl = slice(c.k0 - k0, c.k0 - k0 + c.drift_m.size)
            total[sl] += _totals(c) + s
            count[sl] += 1
        have = count > 0
        knots = np.arange(k1 - k0)
        value = np.interp(knots, knots[have], total[have] / count[have])
        # the bias: the blocks' own (where the drift decays to outside the knots, as in each block)
        bias = float(np.mean([c.bias_m + s for c, s in curves]))
        out[d] = _offset(k0, bias, value - bias)
    stats = {"blocks": len(blocks), "max_shift_m": max((abs(float(v)) for v in shifts.values()), default=0.0)}
    return replace(first, drives=out, stats=stats)


def _offset(k0: int, bias: float, drift: np.ndarray) -> DriveOffset:
    nk = drift.size
    nan = np.full(nk, np.nan)
    return DriveOffset(
        k0=int(k0),
        bias_m=bias,
        drift_m=drift,
        var_bias=float("nan"),
        cov_bias_drift=nan,
        var_drift=nan.copy(),
        cov_drift_next=np.full(max(nk - 1, 0), np.nan),
    )


def adjust_blockwise(
    observations_by_tile: Mapping[tuple[int, int], Sequence[Any]],
    config: AdjustConfig,
    block_tiles: int,
    halo_tiles: int = HALO_TILES,
) -> OffsetModel:
    """Block solves, coarse solve and merge in this process (``tiled.build`` runs them as tasks)."""
    groups = group_tiles(observations_by_tile, block_tiles, halo_tiles)
    models = {b: solve_block([o for k in keys for o in observations_by_tile[k]], config) for b, keys in groups.items()}
    return merge_blocks(models, coarse_shifts(models, config))
