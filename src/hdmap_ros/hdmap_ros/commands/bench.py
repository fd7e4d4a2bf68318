"""``hdmap bench``: the pipeline presets side by side on the same fleet bags, scored and timed.

Each scenario is a fleet bag with its ground truth: either an existing bag (``BAG`` with
``BAG.gt.json`` beside it, as ``hdmap simulate`` writes) or ``MAP:DRIVES[:SEEDS]``, simulated here
with the simulator's default configuration (e.g. ``motorway_ramps:134``, the paper-like scenario).
SEEDS is one seed, a range ``1-8`` or a list ``1,4,7``: one fleet per seed, and a second table
with each figure's mean over the seeds (one fleet can be unlucky: its drives' errors need not
average out, see the realized floor in docs/evaluation.md).
``--set KEY=VALUE`` changes a parameter of every preset run (as ``hdmap bag2map --set``); those
rows are named ``default+`` etc., and the JSON keeps the changes under ``overrides``.
Every (scenario, preset) run happens in a fresh process, one after the other, so that wall time
and peak memory (peak RSS of that process: imports, bag reading, map building and evaluation) are
its own. The table has the evaluator's figures (``hdmap_core.evaluation.evaluate``), the floor
sigma_loc / sqrt(drives), and from the simulator's truth (``BAG.sim.json``) the realized floor, the
share of the ground truth the fleet observed and recall over it; build time and peak RSS.
``--changes``: instead, the map-updating benchmark (``hdmap_ros.commands.bench_changes``; its
options ``--change-*``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hdmap_core.errors import ConfigError
from hdmap_core.simulation.scenarios import NAMED_SCENARIOS
from hdmap_ros.commands import bench_changes
from hdmap_ros.commands.bag2map import add_set_argument

if TYPE_CHECKING:  # the pipeline is heavy: loaded on use
    from collections.abc import Sequence

    import numpy as np

    from hdmap_core.pipeline.config import PipelineConfig

__all__ = [
    "NAME",
    "HELP",
    "add_arguments",
    "run",
    "Scenario",
    "build_and_evaluate",
    "run_one",
    "format_table",
    "summarize_seeds",
    "SCORE_COLUMNS",
    "score_line",
    "format_scale",
]

NAME = "bench"
HELP = "compare the pipeline presets on the same fleet bags: evaluator figures, floor, time, peak memory"
PRESETS = ("default", "paper", "naive")
DEFAULT_SCENARIOS = ("paper_like",)

# (key, header, format) of the table columns; values missing or NaN print as "-".
COLUMNS = (
    ("scenario", "scenario", "{}"),
    ("preset", "preset", "{}"),
    ("drives", "drives", "{:d}"),
    ("drive_km", "drive km", "{:.1f}"),
    ("mean_m", "mean m", "{:.3f}"),
    ("p95_m", "p95 m", "{:.3f}"),
    ("corrected_mean_m", "corr. mean m", "{:.3f}"),
    ("floor_m", "floor m", "{:.3f}"),
    ("mean_over_floor", "mean/floor", "{:.2f}"),
    ("fleet_floor_m", "fleet err m", "{:.3f}"),
    ("drives_per_cut", "drives/cut med.", "{:.0f}"),
    ("sparse_share", "< 5 drives", "{:.0%}"),
    ("coverage", "coverage", "{:.1%}"),
    ("driven_share", "driven", "{:.1%}"),
    ("coverage_driven", "cov. driven", "{:.1%}"),
    ("recall", "recall", "{:.1%}"),
    ("observed_share", "observed", "{:.1%}"),
    ("recall_observed", "recall obs.", "{:.1%}"),
    ("precision", "precision", "{:.1%}"),
    ("type_accuracy", "type acc.", "{:.1%}"),
    ("fragmentation", "fragm.", "{:.2f}"),
    ("splits_merges", "splits/merges found", "{}"),
    ("road_splits_merges", "road splits/merges", "{}"),
    ("long_links", "topo link prec. (long)", "{}"),
    ("lane_coverage", "lane cov.", "{:.1%}"),
    ("lane_precision", "lane prec.", "{:.1%}"),
    ("lane_error_m", "lane err m", "{:.3f}"),
    ("lane_count_accuracy", "lane count", "{:.1%}"),
    ("routes", "routes", "{}"),
    ("build_s", "build s", "{:.1f}"),
    ("lanes_s", "lanes s", "{:.2f}"),
    ("peak_rss_mb", "peak RSS MB", "{:.0f}"),
)

# The table over seeds: the mean over the seeds of each of these figures (formats as in COLUMNS) ...
_SEED_MEANS = (
    "drives",
    "mean_m",
    "corrected_mean_m",
    "floor_m",
    "fleet_floor_m",
    "sparse_share",
    "coverage",
    "driven_share",
    "coverage_driven",
    "recall",
    "observed_share",
    "recall_observed",
    "precision",
    "type_accuracy",
    "fragmentation",
    "build_s",
)
# ... and ratios of those means, the worst seed's ratio, the seeds.
_SEED_EXTRA = {
    "seeds": ("seeds", "seeds", "{}"),
    "drives": ("drives", "drives", "{:.0f}"),
    "mean_over_floor_max": ("mean_over_floor_max", "max seed mean/floor", "{:.2f}"),
    "mean_over_fleet": ("mean_over_fleet", "mean/fleet err", "{:.2f}"),
}
_SEED_ORDER = (
    "scenario",
    "preset",
    "seeds",
    "drives",
    "mean_m",
    "corrected_mean_m",
    "floor_m",
    "mean_over_floor",
    "mean_over_floor_max",
    "fleet_floor_m",
    "mean_over_fleet",
    "sparse_share",
    "coverage",
    "driven_share",
    "coverage_driven",
    "recall",
    "observed_share",
    "recall_observed",
    "precision",
    "type_accuracy",
    "fragmentation",
    "build_s",
)
SEED_COLUMNS = tuple(_SEED_EXTRA.get(k) or next(c for c in COLUMNS if c[0] == k) for k in _SEED_ORDER)


@dataclass(frozen=True)
class Scenario:
    """One fleet bag to benchmark on.

    Attributes:
        name: label in the table.
        bag: fleet bag path.
        gt_path: ground truth (.gt.json).
        sigma_loc_m: localization sigma for the floor (None: the evaluator's default).
    """

    name: str
    bag: str
    gt_path: str
    sigma_loc_m: float | None = None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "scenarios",
        nargs="*",
        metavar="SCENARIO",
        help="fleet bag (with BAG.gt.json beside it), MAP:DRIVES[:SEEDS] to simulate, or a named "
        "scenario NAME[:DRIVES[:SEEDS]] (paper_like); SEEDS: 1, 1-8 or 1,4,7 (several: also a "
        "table of the means over the seeds) "
        f"(default: {' '.join(DEFAULT_SCENARIOS)})",
    )
    parser.add_argument(
        "--presets", default=",".join(PRESETS), help="comma-separated presets to run (default: %(default)s)"
    )
    parser.add_argument(
        "--scale",
        type=float,
        action="append",
        metavar="F",
        help="multiply the drive count of simulated scenarios (repeatable, e.g. --scale 0.25 --scale 1 --scale 4)",
    )
    add_set_argument(
        parser,
        "change one parameter of every preset run (repeatable), as hdmap bag2map --set; "
        "the rows are named default+ etc. (e.g. --presets default --set alignment.robust_loss=false)",
    )
    parser.add_argument("--seed", type=int, default=0, help="pipeline seed (default: %(default)s)")
    parser.add_argument("--work-dir", metavar="DIR", help="keep simulated bags here (default: a temporary dir)")
    parser.add_argument("--json", metavar="FILE", help="write every run's figures as JSON")
    parser.add_argument("--markdown", metavar="FILE", help="write the table as Markdown")
    parser.add_argument("--inline", action="store_true", help="run in this process (peak RSS then not per run)")
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="processes per build, as hdmap bag2map --workers (default: the CPUs available)",
    )
    parser.add_argument(
        "--tiled",
        action="store_true",
        help="build as hdmap bag2map --tiled (tile index on disk, tiles on a Dask LocalCluster of --workers "
        "processes); a second table: build time, drive-km per second per worker, peak RSS of each process",
    )
    parser.add_argument(
        "--changes",
        action="store_true",
        help="instead: the map-updating benchmark (drives needed to follow each kind of road change, the "
        "changed zone after 3 / 5 / 10 drives, false changes on fleets without one; --presets for the "
        "no-change fleets; the --change-* options)",
    )
    bench_changes.add_arguments(parser, prefix="change-")


def _presets(text: str) -> list[str]:
    names = [p.strip() for p in text.split(",") if p.strip()]
    unknown = [p for p in names if p not in PRESETS]
    if not names or unknown:
        raise ConfigError(f"--presets {text!r}: choose from {', '.join(PRESETS)}")
    return names


def _sigma_from_config(config: Any) -> float:
    # The lateral error of a drive at one place: constant bias plus slow drift (independent).
    return math.hypot(config.bias_lateral_sigma_m, config.drift_sigma_m)


def prepare_scenarios(specs: list[str], *, scales: list[float], work_dir: Path) -> list[Scenario]:
    """Resolve scenario specs; ``MAP:DRIVES[:SEED]`` specs are simulated into ``work_dir``."""
    from hdmap_ros.commands.evaluate import sigma_from_sim_json  # noqa: PLC0415

    out = []
    for spec in specs:
        path = Path(spec)
        if path.exists():
            gt = path.with_name(path.name + ".gt.json")
            if not gt.exists():
                raise ConfigError(f"scenario {spec}: no ground truth {gt} beside the bag")
            sim = path.with_name(path.name + ".sim.json")
            sigma = sigma_from_sim_json(sim) if sim.exists() else None
            out.append(Scenario(path.name, str(path), str(gt), sigma))
            continue
        name, drives, seeds, named = _parse_simulated(spec)
        map_name, kw = name, {}
        if named is not None:
            map_name, kw = named["map"], {"label": name, "length_m": named["length_m"], "sim": named["sim"]}
        out.extend(
            _simulate(map_name, max(1, round(drives * s)), seed, work_dir, **kw) for s in scales for seed in seeds
        )
    return out


def _parse_simulated(spec: str) -> tuple[str, int, list[int], dict[str, Any] | None]:
    """``MAP:DRIVES[:SEEDS]`` or ``NAME[:DRIVES[:SEEDS]]`` of a named scenario -> (map or scenario
    name, drives, seeds, the named scenario or None); SEEDS is ``3``, ``1-8`` or ``1,4,7``."""
    parts = spec.split(":")
    named = NAMED_SCENARIOS.get(parts[0])
    if len(parts) > 3 or (named is None and len(parts) < 2):
        raise ConfigError(f"scenario {spec!r}: neither an existing bag nor MAP:DRIVES[:SEEDS]")
    try:
        drives = int(parts[1]) if len(parts) > 1 and parts[1] else named["drives"]
        seeds = _parse_seeds(parts[2]) if len(parts) > 2 else [0]
    except ValueError:
        raise ConfigError(f"scenario {spec!r}: DRIVES and SEEDS must be integers (SEEDS: 3, 1-8 or 1,4,7)") from None
    if any(x < 0 for x in seeds) or len(set(seeds)) != len(seeds):
        raise ConfigError(f"scenario {spec!r}: seeds must be distinct and >= 0")
    if drives < 1:  # a fleet of none was silently made one drive (and named so)
        raise ConfigError(f"scenario {spec!r}: DRIVES must be >= 1, got {drives}")
    return parts[0], drives, seeds, named


def _parse_seeds(text: str) -> list[int]:
    if "-" in text.strip("-"):
        lo, hi = (int(x) for x in text.split("-"))
        if hi < lo:
            raise ValueError(text)
        return list(range(lo, hi + 1))
    return [int(x) for x in text.split(",")]


def _simulate(
    map_name: str,
    n_drives: int,
    seed: int,
    work_dir: Path,
    *,
    label: str | None = None,
    length_m: float | None = None,
    sim: dict[str, Any] | None = None,
) -> Scenario:
    from hdmap_core.groundtruth import save_ground_truth  # noqa: PLC0415
    from hdmap_core.simulation.fleet import SimConfig, load_map, simulate_fleet, write_sim_json  # noqa: PLC0415
    from hdmap_ros.io.bagio import write_fleet_bag  # noqa: PLC0415

    name = f"{label or map_name}_{n_drives}_s{seed}"
    bag = work_dir / name
    config = SimConfig.from_dict({**(sim or {}), "n_drives": n_drives})
    gt = load_map(map_name, length_m=length_m)
    gt_path = bag.with_name(bag.name + ".gt.json")
    if not _cached(bag, gt_path, config, seed):
        fleet = simulate_fleet(gt, config=config, seed=seed)
        write_fleet_bag(bag, fleet.drives, fleet.origin, overwrite=True)
        save_ground_truth(gt, gt_path)
        write_sim_json(fleet, bag.with_name(bag.name + ".sim.json"))
    return Scenario(name, str(bag), str(gt_path), _sigma_from_config(config))


def _cached(bag: Path, gt_path: Path, config: Any, seed: int) -> bool:
    """A bag simulated earlier into the work dir is reused only when its ``.sim.json`` says it was
    made with this very simulator config and seed (a changed scenario or simulator default, e.g.
    the route choice, simulates it anew instead of silently reusing a stale fleet) by this very
    simulator code (``simulator_fingerprint``: fleets of an older simulator moved `paper`'s
    figures by up to 0.1 points), and only when it has the seen counts."""
    sim_path = bag.with_name(bag.name + ".sim.json")
    if not ((bag / "metadata.yaml").exists() and gt_path.exists() and sim_path.exists()):
        return False
    try:
        doc = json.loads(sim_path.read_text())
    except (OSError, ValueError):
        return False
    from hdmap_core.simulation.fleet import simulator_fingerprint  # noqa: PLC0415

    same = (
        doc.get("seed") == seed
        and doc.get("config") == json.loads(json.dumps(config.to_dict()))
        and doc.get("simulator") == simulator_fingerprint()
    )
    return same and isinstance(doc.get("seen_count"), dict)


# One line per map for the measurement scripts (scripts/compare_fleets.py, restitch_state.py):
# mean and offset-corrected mean lateral error [m], coverage, recall, observed share, recall over
# the observed points, precision [%], fragmentation, road splits,merges found/in GT, long
# topology links supported/evaluable, build time [s].
SCORE_COLUMNS = "scenario mean cor cov rec obs recobs prec frag roadsm long build"


def score_line(name: str, report: Any, build_s: float) -> str:
    """One line of ``SCORE_COLUMNS`` for an ``EvalReport``."""
    o = report.overall
    return (
        f"{name} {o.mean_m:.4f} {o.corrected_mean_m:.4f} {100 * report.coverage:.2f} {100 * o.recall:.2f} "
        f"{100 * report.observed_share:.2f} {100 * report.recall_observed:.2f} {100 * o.precision:.2f} "
        f"{report.fragmentation_mean:.3f} {report.found_road_splits}/{report.gt_road_splits},"
        f"{report.found_road_merges}/{report.gt_road_merges} "
        f"{report.n_long_links_supported}/{report.n_long_links_evaluable} {build_s:.1f}"
    )


def build_and_evaluate(
    scenario: Scenario, config: Any, seed: int, workers: int | None = None, *, tiled: bool = False
) -> tuple[Any, ...]:
    """Read the scenario's bag, build the map with ``config`` (a ``PipelineConfig``), evaluate it
    against its ground truth (with the simulator truth of ``BAG.sim.json`` when there is one).
    ``tiled``: build as ``bag2map --tiled`` (``hdmap_ros.tiled.build_from_bag``), before the
    fleet is read for the evaluation, so that the build's peak RSS is its own.

    Returns:
        (fleet, build result, evaluation report, build seconds, worker processes used);
        ``workers`` None: the CPUs available.
    """
    from hdmap_core.evaluation.evaluate import evaluate_map  # noqa: PLC0415
    from hdmap_core.groundtruth import load_ground_truth  # noqa: PLC0415
    from hdmap_core.parallel import available_cpus  # noqa: PLC0415
    from hdmap_core.pipeline import driver as pipeline  # noqa: PLC0415
    from hdmap_ros.commands.evaluate import drive_errors_from_sim_json, seen_counts_from_sim_json  # noqa: PLC0415
    from hdmap_ros.io.bagio import read_fleet_bag  # noqa: PLC0415

    n_workers = workers or available_cpus()
    if tiled:
        from hdmap_core.live.tiles import TileConfig  # noqa: PLC0415
        from hdmap_ros.commands.bag2map import TILE_DEFAULTS  # noqa: PLC0415
        from hdmap_ros.tiled import build_from_bag  # noqa: PLC0415

        t0 = time.perf_counter()
        result = build_from_bag(
            scenario.bag, config=config, tile_config=TileConfig(**TILE_DEFAULTS, seed=seed), workers=n_workers
        )
        build_s = time.perf_counter() - t0
        fleet = read_fleet_bag(scenario.bag)
    else:
        fleet = read_fleet_bag(scenario.bag)
        t0 = time.perf_counter()
        result = pipeline.build_map(fleet.drives, config=config, seed=seed, workers=n_workers)
        build_s = time.perf_counter() - t0
    sim = Path(scenario.bag).with_name(Path(scenario.bag).name + ".sim.json")
    hdmap = result.result.map if tiled else result.map
    rep = evaluate_map(
        hdmap,
        load_ground_truth(scenario.gt_path),
        drives=fleet.drives,
        sigma_loc_m=scenario.sigma_loc_m,
        drive_errors=drive_errors_from_sim_json(sim) if sim.exists() else None,
        seen_counts=seen_counts_from_sim_json(sim) if sim.exists() else None,
    )
    return fleet, result, rep, build_s, n_workers


def _lane_figures(
    scenario: Scenario, hdmap: Any, trajectories: Sequence[np.ndarray] = ()
) -> tuple[dict[str, Any], float]:
    """The lane metrics of the map (``evaluation/lanes.py``; routes: those in ``BAG.sim.json``)
    as row fields, and the seconds the lanes took to derive. The lanes are those of the exports
    (``bag2map --lanelet2``): with the connectors of the drives' ``trajectories``
    (``lanes/connectors.py``) and drive-path lanes (``lanes/drivepath.py``) where the line map has no lane."""
    from hdmap_core.evaluation.lanes import evaluate_lanes  # noqa: PLC0415
    from hdmap_core.groundtruth import load_ground_truth  # noqa: PLC0415
    from hdmap_core.lanes.derive import derive_lanes  # noqa: PLC0415
    from hdmap_core.lanes.drivepath import trajectory_lanes  # noqa: PLC0415

    t0 = time.perf_counter()
    lanes = derive_lanes(hdmap)
    if len(trajectories):
        lanes = trajectory_lanes(lanes, trajectories)
    seconds = time.perf_counter() - t0
    sim = Path(scenario.bag).with_name(Path(scenario.bag).name + ".sim.json")
    routes = None
    if sim.exists():
        truth = json.loads(sim.read_text()).get("truth") or {}
        routes = {str(t.get("route_id")) for t in truth.values() if isinstance(t, dict)}
    rep = evaluate_lanes(lanes, load_ground_truth(scenario.gt_path), route_ids=routes)
    return {
        "lane_coverage": rep.coverage,
        "lane_precision": rep.precision,
        "lane_error_m": rep.mean_error_m,
        "lane_count_accuracy": rep.lane_count_accuracy,
        "routes": f"{rep.routes_routable}/{rep.routes}",
        "route_reachability": rep.route_reachability,
        "n_lanes": rep.n_lanes,
    }, seconds


def preset_config(preset: str, overrides: dict[str, Any] | None = None) -> PipelineConfig:
    """``config_from(preset, overrides)`` (dotted keys).

    Raises:
        ConfigError: a change that does not fit this preset, naming the key."""
    from hdmap_core.pipeline.overrides import config_from  # noqa: PLC0415

    try:
        return config_from(preset, dict(overrides or {}))
    except ConfigError as err:
        raise ConfigError(f"--set {err}") from None


def _check_overrides(presets: list[str], overrides: dict[str, Any]) -> dict[str, Any]:
    """Each preset's config with ``overrides``. Raises ConfigError unless they fit every preset in
    ``presets``; when they fit some, the message names those, for ``--presets``."""
    configs, errors = {}, {}
    for preset in presets:
        try:
            configs[preset] = preset_config(preset, overrides)
        except ConfigError as err:
            errors[preset] = err
    if not errors:
        return configs
    fits = [p for p in presets if p not in errors]
    first = next(iter(errors))
    if fits:
        raise ConfigError(
            f"{errors[first]} (preset {first}); it fits {', '.join(fits)}: choose the presets with --presets"
        )
    raise errors[first]


def run_one(
    scenario: Scenario,
    preset: str,
    seed: int,
    workers: int | None = None,
    overrides: dict[str, Any] | None = None,
    tiled: bool = False,
) -> dict[str, Any]:
    """Read the bag, build the map with ``preset`` (changed by ``overrides``), evaluate it;
    figures as a flat dict.

    ``workers``: processes for the build (None: the CPUs available). The peak RSS is this
    process's plus its largest worker's (an upper bound: pages they share count twice).
    ``tiled``: the tiled build; ``peak_rss_mb`` is then the largest process's of the build
    (before the evaluation), ``peak_rss_by_process`` each one's."""
    import resource  # noqa: PLC0415

    config = preset_config(preset, overrides)
    fleet, result, rep, build_s, n_workers = build_and_evaluate(scenario, config, seed, workers, tiled=tiled)
    scale: dict[str, Any] = {}
    if tiled:
        peaks = dict(result.result.report.peak_rss_mb)
        peaks["main"] = max(peaks.get("main", 0.0), result.index_peak_rss_mb)
        km = result.index.drive_km
        scale = {
            "tiled": True,
            "tiles": result.result.report.tiles,
            "index_s": result.index_seconds,
            "stage_seconds": dict(result.result.report.stage_seconds),
            "peak_rss_by_process": peaks,
            "cpu_by_process": dict(result.result.report.cpu_seconds),
            "km_per_s_worker": km / build_s / max(1, result.result.report.workers),
            "workers": result.result.report.workers,
            "peak_rss_mb": max(peaks.values()),
        }
        result = result.result
    o = rep.overall
    floor = rep.floor_mean_m
    lanes, lanes_s = _lane_figures(scenario, result.map, [d.xy for d in fleet.drives])
    return (
        {
            **lanes,
            "lanes_s": lanes_s,
            "scenario": scenario.name,
            "preset": config.name,
            "overrides": dict(overrides or {}),
            "drives": len(fleet.drives),
            "drive_km": sum(d.length_m for d in fleet.drives) / 1000.0,
            "mean_m": o.mean_m,
            "median_m": o.median_m,
            "p95_m": o.p95_m,
            "corrected_mean_m": o.corrected_mean_m,
            "floor_m": floor,
            "fleet_floor_m": rep.fleet_floor_mean_m,
            "mean_over_floor": _ratio(o.mean_m, floor),
            "drives_per_cut": rep.drive_count_median,
            "density_share": rep.density_share,
            "sparse_share": rep.sparse_share,
            "coverage": rep.coverage,
            "driven_share": rep.driven_share,
            "coverage_driven": rep.coverage_driven,
            "recall": o.recall,
            "observed_share": rep.observed_share,
            "recall_observed": rep.recall_observed,
            "recall_by_seen": [list(b) for b in rep.recall_by_seen],
            "precision": o.precision,
            "type_accuracy": rep.type_accuracy,
            "type_accuracy_corrected": rep.type_accuracy_corrected,
            "std_within_share": rep.std_within_share,
            "std_z_rms": rep.std_z_rms,
            "fragmentation": rep.fragmentation_mean,
            "splits_merges": f"{rep.found_splits}/{rep.gt_splits} {rep.found_merges}/{rep.gt_merges}",
            "gt_splits": rep.gt_splits,
            "gt_merges": rep.gt_merges,
            "found_splits": rep.found_splits,
            "found_merges": rep.found_merges,
            "road_splits_merges": (
                f"{rep.found_road_splits}/{rep.gt_road_splits} {rep.found_road_merges}/{rep.gt_road_merges}"
            ),
            "gt_road_splits": rep.gt_road_splits,
            "gt_road_merges": rep.gt_road_merges,
            "found_road_splits": rep.found_road_splits,
            "found_road_merges": rep.found_road_merges,
            # Long topology links (> link_long_m: the stitcher's) that the GT lane graph supports.
            "long_links": _link_cell(rep.long_link_precision, rep.n_long_links_supported, rep.n_long_links_evaluable),
            "long_link_precision": rep.long_link_precision,
            "n_long_links_evaluable": rep.n_long_links_evaluable,
            "n_long_links_supported": rep.n_long_links_supported,
            "topology_link_precision": rep.topology_link_precision,
            "false_long_links": [t.to_dict() for t in rep.false_topology_links if t.length_m > rep.config.link_long_m],
            "n_features": len(result.map.features),
            "build_s": build_s,
            "stage_seconds": dict(getattr(result.report, "stage_seconds", {}) or {}),
            "workers": n_workers,
            "peak_rss_mb": (
                resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
                + resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
            )
            / 1024.0,
        }
        | scale
        | ({"preset": f"{config.name} tiled"} if tiled else {})
    )


def _link_cell(precision: float, supported: int, evaluable: int) -> str:
    """``"97.1% 68/70"``: precision and counts of the long topology links ("-" when none is evaluable)."""
    return f"{precision:.1%} {supported}/{evaluable}" if evaluable else "-"


def _cell(value: Any, fmt: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    try:
        return fmt.format(value)
    except (ValueError, TypeError):
        return str(value)


def format_table(rows: list[dict[str, Any]], *, markdown: bool = False, columns: tuple = COLUMNS) -> str:
    """The runs as an aligned text table (or a Markdown table) of ``columns`` (key, header, format)."""
    header = [h for _, h, _ in columns]
    body = [[_cell(r.get(k), f) for k, _, f in columns] for r in rows]
    if markdown:
        lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
        return "\n".join(lines + ["| " + " | ".join(b) + " |" for b in body])
    widths = [max(len(x) for x in col) for col in zip(header, *body)]

    def fmt_row(cells: list[str]) -> str:
        return "  ".join(c.rjust(w) if i > 1 else c.ljust(w) for i, (c, w) in enumerate(zip(cells, widths)))

    return "\n".join([fmt_row(header), fmt_row(["-" * w for w in widths])] + [fmt_row(b) for b in body])


def run(args: argparse.Namespace) -> int:
    if args.changes:
        if args.scenarios:
            raise ConfigError("--changes simulates its own fleets: no SCENARIO with it")
        given = {k: getattr(args, k) for k in ("section", "smoke", "cases", "fleets", "seeds", "bags")}
        presets = None if args.presets == ",".join(PRESETS) else args.presets
        return bench_changes.run(
            argparse.Namespace(**given, presets=presets, preset="default", markdown=args.markdown, json=args.json)
        )
    presets = _presets(args.presets)
    scales = args.scale or [1.0]
    if any(s <= 0 for s in scales):
        raise ConfigError("--scale must be > 0")
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {args.workers}")
    overrides = dict(args.overrides)
    configs = _check_overrides(presets, overrides)  # before anything is simulated
    with tempfile.TemporaryDirectory(prefix="hdmap-bench-") as tmp:
        work_dir = Path(args.work_dir) if args.work_dir else Path(tmp)
        work_dir.mkdir(parents=True, exist_ok=True)
        scenarios = prepare_scenarios(list(args.scenarios) or list(DEFAULT_SCENARIOS), scales=scales, work_dir=work_dir)
        rows = []
        for sc in scenarios:
            for preset in presets:
                print(f"hdmap bench: {sc.name} / {configs[preset].name} ...", file=sys.stderr, flush=True)
                rows.append(
                    _run_isolated(
                        sc,
                        preset,
                        args.seed,
                        inline=args.inline,
                        workers=args.workers,
                        overrides=overrides,
                        tiled=args.tiled,
                    )
                )
    summary = summarize_seeds(rows)
    print(format_table(rows))
    if args.tiled:
        print("\nscale (tiled builds; peak RSS of the build, before the evaluation):\n" + format_scale(rows))
    if summary:
        print("\nmean over seeds:\n" + format_table(summary, columns=SEED_COLUMNS))
    if args.json:
        Path(args.json).write_text(json.dumps(rows + summary, indent=1, default=_json_default))
    if args.markdown:
        text = format_table(rows, markdown=True) + "\n"
        if summary:
            text += "\nMean over seeds:\n\n" + format_table(summary, columns=SEED_COLUMNS, markdown=True) + "\n"
        Path(args.markdown).write_text(text)
    return 0


def summarize_seeds(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Rows of one scenario simulated with several seeds (names ``..._s<seed>``), per preset:
    the mean of each figure over the seeds, ``mean_over_floor`` and ``mean_over_fleet`` as ratios
    of the means, ``mean_over_floor_max`` the worst seed's ratio. Marked ``"summary": True``;
    groups of one seed give no row."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in rows:
        base, sep, seed = str(r["scenario"]).rpartition("_s")
        if sep and seed.isdigit():
            groups.setdefault((base, str(r["preset"])), []).append(r)
    out = []
    for (base, preset), runs in groups.items():
        if len(runs) < 2:
            continue
        row: dict[str, Any] = {
            "scenario": base,
            "preset": preset,
            "summary": True,
            "seeds": ",".join(str(r["scenario"]).rpartition("_s")[2] for r in runs),
        }
        for key in _SEED_MEANS:
            vals = [float(r[key]) for r in runs if isinstance(r.get(key), (int, float)) and math.isfinite(r[key])]
            row[key] = sum(vals) / len(vals) if vals else math.nan
        row["mean_over_floor"] = _ratio(row["mean_m"], row["floor_m"])
        row["mean_over_fleet"] = _ratio(row["mean_m"], row["fleet_floor_m"])
        ratios = [_ratio(r.get("mean_m"), r.get("floor_m")) for r in runs]
        row["mean_over_floor_max"] = max((x for x in ratios if math.isfinite(x)), default=math.nan)
        out.append(row)
    return out


def _ratio(a: Any, b: Any) -> float:
    ok = all(isinstance(x, (int, float)) and math.isfinite(x) for x in (a, b))
    return float(a) / float(b) if ok and b > 0 else math.nan


def _json_default(value: Any) -> Any:
    return None if isinstance(value, float) and not math.isfinite(value) else str(value)


def format_scale(rows: list[dict[str, Any]]) -> str:
    """The tiled rows' build time, drive-km per second per worker and peak RSS of each process."""
    lines = []
    for r in rows:
        if not r.get("tiled"):
            continue
        peaks = r.get("peak_rss_by_process", {})
        workers = [v for k, v in peaks.items() if k.startswith("worker")]
        lines.append(
            f"  {r['scenario']} / {r['preset']}: {r['drives']} drives, {r['drive_km']:.1f} drive-km, "
            f"{r['tiles']} tiles, "
            f"{r['workers']} worker(s): build {r['build_s']:.1f} s (index {r['index_s']:.1f} s), "
            f"{r['km_per_s_worker']:.2f} drive-km/s per worker; peak RSS MB main {peaks.get('main', math.nan):.0f}"
            + (f", scheduler {peaks['scheduler']:.0f}" if "scheduler" in peaks else "")
            + (", workers " + " ".join(f"{v:.0f}" for v in workers) if workers else "")
            + "; CPU s "
            + " ".join(f"{v:.1f}" for v in r.get("cpu_by_process", {}).values())
        )
    return "\n".join(lines)


def _run_isolated(
    scenario: Scenario,
    preset: str,
    seed: int,
    *,
    inline: bool,
    workers: int | None = None,
    overrides: dict[str, Any] | None = None,
    tiled: bool = False,
) -> dict[str, Any]:
    if inline:
        return run_one(scenario, preset, seed, workers, overrides, tiled)
    # A fresh process per run: its peak RSS and time are this run's alone.
    with ProcessPoolExecutor(max_workers=1, mp_context=get_context("spawn"), max_tasks_per_child=1) as pool:
        return pool.submit(run_one, scenario, preset, seed, workers, overrides, tiled).result()
