"""Shared pieces of the permutation-synchronisation solvers (spectral, MatchEIG, CLEAR, MatchALS, PGDDS).

- :func:`check_inputs`: the validation every public ``spectral(...)``, ``matchals(...)``, ...
  function does first (shapes, ``view_offsets`` ending at N), so a wrong argument fails with a
  ``ValueError`` naming it instead of deep inside a linear-algebra routine.
- :func:`component_eigh`: the exact eigendecomposition of a symmetric sparse matrix computed one
  connected component at a time. The binary nearest-neighbour graphs these methods are fed fall
  apart into thousands of components of a few keypoints each, so this costs milliseconds where a
  dense N×N decomposition costs seconds, and it never mixes eigenvectors of different
  components inside a degenerate eigenspace (which would correlate unrelated keypoints).
  Only the largest component is ever dense; it must not exceed the solver's ``max_nodes``.
- :func:`zhou_rounding`: the rounding of Zhou et al.'s multi-way matching code (per-seed,
  per-later-view maximum correlation of L2-normalised embedding rows above a threshold).
- :func:`sparse_soft_matches`: the cross-view upper triangle of a sparse score matrix.
"""
from __future__ import annotations

from typing import Optional, Tuple

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ..rounding import estimate_universe_size, relabel_tracks
from .base import SoftMatches

__all__ = ["check_inputs", "check_node_limit", "view_index_of", "component_eigh", "select_eigvecs",
           "zhou_rounding", "sparse_soft_matches", "resolve_universe_size", "parse_universe",
           "check_spectral_settings",
           "repair_tracks"]


def check_inputs(adjacency, view_offsets, *, method: str) -> Tuple[sp.csr_matrix, np.ndarray]:
    """Validate and normalise the input of a synchronisation method.

    Args:
        adjacency: (N, N) scipy.sparse matrix or ndarray of pairwise match scores in [0, 1].
        view_offsets: (V+1,) keypoints of view v are ``view_offsets[v]:view_offsets[v+1]``.
        method: name used in error messages.

    Returns:
        (A, offsets): A is (N, N) float64 CSR, symmetrised as (A + Aᵀ)/2, with the diagonal and
        every within-view block set to zero (a keypoint is never matched inside its own view);
        offsets is int64 (V+1,).

    Raises:
        ValueError: naming ``adjacency`` or ``view_offsets``.
    """
    offs = np.asarray(view_offsets)
    if offs.ndim != 1 or offs.shape[0] < 2:
        raise ValueError(f"{method}: 'view_offsets' must be a 1-D array of V+1 >= 2 entries, "
                         f"got shape {offs.shape}")
    if offs.dtype.kind not in "iu":
        if offs.dtype.kind != "f" or not np.all(offs == np.round(offs)):
            raise ValueError(f"{method}: 'view_offsets' must hold integers, got dtype {offs.dtype}")
    offs = offs.astype(np.int64)
    if sp.issparse(adjacency):
        shape = adjacency.shape
    else:
        adjacency = np.asarray(adjacency)
        if adjacency.dtype.kind not in "biuf":
            raise ValueError(f"{method}: 'adjacency' must be numeric, got dtype {adjacency.dtype}")
        shape = adjacency.shape
    if len(shape) != 2 or shape[0] != shape[1]:
        raise ValueError(f"{method}: 'adjacency' must be a square (N, N) matrix, got shape {tuple(shape)}")
    n = int(shape[0])
    if offs[0] != 0 or offs[-1] != n or np.any(np.diff(offs) < 0):
        raise ValueError(f"{method}: 'view_offsets' must start at 0, be non-decreasing and end at "
                         f"N={n} (the size of 'adjacency'), got {offs.tolist()}")
    a = sp.csr_matrix(adjacency, dtype=np.float64)
    if a.nnz and not np.all(np.isfinite(a.data)):
        raise ValueError(f"{method}: 'adjacency' contains NaN or inf")
    a = ((a + a.T) * 0.5).tocoo()
    view = view_index_of(offs)
    keep = view[a.row] != view[a.col]
    a = sp.csr_matrix((a.data[keep], (a.row[keep], a.col[keep])), shape=(n, n))
    a.eliminate_zeros()
    a.sort_indices()
    return a, offs


def view_index_of(offsets: np.ndarray) -> np.ndarray:
    """(N,) view of every keypoint."""
    return np.repeat(np.arange(len(offsets) - 1, dtype=np.int64), np.diff(offsets))


def check_node_limit(n: int, max_nodes: int, *, method: str, what: str = "keypoints") -> None:
    """Refuse a dense problem that would not fit instead of exhausting memory."""
    if n > max_nodes:
        mib = 4.0 * n * n / 2 ** 20
        raise ValueError(f"{method}: {n} {what} exceed this dense method's node limit max_nodes={max_nodes} "
                         f"(it holds {n}x{n} matrices, {mib:.0f} MiB each); raise max_nodes or use a "
                         f"sparse method (e.g. nn, clear on a nearest-neighbour graph)")


def check_spectral_settings(config, soft_choices: tuple, *, method: str) -> None:
    """The settings spectral, MatchEIG and CLEAR share: ``soft`` output kind, ``max_nodes``, ``universe``."""
    if config.soft not in soft_choices:
        raise ValueError(f"soft must be one of {soft_choices}, got {config.soft!r}")
    if config.max_nodes < 1:
        raise ValueError(f"max_nodes must be >= 1, got {config.max_nodes}")
    parse_universe(config.universe, method=method)


def parse_universe(value, *, method: str) -> Optional[int]:
    """``'est'`` (or None) -> None; a positive integer (or its string) -> int."""
    if value is None:
        return None
    if isinstance(value, str):
        if value.strip().lower() in ("est", "auto", ""):
            return None
        try:
            value = int(value)
        except ValueError:
            raise ValueError(f"{method}: universe size must be 'est' or a positive integer, got {value!r}") from None
    value = int(value)
    if value < 1:
        raise ValueError(f"{method}: universe size must be >= 1, got {value}")
    return value


def resolve_universe_size(universe, adjacency: sp.csr_matrix, offsets: np.ndarray, *, method: str) -> int:
    """The universe size d: given, or estimated from the spectrum (never the true count)."""
    d = parse_universe(universe, method=method)
    n = adjacency.shape[0]
    if d is None:
        d = estimate_universe_size(adjacency, np.diff(offsets))
    return int(max(1, min(d, n)))


# -- eigendecomposition by connected components ------------------------------------------------
class ComponentEig:
    """Eigenpairs of a block-diagonal (after permutation) symmetric matrix.

    Attributes:
        values: (K,) eigenvalues, K = N; pair k belongs to component ``comp[k]``.
        vectors: (N, K) CSC matrix; column k is the unit eigenvector of pair k (supported on its component).
        comp: (K,) component id of each pair; labels: (N,) component id of each node.
    """

    def __init__(self, values, vectors, comp, labels):
        self.values, self.vectors, self.comp, self.labels = values, vectors, comp, labels


def component_eigh(matrix: sp.spmatrix, *, max_nodes: int, method: str) -> ComponentEig:
    """All eigenpairs of the symmetric sparse ``matrix``, one connected component at a time.

    Components of equal size are decomposed in one batched call; only the largest component
    is dense, and it must have at most ``max_nodes`` nodes.
    """
    m = sp.csr_matrix(matrix, dtype=np.float64)
    n = m.shape[0]
    if n == 0:
        return ComponentEig(np.zeros(0), sp.csc_matrix((0, 0)), np.zeros(0, np.int64), np.zeros(0, np.int64))
    n_comp, labels = connected_components(m, directed=False)
    sizes = np.bincount(labels, minlength=n_comp)
    if sizes.max() > max_nodes:
        check_node_limit(int(sizes.max()), max_nodes, method=method,
                         what="keypoints in one connected component of the input graph")
    order = np.argsort(labels, kind="stable")  # nodes grouped by component, ascending inside
    starts = np.r_[0, np.cumsum(sizes)]
    vals, comp, rows, cols, data = [], [], [], [], []
    col0 = 0
    for s in np.unique(sizes):
        comps = np.flatnonzero(sizes == s)
        k = comps.size
        nodes = order[starts[comps][:, None] + np.arange(s)[None, :]]  # (k, s)
        flat = nodes.ravel()
        sub = m[flat][:, flat].tocoo()  # block diagonal by construction
        blocks = np.zeros((k, s, s))
        blocks[sub.row // s, sub.row % s, sub.col % s] = sub.data
        w, v = np.linalg.eigh(blocks)  # (k, s), (k, s, s): v[c, :, j] is eigenvector j
        vals.append(w.ravel())
        comp.append(np.repeat(comps, s))
        # column index of pair (c, j) = col0 + c*s + j; row = nodes[c, i]; value v[c, i, j]
        cc, ii, jj = np.meshgrid(np.arange(k), np.arange(s), np.arange(s), indexing="ij")
        rows.append(nodes[cc, ii].ravel())
        cols.append((col0 + cc * s + jj).ravel())
        data.append(v.ravel())
        col0 += k * s
    values = np.concatenate(vals)
    vectors = sp.csc_matrix((np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    return ComponentEig(values, vectors, np.concatenate(comp), labels)


def select_eigvecs(eig: ComponentEig, d: int, which: str = "LA"):
    """Indices of d eigenpairs: "LA" largest, "SA" smallest, "LM" largest magnitude (stable ties)."""
    key = {"LA": -eig.values, "SA": eig.values, "LM": -np.abs(eig.values)}[which]
    # Round away eigensolver noise so that exactly degenerate eigenvalues tie deterministically.
    return np.argsort(np.round(key, 10), kind="stable")[:d]


# -- rounding and output --------------------------------------------------------------------------
def _normalise_rows(u):
    if sp.issparse(u):
        u = sp.csr_matrix(u)
        norm = np.sqrt(np.asarray(u.multiply(u).sum(axis=1)).ravel())
        inv = np.where(norm > 1e-12, 1.0 / np.maximum(norm, 1e-300), 0.0)
        return sp.diags(inv) @ u
    u = np.asarray(u, dtype=np.float64)
    norm = np.linalg.norm(u, axis=1, keepdims=True)
    return np.where(norm > 1e-12, u / np.maximum(norm, 1e-300), 0.0)


def zhou_rounding(embedding, view_offsets: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """Rounding of an embedding to cycle-consistent tracks, as in Zhou et al.'s multi-way matching code.

    Rows are L2-normalised (zero rows never match). Keypoints are visited in order; an unassigned
    keypoint starts a new track and, in every *later* view, takes the unassigned keypoint of highest
    correlation with itself if that correlation exceeds ``threshold``.

    Args:
        embedding: (N, d) ndarray or scipy.sparse matrix.
        view_offsets: (V+1,).
    Returns:
        (N,) int64 track ids (singletons -1), cycle-consistent by construction.
    """
    u = _normalise_rows(embedding)
    sparse = sp.issparse(u)
    offs = np.asarray(view_offsets, np.int64)
    n, V = int(offs[-1]), len(offs) - 1
    flag = np.zeros(n, bool)
    track = np.full(n, -1, np.int64)
    t = 0
    for a in range(V):
        lo, hi = offs[a], offs[a + 1]
        if hi == lo:
            continue
        ua = u[lo:hi]
        rest = u[hi:]
        corr = ua @ rest.T  # (m_a, N - hi) correlations with all later views
        corr = corr.toarray() if sparse else np.asarray(corr)
        later = [(offs[b] - hi, offs[b + 1] - hi, offs[b]) for b in range(a + 1, V) if offs[b + 1] > offs[b]]
        for i in range(hi - lo):
            if flag[lo + i]:
                continue
            track[lo + i] = t
            flag[lo + i] = True
            row = corr[i]
            for s, e, gofs in later:
                cc = np.where(flag[gofs:gofs + (e - s)], -np.inf, row[s:e])
                j = int(np.argmax(cc))
                if cc[j] > threshold:
                    track[gofs + j] = t
                    flag[gofs + j] = True
            t += 1
    return relabel_tracks(track)


def sparse_soft_matches(scores: sp.spmatrix, view_offsets: np.ndarray, floor: float = 0.01) -> SoftMatches:
    """Cross-view entries above ``floor`` of a symmetric sparse (N, N) score matrix (upper triangle)."""
    s = sp.coo_matrix(scores)
    view = view_index_of(np.asarray(view_offsets, np.int64))
    keep = (s.row < s.col) & (view[s.row] != view[s.col]) & (s.data > floor)
    r, c, v = s.row[keep].astype(np.int64), s.col[keep].astype(np.int64), s.data[keep]
    order = np.lexsort((c, r))
    return SoftMatches(r[order], c[order], np.clip(v[order], 0.0, 1.0))


def repair_tracks(n: int, view_index: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                  scores: np.ndarray) -> np.ndarray:
    """Tracks from a non-cycle-consistent set of kept pairs, the way the reference repaired outputs.

    Tracks are the connected components of the kept pairs; where a component holds several
    keypoints of one view, the keypoint with the highest summed score to the component (its
    summed kept-pair score) stays and the others become unmatched.

    Args:
        n: N. view_index: (N,). rows, cols, scores: (M,) kept pairs (any order, no duplicates).
    Returns:
        (N,) int64 track ids, at most one keypoint per view per track.
    """
    rows = np.asarray(rows, np.int64)
    cols = np.asarray(cols, np.int64)
    scores = np.asarray(scores, np.float64)
    g = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))
    _, comp = connected_components(g, directed=False)
    strength = np.bincount(rows, scores, minlength=n) + np.bincount(cols, scores, minlength=n)
    degree = np.bincount(rows, minlength=n) + np.bincount(cols, minlength=n)
    comp = np.where(degree > 0, comp, -1)
    view_index = np.asarray(view_index, np.int64)
    idx = np.flatnonzero(comp >= 0)
    order = idx[np.lexsort((idx, -strength[idx], view_index[idx], comp[idx]))]
    key_c, key_v = comp[order], view_index[order]
    first = np.r_[True, (key_c[1:] != key_c[:-1]) | (key_v[1:] != key_v[:-1])]
    track = comp.copy()
    track[order[~first]] = -1
    return relabel_tracks(track)
