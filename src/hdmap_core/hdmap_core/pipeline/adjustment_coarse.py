"""The matrix-free offset solve's coarse space: one shift common to every drive at a place.

What the data of the adjustment cannot see is a function ``f(place)`` added to all drives
there (docs/adjustment.md, "Model": the gauge): only the priors hold it. Conjugate gradients
preconditioned by the per-drive blocks (``adjustment_schur``) corrects it one drive-to-drive
hop per iteration, so
on long chains of drives (4x and 16x paper_like) a solve needs hundreds to thousands of
iterations. Here those modes are solved directly (deflation, Tang et al. 2009, "DEF1"):

- ``Z`` (p x m) spans them: per connected group of drives (drives that share a cluster, directly
  or through others; the two directions of a road never do) one column that moves all its drives'
  biases by 1, and the bilinear hat functions of a square grid of ``COARSE_SPACING_M`` over the
  drift knots, the knot placed where its samples' steps are (weighted by the design matrix);
  without drift (one constant per drive: the coarse stage) over the biases, each at its drive's
  samples' mean place;
- with ``E = Z^T H Z`` (m x m, a few hundred to a few thousand) and ``P = I - H Z E^+ Z^T``,
  CG solves ``P H x = P rhs``, and ``Z E^+ Z^T rhs + P^T x`` is the solution of ``H x = rhs``
  (``P H`` is symmetric; the residual of the deflated system is the original's). ``H Z`` is
  formed once per solve (one product with a sparse p x m matrix), so an iteration still costs one
  product with H.

``Z`` depends on the layout, the samples' places and which drives share clusters, all per fit;
each of these is a sum over samples (``place_sums``, ``drive_links``), so over observations held
in parts (``adjustment_dist``) the client adds the parts' shares and builds the same ``Z``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from hdmap_core.parallel import one_blas_thread

__all__ = ["COARSE_SPACING_M", "Deflation", "coarse_basis", "drive_links", "place_sums"]

#: grid spacing of the coarse hat functions [m]
COARSE_SPACING_M = 400.0
#: eigenvalues of E below this fraction of its largest are dropped (hats that coincide on a line)
PINV_RTOL = 1e-12


def place_sums(a: sp.csr_matrix, xy: np.ndarray) -> np.ndarray:
    """(p, 3) per unknown: the sum of its design-matrix weights over the samples with a place,
    and of those weights times the samples' x and y (the knot's place is their ratio)."""
    ok = np.isfinite(xy).all(axis=1) if xy.shape[0] == a.shape[0] else np.zeros(a.shape[0], dtype=bool)
    w = sp.csr_matrix((np.abs(a.data), a.indices, a.indptr), shape=a.shape)
    vals = np.column_stack([ok, np.where(ok[:, None], xy, 0.0)]).astype(float)
    return np.asarray(w.T @ vals)


def drive_links(drive: np.ndarray, cluster: np.ndarray) -> np.ndarray:
    """(k, 2) pairs of drives seen in one cluster (each cluster's drives chained in order): enough
    to find which drives are connected."""
    if drive.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    n = int(drive.max()) + 1
    pairs = np.unique(cluster.astype(np.int64) * n + drive)  # by cluster, then drive
    c, d = pairs // n, pairs % n
    same = c[1:] == c[:-1]
    key = np.unique(d[:-1][same] * n + d[1:][same])
    return np.column_stack([key // n, key % n])


def coarse_basis(
    col0: np.ndarray, n_knots: np.ndarray, sums: np.ndarray, links: np.ndarray, spacing_m: float = COARSE_SPACING_M
) -> sp.csr_matrix:
    """Z (p x m): per connected group of drives its bias column, then the grid's hats over the
    knots (see the module). ``col0``, ``n_knots``: the layout (bias column and knots per drive);
    ``sums``: ``place_sums`` (summed over parts); ``links``: ``drive_links`` (concatenated)."""
    n_drives = col0.size
    p = sums.shape[0]
    graph = sp.coo_matrix((np.ones(len(links)), (links[:, 0], links[:, 1])), shape=(n_drives, n_drives))
    _, group = connected_components(graph, directed=False)
    n_groups = int(group.max(initial=-1)) + 1
    rows, cols, vals = [col0], [group], [np.ones(n_drives)]
    drive_of = np.repeat(np.arange(n_drives), 1 + n_knots)
    is_knot = np.ones(p, dtype=bool)
    is_knot[col0[n_knots > 0]] = False  # a drive without knots: its bias is placed like a knot
    knot = np.flatnonzero(is_knot & (sums[:, 0] > 0))
    if knot.size:
        g = (sums[knot, 1:] / sums[knot, :1]) / spacing_m
        base = np.floor(g.min(axis=0))
        cell = np.floor(g - base).astype(np.int64)
        frac = g - base - cell
        nx, ny = int(cell[:, 0].max()) + 2, int(cell[:, 1].max()) + 2
        for dx in (0, 1):
            for dy in (0, 1):
                w = (frac[:, 0] if dx else 1.0 - frac[:, 0]) * (frac[:, 1] if dy else 1.0 - frac[:, 1])
                node = (group[drive_of[knot]] * nx + cell[:, 0] + dx) * ny + cell[:, 1] + dy
                rows.append(knot)
                cols.append(n_groups + node)
                vals.append(w)
    r, c, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    keep = v > 0
    _, c = np.unique(c[keep], return_inverse=True)  # only the nodes some knot uses
    return sp.csr_matrix((v[keep], (r[keep], c.ravel())), shape=(p, int(c.max(initial=-1)) + 1))


class Deflation:
    """``P = I - H Z E^+ Z^T`` and the correction back to ``H x = rhs`` (see the module), for an
    operator ``h`` with ``matmat`` (H times a sparse matrix)."""

    def __init__(self, h: Any, z: sp.csr_matrix) -> None:
        self.z = z
        self.hz = sp.csr_matrix(h.matmat(z))
        e = np.asarray((z.T @ self.hz).todense())
        with one_blas_thread():
            lam, vec = np.linalg.eigh(0.5 * (e + e.T))
        ok = lam > PINV_RTOL * max(float(lam.max(initial=0.0)), 1e-300)
        self._e_pinv = (vec[:, ok] / lam[ok]) @ vec[:, ok].T
        self.size = int(ok.sum())

    def _coarse(self, v: np.ndarray) -> np.ndarray:
        return np.asarray(self._e_pinv @ np.asarray(self.z.T @ v).ravel())

    def project(self, r: np.ndarray) -> np.ndarray:
        """P r."""
        return np.asarray(r - self.hz @ self._coarse(r)).ravel()

    def solution(self, x: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """Z E^+ Z^T rhs + P^T x: the solution of H x = rhs from one of P H x = P rhs."""
        y = self._e_pinv @ (np.asarray(self.z.T @ rhs).ravel() - np.asarray(self.hz.T @ x).ravel())
        return np.asarray(x + self.z @ y).ravel()
