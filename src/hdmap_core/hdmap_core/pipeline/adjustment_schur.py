"""The offset adjustment's reduced normal equations as an operator: never the drive-pair matrix.

Eliminating a cluster's position from the adjustment (``adjustment.reduced_normal``) gives

    H = A^T W A + P - B diag(1 / W_c) B^T,   B = A^T W E   (E: sample -> cluster incidence)

in which the last term couples every pair of the drives seen in a cluster: d^2 entries per
cluster of d drives, and a factorisation fills in about as much again. Where many drives cross a
place (hundreds at 16x paper_like) that term, not the samples, is what the solve holds. Here H is
applied without forming it, as two sparse products with B and one with the per-drive blocks
``K = A^T W A + P`` (every row of A touches one drive's columns, so K is block diagonal by
drive): linear in the samples. ``SchurSolver`` solves H x = rhs by conjugate gradients,
preconditioned by the per-drive diagonal blocks of H (K minus the pair term's blocks within a
drive; factorised, they are as sparse as K) and deflated by a coarse space of place-wise shifts
(``adjustment_coarse``), warm-started at the previous IRLS solution. The
solution is the explicit solve's within the CG tolerance (relative residual 1e-10: about 1e-9 m
on a 16x tile; tests/test_adjustment_schur.py).

``pair_fill`` counts the explicit term's entries (a slab of rows at a time, stopping past the
budget); ``adjustment._irls`` uses the operator only above
``AdjustConfig.max_pair_fill``, so fleets below it solve exactly as before.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from hdmap_core.pipeline.adjustment_coarse import Deflation

__all__ = ["pair_fill", "SchurNormal", "SchurSolver"]

#: CG stops at this relative residual (NormalSolver's preconditioned CG uses the same)
CG_RTOL = 1e-10
#: CG iterations per solve at most (measured: 43 from zero on a 745-drive tile of 16x paper_like)
CG_MAXITER = 2000
#: ``SchurNormal.toarray`` adds the pair term this many clusters at a time
#: ``pair_fill`` counts the pair term's entries this many rows (unknowns) at a time
PAIR_COUNT_ROWS = 512
DENSE_CHUNK_CLUSTERS = 256


def _weighted_at(a: sp.csr_matrix, info: np.ndarray) -> sp.csr_matrix:
    """A^T W in CSR (rows scaled through .data, as ``adjustment.reduced_normal`` does)."""
    scaled = sp.csr_matrix((a.data * np.repeat(info, np.diff(a.indptr)), a.indices, a.indptr), shape=a.shape)
    return scaled.T.tocsr()


def _incidence(index: np.ndarray, n_cols: int) -> sp.csr_matrix:
    n = index.size
    return sp.csr_matrix((np.ones(n), index, np.arange(n + 1)), shape=(n, n_cols))


def pair_fill(a: sp.csr_matrix, cluster: np.ndarray, n_clusters: int, stop_above: int | None = None) -> int:
    """Entries of the explicit pair term B diag(1/W_c) B^T (its sparsity pattern: which unknowns
    share a cluster; independent of the weights). Counted PAIR_COUNT_ROWS rows at a time, so the
    count holds one slab of the pattern, never all of it; with ``stop_above`` the count stops
    (returning a number above it) as soon as it exceeds it, so it costs at most about that much."""
    pattern = sp.csr_matrix((np.ones(a.nnz), a.indices, a.indptr), shape=a.shape).T.tocsr()
    b = (pattern @ _incidence(cluster, n_clusters)).tocsr()
    bt = b.T.tocsr()
    count = 0
    for r0 in range(0, b.shape[0], PAIR_COUNT_ROWS):
        count += (b[r0 : r0 + PAIR_COUNT_ROWS] @ bt).nnz
        if stop_above is not None and count > stop_above:
            break
    return int(count)


class SchurNormal:
    """H = A^T W A + P - B diag(1/W_c) B^T and its rhs, held as its sparse factors (see the module).

    Args:
        a: (n, p) design matrix (``adjustment.design_matrix``).
        cluster: (n,) cluster of every sample, 0..n_clusters-1.
        n_clusters: number of clusters.
        info: (n,) sample weights / noise variance.
        lateral: (n,) lateral positions.
        prior: (p, p) prior information (``adjustment.prior_matrix``; per drive).
        drive: (n,) drive of every sample (A's row i touches only drive[i]'s columns).
    """

    def __init__(
        self,
        a: sp.csr_matrix,
        cluster: np.ndarray,
        n_clusters: int,
        info: np.ndarray,
        lateral: np.ndarray,
        prior: sp.csr_matrix,
        drive: np.ndarray,
    ) -> None:
        self.a, self.cluster, self.n_clusters, self.lateral, self.prior, self.drive = (
            a,
            cluster,
            n_clusters,
            lateral,
            prior,
            drive,
        )
        self.info = info
        self.shape = (a.shape[1], a.shape[1])
        w_c = np.maximum(np.bincount(cluster, weights=info, minlength=n_clusters), 1e-300)
        self._inv_w = 1.0 / w_c
        awt = _weighted_at(a, info)
        self._k = (awt @ a + prior).tocsr()
        self._b = (awt @ _incidence(cluster, n_clusters)).tocsr()
        self._bt = self._b.T.tocsr()
        mean_l = np.bincount(cluster, weights=info * lateral, minlength=n_clusters) / w_c
        self.rhs = -np.asarray(awt @ (lateral - mean_l[cluster])).ravel()

    def reweighted(self, info: np.ndarray) -> SchurNormal:
        """The same system with other sample weights."""
        return SchurNormal(self.a, self.cluster, self.n_clusters, info, self.lateral, self.prior, self.drive)

    def matvec(self, v: np.ndarray) -> np.ndarray:
        """H @ v."""
        return np.asarray(self._k @ v - self._b @ (self._inv_w * (self._bt @ v))).ravel()

    def __matmul__(self, v: np.ndarray) -> np.ndarray:
        return self.matvec(v)

    def matmat(self, z: sp.spmatrix) -> sp.csr_matrix:
        """H @ z for a sparse z (the coarse space's ``H Z``)."""
        return (self._k @ z - self._b @ (sp.diags(self._inv_w) @ (self._bt @ z))).tocsr()

    def drive_blocks(self) -> sp.csc_matrix:
        """The diagonal blocks of H within each drive (H's other entries set to 0), as CSC.

        The pair term's part within a drive: B restricted to (cluster, drive) groups, i.e. the
        samples of one drive in one cluster summed, which touch that drive's columns only."""
        n_drives = int(self.drive.max(initial=-1)) + 1
        _, group = np.unique(self.cluster.astype(np.int64) * n_drives + self.drive, return_inverse=True)
        group = group.ravel()
        n_groups = int(group.max(initial=-1)) + 1
        group_cluster = np.zeros(n_groups, dtype=np.int64)
        group_cluster[group] = self.cluster
        bg = (_weighted_at(self.a, self.info) @ _incidence(group, n_groups)).tocsr()
        bg_scaled = sp.csr_matrix(
            (bg.data * self._inv_w[group_cluster[bg.indices]], bg.indices, bg.indptr), shape=bg.shape
        )
        return (self._k - bg_scaled @ bg.T).tocsc()

    def toarray(self) -> np.ndarray:
        """Dense H (for the posterior covariance of small problems), the pair term added a chunk of
        clusters at a time (never all its entries at once)."""
        dense = self._k.toarray()
        b = self._b.tocsc()
        for c0 in range(0, self.n_clusters, DENSE_CHUNK_CLUSTERS):
            part = b[:, c0 : c0 + DENSE_CHUNK_CLUSTERS]
            scaled = part @ sp.diags(self._inv_w[c0 : c0 + DENSE_CHUNK_CLUSTERS])
            pairs = (scaled @ part.T).tocoo()  # a product: no duplicate entries
            dense[pairs.row, pairs.col] -= pairs.data
        return dense


class SchurSolver:
    """Conjugate gradients on a ``SchurNormal``, preconditioned by its per-drive blocks (factorised
    each solve: the weights change between IRLS solves, and the blocks are as sparse as K) and,
    with ``coarse`` (``adjustment_coarse.coarse_basis``), deflated by that coarse space.
    ``iterations``: CG iterations of all solves; ``unconverged``: solves that hit CG_MAXITER
    (their last iterate is returned); ``coarse_unknowns``: the last solve's coarse space rank."""

    def __init__(self, coarse: sp.csr_matrix | None = None) -> None:
        self.iterations = 0
        self.unconverged = 0
        self.coarse = coarse
        self.coarse_unknowns = 0

    def solve(self, h: Any, rhs: np.ndarray, x0: np.ndarray) -> np.ndarray:
        """``h``: a ``SchurNormal`` or an operator with its ``matvec``, ``drive_blocks`` (and
        ``matmat`` with ``coarse``)."""
        blocks = spla.splu(
            h.drive_blocks(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True)
        )
        count = [0]

        def _count(_: Any) -> None:
            count[0] += 1

        matvec, b = h.matvec, rhs
        defl = Deflation(h, self.coarse) if self.coarse is not None and self.coarse.shape[1] else None
        if defl is not None:
            matvec, b = (lambda v: defl.project(h.matvec(v))), defl.project(rhs)
            self.coarse_unknowns = defl.size
        x, info = spla.cg(
            spla.LinearOperator(h.shape, matvec=matvec, dtype=float),
            b,
            x0=x0,
            M=spla.LinearOperator(h.shape, matvec=blocks.solve, dtype=float),
            rtol=CG_RTOL,
            atol=0.0,
            maxiter=CG_MAXITER,
            callback=_count,
        )
        self.iterations += count[0]
        self.unconverged += int(info != 0)
        return defl.solution(np.asarray(x), rhs) if defl is not None else np.asarray(x)
