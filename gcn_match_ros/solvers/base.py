"""One interface for every multi-view matching method.

A solver turns a :class:`~gcn_match_ros.problem.Problem` into a
:class:`~gcn_match_ros.problem.Result` in timed steps:

1. ``prepare(problem)`` (e.g. the learned solver picks the model for the descriptors),
2. build the correspondence graph from the descriptors (``graph_config``),
3. ``match(problem, graph, similarity)`` — the method itself — returning :class:`SoftMatches`
   (sparse scores between keypoints of different views) and optionally its own tracks,
4. round the scores to cycle-consistent tracks (:func:`~gcn_match_ros.rounding.greedy_tracks`)
   unless the method rounded itself.

The node, the benchmarks and the command line only use :meth:`Solver.solve` on solvers made
by :func:`gcn_match_ros.solvers.create`, so any registered method can be selected by name,
with settings as ``name:key=value,...``.
"""
from __future__ import annotations

import abc
import dataclasses
import time
from typing import Any, ClassVar, Dict, Optional, Tuple, Type

import numpy as np
import torch

from ..graph import GRAPH_PRESETS, CorrespondenceGraph, GraphConfig, build_graph
from ..problem import Problem, Result
from ..rounding import greedy_tracks
from ..similarity import DescriptorSimilarity
from ..stream import StreamState
from ..threads import Pending, kept_apart
from ..timing import StageTimes, stage

__all__ = ["SoftMatches", "Solver", "SolverConfig", "build_config"]

@dataclasses.dataclass
class SoftMatches:
    """Soft similarity between keypoints of different views, stored sparsely.

    Shapes:
        rows, cols: (M,) int64 global keypoint indices with rows < cols, different views.
        scores: (M,) float32 in [0, 1].
    """

    rows: np.ndarray
    cols: np.ndarray
    scores: np.ndarray

    def __post_init__(self) -> None:
        self.rows = np.asarray(self.rows, np.int64)
        self.cols = np.asarray(self.cols, np.int64)
        self.scores = np.clip(np.asarray(self.scores, np.float32), 0.0, 1.0)
        if not (self.rows.shape == self.cols.shape == self.scores.shape and self.rows.ndim == 1):
            raise ValueError(f"SoftMatches: rows {self.rows.shape}, cols {self.cols.shape} and "
                             f"scores {self.scores.shape} must be equal 1-D shapes")

    @classmethod
    def from_graph(cls, graph: CorrespondenceGraph, values: Optional[np.ndarray] = None,
                   floor: float = 0.0) -> "SoftMatches":
        """Scores on the graph's edges (``values`` per stored edge, default its weights)."""
        r, c, pos = graph.upper_pairs()
        v = (graph.weights if values is None else np.asarray(values))[pos]
        keep = v > floor
        return cls(r[keep], c[keep], v[keep])

    @classmethod
    def from_dense(cls, scores: np.ndarray, view_offsets: np.ndarray, floor: float = 0.01) -> "SoftMatches":
        """Entries above ``floor`` of a dense (N, N) score matrix, cross-view upper triangle only."""
        s = np.asarray(scores)
        r_list, c_list, v_list = [], [], []
        V = len(view_offsets) - 1
        for i in range(V):
            for j in range(i + 1, V):
                blk = s[view_offsets[i]:view_offsets[i + 1], view_offsets[j]:view_offsets[j + 1]]
                a, b = np.nonzero(blk > floor)
                r_list.append(a + view_offsets[i])
                c_list.append(b + view_offsets[j])
                v_list.append(blk[a, b])
        return cls._concat(r_list, c_list, v_list)

    @classmethod
    def from_embedding(cls, emb, view_offsets: np.ndarray, floor: float = 0.01,
                       top_k: Optional[int] = 8) -> "SoftMatches":
        """Scores (E Eᵀ)_ab between views, one view-pair block at a time (never N×N).

        Keeps entries above ``floor`` that are among the ``top_k`` of their row or column
        in that block (``None`` keeps every entry above the floor).

        Shapes: emb (N, d) numpy or torch.
        """
        e = torch.as_tensor(emb, dtype=torch.float32)
        r_list, c_list, v_list = [], [], []
        V = len(view_offsets) - 1
        for i in range(V):
            ei = e[view_offsets[i]:view_offsets[i + 1]]
            for j in range(i + 1, V):
                ej = e[view_offsets[j]:view_offsets[j + 1]]
                if ei.shape[0] == 0 or ej.shape[0] == 0:
                    continue
                blk = ei @ ej.T
                mask = blk > floor
                if top_k is not None:
                    mask &= _top_k_mask(blk, top_k)
                a, b = torch.nonzero(mask, as_tuple=True)
                r_list.append(a.numpy() + view_offsets[i])
                c_list.append(b.numpy() + view_offsets[j])
                v_list.append(blk[a, b].numpy())
        return cls._concat(r_list, c_list, v_list)

    @classmethod
    def _concat(cls, r_list, c_list, v_list) -> "SoftMatches":
        if not r_list:
            return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32))
        return cls(np.concatenate(r_list), np.concatenate(c_list), np.concatenate(v_list))


def _top_k_mask(blk: torch.Tensor, k: int) -> torch.Tensor:
    """Entries among the k largest of their row or of their column."""
    mask = torch.zeros_like(blk, dtype=torch.bool)
    kr, kc = min(k, blk.shape[1]), min(k, blk.shape[0])
    mask.scatter_(1, torch.topk(blk, kr, dim=1).indices, True)
    mask.scatter_(0, torch.topk(blk, kc, dim=0).indices, True)
    return mask


@dataclasses.dataclass
class SolverConfig:
    """Settings every solver has.

    Attributes:
        graph: name of the input graph in :data:`GRAPH_PRESETS`.
        threshold: pairs scoring below it are not merged into tracks.
    """

    graph: str = "ratio0.8"
    threshold: float = 0.5

    def __post_init__(self) -> None:
        if self.graph not in GRAPH_PRESETS:
            raise ValueError(f"unknown graph '{self.graph}'; choose one of {sorted(GRAPH_PRESETS)}")
        if not 0.0 <= self.threshold <= 1.0:
            raise ValueError(f"threshold must be in [0, 1], got {self.threshold}")


class Solver(abc.ABC):
    """Base class of all methods; subclasses set ``name``, ``Config`` and implement :meth:`match`.

    Attributes:
        descriptor_kinds: (dimension, binary) of the descriptors the solver takes; () = any
            (a learned model takes only its training descriptors).
        needs_graph: :meth:`solve` builds the correspondence graph for :meth:`match` (False:
            ``match`` gets ``graph=None`` and builds what it needs itself, e.g. its own
            candidates, or the graph beside other work).
        uses_rig_memory: :meth:`match` takes ``rig=`` (:class:`gcn_match_ros.edges.rig_memory.RigMemory`)
            and :meth:`solve` passes the stream's.
        schedules_beside: :meth:`match` takes ``beside=`` (:meth:`solve`'s) and starts it once
            its own work on the second thread is done; otherwise :meth:`solve` starts it before
            the method runs, which leaves that thread idle.
    """

    name: ClassVar[str]
    Config: ClassVar[Type[SolverConfig]] = SolverConfig
    needs_graph: ClassVar[bool] = True
    uses_rig_memory: ClassVar[bool] = False
    schedules_beside: ClassVar[bool] = False

    def __init__(self, config: Optional[SolverConfig] = None, **settings: Any) -> None:
        if config is not None and settings:
            raise ValueError("give either a config or keyword settings, not both")
        self.config = config if config is not None else build_config(self.Config, settings)

    @property
    def descriptor_kinds(self) -> Tuple[Tuple[int, bool], ...]:
        return ()

    @property
    def keeps_threads_apart(self) -> bool:
        """The method runs part of each window on the process's second thread
        (:func:`gcn_match_ros.threads.alongside`) and :meth:`solve` keeps the two on two CPUs
        meanwhile (:func:`gcn_match_ros.threads.kept_apart`; read after :meth:`prepare`)."""
        return False

    @property
    def graph_config(self) -> GraphConfig:
        """The correspondence graph :meth:`solve` builds (read after :meth:`prepare`)."""
        return GRAPH_PRESETS[self.config.graph]

    @property
    def threshold(self) -> float:
        """Score threshold of the rounding (the setting; a solver may derive it otherwise)."""
        return self.config.threshold

    @property
    def similarity_top_k(self) -> Dict[str, int]:
        """normalization -> the k at which the window's similarity computes each view pair's best
        lists (:class:`gcn_match_ros.similarity.DescriptorSimilarity` ``top_k``, read after
        :meth:`prepare`): for a method whose later reader wants more of them than its first."""
        return {}

    def describe(self) -> str:
        """``name:key=value,...`` for every setting that differs from the default."""
        default = self.Config()
        diff = [f"{f.name}={getattr(self.config, f.name)}" for f in dataclasses.fields(self.config)
                if getattr(self.config, f.name) != getattr(default, f.name)]
        return self.name + (":" + ",".join(diff) if diff else "")

    def prepare(self, problem: Problem) -> None:
        """Set up for ``problem`` before anything is built (e.g. choose the model that takes its
        descriptors); raises ``ValueError`` for a problem the solver cannot take."""

    @abc.abstractmethod
    def match(self, problem: Problem, graph: Optional[CorrespondenceGraph], similarity: DescriptorSimilarity):
        """Run the method on one window.

        Args:
            graph: the correspondence graph (``graph_config``), None when ``needs_graph`` is False.
            similarity: the window's descriptor similarity blocks, shared with the graph.

        Returns:
            (SoftMatches, track or None): scores between keypoints of different views, and
            the method's own (N,) tracks if it rounds itself (None: the shared greedy rounding).
        """

    def solve(self, problem: Problem, graph: Optional[CorrespondenceGraph] = None,
              stream: Optional[StreamState] = None, beside: Optional[Pending] = None) -> Result:
        """Prepare + graph build (unless ``graph`` is given, e.g. a synthetic noisy graph) + match +
        rounding. ``Result.seconds`` is the wall time, ``Result.timings`` its stages
        (:mod:`gcn_match_ros.timing`: graph, similarity, match, rounding and the method's own).
        ``stream``: the state of the stream this window belongs to (:mod:`gcn_match_ros.stream`),
        for solvers that use one (``uses_rig_memory``); None: the window stands alone.
        ``beside``: the caller's work that needs nothing of this solve (a stream's landmark search,
        :func:`gcn_match_ros.stream.solve_window`), started on the second thread when the method
        leaves it idle (``schedules_beside``); the caller takes its result."""
        times = StageTimes()
        start = time.perf_counter()
        extra = {}
        if self.uses_rig_memory and stream is not None:
            extra["rig"] = stream.rig
        if beside is not None and self.schedules_beside:
            extra["beside"] = beside
        elif beside is not None:
            beside.start()
        with times.recording():
            self.prepare(problem)
            with kept_apart(self.keeps_threads_apart):
                similarity = DescriptorSimilarity(problem, top_k=self.similarity_top_k)
                if graph is None and self.needs_graph:
                    with stage("graph"):
                        graph = build_graph(problem, self.graph_config, similarity)
                with stage("match"):
                    soft, track = self.match(problem, graph, similarity, **extra)
                if track is None:
                    with stage("rounding"):
                        track = greedy_tracks(problem.n_keypoints, problem.view_index, soft.rows, soft.cols,
                                              soft.scores, self.threshold)
        seconds = time.perf_counter() - start
        return Result(track=track, pair_rows=soft.rows, pair_cols=soft.cols, pair_scores=soft.scores,
                      seconds=seconds, method=self.describe(), timings=times.seconds)


def build_config(config_cls: Type[SolverConfig], settings: Dict[str, Any]) -> SolverConfig:
    """A solver configuration from settings; string values (command line, ``name:key=value``) are
    read as the field's type.

    Raises:
        ValueError: an unknown setting (the message lists the known ones) or a value that does not read.
    """
    fields = {f.name: f for f in dataclasses.fields(config_cls)}
    kwargs = {}
    for key, value in settings.items():
        if key not in fields:
            raise ValueError(f"unknown setting '{key}' for {config_cls.__name__}; "
                             f"known: {', '.join(sorted(fields))}")
        kwargs[key] = _convert(value, fields[key], config_cls)
    return config_cls(**kwargs)


def _field_kind(field: dataclasses.Field) -> type:
    """The scalar type a setting takes: from its default, else from its annotation."""
    if field.default not in (dataclasses.MISSING, None):
        return type(field.default)
    annotation = str(field.type)
    for kind in (bool, int, float):
        if kind.__name__ in annotation:
            return kind
    return str


def _convert(value: Any, field: dataclasses.Field, config_cls) -> Any:
    """Read a command-line string as the setting's type ("none" for optional settings)."""
    if not isinstance(value, str):
        return value
    kind = _field_kind(field)
    if value.lower() == "none" and field.default is None:
        return None
    try:
        if kind is bool:
            if value.lower() not in ("1", "0", "true", "false", "yes", "no"):
                raise ValueError(value)
            return value.lower() in ("1", "true", "yes")
        return kind(value)
    except ValueError:
        raise ValueError(f"setting '{field.name}' of {config_cls.__name__}: cannot read '{value}' "
                         f"as {kind.__name__}") from None
