"""Tests of gcn_match_ros.solvers.gcn: the shipped models load safely, pick by descriptor, beat nn held out."""
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from gcn_match_ros.metrics import score_result
from gcn_match_ros.learn.checkpoint import load_checkpoint
from gcn_match_ros.problem import load_problem
from gcn_match_ros.rounding import is_cycle_consistent
from gcn_match_ros import solvers
from gcn_match_ros.solvers.gcn import SHIPPED_MODELS

from conftest import needs_two_cpus

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

# Oxford is never trained on (no poses): a held-out problem.
HELD_OUT = Path(__file__).resolve().parents[2] / "shared" / "reference" / "oxford-dev" / "problems" / \
    "oxford_boat_sift_123.npz"


@pytest.mark.parametrize("kind", sorted(SHIPPED_MODELS))
def test_shipped_models_load_weights_only(kind):
    descriptor_dim, _ = kind
    path = SHIPPED_MODELS[kind]
    assert path.is_file()
    assert path.stat().st_size < 10 * 2 ** 20
    payload = torch.load(path, map_location="cpu", weights_only=True)
    assert payload["format"] == "gcn_match_ros/gcn-checkpoint"
    model, meta = load_checkpoint(path)
    assert getattr(model, "edge_head", None) is not None
    # the model takes exactly this descriptor dimension (+ x, y, scale, orientation)
    assert model.config.in_dim == descriptor_dim + 4
    assert 0.0 < meta["config"]["solver"]["threshold"] < 1.0


def test_gcn_picks_the_shipped_model_by_descriptor_and_beats_nn_on_held_out_orb(one_torch_thread):
    from gcn_match_ros.data.convert import make_problem
    from gcn_match_ros.data.scenes import load_scene

    scene = load_scene(DATA, "oxford/graf")  # Oxford: never trained on
    orb = make_problem(scene, (0, 1, 2), "orb", 500)
    sift = load_problem(HELD_OUT)
    solver = solvers.create("gcn")  # one solver instance serves both descriptor types
    r_orb = solver.solve(orb)
    assert solver.checkpoint_path == str(SHIPPED_MODELS[(256, True)])
    r_sift = solver.solve(sift)
    assert solver.checkpoint_path == str(SHIPPED_MODELS[(128, False)])
    assert score_result(orb, r_orb)["F1"] > score_result(orb, solvers.create("nn").solve(orb))["F1"] + 0.02
    assert is_cycle_consistent(r_orb.track, orb.view_index)
    assert r_sift.track.shape == (sift.n_keypoints,)
    # an explicit checkpoint is never switched, and a wrong descriptor dimension is a clear error
    fixed = solvers.create(f"gcn:checkpoint={SHIPPED_MODELS[(128, False)]}")
    with pytest.raises(ValueError, match="takes 128-dimensional descriptors, this window has 256-bit binary"):
        fixed.solve(orb)
    assert fixed.checkpoint_path == str(SHIPPED_MODELS[(128, False)])
    # descriptors no shipped model was trained for are refused, not matched by the wrong model:
    # 256-D real-valued (a learned descriptor) and 128-bit binary (BRIEF-16)
    rng = np.random.default_rng(0)
    learned = dataclasses.replace(orb, descriptors=rng.normal(size=orb.descriptors.shape).astype(np.float32))
    with pytest.raises(ValueError, match="256-D real-valued"):
        solver.solve(learned)
    brief = dataclasses.replace(orb, descriptors=orb.descriptors[:, :128].copy())
    with pytest.raises(ValueError, match="128-bit binary"):
        solver.solve(brief)


def test_shipped_model_beats_nn_on_held_out_and_is_cycle_consistent():
    torch.set_num_threads(1)
    problem = load_problem(HELD_OUT)
    gcn = solvers.create("gcn").solve(problem)
    nn = solvers.create("nn").solve(problem)
    f_gcn, f_nn = score_result(problem, gcn)["F1"], score_result(problem, nn)["F1"]
    assert f_gcn > f_nn + 0.02, (f_gcn, f_nn)
    assert is_cycle_consistent(gcn.track, problem.view_index)
    # at most one keypoint per view in every track
    t = gcn.track
    keep = t >= 0
    pairs = np.stack([t[keep], problem.view_index[keep]], 1)
    assert np.unique(pairs, axis=0).shape[0] == pairs.shape[0]


@pytest.mark.parametrize("preset", ["rome16k", "partial"])
def test_shipped_model_beats_mutual_nn_on_generated_scenes(one_torch_thread, preset):
    """Mean F1 and precision over three generated scenes with seeds no training stream used
    (training: [0, k]), at the shipped threshold (chosen for geometric precision)."""
    from gcn_match_ros.data import synthetic

    gcn, nn = [], []
    for seed in range(3):
        problem = synthetic.random_scene_problem(getattr(synthetic, preset)(3), np.random.default_rng([11, seed]))
        gcn.append(score_result(problem, solvers.create("gcn").solve(problem)))
        nn.append(score_result(problem, solvers.create("nn:graph=mutual").solve(problem)))
    f_gcn, f_nn = np.mean([s["F1"] for s in gcn]), np.mean([s["F1"] for s in nn])
    assert f_gcn > f_nn + 0.02, (f_gcn, f_nn)
    assert np.mean([s["P"] for s in gcn]) > np.mean([s["P"] for s in nn]) + 0.05


def test_threshold_follows_the_model_unless_set():
    solver = solvers.create("gcn")
    sift_t = load_checkpoint(SHIPPED_MODELS[(128, False)])[1]["config"]["solver"]["threshold"]
    orb_t = load_checkpoint(SHIPPED_MODELS[(256, True)])[1]["config"]["solver"]["threshold"]
    assert solver.threshold == sift_t and solver.describe() == "gcn:model=shipped"
    solver._use(str(SHIPPED_MODELS[(256, True)]))
    assert solver.threshold == orb_t and solver.describe() == "gcn:model=shipped"
    fixed = solvers.create("gcn:threshold=0.45")
    fixed._use(str(SHIPPED_MODELS[(256, True)]))
    assert fixed.threshold == 0.45


def test_planar_threshold_follows_the_model_unless_a_threshold_is_set():
    """The shipped models store their validation-F1 threshold for one-plane windows next to the
    precision-first one (models/README.md); a threshold set by hand applies to every window."""
    stored = {kind: load_checkpoint(SHIPPED_MODELS[kind])[1]["config"]["solver"]
              for kind in ((128, False), (256, True))}
    assert all(s["planar_threshold"] < s["threshold"] for s in stored.values())
    solver = solvers.create("gcn")
    assert solver.planar_threshold == stored[(128, False)]["planar_threshold"]
    solver._use(str(SHIPPED_MODELS[(256, True)]))
    assert solver.planar_threshold == stored[(256, True)]["planar_threshold"]
    assert solvers.create("gcn:threshold=0.45").planar_threshold == 0.45
    assert solvers.create("gcn:threshold=0.45,planar_threshold=0.1").planar_threshold == 0.1
    with pytest.raises(ValueError, match="planar_threshold"):
        solvers.create("gcn:planar_threshold=1.5")


def test_chained_models_follow_the_model_unless_set():
    """The shipped ORB model verifies with chained models, the SIFT model without (models/README.md)."""
    solver = solvers.create("gcn")
    assert solver.chained_models is False
    solver._use(str(SHIPPED_MODELS[(256, True)]))
    assert solver.chained_models is True
    off = solvers.create("gcn:chained_models=false")
    off._use(str(SHIPPED_MODELS[(256, True)]))
    assert off.chained_models is False
    assert solvers.create("gcn:chained_models=true").chained_models is True


def test_planar_ratio_follows_the_model_unless_set():
    """The shipped ORB model stores a lower H-vs-F ratio (its noisy seeds of a plane make F
    degenerate, models/README.md); the SIFT model keeps verify.PLANAR_RATIO. The candidate edges
    are fitted with the ratio the solver resolves."""
    from gcn_match_ros.edges.verify import PLANAR_RATIO

    solver = solvers.create("gcn")
    assert "planar_ratio" not in load_checkpoint(SHIPPED_MODELS[(128, False)])[1]["config"]["solver"]
    assert solver.planar_ratio == PLANAR_RATIO and solver.edge_config.planar_ratio == PLANAR_RATIO
    solver._use(str(SHIPPED_MODELS[(256, True)]))
    stored = load_checkpoint(SHIPPED_MODELS[(256, True)])[1]["config"]["solver"]["planar_ratio"]
    assert stored < PLANAR_RATIO and solver.planar_ratio == stored and solver.edge_config.planar_ratio == stored
    assert solvers.create("gcn:planar_ratio=0.9").edge_config.planar_ratio == 0.9
    with pytest.raises(ValueError, match="planar_ratio"):
        solvers.create("gcn:planar_ratio=0")


def test_noise_scaled_residuals_follow_the_model_unless_set():
    """The shipped SIFT model takes the residual features of pairs without sub-pixel keypoints in
    units of their noise, the ORB model in pixels (models/README.md); the candidate edges are
    computed as the solver resolves it."""
    solver = solvers.create("gcn")
    assert solver.noise_scaled_residuals is True and solver.edge_config.noise_scaled_residuals is True
    solver._use(str(SHIPPED_MODELS[(256, True)]))
    assert solver.noise_scaled_residuals is False and solver.edge_config.noise_scaled_residuals is False
    off = solvers.create("gcn:noise_scaled_residuals=false")
    assert off.edge_config.noise_scaled_residuals is False


def test_untrusted_models_guide_candidates_only_when_asked(monkeypatch, one_torch_thread):
    """trusted_candidates=false (the recall-first operating point, config/recall.yaml): a view pair
    whose fitted model is not trusted (generated partial visibility: views 0 and 1 share few
    points) gets guided candidates and geometric features from it; the other view pairs' candidates
    are unchanged. With the verification, which checks against trusted models only, it is refused."""
    import gcn_match_ros.solvers.gcn as gcn_module
    from gcn_match_ros.data import synthetic
    from gcn_match_ros.edges.candidates import EDGE_FEATURES

    with pytest.raises(ValueError, match="needs verify=false"):
        solvers.create("gcn:trusted_candidates=false")
    problem = synthetic.random_scene_problem(synthetic.preset("partial", 4, "sift"), rng=0)
    edges = []
    real = gcn_module.edge_probabilities
    monkeypatch.setattr(gcn_module, "edge_probabilities",
                        lambda model, emb, es, **kw: edges.append(es) or real(model, emb, es, **kw))
    trusted_solver = solvers.create("gcn:verify=false")
    any_solver = solvers.create("gcn:verify=false,trusted_candidates=false")
    assert trusted_solver.edge_config.min_inliers > 0  # the shipped model's trust rule
    assert any_solver.edge_config == dataclasses.replace(trusted_solver.edge_config, min_inliers=0, min_inlier_ratio=0.0)
    trusted_solver.solve(problem)
    any_solver.solve(problem)
    trusted, anything = edges
    assert trusted.models[(0, 1)] is None and anything.models[(0, 1)] is not None
    assert not anything.models[(0, 1)].trusted()
    guided = EDGE_FEATURES.index("guided")
    view = problem.view_index

    def on_pair(es, a, b):
        return (view[es.rows] == a) & (view[es.cols] == b)

    assert trusted.features[on_pair(trusted, 0, 1), guided].sum() == 0
    assert anything.features[on_pair(anything, 0, 1), guided].sum() > 0
    for pair, model in trusted.models.items():
        if model is not None:
            np.testing.assert_array_equal(trusted.rows[on_pair(trusted, *pair)], anything.rows[on_pair(anything, *pair)])


def test_graph_normalization_follows_the_model_unless_set():
    """The shipped models build their graph from the candidate edges' RootSIFT similarities
    (models/README.md), a checkpoint without that choice from the graph it was trained on."""
    solver = solvers.create("gcn")
    assert solver.meta["graph_config"].normalization == "l2"  # what it was trained with
    assert solver.graph_config.normalization == solver.edge_config.normalization == "rootsift"
    assert solvers.create("gcn:graph_normalization=l2").graph_config.normalization == "l2"
    assert solvers.create("gcn:graph=knn8,graph_normalization=l2").graph_config.k == 8
    with pytest.raises(ValueError, match="graph_normalization"):
        solvers.create("gcn:graph_normalization=hellinger")


def test_graph_and_candidate_edges_share_each_view_pairs_best_lists(monkeypatch, one_torch_thread):
    """With one normalization, each view pair's block and best lists are computed once (its
    top-11 serves the graph's top-4), and the solve is the one of lists computed apart."""
    import gcn_match_ros.similarity as similarity
    from gcn_match_ros.data import synthetic

    problem = synthetic.random_scene_problem(synthetic.rome16k(4, n_points=120), rng=3)
    shared = solvers.create("gcn").solve(problem)
    calls = []
    real = similarity.most_similar
    monkeypatch.setattr(similarity, "most_similar", lambda s, kr, kc: calls.append((kr, kc)) or real(s, kr, kc))
    solvers.create("gcn").solve(problem)
    assert calls == [(11, 11)] * 6  # 4 views: 6 view pairs, one list each
    monkeypatch.setattr(similarity.DescriptorSimilarity, "most_similar",
                        lambda self, i, j, norm, kr, kc: real(self.block(i, j, norm).numpy(), kr, kc))
    apart = solvers.create("gcn").solve(problem)
    for a, b in ((shared.track, apart.track), (shared.pair_rows, apart.pair_rows),
                 (shared.pair_scores, apart.pair_scores)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("spec, kind", [("gcn", "sift"), ("gcn:parallel=false", "binary")])
def test_pairs_verification_drops_whatever_their_score_are_not_scored(monkeypatch, one_torch_thread, spec, kind):
    """The edge head scores only the candidates that verification may keep
    (edges.consistency.may_keep): most of a window's candidates disagree with their view pair's
    trusted model. The published pairs and tracks are those of scoring every candidate (SIFT;
    ORB, whose model also chains models for unverified view pairs)."""
    import gcn_match_ros.solvers.gcn as gcn_module
    from gcn_match_ros.data import synthetic

    problem = synthetic.random_scene_problem(synthetic.preset("rome16k", 4, kind), rng=2)
    scored = []
    real = gcn_module.edge_probabilities
    monkeypatch.setattr(gcn_module, "edge_probabilities",
                        lambda model, emb, es, **kw: scored.append(es.rows.shape[0]) or real(model, emb, es, **kw))
    fewer = solvers.create(spec).solve(problem)
    monkeypatch.setattr(gcn_module, "may_keep", lambda model, checkable, res_h, res_f: np.ones(res_h.shape[0], bool))
    every = solvers.create(spec).solve(problem)
    assert scored[0] < 0.5 * scored[1]
    np.testing.assert_array_equal(fewer.track, every.track)
    np.testing.assert_array_equal(fewer.pair_rows, every.pair_rows)
    np.testing.assert_array_equal(fewer.pair_cols, every.pair_cols)
    # the head's matrix products round a row by its place in a chunk: within a float32 ulp
    np.testing.assert_allclose(fewer.pair_scores, every.pair_scores, rtol=0, atol=1e-6)
    assert fewer.pair_rows.size > 0


@pytest.mark.parametrize("descriptor", ["sift", "binary"])
def test_low_texture_window_keeps_the_descriptor_matches(one_torch_thread, descriptor):
    """Views of 8 keypoints: too few for geometric verification (MIN_SEEDS), and the edge head,
    trained on verifiable pairs, scores every edge low. The gcn solver then also keeps nn's
    matches on those view pairs, so it scores as nn does instead of matching nothing."""
    from gcn_match_ros.data import synthetic
    from gcn_match_ros.edges.verify import MIN_SEEDS

    config = dataclasses.replace(synthetic.preset("easy", 3, descriptor), n_points=8)
    f = {"gcn": [], "gcn:descriptor_fallback=false": [], "nn": []}
    for seed in range(3):
        problem = synthetic.random_scene_problem(config, np.random.default_rng([12, seed]))
        assert problem.view_sizes.max() < MIN_SEEDS
        for spec in f:
            result = solvers.create(spec).solve(problem)
            assert is_cycle_consistent(result.track, problem.view_index)
            f[spec].append(score_result(problem, result)["F1"])
    assert np.mean(f["nn"]) > 0.1, f  # descriptors alone find some of the true pairs
    assert np.mean(f["gcn"]) >= np.mean(f["nn"]) - 1e-9, f
    assert max(f["gcn:descriptor_fallback=false"]) < 0.1, f  # the head alone: (almost) nothing


def test_descriptor_fallback_leaves_normal_windows_alone(one_torch_thread):
    """No view below MIN_SEEDS keypoints: the fallback changes nothing (the benchmark tables hold)."""
    problem = load_problem(HELD_OUT)
    a, b = solvers.create("gcn").solve(problem), solvers.create("gcn:descriptor_fallback=false").solve(problem)
    np.testing.assert_array_equal(a.track, b.track)
    np.testing.assert_array_equal(a.pair_scores, b.pair_scores)


def test_device_setting_is_checked_before_any_model_is_loaded():
    with pytest.raises(ValueError, match="device"):
        solvers.create("gcn:device=tpu-please")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="sees no CUDA device"):
            solvers.create("gcn:device=cuda")
    else:  # a GPU machine: the forward pass runs there and scores like the CPU's (float order differs)
        problem = load_problem(HELD_OUT)
        cpu, gpu = (score_result(problem, solvers.create(f"gcn:device={d}").solve(problem))["F1"]
                    for d in ("cpu", "cuda"))
        assert abs(cpu - gpu) < 0.005


@pytest.mark.parametrize("default, bad, error, off, strict", [
    (dict(epipolar_ratio=0.9), "epipolar_ratio=-1", "epipolar_ratio", "epipolar_ratio=0",
     "epipolar_ratio=0.5,neighbours=0"),
    (dict(neighbours=8, min_shared_neighbours=2), "neighbours=4,min_shared_neighbours=5", "neighbourhood",
     "neighbours=0", "epipolar_ratio=0,neighbours=8,min_shared_neighbours=8"),
])
def test_rules_against_repetitions_only_remove_pairs_and_leave_weak_descriptors_alone(one_torch_thread, default, bad,
                                                                                      error, off, strict):
    """The ambiguity rule (Lowe's ratio along the epipolar line) and the neighbourhood rule, both
    on by default, drop pairs before the tracks are merged: what each publishes is a subset of
    the pairs published without it. Generated scenes' weak descriptors (true-match cosine ~0.66)
    are below the cosine they judge: the default solves them exactly as with the rule off. Sharp
    descriptors and a strict setting are judged; bad settings are refused."""
    from gcn_match_ros.data import synthetic

    config = solvers.create("gcn").config
    assert {k: getattr(config, k) for k in default} == default
    with pytest.raises(ValueError, match=error):
        solvers.create(f"gcn:{bad}")
    problem = synthetic.random_scene_problem(synthetic.rome16k(3), np.random.default_rng([11, 0]))
    without = solvers.create(f"gcn:{off}").solve(problem)
    with_default = solvers.create("gcn").solve(problem)
    np.testing.assert_array_equal(with_default.track, without.track)
    np.testing.assert_array_equal(with_default.pair_rows, without.pair_rows)
    # strict: the other rule off, as what one drops changes what the other judges
    sharp = synthetic.random_scene_problem(synthetic.rome16k(3, descriptor_noise=0.3), np.random.default_rng([11, 0]))
    plain = solvers.create("gcn:epipolar_ratio=0,neighbours=0").solve(sharp)
    judged = solvers.create(f"gcn:{strict}").solve(sharp)
    n = sharp.n_keypoints
    assert set((judged.pair_rows * n + judged.pair_cols).tolist()) < set((plain.pair_rows * n + plain.pair_cols).tolist())
    assert is_cycle_consistent(judged.track, sharp.view_index)


def test_epipolar_fit_follows_the_keypoints_localisation(one_torch_thread):
    """By default each view pair's epipolar model is fitted at epipolar_fine_px (0.5 px) where its
    seeds show sub-pixel keypoints and at epipolar_fit_px (2 px, the shipped models' training
    value) otherwise: on a window of precisely localised keypoints (0.1 px noise) it matches as
    well as the fixed 0.5 px fit; on keypoints with 1 px of noise exactly as without the fine
    fit, where the fixed 0.5 px fit loses its models and most of its matches."""
    from gcn_match_ros.data import synthetic
    from gcn_match_ros.edges.candidates import candidate_edges
    from gcn_match_ros.edges.verify import EPIPOLAR_PX, FINE_PX

    default = solvers.create("gcn")
    assert (default.edge_config.epipolar_px, default.edge_config.fine_px) == (EPIPOLAR_PX, FINE_PX)
    assert solvers.create("gcn:epipolar_fit_px=0.5").edge_config.epipolar_px == 0.5
    for bad in ("gcn:epipolar_fit_px=0", "gcn:epipolar_fine_px=-1"):
        with pytest.raises(ValueError, match="epipolar_fi"):
            solvers.create(bad)
    specs = ("gcn", "gcn:epipolar_fine_px=0", "gcn:epipolar_fit_px=0.5")
    for noise, fit_px in ((0.1, FINE_PX), (1.0, EPIPOLAR_PX)):
        problem = synthetic.random_scene_problem(synthetic.rome16k(3, pixel_noise=noise), np.random.default_rng([11, 0]))
        models = [m for m in candidate_edges(problem, default.edge_config).models.values() if m is not None]
        assert models and {m.epipolar_fit_px for m in models} == {fit_px}
        f1 = [score_result(problem, solvers.create(spec).solve(problem))["F1"] for spec in specs]
        if noise < 1.0:
            assert f1[0] > 0.9 and abs(f1[0] - f1[2]) < 0.02
        else:
            assert f1[0] == f1[1] and f1[2] < f1[0] - 0.3


def test_candidates_beside_the_network_change_nothing(one_torch_thread):
    """parallel (the default) computes the candidate edges on a second thread, then the stream's
    landmark search: the same pairs, scores, tracks and landmark ids as on one thread, for
    windows alone and for a stream's windows, whose rig memory the second thread uses."""
    from gcn_match_ros.data import synthetic
    from gcn_match_ros.stream import StreamState, solve_window

    assert solvers.create("gcn").config.parallel
    rng = np.random.default_rng([5, 1])
    problems = [synthetic.random_scene_problem(synthetic.rome16k(4, n_points=120), rng) for _ in range(3)]
    out = {}
    for spec in ("gcn", "gcn:parallel=false"):
        solver, state = solvers.create(spec), StreamState()
        alone = [solver.solve(p) for p in problems]
        rig = dataclasses.replace(problems[0], camera_ids=("cam0", "cam1", "cam2", "cam3"))
        streamed = [solve_window(solver, rig, state, k * 10**8) for k in range(3)]
        out[spec] = (alone + [r for r, _ in streamed], state.rig.reused, [lm.ids for _, lm in streamed])
        assert "candidates" in alone[0].timings and "network" in alone[0].timings
    (par, par_reused, par_ids), (seq, seq_reused, seq_ids) = out.values()
    assert par_reused == seq_reused > 0
    for a, b in zip(par_ids, seq_ids):
        np.testing.assert_array_equal(a, b)
    assert (par_ids[-1] >= 0).any()
    for a, b in zip(par, seq):
        np.testing.assert_array_equal(a.track, b.track)
        np.testing.assert_array_equal(a.pair_rows, b.pair_rows)
        np.testing.assert_array_equal(a.pair_scores, b.pair_scores)


@pytest.mark.parametrize("spec, slow, on_second_thread", [
    ("gcn", "network", True), ("gcn", "candidates", True), ("gcn:parallel=false", None, False), ("nn", None, True)])
def test_work_beside_the_solve_runs_where_the_solver_leaves_the_second_thread_idle(monkeypatch, spec, slow,
                                                                                  on_second_thread):
    """``Solver.solve(beside=...)``: gcn queues it behind its candidate edges on the second thread
    and takes it back when they outlast the network (it would hold up the edge head), queuing it
    again once the edge head is done (beside the verification); a solver with no work of its own
    there starts it first; gcn on one thread leaves it to the caller. The solve's result is the
    same either way."""
    import threading
    import time

    import gcn_match_ros.solvers.gcn as gcn_module
    from gcn_match_ros.data import synthetic
    from gcn_match_ros.edges.candidates import CandidateJob
    from gcn_match_ros.threads import deferred

    def slowed(fn):
        def wrapper(*args, **kwargs):
            time.sleep(0.3)
            return fn(*args, **kwargs)
        return wrapper

    problem = synthetic.random_scene_problem(synthetic.rome16k(3, n_points=60), np.random.default_rng(3))
    solver = solvers.create(spec)
    expected = solver.solve(problem).track
    if slow == "network":
        monkeypatch.setattr(gcn_module, "embed_problem", slowed(gcn_module.embed_problem))
    elif slow == "candidates":
        monkeypatch.setattr(CandidateJob, "_pair", slowed(CandidateJob._pair))
    with deferred(threading.current_thread) as beside:
        result = solver.solve(problem, beside=beside)
        ran_on = beside.result()
    assert (ran_on is not threading.current_thread()) == on_second_thread
    np.testing.assert_array_equal(result.track, expected)


@needs_two_cpus
@pytest.mark.parametrize("spec", ["gcn", "gcn:parallel=false", "gcn:keep_apart=false"])
def test_a_solve_on_two_threads_keeps_them_on_two_cpus_to_the_end_of_its_landmark_search(monkeypatch, spec):
    """``Solver.keeps_threads_apart`` (gcn with ``parallel`` and ``keep_apart``): while a window is
    solved, the network's thread stays on its CPU and the candidate edges and the stream's
    landmark search run on another (threads.kept_apart); every thread's CPUs as before once the
    window is done. On one thread, or with keep_apart=false, nothing is placed."""
    import os
    import threading

    import gcn_match_ros.solvers.gcn as gcn_module
    from gcn_match_ros.data import synthetic
    from gcn_match_ros.edges.candidates import CandidateJob
    from gcn_match_ros.landmarks import LandmarkSearch
    from gcn_match_ros.stream import StreamState, solve_window

    seen = {"network": [], "second": []}
    caller = threading.current_thread()

    def recorded(fn, key=None):
        def wrapper(*args, **kwargs):
            on = key or ("network" if threading.current_thread() is caller else "second")
            seen[on].append(frozenset(os.sched_getaffinity(0)))
            return fn(*args, **kwargs)
        return wrapper

    monkeypatch.setattr(gcn_module, "embed_problem", recorded(gcn_module.embed_problem, "network"))
    monkeypatch.setattr(CandidateJob, "_pair", recorded(CandidateJob._pair))
    monkeypatch.setattr(LandmarkSearch, "help", recorded(LandmarkSearch.help))
    solver = solvers.create(spec)
    assert solver.keeps_threads_apart == (spec == "gcn")
    problem = synthetic.random_scene_problem(synthetic.rome16k(3, n_points=80), np.random.default_rng(4))
    problem = dataclasses.replace(problem, camera_ids=("a", "b", "c"))
    before = frozenset(os.sched_getaffinity(0))
    solver.solve(problem)
    solve_window(solver, problem, StreamState(), 10**8)
    assert os.sched_getaffinity(0) == before
    (network,) = set(seen["network"])
    if solver.keeps_threads_apart:
        assert len(network) == 1 and seen["second"]
        assert all(len(cpus) == 1 and cpus != network for cpus in seen["second"])
    else:
        assert network == before and set(seen["second"]) <= {before}
