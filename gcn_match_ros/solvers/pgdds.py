"""PGDDS (Leonardos, Zhou & Daniilidis, ICRA 2017): projected gradient descent onto doubly-stochastic matrices.

Every view i holds a soft assignment X_i (m_i × K) of its keypoints to K universe points, with
rows summing to 1 and columns to at most 1 (the convex hull of partial permutations). The
synchronisation objective, with W the cross-view input (zero diagonal and within-view blocks),

    f(X) = (1 − γ)/4 ‖X Xᵀ − W‖²  +  γ/4 Σ_i ‖X_i X_iᵀ − I‖²,

is decreased by projected gradient steps

    X ← Proj(X − s ∇f),   ∇f = (1 − γ)(X (XᵀX) − W X) + γ (X_i X_iᵀ X_i − X_i)_i,
    s = 0.99 · 2 / (2γ + 3(1 − γ)(V − 1)),

from a random row-stochastic start, γ = 0.5. Each view's projection onto
{X_i >= 0, X_i 1 = 1, X_iᵀ 1 <= 1} is computed by an inner ADMM (affine step in closed form,
then clipping), warm-started from the previous outer iteration.

Outputs: soft scores X Xᵀ (per view pair, top entries of each row and column); tracks by a
per-view Hungarian assignment of the keypoints to universe points (``rounding="hungarian"``,
assignments weaker than ``threshold`` dropped) or by the shared greedy merging of X Xᵀ
(``rounding="greedy"``). K is estimated from the spectrum by default.

Memory and time grow with N × K (dense): problems above ``max_nodes`` keypoints are refused.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..graph import CorrespondenceGraph
from ..problem import Problem
from ..similarity import DescriptorSimilarity
from ..rounding import relabel_tracks
from ._sync import check_inputs, check_node_limit, parse_universe, resolve_universe_size
from .base import SoftMatches, Solver, SolverConfig
from .registry import register

__all__ = ["pgdds", "pgdds_assignment", "PGDDSConfig", "PGDDSSolver"]

_ROUNDING = ("hungarian", "greedy")


class _PartialDSProjection:
    """Projection of an m×K matrix (m <= K) onto {X >= 0, X 1 = 1, Xᵀ 1 <= 1} by ADMM.

    Splits (X, s) — affine constraints X1 = 1, Xᵀ1 + s = 1, solved in closed form — from
    (Z, t) >= 0 (ρ = 1). The state (Z, t and the scaled duals U, w) persists between calls:
    consecutive inputs of a gradient method are close, so a warm start needs few iterations.
    Stops when the primal and dual residual norms are below ``tol`` × sqrt(m K).
    """

    def __init__(self, m: int, k: int, rho: float = 1.0, tol: float = 1e-4, max_iter: int = 200):
        f32 = np.float32
        self.m, self.k, self.rho, self.tol, self.max_iter = m, k, rho, tol, max_iter
        self.z = np.full((m, k), 1.0 / k, f32)
        self.u = np.zeros((m, k), f32)
        self.t = np.full(k, 1.0 - m / k, f32)
        self.w = np.zeros(k, f32)
        self.iterations = 0

    def __call__(self, y: np.ndarray) -> np.ndarray:
        m, k, rho = self.m, self.k, self.rho
        c1 = 1.0 + rho
        bound = self.tol * np.sqrt(m * k)
        for _ in range(self.max_iter):
            self.iterations += 1
            b = y + rho * (self.z - self.u)
            tw = self.t - self.w
            sum_kappa = rho * (float(tw.sum()) - k + m)
            sum_lam = (float(b.sum()) - m * c1 - m * sum_kappa) / k
            kappa = (b.sum(axis=0) / c1 + tw - 1.0 - sum_lam / c1) / (m / c1 + 1.0 / rho)
            lam = (b.sum(axis=1) - c1 - sum_kappa) / k
            b -= lam[:, None]
            b -= kappa[None, :]
            b /= c1                                       # b is now the affine step X
            s = tw - kappa / rho
            z_old, t_old = self.z, self.t
            self.z = np.maximum(b + self.u, 0.0)
            self.t = np.maximum(s + self.w, 0.0)
            self.u += b - self.z
            self.w += s - self.t
            prim = np.linalg.norm(b - self.z) + np.linalg.norm(s - self.t)
            dual = rho * (np.linalg.norm(self.z - z_old) + np.linalg.norm(self.t - t_old))
            if prim < bound and dual < bound:
                break
        out = self.z
        return out / np.maximum(out.sum(axis=1, keepdims=True), 1e-12)


def pgdds_assignment(adjacency, view_offsets, universe_size="est", gamma: float = 0.5, iters: int = 100,
                     seed: int = 0, max_nodes: int = 6000, restarts: int = 0,
                     perturbation: float = 0.01) -> np.ndarray:
    """Run PGDDS; return the soft assignment X (N, K) (rows sum to 1 per keypoint).

    Args:
        adjacency: (N, N) scipy.sparse matrix or ndarray W of pairwise match scores in [0, 1]
            (diagonal and within-view blocks ignored).
        view_offsets: (V+1,) keypoints of view v are ``view_offsets[v]:view_offsets[v+1]``.
        universe_size: K, or ``"est"`` (spectral estimate); raised to the largest view if smaller.
        gamma: weight of the per-view orthogonality term (0.5).
        iters: projected gradient iterations; seed: seed of the random start.
        max_nodes: refuse N above this.
        restarts: extra runs of ``iters`` iterations, each from the previous result perturbed by
            ``perturbation`` × N(0, 1) and projected (the original's escape from stationary points).
    """
    w_sp, offs = check_inputs(adjacency, view_offsets, method="pgdds")
    n = w_sp.shape[0]
    check_node_limit(n, max_nodes, method="pgdds")
    if not 0.0 <= gamma <= 1.0 or iters < 0:
        raise ValueError(f"pgdds: need 0 <= gamma <= 1 and iters >= 0, got gamma={gamma}, iters={iters}")
    sizes = np.diff(offs)
    if n == 0:
        return np.zeros((0, 0), np.float32)
    k = resolve_universe_size(universe_size, w_sp, offs, method="pgdds")
    k = max(k, int(sizes.max()))
    V = len(sizes)
    f32 = np.float32
    w = w_sp.astype(f32)
    x = np.random.default_rng(int(seed)).random((n, k), dtype=f32)
    x /= x.sum(axis=1, keepdims=True)
    views = [(int(offs[i]), int(offs[i + 1])) for i in range(V) if offs[i + 1] > offs[i]]
    proj = {lo: _PartialDSProjection(hi - lo, k) for lo, hi in views}
    dmax = max(V - 1, 1)
    step = f32(0.99 * 2.0 / (2.0 * gamma + 3.0 * (1.0 - gamma) * dmax))
    g1, g0 = f32(1.0 - gamma), f32(gamma)
    rng = np.random.default_rng(int(seed) + 1)
    for run in range(int(restarts) + 1):
        if run:  # the original's escape from stationary points: perturb, project, descend again
            x = x + f32(perturbation) * rng.standard_normal(x.shape, dtype=f32)
            for lo, hi in views:
                x[lo:hi] = proj[lo](x[lo:hi])
        for _ in range(int(iters)):
            gram = x.T @ x                                            # (K, K) = Σ_j X_jᵀ X_j
            grad = g1 * (x @ gram - w @ x)
            if gamma > 0:
                for lo, hi in views:
                    xi = x[lo:hi]
                    grad[lo:hi] += g0 * (xi @ (xi.T @ xi) - xi)
            x = x - step * grad
            for lo, hi in views:
                x[lo:hi] = proj[lo](x[lo:hi])
    return x


def _hungarian_tracks(x: np.ndarray, offs: np.ndarray, threshold: float) -> np.ndarray:
    """Per view, assign keypoints to distinct universe points maximising Σ X; keep values >= threshold."""
    n = x.shape[0]
    label = np.full(n, -1, np.int64)
    for v in range(len(offs) - 1):
        lo, hi = int(offs[v]), int(offs[v + 1])
        if hi == lo:
            continue
        r, c = linear_sum_assignment(-x[lo:hi])
        ok = x[lo:hi][r, c] >= threshold
        label[lo + r[ok]] = c[ok]
    return relabel_tracks(label)


def pgdds(adjacency, view_offsets, universe_size="est", gamma: float = 0.5, iters: int = 100,
          threshold: float = 0.5, seed: int = 0, max_nodes: int = 6000, restarts: int = 0) -> np.ndarray:
    """PGDDS rounded to tracks by a per-view Hungarian assignment (see :func:`pgdds_assignment`).

    Args:
        threshold: an assignment keypoint → universe point is kept only if X is at least this.

    Returns:
        (N,) int64 track ids, at most one keypoint per view per track (-1: unmatched).
    """
    if not 0.0 <= threshold <= 1.0:
        raise ValueError(f"pgdds: 'threshold' must be in [0, 1], got {threshold}")
    x = pgdds_assignment(adjacency, view_offsets, universe_size, gamma, iters, seed, max_nodes, restarts)
    return _hungarian_tracks(x, np.asarray(view_offsets, np.int64), threshold)


@dataclasses.dataclass
class PGDDSConfig(SolverConfig):
    """Settings of :class:`PGDDSSolver`.

    Attributes:
        graph: input graph W (binary mutual-NN with Lowe's ratio by default).
        threshold: minimum X of a kept assignment (hungarian) or score of a merged pair (greedy).
        universe: ``"est"`` (spectral estimate) or K.
        gamma: weight of the per-view term (0.5). iters: gradient iterations (100: the step
            size shrinks with the number of views, and on the sparse ratio-test graphs of the
            6-view Oxford problems 50 iterations leave X diffuse, recall 0.05).
        rounding: ``"hungarian"`` or ``"greedy"``.
        seed: seed of the random start. max_nodes: refuse problems with more keypoints.
        restarts, perturbation: see :func:`pgdds_assignment` (0 restarts by default).
    """

    graph: str = "ratio0.8"
    threshold: float = 0.5
    universe: str = "est"
    gamma: float = 0.5
    iters: int = 100
    rounding: str = "hungarian"
    seed: int = 0
    max_nodes: int = 6000
    restarts: int = 0
    perturbation: float = 0.01

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.rounding not in _ROUNDING:
            raise ValueError(f"rounding must be one of {_ROUNDING}, got {self.rounding!r}")
        if not 0.0 <= self.gamma <= 1.0 or self.iters < 0 or self.max_nodes < 1 or self.restarts < 0:
            raise ValueError("need 0 <= gamma <= 1, iters >= 0, max_nodes >= 1, restarts >= 0")
        parse_universe(self.universe, method="pgdds")


@register
class PGDDSSolver(Solver):
    """Leonardos et al. 2017 projected gradient descent on partial doubly-stochastic assignments."""

    name = "pgdds"
    Config = PGDDSConfig

    def match(self, problem: Problem, graph: CorrespondenceGraph, similarity: DescriptorSimilarity):
        cfg = self.config
        offs = graph.view_offsets
        x = pgdds_assignment(graph.adjacency(), offs, cfg.universe, cfg.gamma, cfg.iters, cfg.seed,
                             cfg.max_nodes, cfg.restarts, cfg.perturbation)
        soft = SoftMatches.from_embedding(x, offs)
        if cfg.rounding == "hungarian":
            return soft, _hungarian_tracks(x, offs, cfg.threshold)
        return soft, None
