"""Fleet simulator: its output follows its config (real statistics, measured against the GT)."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from hdmap_core.errors import ConfigError, GroundTruthError, NoUsableDataError
from hdmap_core.groundtruth import GroundTruth
from hdmap_core.model import FeatureType, validate_drive
from hdmap_core.simulation.config import DEFAULT_ORIGIN, SimConfig
from hdmap_core.simulation.fleet import (
    decode_runs,
    encode_runs,
    fleet_to_dict,
    load_map,
    route_directions,
    simulate_fleet,
    write_sim_json,
)
from hdmap_core.simulation.synthetic import synthetic_highway

SHORT = dict(snippet_length_min_m=300.0, snippet_length_max_m=600.0)


@pytest.fixture(scope="module")
def ramps() -> GroundTruth:
    return synthetic_highway("motorway_ramps", length_m=2500.0)


@pytest.fixture(scope="module")
def motorway() -> GroundTruth:
    return synthetic_highway("motorway", length_m=2000.0)


def _left(yaw: np.ndarray) -> np.ndarray:
    return np.stack([-np.sin(yaw), np.cos(yaw)], axis=1)


def _head(yaw: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(yaw), np.sin(yaw)], axis=1)


class _Lines:
    """Point-to-polyline distance, optionally of one type only (exact point-segment distance to the
    segments at the k nearest vertices)."""

    def __init__(self, polylines: list[np.ndarray], types: list[int]) -> None:
        self.pts = np.concatenate(polylines)
        self.type = np.concatenate([np.full(len(p), int(t)) for p, t in zip(polylines, types)])
        last = np.concatenate([np.arange(len(p)) == len(p) - 1 for p in polylines])
        self.has_next = ~last
        self.tree = cKDTree(self.pts)

    def distance(self, pts: np.ndarray, ftype: int | None = None, k: int = 12) -> np.ndarray:
        k = min(k, len(self.pts))
        _, j = self.tree.query(pts, k=k)
        j = j.reshape(len(pts), k)
        best = np.full(len(pts), np.inf)
        for col in range(k):
            for a in (j[:, col] - 1, j[:, col]):
                a = np.clip(a, 0, len(self.pts) - 2)
                ok = self.has_next[a] & ((self.type[a] == ftype) if ftype is not None else True)
                p0, p1 = self.pts[a], self.pts[a + 1]
                d = p1 - p0
                t = np.clip(np.sum((pts - p0) * d, axis=1) / np.maximum(np.sum(d * d, axis=1), 1e-12), 0.0, 1.0)
                dist = np.linalg.norm(pts - (p0 + t[:, None] * d), axis=1)
                best = np.where(ok, np.minimum(best, dist), best)
        return best


def _gt_lines(gt: GroundTruth) -> _Lines:
    return _Lines([f.points for f in gt.features], [int(f.type) for f in gt.features])


# ---------------------------------------------------------------------------- determinism


def _same_fleet(a, b) -> bool:
    if [d.drive_id for d in a.drives] != [d.drive_id for d in b.drives]:
        return False
    for da, db in zip(a.drives, b.drives):
        if not (np.array_equal(da.xy, db.xy) and np.array_equal(da.stamps_ns, db.stamps_ns)):
            return False
        if len(da.detections) != len(db.detections):
            return False
        for x, y in zip(da.detections, db.detections):
            if x.type != y.type or not np.array_equal(x.points, y.points):
                return False
    return True


@pytest.mark.slow
def test_same_seed_identical_other_seed_differs(ramps):
    cfg = SimConfig(n_drives=6, **SHORT)
    a = simulate_fleet(ramps, config=cfg, seed=5)
    b = simulate_fleet(ramps, config=cfg, seed=5)
    c = simulate_fleet(ramps, config=cfg, seed=6)
    assert _same_fleet(a, b)
    assert not _same_fleet(a, c)


def test_drive_i_does_not_depend_on_the_number_of_drives(ramps):
    few = simulate_fleet(ramps, config=SimConfig(n_drives=3, **SHORT), seed=2)
    more = simulate_fleet(ramps, config=SimConfig(n_drives=6, **SHORT), seed=2)
    more.drives[:] = more.drives[:3]
    assert _same_fleet(few, more)


def _digest(fleet) -> str:
    """A fingerprint of everything a fleet reports (coordinates rounded to 1e-6 m, so that it
    does not hinge on the last bit of a float)."""
    h = hashlib.sha256()
    for d in fleet.drives:
        h.update(f"{d.drive_id}|{d.vehicle_id}|{len(d.xy)}|{len(d.detections)}".encode())
        h.update(np.asarray(d.stamps_ns, dtype="<i8").tobytes())
        h.update(np.round(np.asarray(d.xy, dtype=float), 6).astype("<f8").tobytes())
        h.update(np.round(np.asarray(d.yaw, dtype=float), 9).astype("<f8").tobytes())
        for det in d.detections:
            h.update(f"{int(det.type)}|{len(det.points)}".encode())
            h.update(np.round(np.asarray(det.points, dtype=float), 6).astype("<f8").tobytes())
    return h.hexdigest()[:16]


@pytest.mark.slow
def test_fleets_are_those_of_the_simulator_before_the_seen_count(ramps):
    # Computed with the simulator of commit a20e467, before it recorded what each drive saw:
    # recording it must not change a single draw (same drives, detections, time stamps).
    assert _digest(simulate_fleet(ramps, config=SimConfig(n_drives=6, **SHORT), seed=5)) == "93251ca3690b6925"
    town04 = load_map("carla_town04")
    assert _digest(simulate_fleet(town04, config=SimConfig(n_drives=5, **SHORT), seed=0)) == "368fe38e05a0e939"


# ---------------------------------------------------------------------------- drives


def test_drives_are_valid_with_metre_poses_and_plausible_stamps(ramps):
    cfg = SimConfig(n_drives=12, **SHORT)
    fleet = simulate_fleet(ramps, config=cfg, seed=1)
    assert fleet.origin == DEFAULT_ORIGIN
    assert len({d.drive_id for d in fleet.drives}) == 12
    starts = [d.start_ns for d in fleet.drives]
    assert starts == sorted(starts)
    for d in fleet.drives:
        validate_drive(d)
        truth = fleet.truth[d.drive_id]
        step = np.linalg.norm(np.diff(truth["true_xy"], axis=0), axis=1)
        assert np.median(step) == pytest.approx(1.0, abs=0.02)
        speed = step.sum() / ((d.stamps_ns[-1] - d.stamps_ns[0]) * 1e-9)
        assert cfg.speed_min_mps - 0.5 <= speed <= cfg.speed_max_mps + 0.5
        assert truth["length_m"] <= cfg.snippet_length_max_m + 2.0
        for det in d.detections:
            sp = np.linalg.norm(np.diff(det.points, axis=0), axis=1)
            assert sp.max() <= 2.0 + 0.5  # 1.5 m spacing plus noise


@pytest.mark.slow
def test_direction_bias_is_respected(ramps):
    cfg = SimConfig(n_drives=200, snippet_length_min_m=20.0, snippet_length_max_m=40.0, direction_bias=0.8)
    fleet = simulate_fleet(ramps, config=cfg, seed=3)
    share = np.mean([t["direction"] == 0 for t in fleet.truth.values()])
    assert share == pytest.approx(0.8, abs=0.08)
    dirs = route_directions(ramps)
    assert {dirs[t["route_id"]] for t in fleet.truth.values()} == {0, 1}


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_coverage_route_choice_drives_every_ramp(seed):
    # 12 ramp routes of ~1.3 km beside 6 through routes of 9 km: drawn by length, a 60-drive fleet
    # leaves some ramps undriven; the coverage choice puts drives on every one.
    gt = synthetic_highway("motorway_ramps", length_m=9000.0)
    ramps = [r.id for r in gt.routes if "exit" in r.id or "entry" in r.id]
    assert len(ramps) == 12

    def undriven(mode: str) -> int:
        cfg = SimConfig(
            n_drives=60,
            direction_bias=0.5,
            snippet_length_min_m=1000.0,
            snippet_length_max_m=3000.0,
            route_weighting=mode,
        )
        used = {t["route_id"] for t in simulate_fleet(gt, config=cfg, seed=seed).truth.values()}
        return sum(r not in used for r in ramps)

    assert undriven("length") >= 2
    assert undriven("coverage") == 0


@pytest.mark.slow
def test_coverage_route_choice_keeps_the_first_drives_when_the_fleet_grows(ramps):
    small = simulate_fleet(ramps, config=SimConfig(n_drives=5), seed=4)
    big = simulate_fleet(ramps, config=SimConfig(n_drives=9), seed=4)
    assert (len(small.drives), len(big.drives)) == (5, 9)
    for a, b in zip(small.drives, big.drives[:5]):
        assert a.drive_id == b.drive_id
        np.testing.assert_array_equal(a.xy, b.xy)


def test_route_directions_of_a_real_two_way_map():
    gt = load_map("esmini_e6mini")  # data/maps ships with the repository: no skip
    dirs = route_directions(gt)
    assert sorted(dirs.values()) == [0, 0, 0, 1, 1, 1]
    heads = {}
    for r in gt.routes:
        c = gt.route_centerline(r)
        heads[r.id] = (c[-1] - c[0]) / np.linalg.norm(c[-1] - c[0])
    for a in gt.routes:
        for b in gt.routes:
            same = dirs[a.id] == dirs[b.id]
            assert (np.dot(heads[a.id], heads[b.id]) > 0) == same


@pytest.mark.slow
def test_lane_changes_stay_on_existing_lanes(motorway):
    cfg = SimConfig.noise_free(
        n_drives=30, lane_change_rate_per_km=3.0, snippet_length_min_m=1000.0, snippet_length_max_m=1500.0
    )
    fleet = simulate_fleet(motorway, config=cfg, seed=4)
    assert sum(t["n_lane_changes"] for t in fleet.truth.values()) > 10
    routes = {r.id: motorway.route_centerline(r) for r in motorway.routes}
    for d in fleet.drives:
        t = fleet.truth[d.drive_id]
        lane_no = int(t["route_id"][-1])
        c = routes[t["route_id"]]
        tree = cKDTree(c)
        _, k = tree.query(t["true_xy"])
        tan = np.gradient(c, axis=0)[k]
        lat = np.sum((t["true_xy"] - c[k]) * np.stack([-tan[:, 1], tan[:, 0]], axis=1), axis=1) / np.linalg.norm(
            tan, axis=1
        )
        # Never left of lane 1 or right of lane 3; at most one lane away.
        assert lat.max() <= (0.05 if lane_no == 1 else 3.6)
        assert lat.min() >= (-0.05 if lane_no == 3 else -3.6)
        if t["n_lane_changes"]:
            assert np.abs(lat).max() > 3.3
            assert len(t["lane_sequence"]) > len(set(lane.split(":")[2] for lane in t["lane_sequence"][:1]))


# ---------------------------------------------------------------------------- localization error


def test_reported_minus_true_pose_is_the_recorded_error(ramps):
    fleet = simulate_fleet(ramps, config=SimConfig(n_drives=5, **SHORT), seed=7)
    assert len(fleet.drives) == 5
    for d in fleet.drives:
        t = fleet.truth[d.drive_id]
        delta = d.xy - t["true_xy"]
        np.testing.assert_allclose(np.sum(delta * _left(d.yaw), axis=1), t["lateral_error_m"], atol=1e-9)
        np.testing.assert_allclose(np.sum(delta * _head(d.yaw), axis=1), t["longitudinal_error_m"], atol=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("sigma", [0.5, 1.0])
def test_measured_lateral_offsets_have_the_configured_sigma(motorway, sigma):
    """Per-drive lateral offset measured from the reported trajectory against the GT lane."""
    cfg = SimConfig(
        n_drives=150,
        bias_lateral_sigma_m=sigma,
        lane_change_rate_per_km=0.0,
        snippet_length_min_m=150.0,
        snippet_length_max_m=250.0,
    )
    fleet = simulate_fleet(motorway, config=cfg, seed=11)
    routes = {r.id: motorway.route_centerline(r) for r in motorway.routes}
    est, rec = [], []
    for d in fleet.drives:
        t = fleet.truth[d.drive_id]
        c = routes[t["route_id"]]
        _, k = cKDTree(c).query(d.xy)
        k = np.clip(k, 1, len(c) - 2)
        tan = c[k + 1] - c[k - 1]
        tan /= np.linalg.norm(tan, axis=1, keepdims=True)
        lat = np.sum((d.xy - c[k]) * np.stack([-tan[:, 1], tan[:, 0]], axis=1), axis=1)
        est.append(np.median(lat))
        rec.append(t["lateral_error_mean_m"])
    est, rec = np.array(est), np.array(rec)
    expected = np.hypot(sigma, cfg.drift_sigma_m)  # bias plus (nearly constant over 250 m) drift
    assert np.std(est) == pytest.approx(expected, rel=0.2)
    assert np.std(est - rec) < 0.2  # only the in-lane wander separates them
    assert np.corrcoef(est, rec)[0, 1] > 0.95
    biases = np.array([t["bias_longitudinal_m"] for t in fleet.truth.values()])
    assert np.std(biases) == pytest.approx(cfg.bias_longitudinal_sigma_m, rel=0.15)


@pytest.mark.slow
def test_drift_has_the_configured_sigma_and_correlation(motorway):
    cfg = SimConfig(
        n_drives=50,
        bias_lateral_sigma_m=0.0,
        bias_longitudinal_sigma_m=0.0,
        snippet_length_min_m=1900.0,
        snippet_length_max_m=2000.0,
    )
    fleet = simulate_fleet(motorway, config=cfg, seed=12)
    errs = [t["lateral_error_m"] for t in fleet.truth.values()]
    pooled = np.concatenate(errs)
    assert np.std(pooled) == pytest.approx(cfg.drift_sigma_m, rel=0.3)
    lag = int(cfg.drift_corr_length_m)
    a = np.concatenate([e[:-lag] for e in errs if len(e) > lag + 100])
    b = np.concatenate([e[lag:] for e in errs if len(e) > lag + 100])
    assert np.corrcoef(a, b)[0, 1] == pytest.approx(np.exp(-1.0), abs=0.2)


# ---------------------------------------------------------------------------- detections


def test_noise_free_detections_lie_on_the_ground_truth(ramps):
    cfg = SimConfig.noise_free(n_drives=8, **SHORT)
    fleet = simulate_fleet(ramps, config=cfg, seed=3)
    lines = _gt_lines(ramps)
    n = 0
    for d in fleet.drives:
        np.testing.assert_allclose(d.xy, fleet.truth[d.drive_id]["true_xy"], atol=1e-12)
        for det in d.detections:
            dist = lines.distance(det.points, int(det.type))
            assert dist.max() < 1e-6
            n += len(det.points)
    assert n > 1000


def test_detections_are_in_driving_direction_and_only_of_the_ego_road(ramps):
    cfg = SimConfig.noise_free(n_drives=8, **SHORT)
    fleet = simulate_fleet(ramps, config=cfg, seed=3)
    feats = ramps.features
    pts = np.concatenate([f.points for f in feats])
    tan = np.concatenate([np.gradient(f.points, axis=0) for f in feats])
    ftype = np.concatenate([np.full(len(f.points), int(f.type)) for f in feats])
    tree = cKDTree(pts)
    opposite_barrier_seen = False
    for d in fleet.drives:
        pose_tree = cKDTree(d.xy)
        for det in d.detections:
            ddir = det.points[-1] - det.points[0]
            _, k = pose_tree.query(det.points.mean(axis=0))
            assert np.dot(ddir, _head(d.yaw[k : k + 1])[0]) > 0  # ordered like the drive
            _, j = tree.query(det.points[len(det.points) // 2])
            if np.dot(tan[j], ddir) < 0:  # a feature of the other carriageway: only its barrier
                assert ftype[j] == int(FeatureType.ROAD_BORDER)
                opposite_barrier_seen = True
    assert opposite_barrier_seen


def test_bias_moves_detections_with_the_trajectory(ramps):
    cfg = SimConfig.noise_free(n_drives=6, bias_lateral_sigma_m=1.0, bias_longitudinal_sigma_m=1.0, **SHORT)
    fleet = simulate_fleet(ramps, config=cfg, seed=9)
    lines = _gt_lines(ramps)
    assert len(fleet.drives) == 6 and all(d.detections for d in fleet.drives)
    for d in fleet.drives:
        t = fleet.truth[d.drive_id]
        assert abs(t["bias_lateral_m"]) + abs(t["bias_longitudinal_m"]) > 0
        pose_tree = cKDTree(d.xy)
        for det in d.detections:
            _, k = pose_tree.query(det.points)
            back = det.points - t["bias_lateral_m"] * _left(d.yaw[k]) - t["bias_longitudinal_m"] * _head(d.yaw[k])
            assert lines.distance(back, int(det.type)).max() < 0.01


def _detected_share(gt: GroundTruth, fleet, cfg: SimConfig) -> dict[str, float]:
    """Share of GT feature points beside the drives that some detection covers, per band."""
    feats = gt.features
    pts = np.concatenate([f.points for f in feats])
    tan = np.concatenate([np.gradient(f.points, axis=0) for f in feats])
    tan /= np.linalg.norm(tan, axis=1, keepdims=True)
    ftype = np.concatenate([np.full(len(f.points), int(f.type)) for f in feats])
    hit = {"ego": [], "next": [], "border": [], "opposite_barrier": []}
    for d in fleet.drives:
        true_xy = fleet.truth[d.drive_id]["true_xy"]
        dist, k = cKDTree(true_xy).query(pts, distance_upper_bound=cfg.border_max_lateral_m + 1.0)
        near = np.isfinite(dist)
        p, t, ft, k = pts[near], tan[near], ftype[near], k[near]
        v = p - true_xy[k]
        along = np.sum(v * _head(d.yaw[k]), axis=1)
        lat = np.sum(v * _left(d.yaw[k]), axis=1)
        beside = (np.abs(along) < 0.5) & (k > 0) & (k < len(true_xy) - 1)
        cos = np.sum(t * _head(d.yaw[k]), axis=1)
        # a GT vertex is covered when a detection polyline passes within 1 cm (chords of the
        # 1.5 m resampling cut curves by < 1 mm)
        covered = _Lines([x.points for x in d.detections], [0] * len(d.detections)).distance(p, k=4) < 0.01
        ftype_near = ft
        marking = ftype_near != int(FeatureType.ROAD_BORDER)
        same = beside & (cos > 0.9)
        groups = {
            "ego": same & marking & (np.abs(lat) <= cfg.ego_marking_max_lateral_m),
            "next": same
            & marking
            & (np.abs(lat) > cfg.ego_marking_max_lateral_m)
            & (np.abs(lat) <= cfg.next_marking_max_lateral_m),
            "border": same & ~marking & (np.abs(lat) <= cfg.border_max_lateral_m),
            # the nearest opposite border on the left is the other carriageway's median barrier
            "opposite_barrier": beside & (cos < -0.9) & ~marking & (lat > 0) & (lat <= cfg.border_max_lateral_m),
        }
        for key, sel in groups.items():
            hit[key].append(covered[sel])
    return {k: float(np.mean(np.concatenate(v))) for k, v in hit.items()}


@pytest.mark.slow
def test_visibility_rates_follow_the_config(motorway):
    cfg = SimConfig.noise_free(
        n_drives=50,
        snippet_length_min_m=600.0,
        snippet_length_max_m=1000.0,
        visibility_ego_marking=0.95,
        visibility_next_marking=0.70,
        visibility_border=0.60,
        # the opposite barrier's share depends on the lane mix (far lanes see it at the band
        # edge); "length" keeps the mix this test was tuned on (route choice is tested below)
        route_weighting="length",
    )
    fleet = simulate_fleet(motorway, config=cfg, seed=21)
    share = _detected_share(motorway, fleet, cfg)
    assert share["ego"] == pytest.approx(0.95, abs=0.04)
    assert share["next"] == pytest.approx(0.70, abs=0.1)
    assert share["border"] == pytest.approx(0.60, abs=0.1)
    assert share["opposite_barrier"] == pytest.approx(0.60, abs=0.15)


@pytest.mark.slow
def test_dropouts_are_gaps_of_the_configured_length(motorway):
    cfg = SimConfig.noise_free(
        n_drives=30, visibility_ego_marking=0.5, snippet_length_min_m=1500.0, snippet_length_max_m=1600.0
    )
    fleet = simulate_fleet(motorway, config=cfg, seed=8)
    gaps = []
    for d in fleet.drives:
        # consecutive detections of the same kind next to each other: the gap between them
        for a, b in zip(d.detections[:-1], d.detections[1:]):
            g = np.linalg.norm(b.points[0] - a.points[-1])
            if a.type == b.type and 0.0 < g < 400.0:
                ta = a.points[-1] - a.points[-2]
                if abs(np.dot(ta / np.linalg.norm(ta), (b.points[0] - a.points[-1]) / g)) > 0.99:
                    gaps.append(g)
    gaps = np.array(gaps)
    assert len(gaps) > 30
    assert np.percentile(gaps, 10) >= cfg.visibility_block_min_m - 1.0
    assert np.median(gaps) <= cfg.visibility_block_max_m


@pytest.mark.slow
def test_misclassification_rates(motorway):
    cfg = SimConfig.noise_free(
        n_drives=60,
        misclass_rate=0.075,
        marking_to_border_rate=0.02,
        snippet_length_min_m=800.0,
        snippet_length_max_m=1000.0,
    )
    fleet = simulate_fleet(motorway, config=cfg, seed=13)
    feats = motorway.features
    pts = np.concatenate([f.points for f in feats])
    ftype = np.concatenate([np.full(len(f.points), int(f.type)) for f in feats])
    tree = cKDTree(pts)
    swapped = to_border = total = 0
    for d in fleet.drives:
        for det in d.detections:
            _, j = tree.query(det.points)
            true = ftype[j]
            m = true != int(FeatureType.ROAD_BORDER)
            total += m.sum()
            swapped += np.sum(m & (true != int(det.type)) & (int(det.type) != int(FeatureType.ROAD_BORDER)))
            to_border += np.sum(m & (int(det.type) == int(FeatureType.ROAD_BORDER)))
    assert swapped / total == pytest.approx(0.075, abs=0.03)
    assert to_border / total == pytest.approx(0.02, abs=0.015)


@pytest.mark.slow
def test_false_positives_are_the_only_detections_off_the_ground_truth(ramps):
    cfg = SimConfig.noise_free(n_drives=20, false_positive_rate_per_km=5.0, **SHORT)
    fleet = simulate_fleet(ramps, config=cfg, seed=14)
    lines = _gt_lines(ramps)
    off = sum(1 for d in fleet.drives for det in d.detections if lines.distance(det.points).max() > 1e-6)
    expected = sum(t["n_false_positives"] for t in fleet.truth.values())
    assert off == expected
    km = sum(d.length_m for d in fleet.drives) / 1000.0
    assert abs(expected - 5.0 * km) < 4.0 * np.sqrt(5.0 * km)


def _gt_points(gt: GroundTruth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All GT feature points (P, 2), their unit tangents (P, 2) and types (P,), in feature order."""
    pts = np.concatenate([f.points for f in gt.features])
    tan = np.concatenate([np.gradient(f.points, axis=0) for f in gt.features])
    ftype = np.concatenate([np.full(len(f.points), int(f.type)) for f in gt.features])
    return pts, tan / np.linalg.norm(tan, axis=1, keepdims=True), ftype


def _seen(gt: GroundTruth, fleet) -> np.ndarray:
    return np.concatenate([fleet.seen_count[f.id] for f in gt.features])


def test_full_visibility_sees_every_point_within_the_bands_and_none_beyond(motorway):
    # Narrow marking bands, so that the lines two lanes away lie beyond the far band.
    cfg = SimConfig.noise_free(n_drives=1, next_marking_max_lateral_m=5.0, far_marking_max_lateral_m=6.5, **SHORT)
    pts, tan, ftype = _gt_points(motorway)
    h = cfg.visibility_edge_m / 2 + 0.05  # the visibility ramps across the band edges
    marking, border = ftype != int(FeatureType.ROAD_BORDER), ftype == int(FeatureType.ROAD_BORDER)
    n_checked: dict[str, int] = {}
    for seed in range(6):
        fleet = simulate_fleet(motorway, config=cfg, seed=seed)
        seen = _seen(motorway, fleet)
        d = fleet.drives[0]
        _, k = cKDTree(d.xy).query(pts)
        v = pts - d.xy[k]
        along, lat = np.sum(v * _head(d.yaw[k]), axis=1), np.sum(v * _left(d.yaw[k]), axis=1)
        cos = np.sum(tan * _head(d.yaw[k]), axis=1)
        beside = (np.abs(along) <= 0.5) & (k >= 2) & (k <= len(d.xy) - 3)
        same, opp = beside & (cos > 0.9), beside & (cos < -0.9)
        groups = {
            "markings within the far band": (same & marking & (np.abs(lat) < cfg.far_marking_max_lateral_m - h), 1),
            "markings beyond it": (same & marking & (np.abs(lat) > cfg.far_marking_max_lateral_m + h), 0),
            "borders within their band": (same & border & (np.abs(lat) < cfg.border_max_lateral_m - h), 1),
            "opposite barrier on the left": (opp & border & (lat > 0) & (lat < cfg.border_max_lateral_m - h), 1),
            "other opposite features": (opp & (marking | (lat < 0) | (lat > cfg.border_max_lateral_m + h)), 0),
            "far from the path": (np.linalg.norm(v, axis=1) > cfg.range_ahead_m + 15.0, 0),
        }
        for name, (sel, want) in groups.items():
            assert np.all(seen[sel] == want), (seed, name)
            n_checked[name] = n_checked.get(name, 0) + int(np.count_nonzero(sel))
        assert set(np.unique(seen)) == {0, 1}
    assert min(n_checked.values()) > 100, n_checked


@pytest.mark.slow
def test_seen_count_is_the_number_of_drives_whose_detections_cover_the_point(motorway):
    # Dropouts, and many stretches reported with the wrong type: a misclassified point was still
    # seen. Noise-free otherwise, so a seen point lies on a detection of each drive that saw it.
    cfg = SimConfig.noise_free(
        n_drives=5,
        visibility_next_marking=0.7,
        visibility_far_marking=0.3,
        visibility_border=0.6,
        misclass_rate=0.3,
        marking_to_border_rate=0.1,
        **SHORT,
    )
    fleet = simulate_fleet(motorway, config=cfg, seed=4)
    pts, _, ftype = _gt_points(motorway)
    covered = np.zeros(len(pts), dtype=int)
    wrong_type = 0  # points a drive reported only with a type other than their own
    for d in fleet.drives:
        lines = _Lines([x.points for x in d.detections], [int(x.type) for x in d.detections])
        on = lines.distance(pts, k=4) < 0.01
        covered += on
        wrong_type += int(np.count_nonzero(on & ~_covered_by_type(lines, pts, ftype)))
    np.testing.assert_array_equal(_seen(motorway, fleet), covered)
    assert covered.max() >= 2 and 0.05 < np.mean(covered > 0) < 0.95
    assert wrong_type > 1000


def _covered_by_type(lines: _Lines, pts: np.ndarray, ftype: np.ndarray) -> np.ndarray:
    """(P,) the point lies on a detection reported with the point's own type."""
    out = np.zeros(len(pts), dtype=bool)
    for t in np.unique(ftype):
        m = ftype == t
        if np.any(lines.type == t):
            out[m] = lines.distance(pts[m], int(t), k=4) < 0.01
    return out


def test_seen_counts_are_split_back_into_the_features(motorway):
    from dataclasses import replace

    from hdmap_core.groundtruth import GTFeature
    from hdmap_core.simulation.sensor import feature_index, seen_per_feature

    line = np.stack([np.arange(4.0), np.zeros(4)], axis=1)
    feats = (
        GTFeature(1, FeatureType.SOLID, line),
        GTFeature(2, FeatureType.DASHED, line[:1]),
        GTFeature(3, FeatureType.SOLID, line[:3] + 1),
        GTFeature(4, FeatureType.SOLID, line[:2] + 2),
        GTFeature(3, FeatureType.SOLID, line + 3),
    )
    gt = replace(motorway, features=feats)
    idx = feature_index(gt)  # indexes features 1, 3, 4, 3 (2 has a single point)
    got = seen_per_feature(gt, idx, np.arange(len(idx.xy)))
    assert set(got) == {1, 2, 4}  # id 3 is not unique
    assert got[1].tolist() == [0, 1, 2, 3] and got[2].tolist() == [0] and got[4].tolist() == [7, 8]


def test_pieces_too_short_to_report_are_not_seen(motorway):
    cfg = SimConfig.noise_free(n_drives=3, min_detection_length_m=5000.0, **SHORT)
    fleet = simulate_fleet(motorway, config=cfg, seed=0)
    assert sum(len(d.detections) for d in fleet.drives) == 0
    assert not _seen(motorway, fleet).any()


def test_measurement_noise_matches_sigma(motorway):
    cfg = SimConfig.noise_free(n_drives=10, noise_sigma_m=0.1, noise_growth_per_m=0.0, noise_corr_length_m=0.0, **SHORT)
    fleet = simulate_fleet(motorway, config=cfg, seed=15)
    lines = _gt_lines(motorway)
    d = np.concatenate([lines.distance(det.points, int(det.type)) for dr in fleet.drives for det in dr.detections])
    # |N(0, s)| has RMS s; a few points may snap to a neighbouring line, none within 3.5 m
    assert np.sqrt(np.mean(d**2)) == pytest.approx(0.1, rel=0.1)


# ---------------------------------------------------------------------------- maps, config, errors


SHARED = ["esmini_e6mini", "esmini_soderleden", "carla_town04", "carla_town06"]


@pytest.mark.parametrize("name", SHARED)
def test_runs_on_every_shared_map(name):
    gt = load_map(name)
    fleet = simulate_fleet(gt, config=SimConfig(n_drives=6, **SHORT), seed=0)
    assert len(fleet.drives) == 6
    for d in fleet.drives:
        validate_drive(d)
    assert sum(len(d.detections) for d in fleet.drives) > 0
    json.dumps(fleet_to_dict(fleet))
    assert {f.id: len(f.points) for f in gt.features} == {i: len(n) for i, n in fleet.seen_count.items()}
    counts = np.concatenate(list(fleet.seen_count.values()))
    assert 0 < np.count_nonzero(counts) < len(counts) and counts.max() <= 6


def test_fleet_json_document(ramps):
    fleet = simulate_fleet(ramps, config=SimConfig(n_drives=2, **SHORT), seed=0)
    doc = json.loads(json.dumps(fleet_to_dict(fleet, include_trajectories=True)))
    assert doc["config"]["bias_lateral_sigma_m"] == 1.0
    one = doc["truth"][fleet.drives[0].drive_id]
    assert one["bias_lateral_m"] == pytest.approx(fleet.truth[fleet.drives[0].drive_id]["bias_lateral_m"])
    assert len(one["true_xy"]) == len(fleet.drives[0].xy)
    assert "true_xy" not in json.loads(json.dumps(fleet_to_dict(fleet)))["truth"][fleet.drives[0].drive_id]
    assert {int(k): decode_runs(v).tolist() for k, v in doc["seen_count"].items()} == {
        k: v.tolist() for k, v in fleet.seen_count.items()
    }


def test_sim_json_file_is_the_fleet_document(ramps, tmp_path):
    fleet = simulate_fleet(ramps, config=SimConfig(n_drives=3, **SHORT), seed=0)
    write_sim_json(fleet, tmp_path / "f.sim.json")
    text = (tmp_path / "f.sim.json").read_text()
    assert json.loads(text) == json.loads(json.dumps(fleet_to_dict(fleet)))
    # one line per feature's run-length code, not one per number
    assert text.count("\n") < 200 + len(ramps.features)


def test_run_length_code_round_trips_and_rejects_garbage():
    v = np.array([0, 0, 0, 2, 2, 1, 0, 0])
    assert encode_runs(v) == [0, 3, 2, 2, 1, 1, 0, 2]
    np.testing.assert_array_equal(decode_runs(encode_runs(v)), v)
    assert encode_runs(np.zeros(0, dtype=int)) == [] and len(decode_runs([])) == 0
    for bad in ([1, 2, 3], [1, 0], [1.5, 2], ["a", 1]):
        with pytest.raises(ValueError):
            decode_runs(bad)


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"bias_lateral_sigma_m": -1.0}, "bias_lateral_sigma_m"),
        ({"visibility_border": 1.5}, "visibility_border"),
        ({"snippet_length_min_m": 900.0, "snippet_length_max_m": 100.0}, "snippet_length_min_m"),
        ({"route_weighting": "random"}, "route_weighting"),
        ({"no_such_knob": 1}, "no_such_knob"),
        ({"n_drives": "many"}, "n_drives"),
    ],
)
def test_bad_config_raises_config_error(overrides, match):
    with pytest.raises(ConfigError, match=match):
        SimConfig.from_dict(overrides)


def test_config_parses_strings():
    cfg = SimConfig.from_dict({"n_drives": "12", "opposite_barrier": "false", "noise_sigma_m": "0.2"})
    assert (cfg.n_drives, cfg.opposite_barrier, cfg.noise_sigma_m) == (12, False, 0.2)


def test_bad_seed_and_empty_map(ramps):
    with pytest.raises(ConfigError, match="seed"):
        simulate_fleet(ramps, config=SimConfig(n_drives=1), seed=-1)
    empty = GroundTruth("empty", (), {}, ())
    with pytest.raises(NoUsableDataError, match="empty"):
        simulate_fleet(empty, config=SimConfig(n_drives=1))
    with pytest.raises(GroundTruthError, match="GroundTruth"):
        simulate_fleet({"features": []}, config=SimConfig(n_drives=1))
    with pytest.raises(ConfigError, match="SimConfig"):
        simulate_fleet(ramps, config={"n_drives": 1})


@pytest.mark.slow
def test_paper_sized_fleet(ramps):
    """134 drives of 100-335 m: the paper's drive count over about 30 km. Its CPU time is printed
    (a figure, not a timed assertion)."""
    import time

    cfg = SimConfig(snippet_length_min_m=100.0, snippet_length_max_m=335.0)
    t0 = time.process_time()
    fleet = simulate_fleet(ramps, config=cfg, seed=0)
    print(f"134 drives simulated in {time.process_time() - t0:.2f} s CPU")
    assert len(fleet.drives) == 134
    assert 25.0 < fleet.summary()["km"] < 35.0


def test_load_map_by_name_and_path(tmp_path):
    from hdmap_core.groundtruth import save_ground_truth

    gt = load_map("lane_drop", length_m=1200.0)
    assert gt.name == "lane_drop"
    save_ground_truth(gt, tmp_path / "x.gt.json")
    assert set(load_map(str(tmp_path / "x.gt.json")).lanes) == set(gt.lanes)
    with pytest.raises(GroundTruthError, match="no map 'autobahn'"):
        load_map("autobahn")


def test_every_parameter_is_documented_with_its_default():
    from dataclasses import fields
    from pathlib import Path

    doc = Path(__file__).resolve().parents[3] / "docs" / "simulator.md"
    text = doc.read_text()
    default = SimConfig()
    missing = [f.name for f in fields(SimConfig) if f"| `{f.name}` | `{getattr(default, f.name)!r}` |" not in text]
    assert missing == []
