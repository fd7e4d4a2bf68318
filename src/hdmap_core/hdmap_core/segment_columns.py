"""Segments (``steps.Segment``) as columns: flat arrays cut by counts, one per field.

The live suite moves many tiles' segments at once (the mapper's store, the batch message of a
fused drive's tiles): made and read as whole arrays they cost a copy per field instead of an
object per step. :func:`segment_columns` and :func:`columns_to_segments` are exact inverses (every
``StepResult`` field, float64 as is).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hdmap_core.steps import Segment, StepResult

__all__ = ["SegmentColumns", "segment_columns", "columns_to_segments", "take_segments", "split_by"]


@dataclass(frozen=True)
class SegmentColumns:
    """The steps of some segments in columns.

    Attributes:
        pivots: (S,) pivot id per segment.
        nsteps: (S,) steps per segment (the steps follow each other in segment order).
        index, s_m, heading, width_m, valid, processed_before, judged: (N,) per step.
        midpoint, pose: (N, 2) per step [m] (pose NaN: not known).
        k: (N,) maxima per step; lateral_m, types, counts, std_m: (sum k,) per maximum.
        n_empty: (N,) empty intervals per step; empty_m: (sum n_empty, 2) [m].
        drive_names: the steps' drive ids, each once; n_drives: (N,) drives per step;
            drive_index: (sum n_drives,) index into ``drive_names`` per (step, drive).
    """

    pivots: tuple[str, ...]
    nsteps: np.ndarray
    index: np.ndarray
    s_m: np.ndarray
    midpoint: np.ndarray
    pose: np.ndarray
    heading: np.ndarray
    width_m: np.ndarray
    valid: np.ndarray
    processed_before: np.ndarray
    judged: np.ndarray
    k: np.ndarray
    lateral_m: np.ndarray
    types: np.ndarray
    counts: np.ndarray
    std_m: np.ndarray
    n_empty: np.ndarray
    empty_m: np.ndarray
    drive_names: tuple[str, ...]
    n_drives: np.ndarray
    drive_index: np.ndarray

    def step_drive_ids(self) -> list[tuple[str, ...]]:
        """The drive ids of every step."""
        names = np.asarray(self.drive_names, dtype=object)
        return [tuple(p.tolist()) for p in split_by(names[self.drive_index], self.n_drives)]


def split_by(flat: np.ndarray, lengths: np.ndarray) -> list[np.ndarray]:
    """``flat`` cut into consecutive pieces of ``lengths``."""
    return np.split(flat, np.cumsum(lengths)[:-1]) if len(lengths) else []


def _cat(parts: list[np.ndarray], dtype, shape=(0,)) -> np.ndarray:
    return np.concatenate(parts).astype(dtype, copy=False) if parts else np.zeros(shape, dtype=dtype)


def segment_columns(segments: Sequence[Segment]) -> SegmentColumns:
    """Segments -> columns (every field exactly)."""
    steps = [st for seg in segments for st in seg.steps]
    lat = [np.asarray(st.lateral_m, dtype=np.float64).reshape(-1) for st in steps]
    empty = [np.asarray(st.empty_m, dtype=np.float64).reshape(-1, 2) for st in steps if st.empty_m is not None]
    names: dict[str, int] = {}
    drive_index = [names.setdefault(d, len(names)) for st in steps for d in st.drive_ids]
    return SegmentColumns(
        pivots=tuple(s.pivot_id for s in segments),
        nsteps=np.array([len(s.steps) for s in segments], dtype=np.int64),
        index=np.array([st.index for st in steps], dtype=np.int64),
        s_m=np.array([st.s_m for st in steps], dtype=np.float64),
        midpoint=np.array([np.asarray(st.midpoint, dtype=np.float64) for st in steps]).reshape(-1, 2),
        pose=np.array(
            [
                np.full(2, np.nan) if st.pose is None else np.asarray(st.pose, dtype=np.float64).reshape(-1)[:2]
                for st in steps
            ]
        ).reshape(-1, 2),
        heading=np.array([st.heading for st in steps], dtype=np.float64),
        width_m=np.array([st.width_m for st in steps], dtype=np.float64),
        valid=np.array([st.valid for st in steps], dtype=bool),
        processed_before=np.array([st.processed_before for st in steps], dtype=bool),
        judged=np.array([st.empty_m is not None for st in steps], dtype=bool),
        k=np.array([len(x) for x in lat], dtype=np.int64),
        lateral_m=_cat(lat, np.float64),
        types=_cat([np.asarray(st.types, dtype=np.int64).reshape(-1) for st in steps], np.int64),
        counts=_cat([np.asarray(st.counts, dtype=np.int64).reshape(-1) for st in steps], np.int64),
        std_m=_cat([np.asarray(st.std_m, dtype=np.float64).reshape(-1) for st in steps], np.float64),
        n_empty=np.array(
            [0 if st.empty_m is None else len(np.asarray(st.empty_m).reshape(-1, 2)) for st in steps], dtype=np.int64
        ),
        empty_m=_cat(empty, np.float64, (0, 2)).reshape(-1, 2),
        drive_names=tuple(names),
        n_drives=np.array([len(st.drive_ids) for st in steps], dtype=np.int64),
        drive_index=np.array(drive_index, dtype=np.int64),
    )


def columns_to_segments(c: SegmentColumns) -> list[Segment]:
    """Columns -> segments (the inverse of :func:`segment_columns`)."""
    lat, typ, cnt, std = (split_by(a, c.k) for a in (c.lateral_m, c.types, c.counts, c.std_m))
    empty = split_by(c.empty_m.reshape(-1, 2), c.n_empty)
    ids = c.step_drive_ids()
    known = np.isfinite(c.pose).all(axis=1)
    out, at = [], 0
    for pivot, n in zip(c.pivots, c.nsteps.tolist(), strict=True):
        steps = tuple(
            StepResult(
                pivot_id=pivot,
                index=int(c.index[i]),
                s_m=float(c.s_m[i]),
                midpoint=c.midpoint[i],
                heading=float(c.heading[i]),
                width_m=float(c.width_m[i]),
                valid=bool(c.valid[i]),
                processed_before=bool(c.processed_before[i]),
                lateral_m=lat[i],
                types=typ[i],
                counts=cnt[i],
                std_m=std[i],
                drive_ids=ids[i],
                empty_m=empty[i] if c.judged[i] else None,
                pose=c.pose[i] if known[i] else None,
            )
            for i in range(at, at + n)
        )
        out.append(Segment(pivot_id=pivot, steps=steps))
        at += n
    return out


def take_segments(c: SegmentColumns, lo: int, hi: int) -> SegmentColumns:
    """The segments ``lo:hi`` of ``c`` (their steps, maxima, intervals and drives), in columns."""
    s0, s1 = (int(x) for x in np.concatenate([[0], np.cumsum(c.nsteps)])[[lo, hi]])
    kc = np.concatenate([[0], np.cumsum(c.k)])
    ec = np.concatenate([[0], np.cumsum(c.n_empty)])
    dc = np.concatenate([[0], np.cumsum(c.n_drives)])
    m, e, d = slice(kc[s0], kc[s1]), slice(ec[s0], ec[s1]), slice(dc[s0], dc[s1])
    st = slice(s0, s1)
    return SegmentColumns(
        pivots=c.pivots[lo:hi],
        nsteps=c.nsteps[lo:hi],
        index=c.index[st],
        s_m=c.s_m[st],
        midpoint=c.midpoint[st],
        pose=c.pose[st],
        heading=c.heading[st],
        width_m=c.width_m[st],
        valid=c.valid[st],
        processed_before=c.processed_before[st],
        judged=c.judged[st],
        k=c.k[st],
        lateral_m=c.lateral_m[m],
        types=c.types[m],
        counts=c.counts[m],
        std_m=c.std_m[m],
        n_empty=c.n_empty[st],
        empty_m=c.empty_m[e],
        drive_names=c.drive_names,
        n_drives=c.n_drives[st],
        drive_index=c.drive_index[d],
    )
