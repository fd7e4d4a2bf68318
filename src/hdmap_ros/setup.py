"""ament_python package hdmap_ros: conversions, bag I/O, the ``hdmap`` CLI and the rclpy nodes."""

from glob import glob
from pathlib import Path

from setuptools import find_packages, setup

PACKAGE = "hdmap_ros"
NODES = ("drive_ingestor", "segment_mapper", "map_stitcher", "map_publisher", "bag_player")

_HERE = Path(__file__).resolve().parent


def _share(subdir: str, pattern: str) -> list[tuple[str, list[str]]]:
    """Install ``subdir/pattern`` (relative to this file) into share/<pkg>/subdir, if any exist."""
    files = sorted(str(Path(p).relative_to(_HERE)) for p in glob(str(_HERE / subdir / pattern)))
    return [(f"share/{PACKAGE}/{subdir}", files)] if files else []


setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        *_share("config", "*.yaml"),
        *_share("launch", "*.py"),
    ],
    # Runtime dependencies come from package.xml (rosdep) or the pinned requirements.txt (pip).
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="hdmap maintainers",
    maintainer_email="hdmap@example.com",
    description="ROS 2 side of hdmap: conversions, rosbag2 I/O, the hdmap CLI and nodes.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "hdmap = hdmap_ros.cli:main",
            *(f"{node} = hdmap_ros.nodes.{node}:main" for node in NODES),
        ],
    },
)
