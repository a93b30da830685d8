"""Tests of gcn_match_ros.plots: training curves, precision-recall, similarity figures and their inputs."""
import dataclasses
import json

import cv2
import numpy as np
import pytest
import torch

from gcn_match_ros import plots
from gcn_match_ros.evaluation import evaluate
from gcn_match_ros.graph import GraphConfig, build_graph
from gcn_match_ros.learn.model import GCN, GCNConfig, embed_problem
from gcn_match_ros.node_features import feature_dim
from gcn_match_ros.problem import Problem

from conftest import SMALL_GCN_LAYERS, permuted_views_problem, permuted_views_problem_with_attributes


@pytest.fixture(autouse=True, scope="module")
def _one_thread(one_torch_thread):
    """Tiny graphs: one intra-op thread is fastest and immune to a busy shared CPU."""


def assert_png(path):
    """``path`` is a non-empty PNG image that reads back as a colour picture."""
    assert path.is_file() and path.stat().st_size > 0
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    img = cv2.imread(str(path))
    assert img is not None and img.ndim == 3 and img.shape[0] > 50 and img.shape[1] > 50
    assert img.std() > 0  # something is drawn


def history(scale=1.0, val=True, best=True):
    """A training history as learn.train writes it: entries every step, validation every 2."""
    train = [{"step": s, "loss": scale / s, "recon": 0.5 * scale / s, "epipolar": 0.1 * scale / s}
             for s in range(1, 7)]
    h = {"train": train, "val": [{"step": s, "loss": 1.2 * scale / s, "recon": 0.6 * scale / s}
                                 for s in (2, 4, 6)] if val else []}
    if best:
        h["best"] = {"source": "val", "step": 6, "loss": 1.2 * scale / 6}
    return h


# ---------------------------------------------------------------------------
# Training curves
# ---------------------------------------------------------------------------
def test_plot_history_of_one_run_from_a_dict(tmp_path):
    out = plots.plot_history(history(), tmp_path / "sub" / "one.png")  # the folder is made
    assert out == tmp_path / "sub" / "one.png"
    assert_png(out)


def test_plot_history_of_several_runs_from_folders_files_and_dicts(tmp_path):
    run_a, run_b = tmp_path / "run_a", tmp_path / "run_b"
    for run, scale in ((run_a, 1.0), (run_b, 3.0)):
        run.mkdir()
        (run / "history.json").write_text(json.dumps(history(scale)))
    assert plots.load_history(run_a) == plots.load_history(run_a / "history.json") == history(1.0)
    out = plots.plot_history([run_a, run_b / "history.json", history(0.5, val=False, best=False)],
                             tmp_path / "three.png", labels=["a", "b", "c"], title="three runs")
    assert_png(out)
    # default labels (folder names), a term only some runs have, a linear axis forced
    assert_png(plots.plot_history([run_a, run_b], tmp_path / "two.png", terms=("recon", "edge"), log_y=False))
    # a loaded history gets the keys it lacks
    assert plots.load_history({"train": [{"step": 1, "loss": 1.0}]}) == {"train": [{"step": 1, "loss": 1.0}],
                                                                        "val": []}


def test_plot_history_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such history file"):
        plots.plot_history(tmp_path / "missing", tmp_path / "x.png")
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "history.json").write_text("{not json")
    with pytest.raises(ValueError, match="not a JSON history"):
        plots.plot_history(tmp_path / "bad", tmp_path / "x.png")
    with pytest.raises(ValueError, match="not a training history"):
        plots.load_history({"train": "oops"})
    with pytest.raises(ValueError, match="1 labels for 2 runs"):
        plots.plot_history([history(), history()], tmp_path / "x.png", labels=["only one"])
    nan_only = {"train": [{"step": 1, "loss": float("nan")}], "val": []}
    with pytest.raises(ValueError, match="no loss values"):
        plots.plot_history(nan_only, tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


# ---------------------------------------------------------------------------
# Precision-recall
# ---------------------------------------------------------------------------
def test_plot_pr_curves_of_an_evaluation(tmp_path):
    problems = [dataclasses.replace(permuted_views_problem(noise=0.8, seed=s), name=f"p{s}") for s in (0, 1)]
    report = evaluate(problems, ["nn", "spectral", "gcn"], progress=False)  # gcn refuses 16-D: no curve
    assert report["methods"]["gcn"]["pr"]["precision"] == []
    assert_png(plots.plot_pr_curves(report, tmp_path / "pr.png"))


# ---------------------------------------------------------------------------
# Similarity figures
# ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def embedded():
    """(problem, its embeddings by a tiny untrained GCN, its input graph)."""
    problem = permuted_views_problem_with_attributes(n_views=3, p=12, dim=16)
    torch.manual_seed(0)
    model = GCN(GCNConfig(in_dim=feature_dim(16), **SMALL_GCN_LAYERS))
    E, graph = embed_problem(model, problem)
    return problem, E, graph


def test_plot_similarity_of_embedded_keypoints(tmp_path, embedded):
    problem, E, graph = embedded
    assert E.shape == (problem.n_keypoints, 12)
    np.testing.assert_allclose(np.linalg.norm(E, axis=1), 1.0, atol=1e-5)
    assert_png(plots.plot_similarity(problem, E, graph, tmp_path / "sim.png"))
    # a subset of the keypoints, a title of one's own
    assert_png(plots.plot_similarity(problem, E, graph, tmp_path / "sim4.png", max_per_view=4, title="four"))


def test_plot_similarity_errors(tmp_path, embedded):
    problem, E, graph = embedded
    with pytest.raises(ValueError, match="has no gt_track"):
        plots.plot_similarity(dataclasses.replace(problem, gt_track=None), E, graph, tmp_path / "x.png")
    big = permuted_views_problem(n_views=3, n_points=600, dim=4)  # 1800 keypoints, all on tracks
    big_graph = build_graph(big, GraphConfig(k=1))
    with pytest.raises(ValueError, match="1800 keypoints are too many"):
        plots.plot_similarity(big, np.eye(big.n_keypoints, 4), big_graph, tmp_path / "x.png", max_per_view=600)
    assert not (tmp_path / "x.png").exists()


def test_plot_similarity_histograms(tmp_path, embedded):
    problem, E, _ = embedded
    other = permuted_views_problem_with_attributes(n_views=3, p=12, dim=16, seed=1)
    rng = np.random.default_rng(0)
    E2 = rng.normal(size=E.shape)
    E2 /= np.linalg.norm(E2, axis=1, keepdims=True)
    out = plots.plot_similarity_histograms({"model": [E, E2], "random": [E2, E]}, [problem, other],
                                           tmp_path / "hist.png")
    assert_png(out)
    with pytest.raises(ValueError, match="needs ground truth"):
        plots.plot_similarity_histograms({"model": [E]}, [dataclasses.replace(problem, gt_track=None)],
                                         tmp_path / "x.png")
    with pytest.raises(ValueError, match="no problem"):
        plots.plot_similarity_histograms({"model": []}, [], tmp_path / "x.png")


def crafted_problem(gt_per_view):
    gt = np.concatenate([np.asarray(g, np.int64) for g in gt_per_view])
    n = gt.size
    offsets = np.r_[0, np.cumsum([len(g) for g in gt_per_view])]
    return Problem(view_offsets=offsets, keypoints=np.zeros((n, 2), np.float32),
                   descriptors=np.ones((n, 4), np.float32), gt_track=gt, name="crafted")


def test_similarity_order_known_answer():
    # track 1 in all three views; 0 and 3 in views 0, 1; 5 in views 1, 2; -1 unmatched, -2 unlabelled
    problem = crafted_problem([[3, -1, 1, -2, 0], [0, 1, -2, 3, 5], [5, -1, 1]])
    rows, offsets = plots.similarity_order(problem)
    # per view: tracked keypoints by track id, then unmatched, then unlabelled ones
    assert rows.tolist() == [4, 2, 0, 1, 3, 5, 6, 8, 9, 7, 12, 10, 11]
    assert offsets.tolist() == [0, 5, 10, 13]
    # two tracks at most: the one seen in most views (1), then the lowest id (0); room for one other
    rows, offsets = plots.similarity_order(problem, max_per_view=2)
    assert rows.tolist() == [4, 2, 5, 6, 12, 11]
    assert offsets.tolist() == [0, 2, 4, 6]
    with pytest.raises(ValueError, match="no gt_track"):
        plots.similarity_order(dataclasses.replace(problem, gt_track=None))


def test_cross_view_similarities_known_answer():
    problem = crafted_problem([[0, 1, -2], [1, 0, -1]])
    e0, e1, e2 = np.eye(3)
    mid = (e0 + e1) / np.sqrt(2)
    E = np.stack([e0, e1, e2, e1, e0, mid])
    same, diff = plots.cross_view_similarities(E, problem)
    # view 0 rows {0, 1} (2 is unlabelled) x view 1 rows {3, 4, 5}: S = [[0, 1, .71], [1, 0, .71]]
    np.testing.assert_allclose(same, [1.0, 1.0])
    np.testing.assert_allclose(diff, [0.0, 1 / np.sqrt(2), 0.0, 1 / np.sqrt(2)])
    # a third view with only unlabelled keypoints adds nothing
    three = crafted_problem([[0, 1, -2], [1, 0, -1], [-2, -2]])
    same3, diff3 = plots.cross_view_similarities(np.vstack([E, [e0, e1]]), three)
    np.testing.assert_allclose(same3, same)
    np.testing.assert_allclose(diff3, diff)
    with pytest.raises(ValueError, match="no gt_track"):
        plots.cross_view_similarities(E, dataclasses.replace(problem, gt_track=None))
    empty_same, empty_diff = plots.cross_view_similarities(E[:3], crafted_problem([[0, 1, -2]]))
    assert empty_same.size == 0 and empty_diff.size == 0  # one view: no cross-view pairs


def test_plot_stage_times(tmp_path):
    windows = {"4 x 500": {"nn": {"similarity": 3.0, "graph": 4.0, "network": 0.0},
                           "gcn (stream)": {"similarity": 6.0, "graph": 9.0, "network": 6.0}},
               "8 x 500": {"nn": {"similarity": 12.0, "graph": 16.0, "network": 0.0}}}
    assert_png(plots.plot_stage_times(windows, tmp_path / "stages.png", title="per stage"))
    wall = {"4 x 500": {"nn": 7.0, "gcn (stream)": 14.0}, "8 x 500": {"nn": 28.0}}  # gcn: two threads
    assert_png(plots.plot_stage_times(windows, tmp_path / "stages_wall.png", wall=wall))


def test_plot_labels_against_geometry(tmp_path):
    points = {"gcn": (0.912, 0.846), "gcn@a482093": (0.403, 0.873), "no cameras": (float("nan"), 0.5)}
    assert_png(plots.plot_labels_against_geometry(points, tmp_path / "labels_geometry.png", title="SIFT"))
