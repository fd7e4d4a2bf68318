"""The launch file: it declares the arguments docs/nodes.md documents and passes ``rate`` as a float
(``rate:=10`` crashed bag_player, INTEGER vs DOUBLE). Read with ``ast`` always; built with
``launch``/``launch_ros`` where they import (not in the wheel install here)."""

from __future__ import annotations

import ast
import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
LAUNCH_FILE = ROOT / "src/hdmap_ros/launch/hdmap.launch.py"


def _documented_arguments() -> set[str]:
    """The ``name:=`` arguments of the ``ros2 launch`` line of docs/nodes.md."""
    text = (ROOT / "docs" / "nodes.md").read_text(encoding="utf-8")
    start = text.index("ros2 launch hdmap_ros hdmap.launch.py")
    return set(re.findall(r"\b(\w+):=", text[start : text.index("`", start)]))


def _name(node: ast.expr) -> str:
    return node.id if isinstance(node, ast.Name) else node.attr if isinstance(node, ast.Attribute) else ""


def _calls(tree: ast.AST, name: str) -> list[ast.Call]:
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call) and _name(n.func) == name]


def _keyword(call: ast.Call, key: str) -> ast.expr | None:
    return next((k.value for k in call.keywords if k.arg == key), None)


def test_the_launch_file_declares_every_documented_argument_and_passes_rate_as_a_float():
    tree = ast.parse(LAUNCH_FILE.read_text(encoding="utf-8"), str(LAUNCH_FILE))
    declared = {c.args[0].value for c in _calls(tree, "DeclareLaunchArgument") if isinstance(c.args[0], ast.Constant)}
    documented = _documented_arguments()
    assert {"bag", "rate", "namespace"} <= documented  # the docs line was found and read
    assert declared == documented
    (player,) = [
        c
        for c in _calls(tree, "Node")
        if isinstance(e := _keyword(c, "executable"), ast.Constant) and e.value == "bag_player"
    ]
    rates = [
        d.values[d.keys.index(k)]
        for d in ast.walk(player)
        if isinstance(d, ast.Dict)
        for k in d.keys
        if isinstance(k, ast.Constant) and k.value == "rate"
    ]
    assert len(rates) == 1, "bag_player gets one 'rate' parameter"
    rate = rates[0]
    assert isinstance(rate, ast.Call) and _name(rate.func) == "ParameterValue"
    (config,) = rate.args
    assert isinstance(config, ast.Call) and _name(config.func) == "LaunchConfiguration"
    assert isinstance(config.args[0], ast.Constant) and config.args[0].value == "rate"
    value_type = _keyword(rate, "value_type")
    assert isinstance(value_type, ast.Name) and value_type.id == "float"
    # every node (not only the player) runs in the namespace argument
    for node in _calls(tree, "Node"):
        ns = _keyword(node, "namespace")
        assert isinstance(ns, ast.Name) and ns.id == "ns"


def test_the_launch_description_gives_bag_player_a_float_rate_in_the_namespace(monkeypatch, tmp_path):
    for module in ("launch", "launch_ros"):
        pytest.importorskip(
            module, reason=f"{module} is not installed (no wheel here; run under a ROS 2 Jazzy install)"
        )
    import ament_index_python.packages  # noqa: PLC0415
    from launch import LaunchContext  # noqa: PLC0415
    from launch.actions import DeclareLaunchArgument  # noqa: PLC0415
    from launch_ros.actions import Node  # noqa: PLC0415
    from launch_ros.parameter_descriptions import ParameterValue  # noqa: PLC0415
    from launch_ros.utilities import evaluate_parameters  # noqa: PLC0415

    # the package need not be colcon-installed for this: only the default params_file path uses it
    monkeypatch.setattr(ament_index_python.packages, "get_package_share_directory", lambda _pkg: str(tmp_path))
    spec = importlib.util.spec_from_file_location("hdmap_launch", LAUNCH_FILE)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    description = module.generate_launch_description()

    context = LaunchContext()
    context.launch_configurations.update({"rate": "10", "namespace": "ns2", "bag": str(tmp_path / "bag")})
    for entity in description.entities:
        if isinstance(entity, DeclareLaunchArgument):
            entity.visit(context)  # the defaults of the arguments not given
    (player,) = [e for e in description.entities if isinstance(e, Node) and e.node_executable == "bag_player"]
    # Node keeps its normalised parameters privately; launch_ros' own tests read them the same way
    params = player._Node__parameters  # type: ignore[attr-defined]
    given = [v for p in params if isinstance(p, dict) for v in p.values() if isinstance(v, ParameterValue)]
    assert len(given) == 1 and isinstance(given[0], ParameterValue) and given[0].value_type is float
    values = {k: v for p in evaluate_parameters(context, params) if isinstance(p, dict) for k, v in p.items()}
    assert values["rate"] == 10.0 and isinstance(values["rate"], float)
    player._perform_substitutions(context)
    assert player.expanded_node_namespace == "/ns2"
