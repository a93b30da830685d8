"""Tests of gcn_match_ros.learn.ddp: data-parallel training (gloo on CPU, loopback only), resume, torchrun CLI."""
import dataclasses
import functools
import json
import os
import socket
import subprocess
import sys
from itertools import islice
from pathlib import Path

import numpy as np
import pytest
import torch

from gcn_match_ros.data import synthetic
from gcn_match_ros.node_features import feature_dim
from gcn_match_ros.learn.checkpoint import load_checkpoint
from gcn_match_ros.learn.model import GCN, GCNConfig
from gcn_match_ros.edges.candidates import EDGE_FEATURES
from gcn_match_ros.learn.config import TrainConfig
from gcn_match_ros.learn.objective import TrainingObjective, make_batch, make_sample, train_step
from gcn_match_ros.learn.sources import ShardedSource, SyntheticSource
from gcn_match_ros.learn.train import train

D = 16
MODEL = GCNConfig(in_dim=feature_dim(D), widths=(16, 16, 16, 16), out_dim=16, groups=4, skip_layers=(2, 4))
SCENE = synthetic.rome16k(3, n_points=12, descriptor_dim=D, descriptor_noise=1.0)
B = 2  # graphs per rank
# with the edge head of the shipped models (it scores edges outside GCN.forward)
EDGE_MODEL = dataclasses.replace(MODEL, edge_features=len(EDGE_FEATURES), edge_hidden=16, edge_k=4)
EDGE_TRAIN = TrainConfig(epipolar_weight=1.0, edge_weight=1.0)
TRAIN = dict(lr=3e-3, checkpoint_every=2, log_every=1, val_every=2, val_size=2, epipolar_weight=1.0,
             progress=False, plot=False)
REPO = Path(__file__).resolve().parents[1]


def _sources():
    gen = functools.partial(synthetic.random_scene_problem, SCENE)
    return SyntheticSource(gen, seed=3), SyntheticSource(gen, seed=4)


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _worker(rank: int, world: int, tmp: str) -> None:
    import torch.distributed as dist
    from torch.nn.parallel import DistributedDataParallel

    torch.set_num_threads(1)
    # a file store: rendezvous without a listening socket (a TCP store listens on every interface)
    dist.init_process_group("gloo", init_method=f"file://{tmp}/store", rank=rank, world_size=world)
    try:
        tmp = Path(tmp)
        src, val = _sources()
        torch.manual_seed(0)
        model = GCN(MODEL)
        ddp = DistributedDataParallel(model)
        samples = [make_sample(p) for p in islice(ShardedSource(src, rank, world)(0), B)]
        loss, _ = train_step(ddp, make_batch(samples), TrainConfig(epipolar_weight=1.0))
        loss.backward()
        torch.save({k: p.grad.clone() for k, p in model.named_parameters()}, tmp / f"grads{rank}.pt")
        torch.manual_seed(0)
        edge_model = GCN(EDGE_MODEL)
        objective = DistributedDataParallel(TrainingObjective(edge_model, EDGE_TRAIN), find_unused_parameters=True)
        loss, _ = train_step(objective, make_batch(samples), EDGE_TRAIN)
        loss.backward()
        torch.save({k: p.grad.clone() for k, p in edge_model.named_parameters()}, tmp / f"edge_grads{rank}.pt")
        # training: 6 steps at once, and 4 steps + resume to 6
        train(MODEL, src, val, TrainConfig(steps=6, batch_size=1, **TRAIN), tmp / "full", distributed=True)
        train(MODEL, src, val, TrainConfig(steps=4, batch_size=1, **TRAIN), tmp / "split", distributed=True)
        hist = train(MODEL, src, val, TrainConfig(steps=6, batch_size=1, **TRAIN), tmp / "split", resume=True,
                     distributed=True)
        (tmp / f"hist{rank}.json").write_text(json.dumps(hist))
    finally:
        dist.destroy_process_group()


@pytest.fixture(autouse=True)
def _loopback(monkeypatch):
    monkeypatch.setenv("GLOO_SOCKET_IFNAME", "lo")  # gloo's transport on loopback only
    monkeypatch.setenv("MASTER_ADDR", "127.0.0.1")
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _params(path):
    return dict(load_checkpoint(path)[0].state_dict())


def test_ddp_gradients_and_training_match_single_process(tmp_path):
    import torch.multiprocessing as mp

    mp.spawn(_worker, args=(2, str(tmp_path)), nprocs=2, join=True)

    # one process over the union of the two shards (problems 0..2B-1 of the stream)
    src, val = _sources()
    torch.manual_seed(0)
    model = GCN(MODEL)
    samples = [make_sample(p) for p in islice(src(0), 2 * B)]
    loss, _ = train_step(model, make_batch(samples), TrainConfig(epipolar_weight=1.0))
    loss.backward()
    ref = {k: p.grad for k, p in model.named_parameters()}
    for rank in (0, 1):
        got = torch.load(tmp_path / f"grads{rank}.pt")
        for k in ref:
            torch.testing.assert_close(got[k], ref[k], rtol=1e-4, atol=1e-5, msg=f"rank {rank} {k}")
    torch.manual_seed(0)
    edge_model = GCN(EDGE_MODEL)
    loss, logs = train_step(edge_model, make_batch(samples), EDGE_TRAIN)
    assert np.isfinite(logs["edge"])
    loss.backward()
    ref = {k: p.grad for k, p in edge_model.named_parameters()}
    assert any(k.startswith("edge_head") for k in ref)
    for rank in (0, 1):
        got = torch.load(tmp_path / f"edge_grads{rank}.pt")
        for k in ref:
            torch.testing.assert_close(got[k], ref[k], rtol=1e-4, atol=1e-5, msg=f"edge model, rank {rank} {k}")

    # DDP with batch 1 per rank trains exactly like one process with batch 2
    single = train(MODEL, src, val, TrainConfig(steps=6, batch_size=2, **TRAIN), tmp_path / "single")
    full = _params(tmp_path / "full" / "checkpoint.pt")
    for k, v in _params(tmp_path / "single" / "checkpoint.pt").items():
        torch.testing.assert_close(full[k], v, rtol=1e-4, atol=1e-5, msg=k)
    full_hist = json.loads((tmp_path / "full" / "history.json").read_text())
    np.testing.assert_allclose([h["loss"] for h in full_hist["train"]], [h["loss"] for h in single["train"]],
                               rtol=1e-4)
    assert [h["step"] for h in full_hist["val"]] == [2, 4, 6]

    # resume: history continues at step 5, the weights equal the uninterrupted run's
    hist0 = json.loads((tmp_path / "hist0.json").read_text())
    assert [h["step"] for h in hist0["train"]] == [1, 2, 3, 4, 5, 6]
    assert [h["step"] for h in hist0["val"]] == [2, 4, 6]
    split = _params(tmp_path / "split" / "checkpoint.pt")
    for k, v in full.items():
        torch.testing.assert_close(split[k], v, rtol=1e-4, atol=1e-5, msg=k)
    assert load_checkpoint(tmp_path / "split" / "checkpoint.pt")[1]["extra"]["step"] == 6
    # only rank 0 validates; both ranks log the same (all-reduced) training losses
    hist1 = json.loads((tmp_path / "hist1.json").read_text())
    assert hist1["val"] == [] or [h["step"] for h in hist1["val"]] == [2, 4]  # rank 1 reads rank 0's file on resume
    np.testing.assert_allclose([h["loss"] for h in hist1["train"]][4:], [h["loss"] for h in hist0["train"]][4:])
    assert sorted(p.name for p in (tmp_path / "split").iterdir()) == ["best.pt", "checkpoint.pt", "history.json"]


def test_torchrun_cli(tmp_path):
    cfg = tmp_path / "model.json"
    cfg.write_text(json.dumps({"widths": [16, 16, 16, 16], "out_dim": 16, "groups": 4, "skip_layers": [2, 4]}))
    run = tmp_path / "run"
    env = dict(os.environ, OMP_NUM_THREADS="1", GLOO_SOCKET_IFNAME="lo", PYTHONPATH=str(REPO))
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nnodes=1", "--nproc_per_node=2",
           "--master_addr=127.0.0.1", f"--master_port={_free_port()}",
           f"--log-dir={tmp_path / 'torchrun'}",  # else torchrun leaves a torchelastic_* directory in /tmp
           "-m", "gcn_match_ros.cli", "train",
           "--train", "synth:easy:3", "-o", str(run), "--steps", "3", "--batch", "1", "--model-config", str(cfg)]
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.count("checkpoints:") == 1 and "x 2 ranks" in proc.stdout  # rank 0 prints
    for name in ("checkpoint.pt", "best.pt", "history.json", "curves.png"):
        assert (run / name).is_file(), name
    assert [h["step"] for h in json.loads((run / "history.json").read_text())["train"]] == [1, 2, 3]
