"""Tests of gcn_match_ros.learn.train: loss goes down, resume, failures while checkpointing."""
import json

import numpy as np
import pytest
import torch

from gcn_match_ros.learn.checkpoint import CheckpointError, load_checkpoint
from gcn_match_ros.learn.config import TrainConfig
from gcn_match_ros.learn.model import GCNConfig
from gcn_match_ros.learn.sources import ProblemFileSource, SyntheticSource
from gcn_match_ros.learn.train import train
from gcn_match_ros.problem import save_problem

from conftest import POSED_GCN as MODEL, failing_torch_save as _failing_save, posed_problem


@pytest.fixture(autouse=True, scope="module")
def _one_thread(one_torch_thread):
    """Tiny graphs: one intra-op thread is fastest and immune to a busy shared CPU."""


def test_training_reduces_loss_and_writes_files(tmp_path):
    rng = np.random.default_rng(2)
    for i in range(4):
        save_problem(posed_problem(rng), tmp_path / "data" / f"p{i}.npz")
    cfg = TrainConfig(lr=3e-3, steps=40, batch_size=2, val_every=20, val_size=2, checkpoint_every=20,
                      log_every=1, epipolar_weight=1.0, progress=True)
    hist = train(MODEL, ProblemFileSource(tmp_path / "data"), SyntheticSource(posed_problem, seed=9),
                 cfg, tmp_path / "run")
    losses = [h["loss"] for h in hist["train"]]
    assert [h["step"] for h in hist["train"]] == list(range(1, 41))
    assert np.mean(losses[-5:]) < 0.7 * np.mean(losses[:5]), (losses[:5], losses[-5:])
    assert [h["step"] for h in hist["val"]] == [20, 40]
    assert hist["val"][-1]["loss"] < hist["val"][0]["loss"] or hist["best"]["step"] == 20
    for name in ("checkpoint.pt", "best.pt", "history.json"):
        assert (tmp_path / "run" / name).is_file()
    assert json.loads((tmp_path / "run" / "history.json").read_text())["train"][-1]["step"] == 40
    model, meta = load_checkpoint(tmp_path / "run" / "best.pt")
    assert meta["graph_config"] == cfg.graph and meta["feature_config"] == cfg.features
    assert meta["config"]["train"]["steps"] == 40 and meta["extra"]["step"] == hist["best"]["step"]
    _, meta = load_checkpoint(tmp_path / "run" / "checkpoint.pt")
    assert meta["extra"]["step"] == 40 and "optimizer" in meta["extra"]
    assert not [p for p in (tmp_path / "run").iterdir() if p.name.endswith(".tmp")]


def _params(model):
    return {k: v.clone() for k, v in model.state_dict().items()}


def test_resume_continues_and_matches_uninterrupted(tmp_path):
    base = dict(lr=3e-3, batch_size=2, checkpoint_every=3, log_every=1, val_every=3, val_size=2,
                progress=False)
    src, val = SyntheticSource(posed_problem, seed=1), SyntheticSource(posed_problem, seed=2)
    full = train(MODEL, src, val, TrainConfig(steps=6, **base), tmp_path / "full")
    train(MODEL, src, val, TrainConfig(steps=3, **base), tmp_path / "split")
    hist = train(MODEL, src, val, TrainConfig(steps=6, **base), tmp_path / "split", resume=True)
    assert [h["step"] for h in hist["train"]] == [1, 2, 3, 4, 5, 6]
    assert [h["step"] for h in hist["val"]] == [3, 6]
    a, _ = load_checkpoint(tmp_path / "full" / "checkpoint.pt")
    b, meta = load_checkpoint(tmp_path / "split" / "checkpoint.pt")
    assert meta["extra"]["step"] == 6
    pa, pb = _params(a), _params(b)
    assert all(torch.allclose(pa[k], pb[k], rtol=0, atol=1e-6) for k in pa)
    for ha, hb in zip(full["train"], hist["train"]):
        assert ha["loss"] == pytest.approx(hb["loss"], rel=1e-5)
    # resuming a finished run does nothing; another architecture is refused
    again = train(MODEL, src, val, TrainConfig(steps=6, **base), tmp_path / "split", resume=True)
    assert [h["step"] for h in again["train"]] == [1, 2, 3, 4, 5, 6]
    other = GCNConfig(in_dim=MODEL.in_dim, widths=(8, 8), groups=4, skip_layers=())
    with pytest.raises(ValueError, match="resume"):
        train(other, src, val, TrainConfig(steps=6, **base), tmp_path / "split", resume=True)


def test_training_failure_during_checkpoint_leaves_previous(tmp_path, monkeypatch):
    calls = {"n": 0}

    def fail_second_checkpoint(name):
        if name.startswith(".checkpoint.pt."):
            calls["n"] += 1
            return calls["n"] >= 2
        return False

    _failing_save(monkeypatch, fail_second_checkpoint)
    cfg = TrainConfig(steps=4, batch_size=1, checkpoint_every=2, progress=False)
    with pytest.raises(OSError, match="disk full"):
        train(MODEL, SyntheticSource(posed_problem), None, cfg, tmp_path)
    monkeypatch.undo()
    _, meta = load_checkpoint(tmp_path / "checkpoint.pt")
    assert meta["extra"]["step"] == 2
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    # and training resumes from there
    hist = train(MODEL, SyntheticSource(posed_problem), None, cfg, tmp_path, resume=True)
    assert [h["step"] for h in hist["train"]][-1] == 4


def test_feature_dim_mismatch_is_explained(tmp_path):
    bad = GCNConfig(in_dim=99, widths=(8, 8), groups=4, skip_layers=())
    with pytest.raises(ValueError, match=r"in_dim=99.*feature_dim\(8, features\) = 12"):
        train(bad, SyntheticSource(posed_problem), None, TrainConfig(steps=1, progress=False), tmp_path)


def test_corrupt_resume_checkpoint_raises(tmp_path):
    (tmp_path / "checkpoint.pt").write_bytes(b"garbage")
    with pytest.raises(CheckpointError):
        train(MODEL, SyntheticSource(posed_problem), None, TrainConfig(steps=1, progress=False), tmp_path,
              resume=True)
