"""DDS test harness for the node tests (not a test module).

**The DDS rule**, kept here in one place: every test that starts DDS sets both
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` (discovery on loopback only) and a ``ROS_DOMAIN_ID`` of
its own, before any context is initialised, through this module (``dds_vars``):

- ``Ros(domain)``: rclpy in this process, on an explicit Context (other test modules' rclpy use is
  untouched); ``Proc(module, domain, ...)``: a node process in its own session (killed as a group);
- ``dds_env(domain)``: the environment of any other subprocess that starts DDS (``hdmap run``);
- ``use_dds(monkeypatch, domain)``: ``hdmap run`` called in this process (``cli.main``).

Domains, this suite's range 70-79: 70-74 the ``ros`` fixture (one per test, by its name,
test/ros/nodes/conftest.py); 74 the conformance, bad-drive and live-changes subprocesses; 75-77
the e2e suite; 78 the live contract. ``HDMAP_TEST_ROS_DOMAIN=N`` puts every one on domain N
instead (a session given a domain of its own, or a machine where 70-79 are taken); the caller's
``ROS_DOMAIN_ID`` is never used, so a test does not land on the domain of the caller's own nodes.
test/conftest.py sets the discovery range for the whole run as well (a safety net), and
test/ros/nodes/test_dds_rule.py checks that no test starts DDS around this module.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import rclpy
from rclpy.context import Context
from rclpy.node import Node

from hdmap_ros.nodes.executor import NodeExecutor

ROOT = Path(__file__).resolve().parents[2]


def ros_domain(domain_id: int) -> int:
    """The domain to use: ``domain_id``, or ``HDMAP_TEST_ROS_DOMAIN`` when set (one domain for a whole
    run, for a machine where this suite's 70-79 are taken by others)."""
    return int(os.environ.get("HDMAP_TEST_ROS_DOMAIN", domain_id))


def dds_vars(domain_id: int) -> dict[str, str]:
    """The two variables of the DDS rule: loopback discovery and the domain (``ros_domain``)."""
    return {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": str(ros_domain(domain_id))}


def use_dds(monkeypatch, domain_id: int) -> int:
    """Set the DDS rule's variables in this process for one test (``monkeypatch`` undoes them);
    the domain."""
    for name, value in dds_vars(domain_id).items():
        monkeypatch.setenv(name, value)
    return ros_domain(domain_id)


def dds_env(domain_id: int) -> dict[str, str]:
    """Environment of a node process: isolated domain, loopback discovery, the source tree first."""
    env = {**os.environ, **dds_vars(domain_id)}
    env["PYTHONPATH"] = os.pathsep.join(
        [str(ROOT / "src/hdmap_core"), str(ROOT / "src/hdmap_ros")]
        + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else [])
    )
    env["PYTHONUNBUFFERED"] = "1"
    return env


def wait_for(pred: Callable[[], object], timeout: float, *, what: str = "condition", poll: float = 0.05):
    """Poll ``pred`` until truthy; return its value or fail with ``what``."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = pred()
        if value:
            return value
        time.sleep(poll)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


class Ros:
    """An initialised context with a spinning executor in a background thread."""

    def __init__(self, domain_id: int) -> None:
        os.environ.update(dds_vars(domain_id))
        domain_id = ros_domain(domain_id)
        self.domain_id = domain_id
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.executor = NodeExecutor(num_threads=4, context=self.context)  # the nodes' own executor
        self.nodes: list[Node] = []
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._stop = False
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop and self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 - shutting down under the spinner
                if self._stop:
                    return
                raise

    def add(self, node: Node) -> Node:
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def node(self, name: str) -> Node:
        return self.add(Node(name, context=self.context))

    def close(self) -> None:
        self._stop = True
        self._thread.join(timeout=5)
        self.executor.shutdown()  # before the nodes go: no callback may run on a destroyed node
        for n in self.nodes:
            n.destroy_node()
        rclpy.try_shutdown(context=self.context)


class Proc:
    """A node process in its own session (so the whole group can be signalled)."""

    def __init__(self, module: str, domain_id: int, params: dict, log: Path) -> None:
        args = [sys.executable, "-m", module, "--ros-args"]
        for k, v in params.items():
            args += ["-p", f"{k}:={_yaml(v)}"]
        self.log = log
        self._fh = open(log, "ab")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(
            args,
            env=dds_env(domain_id),
            stdout=self._fh,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            cwd=str(log.parent),
        )

    def alive(self) -> bool:
        return self.proc.poll() is None

    def kill(self, sig: int = signal.SIGKILL) -> None:
        if self.alive():
            os.killpg(self.proc.pid, sig)
        self.proc.wait(timeout=20)

    def stop(self) -> None:
        if self.alive():
            os.killpg(self.proc.pid, signal.SIGINT)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.kill()
        self._fh.close()

    def output(self) -> str:
        return self.log.read_text(errors="replace")


def _yaml(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return v if v else "''"
    return repr(v)
