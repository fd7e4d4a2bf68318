"""The colcon workspace: message contract, package manifests, and the built install.

The first tests need only the source tree. Those marked ``ros`` check what ``make setup`` built:
they start ``.venv/bin/python`` / ``.venv/bin/hdmap`` from another directory with a clean
environment, as a newcomer would, and skip when the workspace is not built.
"""

from __future__ import annotations

import os
import re
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_MSG_DIR = REPO.parent / "shared" / "interface" / "msg"
MSG_DIR = REPO / "src" / "hdmap_msgs" / "msg"
SRV_DIR = REPO / "src" / "hdmap_msgs" / "srv"
VENV_PY = REPO / ".venv" / "bin" / "python"
VENV_HDMAP = REPO / ".venv" / "bin" / "hdmap"
INSTALL = REPO / "install"

PACKAGES = {  # name -> build type
    "hdmap_msgs": "ament_cmake",
    "hdmap_core": "ament_python",
    "hdmap_ros": "ament_python",
}

_BUILTIN_TYPES = {
    "bool",
    "byte",
    "char",
    "float32",
    "float64",
    "int8",
    "uint8",
    "int16",
    "uint16",
    "int32",
    "uint32",
    "int64",
    "uint64",
    "string",
    "wstring",
}


def _shared_msgs() -> list[Path]:
    return sorted(SHARED_MSG_DIR.glob("*.msg")) if SHARED_MSG_DIR.is_dir() else []


def _needs_shared() -> None:
    if not SHARED_MSG_DIR.is_dir():
        pytest.skip(f"shared interface dir not found at {SHARED_MSG_DIR} (expected ../shared beside the repository)")


_STRING_CONSTANT = re.compile(r"^\s*w?string\S*\s+[A-Z][A-Z0-9_]*\s*=")


def msg_fields(text: str) -> list[str]:
    """The definition lines of a .msg/.srv text: comments dropped, whitespace normalised.

    A string constant's line is kept whole (its value may contain ``#``).
    """
    out = []
    for line in text.splitlines():
        code = line if _STRING_CONSTANT.match(line) else line.split("#", 1)[0]
        code = " ".join(code.split())
        if code:
            out.append(code)
    return out


def _field_types(path: Path) -> set[str]:
    """Types named in a .msg/.srv file, array suffixes and bounds removed."""
    types = set()
    for line in msg_fields(path.read_text()):
        if line == "---":
            continue
        base = re.split(r"[\[<]", line.split(" ")[0])[0]
        types.add(base)
    return types


# --- message contract ------------------------------------------------------------------------


def test_msg_field_normaliser_drops_comments_only():
    text = "float64 x   # the drive's x [m]\n# a comment line\n\nstring S=a#b\nuint8[]  v\n"
    assert msg_fields(text) == ["float64 x", "string S=a#b", "uint8[] v"]


def test_shared_interface_is_present():
    _needs_shared()
    assert _shared_msgs(), f"no .msg files in {SHARED_MSG_DIR}"


@pytest.mark.parametrize("shared", _shared_msgs(), ids=lambda p: p.name)
def test_shared_message_copied_with_identical_fields(shared: Path):
    ours = MSG_DIR / shared.name
    assert ours.is_file(), f"{shared.name} of the shared contract is missing from {MSG_DIR}"
    assert msg_fields(ours.read_text()) == msg_fields(shared.read_text()), (
        f"{ours.relative_to(REPO)} differs from the shared contract in its fields"
    )


@pytest.mark.parametrize("shared", _shared_msgs(), ids=lambda p: p.name)
def test_shared_message_copied_byte_for_byte(shared: Path):
    ours = MSG_DIR / shared.name
    if not ours.is_file():
        pytest.fail(f"{shared.name} missing from {MSG_DIR}")
    assert ours.read_bytes() == shared.read_bytes(), (
        f"{ours.relative_to(REPO)} must be an unchanged copy of the shared file (comments too)"
    )


def test_every_message_dependency_is_declared():
    """Each package named in a field type is a dependency in package.xml and CMakeLists.txt."""
    files = sorted(MSG_DIR.glob("*.msg")) + sorted(SRV_DIR.glob("*.srv"))
    assert files, f"no interfaces in {MSG_DIR}"
    own = {p.stem for p in files}
    used = set()
    for path in files:
        for t in _field_types(path):
            if "/" in t:
                pkg = t.split("/")[0]
                if pkg != "hdmap_msgs":
                    used.add(pkg)
            else:
                assert t in _BUILTIN_TYPES or t in own, (
                    f"{path.name}: type {t!r} is neither builtin nor a message of hdmap_msgs"
                )
    xml = _parse("hdmap_msgs")
    declared = {e.text for tag in ("depend", "build_depend") for e in xml.findall(tag)}
    assert used <= declared, f"hdmap_msgs/package.xml lacks <depend> on {sorted(used - declared)}"
    cmake = (REPO / "src" / "hdmap_msgs" / "CMakeLists.txt").read_text()
    deps_line = re.search(r"DEPENDENCIES([^)]*)\)", cmake)
    assert deps_line, "CMakeLists.txt: rosidl_generate_interfaces has no DEPENDENCIES"
    in_cmake = set(deps_line.group(1).split())
    assert used <= in_cmake, f"CMakeLists.txt DEPENDENCIES lacks {sorted(used - in_cmake)}"
    for pkg in used:
        assert f"find_package({pkg} REQUIRED)" in cmake, f"CMakeLists.txt: no find_package({pkg})"


# --- package manifests -----------------------------------------------------------------------


def _parse(name: str) -> ET.Element:
    return ET.parse(REPO / "src" / name / "package.xml").getroot()


@pytest.mark.parametrize("name,build_type", sorted(PACKAGES.items()))
def test_package_xml_names_package_and_build_type(name: str, build_type: str):
    root = _parse(name)
    assert root.get("format") == "3"
    assert root.findtext("name") == name
    assert root.findtext("export/build_type") == build_type
    assert root.findtext("license") == "Apache-2.0"
    maint = root.find("maintainer")
    assert maint is not None and re.fullmatch(r"[\w.+-]+@[\w-]+(\.[\w-]+)*\.[a-z]{2,}", maint.get("email", ""))
    if build_type == "ament_python":
        assert "python3-pytest" in {e.text for e in root.findall("test_depend")}


@pytest.mark.parametrize("name", sorted(PACKAGES))
def test_package_xml_is_valid_for_catkin_pkg(name: str):
    """catkin_pkg (what colcon and rosdep use) accepts the manifest without warnings."""
    catkin_pkg = pytest.importorskip("catkin_pkg.package")
    warnings: list[str] = []
    pkg = catkin_pkg.parse_package(REPO / "src" / name / "package.xml", warnings=warnings)
    assert pkg.name == name
    assert warnings == []


def test_interface_package_is_in_rosidl_group():
    root = _parse("hdmap_msgs")
    assert root.findtext("member_of_group") == "rosidl_interface_packages"
    build_tools = {e.text for e in root.findall("buildtool_depend")}
    assert {"ament_cmake", "rosidl_default_generators"} <= build_tools
    assert "rosidl_default_runtime" in {e.text for e in root.findall("exec_depend")}


def test_ros_package_depends_on_the_other_two_and_rclpy():
    deps = {e.text for e in _parse("hdmap_ros").findall("exec_depend")}
    assert {"hdmap_core", "hdmap_msgs", "rclpy", "sensor_msgs"} <= deps


def test_core_package_has_no_ros_dependency():
    root = _parse("hdmap_core")
    deps = {e.text for tag in ("depend", "exec_depend", "build_depend") for e in root.findall(tag)}
    assert deps and all(d.startswith("python3-") for d in deps), deps


@pytest.mark.parametrize("name", ["hdmap_core", "hdmap_ros"])
def test_python_package_has_resource_marker_and_script_dir(name: str):
    pkg = REPO / "src" / name
    assert (pkg / "resource" / name).is_file()
    cfg = (pkg / "setup.cfg").read_text()
    assert f"script_dir=$base/lib/{name}" in cfg
    assert f"install_scripts=$base/lib/{name}" in cfg


# --- the built workspace (make setup) ----------------------------------------------------------


def _clean_env() -> dict[str, str]:
    """What a newcomer's fresh shell has: no ROS or venv variables at all."""
    env = {"PATH": "/usr/bin:/bin", "HOME": os.environ.get("HOME", "/tmp"), "LANG": "C.UTF-8"}
    for var in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID"):
        if var in os.environ:
            env[var] = os.environ[var]
    return env


def _needs_build() -> None:
    if not VENV_PY.exists():
        pytest.skip(f"{VENV_PY} missing: run `make setup`")
    if not (INSTALL / "share" / "hdmap_msgs").is_dir():
        pytest.skip(f"{INSTALL} has no hdmap_msgs: run `make setup`")


_ROUND_TRIP = r"""
import sys
from geometry_msgs.msg import Point, PoseStamped
from rclpy.serialization import deserialize_message, serialize_message
from hdmap_msgs.msg import DetectionPolyline, Drive, Map, MapFeature, TopologyNode

drive = Drive(drive_id="d1", vehicle_id="v7")
drive.header.frame_id = "map"
drive.trajectory.poses = [PoseStamped() for _ in range(3)]
drive.trajectory.poses[2].pose.position.x = 12.5
drive.detections = [DetectionPolyline(points=[Point(x=1.0, y=2.0), Point(x=3.0, y=-4.25)])]
back = deserialize_message(serialize_message(drive), Drive)
assert back == drive, (back, drive)

m = Map(version=3, drive_ids=["d1", "d2"],
        features=[MapFeature(points=[Point(x=0.5), Point(x=1.5)])],
        topology=[TopologyNode(position=Point(y=7.0))])
back = deserialize_message(serialize_message(m), Map)
assert back == m, (back, m)

from ament_index_python.packages import get_package_share_directory
print(get_package_share_directory("hdmap_msgs"))
"""


@pytest.mark.ros
def test_built_messages_round_trip_with_nothing_sourced(tmp_path):
    _needs_build()
    proc = subprocess.run(
        [str(VENV_PY), "-c", _ROUND_TRIP], cwd=tmp_path, env=_clean_env(), capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    share = Path(proc.stdout.strip().splitlines()[-1])
    assert share.resolve() == (INSTALL / "share" / "hdmap_msgs").resolve()
    for shared in _shared_msgs():  # the ament index serves the contract too
        assert msg_fields((share / "msg" / shared.name).read_text()) == msg_fields(shared.read_text())


@pytest.mark.slow
@pytest.mark.ros
def test_hdmap_cli_help_runs_from_anywhere(tmp_path):
    _needs_build()
    if not VENV_HDMAP.exists():
        pytest.skip(f"{VENV_HDMAP} missing: run `make setup`")
    proc = subprocess.run(
        [str(VENV_HDMAP), "--help"], cwd=tmp_path, env=_clean_env(), capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("usage: hdmap")


@pytest.mark.ros
def test_node_executables_are_installed_where_ros2_run_looks():
    _needs_build()
    lib = INSTALL / "lib" / "hdmap_ros"
    for exe in ("hdmap", "drive_ingestor", "segment_mapper", "map_stitcher", "map_publisher", "bag_player"):
        path = lib / exe
        assert path.is_file() and os.access(path, os.X_OK), f"{path} missing or not executable"
        first = path.read_text().splitlines()[0]
        assert first.startswith("#!") and "python" in first


@pytest.mark.ros
def test_source_edits_are_live_in_the_install(tmp_path):
    """--symlink-install: the installed hdmap_core is the source tree, no rebuild needed."""
    _needs_build()
    code = "import hdmap_core, hdmap_ros; print(hdmap_core.__file__); print(hdmap_ros.__file__)"
    proc = subprocess.run(
        [str(VENV_PY), "-c", code], cwd=tmp_path, env=_clean_env(), capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    core, ros = (Path(line).resolve() for line in proc.stdout.split())
    assert core == (REPO / "src" / "hdmap_core" / "hdmap_core" / "__init__.py").resolve()
    assert ros == (REPO / "src" / "hdmap_ros" / "hdmap_ros" / "__init__.py").resolve()
