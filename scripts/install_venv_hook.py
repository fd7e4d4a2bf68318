"""Install the .pth hook that makes a built colcon workspace usable from a venv, nothing sourced.

Run with the venv's Python: ``<venv>/bin/python install_venv_hook.py <workspace>``.

Messages built in the workspace need, before Python starts: the workspace's site-packages (and,
after ``--symlink-install``, the package build dirs) on PYTHONPATH, ``<ws>/install/lib`` on
LD_LIBRARY_PATH (the typesupport libraries; the loader reads it only at process start) and
``<ws>/install:<venv>`` on AMENT_PREFIX_PATH (ament index look-ups).
The ros-jazzy wheels ship ``ros_wheels_bootstrapper.pth``, which re-execs every venv Python once
with LD_LIBRARY_PATH set. Python processes ``.pth`` files in sorted name order, so our hook,
named to sort first, adds the variables to ``os.environ`` just before that re-exec and the new
process starts with all of them. The workspace path is written into the venv only.
"""

from __future__ import annotations

import sys
import sysconfig
from pathlib import Path

PTH_NAME = "00-hdmap-workspace.pth"
MODULE_NAME = "_hdmap_workspace_env"
BOOTSTRAPPER_PTH = "ros_wheels_bootstrapper.pth"

_MODULE_TEMPLATE = '''\
"""Written by hdmap scripts/install_venv_hook.py: exposes the colcon workspace {ws!r} to this venv.

Imported from {pth} (sorted before {boot}), so the variables below are in the environment when
the ROS wheels' bootstrapper re-execs Python. Safe to delete; `make setup` writes it again.
"""
import os

_WS_INSTALL = {install!r}
_VENV = {venv!r}
_PYVER = "python%d.%d" % __import__("sys").version_info[:2]


def _prepend(var, values):
    """Put ``values`` (in order) in front of ``var``, skipping ones already there. Changed?"""
    parts = [p for p in os.environ.get(var, "").split(os.pathsep) if p]
    missing = [v for v in values if v not in parts]
    if missing:
        os.environ[var] = os.pathsep.join(missing + parts)
    return bool(missing)


def _python_paths():
    """The workspace's site-packages, then the package dirs its egg-links name.

    ``colcon build --symlink-install`` installs ament_python packages as ``setup.py develop``
    egg-links to ``build/<pkg>`` (symlinks into src/); sourcing setup.bash would put those dirs
    on PYTHONPATH, so this does the same.
    """
    site = os.path.join(_WS_INSTALL, "lib", _PYVER, "site-packages")
    paths = [site]
    try:
        links = sorted(n for n in os.listdir(site) if n.endswith(".egg-link"))
    except OSError:
        links = []
    for name in links:
        try:
            with open(os.path.join(site, name)) as f:
                target = f.readline().strip()
        except OSError:
            continue
        if target and os.path.isdir(target):
            paths.append(target)
    return paths


if os.path.isdir(_WS_INSTALL):
    _prepend("PYTHONPATH", _python_paths())
    _prepend("AMENT_PREFIX_PATH", [_WS_INSTALL, _VENV])
    if _prepend("LD_LIBRARY_PATH", [os.path.join(_WS_INSTALL, "lib")]):
        # The loader only reads LD_LIBRARY_PATH at start: make the bootstrapper re-exec us even
        # if an earlier venv Python already did (e.g. a child started with a changed environment).
        os.environ.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)
'''


def render_hook(ws: Path, venv: Path) -> tuple[str, str]:
    """Return (module text, .pth text) of the hook for workspace ``ws`` and venv ``venv``."""
    module = _MODULE_TEMPLATE.format(
        ws=str(ws), install=str(ws / "install"), venv=str(venv), pth=PTH_NAME, boot=BOOTSTRAPPER_PTH
    )
    return module, f"import {MODULE_NAME}\n"


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    ws = Path(argv[1]).resolve()
    venv = Path(sys.prefix).resolve()
    site_dir = Path(sysconfig.get_paths()["purelib"])
    if not (site_dir / BOOTSTRAPPER_PTH).is_file():
        print(
            f"install_venv_hook: {site_dir / BOOTSTRAPPER_PTH} missing: are the ROS wheels installed in this venv?",
            file=sys.stderr,
        )
        return 1
    if sorted([PTH_NAME, BOOTSTRAPPER_PTH])[0] != PTH_NAME:
        raise RuntimeError("hook .pth must sort before the bootstrapper's")  # programming error
    module, pth = render_hook(ws, venv)
    for path, text in ((site_dir / f"{MODULE_NAME}.py", module), (site_dir / PTH_NAME, pth)):
        if not path.is_file() or path.read_text() != text:
            path.write_text(text)
    print(f"install_venv_hook: {site_dir / PTH_NAME} -> workspace {ws}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
