"""Tests of the configuration: PipelineConfig's defaults, the presets, config_from, the range check."""

from __future__ import annotations

import dataclasses
import math

import pytest

from hdmap_core.checks import check_range
from hdmap_core.errors import ConfigError
from hdmap_core.graph.connection_config import ConnectionConfig
from hdmap_core.graph.stitch_config import StitchConfig
from hdmap_core.pipeline.adjustment import AdjustConfig
from hdmap_core.pipeline.aggregation import AggregationConfig
from hdmap_core.pipeline.alignment import AlignmentConfig
from hdmap_core.pipeline.config import FinalAlignment, FinalSampling, PassConfig, PipelineConfig
from hdmap_core.pipeline.evidence import EvidenceConfig
from hdmap_core.pipeline.overrides import REMOVED_KEYS, config_from, parse_override
from hdmap_core.pipeline.preprocess import PreprocessConfig
from hdmap_core.pipeline.presets import PRESETS, naive, paper, preset
from hdmap_core.pipeline.sampling import SamplingConfig


def _differences(a: object, b: object) -> set[str]:
    """Dotted names of the leaf fields where two configs differ."""
    out: set[str] = set()
    for f in dataclasses.fields(a):  # type: ignore[arg-type]
        x, y = getattr(a, f.name), getattr(b, f.name)
        if dataclasses.is_dataclass(x) and dataclasses.is_dataclass(y) and type(x) is type(y):
            out |= {f"{f.name}.{n}" for n in _differences(x, y)}
        elif x != y:
            out.add(f.name)
    return out


def test_the_defaults_are_the_recommended_method():
    cfg = PipelineConfig()
    assert preset("default") == cfg and cfg.name == "default"
    assert cfg.final_pass is not None and cfg.use_global_adjustment  # two passes with the adjustment
    assert cfg.alignment.solver == "closed_form" and cfg.final_alignment.clustering == "gap"
    assert cfg.final_sampling.outer_border_reach and not cfg.sampling.outer_border_reach
    # the final pass keeps the adjustment's offsets and differs from the first only by its own rules
    final = cfg.final_alignment
    assert isinstance(final, FinalAlignment) and isinstance(cfg.final_sampling, FinalSampling)
    assert _differences(final, cfg.alignment) == {
        "estimate_offsets",
        "clustering",
        "prior_weight",
        "sparse_step_max_drives",
    }
    assert (final.estimate_offsets, final.prior_weight, final.sparse_step_max_drives) == (False, 0.0, 4)
    assert final.sparse_singletons_accept and not cfg.alignment.sparse_singletons_accept
    assert (final.sparse_type_clash_max_drives, final.sparse_disjoint_apart_m, final.sparse_type_clash_keep) == (
        3,
        2.0,
        True,
    )
    assert not _differences(cfg.final_sampling, cfg.sampling)
    assert cfg.stitching.fill_evidence and cfg.evidence is not None
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.final_pass = None  # type: ignore[misc]


@pytest.mark.parametrize(
    "cls",
    [
        PreprocessConfig,
        SamplingConfig,
        AlignmentConfig,
        AggregationConfig,
        AdjustConfig,
        PassConfig,
        ConnectionConfig,
        StitchConfig,
        EvidenceConfig,
    ],
)
def test_every_stage_class_default_is_the_recommended_stage(cls):
    """``XConfig()`` is what ``PipelineConfig()`` holds: no stage keeps other values of its own."""
    held = [v for f in dataclasses.fields(PipelineConfig) if isinstance(v := getattr(PipelineConfig(), f.name), cls)]
    assert held == [cls()]


def test_common_sigma_is_the_adjustment_prior_of_one_drive():
    prior = AdjustConfig()
    assert AggregationConfig().common_sigma_m == math.hypot(prior.bias_sigma_m, prior.drift_sigma_m)


def test_a_switch_turns_its_family_of_fixed_rules_off():
    on, off = StitchConfig(), StitchConfig(refined=False, cleanup=False, track_links=False)
    assert (on.track_search_m, off.track_search_m) == (60.0, 0.0)
    assert (on.path_max_turn_deg, off.path_max_turn_deg) == (60.0, 180.0)
    assert (on.gore_max_m, off.gore_max_m) == (100.0, 0.0)
    assert on.overlap_search_m == off.overlap_search_m == 8.0  # a constant of every preset
    assert StitchConfig(cleanup=False).track_search_m == 60.0  # each switch its own family
    assert (ConnectionConfig(cleanup=False).leftover_max_m, ConnectionConfig().leftover_max_m) == (math.inf, 2.0)
    assert SamplingConfig(refined=False).max_pivot_outside_m == math.inf
    assert AlignmentConfig(sparse_step_max_drives=0).lone_cluster_max_std_m == 0.0
    assert AlignmentConfig(sparse_step_max_std_m=0.2).lone_cluster_max_std_m == 0.2
    with pytest.raises(TypeError):
        StitchConfig(track_search_m=1.0)  # type: ignore[call-arg]  # not a field


def test_paper_differs_from_the_default_only_where_listed():
    """``paper()`` is one pass with the paper's stage settings and the paper's Sec. V-VI."""
    p, d = paper(), PipelineConfig()
    assert p.final_pass is None and not p.use_global_adjustment and p.evidence is None
    assert _differences(p, d) == {
        "sampling.refined",
        "alignment.clustering",
        "alignment.n_iterations",
        "alignment.solver",
        "alignment.robust_loss",
        "alignment.prior_weight",
        "alignment.sparse_step_max_drives",
        "aggregation.kde_bandwidth_factor",
        "aggregation.kde_min_bandwidth_m",
        "aggregation.common_sigma_m",
        "aggregation.refined",
        "final_pass",
        "observation_stride",
        "connection.min_support_share",
        "connection.cleanup",
        "connection.refined",
        "stitching.fill_spacing_m",
        "stitching.min_isolated_length_m",
        "stitching.cleanup",
        "stitching.refined",
        "stitching.track_links",
        "stitching.fill_evidence",
        "mark_on_cut_only",
        "evidence",
        "name",
    }


def test_naive_corrects_no_offset_and_differs_from_paper_only_as_listed():
    n, p = naive(), paper()
    assert not n.alignment.estimate_offsets and n.final_pass is None
    assert n.aggregation.method == "mean" and not n.aggregation.overlap_filter
    # the exact list of what else differs from the paper: the EM gate off, the first clean-up rules
    assert _differences(n, p) == {
        "alignment.estimate_offsets",
        "alignment.silhouette_gate",
        "aggregation.method",
        "aggregation.overlap_filter",
        "connection.min_support_share",
        "connection.cleanup",
        "stitching.fill_spacing_m",
        "stitching.min_isolated_length_m",
        "stitching.cleanup",
        "name",
    }
    assert not (n.connection.refined or n.stitching.refined or n.stitching.track_links)


def test_preset_names_an_unknown_one():
    assert set(PRESETS) == {"default", "paper", "naive"}
    assert all(PRESETS[k]().name == k for k in PRESETS)
    with pytest.raises(ConfigError, match="unknown pipeline preset 'fast'"):
        preset("fast")
    with pytest.raises(ConfigError, match="unknown pipeline preset"):
        config_from("fast", {})


def test_config_from_sets_dotted_fields_and_names_a_wrong_one():
    base = PipelineConfig()
    cfg = config_from("default", {"stitching.track_links": False, "alignment.n_iterations": 2, "observation_stride": 3})
    assert cfg.stitching.track_rejoin_m == 0.0 and base.stitching.track_rejoin_m == 30.0
    assert cfg.alignment.n_iterations == 2 and cfg.observation_stride == 3
    assert cfg.stitching.path_search_m == base.stitching.path_search_m  # the rest untouched
    assert cfg.name == "default+" and config_from(base, {}) == base  # changed, and said so
    # KEY=VALUE texts as the CLI and the nodes give them
    assert config_from("paper", ["stitching.max_distance_m=8", "aggregation.method=mean"]) == config_from(
        "paper", {"stitching.max_distance_m": 8.0, "aggregation.method": "mean"}
    )
    with pytest.raises(ConfigError, match="stitching.nope: StitchConfig has no field 'nope'"):
        config_from(base, {"stitching.nope": 1})
    with pytest.raises(ConfigError, match="stitching.max_distance_m: .*max_distance_m"):  # the field's own check
        config_from(base, {"stitching.max_distance_m": -1.0})
    with pytest.raises(ConfigError, match=r"sampling.margin_m='wide': not a valid value \(a number is expected\)"):
        config_from(base, {"sampling.margin_m": "wide"})
    with pytest.raises(ConfigError, match=r"stitching.track_links=1: not a valid value \(true or false is expected\)"):
        config_from(base, {"stitching.track_links": 1})
    assert config_from(base, ["connection.max_gap_m=inf"]).connection.max_gap_m == float("inf")
    # null where the field may be off (None), refused where it may not
    assert config_from(base, {"stitching.fill_evidence": False, "evidence": None}).evidence is None
    with pytest.raises(ConfigError, match="stitching=null: .*group of settings"):
        config_from(base, {"stitching": None})
    with pytest.raises(ConfigError, match="fill_evidence needs"):  # PipelineConfig's own check, named
        config_from(base, {"evidence": None})
    with pytest.raises(ConfigError, match="observation_stride"):
        config_from(base, {"observation_stride": 0})
    with pytest.raises(
        ConfigError,
        match=r"sampling=1: sampling is a group of settings; set one of its fields, e\.g\. sampling\.step_m",
    ):
        config_from(base, {"sampling": 1})
    with pytest.raises(ConfigError, match="connection=true: connection is a group of settings"):
        config_from(base, {"connection": True})


def test_a_removed_key_is_named_with_what_to_do_instead():
    for key in ("use_global_adjustment", "final_sampling.outer_border_reach", "final_alignment"):
        with pytest.raises(ConfigError, match=rf"{key}: no such setting any more \(.*final_pass"):
            config_from("default", {key: True})
    assert set(REMOVED_KEYS) >= {"use_global_adjustment", "final_sampling", "final_alignment"}


def test_the_final_pass_is_switched_and_set_on_its_own():
    base = PipelineConfig()
    one = config_from(base, {"final_pass": None})
    assert one.final_pass is None and not one.use_global_adjustment
    assert (one.final_sampling, one.final_alignment) == (one.sampling, one.alignment)  # one pass
    with pytest.raises(ConfigError, match="final_pass.sparse_step_max_drives: the final pass is off"):
        config_from("paper", {"final_pass.sparse_step_max_drives": 2})
    # switched on (the recommended final pass), its fields can be set with it, in any order
    on = config_from("paper", {"final_pass.sparse_step_max_drives": 2, "final_pass": True})
    assert on.final_pass == PassConfig(sparse_step_max_drives=2) and on.alignment.sparse_step_max_drives == 0
    assert on.final_alignment.sparse_step_max_drives == 2 and not on.final_alignment.estimate_offsets
    with pytest.raises(ConfigError, match="final_pass=1: final_pass is a group of settings"):
        config_from(base, {"final_pass": 1})
    with pytest.raises(ConfigError, match="final_pass.nope: PassConfig has no field 'nope'"):
        config_from(base, {"final_pass.nope": 1})
    with pytest.raises(
        ConfigError, match="final_pass.sparse_step_max_drives: PassConfig.sparse_step_max_drives must be"
    ):
        config_from(base, {"final_pass.sparse_step_max_drives": -1})


def test_a_first_pass_change_reaches_the_final_pass_unless_the_pass_sets_it():
    base = PipelineConfig()
    cfg = config_from(base, {"sampling.refined": False, "alignment.robust_loss": False, "sampling.step_m": 3.0})
    assert cfg.sampling.max_pivot_outside_m == cfg.final_sampling.max_pivot_outside_m == math.inf
    assert cfg.alignment.robust_loss is False and cfg.final_alignment.robust_loss is False
    assert cfg.final_sampling.step_m == 3.0
    # the sparse-step limit is the final pass's own: a first-pass key leaves it
    cfg = config_from(base, {"alignment.sparse_step_max_drives": 1, "alignment.clustering": "silhouette"})
    assert cfg.final_alignment == base.final_alignment and cfg.alignment.clustering == "silhouette"
    # ... and a final-pass key sets that pass alone, in either order
    for items in (
        {"alignment.sparse_step_max_drives": 1, "final_pass.sparse_step_max_drives": 2},
        {"final_pass.sparse_step_max_drives": 2, "alignment.sparse_step_max_drives": 1},
    ):
        cfg = config_from(base, items)
        assert (cfg.alignment.sparse_step_max_drives, cfg.final_alignment.sparse_step_max_drives) == (1, 2)


def test_adjustment_settings_are_changeable_with_set():
    changed = config_from("default", {"adjustment.loss": "linear", "adjustment.drift_sigma_m": 0.0})
    assert changed.adjustment == dataclasses.replace(AdjustConfig(), loss="linear", drift_sigma_m=0.0)
    with pytest.raises(ConfigError, match="adjustment.loss: AdjustConfig.loss must be one of"):
        config_from("default", {"adjustment.loss": "l3"})


def test_parse_override_reads_json_values_else_strings():
    assert parse_override("stitching.track_rejoin_m=0.5") == ("stitching.track_rejoin_m", 0.5)
    assert parse_override(" a.b = true") == ("a.b", True)
    assert parse_override("alignment.clustering=auto") == ("alignment.clustering", "auto")
    assert parse_override("a.b=[1, 2]") == ("a.b", [1, 2])
    for text in ("inf", "Infinity", " INF", "+inf"):
        assert parse_override(f"sampling.max_pivot_outside_m={text}") == ("sampling.max_pivot_outside_m", float("inf"))
    assert parse_override("a.b=-inf") == ("a.b", float("-inf"))
    for bad in ("a.b", "=1", " =1"):
        with pytest.raises(ConfigError, match="is not KEY=VALUE"):
            parse_override(bad)


@dataclasses.dataclass
class _Probe:
    length_m: float = 1.0
    count: int = 1
    angle_deg: float = 90.0


@pytest.mark.parametrize(
    ("changes", "kwargs", "message"),
    [
        ({"length_m": 0.0}, dict(low=0.0, low_open=True), r"_Probe.length_m must be > 0, got 0.0"),
        ({"length_m": -1.0}, dict(low=0.0), r"_Probe.length_m must be >= 0, got -1.0"),
        ({"length_m": float("inf")}, dict(low=0.0, finite=True), r"must be finite and >= 0, got inf"),
        ({"length_m": float("nan")}, dict(low=0.0), r"must be >= 0, got nan"),
        ({"angle_deg": 181.0}, dict(low=0.0, high=180.0, low_open=True), r"angle_deg must be in \(0, 180\], got 181.0"),
        ({"count": 1.5}, dict(low=1, integer=True), r"count must be an integer >= 1, got 1.5"),
        ({"count": True}, dict(low=1, integer=True), r"count must be an integer >= 1, got True"),
    ],
)
def test_check_range_names_config_field_interval_and_value(changes, kwargs, message):
    probe = _Probe(**changes)
    name = next(iter(changes))
    with pytest.raises(ConfigError, match=message):
        check_range(probe, (name,), **kwargs)
    check_range(_Probe(), (name,), **kwargs)  # the default passes


@pytest.mark.parametrize("key", sorted(k for k in REMOVED_KEYS if "." in k))
def test_a_knob_made_a_constant_is_refused_by_name_and_its_constant_exists(key):
    """Each removed knob names the constant (or the switched rule) that replaced it, with its value."""
    import importlib
    import re

    with pytest.raises(
        ConfigError, match=rf"^{re.escape(key)}: no such setting any more \((a fixed rule now|.*switch)"
    ):
        config_from("default", {key: 1.0})
    text = REMOVED_KEYS[key]
    m = re.search(
        r"(\w+(?:\.\w+)?) = (.+?)(?: while (\S+) is true \((.+) when false\))? in (hdmap_core\.\w+\.\w+)$", text
    )
    if m is None:  # the KDE grid names its function, a former group names what replaced it
        assert key == "aggregation.grid_points" or "is a switch now" in text or " is " in text
        return
    owner = importlib.import_module(m.group(5))
    for part in m.group(1).split("."):
        owner = getattr(owner, part)
    if m.group(3) is None:
        assert repr(owner) == m.group(2)  # the constant exists with the value the message gives
    else:  # a rule of a switch: its values on and off, and the switch a public key
        assert (repr(owner.on), repr(owner.off)) == (m.group(2), m.group(4))
        assert m.group(3) not in REMOVED_KEYS and config_from("default", {m.group(3): False})


def test_the_table_lists_every_fixed_rule_of_the_stage_classes():
    """No constant of a stage class is left out of docs/parameters.md's fixed rules."""
    from hdmap_core.checks import Rule

    for prefix, cls in (
        ("stitching.", StitchConfig),
        ("connection.", ConnectionConfig),
        ("sampling.", SamplingConfig),
        ("aggregation.", AggregationConfig),
    ):
        rules = {n for n, v in vars(cls).items() if isinstance(v, Rule)}
        assert rules and {prefix + n for n in rules} <= set(REMOVED_KEYS)
