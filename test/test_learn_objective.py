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
    assert loss.requires_grad and set(logs) == {"loss", "recon", "epipolar", "edge", "distill"}
    assert logs["epipolar"] > 0 and np.isfinite(logs["loss"])
    assert np.isnan(logs["edge"]) and np.isnan(logs["distill"])  # no edge head, no teacher
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


def _edge_model(edge_k=4, seed=0):
    import dataclasses

    from gcn_match_ros.edges.candidates import EDGE_FEATURES

    torch.manual_seed(seed)
    return GCN(dataclasses.replace(MODEL, edge_features=len(EDGE_FEATURES), edge_hidden=8, edge_k=edge_k))


def test_distillation_from_the_model_itself_adds_its_entropy_and_no_gradient(tmp_path):
    """A student that scores exactly as its teacher sits at the distillation term's minimum:
    the term adds the teacher's mean binary entropy to the loss and nothing to the gradient."""
    from gcn_match_ros.learn.checkpoint import save_checkpoint

    batch = make_batch([make_sample(posed_problem(np.random.default_rng(2))),
                        make_sample(posed_problem(np.random.default_rng(3), n_views=2, p=5))])
    student = _edge_model()
    teacher = tmp_path / "teacher.pt"
    save_checkpoint(teacher, student, {"model": student.config.to_dict()})
    plain = TrainConfig(edge_weight=1.0)
    distilled = TrainConfig(edge_weight=1.0, distill_weight=2.0, teacher=str(teacher))

    loss, logs = train_step(student, batch, plain)
    grads = torch.autograd.grad(loss, list(student.parameters()), allow_unused=True)
    loss_d, logs_d = train_step(student, batch, distilled)
    grads_d = torch.autograd.grad(loss_d, list(student.parameters()), allow_unused=True)

    assert np.isnan(logs["distill"]) and 0 < logs_d["distill"] <= np.log(2) + 1e-6  # a mean binary entropy
    assert logs_d["loss"] == pytest.approx(logs["loss"] + 2.0 * logs_d["distill"], rel=1e-5)
    for g, g_d in zip(grads, grads_d):
        if g is not None:
            torch.testing.assert_close(g_d, g, rtol=1e-4, atol=1e-6)


def test_distillation_moves_the_student_towards_the_teacher(tmp_path):
    from gcn_match_ros.edges.head import edge_config_of
    from gcn_match_ros.learn.checkpoint import save_checkpoint
    from gcn_match_ros.learn.objective import edge_training_inputs

    problem = posed_problem(np.random.default_rng(4))
    batch = make_batch([make_sample(problem)])
    teacher = _edge_model(seed=1)
    path = tmp_path / "teacher.pt"
    save_checkpoint(path, teacher, {"model": teacher.config.to_dict()})
    student = _edge_model(seed=2)
    cfg = TrainConfig(edge_weight=0.0, recon_weight=0.0, epipolar_weight=0.0, distill_weight=1.0, teacher=str(path))
    es, _ = edge_training_inputs(problem, edge_config_of(student))
    args = [torch.from_numpy(a) for a in (es.rows, es.cols, es.features)]

    def gap():
        with torch.no_grad():
            s = torch.sigmoid(student.score_edges(student(batch.x, batch.edge_index, batch.edge_weight), *args))
            t = torch.sigmoid(teacher.score_edges(teacher(batch.x, batch.edge_index, batch.edge_weight), *args))
        return float((s - t).abs().mean())

    before = gap()
    opt = torch.optim.Adam(student.parameters(), lr=1e-2)
    for _ in range(60):
        opt.zero_grad()
        train_step(student, batch, cfg)[0].backward()
        opt.step()
    assert es.rows.shape[0] > 0 and gap() < 0.5 * before


def test_distillation_needs_a_matching_teacher(tmp_path):
    from gcn_match_ros.learn.checkpoint import save_checkpoint

    with pytest.raises(ValueError, match="needs a teacher"):
        TrainConfig(distill_weight=1.0)
    other = _edge_model(edge_k=3)
    path = tmp_path / "k3.pt"
    save_checkpoint(path, other, {"model": other.config.to_dict()})
    batch = make_batch([make_sample(posed_problem(np.random.default_rng(5)))])
    with pytest.raises(ValueError, match="same candidate edges"):
        train_step(_edge_model(), batch, TrainConfig(edge_weight=1.0, distill_weight=1.0, teacher=str(path)))
