"""MatchALS (Zhou, Zhu & Daniilidis, ICCV 2015): multi-image matching via fast alternating minimisation.

The cycle-consistent answer X (N×N, X_ij = 1 when keypoints i and j image the same point) is
low-rank and lies in C = {X: X_ii = 1, within-view blocks 0, 0 <= X <= 1}. MatchALS solves

    min_X  −⟨W, X⟩ + α ‖X‖_* + β ‖X‖_1   s.t.  X ∈ C

with the nuclear norm replaced by its factored form (‖A‖² + ‖B‖²)/2, X = A Bᵀ (A, B: N×r, r a
bound on the universe size), by ADMM on the split X = Z, Z ∈ C:

    X ← Z − (Y − W + β)/μ;  B ← argmin,  A ← argmin (ridge regressions, weight α/μ);  X ← A Bᵀ
    Z ← Proj_C(X + Y/μ);    Y ← Y + μ (X − Z);   μ doubled / halved to balance the residuals.

Defaults follow the reference run of the authors' code: α = 50, β = 0.1, r = 2 × the largest
view, 50 iterations, μ₀ = 64, random uniform initial A (seeded).

Outputs: the continuous X (symmetrised, clamped to [0, 1]) as soft scores; tracks either by
Zhou's rounding of the factor A (``rounding="zhou"``, as the authors' code) or by the shared
greedy merging of X above 0.5 (``rounding="greedy"``, the thresholded output made consistent).

X, Z, Y are dense N×N (float32): the method refuses problems with more than ``max_nodes``
keypoints.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from ..graph import CorrespondenceGraph
from ..problem import Problem
from ..similarity import DescriptorSimilarity
from ..rounding import greedy_tracks
from ._sync import check_inputs, check_node_limit, parse_universe, repair_tracks, zhou_rounding
from .base import SoftMatches, Solver, SolverConfig
from .registry import register

__all__ = ["matchals", "matchals_factor", "MatchALSConfig", "MatchALSSolver"]

_ROUNDING = ("zhou", "greedy", "repair")


def matchals_factor(adjacency, view_offsets, universe_size="2maxv", alpha: float = 50.0, beta: float = 0.1,
                    iters: int = 50, tol: float = 5e-4, mu: float = 64.0, seed: int = 0,
                    max_nodes: int = 6000):
    """Run MatchALS; return the continuous X and the factor A.

    Args:
        adjacency: (N, N) scipy.sparse matrix or ndarray W of pairwise match scores in [0, 1]
            (diagonal and within-view blocks ignored).
        view_offsets: (V+1,) keypoints of view v are ``view_offsets[v]:view_offsets[v+1]``.
        universe_size: rank bound r: an integer, or ``"2maxv"`` (2 × the largest view, the default
            of the reference run) / ``"4maxv"`` (the authors' code default).
        alpha, beta: weights of the nuclear and l1 norms.
        iters: maximum number of ADMM iterations; tol: stop when both residuals are below it.
        mu: initial ADMM penalty; seed: seed of the random initial factor.
        max_nodes: refuse N above this (X, Z, Y are dense N×N).

    Returns:
        (X, A): X (N, N) float32 ndarray, symmetrised (unclamped); A (N, r) float32 ndarray.
    """
    w_sp, offs = check_inputs(adjacency, view_offsets, method="matchals")
    n = w_sp.shape[0]
    check_node_limit(n, max_nodes, method="matchals")
    if alpha <= 0 or beta < 0 or iters < 1 or mu <= 0:
        raise ValueError(f"matchals: need alpha > 0, beta >= 0, iters >= 1, mu > 0; got alpha={alpha}, "
                         f"beta={beta}, iters={iters}, mu={mu}")
    sizes = np.diff(offs)
    if isinstance(universe_size, str) and universe_size.strip().lower().endswith("maxv"):
        factor = universe_size.strip().lower()[:-4]
        try:
            r = float(factor or 1) * (int(sizes.max()) if n else 0)
        except ValueError:
            raise ValueError(f"matchals: universe size must be an integer or '<k>maxv', got {universe_size!r}") from None
    else:
        r = parse_universe(universe_size, method="matchals")
        if r is None:
            raise ValueError("matchals: needs a rank bound (an integer or '2maxv'), not an estimate")
    r = int(min(n, max(1, math.ceil(r)))) if n else 0
    if n == 0:
        return np.zeros((0, 0), np.float32), np.zeros((0, 0), np.float32)

    # numpy float32 throughout: BLAS for the products; plain numpy for the element-wise steps,
    # which stay fast when the cores are shared (torch's intra-op threads do not).
    f32 = np.float32
    w = w_sp.toarray().astype(f32)
    view = np.repeat(np.arange(len(offs) - 1), sizes)
    cross = view[:, None] != view[None, :]          # entries Z may hold (diagonal set to 1 below)
    diag = np.arange(n)
    x = w.copy()
    z = w.copy()
    y = np.zeros((n, n), f32)
    a = np.random.default_rng(int(seed)).random((n, r), dtype=f32)
    eye_r = np.eye(r, dtype=f32)
    mu = float(mu)
    for _ in range(int(iters)):
        x0 = x
        x = z - (y - w + f32(beta)) / f32(mu)
        reg = f32(alpha / mu) * eye_r
        # Ridge regressions; the r×r systems are symmetric positive definite (Cholesky).
        b = cho_solve(cho_factor(a.T @ a + reg, check_finite=False), a.T @ x, check_finite=False).T
        a = cho_solve(cho_factor(b.T @ b + reg, check_finite=False), b.T @ x.T, check_finite=False).T
        x = a @ b.T
        z = x + y / f32(mu)
        z *= cross
        z[diag, diag] = 1.0
        np.clip(z, 0.0, 1.0, out=z)
        y += f32(mu) * (x - z)
        p_res = float(np.linalg.norm(x - z)) / n
        d_res = mu * float(np.linalg.norm(x - x0)) / n
        if p_res < tol and d_res < tol:
            break
        if p_res > 10 * d_res:
            mu *= 2.0
        elif d_res > 10 * p_res:
            mu /= 2.0
    x = (x + x.T) / 2
    return x.astype(f32, copy=False), a.astype(f32, copy=False)


def _soft_from_dense(x: np.ndarray, offs: np.ndarray, floor: float = 0.01) -> SoftMatches:
    return SoftMatches.from_dense(np.clip(x, 0.0, 1.0), offs, floor=floor)


def matchals(adjacency, view_offsets, universe_size="2maxv", alpha: float = 50.0, beta: float = 0.1,
             iters: int = 50, rounding: str = "zhou", threshold: float = 0.5, seed: int = 0,
             max_nodes: int = 6000) -> np.ndarray:
    """MatchALS rounded to cycle-consistent tracks (see :func:`matchals_factor` for the arguments).

    Args:
        rounding: ``"zhou"`` (Zhou's rounding of the factor A at ``threshold``), ``"greedy"``
            (greedy conflict-free merging of the pairs with X >= ``threshold``) or ``"repair"``
            (connected components of X > ``threshold``, keeping per view the keypoint with the
            highest summed X: the protocol of the reference's ``raw>0.5`` row).

    Returns:
        (N,) int64 track ids (-1: unmatched).
    """
    if rounding not in _ROUNDING:
        raise ValueError(f"matchals: 'rounding' must be one of {_ROUNDING}, got {rounding!r}")
    x, a = matchals_factor(adjacency, view_offsets, universe_size, alpha, beta, iters, seed=seed,
                           max_nodes=max_nodes)
    offs = np.asarray(view_offsets, np.int64)
    if rounding == "zhou":
        return zhou_rounding(a, offs, threshold)
    soft = _soft_from_dense(x, offs)
    view = np.repeat(np.arange(len(offs) - 1), np.diff(offs))
    if rounding == "repair":
        keep = soft.scores > threshold
        return repair_tracks(x.shape[0], view, soft.rows[keep], soft.cols[keep], soft.scores[keep])
    return greedy_tracks(x.shape[0], view, soft.rows, soft.cols, soft.scores, threshold)


@dataclasses.dataclass
class MatchALSConfig(SolverConfig):
    """Settings of :class:`MatchALSSolver`.

    Attributes:
        graph: input graph W (the reference ran the original on the binary mutual-NN graph).
        threshold: rounding threshold (Zhou's correlation threshold, or X for greedy): 0.5.
        universe: rank bound r: ``"2maxv"`` (2 × largest view), ``"4maxv"`` or an integer.
        alpha, beta: nuclear / l1 weights (50, 0.1). iters: ADMM iterations (50). tol: 5e-4.
        rounding: ``"zhou"``, ``"greedy"`` or ``"repair"`` (see :func:`matchals`).
        seed: seed of the random initial factor.
        max_nodes: refuse problems with more keypoints (dense N×N matrices).
    """

    graph: str = "mutual"
    threshold: float = 0.5
    universe: str = "2maxv"
    alpha: float = 50.0
    beta: float = 0.1
    iters: int = 50
    tol: float = 5e-4
    rounding: str = "zhou"
    seed: int = 0
    max_nodes: int = 6000

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.rounding not in _ROUNDING:
            raise ValueError(f"rounding must be one of {_ROUNDING}, got {self.rounding!r}")
        if self.iters < 1 or self.alpha <= 0 or self.beta < 0 or self.max_nodes < 1:
            raise ValueError("need iters >= 1, alpha > 0, beta >= 0, max_nodes >= 1")


@register
class MatchALSSolver(Solver):
    """Zhou et al. 2015 MatchALS; continuous X as soft scores, tracks by Zhou's or the greedy rounding."""

    name = "matchals"
    Config = MatchALSConfig

    def match(self, problem: Problem, graph: CorrespondenceGraph, similarity: DescriptorSimilarity):
        cfg = self.config
        offs = graph.view_offsets
        x, a = matchals_factor(graph.adjacency(), offs, cfg.universe, cfg.alpha, cfg.beta, cfg.iters,
                               cfg.tol, seed=cfg.seed, max_nodes=cfg.max_nodes)
        soft = _soft_from_dense(x, offs)
        if cfg.rounding == "zhou":
            return soft, zhou_rounding(a, offs, cfg.threshold)
        if cfg.rounding == "repair":
            keep = soft.scores > cfg.threshold
            return soft, repair_tracks(graph.n_nodes, graph.view_index, soft.rows[keep], soft.cols[keep],
                                       soft.scores[keep])
        return soft, None  # shared greedy rounding at cfg.threshold
