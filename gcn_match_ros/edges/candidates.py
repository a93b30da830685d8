"""Candidate edges and their features for the learned edge scorer (no poses, no labels).

For every pair of views (i, j) the candidates are

- each keypoint's top-``k`` descriptor neighbours in the other view (both directions), and
- optionally geometry-guided candidates: a pose-free two-view model (homography and
  fundamental or, with known intrinsics, essential matrix, OpenCV USAC,
  :mod:`.verify`) is fitted on the confident pairs (mutual nearest neighbours passing
  Lowe's ratio 0.8); when the model is trusted (:meth:`.verify.PairModel.trusted`) every
  keypoint also proposes the keypoint of the other view nearest to its homography transfer
  and the descriptor-best keypoint within ``guide_px`` of its epipolar line.

Per candidate edge (a, b) the features (:data:`EDGE_FEATURES`) are: descriptor cosine,
Lowe ratio from each side, rank from each side, mutual-NN flag, the confident-edge flag,
triangle support (fraction of third views k with some c such that a–c and c–b are both
candidates; and the same on the confident edges only), and the geometric residuals (in
pixels, squashed) of the edge under the trusted H or F, plus whether there is one (an
untrusted model gives no geometric credit). With ``noise_scaled_residuals`` the residuals of a
view pair whose keypoints are not localised to a fraction of a pixel are in units of its noise
(:func:`residual_unit_px`). The trusted models come back with the edges
(:attr:`EdgeSet.models`) for the checks of :mod:`.consistency`. Everything here is computed
from the problem's keypoints and descriptors (and intrinsics, when known) only, in training
and at test time alike.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from typing import Callable, Dict, List, NamedTuple, Optional, Tuple

import numba
import numpy as np
from scipy.spatial import cKDTree
import torch

from ..buckets import bucket_order, bucket_starts, sort_buckets
from ..configs import JsonConfig
from ..descriptors import NORMALIZATIONS, cosine_distance32
from ..geometry import homogeneous, transfer
from ..prefetch import prefetch_row
from ..problem import Problem
from ..similarity import DescriptorSimilarity
from ..threads import SharedTasks
from ..timing import stage
from .rig_memory import RigMemory
from .verify import (AGREE_MIN_PX, AGREE_SIGMAS, EPIPOLAR_PX, FINE_PX, MIN_INLIER_RATIO, MIN_INLIERS, MIN_SEEDS,
                     PLANAR_RATIO, PairModel, check_planar_ratio, fit_pair, matrix_residuals, may_be_trusted,
                     model_matrices)

__all__ = ["EdgeConfig", "EdgeSet", "PairCandidates", "CandidateJob", "candidate_edges", "confident_pairs",
           "residual_unit_px", "EDGE_FEATURES", "RANK_CAP"]

EDGE_FEATURES = ("cosine", "ratio_a", "ratio_b", "rank_a", "rank_b", "mutual", "confident",
                 "tri_all", "tri_conf", "res_log", "res_lin", "has_model", "planar", "guided")

RANK_CAP = 10  # descriptor ranks are features up to this value (min(rank, RANK_CAP) / RANK_CAP)


@dataclasses.dataclass(frozen=True)
class EdgeConfig(JsonConfig):
    """k: descriptor candidates per keypoint and view; geometry: fit H/F per view pair and
    add geometric features; guided: add geometry-guided candidates; guide_px: their
    tolerance; ratio: Lowe ratio of the confident seed pairs; normalization: of the
    descriptors before the cosine (:data:`gcn_match_ros.descriptors.NORMALIZATIONS`);
    min_inliers, min_inlier_ratio: when a fitted model is trusted
    (:meth:`.verify.PairModel.trusted`; 0, 0: any fitted model, the classic RANSAC
    baseline); essential: fit an essential matrix where the problem has intrinsics;
    epipolar_px: inlier threshold of the epipolar model (Sampson distance, pixels); fine_px:
    the threshold tried first, kept for sub-pixel keypoints (:func:`.verify.fit_pair`; 0: off);
    planar_ratio: a view pair is planar when H explains at least this share of what F explains
    (:func:`.verify.fit_pair`); noise_scaled_residuals: the residual features of a view pair of
    noisy keypoints are in units of their noise (:func:`residual_unit_px`)."""

    k: int = 4
    geometry: bool = True
    guided: bool = True
    guide_px: float = 3.0
    ratio: float = 0.8
    normalization: str = "rootsift"
    min_inliers: int = MIN_INLIERS
    min_inlier_ratio: float = MIN_INLIER_RATIO
    essential: bool = True
    epipolar_px: float = EPIPOLAR_PX
    fine_px: float = FINE_PX
    planar_ratio: float = PLANAR_RATIO
    noise_scaled_residuals: bool = False

    def __post_init__(self) -> None:
        if self.normalization not in NORMALIZATIONS:
            raise ValueError(f"EdgeConfig.normalization must be one of {NORMALIZATIONS}, got {self.normalization!r}")
        check_planar_ratio(self.planar_ratio, "EdgeConfig.planar_ratio")

    def fit(self, xa: np.ndarray, xb: np.ndarray, K_a: Optional[np.ndarray] = None,
            K_b: Optional[np.ndarray] = None) -> Optional[PairModel]:
        """The two-view model of seed pairs xa[i] <-> xb[i] at these thresholds, trusted or not
        (:func:`.verify.fit_pair`; an essential matrix when ``essential`` and both intrinsics
        K_a, K_b are given).

        Shapes: xa, xb (S, 2) pixels; K_a, K_b (3, 3).
        """
        if not self.essential:
            K_a = K_b = None
        return fit_pair(xa, xb, K_a=K_a, K_b=K_b, epipolar_px=self.epipolar_px, fine_px=self.fine_px,
                        planar_ratio=self.planar_ratio)

    def fitted_coarse(self, model: Optional[PairModel]) -> bool:
        """Whether ``model`` is an epipolar model fitted at ``epipolar_px``: its seeds showed no
        sub-pixel localisation (:func:`.verify.fit_pair`), so its agreement tolerance is clipped
        to that threshold rather than measured below it."""
        return model is not None and not model.planar and model.epipolar_fit_px >= self.epipolar_px

    def may_fit(self, xa: np.ndarray, xb: np.ndarray) -> bool:
        """Whether :meth:`fit` of these seed pairs could give a model these settings trust: the
        cheap probe of a camera pair that failed before (:func:`.verify.may_be_trusted`).

        Shapes: xa, xb (S, 2) pixels.
        """
        return may_be_trusted(xa, xb, epipolar_px=self.epipolar_px, min_inliers=self.min_inliers,
                              min_inlier_ratio=self.min_inlier_ratio)

    def trusted(self, model: Optional[PairModel]) -> Optional[PairModel]:
        """``model`` with its selected H or F only when these settings trust its support
        (:meth:`.verify.PairModel.trusted`), else None."""
        if model is None or not model.trusted(self.min_inliers, self.min_inlier_ratio):
            return None
        return model.selected()


ViewPair = Tuple[int, int]


@dataclasses.dataclass
class EdgeSet:
    """Undirected candidate edges rows < cols (global indices) and their (M, F) features.

    ``res_px`` (M,) is the residual in pixels under the view pair's trusted model (inf without
    one). ``models``: every view pair (i, j), i < j, whose views were compared -> its trusted
    model (:meth:`.verify.PairModel.selected`), or None when it has none."""

    rows: np.ndarray
    cols: np.ndarray
    features: np.ndarray
    res_px: np.ndarray
    confident: np.ndarray
    models: Dict[ViewPair, Optional[PairModel]] = dataclasses.field(default_factory=dict)

    def subset(self, keep: np.ndarray) -> "EdgeSet":
        """The edges where ``keep`` (M,) bool is True, with the same models."""
        at = np.flatnonzero(keep)  # then take: 0.06 ms for 20 k edges, boolean indexing 0.5 ms
        return EdgeSet(self.rows.take(at), self.cols.take(at), self.features.take(at, axis=0), self.res_px.take(at),
                       self.confident.take(at), self.models)


def residual_unit_px(model: Optional[PairModel], config: EdgeConfig) -> float:
    """Pixels per unit of a view pair's residual features (``res_log``, ``res_lin``): 1, or with
    ``config.noise_scaled_residuals`` and an epipolar ``model`` of noisy keypoints — fitted coarse
    (:meth:`EdgeConfig.fitted_coarse`: its seeds showed no sub-pixel localisation) and measured
    noise sigma above ``config.fine_px`` (:attr:`.verify.PairModel.noise_px` is three sigma) —
    that noise estimate over :data:`.verify.AGREE_MIN_PX`.

    Why: the edge head learns its residual scale where three sigma of the keypoint noise is about
    1 px (SIFT on real images) and scores a true pair the lower the farther it lies from the
    fitted line; with keypoints of 1 px noise (the generated scenes) it refuses true pairs 2-3 px
    off. In units of the pair's own noise they look as sub-pixel keypoints' true pairs do. The few
    real SIFT view pairs fitted at ``epipolar_px`` measure sigma 0.3-0.7 px (median 0.4) and
    mostly keep pixels.
    """
    # noise_px is 0 without F, so the noise test also keeps pixels for a model without one
    if (not config.noise_scaled_residuals or not config.fitted_coarse(model)
            or model.noise_px <= AGREE_SIGMAS * config.fine_px):
        return 1.0
    return max(AGREE_MIN_PX, model.noise_px) / AGREE_MIN_PX


def _squash(d: np.ndarray) -> np.ndarray:
    return np.log1p(np.minimum(d, 1e3)) / np.log1p(1e3)


@dataclasses.dataclass
class PairCandidates:
    """The candidate edges of one view pair (a, b), local indices, and their per-pair features.

    Shapes (M,): ea, eb int64 indices into views a and b; cosine; ratio_a, ratio_b (Lowe ratio
    from each side, capped at 1.5); rank_a, rank_b (capped at :data:`RANK_CAP`); mutual,
    confident, guided bool; res_h, res_f pixel residuals under the pair's H and F (inf without).
    model_kind: 0 no two-view model, 1 fundamental matrix, 2 homography (planar).
    """

    ea: np.ndarray
    eb: np.ndarray
    cosine: np.ndarray
    ratio_a: np.ndarray
    ratio_b: np.ndarray
    rank_a: np.ndarray
    rank_b: np.ndarray
    mutual: np.ndarray
    confident: np.ndarray
    res_h: np.ndarray
    res_f: np.ndarray
    model_kind: float
    guided: np.ndarray


def candidate_edges(problem: Problem, config: EdgeConfig = EdgeConfig(),
                    similarity: Optional[DescriptorSimilarity] = None, rig: Optional[RigMemory] = None) -> EdgeSet:
    """Candidate edges of ``problem`` with their features (see the module docstring).

    ``similarity``: the window's shared descriptor similarity (made here if None); ``rig``: the
    stream's two-view models by camera pair (:mod:`.rig_memory`), used when the problem names
    its cameras.
    """
    return CandidateJob(problem, config, similarity, rig).result()


class CandidateJob:
    """The candidate edges of one window, computed view pair by view pair by whichever threads
    take part (:class:`gcn_match_ros.threads.SharedTasks`): :meth:`help` takes pairs until none
    is left, :meth:`result` helps, waits for the pairs other threads took and puts the edges
    together. The ``gcn`` solver's second thread asks for the result while its first, once its
    network is done, helps instead of idling (a 10 x 1000 window alone: ~1.2 s of pair fits
    after the network, now shared). Each pair's candidates depend on that pair alone, so the
    edges are the same whoever computed them.

    Pairs are taken from the last one back: the graph, built meanwhile on the solver's first
    thread, computes the shared best lists (:meth:`DescriptorSimilarity.most_similar`) from the
    first, so each thread makes some of them instead of one waiting for the other's (a 4 x 500
    stream solve 1.4 ms faster, window by window: benchmarks/results/stage_breakdown.md).

    Args: as :func:`candidate_edges`, and
        keep: the candidates the caller will read, ``keep((i, j), model, part) -> (M_ij,) bool``
            for each view pair's candidates (:class:`PairCandidates`, local indices) and trusted
            model (None without one), asked on the thread that found them: the result holds only
            those, and only they get features (the triangle support, the dearest, still counts
            through every candidate). None: every candidate. Asked per view pair rather than
            once for the window: the assembly of the window's edges, which runs beside the
            solver's network and holds the GIL, is then that much shorter (an 8 x 500 stream
            window 1.75 ms sooner window by window, 0.8-2.8 ms in three pairs of alternating
            processes; 4 x 500 0.23 ms window by window).

    Attributes:
        candidates: how many candidates there were before ``keep``, once :meth:`result` is done.
    """

    def __init__(self, problem: Problem, config: EdgeConfig = EdgeConfig(),
                 similarity: Optional[DescriptorSimilarity] = None, rig: Optional[RigMemory] = None,
                 keep: Optional[Callable[[ViewPair, Optional[PairModel], PairCandidates], np.ndarray]] = None
                 ) -> None:
        self._problem, self._config, self._rig, self._keep = problem, config, rig, keep
        self.candidates = 0
        self._similarity = similarity if similarity is not None else DescriptorSimilarity(problem)
        self._kp = problem.keypoints.astype(np.float64)
        offs = problem.view_offsets
        self._pairs = [(i, j) for i in range(problem.n_views) for j in range(i + 1, problem.n_views)
                       if offs[i + 1] - offs[i] >= 2 and offs[j + 1] - offs[j] >= 2]
        self._tasks = SharedTasks([functools.partial(self._pair, i, j) for i, j in self._pairs],
                                  order=range(len(self._pairs) - 1, -1, -1))

    def help(self) -> None:
        """Compute view pairs not yet taken, on this thread, until none is left."""
        self._tasks.help()

    def result(self) -> EdgeSet:
        """The window's :class:`EdgeSet` (a pair's error re-raised), helping meanwhile."""
        return self._edges(self._tasks.results())

    def _pair(self, i: int, j: int) -> "_PairBlock":
        problem, offs = self._problem, self._problem.view_offsets
        a0, a1, b0, b1 = int(offs[i]), int(offs[i + 1]), int(offs[j]), int(offs[j + 1])
        intrinsics = (problem.K[i], problem.K[j]) if problem.K is not None else (None, None)
        use_rig = self._rig is not None and problem.camera_ids is not None
        cameras = (problem.camera_ids[i], problem.camera_ids[j]) if use_rig else None
        norm = self._config.normalization
        sim = self._similarity.block(i, j, norm)
        # The RANK_CAP + 1 best similarities of every row and column, best first: the
        # candidates, the ratio test and the (capped) ranks all read from them.
        best = self._similarity.most_similar(i, j, norm, min(RANK_CAP + 1, sim.shape[1]),
                                             min(RANK_CAP + 1, sim.shape[0]))
        part, model = _pair_edges(sim, best, self._kp[a0:a1], self._kp[b0:b1], self._config, *intrinsics,
                                  rig=self._rig if use_rig else None, cameras=cameras)
        kept = np.ones(part.ea.shape[0], bool) if self._keep is None else self._keep((i, j), model, part)
        return _PairBlock(*_pair_block(part.ea, part.eb, part.confident, kept, a0, b0, part.cosine, part.ratio_a,
                                       part.ratio_b, part.rank_a, part.rank_b, part.mutual, part.model_kind,
                                       part.guided, part.res_h, part.res_f), model,
                          residual_unit_px(model, self._config))

    def _edges(self, done: List["_PairBlock"]) -> EdgeSet:
        """Every pair's edges (``done``, in the order of the pairs) together, with the features
        that need all pairs (triangle support) and those numpy computes from the residuals."""
        problem = self._problem
        models: Dict[ViewPair, Optional[PairModel]] = {pair: block.model for pair, block in zip(self._pairs, done)}
        self.candidates = sum(block.rows.shape[0] for block in done)
        if not self.candidates:
            z = np.zeros(0, np.int64)
            return EdgeSet(z, z.copy(), np.zeros((0, len(EDGE_FEATURES)), np.float32), np.zeros(0), np.zeros(0, bool),
                           models)

        def cat(field: str) -> np.ndarray:
            return np.concatenate([getattr(block, field) for block in done])

        rows, cols, conf_all = cat("rows"), cat("cols"), cat("confident")
        scored_rows, scored_cols, feats = cat("kept_rows"), cat("kept_cols"), cat("features")
        n, V, view = problem.n_keypoints, problem.n_views, problem.view_index
        by_row = bucket_order(scored_rows, n)[1]
        feats[:, _TRI_ALL] = _triangle_support(n, V, view, rows, cols, np.ones(rows.shape[0], bool), scored_rows,
                                               scored_cols, by_row)
        feats[:, _TRI_CONF] = _triangle_support(n, V, view, rows, cols, conf_all, scored_rows, scored_cols, by_row)
        rmin = cat("res_px")
        unit = np.repeat([block.residual_unit_px for block in done], [block.res_px.shape[0] for block in done])
        in_units = rmin / unit
        feats[:, _RES_LOG] = _squash(in_units)
        feats[:, _RES_LIN] = np.minimum(in_units, 10.0) / 10.0
        return EdgeSet(scored_rows, scored_cols, feats, rmin, feats[:, _CONFIDENT] > 0, models)


class _PairBlock(NamedTuple):
    """One view pair's share of the window's edges (:func:`_pair_block`), its trusted model and the
    unit of its residual features (:func:`residual_unit_px`)."""

    rows: np.ndarray
    cols: np.ndarray
    confident: np.ndarray
    kept_rows: np.ndarray
    kept_cols: np.ndarray
    features: np.ndarray
    res_px: np.ndarray
    model: Optional[PairModel]
    residual_unit_px: float


# The columns of EDGE_FEATURES, by name (constants in the compiled code).
(_COSINE, _RATIO_A, _RATIO_B, _RANK_A, _RANK_B, _MUTUAL, _CONFIDENT, _TRI_ALL, _TRI_CONF, _RES_LOG, _RES_LIN, _HAS_MODEL,
 _PLANAR, _GUIDED) = (EDGE_FEATURES.index(name) for name in (
     "cosine", "ratio_a", "ratio_b", "rank_a", "rank_b", "mutual", "confident", "tri_all", "tri_conf", "res_log",
     "res_lin", "has_model", "planar", "guided"))
_N_FEATURES = len(EDGE_FEATURES)


@numba.njit(cache=True, nogil=True)
def _pair_block(ea, eb, confident, kept, a0, b0, cosine, ratio_a, ratio_b, rank_a, rank_b, mutual, model_kind, guided,
                res_h, res_f):
    """One view pair's candidates as the window's edges take them, on the thread that found them:
    all of them in global indices with their confident flags (the triangle support counts through
    every one), and the ``kept`` ones with their :data:`EDGE_FEATURES` rows, the columns of this
    pair alone filled as numpy fills them (float32 of the float64 rank / RANK_CAP; of the flags),
    those of the window (triangle support) and of the residuals (:meth:`CandidateJob._edges`) left
    at 0, and their residuals (the smaller of H's and F's, :attr:`EdgeSet.res_px`). Compiled, on the
    pair's thread: the assembly's numpy passes over the window's ~10⁵ candidates, column by column (a
    dozen concatenations, takes and casts), held the GIL that the solver's network on the other
    thread waits for.

    Shapes: ea, eb (M,) int64 local indices; confident, kept, mutual, guided (M,) bool; cosine,
    ratio_a, ratio_b (M,) float32; rank_a, rank_b (M,) int64; res_h, res_f (M,) float64 -> rows,
    cols (M,) int64, confident (M,) bool, kept rows, cols (K,) int64, features (K, F) float32,
    res_px (K,) float64.
    """
    m = ea.shape[0]
    rows = ea + a0
    cols = eb + b0
    k = 0
    for e in range(m):
        k += kept[e]
    kept_rows = np.empty(k, np.int64)
    kept_cols = np.empty(k, np.int64)
    features = np.zeros((k, _N_FEATURES), np.float32)
    res_px = np.empty(k, np.float64)
    has, planar = np.float32(model_kind > 0), np.float32(model_kind == 2)
    t = 0
    for e in range(m):
        if not kept[e]:
            continue
        kept_rows[t], kept_cols[t] = rows[e], cols[e]
        row = features[t]
        row[_COSINE], row[_RATIO_A], row[_RATIO_B] = cosine[e], ratio_a[e], ratio_b[e]
        row[_RANK_A] = np.float32(np.float64(rank_a[e]) / RANK_CAP)
        row[_RANK_B] = np.float32(np.float64(rank_b[e]) / RANK_CAP)
        row[_MUTUAL], row[_CONFIDENT] = np.float32(mutual[e]), np.float32(confident[e])
        row[_HAS_MODEL], row[_PLANAR], row[_GUIDED] = has, planar, np.float32(guided[e])
        res_px[t] = np.minimum(res_h[e], res_f[e])
        t += 1
    return rows, cols, confident, kept_rows, kept_cols, features, res_px


def _pair_edges(sim_t: torch.Tensor, best: Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
                xa: np.ndarray, xb: np.ndarray, config: EdgeConfig,
                K_a: Optional[np.ndarray] = None, K_b: Optional[np.ndarray] = None,
                rig: Optional[RigMemory] = None, cameras: Optional[Tuple[str, str]] = None
                ) -> Tuple[PairCandidates, Optional[PairModel]]:
    """Candidates of one view pair (a, b), their per-pair features and the pair's trusted model
    (None without one); ``sim_t`` (n_a, n_b) cosines and ``best`` their min(RANK_CAP + 1, ...) best
    rows and columns (:meth:`gcn_match_ros.similarity.DescriptorSimilarity.most_similar`), K_a, K_b
    intrinsics (None: unknown; used as :meth:`EdgeConfig.fit` says); ``rig``: the stream's
    remembered models, consulted for ``cameras`` (both or neither)."""
    na, nb = sim_t.shape
    sim = sim_t.numpy()
    top_r, ir, top_c, ic = best
    model = None
    if config.geometry:
        seed_a, seed_b, mutual_ab = confident_pairs(top_r, ir, top_c, ic, config.ratio)
        if seed_a.shape[0] < MIN_SEEDS:
            # too few ratio-test survivors (repetitive or noisy descriptors): fit on all
            # mutual nearest neighbours instead; the robust estimator copes with the outliers
            seed_a = np.flatnonzero(mutual_ab)
            seed_b = ir[seed_a, 0]
        with stage("geometry"):
            sa, sb = xa[seed_a], xb[seed_b]

            def fit() -> Optional[PairModel]:
                return config.fit(sa, sb, K_a, K_b)

            if rig is not None:
                model = rig.model(cameras, sa, sb, fit, config.min_inliers, config.min_inlier_ratio,
                                  may_fit=lambda: config.may_fit(sa, sb))
            else:
                model = config.trusted(fit())
    ga = gb = _NONE_GUIDED
    if config.guided and model is not None:
        with stage("geometry"):
            ga, gb = _guided(sim, xa, xb, model, config.guide_px)
    H, Hi, F, has_h, has_f = model_matrices(model)
    ea, eb, guided, s, rank_a, rank_b, rat_a, rat_b, mutual, conf, rh, rf = _pair_candidates(
        sim, top_r, ir, top_c, ic, min(config.k, na, nb), ga, gb, float(config.ratio), xa, xb, H, Hi, F, has_h, has_f)
    kind = 0.0 if model is None else 2.0 if model.planar else 1.0
    return PairCandidates(ea, eb, s, rat_a, rat_b, rank_a, rank_b, mutual, conf, rh, rf, kind, guided), model


_NONE_GUIDED = np.zeros(0, np.int64)


@numba.njit(cache=True, nogil=True)
def _pair_candidates(sim, top_r, ir, top_c, ic, k, ga, gb, ratio, xa, xb, H, Hi, F, has_h, has_f):
    """One view pair's candidates and per-pair features, one compiled call after its fit: each
    keypoint's ``k`` best in the other view and the guided pairs (ga[g], gb[g]), each pair once
    (:func:`_deduplicated`), their descriptor features (:func:`_descriptor_features`) and their
    residuals under H and F where the model has them (:func:`.verify.matrix_residuals`: inf
    elsewhere). One call instead of a dozen numpy steps, which held the GIL that
    the solver's network on the other thread waits for at each of its operations.

    Shapes: sim (na, nb) float32; top_r, ir (na, K), top_c, ic (nb, K) best lists, K >= max(k, 2);
    ga, gb (G,) int64; xa (na, 2), xb (nb, 2) float64; H, Hi, F (3, 3) float64 -> ea, eb (M,) int64,
    guided (M,) bool, then the fields of :class:`PairCandidates` from cosine to res_f, in that order.
    """
    na, nb = sim.shape
    total = (na + nb) * k + ga.shape[0]
    ea = np.empty(total, np.int64)
    eb = np.empty(total, np.int64)
    guided = np.zeros(total, np.bool_)
    m = 0
    for a in range(na):
        for r in range(k):
            ea[m], eb[m] = a, ir[a, r]
            m += 1
    for b in range(nb):
        for r in range(k):
            ea[m], eb[m] = ic[b, r], b
            m += 1
    for g in range(ga.shape[0]):
        ea[m], eb[m], guided[m] = ga[g], gb[g], True
        m += 1
    ea, eb, guided = _deduplicated(ea, eb, guided, na, nb)
    cosine, rank_a, rank_b, ratio_a, ratio_b, mutual, confident = _descriptor_features(sim, top_r, top_c, ea, eb,
                                                                                       ratio)
    rh, rf = matrix_residuals(xa[ea], xb[eb], H, Hi, F, has_h, has_f)
    return ea, eb, guided, cosine, rank_a, rank_b, ratio_a, ratio_b, mutual, confident, rh, rf


@numba.njit(cache=True, nogil=True)
def _deduplicated(ea, eb, guided, na, nb):
    """Each candidate (ea[m], eb[m]) once, ordered by (ea, eb), guided if any copy is. A counting
    sort by ea, then each keypoint's few partners by eb; compiled, with the features below: the
    numpy steps (a sort of the keys, reduceat, a dozen fancy indexings) were ~0.3 ms a 500 x 500
    view pair, and held the GIL the solve's other thread needs.

    Shapes: ea, eb (M,) int64 in [0, na) and [0, nb); guided (M,) bool -> ea, eb (U,) int64,
    guided (U,) bool.
    """
    start = bucket_starts(ea, na)
    fill = start[:-1].copy()
    partner = np.empty(ea.shape[0], np.int64)
    flag = np.empty(ea.shape[0], np.bool_)
    for m in range(ea.shape[0]):
        at = fill[ea[m]]
        partner[at], flag[at] = eb[m], guided[m]
        fill[ea[m]] += 1
    out_a = np.empty(ea.shape[0], np.int64)
    out_b = np.empty(ea.shape[0], np.int64)
    out_guided = np.empty(ea.shape[0], np.bool_)
    sort_buckets(start, partner, flag)  # a keypoint has ~2 k + a few guided partners
    size = 0
    for a in range(na):
        lo, hi = start[a], start[a + 1]
        t = lo
        while t < hi:
            out_a[size], out_b[size], out_guided[size] = a, partner[t], flag[t]
            t += 1
            while t < hi and partner[t] == partner[t - 1]:
                out_guided[size] |= flag[t]
                t += 1
            size += 1
    return out_a[:size], out_b[:size], out_guided[:size]


@numba.njit(cache=True, nogil=True)
def _descriptor_features(sim, top_r, top_c, ea, eb, ratio):
    """The descriptor features of candidates (ea[m], eb[m]): cosine, rank from each side (capped
    at :data:`RANK_CAP`; exact below it), Lowe ratio from each side (cosine distance to the
    candidate over that to the best other keypoint, capped at 1.5), mutual nearest neighbours,
    confident (mutual and both ratios below ``ratio``). float32 arithmetic, as numpy does it on
    these float32 arrays (:func:`gcn_match_ros.descriptors.cosine_distance`).

    Shapes: sim (na, nb); top_r (na, K), top_c (nb, K) float32 best values of each row and
    column, K >= 2; ea, eb (M,) int64 -> cosine (M,) float32, rank_a, rank_b (M,) int64,
    ratio_a, ratio_b (M,) float32, mutual, confident (M,) bool.
    """
    n = ea.shape[0]
    cosine = np.empty(n, np.float32)
    for m in range(n):
        cosine[m] = sim[ea[m], eb[m]]
    rank_a = _ranks(top_r, ea, cosine)
    rank_b = _ranks(top_c, eb, cosine)
    ratio_a = np.empty(n, np.float32)
    ratio_b = np.empty(n, np.float32)
    mutual = np.empty(n, np.bool_)
    confident = np.empty(n, np.bool_)
    tiny, cap = np.float32(1e-9), np.float32(1.5)
    for m in range(n):
        d = cosine_distance32(cosine[m])
        other_a = top_r[ea[m], 1] if rank_a[m] == 0 else top_r[ea[m], 0]
        other_b = top_c[eb[m], 1] if rank_b[m] == 0 else top_c[eb[m], 0]
        qa = d / max(cosine_distance32(other_a), tiny)
        qb = d / max(cosine_distance32(other_b), tiny)
        mutual[m] = rank_a[m] == 0 and rank_b[m] == 0
        confident[m] = mutual[m] and qa < ratio and qb < ratio
        ratio_a[m], ratio_b[m] = min(qa, cap), min(qb, cap)
        rank_a[m], rank_b[m] = min(rank_a[m], RANK_CAP), min(rank_b[m], RANK_CAP)
    return cosine, rank_a, rank_b, ratio_a, ratio_b, mutual, confident


@numba.njit(cache=True, nogil=True)
def _ranks(top, at, s):
    """How many of row ``at[m]``'s best values beat ``s[m]``: the rank of a candidate in its
    keypoint's list. Compiled: numpy's (M, K) comparison took 0.2 ms a 4 x 500 view pair.

    Shapes: top (n, K) float32, at (M,) int64, s (M,) float32 -> (M,) int64."""
    out = np.zeros(at.shape[0], np.int64)
    for m in range(at.shape[0]):
        row = top[at[m]]
        for t in range(row.shape[0]):
            out[m] += row[t] > s[m]
    return out


def confident_pairs(top_r: np.ndarray, ir: np.ndarray, top_c: np.ndarray, ic: np.ndarray,
                    ratio: float) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The confident pairs of a view pair (a, b), the seeds of its two-view model: mutual nearest
    neighbours passing Lowe's ``ratio`` from both sides.

    Args:
        top_r, ir, top_c, ic: a similarity block's best rows and columns, at least two each
            (:func:`gcn_match_ros.similarity.most_similar`).

    Returns:
        keypoints of a, their partners in b (C,) int64, and whether each keypoint of a is its
        nearest neighbour's nearest neighbour (n_a,) bool.
    """
    return _confident_pairs(np.asarray(top_r, np.float32), np.asarray(ir, np.int64),
                            np.asarray(top_c, np.float32), np.asarray(ic, np.int64), float(ratio))


@numba.njit(cache=True, nogil=True)
def _confident_pairs(top_r, ir, top_c, ic, ratio):
    """:func:`confident_pairs`, compiled (a dozen numpy steps a view pair before): the ratios in
    float32 and compared with ``ratio`` in float32, as numpy computes them on these float32 lists
    (:func:`gcn_match_ros.descriptors.cosine_distance`)."""
    na, nb = ir.shape[0], ic.shape[0]
    tiny, limit = np.float32(1e-9), np.float32(ratio)
    passes_c = np.empty(nb, np.bool_)
    for b in range(nb):
        passes_c[b] = cosine_distance32(top_c[b, 0]) / max(cosine_distance32(top_c[b, 1]), tiny) < limit
    mutual = np.empty(na, np.bool_)
    seeds = np.empty(na, np.int64)
    n = 0
    for a in range(na):
        nn = ir[a, 0]
        mutual[a] = ic[nn, 0] == a
        passes_r = cosine_distance32(top_r[a, 0]) / max(cosine_distance32(top_r[a, 1]), tiny) < limit
        if mutual[a] and passes_r and passes_c[nn]:
            seeds[n] = a
            n += 1
    seeds = seeds[:n].copy()
    partners = np.empty(n, np.int64)
    for t in range(n):
        partners[t] = ir[seeds[t], 0]
    return seeds, partners, mutual


def _guided(sim: np.ndarray, xa: np.ndarray, xb: np.ndarray, model: PairModel, px: float):
    """Geometry-guided candidates: nearest keypoint to the H transfer (both directions) and
    the descriptor-best keypoint within ``px`` of the epipolar line (both directions)."""
    out_a, out_b = [], []
    if model.H_inverse is not None:
        # nearest keypoint to each transfer, within px (KD-trees: never an na x nb distance matrix)
        dist, j = cKDTree(xb).query(transfer(model.H, xa), distance_upper_bound=px)
        ok = dist < px
        out_a.append(np.flatnonzero(ok)); out_b.append(j[ok])
        dist, i = cKDTree(xa).query(transfer(model.H_inverse, xb), distance_upper_bound=px)
        ok = dist < px
        out_a.append(i[ok]); out_b.append(np.flatnonzero(ok))
    if model.F is not None:
        la, lb = homogeneous(xa) @ model.F.T, homogeneous(xb) @ model.F  # epipolar lines in b, in a
        j, i = _best_near_lines(sim, la, lb, xa, xb, px)
        ok = j >= 0
        out_a.append(np.flatnonzero(ok)); out_b.append(j[ok])
        ok = i >= 0
        out_a.append(i[ok]); out_b.append(np.flatnonzero(ok))
    if not out_a:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(out_a).astype(np.int64), np.concatenate(out_b).astype(np.int64)


#: How many rows ahead :func:`_best_near_lines` asks for the similarity block's rows
#: (:func:`gcn_match_ros.prefetch.prefetch_row`): 1, 2 and 4 gave the same time.
_PREFETCH_ROWS = 2


@numba.njit(cache=True, nogil=True)
def _best_near_lines(sim, la, lb, xa, xb, px):
    """For each keypoint of a, the most similar keypoint of b within ``px`` of its epipolar line
    and with a within ``px`` of b's line (:func:`gcn_match_ros.geometry.epipolar_distance_matrix`
    < px), and the same for each keypoint of b; -1 where none. The first on ties, as argmax.
    Compiled: one pass over the na x nb pairs, no distance matrix. Per keypoint of a, a loop of
    its own that vectorises puts b's keypoints against its line, undivided by the line's norm:
    the few within a hair more than ``px`` of it are collected without branches, and only they
    are tested as before, distance divided (so the same keypoints pass, bit for bit). 500 x 500:
    0.40 ms testing every pair with a branch, 0.25 with the distances vectorised (one machine),
    0.44 -> 0.30 ms collecting the near ones first (another). Inside the solve most of a call
    waited for the similarity block, read at scattered places after it had left the caches:
    rows asked for ahead (:func:`gcn_match_ros.prefetch.prefetch_row`) took a call at 8 x 500
    from 0.30 to 0.22 ms, at 4 x 500 from 0.25 to 0.22 (timed call by call in the solve).

    Shapes: sim (na, nb); la (na, 3) lines in b, lb (nb, 3) lines in a; xa (na, 2), xb (nb, 2)
    -> (na,), (nb,) int64.
    """
    na, nb = sim.shape
    best_b = np.full(na, -1, np.int64)
    best_a = np.full(nb, -1, np.int64)
    score_b = np.full(na, -np.inf, np.float32)
    score_a = np.full(nb, -np.inf, np.float32)
    norm_b = np.empty(nb)
    for b in range(nb):
        norm_b[b] = max(math.sqrt(lb[b, 0] ** 2 + lb[b, 1] ** 2), 1e-12)
    xb_x, xb_y = xb[:, 0].copy(), xb[:, 1].copy()
    off_line = np.empty(nb)
    near = np.empty(nb + 1, np.int64)
    for a in range(min(_PREFETCH_ROWS, na)):
        prefetch_row(sim, a)
    for a in range(na):
        if a + _PREFETCH_ROWS < na:
            prefetch_row(sim, a + _PREFETCH_ROWS)
        norm_a = max(math.sqrt(la[a, 0] ** 2 + la[a, 1] ** 2), 1e-12)
        _off_line_into(off_line, la[a], xb_x, xb_y)
        # off_line / norm_a < px implies off_line < px * norm_a up to rounding, which the
        # margin covers: a superset of the keypoints that pass, each then tested exactly
        reach = px * norm_a * (1.0 + 1e-9)
        n_near = 0
        for b in range(nb):
            near[n_near] = b
            n_near += off_line[b] < reach
        for t in range(n_near):
            b = near[t]
            if (off_line[b] / norm_a < px
                    and abs(xa[a, 0] * lb[b, 0] + xa[a, 1] * lb[b, 1] + lb[b, 2]) / norm_b[b] < px):
                s = sim[a, b]
                if s > score_b[a]:
                    score_b[a], best_b[a] = s, b
                if s > score_a[b]:
                    score_a[b], best_a[b] = s, a
    return best_b, best_a


@numba.njit(cache=True, nogil=True, inline="never")
def _off_line_into(out, line, x, y):
    """out[b] = |line . (x[b], y[b], 1)|, the distance to the line times its norm: a loop on its
    own that vectorises."""
    l0, l1, l2 = line[0], line[1], line[2]
    for b in range(out.shape[0]):
        out[b] = abs(l0 * x[b] + l1 * y[b] + l2)


def _triangle_support(n, V, view, rows, cols, mask, at_rows=None, at_cols=None, by_row=None) -> np.ndarray:
    """Fraction of third views closing a triangle through ``mask`` edges with each edge of
    (``at_rows``, ``at_cols``); by default the edges (``rows``, ``cols``) themselves. ``by_row``:
    the positions of those edges grouped by row (:func:`gcn_match_ros.buckets.bucket_order`),
    when the caller has them.

    Shapes: view (n,); rows, cols, mask (M,); at_rows, at_cols, by_row (K,) -> (K,) float64.
    """
    if at_rows is None:
        at_rows, at_cols = rows, cols
    if V < 3:
        return np.zeros(at_rows.shape[0])
    at_rows, at_cols = np.asarray(at_rows, np.int64), np.asarray(at_cols, np.int64)
    if by_row is None:
        by_row = bucket_order(at_rows, n)[1]
    indptr, indices = _neighbour_lists(n, np.asarray(rows[mask], np.int64), np.asarray(cols[mask], np.int64))
    views_seen = _common_neighbour_views(indptr, indices, np.asarray(view, np.int64), at_rows, at_cols, by_row, V)
    return views_seen / (V - 2)


@numba.njit(cache=True, nogil=True)
def _neighbour_lists(n, r, c):
    """Neighbour lists (CSR: indptr (n + 1,), indices (2E,)) of the undirected edges (r[e], c[e]):
    a counting sort by keypoint, O(E), unsorted within a list (an edge given twice lists its ends
    twice, which :func:`_common_neighbour_views` counts once)."""
    indptr = np.zeros(n + 1, np.int64)
    for e in range(r.shape[0]):
        indptr[r[e] + 1] += 1
        indptr[c[e] + 1] += 1
    for v in range(n):
        indptr[v + 1] += indptr[v]
    fill = indptr[:-1].copy()
    indices = np.empty(2 * r.shape[0], np.int64)
    for e in range(r.shape[0]):
        indices[fill[r[e]]] = c[e]
        fill[r[e]] += 1
        indices[fill[c[e]]] = r[e]
        fill[c[e]] += 1
    return indptr, indices


@numba.njit(cache=True, nogil=True)
def _common_neighbour_views(indptr, indices, view, rows, cols, by_row, V):
    """Per edge (rows[m], cols[m]) the number of distinct views among the two keypoints' common
    neighbours in the CSR graph (indptr, indices); edges join different views, so each common
    neighbour lies in a third view. Compiled: ~10⁵ edges a window, dozens of neighbours each. The
    edges are visited grouped by row (``by_row``), so each keypoint's neighbours are marked once
    (in the window's order, view pair by view pair, a keypoint's row came back once per view
    pair: 8 x 500, 18 k edges, 2.8 -> 2.3 ms).

    Shapes: rows, cols, by_row (K,) int64 -> (K,) int64.
    """
    out = np.zeros(rows.shape[0], np.int64)
    marked = np.full(indptr.shape[0] - 1, -1, np.int64)  # marked[c] == a: c neighbours a
    counted = np.full(V, -1, np.int64)                   # counted[k] == m: view k counted for m
    current = -1  # the keypoint whose neighbours are marked
    for m in by_row:
        a, b = rows[m], cols[m]
        if a != current:
            for p in range(indptr[a], indptr[a + 1]):
                marked[indices[p]] = a
            current = a
        for p in range(indptr[b], indptr[b + 1]):
            c = indices[p]
            if marked[c] == a and counted[view[c]] != m:
                counted[view[c]] = m
                out[m] += 1
    return out
