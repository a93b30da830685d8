"""Training of the GCN: the resumable, optionally distributed training loop.

:func:`train`: the loop — Adam with exponential decay, validation, atomic checkpoints
``checkpoint.pt`` / ``best.pt``, ``history.json``, ``resume``, and distributed data
parallel training (:mod:`.ddp`). Its data come from :mod:`.sources`, its loss from
:mod:`.objective`, its settings from :class:`.config.TrainConfig`.
"""
from __future__ import annotations

import json
import math
import time
import warnings
from itertools import islice
from pathlib import Path
from typing import Any, Dict, List, Optional, Union

import numpy as np
import torch
from tqdm.auto import tqdm

from .. import plots
from ..edges.head import has_edge_head
from ..node_features import feature_dim
from ..problem import Problem, atomic_write
from . import ddp
from .checkpoint import load_checkpoint, save_checkpoint
from .config import TrainConfig
from .model import GCN, GCNConfig
from .objective import Sample, TrainingObjective, evaluate, make_batch, make_sample, train_step
from .sources import DataSource, ShardedSource

__all__ = ["train"]


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


class _Run:
    """The state of one training run and the steps of its loop (see :func:`train`)."""

    def __init__(self, model_config: GCNConfig, cfg: TrainConfig, out: Path, distributed: bool) -> None:
        self.model_config, self.cfg = model_config, cfg
        self.rank, self.world = ddp.rank_and_world(distributed)
        self.main = self.rank == 0
        self.out = out
        out.mkdir(parents=True, exist_ok=True)
        self.ckpt_path, self.best_path, self.hist_path = out / "checkpoint.pt", out / "best.pt", out / "history.json"
        torch.manual_seed(cfg.seed)
        self.model = GCN(model_config)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        self.scheduler = torch.optim.lr_scheduler.ExponentialLR(
            self.optimizer, gamma=cfg.lr_gamma ** (1.0 / cfg.lr_decay_steps))
        self.step = 0
        self.history: Dict[str, Any] = {"train": [], "val": [], "best": None}
        self.best: Optional[Dict[str, Any]] = None
        self.net: torch.nn.Module = self.model
        self.config_dict = {"model": model_config.to_dict(), "graph": cfg.graph.to_dict(),
                            "features": cfg.features.to_dict(), "train": cfg.to_dict()}
        self.interval: Dict[str, List[float]] = {}  # logged values since the last history entry
        self.since_ckpt: List[float] = []  # training losses since the last checkpoint
        self.t0 = time.perf_counter()

    # -- start -------------------------------------------------------------------------
    def restore(self, resume: bool, init: Optional[Union[str, Path]]) -> None:
        """Continue from the run's own checkpoint (``resume``), else start from ``init``'s weights."""
        if resume and self.ckpt_path.is_file():
            saved, meta = load_checkpoint(self.ckpt_path)
            if meta["model_config"] != self.model_config:
                raise ValueError(f"resume: {self.ckpt_path} was trained with {meta['model_config']}, "
                                 f"not {self.model_config}")
            extra = meta["extra"]
            self.model.load_state_dict(saved.state_dict())
            self.optimizer.load_state_dict(extra["optimizer"])
            self.scheduler.load_state_dict(extra["scheduler"])
            self.step = int(extra["step"])
            self.best = extra.get("best")
            _set_rng_state(extra.get("rng", {}))
            if self.hist_path.is_file():
                history = json.loads(self.hist_path.read_text())
                history["train"] = [h for h in history.get("train", []) if h["step"] <= self.step]
                history["val"] = [h for h in history.get("val", []) if h["step"] <= self.step]
                self.history = history
            self.history["best"] = self.best
        elif init is not None:
            saved, meta = load_checkpoint(init)
            if meta["model_config"] != self.model_config:
                raise ValueError(f"init: {init} has architecture {meta['model_config']}, not {self.model_config}")
            self.model.load_state_dict(saved.state_dict())

    def wrap_distributed(self) -> None:
        """Gradients averaged over the ranks (the objective, edge head included, inside DDP)."""
        self.net = ddp.wrap(TrainingObjective(self.model, self.cfg),
                            has_edge_head=has_edge_head(self.model))

    def sample(self, problem: Problem) -> Sample:
        return make_sample(problem, self.cfg.graph, self.cfg.features)

    # -- one step ----------------------------------------------------------------------
    def optimise(self, samples: List[Sample]) -> Dict[str, float]:
        """Forward, backward and an optimizer step on one batch; returns its logged losses."""
        self.optimizer.zero_grad(set_to_none=True)
        loss, logs = train_step(self.net, make_batch(samples), self.cfg)
        loss.backward()
        if self.cfg.grad_clip is not None:
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.cfg.grad_clip)
        self.optimizer.step()
        self.scheduler.step()
        self.step += 1
        for k, v in logs.items():
            if not math.isnan(v):
                self.interval.setdefault(k, []).append(v)
        self.since_ckpt.append(logs["loss"])
        return logs

    def log_training(self, keys: List[str]) -> None:
        """A history entry: the means since the last one (over every rank's values)."""
        means = {k: float(np.mean(v)) for k, v in self.interval.items()}
        if self.world > 1:  # same keys on all ranks: same code
            sums = ddp.all_reduce_sums([x for k in keys for x in (float(np.sum(self.interval.get(k, []))),
                                                                    float(len(self.interval.get(k, []))))])
            means = {k: sums[2 * i] / sums[2 * i + 1] for i, k in enumerate(keys) if sums[2 * i + 1]}
        self.history["train"].append({"step": self.step, **means, "lr": self.scheduler.get_last_lr()[0],
                                      "seconds": time.perf_counter() - self.t0})
        self.interval = {}

    def validate(self, val_samples: List[Sample]) -> bool:
        """Validation losses into the history; True when they are the best so far."""
        val = evaluate(self.model, val_samples, self.cfg)
        self.history["val"].append({"step": self.step, **val})
        if self.best is None or val["loss"] < self.best["loss"]:
            self.best = {"step": self.step, "loss": val["loss"], "source": "val"}
            return True
        return False

    def close_checkpoint_interval(self, has_validation: bool) -> bool:
        """Without validation data, the best model is the one with the lowest mean training loss
        over a checkpoint interval; True when this interval's is the best so far."""
        improved = False
        if self.world > 1:
            total_n = ddp.all_reduce_sums([float(np.sum(self.since_ckpt)), float(len(self.since_ckpt))])
            self.since_ckpt = [total_n[0] / total_n[1]] if total_n[1] else []
        if not has_validation and self.since_ckpt and self.main:
            mean_train = float(np.mean(self.since_ckpt))
            if self.best is None or mean_train < self.best["loss"]:
                self.best, improved = {"step": self.step, "loss": mean_train, "source": "train"}, True
        self.since_ckpt = []
        return improved

    def save(self, path: Path, with_state: bool) -> None:
        """A checkpoint (atomic); ``with_state``: also optimizer, scheduler and RNG states (resumable)."""
        extra = {"step": self.step, "best": self.best}
        if with_state:
            extra.update(optimizer=self.optimizer.state_dict(), scheduler=self.scheduler.state_dict(),
                         rng=_rng_state())
        save_checkpoint(path, self.model, self.config_dict, extra)

    def save_history(self) -> None:
        _write_json(self.hist_path, self.history)

    def plot(self) -> None:
        """curves.png; a failed plot must not fail a finished run."""
        try:
            plots.plot_history([self.history], self.out / "curves.png", labels=[self.out.name])
        except Exception as exc:  # noqa: BLE001
            warnings.warn(f"could not write {self.out / 'curves.png'}: {type(exc).__name__}: {exc}")


def train(model_config: GCNConfig, train_source: DataSource, val_source: Optional[DataSource] = None,
          train_config: TrainConfig = TrainConfig(), out_dir: Union[str, Path] = "runs/gcn",
          resume: bool = False, init: Optional[Union[str, Path]] = None,
          distributed: bool = False) -> Dict[str, Any]:
    """Train a :class:`.model.GCN`, writing checkpoints and the history to ``out_dir``.

    Files (all written atomically):
        ``checkpoint.pt``: latest model + optimizer + scheduler + step + RNG states +
        best-so-far (every ``checkpoint_every`` steps and at the end);
        ``best.pt``: the model with the lowest validation loss (without a validation
        source: the lowest mean training loss over a checkpoint interval);
        ``history.json``: ``{"train": [...], "val": [...], "best": {...}}`` entries with ``step``.
        ``curves.png``: training / validation curves (:func:`gcn_match_ros.plots.plot_history`, at the end,
        when ``train_config.plot``).
    Both ``.pt`` files load with :func:`.checkpoint.load_checkpoint` and carry the graph and
    feature settings (``train_config.graph`` / ``.features``) inference must reuse.

    Distributed (``distributed=True``, after ``torch.distributed.init_process_group``, e.g.
    under ``torchrun``; see :mod:`.ddp`): every rank calls ``train`` with the same
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
    cfg = train_config
    run = _Run(model_config, cfg, Path(out_dir), distributed)
    run.restore(resume, init)
    if distributed:
        run.wrap_distributed()
    val_samples = ([run.sample(p) for p in islice(val_source(0), cfg.val_size)]
                   if val_source is not None and run.main else [])
    shard = ShardedSource(train_source, run.rank, run.world) if run.world > 1 else train_source
    train_iter = shard(run.step * cfg.batch_size)
    run.model.train()
    last_val = run.history["val"][-1]["loss"] if run.history["val"] else float("nan")
    checked = False
    bar = tqdm(total=cfg.steps, initial=run.step, disable=not (cfg.progress and run.main), desc="train",
               dynamic_ncols=True)
    try:
        while run.step < cfg.steps:
            try:
                samples = [run.sample(next(train_iter)) for _ in range(cfg.batch_size)]
            except StopIteration:
                raise ValueError(f"train_source ran out of problems at step {run.step}; "
                                 f"training sources must be endless (cycle)") from None
            if not checked:
                _check_feature_dim(samples[0], model_config, cfg)
                checked = True
            logs = run.optimise(samples)
            bar.update(1)
            bar.set_postfix(loss=f"{logs['loss']:.4f}", val=f"{last_val:.4f}")

            last = run.step == cfg.steps
            at_checkpoint = run.step % cfg.checkpoint_every == 0 or last
            if run.step % cfg.log_every == 0 or last:
                run.log_training(sorted(logs))
            improved = False
            if val_samples and (run.step % cfg.val_every == 0 or last):
                improved = run.validate(val_samples)
                last_val = run.history["val"][-1]["loss"]
            if at_checkpoint:
                improved = run.close_checkpoint_interval(bool(val_samples)) or improved
            if improved and run.main:
                run.history["best"] = run.best
                run.save(run.best_path, with_state=False)
            if at_checkpoint and run.main:
                run.save(run.ckpt_path, with_state=True)
                run.save_history()
    finally:
        bar.close()
    if run.main and cfg.plot and (run.history["train"] or run.history["val"]):
        run.plot()
    if run.world > 1:
        ddp.barrier()  # every rank returns once rank 0's files are written
    return run.history
