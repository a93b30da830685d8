"""Data-parallel training with PyTorch's own launcher and engine (torchrun + DDP, gloo on CPU).

    torchrun --nproc_per_node=2 -m gcn_match_ros.train_ddp --train DATA... [--val DATA...] -o RUN_DIR \\
        [--steps N] [--batch B] [any other flag of `gcn-match train`, --resume included]

Every process runs :func:`train.run_from_args` with ``distributed=True``: the model is
wrapped in ``torch.nn.parallel.DistributedDataParallel`` (gradients averaged over the
ranks at every step), rank r trains on problems r, r + W, r + 2W, ... of the data stream
(:class:`train.ShardedSource`; ``--batch`` is per rank, the effective batch is B·W), and
only rank 0 validates, prints, shows the progress bar and writes ``checkpoint.pt``,
``best.pt``, ``history.json`` and the plots. ``--resume`` works as in a single process:
every rank loads the run's checkpoint and the stream continues where it stopped.

The process group uses the ``gloo`` backend (CPU) and the usual torchrun environment
(``RANK``, ``WORLD_SIZE``, ``MASTER_ADDR``, ``MASTER_PORT``); on one machine,
``--master_addr 127.0.0.1`` keeps all traffic on the loopback interface (set
``GLOO_SOCKET_IFNAME=lo`` too when the host name resolves to another interface). torchrun's
rendezvous store still *listens* on every interface at ``--master_port`` (torch has no
setting for its bind address): on a shared network, firewall that port.
"""
from __future__ import annotations

import datetime
import os
import sys
from typing import Optional, Sequence

__all__ = ["main"]


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Entry point of ``python -m gcn_match_ros.train_ddp`` under torchrun; returns the exit status."""
    from .cli import _UserError, build_parser

    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in ("-h", "--help"):
        build_parser().parse_args(["train", "--help"])
        return 0
    missing = [k for k in ("RANK", "WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT") if k not in os.environ]
    if missing:
        print(f"train_ddp: error: {', '.join(missing)} not set; start it with "
              f"'torchrun --nproc_per_node=N -m gcn_match_ros.train_ddp ...'", file=sys.stderr)
        return 2
    import torch.distributed as dist

    from .train import run_from_args
    dist.init_process_group("gloo", timeout=datetime.timedelta(minutes=30))
    rank = dist.get_rank()
    try:
        try:
            args = build_parser().parse_args(["train", *argv])
            return int(run_from_args(args, distributed=True) or 0)
        except (_UserError, ValueError, OSError, KeyError) as exc:
            if os.environ.get("GCN_MATCH_DEBUG"):
                raise
            print(f"train_ddp: error (rank {rank}): {exc}", file=sys.stderr)
            return 2
    finally:
        dist.destroy_process_group()


if __name__ == "__main__":
    sys.exit(main())
