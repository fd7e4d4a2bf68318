"""An offset model over one pass's drives as flat arrays: the offsets of many drives at once.

A final pass shifts every sample by its drive's offset (``OffsetModel.offset``, one drive at a
time). Evaluated drive by drive, a pivot's samples cost one Python call per drive that crosses
its steps: at hundreds of drives per place (16x paper_like) that overhead grew faster than the
samples. ``OffsetTable`` holds the curves of the pass's drives once, concatenated, and evaluates
any mix of drives with the same element-wise arithmetic as ``OffsetModel.offset`` (the same
values to the last bit).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np

__all__ = ["OffsetTable", "knot_position", "offset_table"]


def knot_position(
    u: np.ndarray, n_knots: np.ndarray | int, knot_spacing_m: float, correlation_length_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where distances fall on a drift curve: ``u`` the distance in knot spacings from the curve's
    first knot, ``n_knots`` its knots (per element or one). Returns knot index k (0..K-2),
    fraction t in [0, 1], the prior's decay factor rho outside the knots and the distance
    outside them [m] (``OffsetModel``'s arithmetic, shared by ``OffsetTable``)."""
    k = np.clip(np.floor(u), 0, np.maximum(n_knots - 2, 0)).astype(np.int64)
    t = np.clip(u - k, 0.0, 1.0)
    outside_m = np.maximum(-u, u - (n_knots - 1)).clip(min=0.0) * knot_spacing_m
    rho = np.exp(-outside_m / correlation_length_m)
    return k, t, rho, outside_m


class _Curves(Protocol):
    """What the table reads of an ``OffsetModel`` (``DriveOffset`` curves by drive id)."""

    @property
    def knot_spacing_m(self) -> float: ...

    @property
    def correlation_length_m(self) -> float: ...

    @property
    def drives(self) -> dict[str, Any]: ...


@dataclass(frozen=True)
class OffsetTable:
    """The offset curves of drives 0..N-1 (``OffsetModel``'s, see there), flat.

    Attributes:
        knot_spacing_m, correlation_length_m: the model's.
        known: (N,) the model has the drive (else offset 0).
        k0: (N,) first knot index (float, as the model's arithmetic promotes it).
        n_knots: (N,) knots of the drift (0: bias only).
        bias_m: (N,) bias.
        start: (N,) where the drive's knots begin in ``drift_m``.
        drift_m: (sum n_knots,) the drifts at the knots, drive after drive.
        s0_m: (N,) added to every travelled distance first (a clip's start on its drive), or
            None (the distances are the drives' own).
    """

    knot_spacing_m: float
    correlation_length_m: float
    known: np.ndarray
    k0: np.ndarray
    n_knots: np.ndarray
    bias_m: np.ndarray
    start: np.ndarray
    drift_m: np.ndarray
    s0_m: np.ndarray | None = None

    def with_start(self, s0_m: np.ndarray) -> OffsetTable:
        """The same curves read at ``s + s0_m[drive]`` (a clip's distances; ``s0_m`` (N,))."""
        return replace(self, s0_m=np.asarray(s0_m, dtype=float))

    def offset(self, drive: np.ndarray, s_m: np.ndarray) -> np.ndarray:
        """(M,) offsets [m] of drives ``drive`` (M,) (indices 0..N-1) at distances ``s_m`` (M,)."""
        drive = np.asarray(drive, dtype=np.int64)
        s = np.asarray(s_m, dtype=float)
        if self.s0_m is not None:
            s = s + self.s0_m[drive]
        out = np.zeros(s.shape)
        known = self.known[drive]
        n_knots = self.n_knots[drive]
        bias_only = known & (n_knots == 0)
        out[bias_only] = self.bias_m[drive[bias_only]]
        curve = known & (n_knots > 0)
        if not curve.any():
            return out
        # OffsetModel.offset, element-wise with each drive's knots
        dr, s, nk = drive[curve], s[curve], n_knots[curve]
        u = s / self.knot_spacing_m - self.k0[dr]
        k, t, rho, _ = knot_position(u, nk, self.knot_spacing_m, self.correlation_length_m)
        at = self.start[dr] + k
        # (a curve of one knot has no k + 1: the model would fail there; here it is constant)
        g = (1.0 - t) * self.drift_m[at] + t * self.drift_m[np.minimum(k + 1, nk - 1) + self.start[dr]]
        out[curve] = self.bias_m[dr] + rho * g
        return out


def offset_table(model: _Curves, drive_ids: Sequence[str]) -> OffsetTable:
    """``model``'s curves of ``drive_ids`` (drive i of the table is ``drive_ids[i]``)."""
    n = len(drive_ids)
    curves = [model.drives.get(d) for d in drive_ids]
    known = np.array([c is not None for c in curves], dtype=bool)
    k0 = np.array([float(c.k0) if c is not None else 0.0 for c in curves], dtype=float)
    n_knots = np.array([c.drift_m.size if c is not None else 0 for c in curves], dtype=np.int64)
    bias = np.array([float(c.bias_m) if c is not None else 0.0 for c in curves], dtype=float)
    start = np.zeros(n, dtype=np.int64)
    if n:
        start[1:] = np.cumsum(n_knots)[:-1]
    parts = [np.asarray(c.drift_m, dtype=float).ravel() for c in curves if c is not None and c.drift_m.size]
    drift = np.concatenate(parts) if parts else np.zeros(0)
    return OffsetTable(
        float(model.knot_spacing_m), float(model.correlation_length_m), known, k0, n_knots, bias, start, drift
    )
