"""Mutual nearest neighbours: the floor every multi-view method must beat."""
from __future__ import annotations

import dataclasses

from ..graph import CorrespondenceGraph
from ..problem import Problem
from ..similarity import DescriptorSimilarity
from .base import SoftMatches, Solver, SolverConfig
from .registry import register


@dataclasses.dataclass
class NNConfig(SolverConfig):
    """Mutual nearest neighbours with Lowe's ratio 0.8 (``graph=mutual`` drops the ratio test);
    every candidate is merged (threshold 0), best cosine first."""

    graph: str = "ratio0.8"
    threshold: float = 0.0


@register
class NNSolver(Solver):
    """Input nearest neighbours, tracks by greedy conflict-free merging; pair score = cosine."""

    name = "nn"
    Config = NNConfig

    def match(self, problem: Problem, graph: CorrespondenceGraph, similarity: DescriptorSimilarity):
        return SoftMatches.from_graph(graph, values=graph.cosine), None
