"""Data-parallel training with PyTorch's own launcher and engine (torchrun + DDP, gloo on CPU).

    torchrun --nproc_per_node=2 -m gcn_match_ros.cli train --train DATA... [--val DATA...] -o RUN_DIR \\
        [--steps N] [--batch B] [any other flag of `gcn-match train`, --resume included]

``gcn-match train`` started by torchrun (``RANK``, ``WORLD_SIZE``, ``MASTER_ADDR``,
``MASTER_PORT`` set) joins the process group (:func:`init_process_group`) and every
process runs :func:`.train.train` with ``distributed=True``: the model is wrapped in
``torch.nn.parallel.DistributedDataParallel`` (:func:`wrap`: gradients averaged over the
ranks at every step), rank r trains on problems r, r + W, r + 2W, ... of the data stream
(:class:`.sources.ShardedSource`; ``--batch`` is per rank, the effective batch is B·W), and
only rank 0 validates, prints, shows the progress bar and writes ``checkpoint.pt``,
``best.pt``, ``history.json`` and the plots. ``--resume`` works as in a single process:
every rank loads the run's checkpoint and the stream continues where it stopped.

On one machine, ``--master_addr 127.0.0.1`` keeps all traffic on the loopback interface
(set ``GLOO_SOCKET_IFNAME=lo`` too when the host name resolves to another interface).
torchrun's rendezvous store still *listens* on every interface at ``--master_port`` (torch
has no setting for its bind address): on a shared network, firewall that port.
"""
from __future__ import annotations

import datetime
import os
from typing import List, Mapping, Optional, Tuple

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel

__all__ = ["TORCHRUN_VARIABLES", "launched_by_torchrun", "init_process_group", "destroy_process_group", "rank_and_world", "wrap",
           "all_reduce_sums", "barrier"]

#: The environment torchrun gives each process.
TORCHRUN_VARIABLES = ("RANK", "WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT")


def launched_by_torchrun(env: Optional[Mapping[str, str]] = None) -> bool:
    """True when every torchrun variable is set (this process is one rank of a distributed run)."""
    env = os.environ if env is None else env
    return all(k in env for k in TORCHRUN_VARIABLES)


def init_process_group() -> None:
    """Join the default process group of a torchrun launch (gloo backend, 30 min timeout)."""
    dist.init_process_group("gloo", timeout=datetime.timedelta(minutes=30))


def destroy_process_group() -> None:
    """Leave the process group (end of a torchrun launch)."""
    dist.destroy_process_group()


def rank_and_world(distributed: bool) -> Tuple[int, int]:
    """(rank, world size): (0, 1) unless ``distributed``.

    Raises:
        ValueError: ``distributed`` before the process group was initialised.
    """
    if not distributed:
        return 0, 1
    if not dist.is_available() or not dist.is_initialized():
        raise ValueError("train(distributed=True) needs torch.distributed.init_process_group() first")
    return dist.get_rank(), dist.get_world_size()


def wrap(objective: torch.nn.Module, has_edge_head: bool) -> torch.nn.Module:
    """``DistributedDataParallel`` around the training objective (it broadcasts rank 0's
    weights); an optional head (the edge head) is not used by every step."""
    return DistributedDataParallel(objective, find_unused_parameters=has_edge_head)


def all_reduce_sums(values: List[float]) -> List[float]:
    """Element-wise sums of ``values`` over every rank."""
    t = torch.tensor(values, dtype=torch.float64)
    dist.all_reduce(t, op=dist.ReduceOp.SUM)
    return t.tolist()


def barrier() -> None:
    """Wait until every rank gets here."""
    dist.barrier()
