"""Settings of change detection and map updating (docs/updates.md)."""

from __future__ import annotations

from dataclasses import dataclass

from hdmap_core.checks import check_range

__all__ = ["ChangeConfig"]


@dataclass(frozen=True)
class ChangeConfig:
    """How drives are compared with the map, and when a place counts as changed.

    Attributes:
        cell_m: size of a place's cell [m] (each split by driving direction).
        cut_step_m: a drive is compared with the map on a cut across its path every this far [m].
        view_m: each cut reaches this far to each side of the drive [m].
        pair_max_m: a drive's line and a map line of the same class (marking / border) on a cut
            this close are a candidate pair; the largest offset (localisation + change) sought [m].
        max_shift_m: the markings' offset is sought this far around the anchor: the largest move
            of the markings seen (half a lane: farther, a marking pairs with its neighbour) [m].
        kernel_m: kernel width of the offset density per place [m].
        near_m: markings within this of the drive count for type, negative and positive
            evidence (the ego lane's markings, seen by nearly every drive) [m].
        match_m: a drive's marking and a map marking closer than this (after the drive's offset)
            are the same line [m].
        min_pairs: marking pairs a drive needs in a place to give its displacement there.
        min_border_pairs: border pairs it needs to anchor its offset on the borders there
            (else the drive's own offset over all its places anchors it).
        min_points: marking points a drive needs in a place for its type / negative / positive
            shares there.
        min_before, min_after: drives a place needs before and after a change point.
        min_after_shares: drives a place needs after a change point of a share (type, missed,
            extra: noisier than the displacement, and the map's own type errors look alike).
        max_share_before: a share's change counts only where its before median is below this.
        min_shift_m: smallest change of the markings' displacement confirmed [m].
        min_share: smallest change of a share (wrong type, missed, extra) confirmed.
        min_share_drive: smallest share (over the before median) each drive after a change point
            of a share must show: a changed line is one of the two markings near a drive in its
            lane, about half of the points it reads there (a drive misreading pieces of a line
            reads less, and a chance run of such drives at the end of a fleet made false changes).
        z_min: the change in the mean must be this many standard errors of it.
        displacement_floor_m: smallest per-drive spread of the displacement assumed [m].
        share_floor: smallest per-drive spread of a share assumed.
        model_unseen: move the first map's markings that no drive after a shift saw by the shift
            the drives measured (``updates.unseen``; flagged: ``drive_count`` 0).
        unseen_match_m: a first-map marking moved by its place's displacement and a local
            marking this close are the same line, seen moved [m].
        unseen_stay_m: ... a local marking this close to where it was: seen staying [m].
        unseen_seen_m: a moved point with a local marking this close was seen: not modelled [m].
        unseen_line_points: points a first-map marking needs in a place to count as seen.
        unseen_min_lines: lines seen moved a place needs for its unseen markings to move.
        unseen_alike_m: every line seen moved lies within this of their median move [m].
        unseen_radius_m: an unseen point moves by the median move of the seen points this near [m].
        unseen_explained: share of the local map's markings in a place that must lie where a
            first-map marking of their type moved by the place's displacement lies (a shift near
            a lane's width pairs each line with its neighbour: the edge lines are left over).
    """

    cell_m: float = 100.0
    cut_step_m: float = 4.0
    view_m: float = 12.0
    pair_max_m: float = 3.0
    max_shift_m: float = 1.75
    kernel_m: float = 0.15
    near_m: float = 3.0
    match_m: float = 0.4
    min_pairs: int = 15
    min_border_pairs: int = 8
    min_points: int = 10
    min_before: int = 3
    min_after: int = 2
    min_after_shares: int = 3
    max_share_before: float = 0.2
    min_shift_m: float = 0.5
    min_share: float = 0.3
    min_share_drive: float = 0.45
    z_min: float = 5.0
    displacement_floor_m: float = 0.1
    share_floor: float = 0.05
    model_unseen: bool = True
    unseen_match_m: float = 0.5
    unseen_stay_m: float = 0.3
    unseen_seen_m: float = 1.0
    unseen_line_points: int = 10
    unseen_min_lines: int = 2
    unseen_alike_m: float = 0.3
    unseen_radius_m: float = 50.0
    unseen_explained: float = 0.8

    def __post_init__(self) -> None:
        check_range(
            self,
            (
                "cell_m",
                "cut_step_m",
                "view_m",
                "pair_max_m",
                "max_shift_m",
                "kernel_m",
                "near_m",
                "match_m",
                "min_shift_m",
                "z_min",
                "unseen_match_m",
                "unseen_stay_m",
                "unseen_seen_m",
                "unseen_alike_m",
                "unseen_radius_m",
            ),
            low=0.0,
            low_open=True,
        )
        check_range(
            self,
            (
                "displacement_floor_m",
                "share_floor",
                "min_share",
                "min_share_drive",
                "max_share_before",
                "unseen_explained",
            ),
            low=0.0,
            low_open=True,
        )
        check_range(
            self,
            (
                "min_pairs",
                "min_border_pairs",
                "min_points",
                "min_before",
                "min_after",
                "min_after_shares",
                "unseen_line_points",
                "unseen_min_lines",
            ),
            low=1,
            integer=True,
        )
