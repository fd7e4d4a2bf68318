"""The one error hierarchy of hdmap_core.

Public entry points check their input and raise one of these with a message that names what is
wrong (which drive, which field); callers (CLI, nodes) catch ``HdmapError``, report it and go on.
"""

from __future__ import annotations

__all__ = [
    "HdmapError",
    "InvalidDriveError",
    "GroundTruthError",
    "ConfigError",
    "NoUsableDataError",
    "BagError",
    "InvalidMessageError",
]


class HdmapError(Exception):
    """Base class of every error raised on purpose by hdmap."""


class InvalidDriveError(HdmapError):
    """A drive (or one of its detections) is malformed.

    Attributes:
        drive_id: the offending drive's id ("" when unknown).
        reason: a short machine-friendly reason key, e.g. ``"nan_coordinates"``.
    """

    def __init__(self, drive_id: str, reason: str, detail: str = "") -> None:
        self.drive_id = drive_id
        self.reason = reason
        self.detail = detail
        text = f"drive {drive_id!r}: {reason}"
        if detail:
            text += f" ({detail})"
        super().__init__(text)


class GroundTruthError(HdmapError):
    """A ground-truth map file is missing, unreadable or not of the documented format."""


class ConfigError(HdmapError):
    """A configuration value is out of its valid range."""


class NoUsableDataError(HdmapError):
    """There is nothing to work on (e.g. a bag without a single valid drive)."""


class BagError(HdmapError):
    """A bag is missing, unreadable, truncated or corrupted; the message names the path and the damage."""


class InvalidMessageError(HdmapError):
    """A (non-drive) message, e.g. a map or an origin, is malformed; the message names the field."""
