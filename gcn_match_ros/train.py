"""Training of the GCN: data sources, the step function and a resumable trainer.

Pieces, smallest first:

- :class:`DataSource`: any callable ``source(start=0) -> Iterator[Problem]``;
  :class:`ProblemFileSource` (cycles over ``.npz`` problem files) and
  :class:`SyntheticSource` (a generator function) implement it.
- :class:`Sample` / :func:`make_sample`: a problem with its graph and node
  features, built with the settings the model is trained with.
- :class:`Batch` / :func:`make_batch`: samples as one block-diagonal graph.
- :func:`train_step`: forward + loss of one batch (no backward, no optimizer);
  :class:`TrainingObjective` is the same as a module, what distributed training wraps in
  ``DistributedDataParallel``.
- :func:`train`: the loop (Adam, exponential decay, validation, atomic
  checkpoints ``checkpoint.pt`` / ``best.pt``, ``history.json``, ``resume``).

Loss of one problem (the paper's, Sec. 4.2)::

    recon_weight · D(A + I, EEᵀ)  +  epipolar_weight · mean(EEᵀ ∘ G)   (G only with poses)
"""
from __future__ import annotations

import dataclasses
import functools
import json
import math
import time
from itertools import islice
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Protocol, Sequence, Tuple, Union

import numpy as np
import torch
from torch import Tensor

from .bag_source import BagSource
from .features import FeatureConfig, calibrated_points, feature_dim, node_features
from .graph import CorrespondenceGraph, GraphConfig, build_graph
from .losses import epipolar_loss, reconstruction_loss
from .model import GCN, GCNConfig, collate, graph_tensors, load_checkpoint, save_checkpoint
from .problem import Problem, atomic_write, load_problem

__all__ = ["TrainConfig", "DataSource", "ProblemFileSource", "SyntheticSource", "ShardedSource",
           "InterleavedSource", "BagSource", "Sample", "make_sample", "Batch", "make_batch", "train_step",
           "TrainingObjective",
           "evaluate", "train", "data_source", "run_from_args"]


# ---------------------------------------------------------------------------
# Configuration
# ---------------------------------------------------------------------------
@dataclasses.dataclass
class TrainConfig:
    """Optimisation, loss and bookkeeping settings of :func:`train`.

    Attributes:
        lr: Adam learning rate.
        lr_gamma, lr_decay_steps: the learning rate is multiplied by ``lr_gamma`` every
            ``lr_decay_steps`` steps (smoothly: an exponential decay applied every step).
        weight_decay: Adam weight decay.
        steps: total optimisation steps.
        batch_size: graphs (problems) per step, run as one block-diagonal forward.
        recon_kind: "l1" (the paper) or "l2" reconstruction loss.
        recon_weight: weight of the reconstruction loss.
        epipolar_weight: weight of the epipolar loss (the authors: 10); only for
            problems with poses (K, R, t).
        include_identity, include_within_view: see :func:`losses.reconstruction_loss`.
        grad_clip: max global gradient norm, or None.
        val_every: validate every n steps (and at the last step).
        val_size: number of problems taken once from the validation source.
        checkpoint_every: write ``checkpoint.pt`` + ``history.json`` every n steps (and at the end).
        log_every: append a training entry (means since the last one) to the history every n steps.
        seed: seed of the model initialisation.
        graph: graph construction settings (saved with the model; inference reuses them).
        features: node feature settings (saved with the model).
        progress: show a tqdm progress bar.
        plot: write ``curves.png`` (training / validation curves) to the run folder at the end.
    """

    lr: float = 1e-3
    lr_gamma: float = 0.95
    lr_decay_steps: int = 1000
    weight_decay: float = 0.0
    steps: int = 10000
    batch_size: int = 4
    recon_kind: str = "l1"
    recon_weight: float = 1.0
    epipolar_weight: float = 10.0
    edge_weight: float = 0.0  # edge-head loss (edge_head.edge_training_loss), posed problems only
    include_identity: bool = True
    include_within_view: bool = True
    grad_clip: Optional[float] = None
    val_every: int = 500
    val_size: int = 16
    checkpoint_every: int = 500
    log_every: int = 10
    seed: int = 0
    graph: GraphConfig = GraphConfig()
    features: FeatureConfig = FeatureConfig()
    progress: bool = True
    plot: bool = True

    def __post_init__(self) -> None:
        if self.recon_kind not in ("l1", "l2"):
            raise ValueError(f"TrainConfig.recon_kind must be 'l1' or 'l2', got {self.recon_kind!r}")
        for name in ("steps", "batch_size", "val_every", "checkpoint_every", "log_every", "lr_decay_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"TrainConfig.{name} must be >= 1, got {getattr(self, name)}")

    def to_dict(self) -> Dict[str, Any]:
        """Plain JSON-able dict (graph and features nested)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: Dict[str, Any]) -> "TrainConfig":
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError``."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"TrainConfig: unknown keys {sorted(unknown)}")
        d = dict(d)
        if isinstance(d.get("graph"), dict):
            d["graph"] = GraphConfig(**d["graph"])
        if isinstance(d.get("features"), dict):
            d["features"] = FeatureConfig.from_dict(d["features"])
        return cls(**d)


# ---------------------------------------------------------------------------
# Data sources
# ---------------------------------------------------------------------------
class DataSource(Protocol):
    """Where training problems come from: ``source(start=0) -> Iterator[Problem]``.

    The iterator yields the stream of problems from position ``start`` on (0 = the
    beginning). :func:`train` calls ``source(start)`` once per run, with ``start`` =
    the number of problems already consumed when resuming, so a seekable source
    makes a resumed run see exactly the problems an uninterrupted one would. A
    source that cannot seek may ignore ``start`` (a resumed run then sees other
    problems, which is harmless). Training sources should be infinite (cycle or
    generate); a validation source only needs ``TrainConfig.val_size`` problems.
    """

    def __call__(self, start: int = 0) -> Iterator[Problem]: ...


class ProblemFileSource:
    """Cycles over ``.npz`` problem files (:func:`problem.load_problem`).

    Args:
        paths: files, or directories whose ``*.npz`` files are used (sorted).
        shuffle: visit the files in a new random order every epoch (seeded).
        seed: seed of the shuffling; epoch e uses ``default_rng([seed, e])``.
        cycle: repeat forever (training) or stop after one pass (evaluation).
        cache: keep loaded problems in memory.
    """

    seekable = True

    def __init__(self, paths: Union[str, Path, Sequence[Union[str, Path]]], shuffle: bool = True,
                 seed: int = 0, cycle: bool = True, cache: bool = True) -> None:
        if isinstance(paths, (str, Path)):
            paths = [paths]
        files: List[Path] = []
        for p in map(Path, paths):
            if p.is_dir():
                files.extend(sorted(p.glob("*.npz")))
            elif p.is_file():
                files.append(p)
            else:
                raise ValueError(f"ProblemFileSource: {p}: no such file or directory")
        if not files:
            raise ValueError(f"ProblemFileSource: no problem files in {[str(p) for p in paths]}")
        self.files, self.shuffle, self.seed, self.cycle = files, shuffle, seed, cycle
        self._cache: Optional[Dict[Path, Problem]] = {} if cache else None

    def __len__(self) -> int:
        return len(self.files)

    def _load(self, path: Path) -> Problem:
        if self._cache is None:
            return load_problem(path)
        if path not in self._cache:
            self._cache[path] = load_problem(path)
        return self._cache[path]

    def _order(self, epoch: int) -> np.ndarray:
        n = len(self.files)
        return np.random.default_rng([self.seed, epoch]).permutation(n) if self.shuffle else np.arange(n)

    def __call__(self, start: int = 0) -> Iterator[Problem]:
        n = len(self.files)
        k = int(start)
        while self.cycle or k < n:
            epoch, pos = divmod(k, n)
            yield self._load(self.files[self._order(epoch)[pos]])
            k += 1


class SyntheticSource:
    """An endless stream of generated problems.

    Problem k is ``generator_fn(np.random.default_rng([seed, k]))``, so the stream is
    reproducible and seekable (``start`` costs nothing).

    Args:
        generator_fn: ``(rng: np.random.Generator) -> Problem``.
        seed: stream seed (use different seeds for training and validation).
        length: stop after this many problems (None = endless).
    """

    seekable = True

    def __init__(self, generator_fn: Callable[[np.random.Generator], Problem], seed: int = 0,
                 length: Optional[int] = None) -> None:
        self.generator_fn, self.seed, self.length = generator_fn, seed, length

    def __call__(self, start: int = 0) -> Iterator[Problem]:
        k = int(start)
        while self.length is None or k < self.length:
            yield self.generator_fn(np.random.default_rng([self.seed, k]))
            k += 1


class ShardedSource:
    """Rank ``rank``'s disjoint share of a stream split among ``world_size`` ranks.

    Local problem j is problem ``j * world_size + rank`` of ``source``, so local problems
    ``[s, s + n)`` of all ranks together are exactly problems ``[s·W, (s + n)·W)`` of the
    source: distributed training with per-rank batch B sees the problems a single process
    with batch B·W would. Seekable sources (``seekable = True``) are indexed directly;
    other sources are read in full and thinned.
    """

    def __init__(self, source: DataSource, rank: int, world_size: int) -> None:
        if world_size < 1 or not 0 <= rank < world_size:
            raise ValueError(f"ShardedSource: need 0 <= rank < world_size, got rank={rank}, world_size={world_size}")
        self.source, self.rank, self.world_size = source, int(rank), int(world_size)
        self.seekable = bool(getattr(source, "seekable", False))

    def __call__(self, start: int = 0) -> Iterator[Problem]:
        W, r = self.world_size, self.rank
        if not self.seekable:
            yield from islice(self.source(int(start) * W + r), 0, None, W)
            return
        j = int(start)
        while True:
            try:
                yield next(iter(self.source(j * W + r)))
            except StopIteration:
                return
            j += 1


class InterleavedSource:
    """Several sources taken in turn: problem k is problem ``k // G`` of source ``k % G``
    (seekable when every source is); a finite source that runs out is skipped."""

    def __init__(self, sources: Sequence[DataSource]) -> None:
        if not sources:
            raise ValueError("InterleavedSource: no sources")
        self.sources = list(sources)
        self.seekable = all(getattr(s, "seekable", False) for s in self.sources)

    def __call__(self, start: int = 0) -> Iterator[Problem]:
        G, start = len(self.sources), int(start)
        firsts = [start + (g - start) % G for g in range(G)]  # first index >= start of each source
        iters: Dict[int, Iterator[Problem]] = {g: iter(self.sources[g](firsts[g] // G)) for g in range(G)}
        g = start % G
        while iters:
            it = iters.get(g)
            if it is not None:
                try:
                    yield next(it)
                except StopIteration:
                    del iters[g]
            g = (g + 1) % G


# ---------------------------------------------------------------------------
# Samples and batches
# ---------------------------------------------------------------------------
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
    """Samples as one block-diagonal graph (:func:`model.collate`) plus per-graph edges.

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
    ``recon_weight · recon + epipolar_weight · epipolar + edge_weight · edge`` (the
    epipolar and edge terms only for graphs with poses, the edge term only for models with
    an edge head). Works under ``torch.no_grad`` too (validation).

    Returns:
        ``(loss, logs)``: () tensor; logs with float ``loss``, ``recon`` (batch mean),
        ``epipolar`` and ``edge`` (means over graphs with poses; NaN if none). The epipolar
        term is logged even at weight 0, so runs with and without it compare on it.
    """
    net = getattr(model, "module", model)  # the GCN inside a DistributedDataParallel wrapper
    if isinstance(net, TrainingObjective):
        return model(batch)  # (DDP-wrapped) objective: the loss is its forward
    edge_head = getattr(net, "edge_head", None) if config.edge_weight else None
    if net is not model and edge_head is not None:
        raise ValueError("train_step: the model is a wrapped GCN with an edge head, which runs outside "
                         "GCN.forward and so outside the wrapper; wrap TrainingObjective(model, config) in "
                         "DistributedDataParallel instead")
    E_all = model(batch.x, batch.edge_index, batch.edge_weight, batch.node_ptr)
    ptr = batch.node_ptr.tolist()
    total = E_all.new_zeros(())
    recon_sum, epi_sum, n_epi, edge_sum, n_edge = 0.0, 0.0, 0, 0.0, 0
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
        if edge_head is not None and sample.has_poses:
            from .edge_head import edge_training_loss  # optional edge-scoring head
            edge = edge_training_loss(net, E, sample.problem)
            loss = loss + config.edge_weight * edge
            edge_sum += float(edge.detach())
            n_edge += 1
        total = total + loss
    nb = len(batch.samples)
    total = total / nb
    logs = {"loss": float(total.detach()), "recon": recon_sum / nb,
            "epipolar": epi_sum / n_epi if n_epi else float("nan"),
            "edge": edge_sum / n_edge if n_edge else float("nan")}
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
# Trainer
# ---------------------------------------------------------------------------
def _rng_state() -> Dict[str, Any]:
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    return {"torch": torch.get_rng_state(),
            "numpy": [kind, torch.from_numpy(keys.astype(np.int64)), int(pos), int(has_gauss), float(cached)]}


def _set_rng_state(state: Dict[str, Any]) -> None:
    if "torch" in state:
        torch.set_rng_state(state["torch"])
    if "numpy" in state:
        kind, keys, pos, has_gauss, cached = state["numpy"]
        np.random.set_state((kind, keys.numpy().astype(np.uint32), pos, has_gauss, cached))


def _write_json(path: Path, obj: Any) -> None:
    text = json.dumps(obj, indent=1, allow_nan=True)
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def _check_feature_dim(sample: Sample, model_config: GCNConfig, config: TrainConfig) -> None:
    f = sample.features.shape[1]
    if f != model_config.in_dim:
        d = sample.problem.descriptors.shape[1]
        raise ValueError(f"node features have F={f} columns (descriptor D={d}, {config.features}) but "
                         f"model_config.in_dim={model_config.in_dim}; use in_dim=feature_dim({d}, features)"
                         f" = {feature_dim(d, config.features)}")


def _all_reduce_sums(values: List[float]) -> List[float]:
    import torch.distributed as dist

    t = torch.tensor(values, dtype=torch.float64)
    dist.all_reduce(t, op=dist.ReduceOp.SUM)
    return t.tolist()


def train(model_config: GCNConfig, train_source: DataSource, val_source: Optional[DataSource] = None,
          train_config: TrainConfig = TrainConfig(), out_dir: Union[str, Path] = "runs/gcn",
          resume: bool = False, init: Optional[Union[str, Path]] = None,
          distributed: bool = False) -> Dict[str, Any]:
    """Train a :class:`model.GCN`, writing checkpoints and the history to ``out_dir``.

    Files (all written atomically):
        ``checkpoint.pt``: latest model + optimizer + scheduler + step + RNG states +
        best-so-far (every ``checkpoint_every`` steps and at the end);
        ``best.pt``: the model with the lowest validation loss (without a validation
        source: the lowest mean training loss over a checkpoint interval);
        ``history.json``: ``{"train": [...], "val": [...], "best": {...}}`` entries with ``step``.
        ``curves.png``: training / validation curves (:func:`plots.plot_history`, at the end,
        when ``train_config.plot``).
    Both ``.pt`` files load with :func:`model.load_checkpoint` and carry the graph and
    feature settings (``train_config.graph`` / ``.features``) inference must reuse.

    Distributed (``distributed=True``, after ``torch.distributed.init_process_group``, e.g.
    under ``torchrun``; see :mod:`train_ddp`): every rank calls ``train`` with the same
    arguments; the model is wrapped in ``DistributedDataParallel`` (gradients averaged over
    ranks), rank r trains on its :class:`ShardedSource` share of ``train_source`` (the
    effective batch is ``batch_size × world_size``), logged training losses are averaged
    over all ranks, and only rank 0 validates and writes files and the progress bar.

    Args:
        model_config: architecture; ``in_dim`` must equal the feature dimension.
        train_source: a :class:`DataSource` (should be endless).
        val_source: a :class:`DataSource`; its first ``val_size`` problems are the validation set.
        train_config: :class:`TrainConfig`.
        out_dir: output folder (created).
        resume: continue from ``out_dir/checkpoint.pt`` if it exists (same step count,
            optimizer, scheduler and RNG state; the data stream restarts at the
            position the run had reached).
        init: start from this checkpoint's weights (ignored when resuming from a checkpoint);
            its architecture must equal ``model_config``.
        distributed: train data-parallel over the initialised default process group.

    Returns:
        the history dict (also in ``history.json``).
    """
    from tqdm.auto import tqdm

    cfg = train_config
    rank, world = 0, 1
    if distributed:
        import torch.distributed as dist

        if not dist.is_available() or not dist.is_initialized():
            raise ValueError("train(distributed=True) needs torch.distributed.init_process_group() first")
        rank, world = dist.get_rank(), dist.get_world_size()
    main = rank == 0
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path, best_path, hist_path = out / "checkpoint.pt", out / "best.pt", out / "history.json"

    torch.manual_seed(cfg.seed)
    model = GCN(model_config)
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=cfg.lr_gamma ** (1.0 / cfg.lr_decay_steps))
    step = 0
    history: Dict[str, Any] = {"train": [], "val": [], "best": None}
    best: Optional[Dict[str, Any]] = None

    if resume and ckpt_path.is_file():
        saved, meta = load_checkpoint(ckpt_path)
        if meta["model_config"] != model_config:
            raise ValueError(f"resume: {ckpt_path} was trained with {meta['model_config']}, not {model_config}")
        extra = meta["extra"]
        model.load_state_dict(saved.state_dict())
        optimizer.load_state_dict(extra["optimizer"])
        scheduler.load_state_dict(extra["scheduler"])
        step = int(extra["step"])
        best = extra.get("best")
        _set_rng_state(extra.get("rng", {}))
        if hist_path.is_file():
            history = json.loads(hist_path.read_text())
            history["train"] = [h for h in history.get("train", []) if h["step"] <= step]
            history["val"] = [h for h in history.get("val", []) if h["step"] <= step]
        history["best"] = best
    elif init is not None:
        saved, meta = load_checkpoint(init)
        if meta["model_config"] != model_config:
            raise ValueError(f"init: {init} has architecture {meta['model_config']}, not {model_config}")
        model.load_state_dict(saved.state_dict())

    net: torch.nn.Module = model
    if distributed:
        from torch.nn.parallel import DistributedDataParallel

        # broadcasts rank 0's weights; an optional head (edge_head) is not used by every step
        net = DistributedDataParallel(TrainingObjective(model, cfg),
                                      find_unused_parameters=getattr(model, "edge_head", None) is not None)

    config_dict = {"model": model_config.to_dict(), "graph": dataclasses.asdict(cfg.graph),
                   "features": cfg.features.to_dict(), "train": cfg.to_dict()}

    def checkpoint(path: Path, with_state: bool) -> None:
        extra = {"step": step, "best": best}
        if with_state:
            extra.update(optimizer=optimizer.state_dict(), scheduler=scheduler.state_dict(), rng=_rng_state())
        save_checkpoint(path, model, config_dict, extra)

    def sample_of(problem: Problem) -> Sample:
        return make_sample(problem, cfg.graph, cfg.features)

    val_samples = ([sample_of(p) for p in islice(val_source(0), cfg.val_size)]
                   if val_source is not None and main else [])
    shard = ShardedSource(train_source, rank, world) if world > 1 else train_source
    train_iter = shard(step * cfg.batch_size)
    model.train()
    interval: Dict[str, List[float]] = {}
    since_ckpt: List[float] = []
    last_val = history["val"][-1]["loss"] if history["val"] else float("nan")
    checked = False
    t0 = time.perf_counter()
    bar = tqdm(total=cfg.steps, initial=step, disable=not (cfg.progress and main), desc="train",
               dynamic_ncols=True)
    try:
        while step < cfg.steps:
            try:
                samples = [sample_of(next(train_iter)) for _ in range(cfg.batch_size)]
            except StopIteration:
                raise ValueError(f"train_source ran out of problems at step {step}; "
                                 f"training sources must be endless (cycle)") from None
            if not checked:
                _check_feature_dim(samples[0], model_config, cfg)
                checked = True
            optimizer.zero_grad(set_to_none=True)
            loss, logs = train_step(net, make_batch(samples), cfg)
            loss.backward()
            if cfg.grad_clip is not None:
                torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            optimizer.step()
            scheduler.step()
            step += 1
            for k, v in logs.items():
                if not math.isnan(v):
                    interval.setdefault(k, []).append(v)
            since_ckpt.append(logs["loss"])
            bar.update(1)
            bar.set_postfix(loss=f"{logs['loss']:.4f}", val=f"{last_val:.4f}")

            last = step == cfg.steps
            if step % cfg.log_every == 0 or last:
                means = {k: float(np.mean(v)) for k, v in interval.items()}
                if world > 1:  # mean over every rank's values (same keys on all ranks: same code)
                    keys = sorted(logs)
                    sums = _all_reduce_sums([x for k in keys for x in (float(np.sum(interval.get(k, []))),
                                                                         float(len(interval.get(k, []))))])
                    means = {k: sums[2 * i] / sums[2 * i + 1] for i, k in enumerate(keys) if sums[2 * i + 1]}
                entry = {"step": step, **means,
                         "lr": scheduler.get_last_lr()[0], "seconds": time.perf_counter() - t0}
                history["train"].append(entry)
                interval = {}
            improved = False
            if val_samples and (step % cfg.val_every == 0 or last):
                val = evaluate(model, val_samples, cfg)
                last_val = val["loss"]
                history["val"].append({"step": step, **val})
                if best is None or val["loss"] < best["loss"]:
                    best, improved = {"step": step, "loss": val["loss"], "source": "val"}, True
            if step % cfg.checkpoint_every == 0 or last:
                if world > 1:
                    total_n = _all_reduce_sums([float(np.sum(since_ckpt)), float(len(since_ckpt))])
                    since_ckpt = [total_n[0] / total_n[1]] if total_n[1] else []
                if not val_samples and since_ckpt and main:
                    mean_train = float(np.mean(since_ckpt))
                    if best is None or mean_train < best["loss"]:
                        best, improved = {"step": step, "loss": mean_train, "source": "train"}, True
                since_ckpt = []
            if improved and main:
                history["best"] = best
                checkpoint(best_path, with_state=False)
            if (step % cfg.checkpoint_every == 0 or last) and main:
                checkpoint(ckpt_path, with_state=True)
                _write_json(hist_path, history)
    finally:
        bar.close()
    if main and cfg.plot and (history["train"] or history["val"]):
        try:
            from .plots import plot_history

            plot_history([history], out / "curves.png", labels=[out.name])
        except Exception as exc:  # noqa: BLE001 - a failed plot must not fail a finished run
            import warnings

            warnings.warn(f"could not write {out / 'curves.png'}: {type(exc).__name__}: {exc}")
    if world > 1:
        dist.barrier()  # every rank returns once rank 0's files are written
    return history


# ---------------------------------------------------------------------------
# Command line (``gcn-match train`` / ``torchrun -m gcn_match_ros.train_ddp``)
# ---------------------------------------------------------------------------
_SYNTH_VAL_SEED = 1_000_003  # validation scenes never share a seed with training scenes


def _synthetic_source(spec: str, seed: int) -> SyntheticSource:
    from . import synthetic

    parts = spec.split(":")
    usage = (f"use synth:PRESET[:VIEWS[:DESCRIPTOR]] with PRESET one of {', '.join(synthetic.PRESETS)} and "
             f"DESCRIPTOR one of {', '.join(synthetic.DESCRIPTOR_KINDS)}")
    if len(parts) not in (2, 3, 4):
        raise ValueError(f"bad data spec '{spec}': {usage}")
    try:
        views = int(parts[2]) if len(parts) >= 3 else 3
    except ValueError:
        views = 0
    if views < 2:
        raise ValueError(f"bad data spec '{spec}': VIEWS must be an integer >= 2")
    kind = parts[3] if len(parts) == 4 else "sift"
    try:
        config = synthetic.preset(parts[1], views, kind)
    except ValueError as exc:
        raise ValueError(f"bad data spec '{spec}': {exc}; {usage}") from None
    source = SyntheticSource(functools.partial(synthetic.random_scene_problem, config), seed=seed)
    source.description = f"synthetic {parts[1]} scenes, {views} views, {kind} descriptors"  # type: ignore[attr-defined]
    return source


def _expand_specs(specs: Sequence[str]) -> Tuple[List[Path], List[Path], List[str]]:
    """Data specs -> (problem files, bags, synth specs)."""
    import glob

    from .bag_source import BAG_SUFFIXES, is_bag_path

    npz: List[Path] = []
    bag_paths: List[Path] = []
    synth: List[str] = []
    for spec in specs:
        if spec.startswith("synth:"):
            synth.append(spec)
            continue
        hits = sorted(glob.glob(spec)) if any(ch in spec for ch in "*?[") else [spec]
        if not hits:
            raise ValueError(f"no file matches '{spec}'")
        for h in map(Path, hits):
            if not h.exists():
                raise ValueError(f"{h}: no such file or directory")
            if is_bag_path(h):
                bag_paths.append(h)
            elif h.is_dir():
                problems = sorted(h.glob("*.npz"))
                bagged = sorted(q for q in h.iterdir() if is_bag_path(q))
                if not problems and not bagged:
                    raise ValueError(f"{h}: directory holds no problem files (*.npz) or bags "
                                     f"({', '.join('*' + s for s in BAG_SUFFIXES)}, rosbag2 folders)")
                npz.extend(problems)
                bag_paths.extend(bagged)
            elif h.suffix == ".npz":
                npz.append(h)
            else:
                raise ValueError(f"{h}: not a problem file (.npz), a bag (.mcap, .db3, rosbag2 folder) "
                                 f"or synth:PRESET[:VIEWS[:DESCRIPTOR]]")
    return npz, bag_paths, synth


def data_source(specs: Sequence[str], seed: int = 0, train: bool = True) -> DataSource:
    """A :class:`DataSource` from command-line data specs.

    Forms: problem files or globs (``data/*.npz``) or folders of them ->
    :class:`ProblemFileSource`; bags (``.mcap``, ``.db3``, rosbag2 folders, folders of bags)
    -> :class:`BagSource`; ``synth:PRESET[:VIEWS[:DESCRIPTOR]]`` (``synth:rome16k:4``,
    ``synth:partial:3:binary`` for ORB-like codes) -> :class:`SyntheticSource`. Several
    kinds are taken in turn (:class:`InterleavedSource`).
    ``train=False`` (validation): one pass, no repetition, and synthetic scenes from a
    seed range training never uses. The result has a ``description`` attribute.

    Raises:
        ValueError: unknown form, missing files, unreadable bags.
    """
    npz, bag_paths, synth = _expand_specs(specs)
    sources: List[Any] = []
    words: List[str] = []
    if npz:
        sources.append(ProblemFileSource(npz, shuffle=True, seed=seed, cycle=train))
        words.append(f"{len(npz)} problem file(s)")
    if bag_paths:
        bs = BagSource(bag_paths, shuffle=True, seed=seed, cycle=train)
        sources.append(bs)
        words.append(bs.describe())
    for spec in synth:
        s = _synthetic_source(spec, seed if train else seed + _SYNTH_VAL_SEED)
        sources.append(s)
        words.append(s.description)  # type: ignore[attr-defined]
    if not sources:
        raise ValueError("no data given")
    src = sources[0] if len(sources) == 1 else InterleavedSource(sources)
    src.description = "; ".join(words)  # type: ignore[union-attr]
    src.parts = sources  # type: ignore[union-attr]
    return src


def _check_disjoint(train_src: Any, val_src: Any) -> None:
    from .bag_source import check_disjoint_scenes

    parts_t = getattr(train_src, "parts", [train_src])
    parts_v = getattr(val_src, "parts", [val_src])
    files_t = {p.resolve() for s in parts_t if isinstance(s, ProblemFileSource) for p in s.files}
    files_v = {p.resolve() for s in parts_v if isinstance(s, ProblemFileSource) for p in s.files}
    if files_t & files_v:
        raise ValueError(f"{len(files_t & files_v)} problem file(s) are in both --train and --val, "
                         f"e.g. {sorted(files_t & files_v)[0]}")
    for bt in (s for s in parts_t if isinstance(s, BagSource)):
        for bv in (s for s in parts_v if isinstance(s, BagSource)):
            check_disjoint_scenes(bt, bv)


def _first_problem(source: DataSource, what: str) -> Problem:
    try:
        return next(iter(source(0)))
    except StopIteration:
        raise ValueError(f"{what} data yields no problems") from None


def run_from_args(args, distributed: bool = False) -> int:
    """``gcn-match train``: build the sources, configurations and run :func:`train`.

    ``args`` are the parsed ``train`` arguments of :func:`cli.build_parser`. The model
    configuration is, in order: ``--model-config`` JSON (``in_dim`` filled in when missing),
    the run's own ``checkpoint.pt`` when resuming, the ``--init`` checkpoint, else the
    defaults with ``in_dim = feature_dim(D)``; graph and feature settings come from the
    resumed / ``--init`` checkpoint (else defaults). After training, rank 0 prints where
    the checkpoints and plots are and draws, when the validation data has ground truth,
    the similarity matrix and histograms of the best model.

    Raises:
        ValueError / OSError: bad arguments or data (one-line messages for the CLI).
    """
    rank = 0
    if distributed:
        import torch.distributed as dist

        rank = dist.get_rank()
    say = print if rank == 0 else (lambda *a, **k: None)
    out = Path(args.out)
    ckpt = out / "checkpoint.pt"
    if args.steps < 1 or args.batch < 1:
        raise ValueError("--steps and --batch must be >= 1")
    if args.lr <= 0:
        raise ValueError("--lr must be > 0")
    if args.epipolar_weight < 0 or args.edge_weight < 0:
        raise ValueError("--epipolar-weight and --edge-weight must be >= 0")
    if args.init is not None and not Path(args.init).is_file():
        raise ValueError(f"--init {args.init}: no such checkpoint file")

    base: Optional[Dict[str, Any]] = None
    if args.resume and ckpt.is_file():
        _, base = load_checkpoint(ckpt)
        if args.init is not None:
            say(f"resuming {ckpt}: --init {args.init} is ignored")
    elif args.init is not None:
        _, base = load_checkpoint(args.init)
    elif args.resume:
        say(f"no {ckpt} yet: starting a new run")
    graph_config = base["graph_config"] if base else GraphConfig()
    feature_config = base["feature_config"] if base else FeatureConfig()

    train_src = data_source(args.train, seed=args.seed, train=True)
    val_src = data_source(args.val, seed=args.seed, train=False) if args.val else None
    D = _first_problem(train_src, "--train").descriptors.shape[1]
    if val_src is not None:
        _check_disjoint(train_src, val_src)
        Dv = _first_problem(val_src, "--val").descriptors.shape[1]
        if Dv != D:
            raise ValueError(f"--val descriptors have D={Dv} but --train descriptors D={D}")
    in_dim = feature_dim(D, feature_config)
    if args.model_config is not None:
        d = json.loads(Path(args.model_config).read_text())
        if not isinstance(d, dict):
            raise ValueError(f"--model-config {args.model_config}: expected a JSON object of GCNConfig fields")
        d.setdefault("in_dim", in_dim)
        model_config = GCNConfig.from_dict(d)
    elif base is not None:
        model_config = base["model_config"]
    else:
        model_config = GCNConfig(in_dim=in_dim)
    if model_config.in_dim != in_dim:
        raise ValueError(f"the model takes in_dim={model_config.in_dim} features but the data gives "
                         f"{in_dim} (descriptor D={D}); use data with the model's descriptor or --model-config")
    every = max(1, min(500, args.steps // 20))
    cfg = TrainConfig(lr=args.lr, steps=args.steps, batch_size=args.batch, recon_kind=args.recon,
                      epipolar_weight=args.epipolar_weight, edge_weight=args.edge_weight, seed=args.seed,
                      val_every=every, checkpoint_every=every, log_every=max(1, min(10, every)), graph=graph_config,
                      features=feature_config)
    world = dist.get_world_size() if distributed else 1
    say(f"train: {train_src.description}")  # type: ignore[attr-defined]
    if val_src is not None:
        say(f"val:   {val_src.description}")  # type: ignore[attr-defined]
    say(f"model: {len(model_config.widths)} layers, widths {model_config.widths[0]}..{model_config.widths[-1]}, "
        f"in_dim {model_config.in_dim}; {args.steps} steps x {args.batch} graphs"
        + (f" x {world} ranks" if world > 1 else "") + f" -> {out}")
    history = train(model_config, train_src, val_src, cfg, out, resume=args.resume, init=args.init,
                    distributed=distributed)
    if rank != 0:
        return 0
    best = history.get("best") or {}
    say(f"checkpoints: {ckpt} (step {cfg.steps}), {out / 'best.pt'}"
        + (f" (step {best['step']}, {best['source']} loss {best['loss']:.4f})" if best else ""))
    say(f"history: {out / 'history.json'}")
    plots = [out / "curves.png"] if (out / "curves.png").is_file() else []
    if val_src is not None and (out / "best.pt").is_file():
        plots += _result_plots(out, val_src, cfg.val_size)
    if plots:
        say("plots: " + ", ".join(str(p) for p in plots))
    return 0


def _result_plots(out: Path, val_src: DataSource, count: int) -> List[Path]:
    """similarity.png and histograms.png of the best model on labelled validation problems."""
    from . import plots

    problems = [p for p in islice(val_src(0), count) if p.gt_track is not None]
    if not problems:
        return []
    model, meta = load_checkpoint(out / "best.pt")
    written = []
    try:
        plots.plot_similarity(model, problems[0], out / "similarity.png", meta["graph_config"],
                              meta["feature_config"])
        written.append(out / "similarity.png")
        plots.plot_similarity_histograms(model, problems, out / "histograms.png", meta["graph_config"],
                                         meta["feature_config"])
        written.append(out / "histograms.png")
    except ValueError as exc:
        print(f"(no similarity plots: {exc})")
    return written
