"""Tests of the pipeline driver (pipeline.py): presets, processed stretches, bad input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hdmap_core.errors import ConfigError, NoUsableDataError
from hdmap_core.model import Detection, Drive, FeatureType, HDMap
from hdmap_core.pipeline import presets
from hdmap_core.pipeline.aggregation import ProcessedStore
from hdmap_core.pipeline.config import FinalSampling, PipelineConfig
from hdmap_core.pipeline.driver import build_map, map_segments, map_stretches, prepare_drives
from hdmap_core.pipeline.sampling import SamplingConfig, pivot_walk
from hdmap_core.steps import Segment

from pipeline_fleet import LINES, RADIUS_M, make_drive, make_fleet

BIASES = [0.8, -0.5, 0.3, -1.1, 0.6, 0.0, -0.4]


@pytest.fixture(scope="module")
def fleet() -> list[Drive]:
    return make_fleet(BIASES, noise_m=0.03, s1=200.0)


@pytest.fixture(scope="module")
def run(fleet):
    """``run(preset) -> (map_stretches(fleet, preset, seed=0), progress calls)``, computed once per
    module: several tests read the same run (collecting the observations and recording the progress
    calls leave the result as it is)."""
    cache: dict[str, tuple] = {}

    def get(preset: str) -> tuple:
        if preset not in cache:
            calls: list[tuple] = []
            res = map_stretches(
                fleet,
                config=presets.preset(preset),
                seed=0,
                collect_observations=True,
                progress=lambda *a: calls.append(a),
            )
            cache[preset] = (res, calls)
        return cache[preset]

    return get


def _bad_drive() -> Drive:
    xy = np.array([[0.0, 0.0], [np.nan, 1.0], [2.0, 0.0]])
    return Drive("broken", xy, np.zeros(3), np.arange(3, dtype=np.int64), ())


@pytest.mark.parametrize("preset", ["paper", "default", "naive"])
def test_map_segments_recovers_lines(fleet, run, preset):
    segs = run(preset)[0].segments
    assert len(segs) == len(fleet) and all(isinstance(s, Segment) for s in segs)
    valid = [st for seg in segs for st in seg.steps if st.valid]
    assert len(valid) > 80
    truth = np.array(sorted(lat for lat, _ in LINES))
    n_exact = 0
    for st in valid:
        # Lateral positions relative to the road centre (the pivot's cut midpoint is not on it).
        if len(st.lateral_m) == len(truth):
            n_exact += 1
            rel = st.lateral_m - st.lateral_m.mean()
            tol = 0.25 if preset != "naive" else 0.8
            np.testing.assert_allclose(rel, truth - truth.mean(), atol=tol)
            np.testing.assert_array_equal(st.types, [t for _, t in sorted(LINES)])
    assert n_exact > 0.8 * len(valid) if preset != "naive" else n_exact > 0


def test_map_segments_is_map_stretches_segments():
    few = make_fleet([0.3, -0.2], s1=60.0)
    segs = map_segments(few, config=presets.preset("paper"), seed=3)
    again = map_stretches(few, config=presets.preset("paper"), seed=3).segments
    assert [s.pivot_id for s in segs] == [s.pivot_id for s in again]
    steps = [(st.index, st.valid, st.lateral_m.tolist()) for seg in segs for st in seg.steps]
    assert steps and steps == [(st.index, st.valid, st.lateral_m.tolist()) for seg in again for st in seg.steps]


def test_corrected_road_width_beats_naive(run):
    # Border to border is 13 m; without offset correction the outer clusters are smeared.
    def width_error(preset):
        segs = run(preset)[0].segments
        w = [st.lateral_m.max() - st.lateral_m.min() for seg in segs for st in seg.steps if st.valid]
        return abs(np.mean(w) - 13.0)

    assert width_error("default") < 0.1
    assert width_error("paper") < 0.1


def test_processed_stretches_are_skipped(fleet, run):
    res = run("paper")[0]
    c = res.counters
    assert c["steps_skipped_processed"] > 0.5 * c["steps_total"]  # all drives share one road
    # Every drive's stretch was processed through the first pivot.
    for d in fleet:
        assert res.processed.contains(d.drive_id, np.array([50.0, 150.0])).all()
    # Feeding the store back in: nothing is left to map.
    again = map_stretches(fleet, config=presets.preset("paper"), seed=1, processed=res.processed)
    assert again.counters["steps_valid"] == 0
    assert again.counters["steps_skipped_processed"] == again.counters["steps_total"]
    skipped = [st for seg in again.segments for st in seg.steps]
    assert skipped and all(st.processed_before and not st.valid for st in skipped)
    # ... and the store round-trips through JSON.
    assert ProcessedStore.from_json(res.processed.to_json()).intervals == res.processed.intervals


@pytest.mark.slow
def test_drive_beside_the_cut_is_not_marked_processed(fleet):
    """Drives on a ramp beyond the right road border see the ego road's lines, so they take part
    in the ego pivots' steps. The paper's reading marks them processed there, so the ramp is never
    mapped; with mark_on_cut_only they are not on the ego cuts, stay unprocessed and, as pivots,
    map the ramp's outer border (lateral -11.5 m), which no ego drive sees."""
    ramp_lines = LINES + ((-8.5, FeatureType.ROAD_BORDER), (-11.5, FeatureType.ROAD_BORDER))
    ramps = [
        make_drive(f"ramp{k}", lane=-10.0, bias=b, s0=5.0 * k, s1=200.0, lines=ramp_lines)
        for k, b in enumerate([0.2, -0.3, 0.1])
    ]
    drives = [*fleet, *ramps]
    seed = 0
    assert np.random.default_rng(seed).permutation(len(drives))[0] < len(fleet)  # an ego pivot first

    def ramp_steps(mark_on_cut_only: bool) -> list:
        cfg = dataclasses.replace(presets.preset("paper"), mark_on_cut_only=mark_on_cut_only)
        res = map_stretches(drives, config=cfg, seed=seed)
        return [st for seg in res.segments if seg.pivot_id.startswith("ramp") for st in seg.steps]

    n_paper = sum(st.valid for st in ramp_steps(False))
    valid = [st for st in ramp_steps(True) if st.valid]
    assert n_paper < 10  # at most the ends, where no ego pivot step was accepted
    assert len(valid) > 80  # one ramp pivot maps its ~95 steps, the other two are then processed
    found = 0
    for st in valid:
        pts = st.points()[st.types == int(FeatureType.ROAD_BORDER)]
        # The road centre line is an arc of RADIUS_M about (0, RADIUS_M), curving left.
        lateral = RADIUS_M - np.linalg.norm(pts - np.array([0.0, RADIUS_M]), axis=1)
        found += bool(np.any(np.abs(lateral + 11.5) < 0.5))
    assert found > 0.8 * len(valid)


def test_observation_pass_marks_drives_just_beside_the_cut(fleet):
    """Three drives 2 m beyond the right road border (a GNSS error, or a gore between two roads)
    see the ego road's lines. The observation pass (it only feeds the adjustment) counts a drive
    within ``max_pivot_outside_m`` beyond a cut as on it, so they are marked processed by the ego
    pivots and do not sample the whole place again as pivots: at most their ends (before the ego
    pivots' first accepted step) remain. Without the tolerance they add a step per place (53
    observations on top of the ego road's 51)."""
    strays = [make_drive(f"stray{k}", lane=-8.5, bias=0.0, s0=10.0 * k, s1=200.0) for k in range(3)]
    drives = [*fleet, *strays]
    assert np.random.default_rng(0).permutation(len(drives))[0] < len(fleet)  # an ego pivot first
    res = map_stretches(drives, config=presets.preset("default"), seed=0, observations_only=True)
    by_strays = [o for o in res.observations if o.pivot_id.startswith("stray")]
    assert 40 < len(res.observations) - len(by_strays)  # the ego road is observed
    assert len(by_strays) < 10


def test_observations_for_the_adjustment(run):
    res = run("paper")[0]
    assert len(res.observations) == res.counters["steps_valid"]
    ob = res.observations[len(res.observations) // 2]
    m = len(ob.lateral_m)
    assert len(ob.drive_ids) == m and ob.drive_s_m.shape == (m,) and ob.cluster.shape == (m,)
    # Each drive's offset makes its samples agree: corrected samples of one cluster coincide.
    corr = ob.lateral_m + ob.offsets_m
    for c in np.unique(ob.cluster[ob.cluster >= 0]):
        assert np.ptp(corr[ob.cluster == c]) < 0.3
    # drive_s_m is the sampled drive's own travelled distance (drives start at s = 0 here).
    pivot_steps = {st.index: st.s_m for seg in res.segments if seg.pivot_id == ob.pivot_id for st in seg.steps}
    np.testing.assert_allclose(ob.drive_s_m, pivot_steps[ob.index], atol=2.0)


@pytest.mark.slow
def test_observation_pass_runs_the_em_at_every_stride_th_step(fleet):
    base = presets.preset("paper")
    every = map_stretches(fleet, config=base, seed=0, collect_observations=True, observations_only=True).observations
    strided = map_stretches(
        fleet,
        config=dataclasses.replace(base, observation_stride=2),
        seed=0,
        collect_observations=True,
        observations_only=True,
    ).observations
    assert any(ob.index % 2 for ob in every)
    assert strided and all(ob.index % 2 == 0 for ob in strided)
    # a pass whose segments are the map's (no adjustment after it) runs at every step
    full = map_stretches(
        fleet, config=dataclasses.replace(base, observation_stride=2), seed=0, collect_observations=True
    )
    assert any(ob.index % 2 for ob in full.observations)
    with pytest.raises(ConfigError, match="observation_stride"):
        PipelineConfig(observation_stride=0)


def test_fill_evidence_without_profiles_is_a_config_error():
    default = presets.preset("default")
    assert default.evidence is not None and default.stitching.fill_evidence is not None
    # the stitcher's fill test without the profiles it reads would silently test nothing
    with pytest.raises(ConfigError, match="fill_evidence.*evidence"):
        dataclasses.replace(default, evidence=None)
    # both off, or profiles without the test (e.g. for a stitcher configured elsewhere), are fine
    dataclasses.replace(default, evidence=None, stitching=dataclasses.replace(default.stitching, fill_evidence=None))
    dataclasses.replace(default, stitching=dataclasses.replace(default.stitching, fill_evidence=None))


def test_prepare_drives_rejects_with_reasons(fleet):
    dup = fleet[0]
    usable, rejected = prepare_drives([*fleet[:2], _bad_drive(), dup])
    assert [d.drive_id for d in usable] == [fleet[0].drive_id, fleet[1].drive_id]
    assert rejected[0][0] == "broken" and rejected[0][1].startswith("non_finite_coordinates")
    assert rejected[1] == (dup.drive_id, "duplicate_drive_id")


def test_map_stretches_raises_without_usable_drive():
    with pytest.raises(NoUsableDataError):
        map_stretches([_bad_drive()])


def test_build_map_rejects_malformed_drive_and_goes_on(fleet):
    pytest.importorskip("hdmap_core.graph.map_graph")
    bad_type = Drive("badtype", fleet[0].xy, fleet[0].yaw, fleet[0].stamps_ns, (Detection(7, fleet[0].xy),))  # type: ignore[arg-type]
    res = build_map([*fleet, _bad_drive(), bad_type], config=presets.preset("default"), seed=0)
    rep = res.report
    assert rep.n_drives_in == len(fleet) + 2 and rep.n_drives_used == len(fleet)
    assert {d for d, _ in rep.rejected} == {"broken", "badtype"}
    # the drives it used: the input's usable ones, in order, the same objects
    assert len(res.drives) == len(fleet) and all(a is b for a, b in zip(res.drives, fleet))
    assert isinstance(res.map, HDMap) and len(res.map.features) >= 6
    assert rep.km_mapped > 0.1 and rep.steps_total > 0
    assert "rejected 'broken'" in rep.summary()


def test_build_map_all_bad_raises():
    with pytest.raises(NoUsableDataError, match="none of the 1 drive"):
        build_map([_bad_drive()])


@pytest.mark.slow
def test_end_to_end_on_simulated_motorway():
    """Simulated fleet on the built-in curved motorway: the default map beats the naive one."""
    from hdmap_core.evaluation.evaluate import evaluate_map
    from hdmap_core.simulation.fleet import SimConfig, simulate_fleet
    from hdmap_core.simulation.synthetic import synthetic_highway

    gt = synthetic_highway("motorway", length_m=1500.0, seed=0)
    fleet = simulate_fleet(
        gt, config=SimConfig(n_drives=30, snippet_length_min_m=500.0, snippet_length_max_m=1500.0), seed=0
    )
    scores = {}
    for preset in ("default", "naive"):
        res = build_map(fleet.drives, config=presets.preset(preset), seed=0)
        scores[preset] = evaluate_map(res.map, gt, drives=fleet.drives).overall
    good, naive = scores["default"], scores["naive"]
    assert good.coverage > 0.9
    assert good.corrected_mean_m < 0.12
    assert good.mean_m < naive.mean_m
    assert good.precision > 0.95


def test_progress_reports_every_pivot(fleet, run):
    calls = run("paper")[1]
    assert calls[-1] == ("pivots", len(fleet), len(fleet))
    assert [c[1] for c in calls] == list(range(1, len(fleet) + 1))


def test_final_sampling_keeps_a_far_border_only_one_drive_saw(fixed):
    """The default preset's final pass keeps a side's samples up to a border only one drive saw
    when nothing lies beyond it (``SamplingConfig.outer_border_reach``); the first pass, which
    feeds the adjustment, samples as before. Two drives: the far left border at +8 m (the solid
    line at +5.25 m before it unseen) is in the map with the option, not without it."""
    B, S, D = FeatureType.ROAD_BORDER, FeatureType.SOLID, FeatureType.DASHED
    a = make_drive("a", lane=-3.5, bias=0.0, lines=((-6.5, B), (-5.25, S), (-1.75, D), (1.75, D)))
    b = make_drive("b", lane=0.0, bias=0.0, lines=((-6.5, B), (-1.75, D), (1.75, D), (8.0, B)))
    default = PipelineConfig()
    assert default.final_sampling.outer_border_reach and not default.sampling.outer_border_reach

    def far_border_points(config: PipelineConfig) -> int:
        m = build_map([a, b], config=config, seed=0).map
        n = 0
        for f in m.features:
            if f.type != FeatureType.ROAD_BORDER:
                continue
            r = np.hypot(f.points[:, 0], f.points[:, 1] - RADIUS_M)  # the road is an arc about (0, R)
            n += int(np.count_nonzero(np.abs((RADIUS_M - r) - 8.0) < 0.5))
        return n

    assert far_border_points(default) > 50
    fixed(FinalSampling, outer_border_reach=False)  # the rule off
    assert far_border_points(default) == 0


def test_steps_off_their_pivots_road_are_not_aligned(fixed):
    """``SamplingConfig.max_pivot_outside_m`` (default preset, both passes): a step whose pivot
    lies beyond its refined cut is rejected, not aligned. Two drives that see only a border and
    a line 16.5-20 m to their left (a junction's far side): the one-sided cut lies 12.5 m left of
    the pivot, the lines are mapped without the check and not with it."""
    B, D = FeatureType.ROAD_BORDER, FeatureType.DASHED
    far = [make_drive(k, lane=0.0, bias=0.0, lines=((20.0, B), (16.5, D))) for k in "ab"]
    default = PipelineConfig()
    assert default.sampling.max_pivot_outside_m == 2.0 and default.final_sampling.max_pivot_outside_m == 2.0

    def valid_steps(config: PipelineConfig) -> int:
        res = map_stretches(far, config=config, seed=0)
        return sum(st.valid for seg in res.segments for st in seg.steps)

    assert valid_steps(default) == 0
    fixed(SamplingConfig, max_pivot_outside_m=float("inf"))  # the check off, in both passes
    assert default.final_sampling.max_pivot_outside_m == float("inf")
    assert valid_steps(default) > 100
    for name in ("paper", "naive"):  # the paper's reading: no check
        assert presets.preset(name).sampling.max_pivot_outside_m == float("inf")


def test_steps_carry_the_pivots_own_corrected_position(fleet, run):
    """Every step, rejected or not, carries its pivot's position (``StepResult.pose``): on the
    step's cut (no offset along it) and inside the road it describes; the default preset's final
    pass corrects it by the offset model, so it differs from the raw trajectory point there."""
    for preset in ("paper", "default"):
        res = run(preset)[0]
        steps = [st for seg in res.segments for st in seg.steps if not st.processed_before]
        assert steps and all(st.pose is not None for st in steps)
        for st in steps:
            rel = np.asarray(st.pose) - np.asarray(st.midpoint)
            along = rel @ np.array([np.cos(st.heading), np.sin(st.heading)])
            across = rel @ np.array([-np.sin(st.heading), np.cos(st.heading)])
            assert abs(along) < 1e-6 and abs(across) <= 0.5 * st.width_m
        drives = {d.drive_id: d for d in fleet}
        moved = [
            float(np.hypot(*(np.asarray(st.pose) - pivot_walk(drives[st.pivot_id], step_m=2.0)[1][st.index])))
            for st in steps
        ]
        assert (max(moved) > 0.05) == (preset == "default")  # the biases are 0.3-1.1 m


def test_report_counts_the_steps_off_their_pivots_road():
    """The build report names how many rejected steps lay off their pivot's road (the summary
    line says so only when there are any)."""
    B, D = FeatureType.ROAD_BORDER, FeatureType.DASHED
    far = [make_drive(k, lane=0.0, bias=0.0, lines=((20.0, B), (16.5, D))) for k in "ab"]
    rep = build_map(far, config=presets.preset("default"), seed=0).report
    assert 0 < rep.steps_off_road <= rep.steps_rejected <= rep.steps_total
    assert f"({rep.steps_off_road} off their pivot's road)" in rep.summary()
    road = make_fleet([0.3, -0.2, 0.1], noise_m=0.0, s1=120.0)
    ok = build_map(road, config=presets.preset("default"), seed=0).report
    assert ok.steps_off_road == 0 and "off their pivot's road" not in ok.summary()


def test_final_pass_with_a_given_model_holds_one_pivot_of_hits(fleet, run, monkeypatch):
    """With the offset model given only the final pass runs (a tiled build's final pass): the hit
    cache then holds the latest pivot only (bounded memory), and the segments are those of a
    cache holding every pivot."""
    import hdmap_core.pipeline.driver as drv  # noqa: PLC0415

    config = presets.preset("default")
    assert config.evidence is not None  # the evidence profiles read the cache back
    model = run("default")[0].offset_model
    sizes: list[int] = []

    class Recording(drv._LatestOnly):
        def __setitem__(self, key, value):
            super().__setitem__(key, value)
            sizes.append(len(self))

    monkeypatch.setattr(drv, "_LatestOnly", Recording)
    got = map_stretches(fleet, config=config, seed=0, offset_model=model).segments
    monkeypatch.setattr(drv, "_LatestOnly", dict)
    want = map_stretches(fleet, config=config, seed=0, offset_model=model).segments
    assert len(sizes) == len(fleet) and max(sizes) == 1
    flat = [(s.pivot_id, st.index, st.valid, st.lateral_m.tolist()) for s in got for st in s.steps]
    assert flat and flat == [(s.pivot_id, st.index, st.valid, st.lateral_m.tolist()) for s in want for st in s.steps]
