"""The DDS rule of the test suite (support/nodes_harness.py): every test that starts DDS sets
loopback discovery and a domain of its own, through the harness."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

pytest.importorskip("rclpy")

from nodes_harness import dds_env, dds_vars, use_dds  # noqa: E402

TEST_ROOT = Path(__file__).resolve().parents[2]
HARNESS = TEST_ROOT / "support" / "nodes_harness.py"
SUITE_CONFTEST = TEST_ROOT / "conftest.py"
# a DDS participant made outside the harness's Ros
_CONTEXT = re.compile(r"rclpy\.init\(|\bContext\(\)")
# the rule's variables set by hand
_SETS_VAR = re.compile(r"""(setenv\(\s*|environ\[\s*)["']ROS_(DOMAIN_ID|AUTOMATIC_DISCOVERY_RANGE)["']""")
# `hdmap run` (it starts the node suite): as a subprocess or through cli.main in this process
_RUNS_SUITE = re.compile(r"""["']hdmap_ros\.cli["'],\s*["']run["']|cli\.main\(\s*\[\s*["']run["']""")


def _test_sources() -> dict[Path, str]:
    """Every test module and helper but the harness and this file (whose patterns would match)."""
    skip = {HARNESS, Path(__file__).resolve()}
    return {p: p.read_text() for p in sorted(TEST_ROOT.rglob("*.py")) if p.resolve() not in skip}


def test_the_harness_sets_loopback_discovery_and_the_domain(monkeypatch):
    monkeypatch.delenv("HDMAP_TEST_ROS_DOMAIN", raising=False)
    monkeypatch.setenv("ROS_DOMAIN_ID", "3")  # the caller's own domain is not taken
    assert dds_vars(71) == {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": "71"}
    env = dds_env(72)
    assert env["ROS_DOMAIN_ID"] == "72" and env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    monkeypatch.setenv("HDMAP_TEST_ROS_DOMAIN", "65")  # one domain for the whole run
    assert dds_env(72)["ROS_DOMAIN_ID"] == "65"
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET")
    assert use_dds(monkeypatch, 74) == 65
    assert os.environ["ROS_DOMAIN_ID"] == "65" and os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"


def test_no_test_starts_dds_around_the_harness():
    """Only the harness makes an rclpy context or sets the rule's variables (test/conftest.py sets
    the discovery range for the whole run); a module that runs `hdmap run` takes its environment
    from the harness."""
    wrong = []
    for path, text in _test_sources().items():
        where = path.relative_to(TEST_ROOT)
        if _CONTEXT.search(text):
            wrong.append(f"{where}: makes an rclpy context (use nodes_harness.Ros)")
        if path != SUITE_CONFTEST and _SETS_VAR.search(text):
            wrong.append(f"{where}: sets a ROS_ variable by hand (use nodes_harness.use_dds / dds_env)")
        if _RUNS_SUITE.search(text) and not re.search(r"\b(dds_env|use_dds)\(", text):
            wrong.append(f"{where}: runs `hdmap run` without nodes_harness.dds_env / use_dds")
    assert not wrong, "\n".join(wrong)


def test_the_scan_finds_what_it_looks_for():
    assert _CONTEXT.search("rclpy.init(context=ctx)") and _CONTEXT.search("c = Context()")
    assert _SETS_VAR.search('monkeypatch.setenv("ROS_DOMAIN_ID", "7")')
    assert _SETS_VAR.search("os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'")
    assert _RUNS_SUITE.search('[sys.executable, "-m", "hdmap_ros.cli", "run", bag]')
    assert _RUNS_SUITE.search('cli.main(["run", str(bag)])')
    assert not _RUNS_SUITE.search('cli.main(["bag2map", str(bag)])')
