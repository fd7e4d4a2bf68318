"""Shared fixtures and the environment of the whole suite.

DDS: every test that can start a ROS 2 context (node tests, ``hdmap run``, a node subprocess) keeps
discovery on this machine. The variable is set here, before any test module imports rclpy, so a
bare ``pytest`` run is as safe as ``make test`` (which exports the same). ``ROS_DOMAIN_ID`` is left
as the caller set it (the node tests choose their own domains, see support/nodes_harness.py).

Helper modules shared by several test folders live in ``test/support/`` (on ``pythonpath`` in
pytest.ini): ``pipeline_fleet`` (a tiny deterministic fleet for the stage tests), ``bag_samples``
(drives and maps for bag and message round trips), ``nodes_harness`` (the DDS harness).
"""

from __future__ import annotations

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
