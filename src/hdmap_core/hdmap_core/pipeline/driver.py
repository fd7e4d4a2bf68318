"""The whole method (Immel et al. 2023): drives in, hierarchical map out.

``map_segments`` runs stages 1-4 (preprocessing, lateral sampling, EM offset estimation,
aggregation) along random pivot drives and returns one ``Segment`` per pivot; ``build_map`` adds
the connection (Sec. V, ``hdmap_core.graph.connection``) and stitching (Sec. VI,
``hdmap_core.graph.map_graph``) stages and a run report.

Presets (``PipelineConfig.preset``):
- "paper": the paper's method as written; its open values read as documented in docs/pipeline.md.
- "default": the improved variant: fast exact per-step EM (closed form, gap clustering after warm
  start, offsets carried along a drive) plus the global joint offset adjustment
  (``hdmap_core.pipeline.adjustment``): a first pass produces per-step observations, one sparse
  adjustment estimates every drive's offset curve, and a second pass samples and aggregates with
  the samples shifted by it.
- "naive": no offset correction at all: cluster means of the raw samples (the baseline).
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields, is_dataclass, replace
from typing import Any

import numpy as np

try:  # threadpoolctl comes with scikit-learn
    from threadpoolctl import threadpool_limits
except ImportError:  # pragma: no cover
    threadpool_limits = None

from hdmap_core.pipeline.aggregation import AggregationConfig, ProcessedStore, aggregate_many
from hdmap_core.pipeline.alignment import AlignmentConfig, align_step, align_steps_gap, gap_batchable
from hdmap_core.errors import ConfigError, InvalidDriveError, NoUsableDataError
from hdmap_core.model import Drive, HDMap, validate_drive
from hdmap_core.parallel import ForkWorker, can_fork, map_balanced, split_order
from hdmap_core.pipeline.evidence import EvidenceConfig, step_profiles
from hdmap_core.pipeline.preprocess import DetectionIndex, PreprocessConfig, preprocess, trajectory_index
from hdmap_core.pipeline.sampling import PivotSamples, SamplingConfig, pivot_groups, pivot_walk, sample_pivot
from hdmap_core.geometry import arc_length, wrap_angle
from hdmap_core.steps import Segment, StepObservations, StepResult, left_normal

__all__ = [
    "PipelineConfig",
    "BuildReport",
    "BuildResult",
    "MappingResult",
    "build_map",
    "map_segments",
    "map_stretches",
    "prepare_drives",
]

_PRESETS = ("paper", "default", "naive")
ProgressFn = Callable[[str, int, int], None]

_EMPTY_F = np.zeros(0)
# Tracked offsets are re-checked for lane-periodic lock-in every this many steps (50 m).
_RECHECK_EVERY_STEPS = 25
_EMPTY_I = np.zeros(0, dtype=np.int64)


@dataclass(frozen=True)
class PipelineConfig:
    """All options of the pipeline, one frozen config per stage.

    Attributes:
        preprocess, sampling, alignment, aggregation: stages 1-4.
        use_global_adjustment: run the global joint per-drive offset adjustment between a first
            (observation) pass and the final sampling/aggregation pass.
        adjustment: ``hdmap_core.pipeline.adjustment.AdjustConfig``; None with ``use_global_adjustment``
            becomes its defaults, so that its fields can be changed like any stage's.
        final_alignment_changes: where the EM of the second pass (samples already shifted by
            the offset model) differs from ``alignment``, as ``{field: value}`` (stored as sorted
            pairs); the pass's config is the property ``final_alignment``. Empty: as ``alignment``.
        final_sampling_changes: likewise, where the second pass samples unlike ``sampling``
            (property ``final_sampling``). The step, initial cut and heading limit cannot differ
            (the passes share the pivots' steps and the cut-line intersections); the cut
            refinement may. Kept as changes, not as whole configs, so that a change of
            ``sampling`` / ``alignment`` reaches the second pass wherever it does not differ on
            purpose.
        observation_stride: with ``use_global_adjustment``, the first pass, which only collects
            step observations for the adjustment (its segments are replaced by the final pass),
            runs the EM at every this-th step of a pivot. The adjustment fits curves with knots
            every 200 m, so steps 4 m apart inform it as well as steps 2 m apart; the EM, the
            largest cost of a build, halves. 1 = every step. Above 2 the accepted steps lie
            further apart than the processed-stretch marks' merge gap (3 steps) and later pivots
            redo those stretches (measured: docs/pipeline.md, "Two passes").
        connection: ``hdmap_core.graph.connection.ConnectionConfig`` (None: its defaults).
        stitching: ``hdmap_core.graph.map_graph`` config (None: its defaults).
        mark_on_cut_only: a drive's stretch is stored as processed at an accepted step only when
            the drive itself was on the step's refined cut (its trajectory within half the cut
            length of the midpoint). Off (the paper's reading): every drive whose samples took
            part is marked, so a drive on a ramp beside the ego road, which sees the ego road's
            lines, never becomes a pivot there and the ramp's outer features are not mapped.
        evidence: negative evidence per step of the pass whose segments are returned
            (``hdmap_core.pipeline.evidence``: where the drives that passed saw nothing, carried as
            ``StepResult.empty_m``; the stitcher drops fills through such places when its
            ``fill_evidence`` is set). None: no profiles (the paper, the plain default).
        name: the preset this config came from ("" when built by hand).
    """

    preprocess: PreprocessConfig = PreprocessConfig()
    sampling: SamplingConfig = SamplingConfig()
    alignment: AlignmentConfig = AlignmentConfig()
    aggregation: AggregationConfig = AggregationConfig()
    use_global_adjustment: bool = False
    adjustment: Any = None
    final_alignment_changes: Any = ()
    final_sampling_changes: Any = ()
    observation_stride: int = 1
    connection: Any = None
    stitching: Any = None
    mark_on_cut_only: bool = False
    evidence: EvidenceConfig | None = None
    name: str = ""

    def __post_init__(self) -> None:
        for name, base in (("final_sampling", self.sampling), ("final_alignment", self.alignment)):
            changes = _changes(getattr(self, f"{name}_changes"), f"PipelineConfig.{name}_changes")
            if name == "final_sampling" and (shared := sorted(set(dict(changes)) & set(_SHARED_SAMPLING))):
                raise ConfigError(
                    f"PipelineConfig.final_sampling cannot change {', '.join(shared)}: the passes share "
                    f"the pivots' steps ({', '.join(_SHARED_SAMPLING)} are sampling's)"
                )
            known = {f.name for f in fields(base)}
            for key, _ in changes:
                if key not in known:
                    raise ConfigError(f"PipelineConfig.{name}_changes: {type(base).__name__} has no field {key!r}")
            try:
                derived = replace(base, **dict(changes))
            except ConfigError as err:
                raise ConfigError(f"PipelineConfig.{name}_changes: {err}") from err
            except (TypeError, ValueError) as err:
                raise ConfigError(f"PipelineConfig.{name}_changes: not a valid value ({err})") from err
            object.__setattr__(self, f"{name}_changes", changes)
            object.__setattr__(self, f"_{name}", derived)
        if self.use_global_adjustment and self.adjustment is None:
            # The adjustment runs: its settings are the defaults, held explicitly so that
            # ``with_overrides`` ("--set adjustment.loss=linear") reaches them.
            from hdmap_core.pipeline.adjustment import AdjustConfig  # noqa: PLC0415 (stage module, loaded on use)

            object.__setattr__(self, "adjustment", AdjustConfig())
        if not (isinstance(self.observation_stride, int) and self.observation_stride >= 1):
            raise ConfigError(f"PipelineConfig.observation_stride must be an int >= 1, got {self.observation_stride!r}")
        # The stitcher's fill test reads the profiles this config's ``evidence`` makes; without
        # them it would silently test nothing.
        if getattr(self.stitching, "fill_evidence", None) is not None and self.evidence is None:
            raise ConfigError(
                "PipelineConfig.stitching.fill_evidence needs the negative-evidence profiles of "
                "PipelineConfig.evidence, which is None: set both (or neither)"
            )

    @property
    def final_sampling(self) -> SamplingConfig:
        """The second pass's sampling options: ``sampling`` with ``final_sampling_changes``."""
        return self._final_sampling  # type: ignore[attr-defined]  # set in __post_init__

    @property
    def final_alignment(self) -> AlignmentConfig:
        """The second pass's EM options: ``alignment`` with ``final_alignment_changes``."""
        return self._final_alignment  # type: ignore[attr-defined]  # set in __post_init__

    @classmethod
    def preset(cls, name: str) -> PipelineConfig:  # type: ignore[override]
        """The named preset: "paper", "default" or "naive" (see the module docstring)."""
        if name == "paper":
            # stages 5-6 too as the paper writes them: every leftover joined, same-type unmodified
            # assignment across segments, none of our clean-up (the dataclass defaults are ours)
            from hdmap_core.graph.connection import ConnectionConfig  # noqa: PLC0415 (stage modules, loaded on use)
            from hdmap_core.graph.map_graph import StitchConfig  # noqa: PLC0415

            return cls(connection=ConnectionConfig.paper(), stitching=StitchConfig.paper(), name="paper")
        if name == "naive":
            return cls(
                sampling=SamplingConfig(),
                alignment=AlignmentConfig(estimate_offsets=False, silhouette_gate=-1.0),
                aggregation=AggregationConfig(method="mean", overlap_filter=False),
                name="naive",
            )
        if name == "default":
            fast = AlignmentConfig(
                clustering="auto",
                solver="closed_form",
                n_iterations=4,
                prior_weight=1.0,
                robust_loss=True,
                min_cluster_drives=1,
                # Labels are fixed in the M-step and the closed form minimises the variance; the
                # penalty would only push apart clusters of one feature split by a gap.
                penalty_lm_threshold=2.0,
                lone_cluster_max_std_m=0.3,
                # Steps of <= 3 drives: judged without the one-sample clusters (lines one drive
                # misses), when every cluster is tight; type-clashing singletons dropped.
                sparse_step_max_drives=3,
                sparse_step_max_std_m=0.3,
                sparse_type_clash_m=1.0,
            )
            # final pass (docs/pipeline.md, sparse fleets; the first pass, whose steps feed the
            # adjustment, keeps its rules): a sparse step of singletons and one shared cluster is
            # accepted when tight, and steps of 4 drives are judged by the sparse-step rule too
            # (type-clashing singletons still dropped only with <= 3)
            final = dict(
                clustering="gap", prior_weight=0.0, estimate_offsets=False, sparse_singletons_accept=True,
                sparse_step_max_drives=4, sparse_type_clash_max_drives=3,
                # two drives that share no line but contradict none (each sees lines the other
                # misses, 2+ m apart) are accepted as one drive alone would be
                sparse_disjoint_apart_m=2.0,
                # drives that place a line at one spot but disagree on solid/dashed saw a line:
                # kept, of unknown type, typed along its polyline (docs/pipeline.md, "Type
                # clashes kept")
                sparse_type_clash_keep=True,
            )
            from hdmap_core.graph.connection import ConnectionConfig  # noqa: PLC0415 (stage modules, loaded on use)
            from hdmap_core.graph.map_graph import StitchConfig  # noqa: PLC0415

            # a step whose pivot lies over 2 m beyond its smoothed cut is on no road the cut
            # describes (junctions: docs/pipeline.md, "Steps off their pivot's road")
            sampling = SamplingConfig(min_border_support_fraction=0.05, open_side_gap_m=4.0, max_pivot_outside_m=2.0)
            # the adjustment's prior of one drive's lateral error (bias and drift) is the error a
            # map point keeps from its drives on average (AggregationConfig.common_sigma_m)
            from hdmap_core.pipeline.adjustment import AdjustConfig  # noqa: PLC0415

            prior = AdjustConfig()
            return cls(
                sampling=sampling,
                alignment=fast,
                aggregation=AggregationConfig(
                    kde_bandwidth_factor=1.0, kde_min_bandwidth_m=0.15, tie_by_position=True,
                    # two drives' border on a line is a border there too (docs/pipeline.md,
                    # "Borders on lines")
                    border_beside_marking_drives=2,
                    common_sigma_m=float(np.hypot(prior.bias_sigma_m, prior.drift_sigma_m)),
                ),
                use_global_adjustment=True,
                adjustment=prior,
                final_alignment_changes=final,
                # final pass (samples corrected): a side without a first border keeps its samples
                # up to a border only one drive saw when nothing lies beyond it (docs/pipeline.md,
                # "Far borders one drive saw"); the first pass, which feeds the adjustment, does not
                # (the off-cut margin stays 2 m: 1 m cost a 20-drive bag 3.5 points of coverage,
                # docs/pipeline.md "Steps off their pivot's road")
                final_sampling_changes={"outer_border_reach": True},
                # the first pass only feeds the adjustment (knots every 200 m): EM every 4 m
                observation_stride=2,
                mark_on_cut_only=True,
                # where drives passed and saw nothing: fills through such places are dropped
                # (docs/pipeline.md, "Negative evidence")
                # judged where >= 2 detections are expected (3 in the dataclass): the 30-drive
                # fleets' false fills lie where 1-4 drives pass (docs/pipeline.md, "Negative
                # evidence")
                evidence=EvidenceConfig(min_expected=2.0),
                # straight carriageway lines crossed at 12-30 deg paired in their own direction (an
                # entry ramp's pivot; not lines curving with the pivot: docs/pipeline.md, "Lines
                # crossed by an entering pivot")
                connection=ConnectionConfig(
                    # the last step's open ends are paired first, ends bridged from earlier steps
                    # take what is left (docs/pipeline.md "Fresh tips first")
                    fresh_first=True,
                    support_window_m=4.0,
                    window_min_count=1,
                    # ... and a line a lane from both its neighbours, whatever its support (one
                    # drive's lane beside lines many saw; docs/pipeline.md "Lone lines")
                    lone_line_gap_m=3.0,
                    # ... an edge line only 0.8 m from its border (not a marking on the border;
                    # docs/pipeline.md "Lone edge lines")
                    lone_line_border_gap_m=0.8,
                    # ... and only on its outer side (a lane line's copy typed as border is no
                    # edge line's border; docs/pipeline.md "Lone edge lines")
                    lone_line_border_outer=True,
                    # a topology node reaches 0.5 m beyond its pivot: the node of a junction step
                    # whose cut lies beside the pivot describes the road it drove (docs/pipeline.md
                    # "The pivot's own road in its topology node")
                    topo_pivot_lane_m=0.5,
                    separation_count_ratio=0.5,
                    line_frame_deg=12.0,
                    line_frame_bend_deg=5.0,
                    # a step's connection angles are judged less the maxima's noise: tight loops
                    # (docs/pipeline.md "Connection angles on tight curves")
                    mean_angle_slack=True,
                ),
                stitching=StitchConfig(
                    # junction pieces already joined to the map through one end get their other end
                    # linked too; a ramp chain ending (starting) short of the gore follows its own
                    # arc onto the road (docs/graph.md)
                    link_within_component=True, path_search_m=36.0, path_max_turn_deg=60.0,
                    # an end (linked or not) follows the path its pivot drove through a junction
                    # whose steps failed, onto the road it entered (docs/graph.md, "Track links")
                    track_search_m=60.0, track_linked_ends=True,
                    # ... but not onto a road that runs into what the end reaches anyway: a side
                    # step from a ramp onto the main road beside it (docs/graph.md, "Side steps")
                    track_rejoin_m=30.0,
                    # ... nor across the split behind an end or the merge ahead of a start
                    track_rejoin_both=True,
                    # ... landing where its pivot has settled onto the road, not where it still
                    # turns into it (docs/graph.md, "Track settling")
                    track_settle_deg=8.0,
                    # ... and a pivot's track leaving one mapped road through failed steps onto
                    # another links the two where no chain ends there (docs/graph.md, "Track bridges")
                    track_bridge_m=60.0,
                    # ... also from a road whose cross-section the track's first point after a gap
                    # misses by up to 2 m (docs/graph.md, "Track bridges")
                    track_bridge_leave_margin_m=2.0,
                    # tracks are the pivot's own corrected positions, not its steps' cut midpoints,
                    # which fly off onto other roads where steps fail (docs/graph.md, "Tracks of poses")
                    track_pose=True,
                    # fills through stretches the drives saw empty are dropped (the profiles come
                    # from ``evidence`` above; docs/pipeline.md, "Negative evidence")
                    fill_evidence=EvidenceConfig(min_expected=2.0),
                    # two roads side by side join only at a shallow angle (docs/graph.md), side by
                    # side also when their lines barely overlap across the road
                    side_link_angle_deg=30.0, side_link_overlap=0.5,
                    # ... and never backward for the partner: a ramp node leaving the road was linked
                    # 97 deg off its own heading to a main-road start beside it (docs/graph.md)
                    partner_angle_deg=90.0,
                    # type flicker on sparse lines: a run of >= 2 drives relabelled only as a minority,
                    # one drive's misclassified stretch up to 250 m (docs/pipeline.md, sparse fleets)
                    sparse_minority_only=True, single_drive_run_m=250.0,
                    # ... and only runs of <= 3 drives: 4-5 drives agreeing on a type are a real
                    # stretch (a solid run before a gore), not a misclassification (docs/pipeline.md,
                    # "Type runs of 4-5 drives")
                    sparse_drive_count=3,
                    # ... and a one-drive run at a line's end after a better supported run of the
                    # other type (docs/pipeline.md, sparse fleets)
                    single_drive_end_run_m=250.0,
                    # ... also where its neighbour run lies beyond a leftover edge the polyline
                    # goes on through (docs/pipeline.md, "Type runs across leftover edges")
                    single_drive_end_through_leftover=True,
                    # loose ends also compared in their lines' frame from 3 deg off the pivot's
                    # heading (10 in the dataclass), such joins refused where a pivot turned
                    # through the gap (docs/pipeline.md, sparse fleets)
                    join_line_heading_deg=3.0, join_line_cross_deg=30.0, join_line_cross_lateral_m=12.0,
                    # ... and a solid end joins a dashed start (or the reverse) up to 10 m ahead: one
                    # line whose type flickered where a segment ended (docs/pipeline.md, "Loose ends of
                    # the other marking type")
                    join_other_marking_m=10.0,
                    # an isolated 1-2-drive border between lane lines is a misclassified marking:
                    # dropped, or kept as a dashed line where one drive saw it and no line is
                    # mapped there (docs/pipeline.md, "Inner borders kept as lane lines")
                    inner_border_max_m=5.0, inner_border_max_drives=2, inner_border_dashed_drives=1,
                    # one drive's (or a disputed) marking within 1.5 m of the border is the solid
                    # edge line (docs/pipeline.md, "Edge lines")
                    edge_line_solid_m=1.5,
                    # a loose end's stub of <= 12 m reached by a fill jumping >= 2 m sideways of the
                    # pivot's heading (onto the neighbouring lane's line) is dropped where other
                    # lines map its cross-section (docs/pipeline.md, "Town04's stray pieces")
                    end_stub_max_m=12.0,
                ),
                name="default",
            )
        raise ConfigError(f"unknown pipeline preset {name!r}; choose one of {_PRESETS}")

    def with_overrides(self, overrides: Mapping[str, object]) -> PipelineConfig:
        """This config with each dotted key set, e.g. ``{"stitching.track_rejoin_m": 0.0}``.

        A ``final_sampling.*`` (``final_alignment.*``) key sets that field in the second pass
        alone (one of ``final_sampling_changes``); ``final_sampling=null`` drops those changes. A
        ``sampling.*`` (``alignment.*``) key sets the first pass and so also the second wherever
        that one does not differ on purpose.

        Every stage config's own checks run on its new value. The name gets a ``+`` (the preset
        with changes), so reports do not pass the result off as the preset itself.

        Raises:
            ConfigError: a key names no field (or a stage that is off, None, in this config; or
                the second pass of a config without one), or a value the field rejects; the
                message names the key.
        """
        config: PipelineConfig = self
        second_pass_keys = []
        for key, value in overrides.items():
            head, _, rest = key.partition(".")
            if head not in _FINAL_PASS:
                config = _override(config, key, value, key)
                continue
            if not rest:
                if value is not None:
                    raise _group_error(key, value, getattr(config, head), "or null to drop the second pass's own settings",
                                       skip=_SHARED_SAMPLING if head == "final_sampling" else ())
                config = replace(config, **{f"{head}_changes": ()})
                continue
            second_pass_keys.append(key)
            field_name, _, deeper = rest.partition(".")
            if deeper:
                raise ConfigError(f"{key}: {type(getattr(config, head)).__name__}.{field_name} has no fields to set")
            _override(getattr(config, head), field_name, value, key)  # the field's kind and checks
            changes = dict(getattr(config, f"{head}_changes"))
            changes[field_name] = value
            try:
                config = replace(config, **{f"{head}_changes": changes})
            except ConfigError as err:
                raise ConfigError(f"{key}: {err}") from err
        if second_pass_keys and not config.use_global_adjustment:
            raise ConfigError(
                f"{second_pass_keys[0]}: {second_pass_keys[0].partition('.')[0]} is off in this config "
                "(it has no second pass: use_global_adjustment is false)"
            )
        if overrides and not config.name.endswith("+"):
            config = replace(config, name=f"{config.name}+")
        return config


#: The second pass's stage configs (derived from the first pass's and their changes).
_FINAL_PASS = ("final_sampling", "final_alignment")
#: Sampling fields both passes share (the pivots' steps and the cut-line intersections).
_SHARED_SAMPLING = ("step_m", "initial_half_length_m", "max_heading_diff_deg")


def _changes(value: object, name: str) -> tuple[tuple[str, Any], ...]:
    """``{field: value}`` (or pairs) as sorted ``(field, value)`` pairs: one form, comparable."""
    try:
        pairs = dict(value.items() if isinstance(value, Mapping) else value)  # type: ignore[union-attr]
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{name} must be a mapping of field names to values, got {value!r}") from err
    if not all(isinstance(k, str) for k in pairs):
        raise ConfigError(f"{name} must be a mapping of field names to values, got {value!r}")
    return tuple(sorted(pairs.items()))


def _group_error(key: str, value: object, group: object, also: str = "", skip: Sequence[str] = ()) -> ConfigError:
    """The error for a value given to a whole stage config (``key``, holding ``group``); the
    example field is its first not in ``skip`` (fields the key may not change)."""
    example = next(f.name for f in fields(group) if f.name not in skip)
    name = key.rpartition(".")[2]
    return ConfigError(
        f"{key}={_shown(value)}: {name} is a group of settings; set one of its fields, "
        f"e.g. {key}.{example}=...{', ' + also if also else ''}"
    )


def _shown(value: object) -> str:
    """A ``--set`` value as it is written there (``true``, ``null``, ``inf``, ``'gap'``)."""
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, float) and not np.isfinite(value):
        return str(value)  # inf, -inf, nan
    try:
        return json.dumps(value)
    except (TypeError, ValueError):
        return repr(value)


def parse_override(text: str) -> tuple[str, object]:
    """One ``KEY=VALUE`` change as ``bag2map --set`` and the nodes' ``preset_overrides`` take it:
    the dotted key and the value as JSON (numbers, true/false, null, lists), ``inf`` / ``-inf``
    as floats (several limits are off at inf, e.g. ``sampling.max_pivot_outside_m=inf``), else as
    the string itself (``alignment.clustering=auto``). Whether it fits is
    :meth:`PipelineConfig.with_overrides`' check.

    Raises:
        ConfigError: no ``=``, or nothing before it.
    """
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise ConfigError(f"{text!r} is not KEY=VALUE")
    if raw.strip().lower() in ("inf", "+inf", "-inf", "infinity", "+infinity", "-infinity"):
        return key.strip(), float(raw.strip().lower().replace("infinity", "inf"))
    try:
        return key.strip(), json.loads(raw)
    except json.JSONDecodeError:
        return key.strip(), raw


def _override(config: object, key: str, value: object, full: str) -> object:
    """``config`` (a dataclass) with the dotted ``key`` set to ``value`` (``full``: the whole key)."""
    head, _, rest = key.partition(".")
    if not is_dataclass(config) or head not in {f.name for f in fields(config)}:
        raise ConfigError(f"{full}: {type(config).__name__} has no field {head!r}")
    if not rest:
        now = getattr(config, head)
        spec = next(f for f in fields(config) if f.name == head)
        optional = value is None and ("None" in str(spec.type) or spec.default is None)
        if is_dataclass(now) and not optional:
            raise _group_error(full, value, now)
        if not optional and isinstance(now, (int, float)) and not isinstance(now, bool) and not (
            isinstance(value, (int, float)) and not isinstance(value, bool)
        ):
            raise ConfigError(f"{full}={_shown(value)}: not a valid value (a number is expected)")
        if isinstance(now, bool) and not isinstance(value, bool):
            raise ConfigError(f"{full}={_shown(value)}: not a valid value (true or false is expected)")
        try:
            return replace(config, **{head: value})
        except ConfigError as err:
            raise ConfigError(f"{full}: {err}") from err
        except (TypeError, ValueError) as err:  # a value of the wrong kind fails the field's check
            raise ConfigError(f"{full}={_shown(value)}: not a valid value ({err})") from err
    inner = getattr(config, head)
    if inner is None:
        raise ConfigError(f"{full}: {head} is off (None) in this config")
    return replace(config, **{head: _override(inner, rest, value, full)})


@dataclass(frozen=True)
class BuildReport:
    """What a run did.

    Attributes:
        n_drives_in: drives given.
        n_drives_used: valid, distinct drives used.
        rejected: (drive_id, reason) per rejected drive.
        km_mapped: pivot distance of accepted steps [km].
        steps_total: sampling steps of all pivots (incl. skipped ones).
        steps_rejected: steps without a result (EM gate failed, no samples, or off the road).
        steps_off_road: of those, the steps whose pivot lay beyond its refined cut
            (``SamplingConfig.max_pivot_outside_m``): not aligned.
        steps_skipped_processed: steps skipped as already processed through another pivot.
        seconds: wall time of the whole run [s].
        stage_seconds: wall time per stage [s].
    """

    n_drives_in: int = 0
    n_drives_used: int = 0
    rejected: list[tuple[str, str]] = field(default_factory=list)
    km_mapped: float = 0.0
    steps_total: int = 0
    steps_rejected: int = 0
    steps_off_road: int = 0
    steps_skipped_processed: int = 0
    seconds: float = 0.0
    stage_seconds: dict[str, float] = field(default_factory=dict)

    def summary(self) -> str:
        """A few readable lines."""
        lines = [
            f"drives: {self.n_drives_used} used of {self.n_drives_in} ({len(self.rejected)} rejected)",
            f"steps: {self.steps_total} total, {self.steps_rejected} rejected"
            + (f" ({self.steps_off_road} off their pivot's road)" if self.steps_off_road else "") + ", "
            f"{self.steps_skipped_processed} skipped (processed before); {self.km_mapped:.2f} km mapped",
            f"time: {self.seconds:.2f} s (" + ", ".join(f"{k} {v:.2f}" for k, v in self.stage_seconds.items()) + ")",
        ]
        for did, reason in self.rejected[:10]:
            lines.append(f"  rejected {did!r}: {reason}")
        if len(self.rejected) > 10:
            lines.append(f"  ... and {len(self.rejected) - 10} more rejected")
        return "\n".join(lines)


@dataclass(frozen=True)
class BuildResult:
    """Output of ``build_map``: the map, the per-pivot segments and the report."""

    map: HDMap
    segments: list[Segment]
    report: BuildReport


@dataclass(frozen=True)
class MappingResult:
    """Output of ``map_stretches`` (stages 1-4).

    Attributes:
        segments: one per pivot drive, in pivot order. A run of steps skipped as processed
            before is represented by its first and last step (``processed_before=True``).
        processed: the processed-stretch store after the run (input store plus new stretches).
        observations: one per accepted step of the first (observation) pass; empty unless
            requested or used by the global adjustment.
        offset_model: the global offset model (None without global adjustment).
        counters: steps_total, steps_rejected, steps_skipped_processed, steps_valid,
            steps_off_road.
        stage_seconds: wall time per stage [s].
    """

    segments: list[Segment]
    processed: ProcessedStore
    observations: list[StepObservations]
    offset_model: Any
    counters: dict[str, int]
    stage_seconds: dict[str, float]


# ----------------------------------------------------------------------------- input


def prepare_drives(drives: Sequence[Drive]) -> tuple[list[Drive], list[tuple[str, str]]]:
    """Validate drives; invalid and duplicate ones are rejected with a reason, never raised.

    Returns:
        (usable drives in input order, [(drive_id, reason), ...]).
    """
    ok: list[Drive] = []
    rejected: list[tuple[str, str]] = []
    seen: set[str] = set()
    for d in drives:
        try:
            validate_drive(d)
        except InvalidDriveError as err:
            rejected.append((err.drive_id, f"{err.reason}" + (f": {err.detail}" if err.detail else "")))
            continue
        if d.drive_id in seen:
            rejected.append((d.drive_id, "duplicate_drive_id"))
            continue
        seen.add(d.drive_id)
        ok.append(d)
    return ok, rejected


# ----------------------------------------------------------------------------- stages 2-4 per pivot


@dataclass
class _Counters:
    total: int = 0
    rejected: int = 0
    skipped: int = 0
    valid: int = 0
    off_road: int = 0


class _OffsetMemory:
    """Offsets of drives from accepted steps of earlier pivots, by the drive's own distance.

    A drive entering a step without an offset carried along the current pivot starts from the
    offset it had nearby (within ``reach_m``) through an earlier pivot, instead of being
    registered from scratch (which can lock a drive that sees only dashed lines onto the
    neighbouring lane).
    """

    def __init__(self, n_drives: int, *, reach_m: float = 50.0) -> None:
        self.reach_m = reach_m
        self._s: list[list[np.ndarray]] = [[] for _ in range(n_drives)]
        self._o: list[list[np.ndarray]] = [[] for _ in range(n_drives)]
        self._sorted: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def add(self, drive: np.ndarray, s_m: np.ndarray, offset_m: np.ndarray) -> None:
        for d in np.unique(drive):
            sel = drive == d
            self._s[int(d)].append(s_m[sel])
            self._o[int(d)].append(offset_m[sel])
            self._sorted.pop(int(d), None)

    def lookup(self, uniq: np.ndarray, sample_s: np.ndarray, local: np.ndarray) -> np.ndarray:
        out = np.full(len(uniq), np.nan)
        for k, d in enumerate(uniq.tolist()):
            if not self._s[d]:
                continue
            if d not in self._sorted:
                s_all = np.concatenate(self._s[d])
                o_all = np.concatenate(self._o[d])
                order = np.argsort(s_all)
                self._sorted[d] = (s_all[order], o_all[order])
            s_all, o_all = self._sorted[d]
            s = float(sample_s[local == k].mean())
            i = int(np.clip(np.searchsorted(s_all, s), 1, len(s_all) - 1)) if len(s_all) > 1 else 0
            j = i - 1 if i > 0 and abs(s_all[i - 1] - s) < abs(s_all[i] - s) else i
            if abs(s_all[j] - s) <= self.reach_m:
                out[k] = o_all[j]
        return out


class _Tracks:
    """The recorded trajectories of all drives, flat, for positions at travelled distances."""

    def __init__(self, drives: Sequence[Drive]) -> None:
        s_parts, xy_parts = [], []
        self.length_m = np.zeros(len(drives))
        for k, d in enumerate(drives):
            xy = np.asarray(d.xy, dtype=float)
            s = arc_length(xy)
            s_parts.append(s)
            xy_parts.append(xy)
            self.length_m[k] = s[-1] if len(s) else 0.0
        self.start = np.concatenate([[0], np.cumsum([len(v) for v in s_parts])]).astype(np.int64)
        self.s = np.concatenate(s_parts) if s_parts else np.zeros(0)
        self.xy = np.concatenate(xy_parts) if xy_parts else np.zeros((0, 2))
        # Each drive's (sorted) distances offset by its index, so one search serves all drives.
        self._big = float(self.length_m.max()) + 1.0 if len(drives) else 1.0
        self._key = self.s + self._big * np.repeat(np.arange(len(drives)), np.diff(self.start))

    def position(self, drive: np.ndarray, s_m: np.ndarray) -> np.ndarray:
        """(N, 2) positions of drives ``drive`` (N,) at their travelled distances ``s_m`` (N,) [m]
        (linear interpolation, clamped to the trajectory)."""
        drive = np.asarray(drive, dtype=np.int64)
        s = np.clip(np.asarray(s_m, dtype=float), 0.0, self.length_m[drive])
        lo, hi = self.start[drive], self.start[drive + 1]
        out = np.empty((len(drive), 2))
        single = hi - lo < 2
        out[single] = self.xy[lo[single]]
        m = ~single
        if m.any():
            j = np.searchsorted(self._key, s[m] + self._big * drive[m], side="right")
            j = np.clip(j, lo[m] + 1, hi[m] - 1)
            s0, s1 = self.s[j - 1], self.s[j]
            w = np.where(s1 > s0, (s[m] - s0) / np.where(s1 > s0, s1 - s0, 1.0), 0.0)[:, None]
            out[m] = (1.0 - w) * self.xy[j - 1] + w * self.xy[j]
        return out


def _step(
    pivot_id: str,
    q: int,
    ps: PivotSamples,
    *,
    drive_ids: tuple[str, ...] = (),
    processed: bool = False,
    maxima: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
    empty: np.ndarray | None = None,
) -> StepResult:
    """Step ``q`` of a pivot: valid with ``maxima`` (lateral_m, types, counts, std_m), else a
    placeholder (rejected, or ``processed`` before) that carries only the step's geometry."""
    lateral_m, types, counts, std_m = maxima if maxima is not None else (_EMPTY_F, _EMPTY_I, _EMPTY_I, _EMPTY_F)
    return StepResult(
        pivot_id=pivot_id,
        index=q,
        s_m=float(ps.s_m[q]),
        midpoint=ps.midpoint[q],
        heading=float(ps.heading[q]),
        width_m=float(ps.width_m[q]),
        valid=maxima is not None,
        processed_before=processed,
        lateral_m=lateral_m,
        types=types,
        counts=counts,
        std_m=std_m,
        drive_ids=drive_ids,
        empty_m=empty,
        pose=(ps.point if ps.pose is None else ps.pose)[q],
    )


def _profiles(
    index: DetectionIndex, evidence: tuple[DetectionIndex, EvidenceConfig], ps: PivotSamples, steps: np.ndarray,
    shift: Callable[[np.ndarray, np.ndarray], np.ndarray] | None, hits: tuple[np.ndarray, ...] | None,
    max_heading_diff_deg: float,
) -> dict[int, np.ndarray]:
    """Empty intervals (``hdmap_core.pipeline.evidence.step_profiles``) of the pivot's ``steps``, from
    the step's midpoint. ``hits``: the pivot's raw same-direction detection crossings (step, t,
    type, drive, drive s) when cached, else intersected here."""
    tindex, cfg = evidence
    if len(steps) == 0:
        return {}
    normal = left_normal(ps.heading).reshape(-1, 2)
    max_diff = np.deg2rad(max_heading_diff_deg)

    def crossings(idx: DetectionIndex, half_m: float) -> tuple[np.ndarray, ...]:
        # same-direction crossings of the steps' cuts: (step, t, drive, drive s)
        c = idx.intersect(ps.point[steps], normal[steps], np.full(len(steps), half_m))
        ok = np.abs(wrap_angle(c.drive_yaw - ps.heading[steps[c.cut]])) <= max_diff
        return steps[c.cut[ok]], c.t_m[ok], c.drive[ok], c.drive_s_m[ok]

    cq, ct, cd, cs = crossings(tindex, cfg.half_length_m)
    if hits is None:
        hq, ht, hd, hs = crossings(index, cfg.half_length_m + cfg.window_m)
    else:
        want = np.zeros(ps.n_steps, dtype=bool)
        want[steps] = True
        ok = want[hits[0]]
        hq, ht, hd, hs = hits[0][ok], hits[1][ok], hits[3][ok], hits[4][ok]
    if shift is not None:
        if len(ct):
            ct = ct + np.asarray(shift(cd.astype(np.int64), cs), dtype=float)
        if len(ht):
            ht = ht + np.asarray(shift(hd.astype(np.int64), hs), dtype=float)
    prof = step_profiles(ps.n_steps, cq, ct, cd, hq, ht, hd, config=cfg)
    mid = np.einsum("ij,ij->i", ps.midpoint - ps.point, normal)
    return {int(q): prof[q] - mid[q] if len(prof[q]) else prof[q] for q in steps.tolist()}


def _run_pivot(
    index: DetectionIndex,
    pivot: Drive,
    skip: np.ndarray,
    *,
    config: PipelineConfig,
    alignment: AlignmentConfig,
    shift: Callable[[np.ndarray, np.ndarray], np.ndarray] | None,
    observations: list[StepObservations] | None,
    counters: _Counters,
    memory: _OffsetMemory | None = None,
    hit_cache: dict | None = None,
    tracks: _Tracks | None = None,
    stride: int = 1,
    evidence: tuple[DetectionIndex, EvidenceConfig] | None = None,
    sampling: SamplingConfig | None = None,
) -> tuple[Segment, np.ndarray, np.ndarray]:
    """Stages 2-4 along one pivot. Returns (segment, marked drive indices, their s [m]).

    The EM runs step by step (offsets are carried along the pivot); sampling before it and the
    aggregation after it run on all steps of the pivot at once. ``stride`` > 1: the EM runs only
    at steps whose index is a multiple of it (the others count as rejected).
    """
    ps = sample_pivot(index, pivot, config=sampling or config.sampling, skip=skip, shift=shift, cache=hit_cache)
    pid = pivot.drive_id
    ids = np.asarray(index.drive_ids, dtype=object)
    n_all = len(index.drive_ids)
    prev = np.full(n_all, np.nan)  # last accepted offset per drive along this pivot
    use_prior = alignment.prior_weight > 0 or alignment.clustering == "auto"
    status = np.zeros(ps.n_steps, dtype=np.int8)  # 0 rejected, 1 skipped, 2 accepted
    status[ps.skipped] = 1
    step_ids: list[tuple[str, ...]] = [()] * ps.n_steps
    cx: list[np.ndarray] = []
    cstep: list[np.ndarray] = []
    clab: list[np.ndarray] = []
    ctyp: list[np.ndarray] = []
    cdrv: list[np.ndarray] = []
    cds: list[np.ndarray] = []
    base = 0
    mem_d: list[np.ndarray] = []
    mem_s: list[np.ndarray] = []
    mem_o: list[np.ndarray] = []
    todo = np.flatnonzero(~ps.skipped)
    if ps.off_cut is not None:
        todo = todo[~ps.off_cut[todo]]  # RULE: the pivot is not on the road its cut describes
    if stride > 1:
        todo = todo[todo % stride == 0]
    # Without offset estimation the steps are independent: all of them clustered and scored at
    # once; the ones a special rule judges are left to align_step.
    batch = align_steps_gap(ps.lateral_m, ps.types, ps.drive, ps.ptr, todo, config=alignment) if gap_batchable(alignment) else {}
    # every step's distinct drives and local drive codes at once (a per-step np.unique each)
    owner = np.repeat(np.arange(ps.n_steps, dtype=np.int64), np.diff(ps.ptr))
    step_drive, sample_code = np.unique(owner * np.int64(n_all) + ps.drive, return_inverse=True)
    code_ptr = np.searchsorted(step_drive, np.arange(ps.n_steps + 1, dtype=np.int64) * n_all)
    step_drive %= n_all
    for q in todo:
        a, b = int(ps.ptr[q]), int(ps.ptr[q + 1])
        if b - a < 2:
            continue
        x, ty, dg = ps.lateral_m[a:b], ps.types[a:b], ps.drive[a:b]
        c0 = int(code_ptr[q])
        uniq, local = step_drive[c0 : int(code_ptr[q + 1])], sample_code[a:b] - c0
        al = batch.get(int(q))
        if al is None:
            prior = prev[uniq] if use_prior else None
            init = None
            if memory is not None and prior is not None and np.isnan(prior).any():
                init = memory.lookup(uniq, ps.drive_s_m[a:b], local)
            al = align_step(x, ty, local, config=alignment, prior=prior, init=init, recheck=bool(q % _RECHECK_EVERY_STEPS < stride))
        step_ids[q] = tuple(ids[uniq])
        if not al.valid:
            continue
        status[q] = 2
        prev[uniq] = al.offsets_m
        lab = np.where(al.labels >= 0, al.labels + base, -1)
        base += int(al.labels.max()) + 1
        if memory is not None:
            cnt = np.bincount(local, minlength=len(uniq))
            s_mean = np.bincount(local, weights=ps.drive_s_m[a:b], minlength=len(uniq)) / np.maximum(cnt, 1)
            mem_d.append(uniq)
            mem_s.append(s_mean)
            mem_o.append(al.offsets_m)
        cx.append(x + al.offsets_m[local])
        cstep.append(np.full(b - a, q))
        clab.append(lab)
        ctyp.append(ty if al.types is None else al.types)
        cdrv.append(dg)
        cds.append(ps.drive_s_m[a:b])
        if observations is not None:
            observations.append(
                StepObservations(
                    pivot_id=pid,
                    index=int(q),
                    midpoint=ps.midpoint[q],
                    heading=float(ps.heading[q]),
                    drive_ids=tuple(ids[dg]),
                    drive_s_m=ps.drive_s_m[a:b],
                    lateral_m=x,
                    types=ty,
                    # a type clash kept as a line of unknown type is no cluster of these types
                    cluster=al.labels if al.types is None else np.where(al.types == ty, al.labels, -1),
                    offsets_m=al.offsets_m[local],
                )
            )
    if memory is not None and mem_d:
        memory.add(np.concatenate(mem_d), np.concatenate(mem_s), np.concatenate(mem_o))
    if cx:
        xs, st, lb, ty, dv, ds = (np.concatenate(v) for v in (cx, cstep, clab, ctyp, cdrv, cds))
        agg = aggregate_many(xs, st, lb, ty, dv, config=config.aggregation)
    else:
        xs = st = lb = ty = dv = ds = _EMPTY_I
        agg = aggregate_many(_EMPTY_F, _EMPTY_I, _EMPTY_I, _EMPTY_I, _EMPTY_I, config=config.aggregation)
    ptr = np.searchsorted(agg.step, np.arange(ps.n_steps + 1))
    has = np.diff(ptr) > 0
    status[(status == 2) & ~has] = 0
    steps: list[StepResult] = []
    # A run of skipped (processed before) steps is represented by its first and last step only:
    # they carry no data, and connection only needs to see where such a run starts and ends.
    sk = status == 1
    inner = sk.copy()
    inner[:-1] &= sk[1:]
    inner[1:] &= sk[:-1]
    if len(inner):
        inner[0] = inner[-1] = False
    empty: dict[int, np.ndarray] = {}
    if evidence is not None:
        cached = hit_cache.get(pid, (None, None))[1] if hit_cache is not None else None
        empty = _profiles(index, evidence, ps, np.flatnonzero(status != 1), shift, cached,
                          config.sampling.max_heading_diff_deg)
    for q in range(ps.n_steps):
        if inner[q]:
            continue
        if status[q] != 2:
            steps.append(_step(pid, q, ps, processed=bool(status[q] == 1), drive_ids=step_ids[q], empty=empty.get(q)))
            continue
        a, b = ptr[q], ptr[q + 1]
        maxima = (agg.lateral_m[a:b], agg.types[a:b], agg.counts[a:b], agg.std_m[a:b])
        steps.append(_step(pid, q, ps, drive_ids=step_ids[q], maxima=maxima, empty=empty.get(q)))
    counters.total += ps.n_steps
    counters.skipped += int((status == 1).sum())
    counters.valid += int((status == 2).sum())
    counters.rejected += int((status == 0).sum())
    if ps.off_cut is not None:
        counters.off_road += int((ps.off_cut & ~ps.skipped).sum())
    # Processed stretches: every drive that took part in an accepted step, keyed by its own
    # travelled distance there (mean of its samples), plus the pivot itself. With ``tracks``
    # (mark_on_cut_only) only drives that were themselves on the refined cut.
    ok = (lb >= 0) & (status[st] == 2) if len(lb) else np.zeros(0, bool)
    key = st[ok] * np.int64(n_all) + dv[ok]
    uk, inv = np.unique(key, return_inverse=True)
    s_mean = np.bincount(inv, weights=ds[ok], minlength=len(uk)) / np.maximum(np.bincount(inv, minlength=len(uk)), 1)
    if tracks is not None and len(uk):
        uq, ud = uk // n_all, uk % n_all
        pos = tracks.position(ud, s_mean)
        lat = ((pos - ps.midpoint[uq]) * left_normal(ps.heading[uq]).reshape(-1, 2)).sum(axis=1)
        if shift is not None:
            lat = lat + np.asarray(shift(ud, s_mean), dtype=float)
        on_cut = np.abs(lat) <= 0.5 * ps.width_m[uq]
        uk, s_mean = uk[on_cut], s_mean[on_cut]
    valid_q = np.flatnonzero(status == 2)
    pidx = index.drive_ids.index(pid)
    md = np.concatenate([uk % n_all, np.full(len(valid_q), pidx)]).astype(np.int64)
    ms = np.concatenate([s_mean, ps.s_m[valid_q]])
    return Segment(pivot_id=pid, steps=tuple(steps)), md, ms


def _run_pass(
    drives: list[Drive],
    index: DetectionIndex,
    order: np.ndarray,
    processed: ProcessedStore,
    *,
    config: PipelineConfig,
    alignment: AlignmentConfig,
    shift: Callable[[np.ndarray, np.ndarray], np.ndarray] | None,
    observations: list[StepObservations] | None,
    counters: _Counters,
    progress: ProgressFn | None,
    hit_cache: dict | None = None,
    tracks: _Tracks | None = None,
    stride: int = 1,
    evidence: tuple[DetectionIndex, EvidenceConfig] | None = None,
    sampling: SamplingConfig | None = None,
) -> tuple[list[Segment], ProcessedStore]:
    segments: list[Segment] = []
    step_m = config.sampling.step_m
    memory = _OffsetMemory(len(drives)) if (alignment.clustering == "auto" and alignment.estimate_offsets) else None
    for n_done, di in enumerate(order):
        pivot = drives[int(di)]
        s, _, _ = pivot_walk(pivot, step_m=step_m)
        skip = processed.contains(pivot.drive_id, s)
        seg, md, ms = _run_pivot(
            index, pivot, skip, config=config, alignment=alignment, shift=shift, observations=observations, counters=counters,
            memory=memory, hit_cache=hit_cache, tracks=tracks, stride=stride, evidence=evidence, sampling=sampling,
        )
        segments.append(seg)
        if len(md):
            marks: dict[str, np.ndarray] = {}
            order_d = np.argsort(md, kind="stable")
            md, ms = md[order_d], ms[order_d]
            cut = np.flatnonzero(np.diff(md)) + 1
            for dd, ss in zip(np.split(md, cut), np.split(ms, cut)):
                marks[index.drive_ids[int(dd[0])]] = ss
            processed = processed.with_marks(marks, pad_m=0.5 * step_m, merge_gap_m=3.0 * step_m)
        if progress is not None:
            progress("pivots", n_done + 1, len(order))
    return segments, processed


def _check_workers(workers: int) -> int:
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise ConfigError(f"workers must be an integer >= 1, got {workers!r}")
    return int(workers)


def _merge_parts(
    parts: list[tuple[list[Segment], ProcessedStore, list | None, _Counters]],
    order: np.ndarray,
    drives: list[Drive],
    store_in: ProcessedStore,
) -> tuple[list[Segment], ProcessedStore, list | None, _Counters]:
    """One pass's results of independent pivot shares, as one process in ``order`` gives them.

    A share's pivots only mark drives of its own groups, so each drive's intervals come from the
    share that owns it (from the input store when no share has its pivots' groups: unchanged).
    """
    if len(parts) == 1:
        return parts[0]
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order))
    pos = {d.drive_id: int(rank[i]) for i, d in enumerate(drives)}
    segments = sorted((seg for p in parts for seg in p[0]), key=lambda seg: pos[seg.pivot_id])
    obs = None
    if parts[0][2] is not None:
        obs = sorted((o for p in parts for o in p[2] or []), key=lambda o: pos[o.pivot_id])
    counters = _Counters()
    for p in parts:
        for f in ("total", "rejected", "skipped", "valid", "off_road"):
            setattr(counters, f, getattr(counters, f) + getattr(p[3], f))
    intervals = dict(store_in.intervals)
    for p in parts:
        for did, iv in p[1].intervals.items():
            if iv != store_in.intervals.get(did):
                intervals[did] = iv
    return segments, ProcessedStore(intervals), obs, counters


def _shift_fn(model: Any, drive_ids: tuple[str, ...]) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    def shift(drive_idx: np.ndarray, s_m: np.ndarray) -> np.ndarray:
        out = np.zeros(len(drive_idx))
        if len(drive_idx) == 0:
            return out
        order = np.argsort(drive_idx, kind="stable")
        di = drive_idx[order]
        cut = np.flatnonzero(np.diff(di)) + 1
        for part in np.split(order, cut):
            out[part] = model.offset(drive_ids[int(drive_idx[part[0]])], s_m[part])
        return out

    return shift


def map_stretches(
    drives: Sequence[Drive],
    *,
    config: PipelineConfig = PipelineConfig.preset("default"),
    seed: int = 0,
    processed: ProcessedStore | None = None,
    collect_observations: bool = False,
    progress: ProgressFn | None = None,
    validated: bool = False,
    offset_model: Any = None,
    observations_only: bool = False,
    workers: int = 1,
) -> MappingResult:
    """Stages 1-4 on valid drives, with the processed-stretch store in and out.

    Args:
        drives: drives (invalid ones are skipped silently here; use ``build_map`` for a report,
            or pass ``validated=True`` when they were checked already).
        config: pipeline options.
        seed: seeds the random pivot order.
        processed: stretches processed earlier (skipped as pivots' steps); not modified.
        collect_observations: also return the per-step observations of the (first) pass.
        progress: optional callback(stage, done, total).
        offset_model: a fleet-wide ``adjustment.OffsetModel`` estimated elsewhere (e.g. from the
            observations of every tile of a live map): only the final pass runs, with the drives
            shifted by it (``config.final_alignment``); no first pass, no adjustment here.
        observations_only: the caller uses only the observations (e.g. a live tile's
            observation pass feeding a fleet-wide adjustment): the EM runs at
            ``config.observation_stride`` as in the first pass of an adjusted build, and the
            segments are those of that pass.
        workers: processes for the pivot passes (this one plus forked children, on systems with
            ``fork``). Only independent pivot groups (``sampling.pivot_groups``, e.g. the two
            carriageways of a highway) run apart, so the result is the one-process result. Do not
            fork from a process with native threads of its own (a ROS node): keep 1 there.

    Returns:
        The segments, the updated store, observations and counters.

    Raises:
        NoUsableDataError: no valid drive.
    """
    if not validated:
        drives, _ = prepare_drives(drives)
    drives = list(drives)
    if not drives:
        raise NoUsableDataError("no valid drive to map")
    # Tens of thousands of tiny (D x D) solves: multithreaded BLAS only adds sync overhead
    # (measured: 3.6 ms per 55 x 55 solve with 2 threads on a loaded 2-core machine).
    limit = threadpool_limits(limits=1, user_api="blas") if threadpool_limits is not None else contextlib.nullcontext()
    with limit:
        return _map_stretches(drives, config=config, seed=seed, processed=processed,
                              collect_observations=collect_observations, progress=progress,
                              offset_model=offset_model, observations_only=observations_only,
                              workers=_check_workers(workers))


def _map_stretches(
    drives: list[Drive],
    *,
    config: PipelineConfig,
    seed: int,
    processed: ProcessedStore | None,
    collect_observations: bool,
    progress: ProgressFn | None,
    offset_model: Any = None,
    observations_only: bool = False,
    workers: int = 1,
) -> MappingResult:
    store_in = processed if processed is not None else ProcessedStore()
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    index = preprocess(drives, config=config.preprocess, workers=workers)
    seconds["preprocess"] = time.perf_counter() - t0
    order = np.random.default_rng(seed).permutation(len(drives))
    obs: list[StepObservations] | None = [] if (collect_observations or config.use_global_adjustment) else None
    hit_cache: dict | None = {} if config.use_global_adjustment else None
    tracks = _Tracks(drives) if config.mark_on_cut_only else None
    model = offset_model
    final = model is not None or (config.use_global_adjustment and not observations_only)
    evidence = None
    if config.evidence is not None and not observations_only:
        t0 = time.perf_counter()
        evidence = (trajectory_index(drives, cell_m=config.preprocess.grid_cell_m), config.evidence)
        seconds["preprocess"] += time.perf_counter() - t0
    shares = [order]
    if workers > 1 and len(drives) > 1 and can_fork():
        t0 = time.perf_counter()
        group = pivot_groups(index, drives, config=config.sampling)
        shares = split_order(order, group, np.array([d.length_m for d in drives]), workers)
        seconds["grouping"] = time.perf_counter() - t0
    first_stride = config.observation_stride if (config.use_global_adjustment or observations_only) else 1
    adjust = model is None and config.use_global_adjustment

    def first(share: np.ndarray, report: ProgressFn | None) -> tuple[list[Segment], ProcessedStore, list | None, _Counters]:
        c = _Counters()
        o: list[StepObservations] | None = [] if obs is not None else None
        segs, st = _run_pass(
            drives, index, share, store_in, config=config, alignment=config.alignment, shift=None,
            observations=o, counters=c, progress=report, hit_cache=hit_cache,
            tracks=tracks, stride=first_stride, evidence=None if final else evidence,
        )
        return segs, st, o, c

    def second(share: np.ndarray, m: Any, report: ProgressFn | None) -> tuple[list[Segment], ProcessedStore, None, _Counters]:
        c = _Counters()
        segs, st = _run_pass(
            drives, index, share, store_in, config=config,
            alignment=config.final_alignment, shift=_shift_fn(m, index.drive_ids),
            observations=None, counters=c, progress=report, hit_cache=hit_cache,
            tracks=tracks, evidence=evidence, sampling=config.final_sampling,
        )
        return segs, st, None, c

    def job(channel: Any, share: np.ndarray) -> None:
        # runs in a worker process: the same passes on its share, results sent back
        m = model
        if m is None:
            segs, st, o, c = first(share, None)
            channel.send((segs if not adjust else [], st, o, c))
            if not adjust:
                return
            m = channel.recv()
        channel.send(second(share, m, None))

    report = None
    if progress is not None:
        total = len(order)
        report = lambda stage, done, _n: progress(stage, done, total)  # noqa: E731
    def run(pass_: Callable[..., tuple]) -> tuple[list[Segment], ProcessedStore, list | None, _Counters]:
        # this process's share here, the others' from their workers (or here, if one failed)
        parts = [pass_(shares[0], report)]
        for w, sh in zip(workers_, shares[1:]):
            got = w.result()
            parts.append(pass_(sh, None) if w.failed else got)
        if progress is not None and len(shares) > 1:
            progress("pivots", len(order), len(order))
        return _merge_parts(parts, order, drives, store_in)

    workers_ = [ForkWorker(lambda ch, sh=sh: job(ch, sh)) for sh in shares[1:]]
    try:
        if model is None:
            t0 = time.perf_counter()
            segments, store, obs, counters = run(first)
            seconds["sampling_em"] = time.perf_counter() - t0
        if adjust:
            try:
                from hdmap_core.pipeline.adjustment import adjust_offsets
            except ImportError as err:  # the module is part of the package; say so clearly if absent
                raise ConfigError(f"use_global_adjustment needs hdmap_core.pipeline.adjustment: {err}") from err
            t0 = time.perf_counter()
            model = adjust_offsets(obs or [], config=config.adjustment)  # set whenever the adjustment runs
            seconds["adjustment"] = time.perf_counter() - t0
        if model is not None:
            t0 = time.perf_counter()
            if adjust:
                for w in workers_:
                    w.send(model)
            segments, store, _, counters = run(lambda sh, rep: second(sh, model, rep))
            seconds["final_pass"] = time.perf_counter() - t0
    finally:
        for w in workers_:
            w.close()
    return MappingResult(
        segments=segments,
        processed=store,
        observations=obs if obs is not None else [],
        offset_model=model,
        counters={
            "steps_total": counters.total,
            "steps_rejected": counters.rejected,
            "steps_skipped_processed": counters.skipped,
            "steps_valid": counters.valid,
            "steps_off_road": counters.off_road,
        },
        stage_seconds=seconds,
    )


def map_segments(
    drives: Sequence[Drive],
    *,
    config: PipelineConfig = PipelineConfig.preset("default"),
    seed: int = 0,
    processed: ProcessedStore | None = None,
) -> list[Segment]:
    """Stages 1-4 only: one ``Segment`` per pivot drive (see ``map_stretches`` for the store)."""
    return map_stretches(drives, config=config, seed=seed, processed=processed).segments


def build_map(
    drives: Sequence[Drive],
    *,
    config: PipelineConfig = PipelineConfig.preset("default"),
    seed: int = 0,
    progress: ProgressFn | None = None,
    workers: int = 1,
) -> BuildResult:
    """Build the hierarchical map from fleet drives (the whole method).

    Invalid drives (``validate_drive`` fails) and repeated drive ids are rejected with a reason
    in the report; the run goes on with the rest.

    Args:
        drives: the fleet drives.
        config: pipeline options (default: the "default" preset).
        seed: seeds the random pivot order.
        progress: optional callback(stage, done, total).
        workers: processes for the pivot passes (see ``map_stretches``); the map is the same.

    Returns:
        The map, the per-pivot segments and the report.

    Raises:
        NoUsableDataError: no usable drive.
    """
    from hdmap_core.graph.connection import ConnectionConfig, connect_segment
    from hdmap_core.graph.map_graph import stitch

    t_start = time.perf_counter()
    drives_in = list(drives)
    usable, rejected = prepare_drives(drives_in)
    if not usable:
        raise NoUsableDataError(f"none of the {len(drives_in)} drive(s) is usable: " + "; ".join(f"{d!r}: {r}" for d, r in rejected[:5]))
    res = map_stretches(usable, config=config, seed=seed, progress=progress, validated=True, workers=workers)
    seconds = dict(res.stage_seconds)
    t0 = time.perf_counter()
    ccfg = config.connection if config.connection is not None else ConnectionConfig()
    segs = res.segments
    # segments are connected one by one: over the workers by their step counts
    graphs = map_balanced(lambda i: connect_segment(segs[i], config=ccfg), [len(g.steps) for g in segs], workers)
    seconds["connection"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    hdmap = stitch(graphs, config=config.stitching) if config.stitching is not None else stitch(graphs)
    seconds["stitching"] = time.perf_counter() - t0
    c = res.counters
    report = BuildReport(
        n_drives_in=len(drives_in),
        n_drives_used=len(usable),
        rejected=rejected,
        km_mapped=c["steps_valid"] * config.sampling.step_m / 1000.0,
        steps_total=c["steps_total"],
        steps_rejected=c["steps_rejected"],
        steps_skipped_processed=c["steps_skipped_processed"],
        steps_off_road=c["steps_off_road"],
        seconds=time.perf_counter() - t_start,
        stage_seconds=seconds,
    )
    return BuildResult(map=hdmap, segments=res.segments, report=report)
