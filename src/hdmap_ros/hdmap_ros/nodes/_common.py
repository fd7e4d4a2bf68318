"""Shared glue of the nodes: parameter declaration, the default YAML, ``main`` and diagnostics."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterImmutableException,
    ParameterUninitializedException,
)
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.serialization import deserialize_message

from hdmap_core.errors import ConfigError, HdmapError, InvalidMessageError
from hdmap_core.model import Drive, validate_drive
from hdmap_ros.convert.messages import msg_to_drive
from hdmap_ros.io.cdr import decode_drive, encode_drive
from hdmap_ros.nodes import qos
from hdmap_ros.nodes.diagnostics import Health, health_to_msg
from hdmap_ros.nodes.executor import NodeExecutor

__all__ = [
    "declare",
    "declare_strings",
    "declare_pipeline_config",
    "params_file",
    "with_default_params",
    "run_node",
    "HealthMixin",
    "preset_config",
    "drive_from_wire",
    "drive_to_wire",
    "ros_home",
    "state_path",
    "warn_unknown_parameters",
]

PACKAGE = "hdmap_ros"
# What rclpy raises when a given parameter value does not fit its declaration.
PARAMETER_ERRORS = (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterImmutableException,
    ParameterUninitializedException,
)
# src/hdmap_ros/hdmap_ros/nodes/_common.py -> src/hdmap_ros/config/hdmap.yaml
_SOURCE_YAML = Path(__file__).resolve().parents[2] / "config" / "hdmap.yaml"


def params_file() -> Path | None:
    """config/hdmap.yaml from the installed share directory, else the source tree, else None."""
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory  # noqa: PLC0415

        share = Path(get_package_share_directory(PACKAGE)) / "config" / "hdmap.yaml"
        if share.is_file():
            return share
    except (ImportError, PackageNotFoundError, LookupError, ValueError):
        pass
    return _SOURCE_YAML if _SOURCE_YAML.is_file() else None


def with_default_params(args: Sequence[str] | None) -> list[str]:
    """ROS arguments with the package's default YAML loaded first (later --params-file override it)."""
    argv = list(sys.argv if args is None else args)
    yaml = params_file()
    if yaml is None or os.environ.get("HDMAP_NO_DEFAULT_PARAMS"):
        return argv
    # Parameter files given later win, so the user's own --params-file still overrides ours.
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        return argv[: i + 1] + ["--params-file", str(yaml)] + argv[i + 1 :]
    return argv + ["--ros-args", "--params-file", str(yaml)]


def ros_home() -> Path:
    """``$ROS_HOME``, else ``~/.ros`` (where ROS 2 keeps a user's state)."""
    return Path(os.environ.get("ROS_HOME") or Path.home() / ".ros")


def state_path(value: str, default_name: str) -> str:
    """A store's path: ``value`` (``~`` expanded), or ``$ROS_HOME/hdmap/<default_name>`` when empty."""
    return os.path.expanduser(value) if value else str(ros_home() / "hdmap" / default_name)


def declare(
    node: Node,
    name: str,
    default: Any,
    description: str,
    *,
    lo: float | int | None = None,
    hi: float | int | None = None,
    dynamic: str | None = None,
) -> Any:
    """Declare a parameter with description, range and default; return its value.

    ``dynamic``: the name of the node attribute that holds the value; the parameter can then be
    set at run time (``ros2 param set``), checked against its range and type by rclpy and by
    :func:`_on_set` (an integer for a float is taken as that float), and the attribute follows.
    Without it the parameter is read-only.

    ``lo``/``hi`` become a FloatingPointRange (float default) or IntegerRange (int default);
    rclpy then rejects out-of-range values given in YAML or on the command line. A float parameter
    given an integer (``rate:=10``, YAML ``rate: 10``) takes it as that float.
    """
    desc = ParameterDescriptor(description=description, read_only=dynamic is None)
    if dynamic is not None:
        _dynamic_table(node)[name] = (dynamic, type(default))
    if isinstance(default, float):
        given = node._parameter_overrides.get(name)  # rclpy keeps the overrides here until declared
        if given is not None and given.type_ == Parameter.Type.INTEGER:
            node._parameter_overrides[name] = Parameter(name, Parameter.Type.DOUBLE, float(given.value))
    if lo is not None and hi is not None:
        if isinstance(default, bool):
            pass
        elif isinstance(default, int):
            desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
        elif isinstance(default, float):
            desc.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
    return node.declare_parameter(name, default, desc).value


def _dynamic_table(node: Node) -> dict[str, tuple[str, type]]:
    """The node's run-time parameters (name -> attribute, type); the set callbacks on first use."""
    table = node.__dict__.get("_hdmap_dynamic")
    if table is None:
        table = node.__dict__["_hdmap_dynamic"] = {}
        node.add_pre_set_parameters_callback(lambda params: _as_declared(table, params))
        node.add_on_set_parameters_callback(lambda params: _on_set(node, table, params))
    return table


def _as_declared(table: dict[str, tuple[str, type]], params: list[Parameter]) -> list[Parameter]:
    """An integer set on a float parameter becomes that float (``ros2 param set /n rate 10``)."""
    out = []
    for p in params:
        entry = table.get(p.name)
        if entry is not None and entry[1] is float and p.type_ == Parameter.Type.INTEGER:
            p = Parameter(p.name, Parameter.Type.DOUBLE, float(p.value))
        out.append(p)
    return out


def _on_set(node: Node, table: dict[str, tuple[str, type]], params: list[Parameter]) -> SetParametersResult:
    """Check a run-time change (rclpy has checked ranges and read-only already) and apply it."""
    for p in params:
        entry = table.get(p.name)
        if entry is not None and not isinstance(p.value, entry[1]):
            reason = f"{p.name} must be a {entry[1].__name__}, got {p.value!r}"
            return SetParametersResult(successful=False, reason=reason)
    for p in params:
        entry = table.get(p.name)
        if entry is not None:
            changed = hasattr(node, entry[0]) and getattr(node, entry[0]) != p.value  # not the declaration
            setattr(node, entry[0], p.value)
            if changed:
                node.get_logger().info(f"parameter {p.name} set to {p.value!r}")
    return SetParametersResult(successful=True)


def declare_strings(node: Node, name: str, description: str) -> list[str]:
    """Declare a string-array parameter whose default is the empty list; return its value.

    Declared with a value (a parameter declared with only a type has none, and rclpy then answers a
    whole get_parameters request empty: ``ros2 param dump`` printed ``{}``). rclpy types ``[]`` as a
    byte array, so the type is left dynamic and checked here.
    """
    desc = ParameterDescriptor(description=description, read_only=True, dynamic_typing=True)
    value = node.declare_parameter(name, [], desc).value
    items = list(value or [])
    if not all(isinstance(v, str) for v in items):
        raise ConfigError(f"parameter {name!r} must be a list of strings, got {value!r}")
    return items


def declare_pipeline_config(node: Node) -> Any:
    """Declare the ``preset`` and ``preset_overrides`` parameters (the mapper's and the
    stitcher's must match) and return the pipeline config they name (:func:`preset_config`)."""
    preset = declare(node, "preset", "default", "Pipeline preset: default, paper or naive.")
    overrides = declare_strings(
        node,
        "preset_overrides",
        "KEY=VALUE changes of preset parameters, as `hdmap bag2map --set` "
        "(the mapper's and the stitcher's must match).",
    )
    return preset_config(preset, overrides)


def preset_config(name: str, overrides: Sequence[str] = ()) -> Any:
    """The pipeline's named preset (``default``, ``paper``, ``naive``) with ``overrides``, each
    ``KEY=VALUE`` as ``hdmap bag2map --set`` takes it (the node parameter ``preset_overrides``).

    Raises:
        ConfigError: an unknown preset, or an override the config does not take (named).
    """
    from hdmap_core.pipeline.overrides import config_from  # noqa: PLC0415

    try:
        return config_from(name, list(overrides))
    except ConfigError as err:
        raise ConfigError(f"preset_overrides: {err}" if overrides else str(err)) from err


def drive_from_wire(data: Any, msg_class: Any, *, expected_frame: str | None) -> Drive:
    """A validated drive from a received hdmap_msgs/Drive: CDR bytes (a ``raw`` subscription) or
    a message object.

    Bytes of the common layout are read vectorised (``io.cdr.decode_drive``, no Python object per
    point); anything else goes the generic, exact way (``convert.messages.msg_to_drive``).

    Raises:
        InvalidDriveError: malformed content, with its reason.
        InvalidMessageError: bytes that are no Drive message.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        return msg_to_drive(data, expected_frame=expected_frame)
    drive = decode_drive(bytes(data))
    if drive is not None:
        return validate_drive(drive, expected_frame=expected_frame or "")
    try:
        msg = deserialize_message(bytes(data), msg_class)
    except Exception as err:  # noqa: BLE001 - whatever the C deserializer raises on foreign bytes
        raise InvalidMessageError(f"not a {msg_class.__name__} message: {err}") from err
    return msg_to_drive(msg, expected_frame=expected_frame)


def drive_to_wire(drive: Drive) -> bytes:
    """A drive as hdmap_msgs/Drive CDR bytes, for ``publish`` (``io.cdr.encode_drive``: the
    generic encoding's bytes, without a Python object per point)."""
    return encode_drive(drive)


class HealthMixin:
    """Periodic /diagnostics of a node's :class:`Health`."""

    health: Health

    def _init_health(self: Any, label: str, item: str = "drives") -> None:
        period = declare(self, "diagnostics_period_s", 1.0, "Period of /diagnostics messages [s].", lo=0.05, hi=60.0)
        self.health = Health(name=f"hdmap: {label}", hardware_id=self.get_fully_qualified_name(), item=item)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", qos.DIAGNOSTICS)
        self._diag_timer = self.create_timer(period, self.publish_health)

    def publish_health(self: Any) -> None:
        self._diag_pub.publish(health_to_msg([self.health], stamp=self.get_clock().now().to_msg()))


# Parameters every node has (rclpy's own), never reported as unknown.
_BUILTIN_PARAMETERS = {"use_sim_time", "start_type_description_service", "qos_overrides"}


def warn_unknown_parameters(node: Node) -> list[str]:
    """Log a warning for every parameter given to the node (YAML, ``-p``) that it does not declare
    (e.g. a misspelt key, which would otherwise be silently ignored); returns their names."""
    unknown = sorted(
        k
        for k in node._parameter_overrides  # what was given and not taken by a declaration
        if not node.has_parameter(k) and k.split(".", 1)[0] not in _BUILTIN_PARAMETERS
    )
    for k in unknown:
        node.get_logger().warning(f"parameter {k!r} is not a parameter of {node.get_name()}: ignored (misspelt?)")
    return unknown


def parameter_error(err: BaseException) -> str:
    """One line naming the parameter and what is wrong with its value (rclpy's own text spans lines)."""
    return " ".join(str(err).split())


def run_node(
    factory: Callable[[], Node], args: Sequence[str] | None = None, *, until: Callable[[Any], bool] | None = None
) -> None:
    """The ros2/demos ``main``: init, spin, clean shutdown on Ctrl-C or external shutdown.

    ``until``: spin only until it returns True for the node (e.g. a player at the end of its bag).
    """
    rclpy.init(args=with_default_params(args))
    node = None
    try:
        try:
            node = factory()
        except HdmapError as err:  # a parameter the node cannot work with: named, no traceback
            print(f"hdmap {getattr(factory, '__name__', 'node')}: error: {err}", file=sys.stderr)
            raise SystemExit(2) from None
        except PARAMETER_ERRORS as err:  # e.g. a YAML value out of its range: one line, no traceback
            print(f"hdmap {getattr(factory, '__name__', 'node')}: error: {parameter_error(err)}", file=sys.stderr)
            raise SystemExit(2) from None
        warn_unknown_parameters(node)
        # Two threads: a node's receiving callbacks (own callback group) stay responsive while its
        # worker callback maps or stitches; callbacks of one group never run concurrently.
        executor = NodeExecutor(num_threads=2)
        executor.add_node(node)
        if until is None:
            executor.spin()
        else:
            while rclpy.ok() and not until(node):
                executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
