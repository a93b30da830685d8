"""The learned matcher: a trained GCN embeds the keypoints; its edge head (or EEᵀ) scores the pairs.

The checkpoint carries the graph and feature settings the network was trained with,
so the input is rebuilt exactly as in training. With an edge head (the shipped models) the
head scores the candidate edges, and the matches and tracks are then checked against the
window's trusted pose-free two-view geometry (:mod:`gcn_match_ros.edges.consistency`:
pairs that disagree are dropped, tracks are merged only when every two members agree).
Without one, EEᵀ is computed one view-pair block at a time (never N×N) and each keypoint's
best candidates per view are kept. Tracks come from the shared greedy conflict-free merging.
"""
from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path
from typing import Callable, Dict, Optional, Tuple

import numpy as np
import torch

from ..descriptors import NORMALIZATIONS, describe_descriptor_kind, descriptor_kind
from ..edges.ambiguity import ambiguous_pairs, check_ratio, near_copies
from ..edges.candidates import RANK_CAP, CandidateJob, EdgeConfig, PairCandidates, ViewPair
from ..edges.consistency import UNVERIFIED_THRESHOLD, WindowGeometry, checkable_view_pairs, may_keep, verified_tracks
from ..edges.head import edge_config_of, edge_probabilities, has_edge_head
from ..edges.neighbourhood import MIN_SHARED, NEIGHBOURS, check_neighbourhood
from ..edges.rig_memory import RigMemory
from ..edges.verify import EPIPOLAR_PX, FINE_PX, MIN_SEEDS, PLANAR_RATIO, PairModel, check_planar_ratio
from ..graph import GRAPH_PRESETS, CorrespondenceGraph, GraphConfig, build_graph
from ..learn.checkpoint import load_checkpoint
from ..learn.model import embed_problem
from ..node_features import feature_dim
from ..problem import Problem
from ..similarity import DescriptorSimilarity
from ..threads import Pending, alongside
from ..timing import stage
from .base import SoftMatches, Solver, SolverConfig
from .registry import register
from .nn import NNSolver

__all__ = ["GCNSolver", "GCNSolverConfig", "DEFAULT_CHECKPOINT", "SHIPPED_MODELS"]

_MODELS = Path(__file__).resolve().parents[1] / "models"
#: The models shipped inside the package (trained by the commands in models/README.md), by
#: descriptor kind (dimension, binary): 128-D real-valued = SIFT, 256 bits = ORB (32 bytes
#: unpacked to 0/1). Other descriptors (e.g. 256-D real-valued learned ones, 128-bit BRIEF)
#: have no shipped model: they need ``gcn:checkpoint=...``.
SHIPPED_MODELS = {(128, False): _MODELS / "default.pt", (256, True): _MODELS / "orb.pt"}
#: The SIFT model, used until a problem tells the descriptor kind.
DEFAULT_CHECKPOINT = SHIPPED_MODELS[(128, False)]


@dataclasses.dataclass
class GCNSolverConfig(SolverConfig):
    """Attributes:
        graph: "checkpoint" (the graph the model was trained on) or a preset name.
        checkpoint: path of a checkpoint; "" = the shipped model for the problem's
            descriptor kind (:data:`SHIPPED_MODELS`).
        graph_normalization: the descriptor normalization of the graph's similarities (``l2``,
            ``rootsift``); "": the loaded model's choice (``config["solver"]["graph_normalization"]``:
            ``rootsift`` for the shipped models, measured as accurate as their training graph's
            ``l2``, models/README.md), else that of the graph above. When it is the candidate
            edges' normalization the two share each view pair's similarity block and best lists.
        top_k: candidates kept per keypoint and view in the soft output.
        floor: scores at or below it are not listed.
        device: torch device for the forward pass ("cpu", "cuda").
        descriptor_fallback: with an edge-scoring model, view pairs that geometric verification
            cannot check — one view has fewer keypoints than it needs seeds
            (``edges.verify.MIN_SEEDS``), as in a low-texture window — also get the ``nn``
            solver's matches (mutual nearest neighbours passing the ratio test, scored by
            cosine). The head never saw such pairs in training and scores every edge of them
            low, so without this a low-texture window matches nothing. False: the head alone.
        verify: with an edge-scoring model, keep only matches and tracks that agree with the
            window's trusted two-view geometry (:mod:`gcn_match_ros.edges.consistency`).
        unverified_threshold: the score a pair needs on a view pair with enough keypoints but
            no trusted model (views that most likely share no scene).
        chained_models: with ``verify``, view pairs without a trusted model get one fitted on
            the pairs that tracks chain through other views, when it has trusted support
            (:mod:`gcn_match_ros.edges.consistency`); None: the loaded model's choice
            (``config["solver"]["chained_models"]``: true for the shipped ORB model, see
            models/README.md), else False.
        rotation_cycles: with ``verify`` and known intrinsics, models whose rotation closes none
            of the window's rotation cycles are not trusted (:mod:`gcn_match_ros.edges.rotation_cycles`):
            for wide views of large scenes with repeated structure (castle-P19: geometric precision
            0.80 -> 0.86); off by default, as a small object's rotations are too uncertain for it
            (generated scenes: F1 0.82 -> 0.29; benchmarks/results/model_cycles.md).
        epipolar_ratio: with ``verify``, a strong pair (cosine at least
            :data:`gcn_match_ros.edges.ambiguity.MIN_JUDGED_COSINE`) of a view pair with a
            trusted epipolar model is dropped when another keypoint along its epipolar line is
            nearly as similar to it (Lowe's ratio along the line at or above this): repetitions
            of a structure the cameras move along (castle-P19's facade: geometric precision
            0.85 -> 0.90 at 0.9, 0.91 at 0.8 with fewer right pairs; generated scenes, whose
            weak descriptors are not judged: unchanged). 0: off.
        epipolar_fit_px: inlier threshold (Sampson distance, pixels) of the two-view epipolar
            models, which also caps the tolerance within which a pair agrees with one
            (:func:`gcn_match_ros.edges.verify.fit_pair`); 2 px, the shipped models' training
            value, suits keypoints with ~1 px of noise (the generated scenes).
        epipolar_fine_px: the fit threshold tried first; kept for a view pair whose seeds show
            keypoints localised to a fraction of a pixel (SIFT on real images, ~0.1-0.4 px),
            else the pair is fitted again at ``epipolar_fit_px``
            (:func:`gcn_match_ros.edges.verify.fit_pair`). At 2 px a model of such keypoints also
            explains repetitions shifted a few pixels off the true epipolar lines and tilts its
            lines towards them (castle-P19: lines ~4 degrees off, a third of a view pair's pairs
            wrong). 0: off (every model at ``epipolar_fit_px``). Measured in
            benchmarks/results/geometric_eval.md.
        neighbours: with ``verify``, a kept pair whose descriptors are near-copies (cosine at
            least :data:`gcn_match_ros.edges.ambiguity.MIN_JUDGED_COSINE`) must share at least
            ``min_shared_neighbours`` of its k = ``neighbours`` nearest confident pairs (scored at
            least ``threshold``) of its view pair in both views
            (:mod:`gcn_match_ros.edges.neighbourhood`): a match shifted to a repetition of its
            point keeps the epipolar geometry but not its neighbours. 0: off. Measured in
            benchmarks/results/geometric_eval.md.
        min_shared_neighbours: see ``neighbours``.
        prefer_localised: with ``verify``, the tracks of a window that sees one plane (see
            ``planar_threshold``) take of near-duplicate keypoints (closer than
            :data:`gcn_match_ros.edges.duplicates.DUPLICATE_PX`: ORB's pyramid levels report
            one corner several times) the ones the homographies place best
            (:mod:`gcn_match_ros.edges.duplicates`).
        planar_threshold: with ``verify``, the threshold of pairs checked point to point, so that
            none of the repetitions along an epipolar line that the precision-first ``threshold``
            guards against pass: every pair of a window that sees one plane (every view pair of at
            least three views verified by a homography,
            :attr:`gcn_match_ros.edges.consistency.WindowGeometry.one_plane`), and in other windows
            a pair that adds to a track a keypoint the track's members place
            (:mod:`gcn_match_ros.edges.placement`). < 0: ``threshold`` when that is set,
            else the loaded model's choice (``config["solver"]["planar_threshold"]``: its
            validation-F1 threshold, models/README.md), else ``threshold``.
        planar_ratio: a view pair's two-view model is the homography when it explains at least
            this share of the seeds the fundamental matrix explains (:func:`gcn_match_ros.edges.verify.fit_pair`).
            < 0: the loaded model's choice (``config["solver"]["planar_ratio"]``: 0.7 for the shipped
            ORB model, whose noisy seeds of a plane make the fundamental matrix degenerate;
            models/README.md), else :data:`gcn_match_ros.edges.verify.PLANAR_RATIO`.
        support_threshold: with ``verify``, a track of two that at least
            :data:`gcn_match_ros.edges.support.MIN_EXPECTED` other views verified against both
            of its views should show, yet none joined, is kept only when its pair scores at
            least this (:mod:`gcn_match_ros.edges.support`): for views of unoccluded surfaces
            with repetitions (castle-P19's facades with SIFT, 0.8: geometric precision at
            separation 3 0.84 -> 0.86); off by default, as it takes a point inside a view for one
            seen there (generated scenes with partial visibility lose F1). 0: off.
        trusted_candidates: guided candidates and the geometric edge features come only from view
            pairs whose two-view model is trusted (the loaded model's ``min_inliers`` and
            ``min_inlier_ratio``, :meth:`gcn_match_ros.edges.verify.PairModel.trusted`); an
            untrusted model gives none. False: from any model the fit returns, as before issue 11
            — with ``verify=false`` and ``threshold=0.3`` the recall-first operating point of the
            day issues 11 and 12 were filed (``config/recall.yaml``: held-out ORB F1 / AP 0.737 /
            0.768, the filing's solver 0.733 / 0.754: benchmarks/results/real_eval_operating_points.md;
            with trusted models only 0.718 / 0.732: real_eval_filing.md). Needs ``verify=false``:
            the verification checks pairs against trusted models only.
        noise_scaled_residuals: the edge head's residual features of a view pair of noisy
            keypoints (its model fitted at ``epipolar_fit_px``, its measured noise sigma above
            ``epipolar_fine_px``) are in units of that noise
            (:func:`gcn_match_ros.edges.candidates.residual_unit_px`; generated scenes with 1 px of
            noise: rome16k F1 +0.036, real SIFT windows as before);
            None: the loaded model's choice (``config["solver"]["noise_scaled_residuals"]``: true
            for the shipped SIFT model, models/README.md), else False.
        parallel: compute the candidate edges on a second thread while the graph and the network
            run (:func:`gcn_match_ros.threads.alongside`); the same results either way. False:
            one thread.
        keep_apart: with ``parallel``, keep the two threads on two CPUs while a window is solved,
            the one the solving thread is on and the next (:func:`gcn_match_ros.threads.kept_apart`;
            where a kernel packs light loads onto one CPU, as this project's VM's does, the node's
            4 x 500 latency p95 48.8 -> 39.4 ms, benchmarks/results/node_latency_4x500_repeats.md);
            the same results either way. False: the OS places them.
    """

    graph: str = "checkpoint"
    threshold: float = -1.0  # < 0: the checkpoint's config["solver"]["threshold"], else 0.5
    checkpoint: str = ""
    graph_normalization: str = ""
    top_k: int = 8
    floor: float = 0.01
    device: str = "cpu"
    descriptor_fallback: bool = True
    verify: bool = True
    unverified_threshold: float = UNVERIFIED_THRESHOLD
    chained_models: Optional[bool] = None
    rotation_cycles: bool = False
    epipolar_ratio: float = 0.9
    epipolar_fit_px: float = EPIPOLAR_PX
    epipolar_fine_px: float = FINE_PX
    neighbours: int = NEIGHBOURS
    min_shared_neighbours: int = MIN_SHARED
    prefer_localised: bool = True
    planar_threshold: float = -1.0
    planar_ratio: float = -1.0
    support_threshold: float = 0.0
    trusted_candidates: bool = True
    noise_scaled_residuals: Optional[bool] = None
    parallel: bool = True
    keep_apart: bool = True

    def __post_init__(self) -> None:
        if self.graph != "checkpoint" and self.graph not in GRAPH_PRESETS:
            raise ValueError(f"unknown graph '{self.graph}'; choose 'checkpoint' or one of {sorted(GRAPH_PRESETS)}")
        if self.graph_normalization and self.graph_normalization not in NORMALIZATIONS:
            raise ValueError(f"graph_normalization must be one of {NORMALIZATIONS} or '' (the model's choice), "
                             f"got {self.graph_normalization!r}")
        for name in ("threshold", "planar_threshold"):
            value = getattr(self, name)
            if not (0.0 <= value <= 1.0 or value == -1.0):
                raise ValueError(f"{name} must be in [0, 1] (or -1: the model's choice), got {value}")
        if self.planar_ratio != -1.0:
            check_planar_ratio(self.planar_ratio, "planar_ratio (or -1: the model's choice)")
        if self.top_k < 1:
            raise ValueError(f"top_k must be >= 1, got {self.top_k}")
        for name in ("unverified_threshold", "support_threshold"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        check_ratio(self.epipolar_ratio)
        if self.verify and not self.trusted_candidates:
            raise ValueError("trusted_candidates=false needs verify=false: the verification checks pairs against "
                             "trusted two-view models only")
        check_neighbourhood(self.neighbours, self.min_shared_neighbours)
        if not self.epipolar_fit_px > 0.0:
            raise ValueError(f"epipolar_fit_px must be > 0, got {self.epipolar_fit_px}")
        if not self.epipolar_fine_px >= 0.0:
            raise ValueError(f"epipolar_fine_px must be >= 0 (0: off), got {self.epipolar_fine_px}")
        try:
            device = torch.device(self.device)
        except RuntimeError as exc:
            raise ValueError(f"device: {exc}") from None
        if device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError(f"device '{self.device}': this torch ({torch.__version__}) sees no CUDA device")


@functools.lru_cache(maxsize=4)
def _load(path: str, device: str, mtime: float):
    model, meta = load_checkpoint(path, map_location=device)
    return model.to(device).eval(), meta


@register
class GCNSolver(Solver):
    """Phillips & Daniilidis' GCN: unit embeddings E, pair scores (EEᵀ)_ab clipped to [0, 1]."""

    name = "gcn"
    Config = GCNSolverConfig
    needs_graph = False  # match builds it, beside the candidate edges
    uses_rig_memory = True
    schedules_beside = True

    def __init__(self, config=None, **settings) -> None:
        super().__init__(config, **settings)
        self._use(os.fspath(self.config.checkpoint or DEFAULT_CHECKPOINT))

    def _use(self, path: str) -> None:
        """Load (cached) the checkpoint at ``path``."""
        # mtime in the cache key: a retrained file at the same path is reloaded.
        mtime = os.path.getmtime(path) if os.path.isfile(path) else 0.0
        self.model, self.meta = _load(path, self.config.device, mtime)
        self.checkpoint_path = path

    @property
    def threshold(self) -> float:
        """The threshold setting, else the one selected with the loaded model (its validation
        split; models/README.md), else 0.5."""
        if self.config.threshold >= 0:
            return self.config.threshold
        return float(self._model_choice("threshold", 0.5))

    @property
    def planar_threshold(self) -> float:
        """The planar_threshold setting, else the threshold setting, else the one stored with the
        loaded model, else :attr:`threshold` (:class:`GCNSolverConfig`)."""
        if self.config.planar_threshold >= 0:
            return self.config.planar_threshold
        if self.config.threshold >= 0:
            return self.config.threshold
        return float(self._model_choice("planar_threshold", self.threshold))

    @property
    def chained_models(self) -> bool:
        """The chained_models setting, else the loaded model's choice, else False."""
        if self.config.chained_models is not None:
            return self.config.chained_models
        return bool(self._model_choice("chained_models", False))

    def _model_choice(self, name: str, default):
        """A solver setting stored with the loaded model (``config["solver"]``, chosen after
        training: models/README.md), else ``default``."""
        return (self.meta["config"].get("solver") or {}).get(name, default)

    @property
    def descriptor_kinds(self) -> Tuple[Tuple[int, bool], ...]:
        """(dimension, binary) of the descriptors this solver takes: every shipped model's kind,
        or with a checkpoint setting its dimension, as real-valued and as binary."""
        if self.config.checkpoint:
            dim = int(self.meta["model_config"].in_dim - feature_dim(0, self.meta["feature_config"]))
            return ((dim, False), (dim, True))
        return tuple(k for k, p in sorted(SHIPPED_MODELS.items()) if p.is_file())

    def prepare(self, problem: Problem) -> None:
        """With no checkpoint setting, switch to the shipped model for this descriptor kind.

        Raises:
            ValueError: no shipped model takes these descriptors, or the checkpoint set takes
                descriptors of another dimension (both named in the message).
        """
        if problem.n_keypoints == 0:
            return
        kind = descriptor_kind(problem.descriptors)
        if self.config.checkpoint:
            takes = self.descriptor_kinds[0][0]
            if kind[0] != takes:
                raise ValueError(f"gcn:checkpoint={self.config.checkpoint} takes {takes}-dimensional descriptors, "
                                 f"this window has {describe_descriptor_kind(kind)} ones")
            return
        path = SHIPPED_MODELS.get(kind)
        if path is None or not path.is_file():
            have = ", ".join(describe_descriptor_kind(k) for k in self.descriptor_kinds) or "none"
            raise ValueError(f"no shipped gcn model takes {describe_descriptor_kind(kind)} descriptors "
                             f"(shipped: {have}); train one and pass gcn:checkpoint=PATH")
        if os.fspath(path) != self.checkpoint_path:
            self._use(os.fspath(path))

    @property
    def graph_config(self) -> GraphConfig:
        """The graph the model was trained on (``graph=checkpoint``), else the preset; its
        normalization as :attr:`GCNSolverConfig.graph_normalization` says."""
        config = self.meta["graph_config"] if self.config.graph == "checkpoint" else GRAPH_PRESETS[self.config.graph]
        normalization = (self.config.graph_normalization
                         or self._model_choice("graph_normalization", config.normalization))
        return dataclasses.replace(config, normalization=normalization)

    @property
    def keeps_threads_apart(self) -> bool:
        """``keep_apart`` where the candidate edges run beside the graph and the network
        (``parallel``, a model with an edge head: :meth:`match`)."""
        return self.config.keep_apart and self.config.parallel and has_edge_head(self.model)

    @property
    def similarity_top_k(self) -> Dict[str, int]:
        """The candidate edges' best lists (RANK_CAP + 1): computed at that k by whichever of the
        graph (which reads the first 4) and the candidate edges asks first."""
        if not has_edge_head(self.model):
            return {}
        return {self.edge_config.normalization: RANK_CAP + 1}

    @property
    def edge_config(self) -> EdgeConfig:
        """The candidate edges the loaded model was trained on, with this solver's epipolar
        fit thresholds, H-vs-F choice (:attr:`planar_ratio`), trust rule (``trusted_candidates``) and
        residual units (:attr:`noise_scaled_residuals`)."""
        edges = dataclasses.replace(edge_config_of(self.model), epipolar_px=self.config.epipolar_fit_px,
                                    fine_px=self.config.epipolar_fine_px, planar_ratio=self.planar_ratio,
                                    noise_scaled_residuals=self.noise_scaled_residuals)
        if not self.config.trusted_candidates:
            edges = dataclasses.replace(edges, min_inliers=0, min_inlier_ratio=0.0)
        return edges

    @property
    def noise_scaled_residuals(self) -> bool:
        """The noise_scaled_residuals setting, else the loaded model's choice, else False."""
        if self.config.noise_scaled_residuals is not None:
            return self.config.noise_scaled_residuals
        return bool(self._model_choice("noise_scaled_residuals", False))

    @property
    def planar_ratio(self) -> float:
        """The planar_ratio setting, else the loaded model's choice, else
        :data:`gcn_match_ros.edges.verify.PLANAR_RATIO`."""
        if self.config.planar_ratio > 0:
            return self.config.planar_ratio
        return float(self._model_choice("planar_ratio", PLANAR_RATIO))

    def describe(self) -> str:
        base = super().describe()
        return base if self.config.checkpoint else base + (":" if ":" not in base else ",") + "model=shipped"

    def match(self, problem: Problem, graph: Optional[CorrespondenceGraph], similarity: DescriptorSimilarity,
              rig: Optional[RigMemory] = None, beside: Optional[Pending] = None):
        edges = self.edge_config if has_edge_head(self.model) and problem.n_keypoints else None
        # The candidate edges need neither the graph nor the network: with parallel, they are
        # computed on the second thread meanwhile (threads.alongside), and this thread takes
        # the view pairs still left once its network is done; the stage "waiting" is the time
        # it then idles for the pairs the second thread is on.
        # Verification drops the pairs that disagree with their view pair's trusted model
        # whatever their score (80-94 % of the candidates of generated and real windows): they
        # get no features and are not scored (consistency.may_keep, view pair by view pair as the
        # candidate edges find them). Every later step reads only pairs it may keep, so the
        # published pairs and tracks are the same. (Rotation cycles may still drop a model,
        # which turns its view pair's pairs into scored ones: there every candidate is kept.)
        verify_first = edges is not None and self._verifies(edges) and not self.config.rotation_cycles
        keep = _may_keep_rule(problem) if verify_first else None
        job = CandidateJob(problem, edges, similarity, rig, keep) if edges is not None else None
        with alongside(_timed_candidates, job, parallel=self.config.parallel and job is not None) as candidates:
            if beside is not None and self.config.parallel:
                beside.start()  # the caller's work (Solver.solve), queued behind the candidate edges
            if graph is None:
                with stage("graph"):
                    graph = build_graph(problem, self.graph_config, similarity)
            if problem.n_keypoints == 0:
                return SoftMatches.from_graph(graph), None
            with torch.inference_mode():
                with stage("network"):
                    emb, _ = embed_problem(self.model, problem, self.graph_config, self.meta["feature_config"],
                                           graph=graph)
                if edges is None:
                    return SoftMatches.from_embedding(emb, problem.view_offsets, floor=self.config.floor,
                                                      top_k=self.config.top_k), None
                # Learned edge scorer over descriptor + geometry-guided candidates (pose-free).
                # The caller's work (queued behind the candidate edges) has the second thread from
                # their end on, beside the edge head, the verification and the tracks: a head
                # large enough to split (edge_probabilities) then runs both halves here. Taking
                # that work back until the head was done left the second thread idle meanwhile
                # (solve + landmarks, window by window: 4 x 500 0.9 ms, 4 x 1000 1.7, 10 x 1000
                # 30 ms slower; 8 x 500 the same).
                with stage("candidates"):
                    job.help()
                with stage("waiting"):
                    es = candidates.result()
                if job.candidates == 0:
                    return SoftMatches.from_graph(graph, values=graph.weights * 0), None
                geometry = self._geometry(problem, es.models, edges)
                with stage("edge_head"):
                    soft = SoftMatches(es.rows, es.cols, edge_probabilities(self.model, torch.from_numpy(emb), es,
                                                                            parallel=self.config.parallel))
        if self.config.descriptor_fallback and edges.geometry:
            with stage("candidates"):
                soft = _with_descriptor_matches(problem, soft, similarity)
        if geometry is not None:
            if self.config.epipolar_ratio > 0:
                with stage("rounding"):
                    clear = ~ambiguous_pairs(geometry, similarity, edges.normalization,
                                             soft.rows, soft.cols, self.config.epipolar_ratio)
                soft = SoftMatches(soft.rows[clear], soft.cols[clear], soft.scores[clear])
            return self._verified(soft, geometry, similarity, edges.normalization)
        return soft, None

    def _verifies(self, edges: EdgeConfig) -> bool:
        """Whether the pairs are verified against the view pairs' trusted models."""
        return bool(self.config.verify and edges.geometry)

    def _geometry(self, problem: Problem, models: Dict[ViewPair, Optional[PairModel]],
                  edges: EdgeConfig) -> Optional[WindowGeometry]:
        """The window's trusted ``models`` (:attr:`gcn_match_ros.edges.candidates.EdgeSet.models`)
        that verification checks the pairs against; None when the solver does not verify."""
        if not self._verifies(edges):
            return None
        return WindowGeometry(problem, models, self.config.unverified_threshold, edges)

    def _verified(self, soft: SoftMatches, geometry: WindowGeometry, similarity: DescriptorSimilarity,
                  normalization: str):
        """The pairs ``geometry`` keeps, and tracks whose members all agree with it."""
        with stage("rounding"):
            keep, track = verified_tracks(geometry, soft.rows, soft.cols, soft.scores, self.threshold,
                                          self.chained_models, self.config.rotation_cycles,
                                          self.config.neighbours, self.config.min_shared_neighbours,
                                          functools.partial(near_copies, geometry, similarity, normalization),
                                          prefer_localised=self.config.prefer_localised,
                                          planar_threshold=self.planar_threshold,
                                          support_threshold=self.config.support_threshold)
        return SoftMatches(soft.rows[keep], soft.cols[keep], soft.scores[keep]), track


def _may_keep_rule(problem: Problem) -> Callable[[ViewPair, Optional[PairModel], PairCandidates], np.ndarray]:
    """The candidate edges' ``keep`` rule when the solve verifies: each view pair's candidates that
    the window's trusted models may keep (:func:`gcn_match_ros.edges.consistency.may_keep`)."""
    checkable = checkable_view_pairs(problem)

    def keep(pair: ViewPair, model: Optional[PairModel], part: PairCandidates) -> np.ndarray:
        return may_keep(model, bool(checkable[pair]), part.res_h, part.res_f)

    return keep


def _timed_candidates(job: CandidateJob):
    with stage("candidates"):
        return job.result()


def _with_descriptor_matches(problem: Problem, soft: SoftMatches, similarity: DescriptorSimilarity) -> SoftMatches:
    """``soft`` plus the ``nn`` solver's matches (mutual NN, ratio 0.8, score = cosine) on every
    view pair with a view of fewer than ``edges.verify.MIN_SEEDS`` keypoints, the larger score
    where both have a pair (:attr:`GCNSolverConfig.descriptor_fallback`). Unchanged when no view
    is that small."""
    small = problem.view_sizes < MIN_SEEDS
    if not small.any():
        return soft
    nn_solver = NNSolver()
    nn, _ = nn_solver.match(problem, build_graph(problem, nn_solver.graph_config, similarity), similarity)
    view = problem.view_index
    keep = small[view[nn.rows]] | small[view[nn.cols]]
    n = problem.n_keypoints
    keys = np.r_[soft.rows * n + soft.cols, nn.rows[keep] * n + nn.cols[keep]]
    scores = np.r_[soft.scores, nn.scores[keep]].astype(np.float32)
    order = np.lexsort((-scores, keys))  # per pair, the larger score first
    keys, scores = keys[order], scores[order]
    first = np.r_[True, keys[1:] != keys[:-1]]
    return SoftMatches(keys[first] // n, keys[first] % n, scores[first])
