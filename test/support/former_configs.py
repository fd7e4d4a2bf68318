"""The stage classes' former own defaults, for the rule tests written against them.

Until the stage classes' defaults became the recommended method, ``SamplingConfig()``,
``AlignmentConfig()`` and ``AggregationConfig()`` were the paper's reading and
``ConnectionConfig()`` / ``StitchConfig()`` the graph's first implementation (no ``refined`` or
``track_links`` rules); many tests switch one rule on against that plain base. ``former(cls, **kw)``
is exactly the former ``cls(**kw)``: public fields in ``kw`` are passed on, and a fixed rule in
``kw`` (a class constant, or a ``Rule`` of a switch) is set on a subclass made for the call, so a
test can still probe a rule at another value than the adopted one. ``former_paper(cls)`` is the
stage of the ``paper`` preset (the former ``cls.paper()``).
"""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

from hdmap_core.graph.connection_config import ConnectionConfig
from hdmap_core.graph.stitch_config import StitchConfig
from hdmap_core.pipeline.aggregation import AggregationConfig
from hdmap_core.pipeline.alignment import AlignmentConfig
from hdmap_core.pipeline.evidence import EvidenceConfig
from hdmap_core.pipeline.presets import paper
from hdmap_core.pipeline.sampling import SamplingConfig

__all__ = ["former", "former_paper", "former_replace"]

C = TypeVar("C")

# the former defaults: public fields ...
_FIELDS: dict[type, dict[str, Any]] = {
    SamplingConfig: {"refined": False},
    AlignmentConfig: {
        "clustering": "silhouette",
        "n_iterations": 5,
        "solver": "lm",
        "robust_loss": False,
        "prior_weight": 0.0,
        "sparse_step_max_drives": 0,
    },
    AggregationConfig: {
        "kde_bandwidth_factor": 6.0,
        "kde_min_bandwidth_m": 0.02,
        "common_sigma_m": 0.0,
        "refined": False,
    },
    ConnectionConfig: {"refined": False},
    StitchConfig: {"refined": False, "track_links": False, "fill_evidence": False},
    EvidenceConfig: {"min_expected": 3.0},
}
# ... and rules whose former default no preset reached (each was inert where the presets used it)
_RULES: dict[type, dict[str, Any]] = {
    AlignmentConfig: {"lone_cluster_max_std_m": 0.0, "sparse_type_clash_m": 0.0, "penalty_lm_threshold": 0.3},
    ConnectionConfig: {"lone_line_border_gap_m": None, "lone_line_border_outer": False},
}


def former(cls: type[C], **kw: Any) -> C:
    """The former ``cls(**kw)`` (module docstring)."""
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    rules = {**_RULES.get(cls, {}), **{k: v for k, v in kw.items() if k not in names}}
    for name in rules:
        assert hasattr(cls, name), f"{cls.__name__} has no field or fixed rule {name!r}"
    made = type(cls.__name__, (cls,), rules) if rules else cls
    return made(**{**_FIELDS.get(cls, {}), **{k: v for k, v in kw.items() if k in names}})


def former_paper(cls: type[C]) -> C:
    """The ``paper`` preset's stage of class ``cls``."""
    p = paper()
    return next(getattr(p, f.name) for f in dataclasses.fields(p) if type(getattr(p, f.name)) is cls)


def former_replace(obj: C, **kw: Any) -> C:
    """``dataclasses.replace(obj, **kw)`` where ``kw`` may also name fixed rules (set as in
    :func:`former`, on a subclass of ``obj``'s class)."""
    cls = type(obj)
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    rules = {k: v for k, v in kw.items() if k not in names}
    for name in rules:
        assert hasattr(cls, name), f"{cls.__name__} has no field or fixed rule {name!r}"
    made = type(cls.__name__, (cls,), rules) if rules else cls
    kept = {f.name: getattr(obj, f.name) for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    return made(**{**kept, **{k: v for k, v in kw.items() if k in names}})
