"""Tests of the generated parameter table (docs/parameters.md) and of --set for every key in it."""

from __future__ import annotations

import dataclasses
import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

from hdmap_core.pipeline.config import PipelineConfig
from hdmap_core.pipeline.overrides import config_from

REPO = Path(__file__).resolve().parents[2]


def _load() -> ModuleType:
    spec = importlib.util.spec_from_file_location("_scripts_param_table", REPO / "scripts" / "param_table.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def table() -> ModuleType:
    return _load()


def test_the_committed_table_is_the_one_the_code_makes(table):
    """Stale when a field, a default, a preset or a docstring changed without
    ``python scripts/param_table.py``."""
    assert (REPO / "docs" / "parameters.md").read_text() == table.render()


def test_every_listed_key_has_an_effect(table):
    text = table.render()
    rows = [line for line in text.splitlines() if line.startswith("| `")]
    assert rows and all(not line.rstrip().endswith("|  |") for line in rows)
    assert f"{len(table.public_keys())} settable keys." in text


def test_every_public_key_is_settable_with_set(table):
    """Each key takes its own default back (a no-op), so config_from reaches every one of them."""
    base = PipelineConfig()
    assert table.public_keys()
    for key in table.public_keys():
        value = base
        for part in key.split("."):
            value = getattr(value, part)
        got = config_from(base, {key: value})
        assert dataclasses.replace(got, name=base.name) == base, key


def test_the_public_parameters_are_few(table):
    """At most ~60 keys: a rule measured and adopted is a constant, not a knob (STYLE.md)."""
    assert len(table.public_keys()) <= 60
