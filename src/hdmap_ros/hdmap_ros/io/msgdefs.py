"""The message definitions of hdmap_msgs, from one source of truth, and a rosbags typestore.

The ``.msg`` texts are read from the installed ``hdmap_msgs`` package (``share/hdmap_msgs/msg``,
found through the ament index) when it is installed; otherwise from the source tree beside this
package (``src/hdmap_msgs/msg``), so that the source tree works without a colcon build. Nothing
here imports rclpy or generated message modules.
"""

from __future__ import annotations

import functools
from pathlib import Path

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from hdmap_core.errors import HdmapError

__all__ = ["PACKAGE", "default_typestore", "hdmap_msg_dir", "hdmap_msg_texts", "make_typestore"]

PACKAGE = "hdmap_msgs"

# src/hdmap_ros/hdmap_ros/msgdefs.py -> src/hdmap_msgs/msg (resolve() follows a symlink install).
_SOURCE_MSG_DIR = Path(__file__).resolve().parents[2] / PACKAGE / "msg"


def _installed_msg_dir() -> Path | None:
    try:
        from ament_index_python.packages import (  # noqa: PLC0415 - optional dependency
            PackageNotFoundError,
            get_package_share_directory,
        )
    except ImportError:
        return None
    try:
        share = Path(get_package_share_directory(PACKAGE))
    except (PackageNotFoundError, LookupError, ValueError, OSError):  # OSError: AMENT_PREFIX_PATH unset
        return None
    msg_dir = share / "msg"
    return msg_dir if any(msg_dir.glob("*.msg")) else None


def hdmap_msg_dir() -> Path:
    """The directory holding the hdmap_msgs ``.msg`` files (installed share dir, else source tree).

    Raises:
        HdmapError: neither an installed hdmap_msgs nor the source tree is found.
    """
    installed = _installed_msg_dir()
    if installed is not None:
        return installed
    if any(_SOURCE_MSG_DIR.glob("*.msg")):
        return _SOURCE_MSG_DIR
    raise HdmapError(
        f"cannot find the {PACKAGE} message definitions: the package is not installed "
        f"(ament index) and {_SOURCE_MSG_DIR} holds no .msg files"
    )


def hdmap_msg_texts() -> dict[str, str]:
    """Map ``"hdmap_msgs/msg/<Name>"`` to the text of ``<Name>.msg``, for every message there."""
    msg_dir = hdmap_msg_dir()
    return {f"{PACKAGE}/msg/{path.stem}": path.read_text(encoding="utf-8") for path in sorted(msg_dir.glob("*.msg"))}


@functools.lru_cache(maxsize=1)
def _cached_typestore() -> Typestore:
    return make_typestore()


def make_typestore() -> Typestore:
    """A rosbags typestore of ROS 2 Jazzy with every hdmap_msgs message registered.

    Returns a new typestore on each call; :func:`default_typestore` returns a shared one.
    """
    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict = {}
    for name, text in hdmap_msg_texts().items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def default_typestore() -> Typestore:
    """A process-wide typestore (built once by :func:`make_typestore`); do not register into it."""
    return _cached_typestore()
