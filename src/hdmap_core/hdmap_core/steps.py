"""Hand-off data between the lateral stages (Sec. IV) and the connection stages (Sec. V/VI).

``StepResult`` is one sampling step of one pivot drive after aggregation; ``Segment`` is the
ordered steps of one pivot drive. ``StepObservations`` is what the per-step EM saw at an accepted
step (every sample with its drive, lateral position and cluster label); the global offset
adjustment (``hdmap_core.pipeline.adjustment``) consumes these.

Lateral positions are measured along the cut line from the step's midpoint, positive to the left
of the heading: world point = midpoint + lateral_m * left_normal(heading).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hdmap_core.geometry import left_normal  # re-exported: the steps' lateral convention

__all__ = ["StepResult", "Segment", "StepObservations", "left_normal"]


@dataclass(frozen=True)
class StepResult:
    """One accepted (or rejected) sampling step of one pivot drive.

    Attributes:
        pivot_id: drive id of the pivot.
        index: step number along the pivot (0, 1, ...), ``step_m`` apart.
        s_m: travelled distance of the pivot at this step [m].
        midpoint: (2,) road midpoint (after drift removal) [m].
        heading: ENU yaw of the cut's forward direction [rad].
        width_m: refined cut-line length (ego-road width estimate) [m].
        valid: False when the EM rejected the step (silhouette below the gate) or no samples.
        processed_before: True when this stretch was already mapped through another pivot.
        lateral_m: (K,) aggregated maxima along the cut, + = left of heading [m].
        types: (K,) FeatureType codes (int).
        counts: (K,) number of drives supporting each maximum.
        std_m: (K,) 1-sigma lateral uncertainty of each maximum [m].
        drive_ids: drives that took part in this step.
        empty_m: (M, 2) intervals [lo, hi] along the cut, from the midpoint (+ = left) [m], where
            the drives that passed saw nothing though a line there would have been detected
            (``hdmap_core.pipeline.evidence``); None: not judged (no profile made for this step).
        pose: (2,) the pivot's own trajectory point at this step, corrected like its samples
            (``PivotSamples.pose``) [m]: where it drove, while a rejected step's midpoint may lie
            on another road; None: not known.
    """

    pivot_id: str
    index: int
    s_m: float
    midpoint: np.ndarray
    heading: float
    width_m: float
    valid: bool
    processed_before: bool
    lateral_m: np.ndarray
    types: np.ndarray
    counts: np.ndarray
    std_m: np.ndarray
    drive_ids: tuple[str, ...] = ()
    empty_m: np.ndarray | None = None
    pose: np.ndarray | None = None

    def points(self) -> np.ndarray:
        """(K, 2) world points of the maxima [m]."""
        lat = np.asarray(self.lateral_m, dtype=float).reshape(-1)
        return np.asarray(self.midpoint, dtype=float)[None, :] + lat[:, None] * left_normal(self.heading)[None, :]


@dataclass(frozen=True)
class Segment:
    """The steps of one pivot drive, in order of ``index``."""

    pivot_id: str
    steps: tuple[StepResult, ...] = ()


@dataclass(frozen=True)
class StepObservations:
    """What the per-step EM saw at one accepted step (input of the global offset adjustment).

    Attributes:
        pivot_id: drive id of the pivot.
        index: step number along the pivot.
        midpoint: (2,) cut-line midpoint used for sampling (before drift removal) [m].
        heading: ENU yaw of the cut's forward direction [rad].
        drive_ids: (M,) drive id of each sample.
        drive_s_m: (M,) travelled distance of the sampled drive at the sample [m] (the sample point
            projected onto that drive's trajectory).
        lateral_m: (M,) raw sample position along the cut, + = left [m] (no offset applied).
        types: (M,) FeatureType codes.
        cluster: (M,) int label from the EM's final clustering; labels are unique within the step
            across types; -1 = outlier / dropped.
        offsets_m: (M,) the per-step EM offset of each sample's drive [m]; empty when not estimated.
    """

    pivot_id: str
    index: int
    midpoint: np.ndarray
    heading: float
    drive_ids: tuple[str, ...]
    drive_s_m: np.ndarray
    lateral_m: np.ndarray
    types: np.ndarray
    cluster: np.ndarray
    offsets_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
