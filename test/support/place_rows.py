"""Hand-made per-drive place evidence for the change detection tests (not a test module): drive
``d`` is ``d{d:02d}`` an hour after drive ``d - 1``, place ``i`` is the key ``(i, 0, 0)``."""

from __future__ import annotations

from hdmap_core.updates.evidence import PlaceEvidence

HOUR = 3_600_000_000_000  # ns between two drives


def place_row(
    d: int, i: int, displacement_m: float, *, n_pairs: int = 40, n_typed: int = 0, n_wrong_type: int = 0
) -> PlaceEvidence:
    """Drive ``d``'s evidence at place ``i``: its markings displaced ``displacement_m`` against the
    borders (NaN: none measured) over ``n_pairs`` pairs, ``n_wrong_type`` of ``n_typed`` typed
    points read as the other type, no negative evidence."""
    return PlaceEvidence(
        drive_id=f"d{d:02d}",
        time_ns=(d + 1) * HOUR,
        key=(i, 0, 0),
        n_cuts=25,
        offset_m=displacement_m,
        anchor_m=0.0,
        anchored_on_borders=True,
        displacement_m=displacement_m,
        n_pairs=n_pairs,
        n_typed=n_typed,
        n_wrong_type=n_wrong_type,
        n_map_near=0,
        n_missed=0,
        n_drive_near=0,
        n_extra=0,
    )
