"""Settings of a training run (:func:`.train.train`), stored in every checkpoint it writes."""
from __future__ import annotations

import dataclasses
from typing import Optional

from ..configs import JsonConfig
from ..graph import GraphConfig
from ..node_features import FeatureConfig

__all__ = ["TrainConfig"]


@dataclasses.dataclass
class TrainConfig(JsonConfig):
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
        distill_weight: weight of the edge head's distillation term
            (:func:`objective.edge_distillation_loss`), posed problems only; 0: none.
        teacher: checkpoint whose edge head the distillation term copies (same candidate
            edges and node features as the model trained); required when distill_weight > 0.
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
    edge_weight: float = 0.0  # edge-head loss (objective.edge_training_loss), posed problems only
    distill_weight: float = 0.0
    teacher: str = ""
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
        if self.distill_weight < 0 or (self.distill_weight > 0 and not self.teacher):
            raise ValueError(f"TrainConfig.distill_weight={self.distill_weight} needs a teacher checkpoint "
                             f"and must be >= 0 (teacher={self.teacher!r})")


