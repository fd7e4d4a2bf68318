"""Preset plus ``KEY=VALUE`` changes -> ``PipelineConfig``: the one way every caller builds a config.

``bag2map``/``bench``/``run --set``, the nodes' ``preset_overrides`` parameter and the scripts all
call :func:`config_from`. A key is a dotted path into ``PipelineConfig``
(``stitching.max_distance_m``, ``final_pass.sparse_step_max_drives``); a value is JSON (numbers,
true/false, null, lists), ``inf``/``-inf``, or else the string itself (:func:`parse_override`).
A key of a rule fixed since (``REMOVED_KEYS``: a constant, or a rule of a stage's switch) is
refused with what became of it.

The two passes: the final pass samples and aligns as the first except where ``PassConfig`` says
otherwise, so a ``sampling.*`` / ``alignment.*`` key reaches both passes and a ``final_pass.*``
key (``final_pass.sparse_step_max_drives``) sets the final pass alone. ``final_pass=null`` drops
the final pass and the adjustment; ``final_pass=true`` adds the recommended one. The switch applies first and
final-pass keys last, whatever their order.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import fields, is_dataclass, replace

from hdmap_core.checks import Rule
from hdmap_core.errors import ConfigError
from hdmap_core.pipeline.config import FinalAlignment, FinalSampling, PassConfig, PipelineConfig
from hdmap_core.pipeline.presets import preset as named_preset

__all__ = ["REMOVED_KEYS", "config_from", "parse_override"]


def _fixed(module: str, constant: str, value: object) -> str:
    return f"a fixed rule now: {constant} = {value!r} in hdmap_core.pipeline.{module}"


def _fixed_graph(module: str, constant: str, value: object) -> str:
    return f"a fixed rule now: {constant} = {value!r} in hdmap_core.graph.{module}"


def _fixed_rules(prefix: str, cls: type) -> dict[str, str]:
    """``{key: text}`` of every fixed rule of the config class ``cls`` (a constant of the class, or
    a :class:`~hdmap_core.checks.Rule` of one of its switches), keys under ``prefix``."""
    out: dict[str, str] = {}
    names = {f.name for f in fields(cls)}
    for klass in reversed(cls.__mro__):
        for name, value in vars(klass).items():
            if name.startswith("_") or name in names:
                continue
            where = f"in {klass.__module__}"
            if isinstance(value, Rule):
                out[prefix + name] = (
                    f"a fixed rule now: {cls.__name__}.{name} = {value.on!r} while {prefix}{value.switch} is true "
                    f"({value.off!r} when false) {where}"
                )
            elif isinstance(value, (bool, int, float, str, tuple)):
                out[prefix + name] = f"a fixed rule now: {cls.__name__}.{name} = {value!r} {where}"
    return out


def _all_fixed_rules() -> dict[str, str]:
    """The fixed rules of every stage config of ``PipelineConfig``, and of the final pass."""
    out: dict[str, str] = {}
    default = PipelineConfig()
    for f in fields(default):
        value = getattr(default, f.name)
        if is_dataclass(value) and not isinstance(value, PassConfig):
            out.update(_fixed_rules(f"{f.name}.", type(value)))
    for cls in (FinalSampling, FinalAlignment):
        final = _fixed_rules("final_pass.", cls)
        out.update({k: v for k, v in final.items() if k.rpartition(".")[2] in vars(cls)})
    return out


#: Keys that were public once and are not any more, with what became of them.
REMOVED_KEYS: dict[str, str] = {
    **_all_fixed_rules(),
    "alignment.lone_cluster_max_std_m": "a fixed rule now: AlignmentConfig.lone_cluster_max_std_m is "
    "alignment.sparse_step_max_std_m while alignment.sparse_step_max_drives > 0 (else 0) "
    "in hdmap_core.pipeline.alignment",
    "stitching.fill_evidence.min_expected": "stitching.fill_evidence is a switch now (true/false): the fill test "
    "uses the profiles of evidence.* (evidence.min_expected)",
    "stitching.fill_evidence.max_seen_ratio": "stitching.fill_evidence is a switch now (true/false): the fill test "
    "uses the profiles of evidence.* (evidence.max_seen_ratio)",
    "use_global_adjustment": "the adjustment runs exactly when there is a final pass: set final_pass=null "
    "(one pass, no adjustment) or final_pass=true",
    "final_sampling": "the final pass is explicit now: final_pass.<field> (PassConfig)",
    "final_alignment": "the final pass is explicit now: final_pass.<field> (PassConfig)",
    "sampling.border_window_m": _fixed("sampling", "_BORDER_WINDOW_M", 2.0),
    "sampling.width_smoothing_steps": _fixed("sampling", "_WIDTH_SMOOTHING_STEPS", 10),
    "sampling.width_decay": _fixed("sampling", "_WIDTH_DECAY", 0.8),
    "sampling.midpoint_smoothing_steps": _fixed("sampling", "_MIDPOINT_SMOOTHING_STEPS", 5),
    "sampling.default_width_m": _fixed("sampling", "_DEFAULT_WIDTH_M", 16.0),
    "sampling.min_width_m": _fixed("sampling", "_MIN_WIDTH_M", 3.0),
    "alignment.k_max": _fixed("alignment", "K_MAX", 6),
    "alignment.single_cluster_silhouette": _fixed("alignment", "SINGLE_CLUSTER_SILHOUETTE", 0.5),
    "alignment.gap_split_m": _fixed("alignment", "GAP_SPLIT_M", 1.0),
    "alignment.penalty_s_per_m2": _fixed("alignment", "PENALTY_S_PER_M2", 0.25),
    "alignment.max_offset_m": _fixed("alignment", "MAX_OFFSET_M", 5.0),
    "aggregation.grid_points": "a fixed rule now: the KDE maximum is searched on 16 grid points "
    "(hdmap_core.pipeline.aggregation.kde_maxima)",
    "aggregation.single_drive_std_m": _fixed("aggregation", "SINGLE_DRIVE_STD_M", 0.5),
    "adjustment.robust_k": _fixed("adjustment", "ROBUST_K", 2.5),
    "adjustment.huber_warmup_iterations": _fixed("adjustment", "HUBER_WARMUP_ITERATIONS", 2),
    "adjustment.tol_m": _fixed("adjustment", "TOL_M", 2e-3),
    "adjustment.reassociate_gate_m": _fixed("adjustment", "REASSOCIATE_GATE_M", 1.0),
    "adjustment.thin_drives": _fixed("adjustment", "THIN_DRIVES", 16),
    "adjustment.shift_search_m": _fixed("adjustment", "SHIFT_SEARCH_M", 4.5),
    "evidence.bands_m": _fixed("evidence", "BANDS_M", (3.0, 6.5, 10.0)),
    "evidence.rates": _fixed("evidence", "RATES", (0.9, 0.6, 0.2)),
    "evidence.window_m": _fixed("evidence", "SEEN_WINDOW_M", 1.0),
    "evidence.bin_m": _fixed("evidence", "_BIN_M", 0.5),
    "evidence.half_length_m": _fixed("evidence", "PROFILE_HALF_LENGTH_M", 15.0),
    "evidence.min_interval_m": _fixed("evidence", "_MIN_INTERVAL_M", 2.5),
    "evidence.refute_share": _fixed("evidence", "_REFUTE_SHARE", 0.5),
    "evidence.sample_m": _fixed("evidence", "_SAMPLE_M", 2.0),
    "evidence.min_edge_m": _fixed("evidence", "_MIN_EDGE_M", 3.0),
    "evidence.along_m": _fixed("evidence", "_ALONG_M", 1.0),
    "evidence.heading_deg": _fixed("evidence", "_HEADING_DEG", 30.0),
    "connection.bridge_edge_min_m": _fixed_graph("assignment", "_BRIDGE_EDGE_MIN_M", 3.0),
    "connection.line_frame_min_m": _fixed_graph("connection", "_LINE_FRAME_MIN_M", 1.5),
    "connection.tip_frame_max_deg": _fixed_graph("connection", "_TIP_FRAME_MAX_DEG", 30.0),
    "connection.tip_frame_min_m": _fixed_graph("connection", "_TIP_FRAME_MIN_M", 4.0),
    "connection.max_mean_angle_deg": _fixed_graph("connection", "_MAX_MEAN_ANGLE_DEG", 15.0),
    "stitching.end_stub_side_m": _fixed_graph("cleanup", "_END_STUB_SIDE_M", 2.0),
    "stitching.join_gap_coverage": _fixed_graph("loose_ends", "_JOIN_GAP_COVERAGE", 0.8),
    "stitching.refuted_piece_max_drives": _fixed_graph("export", "_REFUTED_PIECE_MAX_DRIVES", 1),
    "stitching.track_bridge_heading_deg": _fixed_graph("tracks", "_TRACK_BRIDGE_HEADING_DEG", 45.0),
    "stitching.track_max_gap_m": _fixed_graph("tracks", "_TRACK_MAX_GAP_M", 6.0),
    "stitching.track_max_jump_m": _fixed_graph("tracks", "_TRACK_MAX_JUMP_M", 12.0),
    "stitching.angle_free_m": _fixed_graph("links", "_ANGLE_FREE_M", 3.0),
    "stitching.behind_tol_m": _fixed_graph("links", "_BEHIND_TOL_M", 1.0),
    "stitching.branch_any_marking": _fixed_graph("loose_ends", "_BRANCH_ANY_MARKING", True),
    "stitching.branch_divergence_m": _fixed_graph("loose_ends", "_BRANCH_DIVERGENCE_M", 0.3),
    "stitching.branch_radius_m": _fixed_graph("loose_ends", "_BRANCH_RADIUS_M", 8.0),
    "stitching.duplicate_m": _fixed_graph("linking", "_DUPLICATE_M", 0.25),
    "stitching.edge_line_max_drives": _fixed_graph("export", "_EDGE_LINE_MAX_DRIVES", 1),
    "stitching.end_stub_slope": _fixed_graph("cleanup", "_END_STUB_SLOPE", 0.1),
    "stitching.feature_max_m": _fixed_graph("linking", "_FEATURE_MAX_M", 2.0),
    "stitching.join_angle_deg": _fixed_graph("loose_ends", "_JOIN_ANGLE_DEG", 1.0),
    "stitching.join_gap_heading_deg": _fixed_graph("loose_ends", "_JOIN_GAP_HEADING_DEG", 10.0),
    "stitching.join_lateral_m": _fixed_graph("loose_ends", "_JOIN_LATERAL_M", 0.5),
    "stitching.join_line_cross_lateral_m": _fixed_graph("loose_ends", "_JOIN_LINE_CROSS_LATERAL_M", 12.0),
    "stitching.overlap_along_m": _fixed_graph("trim", "_OVERLAP_ALONG_M", 1.2),
    "stitching.overlap_feature_m": _fixed_graph("trim", "_OVERLAP_FEATURE_M", 0.5),
    "stitching.overlap_radius_m": _fixed_graph("trim", "_OVERLAP_RADIUS_M", 1.2),
    "stitching.overlap_share": _fixed_graph("trim", "_OVERLAP_SHARE", 0.6),
    "stitching.path_curvature_m": _fixed_graph("linking", "_PATH_CURVATURE_M", 20.0),
    "stitching.twin_along_m": _fixed_graph("loose_ends", "_TWIN_ALONG_M", 1.2),
    "stitching.twin_lateral_m": _fixed_graph("loose_ends", "_TWIN_LATERAL_M", 0.5),
}


def _removed(key: str) -> str | None:
    """What became of a removed ``key``, or None when it is not one."""
    return REMOVED_KEYS.get(key) or REMOVED_KEYS.get(key.partition(".")[0])


def parse_override(text: str) -> tuple[str, object]:
    """One ``KEY=VALUE`` change as ``--set`` and the nodes' ``preset_overrides`` take it: the dotted
    key and the value as JSON (numbers, true/false, null, lists), ``inf`` / ``-inf`` as floats
    (several limits are off at inf, e.g. ``connection.max_gap_m=inf``), else the string
    itself (``alignment.clustering=auto``). Whether it fits is :func:`config_from`'s check.

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


def config_from(
    preset: str | PipelineConfig = "default", overrides: Mapping[str, object] | Iterable[str] = ()
) -> PipelineConfig:
    """The preset (a name, or a config) with each override applied.

    Args:
        preset: "default", "paper", "naive" (``hdmap_core.pipeline.presets``) or a config.
        overrides: ``{dotted key: value}``, or ``KEY=VALUE`` texts (parsed by :func:`parse_override`).

    Returns:
        The config; with any override its name gets a ``+`` (the preset with changes), so reports
        do not pass it off as the preset itself.

    Raises:
        ConfigError: an unknown preset, a key that names no field (or a removed one, or the final
            pass of a config without one), or a value the field rejects; the message names the key.
    """
    config = named_preset(preset) if isinstance(preset, str) else preset
    if isinstance(overrides, Mapping):
        items = list(overrides.items())
    else:
        items = [parse_override(text) for text in overrides]
    for key, _ in items:
        if (what := _removed(key)) is not None:
            raise ConfigError(f"{key}: no such setting any more ({what})")
    switches = [(k, v) for k, v in items if k == "final_pass"]
    final = [(k, v) for k, v in items if k.startswith("final_pass.")]
    first = [(k, v) for k, v in items if k != "final_pass" and not k.startswith("final_pass.")]
    for key, value in switches:
        config = _switch_final_pass(config, key, value)
    for key, value in first + final:
        if key.startswith("final_pass.") and config.final_pass is None:
            raise ConfigError(f"{key}: the final pass is off in this config (final_pass is null: set final_pass=true)")
        config = _checked(config, key, value)
    if items and not config.name.endswith("+"):
        config = replace(config, name=f"{config.name}+")
    return config


def _checked(config: PipelineConfig, key: str, value: object) -> PipelineConfig:
    """``config`` with ``key`` set; a failing ``PipelineConfig`` check is named by ``key``."""
    try:
        return _override(config, key, value, key)  # type: ignore[return-value]
    except ConfigError as err:
        if str(err).startswith(key):
            raise
        raise ConfigError(f"{key}: {err}") from err


def _switch_final_pass(config: PipelineConfig, key: str, value: object) -> PipelineConfig:
    """``final_pass=null|false`` (one pass) or ``final_pass=true`` (the recommended final pass)."""
    if value is None or value is False:
        return replace(config, final_pass=None)
    if value is True:
        if config.final_pass is not None:
            return config
        return replace(config, final_pass=PassConfig())
    raise ConfigError(
        f"{key}={_shown(value)}: final_pass is a group of settings; set one of its fields, e.g. "
        "final_pass.sparse_step_max_drives=..., or true / null to switch the final pass on / off"
    )


def _group_error(key: str, value: object, group: object) -> ConfigError:
    """The error for a value given to a whole stage config (``key``, holding ``group``)."""
    example = fields(group)[0].name  # type: ignore[arg-type]
    name = key.rpartition(".")[2]
    return ConfigError(
        f"{key}={_shown(value)}: {name} is a group of settings; set one of its fields, e.g. {key}.{example}=..."
    )


def _shown(value: object) -> str:
    """A ``--set`` value as it is written there (``true``, ``null``, ``inf``, ``'gap'``)."""
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)  # inf, -inf, nan
    try:
        return json.dumps(value)
    except (TypeError, ValueError):
        return repr(value)


def _override(config: object, key: str, value: object, full: str) -> object:
    """``config`` (a dataclass) with the dotted ``key`` set to ``value`` (``full``: the whole key)."""
    head, _, rest = key.partition(".")
    if not is_dataclass(config) or head not in {f.name for f in fields(config)}:
        raise ConfigError(f"{full}: {type(config).__name__} has no field {head!r}")
    now = getattr(config, head)
    if not rest:
        spec = next(f for f in fields(config) if f.name == head)
        optional = value is None and "None" in str(spec.type)
        if is_dataclass(now) and not optional:
            raise _group_error(full, value, now)
        if value is None and not optional:
            raise ConfigError(f"{full}=null: not a valid value ({head} cannot be off)")
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        if not optional and isinstance(now, (int, float)) and not isinstance(now, bool) and not number:
            raise ConfigError(f"{full}={_shown(value)}: not a valid value (a number is expected)")
        if isinstance(now, bool) and not isinstance(value, bool):
            raise ConfigError(f"{full}={_shown(value)}: not a valid value (true or false is expected)")
        try:
            return replace(config, **{head: value})  # type: ignore[type-var]  # a dataclass instance, checked above
        except ConfigError as err:
            raise ConfigError(f"{full}: {err}") from err
        except (TypeError, ValueError) as err:  # a value of the wrong kind fails the field's check
            raise ConfigError(f"{full}={_shown(value)}: not a valid value ({err})") from err
    if now is None:
        raise ConfigError(f"{full}: {head} is off (None) in this config")
    return replace(config, **{head: _override(now, rest, value, full)})  # type: ignore[type-var]
