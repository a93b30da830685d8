"""Training of the GCN: data sources, the step function and a resumable trainer.

Pieces, smallest first:

- :class:`DataSource`: any callable ``source(start=0) -> Iterator[Problem]``;
  :class:`ProblemFileSource` (cycles over ``.npz`` problem files) and
  :class:`SyntheticSource` (a generator function) implement it.
- :class:`Sample` / :func:`make_sample`: a problem with its graph and node
  features, built with the settings the model is trained with.
- :class:`Batch` / :func:`make_batch`: samples as one block-diagonal graph.
- :func:`train_step`: forward + loss of one batch (no backward, no optimizer), so
  a ``DistributedDataParallel``-wrapped model can be passed unchanged.
- :func:`train`: the loop (Adam, exponential decay, validation, atomic
  checkpoints ``checkpoint.pt`` / ``best.pt``, ``history.json``, ``resume``).

Loss of one problem (the paper's, Sec. 4.2)::

    recon_weight · D(A + I, EEᵀ)  +  epipolar_weight · mean(EEᵀ ∘ G)   (G only with poses)
"""
from __future__ import annotations

import dataclasses
import json
import math
import time
from itertools import islice
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Protocol, Sequence, Tuple, Union

import numpy as np
import torch
from torch import Tensor

from .features import FeatureConfig, calibrated_points, feature_dim, node_features
from .graph import CorrespondenceGraph, GraphConfig, build_graph
from .losses import epipolar_loss, reconstruction_loss
from .model import GCN, GCNConfig, collate, graph_tensors, load_checkpoint, save_checkpoint
from .problem import Problem, atomic_write, load_problem

__all__ = ["TrainConfig", "DataSource", "ProblemFileSource", "SyntheticSource", "Sample", "make_sample",
           "Batch", "make_batch", "train_step", "evaluate", "train"]


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

    def __init__(self, generator_fn: Callable[[np.random.Generator], Problem], seed: int = 0,
                 length: Optional[int] = None) -> None:
        self.generator_fn, self.seed, self.length = generator_fn, seed, length

    def __call__(self, start: int = 0) -> Iterator[Problem]:
        k = int(start)
        while self.length is None or k < self.length:
            yield self.generator_fn(np.random.default_rng([self.seed, k]))
            k += 1


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
def train_step(model: torch.nn.Module, batch: Batch, config: TrainConfig) -> Tuple[Tensor, Dict[str, float]]:
    """Forward pass and loss of one batch; the caller runs backward and the optimizer.

    The loss is the mean over the batch's graphs of
    ``recon_weight · recon + epipolar_weight · epipolar`` (the epipolar term only for
    graphs with poses). Works under ``torch.no_grad`` too (validation).

    Returns:
        ``(loss, logs)``: () tensor; logs with float ``loss``, ``recon`` (batch mean)
        and ``epipolar`` (mean over graphs with poses; NaN if none).
    """
    E_all = model(batch.x, batch.edge_index, batch.edge_weight, batch.node_ptr)
    ptr = batch.node_ptr.tolist()
    total = E_all.new_zeros(())
    recon_sum, epi_sum, n_epi = 0.0, 0.0, 0
    for b, sample in enumerate(batch.samples):
        E = E_all[ptr[b]:ptr[b + 1]]
        ei, ew = batch.edges[b]
        vo = sample.graph.view_offsets
        recon = reconstruction_loss(E, ei, ew, E.shape[0], vo, kind=config.recon_kind,
                                    include_identity=config.include_identity,
                                    include_within_view=config.include_within_view)
        loss = config.recon_weight * recon
        recon_sum += float(recon.detach())
        if config.epipolar_weight and sample.has_poses:
            p = sample.problem
            epi = epipolar_loss(E, torch.from_numpy(sample.points), torch.from_numpy(p.R),
                                torch.from_numpy(p.t), vo)
            loss = loss + config.epipolar_weight * epi
            epi_sum += float(epi.detach())
            n_epi += 1
        total = total + loss
    nb = len(batch.samples)
    total = total / nb
    logs = {"loss": float(total.detach()), "recon": recon_sum / nb,
            "epipolar": epi_sum / n_epi if n_epi else float("nan")}
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


def train(model_config: GCNConfig, train_source: DataSource, val_source: Optional[DataSource] = None,
          train_config: TrainConfig = TrainConfig(), out_dir: Union[str, Path] = "runs/gcn",
          resume: bool = False) -> Dict[str, Any]:
    """Train a :class:`model.GCN`, writing checkpoints and the history to ``out_dir``.

    Files (all written atomically):
        ``checkpoint.pt``: latest model + optimizer + scheduler + step + RNG states +
        best-so-far (every ``checkpoint_every`` steps and at the end);
        ``best.pt``: the model with the lowest validation loss (without a validation
        source: the lowest mean training loss over a checkpoint interval);
        ``history.json``: ``{"train": [...], "val": [...], "best": {...}}`` entries with ``step``.
    Both ``.pt`` files load with :func:`model.load_checkpoint` and carry the graph and
    feature settings (``train_config.graph`` / ``.features``) inference must reuse.

    Args:
        model_config: architecture; ``in_dim`` must equal the feature dimension.
        train_source: a :class:`DataSource` (should be endless).
        val_source: a :class:`DataSource`; its first ``val_size`` problems are the validation set.
        train_config: :class:`TrainConfig`.
        out_dir: output folder (created).
        resume: continue from ``out_dir/checkpoint.pt`` if it exists (same step count,
            optimizer, scheduler and RNG state; the data stream restarts at the
            position the run had reached).

    Returns:
        the history dict (also in ``history.json``).
    """
    from tqdm.auto import tqdm

    cfg = train_config
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

    config_dict = {"model": model_config.to_dict(), "graph": dataclasses.asdict(cfg.graph),
                   "features": cfg.features.to_dict(), "train": cfg.to_dict()}

    def checkpoint(path: Path, with_state: bool) -> None:
        extra = {"step": step, "best": best}
        if with_state:
            extra.update(optimizer=optimizer.state_dict(), scheduler=scheduler.state_dict(), rng=_rng_state())
        save_checkpoint(path, model, config_dict, extra)

    def sample_of(problem: Problem) -> Sample:
        return make_sample(problem, cfg.graph, cfg.features)

    val_samples = [sample_of(p) for p in islice(val_source(0), cfg.val_size)] if val_source is not None else []
    train_iter = train_source(step * cfg.batch_size)
    model.train()
    interval: Dict[str, List[float]] = {}
    since_ckpt: List[float] = []
    last_val = history["val"][-1]["loss"] if history["val"] else float("nan")
    checked = False
    t0 = time.perf_counter()
    bar = tqdm(total=cfg.steps, initial=step, disable=not cfg.progress, desc="train", dynamic_ncols=True)
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
            loss, logs = train_step(model, make_batch(samples), cfg)
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
                entry = {"step": step, **{k: float(np.mean(v)) for k, v in interval.items()},
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
                if not val_samples and since_ckpt:
                    mean_train = float(np.mean(since_ckpt))
                    if best is None or mean_train < best["loss"]:
                        best, improved = {"step": step, "loss": mean_train, "source": "train"}, True
                since_ckpt = []
            if improved:
                history["best"] = best
                checkpoint(best_path, with_state=False)
            if step % cfg.checkpoint_every == 0 or last:
                checkpoint(ckpt_path, with_state=True)
                _write_json(hist_path, history)
    finally:
        bar.close()
    return history
