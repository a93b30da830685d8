"""Honest baseline for test-time geometry: mutual NN + ratio 0.8, verified per view pair.

The same pose-free two-view verification as the learned ``gcn`` solver's features
(:mod:`gcn_match_ros.edges.verify`: USAC-MAGSAC homography and fundamental matrix on the confident
pairs, H chosen when it explains the seeds about as well as F); a nearest-neighbour pair
is kept when its residual under the selected model is below ``px`` pixels (pairs of a view
pair where no model could be fitted are kept). ``guided=true`` also adds, like the
learned solver's candidates, the geometry-guided pairs (nearest keypoint to the H transfer /
descriptor-best within ``px`` of the epipolar line), scored by their cosine.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

from ..edges.candidates import EDGE_FEATURES, EdgeConfig, candidate_edges
from ..graph import CorrespondenceGraph
from ..problem import Problem
from ..similarity import DescriptorSimilarity
from .base import SoftMatches, Solver, SolverConfig
from .registry import register

_F = {n: i for i, n in enumerate(EDGE_FEATURES)}


@dataclasses.dataclass
class NNRansacConfig(SolverConfig):
    """Settings: px, the residual (pixels) a pair may have under its view pair's model; guided,
    add the geometry-guided candidates. The ``graph`` setting is not used (no graph is built)."""

    threshold: float = 0.0
    px: float = 3.0
    guided: bool = False


@register
class NNRansacSolver(Solver):
    """Mutual NN + Lowe 0.8 + per-pair RANSAC verification (optionally guided matching)."""

    name = "nn-ransac"
    Config = NNRansacConfig
    needs_graph = False  # the candidate edges hold the mutual nearest neighbours already

    def match(self, problem: Problem, graph: Optional[CorrespondenceGraph], similarity: DescriptorSimilarity):
        es = candidate_edges(problem, EdgeConfig(k=1, guided=self.config.guided, guide_px=self.config.px,
                                                 normalization="l2"), similarity)
        f = es.features
        ok_geo = (f[:, _F["has_model"]] == 0) | (es.res_px < self.config.px)
        base = f[:, _F["confident"]] > 0
        if self.config.guided:
            base = base | (f[:, _F["guided"]] > 0)
        keep = base & ok_geo
        return SoftMatches(es.rows[keep], es.cols[keep], f[keep, _F["cosine"]]), None
