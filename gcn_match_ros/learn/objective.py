"""What one training step computes: samples, batches and the loss of a batch.

- :class:`Sample` / :func:`make_sample`: a problem with its graph and node features, built
  with the settings the model is trained with;
- :class:`Batch` / :func:`make_batch`: samples as one block-diagonal graph;
- :func:`train_step`: forward + loss of one batch (no backward, no optimizer);
  :class:`TrainingObjective` is the same as a module, what distributed training wraps in
  ``DistributedDataParallel``; :func:`evaluate`: mean losses without gradients.

Loss of one problem (the paper's, Sec. 4.2, plus the edge head's)::

    recon_weight · D(A + I, EEᵀ)  +  epipolar_weight · mean(EEᵀ ∘ G)  +  edge_weight · edge
        +  distill_weight · distill
    (G and the edge terms only with poses, the edge terms only for models with an edge head;
    distill copies a teacher checkpoint's edge scores: :func:`edge_distillation_loss`)
"""
from __future__ import annotations

import dataclasses
import functools
import math
from collections import OrderedDict
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor

from ..edges.candidates import EdgeConfig, EdgeSet, candidate_edges
from ..edges.head import edge_config_of, has_edge_head
from ..geometry import fundamental_from_poses, sampson_distance
from ..graph import CorrespondenceGraph, GraphConfig, build_graph
from ..node_features import FeatureConfig, calibrated_points, node_features
from ..problem import Problem
from ..view_pairs import by_view_pair
from .checkpoint import load_checkpoint
from .config import TrainConfig
from .losses import distillation_loss, edge_loss, epipolar_loss, reconstruction_loss
from .model import collate, graph_tensors

__all__ = ["Sample", "make_sample", "Batch", "make_batch", "TrainingObjective", "train_step", "evaluate",
           "edge_training_inputs", "edge_training_loss", "edge_distillation_loss"]


@dataclasses.dataclass
class Sample:
    """A problem ready for the network.

    Shapes:
        graph: :class:`graph.CorrespondenceGraph` over the problem's N keypoints.
        features: (N, F) float32 node features.
        points: (N, 3) float64 calibrated homogeneous keypoints, or None without poses.
    """

    problem: Problem
    graph: CorrespondenceGraph
    features: np.ndarray
    points: Optional[np.ndarray] = None

    @property
    def has_poses(self) -> bool:
        return self.points is not None


def make_sample(problem: Problem, graph_config: GraphConfig = GraphConfig(),
                feature_config: FeatureConfig = FeatureConfig()) -> Sample:
    """Build the graph, the node features and (with poses) the calibrated points."""
    points = calibrated_points(problem) if problem.has_poses else None
    return Sample(problem, build_graph(problem, graph_config), node_features(problem, feature_config), points)


@dataclasses.dataclass
class Batch:
    """Samples as one block-diagonal graph (:func:`.model.collate`) plus per-graph edges.

    Shapes:
        x (ΣN_b, F), edge_index (2, ΣE_b), edge_weight (ΣE_b,), node_ptr (B+1,);
        edges[b]: graph b's own (edge_index (2, E_b), edge_weight (E_b,)) in local indices.
    """

    samples: List[Sample]
    x: Tensor
    edge_index: Tensor
    edge_weight: Tensor
    node_ptr: Tensor
    edges: List[Tuple[Tensor, Tensor]]


def make_batch(samples: Sequence[Sample]) -> Batch:
    """Collate samples for :func:`train_step`."""
    edges = [graph_tensors(s.graph) for s in samples]
    x, ei, ew, ptr = collate([(s.features, e[0], e[1]) for s, e in zip(samples, edges)])
    return Batch(list(samples), x, ei, ew, ptr, edges)


# ---------------------------------------------------------------------------
# Step function
# ---------------------------------------------------------------------------
class TrainingObjective(torch.nn.Module):
    """:func:`train_step` of ``model`` as a module's ``forward(batch) -> (loss, logs)``.

    Distributed training wraps this, not the GCN, in ``DistributedDataParallel``: the edge
    head scores edges from the embeddings outside ``GCN.forward``, and DDP must see every
    use of a parameter inside the one forward it wraps.
    """

    def __init__(self, model: torch.nn.Module, config: TrainConfig) -> None:
        super().__init__()
        self.model = model
        self.config = config

    def forward(self, batch: Batch) -> Tuple[Tensor, Dict[str, float]]:
        return train_step(self.model, batch, self.config)


def train_step(model: torch.nn.Module, batch: Batch, config: TrainConfig) -> Tuple[Tensor, Dict[str, float]]:
    """Forward pass and loss of one batch; the caller runs backward and the optimizer.

    The loss is the mean over the batch's graphs of
    ``recon_weight · recon + epipolar_weight · epipolar + edge_weight · edge
    + distill_weight · distill`` (the epipolar and edge terms only for graphs with poses, the
    edge terms only for models with an edge head, distill only with ``config.teacher``). Works
    under ``torch.no_grad`` too (validation).

    Returns:
        ``(loss, logs)``: () tensor; logs with float ``loss``, ``recon`` (batch mean),
        ``epipolar``, ``edge`` and ``distill`` (means over graphs with poses; NaN if none). The
        epipolar term is logged even at weight 0, so runs with and without it compare on it.
    """
    net = getattr(model, "module", model)  # the GCN inside a DistributedDataParallel wrapper
    if isinstance(net, TrainingObjective):
        return model(batch)  # (DDP-wrapped) objective: the loss is its forward
    use_edge_head = bool(config.edge_weight) and has_edge_head(net)
    teacher = _teacher(config.teacher, net) if config.distill_weight and has_edge_head(net) else None
    if net is not model and (use_edge_head or teacher is not None):
        raise ValueError("train_step: the model is a wrapped GCN with an edge head, which runs outside "
                         "GCN.forward and so outside the wrapper; wrap TrainingObjective(model, config) in "
                         "DistributedDataParallel instead")
    E_all = model(batch.x, batch.edge_index, batch.edge_weight, batch.node_ptr)
    if teacher is not None:
        with torch.no_grad():
            E_teacher = teacher(batch.x, batch.edge_index, batch.edge_weight, batch.node_ptr)
    ptr = batch.node_ptr.tolist()
    total = E_all.new_zeros(())
    recon_sum, epi_sum, n_epi, edge_sum, n_edge, distill_sum, n_distill = 0.0, 0.0, 0, 0.0, 0, 0.0, 0
    for b, sample in enumerate(batch.samples):
        E = E_all[ptr[b]:ptr[b + 1]]
        ei, ew = batch.edges[b]
        vo = sample.graph.view_offsets
        recon = reconstruction_loss(E, ei, ew, E.shape[0], vo, kind=config.recon_kind,
                                    include_identity=config.include_identity,
                                    include_within_view=config.include_within_view)
        loss = config.recon_weight * recon
        recon_sum += float(recon.detach())
        if sample.has_poses:
            p = sample.problem
            epi = epipolar_loss(E, torch.from_numpy(sample.points), torch.from_numpy(p.R),
                                torch.from_numpy(p.t), vo)
            if config.epipolar_weight:
                loss = loss + config.epipolar_weight * epi
            epi_sum += float(epi.detach())
            n_epi += 1
        if use_edge_head and sample.has_poses:
            edge = edge_training_loss(net, E, sample.problem)
            loss = loss + config.edge_weight * edge
            edge_sum += float(edge.detach())
            n_edge += 1
        if teacher is not None and sample.has_poses:
            distill = edge_distillation_loss(net, E, teacher, E_teacher[ptr[b]:ptr[b + 1]], sample.problem)
            loss = loss + config.distill_weight * distill
            distill_sum += float(distill.detach())
            n_distill += 1
        total = total + loss
    nb = len(batch.samples)
    total = total / nb
    logs = {"loss": float(total.detach()), "recon": recon_sum / nb,
            "epipolar": epi_sum / n_epi if n_epi else float("nan"),
            "edge": edge_sum / n_edge if n_edge else float("nan"),
            "distill": distill_sum / n_distill if n_distill else float("nan")}
    return total, logs


def evaluate(model: torch.nn.Module, samples: Sequence[Sample], config: TrainConfig) -> Dict[str, float]:
    """Mean losses over ``samples`` (eval mode, no gradients), batched by ``config.batch_size``."""
    was_training = model.training
    model.eval()
    sums: Dict[str, float] = {}
    counts: Dict[str, int] = {}
    try:
        with torch.no_grad():
            for i in range(0, len(samples), config.batch_size):
                chunk = samples[i:i + config.batch_size]
                _, logs = train_step(model, make_batch(chunk), config)
                for k, v in logs.items():
                    if not math.isnan(v):
                        sums[k] = sums.get(k, 0.0) + v * len(chunk)
                        counts[k] = counts.get(k, 0) + len(chunk)
    finally:
        model.train(was_training)
    return {k: sums[k] / counts[k] for k in sums}


# ---------------------------------------------------------------------------
# The edge head's term
# ---------------------------------------------------------------------------
_EDGE_CACHE: "OrderedDict[tuple, Tuple[EdgeSet, np.ndarray]]" = OrderedDict()
_EDGE_CACHE_SIZE = 256


def edge_training_inputs(problem: Problem, config: EdgeConfig) -> Tuple[EdgeSet, np.ndarray]:
    """The candidate edges of a posed problem and each one's Sampson distance in pixels under
    the true poses (inf across views without a pair to measure), cached by problem name:
    training visits the same problems again and again."""
    key = (problem.name, problem.n_keypoints, config)
    if problem.name and key in _EDGE_CACHE:
        return _EDGE_CACHE[key]
    es = candidate_edges(problem, config)
    res = np.full(es.rows.shape[0], np.inf)
    view = problem.view_index
    va, vb = view[es.rows], view[es.cols]
    for (a, b), m in by_view_pair(va, vb).items():
        if a < b:
            F = fundamental_from_poses(problem.K[a], problem.R[a], problem.t[a],
                                       problem.K[b], problem.R[b], problem.t[b])
            res[m] = sampson_distance(F, problem.keypoints[es.rows[m]].astype(np.float64),
                                      problem.keypoints[es.cols[m]].astype(np.float64))
    if problem.name:
        _EDGE_CACHE[key] = (es, res)
        while len(_EDGE_CACHE) > _EDGE_CACHE_SIZE:
            _EDGE_CACHE.popitem(last=False)
    return es, res


def edge_training_loss(net: torch.nn.Module, E: Tensor, problem: Problem) -> Tensor:
    """Edge-head loss of one posed problem (``net``: a GCN with an edge head): reconstruction
    of the candidate adjacency plus the epipolar term from the true poses
    (:func:`.losses.edge_loss`). No match labels."""
    es, res = edge_training_inputs(problem, edge_config_of(net))
    if es.rows.shape[0] == 0:
        return E.sum() * 0.0
    logits = net.score_edges(E, torch.from_numpy(es.rows), torch.from_numpy(es.cols),
                             torch.from_numpy(es.features))
    return edge_loss(logits, torch.from_numpy(np.minimum(res, 1e3)))


def edge_distillation_loss(net: torch.nn.Module, E: Tensor, teacher: torch.nn.Module, E_teacher: Tensor,
                           problem: Problem) -> Tensor:
    """:func:`.losses.distillation_loss` of ``net``'s edge head against ``teacher``'s on the
    candidate edges of one problem (those of :func:`edge_training_inputs`, which both heads
    score): a smaller network learns the scores of a trained one, calibration included.

    Shapes: E (N, out_dim) of ``net``, E_teacher (N, teacher's out_dim) -> ()."""
    es, _ = edge_training_inputs(problem, edge_config_of(net))
    if es.rows.shape[0] == 0:
        return E.sum() * 0.0
    rows, cols, features = torch.from_numpy(es.rows), torch.from_numpy(es.cols), torch.from_numpy(es.features)
    with torch.no_grad():
        target = teacher.score_edges(E_teacher, rows, cols, features)
    return distillation_loss(net.score_edges(E, rows, cols, features), target)


@functools.lru_cache(maxsize=2)
def _load_teacher(path: str) -> torch.nn.Module:
    teacher, _ = load_checkpoint(path)
    return teacher.requires_grad_(False)


def _teacher(path: str, net: torch.nn.Module) -> torch.nn.Module:
    """The teacher checkpoint of the distillation term (loaded once, eval mode, no gradients);
    it must score the candidate edges ``net`` is trained on, from the same node features."""
    teacher = _load_teacher(path)
    if not has_edge_head(teacher) or edge_config_of(teacher) != edge_config_of(net) \
            or teacher.config.in_dim != net.config.in_dim:
        raise ValueError(f"teacher {path}: its edge head must score the same candidate edges "
                         f"({edge_config_of(net)}) from the same {net.config.in_dim} node features")
    return teacher
