"""Honest baseline for test-time geometry: mutual NN + ratio 0.8, verified per view pair.

Plain ``nn-ransac`` is the classic baseline: per view pair a USAC homography and
fundamental matrix (1.5 px, whatever the keypoints' localisation) on the confident pairs (:mod:`gcn_match_ros.edges.verify`, H
chosen when it explains the seeds about as well as F, any fitted model believed); a
nearest-neighbour pair is kept when its residual under the selected model is below ``px``
pixels, and pairs of a view pair where no model could be fitted are kept.

``guided=true`` is the learned solver's geometry without the network: its candidate
generation (trusted models only, an essential matrix where intrinsics are known, and the
geometry-guided pairs — nearest keypoint to the H transfer / descriptor-best near the epipolar
line — scored by their cosine) and its checks (:mod:`gcn_match_ros.edges.consistency`: pairs
that disagree with a trusted model dropped, none on view pairs without one, tracks merged only
when every two members agree).
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Optional

from ..edges.ambiguity import ambiguous_pairs, check_ratio, near_copies
from ..edges.candidates import EDGE_FEATURES, EdgeConfig, candidate_edges
from ..edges.consistency import WindowGeometry, verified_tracks
from ..edges.neighbourhood import MIN_SHARED, check_neighbourhood
from ..edges.rig_memory import RigMemory
from ..edges.verify import RANSAC_PX
from ..graph import CorrespondenceGraph
from ..problem import Problem
from ..similarity import DescriptorSimilarity
from .base import SoftMatches, Solver, SolverConfig
from .registry import register

_F = {n: i for i, n in enumerate(EDGE_FEATURES)}


@dataclasses.dataclass
class NNRansacConfig(SolverConfig):
    """Settings: px, the residual (pixels) a pair may have under its view pair's model; guided,
    add the geometry-guided candidates; chained_models: with ``guided``, view pairs without a
    trusted model may gain one from the tracks chained through other views
    (:mod:`gcn_match_ros.edges.consistency`); rotation_cycles: with ``guided`` and known
    intrinsics, models closing none of the window's rotation cycles are not trusted
    (:mod:`gcn_match_ros.edges.rotation_cycles`; off by default, as for gcn); epipolar_ratio: with
    ``guided``, strong pairs with a near-copy along their epipolar line are dropped, as gcn does
    (:mod:`gcn_match_ros.edges.ambiguity`; 0: off); neighbours, min_shared_neighbours: with ``guided``,
    near-copy pairs that keep too few of their neighbours are dropped, as gcn does
    (:mod:`gcn_match_ros.edges.neighbourhood`; 0: off); prefer_localised: with ``guided``, the tracks of a
    window that sees one plane take the near-duplicate keypoints its homographies place best, as
    gcn's do (:mod:`gcn_match_ros.edges.duplicates`). The ``graph`` setting is not used (no graph is built)."""

    threshold: float = 0.0
    px: float = 3.0
    guided: bool = False
    chained_models: bool = False
    rotation_cycles: bool = False
    epipolar_ratio: float = 0.0
    neighbours: int = 0
    min_shared_neighbours: int = MIN_SHARED
    prefer_localised: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        check_ratio(self.epipolar_ratio)
        check_neighbourhood(self.neighbours, self.min_shared_neighbours)


@register
class NNRansacSolver(Solver):
    """Mutual NN + Lowe 0.8 + per-pair RANSAC verification (optionally guided matching)."""

    name = "nn-ransac"
    Config = NNRansacConfig
    needs_graph = False  # the candidate edges hold the mutual nearest neighbours already
    uses_rig_memory = True

    def match(self, problem: Problem, graph: Optional[CorrespondenceGraph], similarity: DescriptorSimilarity,
              rig: Optional[RigMemory] = None):
        if self.config.guided:
            edges = EdgeConfig(k=1, guided=True, guide_px=self.config.px, normalization="l2")
            es = candidate_edges(problem, edges, similarity, rig)
            f = es.features
            pick = (f[:, _F["confident"]] > 0) | (f[:, _F["guided"]] > 0)
            rows, cols, scores = es.rows[pick], es.cols[pick], f[pick, _F["cosine"]]
            # scores are cosines: no pair of a view pair without a trusted model is kept
            geometry = WindowGeometry(problem, es.models, unverified_threshold=1.0, edges=edges)
            if self.config.epipolar_ratio > 0:
                clear = ~ambiguous_pairs(geometry, similarity, edges.normalization, rows, cols,
                                         self.config.epipolar_ratio)
                rows, cols, scores = rows[clear], cols[clear], scores[clear]
            keep, track = verified_tracks(geometry, rows, cols, scores, self.threshold, self.config.chained_models,
                                          self.config.rotation_cycles, self.config.neighbours,
                                          self.config.min_shared_neighbours,
                                          functools.partial(near_copies, geometry, similarity, edges.normalization),
                                          prefer_localised=self.config.prefer_localised)
            return SoftMatches(rows[keep], cols[keep], scores[keep]), track
        es = candidate_edges(problem, EdgeConfig(k=1, guided=False, normalization="l2", min_inliers=0,
                                                 min_inlier_ratio=0.0, essential=False, epipolar_px=RANSAC_PX / 2,
                                                 fine_px=0.0),
                             similarity, rig)
        f = es.features
        keep = (f[:, _F["confident"]] > 0) & ((f[:, _F["has_model"]] == 0) | (es.res_px < self.config.px))
        return SoftMatches(es.rows[keep], es.cols[keep], f[keep, _F["cosine"]]), None
