"""Tests of gcn_match_ros.learn.objective: samples, batches and the loss of one training step."""
import numpy as np
import pytest
import torch

from gcn_match_ros.learn.config import TrainConfig
from gcn_match_ros.learn.model import GCN
from gcn_match_ros.learn.objective import evaluate, make_batch, make_sample, train_step
from gcn_match_ros.node_features import feature_dim

from conftest import POSED_DESCRIPTOR_DIM as D, POSED_GCN as MODEL, posed_problem


@pytest.fixture(autouse=True, scope="module")
def _one_thread(one_torch_thread):
    """Tiny graphs: one intra-op thread is fastest and immune to a busy shared CPU."""


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
