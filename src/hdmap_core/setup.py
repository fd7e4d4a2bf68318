"""ament_python package hdmap_core: the data model and the algorithms (no ROS imports)."""

from setuptools import find_packages, setup

PACKAGE = "hdmap_core"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
    ],
    # Runtime dependencies come from package.xml (rosdep) or the pinned requirements.txt (pip).
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="hdmap maintainers",
    maintainer_email="hdmap@example.com",
    description="Lane-level HD maps from noisy fleet data: data model and algorithms.",
    license="Apache-2.0",
    tests_require=["pytest"],
)
