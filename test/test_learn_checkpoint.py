"""Tests of gcn_match_ros.learn.checkpoint: round trip, refused files, atomic writes."""
import pytest
import torch

from gcn_match_ros.graph import GraphConfig
from gcn_match_ros.learn.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from gcn_match_ros.learn.model import GCN, GCNConfig
from gcn_match_ros.node_features import FeatureConfig

from conftest import (POSED_GCN as MODEL, SMALL_GCN_LAYERS as SMALL, failing_torch_save as _failing_save,
                      gcn_inputs as inputs, permuted_views_problem_with_attributes as permuted_problem)


@pytest.fixture(autouse=True, scope="module")
def _one_thread(one_torch_thread):
    """Tiny graphs: one intra-op thread is fastest and immune to a busy shared CPU."""


def test_checkpoint_round_trip(tmp_path):
    prob = permuted_problem()
    x, ei, ew, _ = inputs(prob)
    torch.manual_seed(1)
    model = GCN(GCNConfig(in_dim=x.shape[1], **SMALL)).eval()
    gcfg, fcfg = GraphConfig(k=3, mutual=True), FeatureConfig(orientation=False)
    path = tmp_path / "m.pt"
    save_checkpoint(path, model, {"graph": vars(gcfg).copy(), "features": fcfg.to_dict()}, {"step": 7})
    loaded, meta = load_checkpoint(path)
    assert not loaded.training
    assert meta["model_config"] == model.config
    assert meta["graph_config"] == gcfg and meta["feature_config"] == fcfg
    assert meta["extra"]["step"] == 7
    with torch.no_grad():
        assert torch.equal(loaded(x, ei, ew), model(x, ei, ew))
    assert [p.name for p in tmp_path.iterdir()] == ["m.pt"]  # no temp file left


def test_checkpoint_errors(tmp_path):
    model = GCN(GCNConfig(in_dim=20, **SMALL))
    with pytest.raises(CheckpointError, match="no such checkpoint file"):
        load_checkpoint(tmp_path / "missing.pt")
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"\x00not a checkpoint" * 10)
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        load_checkpoint(garbage)
    good = tmp_path / "good.pt"
    save_checkpoint(good, model)
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        load_checkpoint(truncated)
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(3)}, other)
    with pytest.raises(CheckpointError, match="not a gcn_match_ros/gcn-checkpoint file"):
        load_checkpoint(other)
    pickled = tmp_path / "pickled.pt"
    torch.save({"format": "gcn_match_ros/gcn-checkpoint", "obj": object()}, pickled)
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        load_checkpoint(pickled)  # refused by weights_only
    mismatch = tmp_path / "mismatch.pt"
    save_checkpoint(mismatch, model, {"model": GCNConfig(in_dim=20, widths=(8, 8), groups=4,
                                                         skip_layers=()).to_dict()})
    with pytest.raises(CheckpointError, match="weights do not fit"):
        load_checkpoint(mismatch)
    badcfg = tmp_path / "badcfg.pt"
    save_checkpoint(badcfg, model, {"graph": {"k": 0}})
    with pytest.raises(CheckpointError, match="invalid configuration"):
        load_checkpoint(badcfg)
    assert issubclass(CheckpointError, ValueError)


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
