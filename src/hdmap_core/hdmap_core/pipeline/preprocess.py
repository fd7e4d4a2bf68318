"""Sec. III: input preprocessing and the spatial index over detection segments.

Detection polylines shorter than ``min_length_m`` (paper: 3 m) are dropped as likely
misdetections, the rest thinned with Ramer-Douglas-Peucker. All remaining segments of all drives
go into one flat array set (``DetectionIndex``) with a uniform grid hash over their bounding boxes,
which answers "which segments cross these cut lines" for many cut lines at once. (The paper uses
an axis-aligned bounding-box tree; any index over segments that answers cut-line queries will do,
and a numpy grid is faster here.)

Every segment end point also carries the travelled distance of its own drive there (the point
projected onto that drive's trajectory) and the drive's heading, which the sampling stage needs for
the opposite-direction filter and the processed-stretch keys.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import ClassVar

import numpy as np
from scipy.spatial import cKDTree

from hdmap_core.checks import check_range
from hdmap_core.geometry import (
    arc_length,
    interp_angle,
    rdp_mask_many,
    split_long_segments,
)
from hdmap_core.model import Detection, Drive, FeatureType
from hdmap_core.parallel import map_balanced

__all__ = ["trajectory_index", "PreprocessConfig", "DetectionIndex", "CutHits", "preprocess", "clean_drive"]


@dataclass(frozen=True)
class PreprocessConfig:
    """Preprocessing options.

    Attributes:
        min_length_m: detection polylines shorter than this are dropped (paper: 3 m).
        rdp_epsilon_m: Ramer-Douglas-Peucker tolerance [m] (paper: unspecified; well below the
            measurement noise so the shape is kept).
    """

    min_length_m: float = 3.0
    rdp_epsilon_m: float = 0.05

    #: longer segments are split, which keeps grid cells per segment small [m]
    max_segment_m: ClassVar[float] = 10.0
    #: cell size of the spatial hash [m]
    grid_cell_m: ClassVar[float] = 5.0

    def __post_init__(self) -> None:
        check_range(self, ("rdp_epsilon_m",), low=0.0, low_open=True)
        check_range(self, ("min_length_m",), low=0.0)


#: cut lines intersected per call of the vectorised crossing test (``DetectionIndex.intersect``):
#: its candidate pairs, and so its memory, grow with the cuts times the drives per grid cell
INTERSECT_CHUNK_CUTS = 64


@dataclass(frozen=True)
class CutHits:
    """Intersections of cut lines with detection segments (one row per hit).

    Attributes:
        cut: (H,) index of the cut line.
        t_m: (H,) position along the cut line (+ = along cut_dir) [m].
        types: (H,) FeatureType codes.
        drive: (H,) drive index into ``DetectionIndex.drive_ids``.
        drive_s_m: (H,) travelled distance of that drive at the hit [m].
        drive_yaw: (H,) that drive's heading at the hit [rad].
    """

    cut: np.ndarray
    t_m: np.ndarray
    types: np.ndarray
    drive: np.ndarray
    drive_s_m: np.ndarray
    drive_yaw: np.ndarray


@dataclass(frozen=True)
class DetectionIndex:
    """All detection segments of all drives, flat, plus a uniform grid hash over them.

    Attributes:
        drive_ids: the drives, in input order (drive index = position).
        seg_a, seg_b: (S, 2) segment end points [m].
        seg_type: (S,) FeatureType codes.
        seg_drive: (S,) drive index.
        seg_s_a, seg_s_b: (S,) travelled distance of the own drive at the end points [m].
        seg_yaw: (S,) heading of the own drive at the segment [rad].
        cell_m: grid cell size [m].
        cell_keys: (C,) sorted keys of the non-empty cells.
        cell_start: (C + 1,) CSR offsets into ``cell_segs``.
        cell_segs: segment ids per cell.
        n_polylines_in, n_polylines_kept: counted by preprocessing.
        n_points_in, n_points_kept: vertices before / after RDP.
    """

    drive_ids: tuple[str, ...]
    seg_a: np.ndarray
    seg_b: np.ndarray
    seg_type: np.ndarray
    seg_drive: np.ndarray
    seg_s_a: np.ndarray
    seg_s_b: np.ndarray
    seg_yaw: np.ndarray
    cell_m: float
    cell_keys: np.ndarray
    cell_start: np.ndarray
    cell_segs: np.ndarray
    n_polylines_in: int = 0
    n_polylines_kept: int = 0
    n_points_in: int = 0
    n_points_kept: int = 0

    @property
    def n_segments(self) -> int:
        return len(self.seg_type)

    def candidates(
        self, origin: np.ndarray, direction: np.ndarray, half_len_m: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Candidate (cut, segment) pairs: every segment that may cross a cut line.

        Exact superset: the cut line is sampled every cell/2, and segments were inserted into all
        cells of their bounding box grown by cell/4, so a crossing point is always within reach of
        a sample point's cell. Pairs may repeat.

        Args:
            origin: (Q, 2) cut midpoints [m]; direction: (Q, 2) unit vectors; half_len_m: (Q,).

        Returns:
            (cut (P,), seg (P,)) index arrays.
        """
        q = len(origin)
        if q == 0 or len(self.cell_keys) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        delta = 0.5 * self.cell_m
        n_pts = np.floor(2.0 * half_len_m / delta).astype(np.int64) + 2
        owner = np.repeat(np.arange(q), n_pts)
        first = np.concatenate([[0], np.cumsum(n_pts)[:-1]])
        k = np.arange(len(owner)) - first[owner]
        t = np.minimum(-half_len_m[owner] + k * delta, half_len_m[owner])
        p = origin[owner] + t[:, None] * direction[owner]
        keys = _cell_key(
            np.floor(p[:, 0] / self.cell_m).astype(np.int64), np.floor(p[:, 1] / self.cell_m).astype(np.int64)
        )
        # Distinct (cut, cell) pairs; sample points of one cut are in order, so neighbours suffice
        # for most repeats, and a full sort is not needed for correctness (pairs may repeat).
        dup = np.zeros(len(keys), dtype=bool)
        dup[1:] = (keys[1:] == keys[:-1]) & (owner[1:] == owner[:-1])
        owner, keys = owner[~dup], keys[~dup]
        pos = np.searchsorted(self.cell_keys, keys)
        pos = np.minimum(pos, len(self.cell_keys) - 1)
        found = self.cell_keys[pos] == keys
        owner, pos = owner[found], pos[found]
        cnt = self.cell_start[pos + 1] - self.cell_start[pos]
        cut = np.repeat(owner, cnt)
        off = np.repeat(self.cell_start[pos] - np.concatenate([[0], np.cumsum(cnt)[:-1]]), cnt)
        seg = self.cell_segs[np.arange(len(cut)) + off]
        return cut, seg

    def intersect(self, origin: np.ndarray, direction: np.ndarray, half_len_m: np.ndarray) -> CutHits:
        """All crossings of the given cut lines with detection segments (each crossing once).

        Args:
            origin: (Q, 2) cut midpoints [m]; direction: (Q, 2) unit vectors; half_len_m: (Q,) [m].
        """
        origin = np.asarray(origin, dtype=float).reshape(-1, 2)
        direction = np.asarray(direction, dtype=float).reshape(-1, 2)
        half_len_m = np.broadcast_to(np.asarray(half_len_m, dtype=float), (len(origin),))
        q = len(origin)
        if q <= INTERSECT_CHUNK_CUTS:
            return self._intersect(origin, direction, half_len_m)
        # RULE bounded memory: the candidate pairs of all cuts at once grow with the drives per
        # cell (a dense tile of 745 drives: 0.5 GB in one call). Chunks of consecutive cuts give
        # the same hits in the same (cut, segment) order: every step below is per pair or per cut.
        parts = []
        for c0 in range(0, q, INTERSECT_CHUNK_CUTS):
            sl = slice(c0, min(c0 + INTERSECT_CHUNK_CUTS, q))
            h = self._intersect(origin[sl], direction[sl], half_len_m[sl])
            parts.append(replace(h, cut=h.cut + c0))
        return CutHits(*(np.concatenate([getattr(h, f.name) for h in parts]) for f in fields(CutHits)))

    def _intersect(self, origin: np.ndarray, direction: np.ndarray, half_len_m: np.ndarray) -> CutHits:
        cut, seg = self.candidates(origin, direction, half_len_m)
        # Signed distance of both end points from the cut line (left of its direction > 0): a
        # segment crosses where they differ in sign; an end point on the line counts for the
        # segment starting there (u in [0, 1), as ``cut_segment_intersections``). Most candidate
        # pairs (a segment in a cell the cut passes through) fail this test, so the crossing
        # itself is computed for the few that pass.
        c0 = direction[:, 0] * origin[:, 1] - direction[:, 1] * origin[:, 0]
        dx, dy, cc = direction[cut, 0], direction[cut, 1], c0[cut]
        sa = dx * self.seg_a[seg, 1] - dy * self.seg_a[seg, 0] - cc
        sb = dx * self.seg_b[seg, 1] - dy * self.seg_b[seg, 0] - cc
        cross = ((sa <= 0.0) & (sb > 0.0)) | ((sa >= 0.0) & (sb < 0.0))
        cut, seg, sa, sb = cut[cross], seg[cross], sa[cross], sb[cross]
        u = sa / (sa - sb)
        a = self.seg_a[seg]
        p = a + u[:, None] * (self.seg_b[seg] - a) - origin[cut]
        t = p[:, 0] * direction[cut, 0] + p[:, 1] * direction[cut, 1]
        hit = np.abs(t) <= half_len_m[cut]
        cut, seg, t, u = cut[hit], seg[hit], t[hit], u[hit]
        if len(cut):
            # A segment spans several cells: keep one hit per (cut, segment).
            _, first = np.unique(cut * np.int64(self.n_segments + 1) + seg, return_index=True)
            cut, seg, t, u = cut[first], seg[first], t[first], u[first]
        s = self.seg_s_a[seg] + u * (self.seg_s_b[seg] - self.seg_s_a[seg])
        return CutHits(
            cut=cut,
            t_m=t,
            types=self.seg_type[seg],
            drive=self.seg_drive[seg],
            drive_s_m=s,
            drive_yaw=self.seg_yaw[seg],
        )


# Grid keys hold 2^31 cells either side of the origin per axis. A segment is indexed in at most
# _MAX_CELLS_PER_SEGMENT cells (a 320 m square at 5 m cells; see _grid_pairs): detection segments
# are split to max_segment_m, trajectory steps of plausible drives are at most 100 m. A detection
# segment is split into at most _MAX_PIECES pieces (40 km at 10 m; longer ones only come from a
# defect, and their pieces then exceed the cell bound).
_KEY_HALF = float(1 << 31)
_MAX_CELLS_PER_SEGMENT = 4096
_MAX_PIECES = 4096


def _cell_key(ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
    # 2^31 cells per axis is far beyond any map extent at metre-scale cells.
    return (ix + (1 << 31)) * (1 << 32) + (iy + (1 << 31))


def _project_on_trajectory(drive: Drive, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(s (N,), yaw (N,)) of points projected onto the drive's trajectory."""
    xy = np.asarray(drive.xy, dtype=float)
    s_traj = arc_length(xy)
    # a point whose distance overflows (far beyond any plausible drive) gets index len(xy): clamp
    idx = np.minimum(cKDTree(xy).query(pts)[1], len(xy) - 1)
    # Refine along the local tangent so s is not quantised to the pose spacing.
    nxt = np.minimum(idx + 1, len(xy) - 1)
    prv = np.maximum(idx - 1, 0)
    tan = xy[nxt] - xy[prv]
    norm = np.hypot(tan[:, 0], tan[:, 1])
    tan = tan / np.where(norm > 1e-9, norm, 1.0)[:, None]
    s = s_traj[idx] + np.einsum("ij,ij->i", pts - xy[idx], tan)
    s = np.clip(s, 0.0, s_traj[-1])
    keep = np.concatenate([[True], np.diff(s_traj) > 1e-9])
    yaw = interp_angle(s, s_traj[keep], np.asarray(drive.yaw, dtype=float)[keep])
    return s, yaw


# Drives are thinned in chunks of about this many detection points: the per-level RDP arrays
# then stay in cache (measured: 4.8 -> 3.2 s for 4.2 M points), and the chunks can go to
# several processes.
_CHUNK_POINTS = 100_000


@dataclass
class _Thinned:
    """The detection segments of a run of drives after filtering, RDP and segment splitting,
    with their grid cells (segment numbers local to the run)."""

    seg_a: np.ndarray  # (S, 2)
    seg_b: np.ndarray  # (S, 2)
    seg_type: np.ndarray  # (S,) int8
    seg_drive: np.ndarray  # (S,) int32, index into the full drive list
    seg_s_a: np.ndarray  # (S,) own drive's travelled distance at the ends
    seg_s_b: np.ndarray
    seg_yaw: np.ndarray  # (S,) own drive's heading at the segment start
    cell_key: np.ndarray  # (K,) a cell each segment touches ...
    cell_seg: np.ndarray  # (K,) ... and the segment (local number)
    n_polylines_kept: int
    n_points_in: int
    n_points_kept: int


def preprocess(
    drives: list[Drive], *, config: PreprocessConfig = PreprocessConfig(), workers: int = 1
) -> DetectionIndex:
    """Filter, thin and index the detections of valid drives (Sec. III).

    Args:
        drives: validated drives (see ``model.validate_drive``); detections of type UNKNOWN are
            ignored.
        config: preprocessing options.
        workers: processes for the thinning (forked children; see ``hdmap_core.parallel``). Every
            step is per polyline, so the index is the same for any number.

    Returns:
        The detection index; drive index i is ``drives[i]``.
    """
    chunks = _drive_chunks(drives)  # of about equal size
    parts = map_balanced(lambda i: _thin(drives, *chunks[i], config), [1.0] * len(chunks), workers)
    n_points_in = sum(t.n_points_in for t in parts)
    n_points_kept = sum(t.n_points_kept for t in parts)
    n_kept = sum(t.n_polylines_kept for t in parts)
    cat = {
        f: np.concatenate([getattr(t, f) for t in parts])
        for f in ("seg_a", "seg_b", "seg_type", "seg_drive", "seg_s_a", "seg_s_b", "seg_yaw", "cell_key")
    }
    offset = np.cumsum([0] + [len(t.seg_type) for t in parts[:-1]])
    cell_seg = np.concatenate([t.cell_seg + off for t, off in zip(parts, offset)]) if parts else np.zeros(0, np.int64)
    keys, start, segs = _grid_csr(cat["cell_key"], cell_seg)
    n_in = sum(len(d.detections) for d in drives)
    return DetectionIndex(
        drive_ids=tuple(d.drive_id for d in drives),
        seg_a=cat["seg_a"],
        seg_b=cat["seg_b"],
        seg_type=cat["seg_type"],
        seg_drive=cat["seg_drive"],
        seg_s_a=cat["seg_s_a"],
        seg_s_b=cat["seg_s_b"],
        seg_yaw=cat["seg_yaw"],
        cell_m=config.grid_cell_m,
        cell_keys=keys,
        cell_start=start,
        cell_segs=segs,
        n_polylines_in=n_in,
        n_polylines_kept=n_kept,
        n_points_in=n_points_in,
        n_points_kept=n_points_kept,
    )


def _drive_chunks(drives: list[Drive]) -> list[tuple[int, int]]:
    """Runs [lo, hi) of drives with about ``_CHUNK_POINTS`` detection points each."""
    out: list[tuple[int, int]] = []
    lo, acc = 0, 0
    for di, drive in enumerate(drives):
        acc += sum(len(det.points) for det in drive.detections)
        if acc >= _CHUNK_POINTS:
            out.append((lo, di + 1))
            lo, acc = di + 1, 0
    if lo < len(drives) or not out:
        out.append((lo, len(drives)))
    return out


def _thin(drives: list[Drive], lo: int, hi: int, config: PreprocessConfig) -> _Thinned:
    """Drop short and UNKNOWN polylines, RDP, split long segments, project on the own drive."""
    chunks: list[np.ndarray] = []
    ptypes: list[int] = []
    pdrive: list[int] = []
    for di in range(lo, hi):
        for det in drives[di].detections:
            if int(det.type) == FeatureType.UNKNOWN:
                continue
            pts = np.asarray(det.points, dtype=float)
            if len(pts) < 2:
                continue
            chunks.append(pts)
            ptypes.append(int(det.type))
            pdrive.append(di)
    n_points_in = int(sum(len(c) for c in chunks))
    if not chunks:
        return _segments(
            drives,
            lo,
            hi,
            np.zeros((0, 2)),
            np.zeros(0, np.int64),
            np.zeros(0, np.int8),
            np.zeros(0, np.int32),
            config,
            n_points_in,
            0,
        )
    counts = np.array([len(c) for c in chunks])
    xy = np.concatenate(chunks)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    seg_len = np.hypot(*np.diff(xy, axis=0).T)
    # Polyline length = sum of its own segments (the one bridging to the next is excluded).
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    ends = starts + counts - 1
    lengths = cum[ends] - cum[starts]
    good = lengths >= config.min_length_m
    xy, starts, counts = _select_polylines(xy, starts, counts, good)
    ptypes_a = np.asarray(ptypes, dtype=np.int8)[good]
    pdrive_a = np.asarray(pdrive, dtype=np.int32)[good]
    mask = rdp_mask_many(xy, starts, config.rdp_epsilon_m) if len(xy) else np.zeros(0, bool)
    kept_counts = np.add.reduceat(mask, starts) if len(starts) else np.zeros(0, np.int64)
    xy = xy[mask]
    starts = np.concatenate([[0], np.cumsum(kept_counts)[:-1]]).astype(np.int64) if len(starts) else starts
    n_points_kept = len(xy)
    xy, starts = split_long_segments(xy, starts, config.max_segment_m, max_pieces=_MAX_PIECES)
    counts = np.diff(np.concatenate([starts, [len(xy)]])).astype(np.int64)
    return _segments(drives, lo, hi, xy, counts, ptypes_a, pdrive_a, config, n_points_in, n_points_kept)


def _segments(
    drives: list[Drive],
    lo: int,
    hi: int,
    xy: np.ndarray,
    counts: np.ndarray,
    ptypes: np.ndarray,
    pdrive: np.ndarray,
    config: PreprocessConfig,
    n_points_in: int,
    n_points_kept: int,
) -> _Thinned:
    """Segments of back-to-back polylines (drive by drive) with their own drive's distance and
    heading, and the grid cells they touch."""
    # Per-vertex own-drive distance and heading; vertices come drive by drive.
    v_drive = np.repeat(pdrive, counts)
    v_s = np.zeros(len(xy))
    v_yaw = np.zeros(len(xy))
    bounds = np.searchsorted(v_drive, np.arange(lo, hi + 1))
    for k in np.flatnonzero(np.diff(bounds)):
        sel = slice(bounds[k], bounds[k + 1])
        v_s[sel], v_yaw[sel] = _project_on_trajectory(drives[lo + k], xy[sel])
    # Segments: consecutive vertices inside one polyline.
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64) if len(counts) else np.zeros(0, np.int64)
    is_last = np.zeros(len(xy), dtype=bool)
    if len(xy):
        is_last[starts + counts - 1] = True
    a_idx = np.flatnonzero(~is_last)
    seg_a, seg_b = xy[a_idx], xy[a_idx + 1]
    cell_key, cell_seg = _grid_pairs(seg_a, seg_b, config.grid_cell_m)
    return _Thinned(
        seg_a=seg_a,
        seg_b=seg_b,
        seg_type=np.repeat(ptypes, counts)[a_idx],
        seg_drive=v_drive[a_idx],
        seg_s_a=v_s[a_idx],
        seg_s_b=v_s[a_idx + 1],
        seg_yaw=v_yaw[a_idx],
        cell_key=cell_key,
        cell_seg=cell_seg,
        n_polylines_kept=len(counts),
        n_points_in=n_points_in,
        n_points_kept=n_points_kept,
    )


def trajectory_index(drives: list[Drive], *, cell_m: float = PreprocessConfig.grid_cell_m) -> DetectionIndex:
    """The drives' own trajectories as a segment index (type UNKNOWN), for cut-line crossings:
    where each drive passed a cut (``hdmap_core.pipeline.evidence``). Drive index i is ``drives[i]``;
    validated drives (``model.validate_drive``: one finite yaw per pose)."""
    a_parts, b_parts, d_parts, sa_parts, sb_parts, y_parts = [], [], [], [], [], []
    for di, drive in enumerate(drives):
        xy = np.asarray(drive.xy, dtype=float).reshape(-1, 2)
        if len(xy) < 2:
            continue
        s = arc_length(xy)
        yaw = np.asarray(drive.yaw, dtype=float).reshape(-1)
        a_parts.append(xy[:-1])
        b_parts.append(xy[1:])
        d_parts.append(np.full(len(xy) - 1, di, dtype=np.int32))
        sa_parts.append(s[:-1])
        sb_parts.append(s[1:])
        y_parts.append(yaw[:-1])
    cat = lambda parts, empty: np.concatenate(parts) if parts else empty  # noqa: E731
    seg_a, seg_b = cat(a_parts, np.zeros((0, 2))), cat(b_parts, np.zeros((0, 2)))
    keys, start, segs = _build_grid(seg_a, seg_b, cell_m)
    return DetectionIndex(
        drive_ids=tuple(d.drive_id for d in drives),
        seg_a=seg_a,
        seg_b=seg_b,
        seg_type=np.full(len(seg_a), int(FeatureType.UNKNOWN), dtype=np.int8),
        seg_drive=cat(d_parts, np.zeros(0, np.int32)),
        seg_s_a=cat(sa_parts, np.zeros(0)),
        seg_s_b=cat(sb_parts, np.zeros(0)),
        seg_yaw=cat(y_parts, np.zeros(0)),
        cell_m=cell_m,
        cell_keys=keys,
        cell_start=start,
        cell_segs=segs,
    )


def _select_polylines(xy: np.ndarray, starts: np.ndarray, counts: np.ndarray, good: np.ndarray):
    vmask = np.repeat(good, counts)
    counts = counts[good]
    return xy[vmask], np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64), counts


def _build_grid(seg_a: np.ndarray, seg_b: np.ndarray, cell_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CSR grid hash: every segment in all cells its bounding box (grown by cell/4) touches."""
    return _grid_csr(*_grid_pairs(seg_a, seg_b, cell_m))


def _grid_pairs(seg_a: np.ndarray, seg_b: np.ndarray, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(cell key (K,), segment (K,)): every cell a segment's bounding box grown by cell/4 touches."""
    if len(seg_a) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pad = 0.25 * cell_m
    with np.errstate(invalid="ignore", over="ignore"):
        lo_f = np.floor((np.minimum(seg_a, seg_b) - pad) / cell_m)
        hi_f = np.floor((np.maximum(seg_a, seg_b) + pad) / cell_m)
        span = (hi_f[:, 0] - lo_f[:, 0] + 1) * (hi_f[:, 1] - lo_f[:, 1] + 1)
    # RULE: a segment over _MAX_CELLS_PER_SEGMENT cells (or beyond the key range) is left out of the
    # index rather than sized into memory: plausible drives never have one (detection segments are
    # split to max_segment_m, poses lie at most PhysicalBounds.max_pose_step_m apart), only a
    # defect does (one point at 1e12 m asked for terabytes).
    in_keys = (np.abs(lo_f).max(axis=1) < _KEY_HALF) & (np.abs(hi_f).max(axis=1) < _KEY_HALF)
    ok = (span <= _MAX_CELLS_PER_SEGMENT) & in_keys
    ids = np.flatnonzero(ok)
    lo, hi = lo_f[ids].astype(np.int64), hi_f[ids].astype(np.int64)
    nx, ny = hi[:, 0] - lo[:, 0] + 1, hi[:, 1] - lo[:, 1] + 1
    n = nx * ny
    seg = np.repeat(np.arange(len(ids)), n)
    first = np.concatenate([[0], np.cumsum(n)[:-1]])
    k = np.arange(len(seg)) - first[seg]
    ix = lo[seg, 0] + k % nx[seg]
    iy = lo[seg, 1] + k // nx[seg]
    return _cell_key(ix, iy), ids[seg].astype(np.int64)


def _grid_csr(keys: np.ndarray, seg: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(sorted distinct cell keys, CSR starts, segments per cell) of (cell, segment) pairs."""
    if len(keys) == 0:
        return np.zeros(0, np.int64), np.zeros(1, np.int64), np.zeros(0, np.int64)
    # The order of the segments within a cell is free (``intersect`` sorts its hits by cut and
    # segment), so an unstable sort does (twice as fast as a stable one on millions of keys).
    order = np.argsort(keys)
    keys, seg = keys[order], seg[order]
    ustart = np.flatnonzero(np.concatenate([[True], keys[1:] != keys[:-1]]))
    start = np.concatenate([ustart, [len(keys)]]).astype(np.int64)
    return keys[ustart], start, seg


def clean_drive(drive: Drive, *, config: PreprocessConfig = PreprocessConfig()) -> Drive:
    """One drive's detections filtered and thinned by the rules of :func:`preprocess` (the live
    ingestor cleans each drive as it comes).

    Detection polylines of type UNKNOWN, of fewer than 2 points or shorter than
    ``config.min_length_m`` are dropped (likely misdetections), the rest thinned with
    Ramer-Douglas-Peucker (``config.rdp_epsilon_m``). :func:`preprocess` applies the same rules
    again; both are idempotent, so a drive cleaned early maps the same.

    Args:
        drive: a validated drive (not modified).
    """
    kept = []
    for det in drive.detections:
        pts = np.asarray(det.points, dtype=float)
        if int(det.type) == FeatureType.UNKNOWN or len(pts) < 2:
            continue
        if float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()) < config.min_length_m:
            continue
        kept.append((det, pts))
    if not kept:
        return replace(drive, detections=())
    xy = np.vstack([p for _, p in kept])
    starts = np.cumsum([0] + [len(p) for _, p in kept[:-1]])
    mask = rdp_mask_many(xy, np.asarray(starts), config.rdp_epsilon_m)
    dets = tuple(Detection(type=det.type, points=pts[mask[s : s + len(pts)]]) for (det, pts), s in zip(kept, starts))
    return replace(drive, detections=dets)
