"""Tests of gcn_match_ros.train: loss goes down, resume, atomic checkpoints, data sources."""
import json
import os

import numpy as np
import pytest
import torch

from gcn_match_ros.learn import checkpoint as checkpoint_mod
from gcn_match_ros.node_features import feature_dim
from gcn_match_ros.learn.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from gcn_match_ros.learn.model import GCN, GCNConfig
from gcn_match_ros.problem import Problem, save_problem
from gcn_match_ros.learn.config import TrainConfig
from gcn_match_ros.learn.objective import evaluate, make_batch, make_sample, train_step
from gcn_match_ros.learn.sources import ProblemFileSource, SyntheticSource
from gcn_match_ros.learn.train import train

D = 8
MODEL = GCNConfig(in_dim=feature_dim(D), widths=(16, 16, 16, 16), out_dim=16, groups=4, skip_layers=(2, 4))


@pytest.fixture(autouse=True, scope="module")
def _one_thread(one_torch_thread):
    """Tiny graphs: one intra-op thread is fastest and immune to a busy shared CPU."""


def _rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def posed_problem(rng, n_views=3, p=8, noise=0.3):
    """p scene points seen by every view in random order; descriptors = point descriptor + noise."""
    K = np.array([[400.0, 0, 320], [0, 400, 240], [0, 0, 1]])
    P = rng.uniform(-1, 1, size=(p, 3))
    base = rng.normal(size=(p, D))
    kps, desc, gt, Rs, ts = [], [], [], [], []
    for _ in range(n_views):
        R, t = _rotation(rng), np.array([0.0, 0.0, 5.0]) + 0.3 * rng.normal(size=3)
        perm = rng.permutation(p)
        x = (K @ (R @ P[perm].T + t[:, None])).T
        kps.append(x[:, :2] / x[:, 2:])
        desc.append(base[perm] + noise * rng.normal(size=(p, D)))
        gt.append(perm)
        Rs.append(R)
        ts.append(t)
    return Problem(view_offsets=np.arange(n_views + 1) * p, keypoints=np.concatenate(kps),
                   descriptors=np.concatenate(desc), K=np.stack([K] * n_views), R=np.stack(Rs),
                   t=np.stack(ts), image_size=np.tile([640, 480], (n_views, 1)), gt_track=np.concatenate(gt))


def test_sample_batch_and_step():
    rng = np.random.default_rng(0)
    samples = [make_sample(posed_problem(rng)), make_sample(posed_problem(rng, n_views=2, p=5))]
    assert samples[0].has_poses and samples[0].features.shape == (24, feature_dim(D))
    batch = make_batch(samples)
    assert batch.node_ptr.tolist() == [0, 24, 34]
    torch.manual_seed(0)
    model = GCN(MODEL)
    loss, logs = train_step(model, batch, TrainConfig())
    assert loss.requires_grad and set(logs) == {"loss", "recon", "epipolar", "edge"}
    assert logs["epipolar"] > 0 and np.isfinite(logs["loss"])
    assert np.isnan(logs["edge"])  # no edge head
    # at epipolar weight 0 the term is still logged but not part of the loss
    loss0, logs0 = train_step(model, batch, TrainConfig(epipolar_weight=0.0))
    assert logs0["epipolar"] == pytest.approx(logs["epipolar"])
    assert logs0["loss"] == pytest.approx(logs["recon"], rel=1e-5)
    loss.backward()
    ev = evaluate(model, samples, TrainConfig(batch_size=1))
    assert ev["loss"] == pytest.approx(logs["loss"], rel=1e-4)


def test_wrapped_gcn_with_edge_head_is_refused():
    import dataclasses

    from gcn_match_ros.edges.candidates import EDGE_FEATURES

    class Wrapper(torch.nn.Module):  # stands in for DistributedDataParallel(GCN)
        def __init__(self, module):
            super().__init__()
            self.module = module

        def forward(self, *args):
            return self.module(*args)

    batch = make_batch([make_sample(posed_problem(np.random.default_rng(1)))])
    edge_model = GCN(dataclasses.replace(MODEL, edge_features=len(EDGE_FEATURES), edge_hidden=8, edge_k=4))
    with pytest.raises(ValueError, match="wrap TrainingObjective"):
        train_step(Wrapper(edge_model), batch, TrainConfig(edge_weight=1.0))
    # without the edge term, or without a head, a wrapped GCN is fine
    assert np.isnan(train_step(Wrapper(edge_model), batch, TrainConfig(edge_weight=0.0))[1]["edge"])
    assert np.isfinite(train_step(Wrapper(GCN(MODEL)), batch, TrainConfig())[0].item())


def test_sources(tmp_path):
    rng = np.random.default_rng(1)
    for i in range(3):
        save_problem(posed_problem(rng), tmp_path / f"p{i}.npz")
    src = ProblemFileSource(tmp_path, shuffle=True, seed=3)
    seq = [p.name for p, _ in zip(src(), range(7))]
    assert sorted(seq[:3]) == ["p0", "p1", "p2"] and sorted(seq[3:6]) == ["p0", "p1", "p2"]
    assert [p.name for p, _ in zip(src(4), range(3))] == seq[4:7]  # seekable
    once = ProblemFileSource([tmp_path / "p1.npz", tmp_path / "p0.npz"], shuffle=False, cycle=False)
    assert [p.name for p in once()] == ["p1", "p0"]
    syn = SyntheticSource(posed_problem, seed=5)
    a = [p.keypoints for p, _ in zip(syn(), range(3))]
    b = next(syn(2)).keypoints
    assert np.array_equal(a[2], b)
    with pytest.raises(ValueError, match="no such file or directory"):
        ProblemFileSource(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no problem files"):
        ProblemFileSource(tmp_path / "empty")


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


def _failing_save(monkeypatch, should_fail):
    real = torch.save

    def fake(obj, f, *args, **kwargs):
        if should_fail(os.path.basename(f)):
            with open(f, "wb") as fh:
                fh.write(b"partial")  # a half-written file ...
            raise OSError("disk full")  # ... then the write fails
        return real(obj, f, *args, **kwargs)

    monkeypatch.setattr(checkpoint_mod.torch, "save", fake)


def test_checkpoint_write_is_atomic(tmp_path, monkeypatch):
    model = GCN(MODEL)
    path = tmp_path / "m.pt"
    save_checkpoint(path, model, extra={"step": 1})
    before = path.read_bytes()
    _failing_save(monkeypatch, lambda name: True)
    with pytest.raises(OSError, match="disk full"):
        save_checkpoint(path, model, extra={"step": 2})
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["m.pt"]
    with pytest.raises(OSError):
        save_checkpoint(tmp_path / "new.pt", model)
    assert [p.name for p in tmp_path.iterdir()] == ["m.pt"]
    monkeypatch.undo()
    assert load_checkpoint(path)[1]["extra"]["step"] == 1


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
