"""Shared fixtures and the environment of the whole suite.

DDS: every test that starts DDS sets loopback discovery and a domain of its own through
support/nodes_harness.py (the DDS rule and the domains are written there). The discovery range is
also set here for the whole run, before any test module imports rclpy, so a bare ``pytest`` run is
as safe as ``make test`` (which exports the same).

Helper modules shared by several test folders live in ``test/support/`` (on ``pythonpath`` in
pytest.ini): ``pipeline_fleet`` (a tiny deterministic fleet for the stage tests), ``bag_samples``
(drives and maps for bag and message round trips), ``nodes_harness`` (the DDS harness).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import pytest

# Discovery on loopback only: Fast DDS would otherwise multicast out of the network interface.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

REPO_ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def repo_root() -> Path:
    """The repository's top folder (scripts/, bags/, docs/ below it)."""
    return REPO_ROOT


@pytest.fixture(scope="session")
def sample_bags() -> Path:
    """bags/ of the repository: the two 20-drive sample fleets (``e6mini_20``, ``ramps_20``, each
    with ``.gt.json`` and ``.sim.json``) and the damaged inputs (bags/README.md)."""
    return REPO_ROOT / "bags"


@pytest.fixture
def fixed(monkeypatch: pytest.MonkeyPatch):
    """Set fixed rules of config classes for one test, to probe a rule at another value than the
    adopted one: ``fixed(StitchConfig, track_search_m=20.0)``. A rule set here holds whatever the
    class's switches say (a plain class attribute replaces the switched ``Rule``)."""

    def set_rules(cls: type, **values: object) -> None:
        fields = {f.name for f in dataclasses.fields(cls)}
        for name, value in values.items():
            assert hasattr(cls, name) and name not in fields, f"{cls.__name__}.{name} is no fixed rule"
            monkeypatch.setattr(cls, name, value)

    return set_rules
