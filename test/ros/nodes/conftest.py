"""Fixtures of the node tests."""

from __future__ import annotations

import zlib

import pytest


@pytest.fixture
def ros(request):
    """rclpy nodes in a context of their own: one domain per test (70-74, by the test's name;
    the DDS rule and the other tests' domains: support/nodes_harness.py), so a straggler never
    crosses tests."""
    from nodes_harness import Ros  # noqa: PLC0415 - needs rclpy; test modules skip without it

    r = Ros(70 + zlib.crc32(request.node.name.encode()) % 5)
    yield r
    r.close()
