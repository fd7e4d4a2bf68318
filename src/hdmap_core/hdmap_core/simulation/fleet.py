"""Fleet simulator: realistic drives with detections over a ground-truth map.

Every drive is a snippet of a ground-truth route (chosen with a bias toward one driving
direction), driven with lane keeping, in-lane wander and occasional lane changes, with poses about
every metre. It reports what a series vehicle would (docs/simulator.md has the whole model):

* a pose trajectory with a per-drive localization error: a constant lateral and longitudinal bias
  plus a slow Gauss-Markov drift, in the vehicle frame (lateral along the left normal of the
  heading, longitudinal along the heading);
* detection polylines of the ground-truth features of its own carriageway (and the opposite
  median barrier), with visibility falling with lateral distance, dropouts as on/off gaps,
  measurement noise growing with distance, dashed<->solid (and rarely marking->border)
  misclassification, and short false positives. Everything a drive reports is displaced by that
  drive's pose error, so trajectory and detections stay consistent with each other.

Sign convention (shared with ``simulation.chains``): a drive whose pose error is ``e`` (left of the
heading) reports every point ``e`` further left than the truth.

The simulation is deterministic: drive ``i`` draws from its own ``numpy.random.Generator``
spawned from ``seed``, so it does not change when ``n_drives`` does.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from hdmap_core import geometry, groundtruth
from hdmap_core.errors import ConfigError, GroundTruthError, NoUsableDataError
from hdmap_core.geometry import arc_length, resample_evenly, unit_tangents
from hdmap_core.groundtruth import GroundTruth, GTRoute, load_ground_truth
from hdmap_core.model import Drive, GeoOrigin
from hdmap_core.simulation import changes as sim_changes
from hdmap_core.simulation import config as sim_config
from hdmap_core.simulation import sensor as sim_sensor
from hdmap_core.simulation import synthetic
from hdmap_core.simulation.changes import CHANGE_GAP_S, RoadChange, apply_changes
from hdmap_core.simulation.config import SimConfig
from hdmap_core.simulation.sensor import (
    FeatureIndex,
    detections,
    false_positives,
    feature_index,
    gauss_markov,
    seen_per_feature,
    smoothstep,
)

__all__ = [
    "Fleet",
    "simulate_fleet",
    "FleetStream",
    "route_directions",
    "load_map",
    "maps_dirs",
    "fleet_to_dict",
    "write_sim_json",
    "encode_runs",
    "decode_runs",
]


@dataclass(frozen=True)
class Fleet:
    """The simulator's output.

    Attributes:
        drives: the drive snippets, in start-time order.
        origin: WGS84 origin of the map frame (``config.origin``, by default ``DEFAULT_ORIGIN``).
        truth: per drive id: route id, direction, true biases, error statistics, lane sequence,
            detection counts, and the true trajectory (``true_xy``, (N, 2)) and true lateral /
            longitudinal error per pose (``lateral_error_m``, ``longitudinal_error_m``, (N,)).
        config: the configuration used.
        seed: the seed used.
        map_name: name of the ground truth.
        seen_count: per ground-truth feature id, (N_f,) int64: for each of its points the number
            of distinct drives that detected it (visible and reported in a detection polyline,
            of whatever type); what no drive saw cannot be in any map made from this fleet.
    """

    drives: list[Drive]
    origin: GeoOrigin
    truth: dict[str, dict]
    config: SimConfig
    seed: int = 0
    map_name: str = ""
    extra: dict = field(default_factory=dict, compare=False)
    seen_count: dict[int, np.ndarray] = field(default_factory=dict, compare=False)

    def summary(self) -> dict:
        """Counts: drives, driven km, detections (and false positives among them)."""
        if not self.drives and "summary" in self.extra:  # streamed (``FleetStream.fleet``)
            return dict(self.extra["summary"])
        km = sum(d.length_m for d in self.drives) / 1000.0
        return {
            "drives": len(self.drives),
            "km": round(km, 3),
            "detections": sum(len(d.detections) for d in self.drives),
            "false_positives": sum(int(t["n_false_positives"]) for t in self.truth.values()),
            "poses": sum(len(d.xy) for d in self.drives),
        }


_ARRAY_KEYS = ("true_xy", "lateral_error_m", "longitudinal_error_m")


#: Besides this one, the modules whose source decides what a map, a config and a seed simulate.
_FINGERPRINTED = (sim_config, sim_sensor, synthetic, sim_changes, groundtruth, geometry)


@functools.lru_cache(maxsize=1)
def simulator_fingerprint() -> str:
    """A hash of the source of the modules that turn a map, a config and a seed into a fleet
    (this one, its config and defaults, the sensor model, the synthetic maps, the road changes,
    the ground-truth loader, the geometry they use): written to
    ``OUT.sim.json`` so that a fleet cached by an older simulator is recognised as stale."""
    h = hashlib.sha1()
    for mod_file in (__file__, *(str(m.__file__) for m in _FINGERPRINTED)):
        h.update(Path(mod_file).read_bytes())
    return h.hexdigest()[:16]


def fleet_to_dict(fleet: Fleet, *, include_trajectories: bool = False) -> dict:
    """The JSON document of ``OUT.sim.json``: config, seed, origin, summary and per-drive truth.

    Per-pose arrays (true trajectory and errors) are left out unless ``include_trajectories``.
    """
    truth = {}
    for did, t in fleet.truth.items():
        row = {k: v for k, v in t.items() if k not in _ARRAY_KEYS}
        if include_trajectories:
            row.update({k: np.round(np.asarray(t[k]), 4).tolist() for k in _ARRAY_KEYS})
        truth[did] = row
    return {
        "map": fleet.map_name,
        "seed": fleet.seed,
        "simulator": simulator_fingerprint(),
        "origin": asdict(fleet.origin),
        "config": fleet.config.to_dict(),
        "summary": fleet.summary(),
        "truth": truth,
        "seen_count": {str(fid): encode_runs(n) for fid, n in fleet.seen_count.items()},
    }


def encode_runs(values: np.ndarray) -> list[int]:
    """Run-length code of a 1-D int sequence: ``[value, run length, value, run length, ...]``."""
    v = np.asarray(values, dtype=np.int64).reshape(-1)
    if len(v) == 0:
        return []
    start = np.flatnonzero(np.concatenate([[True], v[1:] != v[:-1]]))
    runs = np.diff(np.concatenate([start, [len(v)]]))
    return np.stack([v[start], runs], axis=1).reshape(-1).tolist()


def decode_runs(code: object) -> np.ndarray:
    """(N,) int64, the inverse of ``encode_runs``.

    Raises:
        ValueError: ``code`` is not a flat list of (value, run length >= 1) pairs of integers.
    """
    arr = np.asarray(code if code is not None else [], dtype=float).reshape(-1)
    if len(arr) % 2 or not np.all(np.isfinite(arr)) or np.any(arr != np.round(arr)):
        raise ValueError("not a list of integer (value, run length) pairs")
    pairs = arr.astype(np.int64).reshape(-1, 2)
    if np.any(pairs[:, 1] < 1):
        raise ValueError("run lengths must be >= 1")
    return np.repeat(pairs[:, 0], pairs[:, 1])


# ------------------------------------------------------------------------------ map lookup


def maps_dirs() -> list[Path]:
    """Directories searched for ``<name>.gt.json``: ``$HDMAP_MAPS_DIR`` (os.pathsep separated),
    then ``data/maps`` of the repository (the real maps shipped with it, licences in its README):
    the first ``data/maps`` holding a ``*.gt.json`` in a parent of this package or of the working
    directory."""
    out: list[Path] = []
    env = os.environ.get("HDMAP_MAPS_DIR", "")
    out += [Path(p) for p in env.split(os.pathsep) if p]
    for start in (Path(__file__).resolve(), Path.cwd().resolve()):
        for parent in start.parents if start.is_file() else (start, *start.parents):
            cand = parent / "data" / "maps"
            if cand.is_dir() and cand not in out and any(cand.glob("*.gt.json")):
                out.append(cand)
                break
    return [p for p in out if p.is_dir()]


def load_map(name_or_path: str, *, length_m: float | None = None, map_seed: int = 0) -> GroundTruth:
    """Ground truth by name: a synthetic layout (``motorway``, ``motorway_ramps``, ``lane_drop``;
    ``length_m`` and ``map_seed`` apply), a shipped map name (``esmini_e6mini``, found via
    ``maps_dirs()``) or a path to a ``.gt.json`` file.

    Raises:
        GroundTruthError: nothing of that name, or the file is not a ground-truth map.
        ConfigError: a bad synthetic length.
    """
    if name_or_path in synthetic.SYNTHETIC_NAMES:
        kw = {"length_m": float(length_m)} if length_m is not None else {}
        return synthetic.synthetic_highway(name_or_path, seed=map_seed, **kw)
    path = Path(name_or_path)
    if path.suffix == ".json" or path.exists():
        return load_ground_truth(path)
    for d in maps_dirs():
        cand = d / f"{name_or_path}.gt.json"
        if cand.is_file():
            return load_ground_truth(cand)
    shared = sorted({p.name[: -len(".gt.json")] for d in maps_dirs() for p in d.glob("*.gt.json")})
    raise GroundTruthError(
        f"no map {name_or_path!r}: not a synthetic name ({', '.join(synthetic.SYNTHETIC_NAMES)}), not a file, "
        f"not a shipped map ({', '.join(shared) or 'no data/maps found; set HDMAP_MAPS_DIR'})"
    )


# ------------------------------------------------------------------------------ routes


def route_directions(gt: GroundTruth) -> dict[str, int]:
    """Driving direction of each route: 0 (primary) or 1 (the opposite carriageway).

    Uses ``gt.extra["route_directions"]`` when it names every route (synthetic maps); otherwise
    compares each route's heading with the longest route's heading where they run within 30 m
    (same or opposite carriageway), falling back to their overall directions.
    """
    given = gt.extra.get("route_directions")
    if isinstance(given, dict) and all(r.id in given for r in gt.routes):
        labels: list = []
        for r in gt.routes:
            if given[r.id] not in labels:
                labels.append(given[r.id])
        return {r.id: min(labels.index(given[r.id]), 1) for r in gt.routes}
    lines = {r.id: resample_evenly(gt.route_centerline(r), 5.0) for r in gt.routes}
    ref_id = max(lines, key=lambda k: len(lines[k]))
    ref = lines[ref_id]
    ref_t = unit_tangents(ref)
    tree = cKDTree(ref)
    out = {}
    for rid, pts in lines.items():
        dist, k = tree.query(pts, distance_upper_bound=30.0)
        ok = np.isfinite(dist)
        if ok.sum() >= 3:
            score = float(np.mean(np.sum(unit_tangents(pts)[ok] * ref_t[k[ok]], axis=1)))
        else:
            score = float(np.dot(pts[-1] - pts[0], ref[-1] - ref[0]))
        out[rid] = 0 if score >= 0 else 1
    return out


@dataclass(frozen=True)
class _RouteGeom:
    """A route resampled at the pose spacing, with the lateral offsets to its neighbour lanes.

    xy (M, 2), s (M,), tangent/left (M, 2); lane (M,) index into ``lane_ids``; off_left/right
    (M,) lateral offset of the left/right neighbour lane's centre [m], NaN where there is none;
    nb_left/right (M,) index into ``lane_ids`` (-1 none).
    """

    route_id: str
    xy: np.ndarray
    s: np.ndarray
    tangent: np.ndarray
    left: np.ndarray
    lane: np.ndarray
    off_left: np.ndarray
    off_right: np.ndarray
    nb_left: np.ndarray
    nb_right: np.ndarray
    lane_ids: tuple[str, ...]

    @property
    def length_m(self) -> float:
        return float(self.s[-1])


def _route_pieces(gt: GroundTruth, route: GTRoute) -> list[tuple[str, np.ndarray]]:
    """(lane id, centerline part) in driving order. At a route lane change the vehicle leaves
    the first lane halfway along it and joins the side-by-side lane there (the jump is blended
    out later)."""
    changes = set(route.lane_changes)
    out = []
    a = 0.0
    for i, lid in enumerate(route.lanes):
        cl = gt.lanes[lid].centerline
        b = (a + (1.0 - a) / 2.0) if i in changes else 1.0
        s = arc_length(cl)
        total = s[-1] if len(s) else 0.0
        keep = (s >= a * total - 1e-9) & (s <= b * total + 1e-9)
        part = cl[keep] if keep.sum() >= 2 else cl
        out.append((lid, part))
        a = b if i in changes else 0.0
    return out


def _build_route_geom(gt: GroundTruth, route: GTRoute, spacing_m: float, trees: dict) -> _RouteGeom:
    pieces = _route_pieces(gt, route)
    lane_ids = tuple(dict.fromkeys(lid for lid, _ in pieces))
    pts = np.concatenate([p for _, p in pieces])
    lab = np.concatenate([np.full(len(p), lane_ids.index(lid)) for lid, p in pieces])
    starts = np.cumsum([0] + [len(p) for _, p in pieces])[1:-1]
    keep = np.ones(len(pts), dtype=bool)
    keep[1:] = np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-3
    # Blend lateral jumps at joints (route lane changes, taper links): half before, half after.
    s = arc_length(pts)
    for j in starts:
        if j < 2 or j >= len(pts):
            continue
        t = pts[j - 1] - pts[j - 2]
        t = t / max(np.linalg.norm(t), 1e-12)
        jump = pts[j] - pts[j - 1]
        jump = jump - np.dot(jump, t) * t
        if np.linalg.norm(jump) < 0.2:
            continue
        w = 50.0
        x = (s - (s[j] - w)) / (2.0 * w)
        before = (s >= s[j] - w) & (np.arange(len(s)) < j)
        after = (s <= s[j] + w) & (np.arange(len(s)) >= j)
        pts = pts.copy()
        pts[before] += smoothstep(x[before])[:, None] * jump
        pts[after] -= (1.0 - smoothstep(x[after]))[:, None] * jump
    pts, lab = pts[keep], lab[keep]
    s = arc_length(pts)
    n = max(2, int(np.floor(s[-1] / spacing_m)) + 1)
    q = np.arange(n) * spacing_m
    xy = np.stack([np.interp(q, s, pts[:, 0]), np.interp(q, s, pts[:, 1])], axis=1)
    lane = lab[np.clip(np.searchsorted(s, q, side="right") - 1, 0, len(lab) - 1)]
    tangent = unit_tangents(xy)
    left = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    off = {"left": np.full(n, np.nan), "right": np.full(n, np.nan)}
    nb = {"left": np.full(n, -1), "right": np.full(n, -1)}
    all_ids = list(lane_ids)
    for k, lid in enumerate(lane_ids):
        sel = np.flatnonzero(lane == k)
        for side in ("left", "right"):
            nid = getattr(gt.lanes[lid], side)
            if not nid or nid not in gt.lanes or len(sel) == 0:
                continue
            if nid not in trees:
                trees[nid] = cKDTree(gt.lanes[nid].centerline)
            _, m = trees[nid].query(xy[sel])
            v = gt.lanes[nid].centerline[m] - xy[sel]
            along = np.sum(v * tangent[sel], axis=1)
            lat = np.sum(v * left[sel], axis=1)
            good = (np.abs(along) < 1.0) & ((lat > 1.0) if side == "left" else (lat < -1.0)) & (np.abs(lat) < 8.0)
            if nid not in all_ids:
                all_ids.append(nid)
            off[side][sel[good]] = lat[good]
            nb[side][sel[good]] = all_ids.index(nid)
    return _RouteGeom(
        route.id, xy, q, tangent, left, lane, off["left"], off["right"], nb["left"], nb["right"], tuple(all_ids)
    )


# ------------------------------------------------------------------------------ drives


def _lane_change_offsets(
    geom: _RouteGeom, k0: int, m: int, cfg: SimConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Lateral offset (m,) of lane-change manoeuvres (out to a neighbour lane, stay, back) and the
    side (m,) the vehicle is in (+1 left, -1 right, 0 own lane). A manoeuvre only starts where the
    neighbour exists and returns before the neighbour lane ends."""
    off = np.zeros(m)
    side_of = np.zeros(m, dtype=int)
    if cfg.lane_change_rate_per_km <= 0 or m < 3:
        return off, side_of
    step = cfg.pose_spacing_m
    mean_gap = 1000.0 / cfg.lane_change_rate_per_km
    pos = rng.exponential(mean_gap)
    while True:
        i0 = int(pos / step)
        if i0 >= m - 2:
            break
        n_t = max(1, int(rng.uniform(cfg.lane_change_length_min_m, cfg.lane_change_length_max_m) / step))
        n_s = int(rng.uniform(cfg.lane_change_stay_min_m, cfg.lane_change_stay_max_m) / step)
        sides = [sd for sd, arr in ((1, geom.off_left), (-1, geom.off_right)) if np.isfinite(arr[k0 + i0])]
        if not sides:
            pos += n_t * step
            continue
        side = int(rng.choice(sides))
        arr = (geom.off_left if side == 1 else geom.off_right)[k0 + i0 : k0 + m]
        gone = np.flatnonzero(~np.isfinite(arr))
        if len(gone):  # return before the neighbour lane ends
            n_s = min(n_s, int(gone[0]) - 2 * n_t)
            if n_s < 0:
                pos += n_t * step
                continue
        j = np.arange(2 * n_t + n_s)
        prof = np.where(
            j < n_t, smoothstep(j / n_t), np.where(j < n_t + n_s, 1.0, 1.0 - smoothstep((j - n_t - n_s) / n_t))
        )
        prof = prof[: m - i0]
        off[i0 : i0 + len(prof)] = prof * np.nan_to_num(arr[: len(prof)])
        side_of[i0 : i0 + len(prof)] = np.where(prof > 0.5, side, 0)
        pos = (i0 + len(j)) * step + rng.exponential(mean_gap)
    return off, side_of


def _lane_sequence(geom: _RouteGeom, k0: int, side_of: np.ndarray) -> list[str]:
    sl = slice(k0, k0 + len(side_of))
    lane = np.where(side_of == 1, geom.nb_left[sl], np.where(side_of == -1, geom.nb_right[sl], geom.lane[sl]))
    lane = np.where(lane < 0, geom.lane[sl], lane)
    keep = np.ones(len(lane), dtype=bool)
    keep[1:] = lane[1:] != lane[:-1]
    return [geom.lane_ids[i] for i in lane[keep]]


def _draw_snippet(geom: _RouteGeom, cfg: SimConfig, rng: np.random.Generator) -> tuple[int, int]:
    """(first pose index, pose count) of a snippet of random length at a uniformly random place."""
    step = cfg.pose_spacing_m
    snip = rng.uniform(cfg.snippet_length_min_m, cfg.snippet_length_max_m)
    total = geom.length_m
    start_m = rng.uniform(0.0, total - snip) if snip < total else 0.0
    k0 = int(round(start_m / step))
    return k0, max(2, min(len(geom.s) - k0, int(round(snip / step)) + 1))


class _PlaceCounts:
    """Drives so far per place (a ``cell_m`` grid cell of one driving direction), for the
    "coverage" route choice."""

    def __init__(self, cell_m: float) -> None:
        self.cell_m = cell_m
        self.ids: dict[tuple[int, int, int], int] = {}
        self.count = np.zeros(0, dtype=np.int64)
        self._cells: dict[str, np.ndarray] = {}  # route id -> cell id per pose

    def cells(self, geom: _RouteGeom, direction: int) -> np.ndarray:
        got = self._cells.get(geom.route_id)
        if got is None:
            ij = np.floor(geom.xy / self.cell_m).astype(np.int64)
            got = np.array(
                [self.ids.setdefault((direction, int(i), int(j)), len(self.ids)) for i, j in ij], dtype=np.int64
            )
            self._cells[geom.route_id] = got
            if len(self.ids) > len(self.count):
                self.count = np.concatenate([self.count, np.zeros(len(self.ids) - len(self.count), dtype=np.int64)])
        return got

    def score(self, geom: _RouteGeom, direction: int, snippet: tuple[int, int]) -> tuple[int, float]:
        """(fewest drives at a place of the snippet, mean drives over its places): lower is emptier."""
        k0, m = snippet
        cells = np.unique(self.cells(geom, direction)[k0 : k0 + m])  # may grow ``count``: index after
        c = self.count[cells]
        return int(c.min()), float(c.mean())

    def add(self, geom: _RouteGeom, direction: int, snippet: tuple[int, int]) -> None:
        k0, m = snippet
        cells = np.unique(self.cells(geom, direction)[k0 : k0 + m])
        self.count[cells] += 1


def _simulate_drive(
    i: int,
    drive_id: str,
    geom: _RouteGeom,
    direction: int,
    start_ns: int,
    idx: FeatureIndex,
    cfg: SimConfig,
    rng: np.random.Generator,
    snippet: tuple[int, int] | None = None,
) -> tuple[Drive, dict, np.ndarray]:
    """One drive: the drive, its truth, and (S,) the indices into ``idx`` of the ground-truth
    feature points it detected (each once)."""
    step = cfg.pose_spacing_m
    if snippet is None:
        snippet = _draw_snippet(geom, cfg, rng)
    k0, m = snippet
    sl = slice(k0, k0 + m)
    wander = gauss_markov(m, step, cfg.wander_sigma_m, cfg.wander_corr_length_m, rng)
    lc, side_of = _lane_change_offsets(geom, k0, m, cfg, rng)
    true_xy = geom.xy[sl] + (wander + lc)[:, None] * geom.left[sl]
    yaw = np.arctan2(*np.gradient(true_xy, axis=0)[:, ::-1].T)
    head = np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
    left = np.stack([-head[:, 1], head[:, 0]], axis=1)
    b_lat = rng.normal(0.0, cfg.bias_lateral_sigma_m) if cfg.bias_lateral_sigma_m > 0 else 0.0
    b_lon = rng.normal(0.0, cfg.bias_longitudinal_sigma_m) if cfg.bias_longitudinal_sigma_m > 0 else 0.0
    e_lat = b_lat + gauss_markov(m, step, cfg.drift_sigma_m, cfg.drift_corr_length_m, rng)
    e_lon = b_lon + gauss_markov(m, step, cfg.drift_sigma_m, cfg.drift_corr_length_m, rng)
    disp = e_lat[:, None] * left + e_lon[:, None] * head
    speed = rng.uniform(cfg.speed_min_mps, cfg.speed_max_mps)
    stamps = start_ns + np.rint(np.arange(m) * (step / speed) * 1e9).astype(np.int64)
    length = float(np.linalg.norm(np.diff(true_xy, axis=0), axis=1).sum())
    dets, seen = detections(idx, true_xy, yaw, disp, cfg, rng)
    fps = false_positives(true_xy, yaw, disp, length, cfg, rng)
    vehicle = f"veh{int(rng.integers(0, cfg.n_vehicles)):03d}"
    drive = Drive(drive_id, true_xy + disp, yaw, stamps, tuple(dets + fps), vehicle_id=vehicle)
    lanes = _lane_sequence(geom, k0, side_of)
    truth = {
        "index": i,
        "route_id": geom.route_id,
        "direction": direction,
        "route_start_m": round(float(geom.s[k0]), 3),
        "length_m": round(length, 3),
        "speed_mps": round(float(speed), 3),
        "vehicle_id": vehicle,
        "bias_lateral_m": float(b_lat),
        "bias_longitudinal_m": float(b_lon),
        "drift_sigma_m": cfg.drift_sigma_m,
        "drift_corr_length_m": cfg.drift_corr_length_m,
        "lateral_error_mean_m": float(e_lat.mean()),
        "lateral_error_std_m": float(e_lat.std()),
        "longitudinal_error_mean_m": float(e_lon.mean()),
        "lane_sequence": lanes,
        "n_lane_changes": int(np.count_nonzero(np.diff(side_of))),
        "n_detections": len(dets) + len(fps),
        "n_false_positives": len(fps),
        "true_xy": true_xy,
        "lateral_error_m": e_lat,
        "longitudinal_error_m": e_lon,
    }
    return drive, truth, seen


def simulate_fleet(
    gt: GroundTruth, *, config: SimConfig = SimConfig(), seed: int = 0, changes: Sequence[RoadChange] = ()
) -> Fleet:
    """Simulate ``config.n_drives`` drive snippets over the routes of ``gt``.

    Args:
        gt: ground truth with at least one route of >= 2 m.
        config: all simulator parameters.
        seed: seed of everything random; the same (gt, config, seed) gives identical output.
        changes: road changes (``simulation.changes``): drive ``i`` sees ``gt`` with every change
            of ``after_drive <= i`` applied; the first drive after a change starts
            ``CHANGE_GAP_S`` later than it would have. Drives before the first change are those
            of the same simulation without changes. ``Fleet.extra`` then holds ``changes``
            (with their ``time_ns``), ``gt_before`` and ``gt_after`` (as of the last drive);
            ``seen_count`` refers to ``gt_after``.

    Returns:
        the ``Fleet``: drives (map frame, with localization error), origin, per-drive truth, and
        per ground-truth feature point the number of drives that detected it.

    Raises:
        ConfigError: ``seed`` is negative or not an integer, or the config is invalid.
        GroundTruthError: ``gt`` is not a ``GroundTruth``.
        NoUsableDataError: ``gt`` has no usable route.
        GroundTruthError: a change does not fit ``gt`` (unknown route, zone off it).
    """
    stream = FleetStream(gt, config=config, seed=seed, changes=changes, keep_arrays=True)
    drives = list(stream)
    return Fleet(
        drives,
        stream.origin,
        stream.truth,
        config,
        int(seed),
        gt.name,
        extra=stream.change_extra(),
        seen_count=stream.seen_count(),
    )


class FleetStream:
    """The drives of :func:`simulate_fleet`, one at a time (the same drives, in the same order),
    for fleets too large to hold: iterate once; the truth rows and the seen counts grow as it goes.

    Attributes:
        origin, config, seed, map_name: as in ``Fleet``.
        truth: per drive id simulated so far, its truth row (per-pose arrays only with
            ``keep_arrays``).

    Raises:
        as :func:`simulate_fleet` (on construction).
    """

    def __init__(
        self,
        gt: GroundTruth,
        *,
        config: SimConfig = SimConfig(),
        seed: int = 0,
        changes: Sequence[RoadChange] = (),
        keep_arrays: bool = False,
    ) -> None:
        if not isinstance(gt, GroundTruth):
            raise GroundTruthError(f"simulate_fleet: expected a GroundTruth, got {type(gt).__name__}")
        if not isinstance(config, SimConfig):
            raise ConfigError(f"simulate_fleet: expected a SimConfig, got {type(config).__name__}")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ConfigError(f"simulate_fleet: seed must be a non-negative integer, got {seed!r}")
        config.validate()
        routes = [r for r in gt.routes if len(r.lanes) and len(gt.route_centerline(r)) >= 2]
        self._lengths = {r.id: float(arc_length(gt.route_centerline(r))[-1]) for r in routes}
        routes = [r for r in routes if self._lengths[r.id] >= 2.0]
        if not routes:
            raise NoUsableDataError(f"ground truth {gt.name!r} has no route to drive on")
        self.gt, self.config, self.seed, self.map_name = gt, config, int(seed), gt.name
        self.origin = config.origin
        self.keep_arrays = keep_arrays
        self.changes = tuple(changes)
        self._dirs = route_directions(gt)
        self._by_dir = {d: [r for r in routes if self._dirs[r.id] == d] for d in (0, 1)}
        self._epochs = _epochs(gt, self.changes)
        self._epoch = self._epochs[0]
        self._timed: list[RoadChange] = []
        self.truth: dict[str, dict] = {}
        self._counts = {"drives": 0, "m": 0.0, "detections": 0, "false_positives": 0, "poses": 0}
        self._started = False

    def summary(self) -> dict:
        """``Fleet.summary`` of the drives simulated so far."""
        c = self._counts
        return {
            "drives": c["drives"],
            "km": round(c["m"] / 1000.0, 3),
            "detections": c["detections"],
            "false_positives": c["false_positives"],
            "poses": c["poses"],
        }

    def seen_count(self) -> dict[int, np.ndarray]:
        """``Fleet.seen_count`` of the drives simulated so far (with changes: of the road as of the
        last drive; a feature kept whole keeps its id and points, so its counts add up)."""
        epoch = self._epoch
        if not self.changes:
            return seen_per_feature(self.gt, epoch.idx, epoch.seen)
        seen_count: dict[int, np.ndarray] = {}
        for e in self._epochs[: self._epochs.index(epoch) + 1]:
            for fid, n in seen_per_feature(e.gt, e.idx, e.seen).items():
                same = fid in seen_count and len(seen_count[fid]) == len(n)
                seen_count[fid] = seen_count[fid] + n if same else n
        ids_after = {(f.id, len(f.points)) for f in epoch.gt.features}
        return {fid: n for fid, n in seen_count.items() if (fid, len(n)) in ids_after}

    def change_extra(self) -> dict:
        """``Fleet.extra`` of a simulation with changes (after the iteration): ``changes`` with
        their ``time_ns``, ``gt_before``, ``gt_after`` (as of the last drive); empty without."""
        if not self.changes:
            return {}
        return {"changes": list(self._timed), "gt_before": self.gt, "gt_after": self._epoch.gt}

    def fleet(self) -> Fleet:
        """A ``Fleet`` without its drives (they were streamed), for ``write_sim_json``."""
        return Fleet(
            [],
            self.origin,
            self.truth,
            self.config,
            self.seed,
            self.map_name,
            extra={"summary": self.summary(), **self.change_extra()},
            seen_count=self.seen_count(),
        )

    def __iter__(self) -> Iterator[Drive]:
        if self._started:
            raise ConfigError("a FleetStream is iterated once")
        self._started = True
        gt, config, seed = self.gt, self.config, self.seed
        lengths, dirs, by_dir, epochs = self._lengths, self._dirs, self._by_dir, self._epochs
        children = np.random.SeedSequence(int(seed)).spawn(config.n_drives)
        t_ns = int(config.start_time_ns)
        places = _PlaceCounts(config.coverage_cell_m)

        def geom_of(route: GTRoute) -> _RouteGeom:
            epoch = self._epoch
            if route.id not in epoch.geoms:
                epoch.geoms[route.id] = _build_route_geom(epoch.gt, route, config.pose_spacing_m, epoch.trees)
            return epoch.geoms[route.id]

        for i, child in enumerate(children):
            rng = np.random.default_rng(child)
            gap_ns = 0
            while self._epoch.next_at is not None and i >= self._epoch.next_at:
                self._epoch = epochs[epochs.index(self._epoch) + 1]
                gap_ns = int(CHANGE_GAP_S * 1e9)
            d = 0 if rng.random() < config.direction_bias else 1
            pool = by_dir[d] or by_dir[1 - d]
            w = np.array([lengths[r.id] if config.route_weighting != "uniform" else 1.0 for r in pool])
            snippet = None
            if config.route_weighting == "coverage":
                # Of a few snippets drawn as for "length", drive the one over the least-driven place.
                best = None
                for _ in range(config.coverage_candidates):
                    cand = pool[int(rng.choice(len(pool), p=w / w.sum()))]
                    snip = _draw_snippet(geom_of(cand), config, rng)
                    key = places.score(geom_of(cand), dirs[cand.id], snip)
                    if best is None or key < best[0]:
                        best = (key, cand, snip)
                assert best is not None  # coverage_candidates >= 1 (SimConfig.validate)
                _, route, snippet = best
                places.add(geom_of(route), dirs[route.id], snippet)
            else:
                route = pool[int(rng.choice(len(pool), p=w / w.sum()))]
            if i > 0:
                t_ns += int(rng.uniform(config.drive_gap_min_s, config.drive_gap_max_s) * 1e9)
            if gap_ns:
                self._timed += [replace(c, time_ns=t_ns + gap_ns // 2) for c in self._epoch.made]
                t_ns += gap_ns
            drive_id = f"{gt.name}_s{seed}_{i:04d}"
            drive, tr, seen = _simulate_drive(
                i, drive_id, geom_of(route), dirs[route.id], t_ns, self._epoch.idx, config, rng, snippet
            )
            if not self.keep_arrays:
                tr = {k: v for k, v in tr.items() if k not in _ARRAY_KEYS}
            self.truth[drive_id] = tr
            self._epoch.seen[seen] += 1  # ``seen`` holds each point once: distinct drives
            c = self._counts
            c["drives"] += 1
            c["m"] += drive.length_m
            c["detections"] += len(drive.detections)
            c["false_positives"] += int(tr["n_false_positives"])
            c["poses"] += len(drive.xy)
            yield drive
        if self.changes:
            gap_ns = int(CHANGE_GAP_S * 1e9)
            if epochs[0].made:  # changes before the first drive
                start = int(config.start_time_ns) - gap_ns // 2
                self._timed = [replace(c, time_ns=start) for c in epochs[0].made] + self._timed
            for e in epochs[epochs.index(self._epoch) + 1 :]:  # changes after the last drive
                t_ns += gap_ns
                self._timed += [replace(c, time_ns=t_ns - gap_ns // 2) for c in e.made]


@dataclass(eq=False)
class _Epoch:
    """The road between two changes: its ground truth and what the drives on it need."""

    gt: GroundTruth
    next_at: int | None  # first drive of the next epoch
    made: tuple[RoadChange, ...]  # the changes that made it
    idx: FeatureIndex
    seen: np.ndarray
    geoms: dict = field(default_factory=dict)
    trees: dict = field(default_factory=dict)


def _epochs(gt: GroundTruth, changes: Sequence[RoadChange]) -> list[_Epoch]:
    """The road's epochs in order: as it was (with the changes ``@0`` made), then after each
    group of changes of the same ``after_drive``."""
    starts = sorted({c.after_drive for c in changes} | {0})
    out: list[_Epoch] = []
    road = gt
    for k, first in enumerate(starts):
        made = tuple(c for c in changes if c.after_drive == first)
        road = apply_changes(road, made)
        idx = feature_index(road)
        nxt = starts[k + 1] if k + 1 < len(starts) else None
        out.append(_Epoch(road, nxt, made, idx, np.zeros(len(idx.xy), dtype=np.int64)))
    return out


def write_sim_json(fleet: Fleet, path: str | Path, *, include_trajectories: bool = False) -> None:
    """Write ``fleet_to_dict(fleet)`` as JSON (``OUT.sim.json``), indented, except that each
    feature's run-length coded seen count is kept on one line (Town04, 100 drives: 19 kB instead
    of 46 kB)."""
    doc = fleet_to_dict(fleet, include_trajectories=include_trajectories)
    seen = doc.pop("seen_count")
    text = json.dumps(doc, indent=1)
    rows = ",\n".join(f"  {json.dumps(k)}: {json.dumps(v, separators=(',', ':'))}" for k, v in seen.items())
    tail = f',\n "seen_count": {{\n{rows}\n }}\n}}' if rows else ',\n "seen_count": {}\n}'
    Path(path).write_text(text[: text.rindex("}")].rstrip() + tail)
