"""Named fleet scenarios of the benchmarks: a map, its length and the simulator's settings.

Each is a synthetic layout with simulator overrides. ``paper_like`` follows the paper's data set
(Sec. VII): both directions with exits and entries, 134 drive snippets, ~400 drive-km, 5-25 drives
per place (a 12 km motorway with an interchange every 3 km, snippets of 2-6 km; the simulator's
"coverage" route choice drives every ramp, and a mild direction bias keeps the lesser direction
at >= 5 drives per place too: 96 % of its 50 m places have 5-25 drives). Used by ``hdmap bench``
and the map-updating benchmark's no-change fleets.
"""

from __future__ import annotations

from typing import Any

__all__ = ["NAMED_SCENARIOS"]

NAMED_SCENARIOS: dict[str, dict[str, Any]] = {
    "paper_like": {
        "map": "motorway_ramps",
        "length_m": 12000.0,
        "drives": 134,
        "sim": {"snippet_length_min_m": 2000.0, "snippet_length_max_m": 6000.0, "direction_bias": 0.55},
    },
}
