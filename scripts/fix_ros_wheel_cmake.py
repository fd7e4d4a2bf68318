"""Point the ROS wheels' exported CMake targets at this venv's Python and numpy headers.

The ros-jazzy-* wheels were built in a manylinux container, and their
``share/*/cmake/export_*__rosidl_generator_pyExport.cmake`` files name that container's include
directories (``/opt/python/cp311-cp311/...``). CMake then refuses to generate any package that
uses the message targets ("includes non-existent path"). This rewrites those paths, in the venv
that runs this script only, to ``sysconfig``'s include dir and ``numpy.get_include()``.
Idempotent: a file with nothing to rewrite is left untouched. See shared/notes/ros-wheels.md.

Usage: <venv>/bin/python fix_ros_wheel_cmake.py   (prints how many files it changed)
"""

from __future__ import annotations

import re
import sys
import sysconfig
from pathlib import Path

import numpy

# Any foreign interpreter prefix the wheel builder may have used (cp311-cp311, cp312-cp312, ...).
_PY_INCLUDE = re.compile(r"/opt/python/[^/;\"]+/include/python3\.\d+")
_NP_INCLUDE = re.compile(r"/opt/python/[^/;\"]+/lib/python3\.\d+/site-packages/numpy/(?:_core|core)/include")


def fix_file(path: Path, *, py_include: str, np_include: str) -> bool:
    """Rewrite one export file in place; return True if it changed."""
    text = path.read_text()
    new = _NP_INCLUDE.sub(np_include, text)
    new = _PY_INCLUDE.sub(py_include, new)
    if new == text:
        return False
    path.write_text(new)
    return True


def main() -> int:
    prefix = Path(sys.prefix)
    py_include = sysconfig.get_paths()["include"]
    np_include = numpy.get_include()
    for needed in (py_include, np_include):
        if not Path(needed).is_dir():
            print(f"fix_ros_wheel_cmake: include dir missing: {needed}", file=sys.stderr)
            return 1
    pattern = "share/*/cmake/export_*__rosidl_generator_pyExport.cmake"
    changed = [p for p in sorted(prefix.glob(pattern)) if fix_file(p, py_include=py_include, np_include=np_include)]
    print(f"fix_ros_wheel_cmake: rewrote {len(changed)} export file(s) under {prefix}/share")
    return 0


if __name__ == "__main__":
    sys.exit(main())
