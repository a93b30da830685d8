"""Tests of gcn_match_ros.edges.rig_memory and gcn_match_ros.stream: two-view models reused
across a stream's windows while they hold, re-fitted when the geometry changes, and the same
answers online (one window at a time) and offline (solve_stream)."""
import dataclasses

import numpy as np
import pytest

from gcn_match_ros import solvers
from gcn_match_ros.data import synthetic
from gcn_match_ros.edges.rig_memory import MAX_SKIPPED, RigMemory
from gcn_match_ros.edges.verify import MIN_INLIER_RATIO, MIN_INLIERS, fit_pair, residuals
from gcn_match_ros import geometry
from gcn_match_ros.stream import StreamState, solve_stream, solve_window

H_A = np.array([[1.1, 0.05, 12.0], [-0.03, 0.95, -7.0], [2e-4, -1e-4, 1.0]])
H_B = np.array([[0.9, -0.2, 40.0], [0.15, 1.05, 30.0], [-1e-4, 2e-4, 1.0]])


def _seeds(H, rng, n=60, outliers=10):
    xa = rng.uniform(0, 640, (n, 2))
    xb = geometry.transfer(H, xa) + rng.normal(scale=0.3, size=(n, 2))
    xb[:outliers] = rng.uniform(0, 640, (outliers, 2))
    return xa, xb


class _CountingFit:
    def __init__(self, xa, xb):
        self.xa, self.xb, self.calls = xa, xb, 0

    def __call__(self):
        self.calls += 1
        return fit_pair(self.xa, self.xb)


def test_a_model_that_still_holds_is_reused_without_a_fit():
    rng = np.random.default_rng(0)
    rig = RigMemory()
    first = _CountingFit(*_seeds(H_A, rng))
    model = rig.model(("cam0", "cam1"), first.xa, first.xb, first)
    assert model is not None and model.planar and first.calls == 1 and len(rig) == 1
    # the next window of the same rig: other points, same relative pose
    nxt = _CountingFit(*_seeds(H_A, rng))
    again = rig.model(("cam0", "cam1"), nxt.xa, nxt.xb, nxt)
    assert nxt.calls == 0 and rig.reused == 1 and again.H is model.H
    assert again.seeds == 60 and again.inliers >= 45  # support counted on the new seeds
    # another camera pair is a different entry
    other = _CountingFit(*_seeds(H_A, rng))
    rig.model(("cam0", "cam2"), other.xa, other.xb, other)
    assert other.calls == 1 and len(rig) == 2


@pytest.mark.parametrize("trust", [(MIN_INLIERS, MIN_INLIER_RATIO), (0, 0.0)])
def test_a_model_whose_geometry_changed_is_refitted_every_time(trust):
    """Whatever the trust rule: (0, 0) is that of gcn:trusted_candidates=false (config/recall.yaml),
    under which any fitted model is kept."""
    rng = np.random.default_rng(1)
    rig = RigMemory()
    w0 = _CountingFit(*_seeds(H_A, rng))
    rig.model(("a", "b"), w0.xa, w0.xb, w0, *trust)
    # cameras on different robots: every window another relative pose
    for k, H in enumerate([H_B, H_A @ H_B, H_B @ H_B]):
        w = _CountingFit(*_seeds(H, rng))
        model = rig.model(("a", "b"), w.xa, w.xb, w, *trust)
        assert w.calls == 1, k  # never matched with the stale model
        assert rig.invalidated == k + 1 and rig.reused == 0
        assert residuals(model, w.xa[10:], w.xb[10:])[0].max() < 2.0  # the new geometry, not the old


def test_an_untrusted_fit_is_not_remembered_and_backs_off():
    rng = np.random.default_rng(2)
    rig = RigMemory()
    xa, xb = rng.uniform(0, 640, (40, 2)), rng.uniform(0, 640, (40, 2))  # no geometry at all
    fit = _CountingFit(xa, xb)
    fitted_at = []
    for window in range(20):
        before = fit.calls
        assert rig.model(("a", "b"), xa, xb, fit) is None and len(rig) == 0
        if fit.calls > before:
            fitted_at.append(window)
    # after k failures in a row the pair skips 2^k - 1 windows, at most MAX_SKIPPED
    assert fitted_at == [0, 2, 6, 14]
    assert rig.fitted == 4 and rig.skipped == 16
    # the pair comes to overlap: found again at its next fit, and its back-off is over
    good = _CountingFit(*_seeds(H_A, rng))
    found = [rig.model(("a", "b"), good.xa, good.xb, good) is not None for _ in range(MAX_SKIPPED + 1)]
    assert found.index(True) <= MAX_SKIPPED and all(found[found.index(True):]) and good.calls == 1
    # other camera pairs are not held back
    other = _CountingFit(*_seeds(H_A, rng))
    assert rig.model(("a", "c"), other.xa, other.xb, other) is not None and other.calls == 1


def test_a_backing_off_pair_is_probed_before_it_is_fitted_again():
    """``may_fit``: the cheap check asked before re-fitting a pair whose last fit failed (not
    before its first fit); no support there, no fit, and the pair backs off as after a failed
    fit; support there, the fit."""
    rng = np.random.default_rng(3)
    rig = RigMemory()
    xa, xb = rng.uniform(0, 640, (40, 2)), rng.uniform(0, 640, (40, 2))  # no geometry at all
    fit, asked = _CountingFit(xa, xb), []

    def may_fit():
        asked.append(True)
        return False

    looked_at = [rig.model(("a", "b"), xa, xb, fit, may_fit=may_fit) for _ in range(15)]
    assert looked_at == [None] * 15 and fit.calls == 1  # fitted once, then only probed
    assert len(asked) == rig.probed == 3 and rig.fitted == 1  # windows 2, 6 and 14, as fits were
    assert rig.skipped == 11
    good = _CountingFit(*_seeds(H_A, rng))
    found = [rig.model(("a", "b"), good.xa, good.xb, good, may_fit=lambda: True) for _ in range(MAX_SKIPPED + 1)]
    assert any(m is not None for m in found) and good.calls == 1


def test_a_pair_whose_model_fails_is_refitted_at_once():
    """Back-off is for pairs without a model: a remembered model that fails its re-check is
    re-fitted in the same window (never matched with the stale one)."""
    rng = np.random.default_rng(5)
    rig = RigMemory()
    w0 = _CountingFit(*_seeds(H_A, rng))
    rig.model(("a", "b"), w0.xa, w0.xb, w0)
    xa, xb = rng.uniform(0, 640, (40, 2)), rng.uniform(0, 640, (40, 2))
    lost = _CountingFit(xa, xb)
    assert rig.model(("a", "b"), xa, xb, lost) is None and lost.calls == 1 and rig.invalidated == 1


def _assert_solve_stream_answers_alike(spec, windows, online):
    """solve_stream (a fresh solver of ``spec``) gives the tracks and scores ``online`` holds for
    ``windows``, one window at a time as the node solves them."""
    offline = [r for r, _ in solve_stream(solvers.create(spec), windows, stamps_ns=range(len(windows)))]
    for a, b in zip(online, offline, strict=True):
        np.testing.assert_array_equal(a.track, b.track)
        np.testing.assert_array_equal(a.pair_scores, b.pair_scores)


def test_a_stream_reuses_models_and_answers_as_solve_stream():
    base = synthetic.random_scene_problem(synthetic.rome16k(3, n_points=200), rng=np.random.default_rng(9))
    windows = [dataclasses.replace(base, camera_ids=("c0", "c1", "c2"), name=f"w{k}") for k in range(3)]
    solver = solvers.create("gcn")
    state = StreamState()
    online = [solver.solve(w, stream=state) for w in windows]  # the node: one window at a time
    trusted = len(state.rig)  # view pairs with a trusted model: fitted once, then reused
    assert trusted >= 2 and state.rig.reused == 2 * trusted
    # a pair without one: fitted in windows 0 and 2, skipped in window 1 (back-off)
    assert state.rig.fitted == 3 + (3 - trusted) and state.rig.skipped == 3 - trusted
    _assert_solve_stream_answers_alike("gcn", windows, online)
    # a window that names no cameras never touches the memory
    counts = (state.rig.fitted, state.rig.reused)
    solver.solve(dataclasses.replace(base, camera_ids=None), stream=state)
    assert (state.rig.fitted, state.rig.reused) == counts


def test_the_recall_preset_answers_online_as_offline():
    """gcn:trusted_candidates=false remembers untrusted models too: the node's windows and
    solve_stream still agree."""
    base = synthetic.random_scene_problem(synthetic.preset("partial", 4, "sift"), rng=np.random.default_rng(0))
    windows = [dataclasses.replace(base, camera_ids=("c0", "c1", "c2", "c3"), name=f"w{k}") for k in range(3)]
    spec = "gcn:verify=false,threshold=0.3,trusted_candidates=false"
    state = StreamState()
    solver = solvers.create(spec)
    online = [solver.solve(w, stream=state) for w in windows]
    assert len(state.rig) == 6 and state.rig.reused == 12  # every pair, views 0 and 1's untrusted model too
    _assert_solve_stream_answers_alike(spec, windows, online)


def test_reused_models_match_as_well_as_fresh_fits():
    """With the rig's models remembered the tracks equal those of fitting every window afresh
    when the windows share the geometry (the re-check keeps the same model)."""
    base = synthetic.random_scene_problem(synthetic.rome16k(3, n_points=200), rng=np.random.default_rng(3))
    window = dataclasses.replace(base, camera_ids=("c0", "c1", "c2"))
    solver = solvers.create("gcn")
    cold = solver.solve(window)
    state = StreamState()
    solver.solve(window, stream=state)
    warm = solver.solve(window, stream=state)
    assert state.rig.reused == len(state.rig) >= 2
    np.testing.assert_array_equal(cold.track, warm.track)


def test_a_stream_without_landmarks_solves_alike_and_leaves_the_tracker_alone():
    base = synthetic.random_scene_problem(synthetic.rome16k(3, n_points=120), rng=np.random.default_rng(4))
    window = dataclasses.replace(base, camera_ids=("c0", "c1", "c2"))
    with_ids, without = StreamState(), StreamState()
    solver = solvers.create("nn")
    for k in range(2):
        a, ids = solve_window(solver, window, with_ids, k)
        b, none = solve_window(solver, window, without, k, landmarks=False)
        np.testing.assert_array_equal(a.track, b.track)
        assert none is None and (ids.ids >= 0).any()
    assert len(with_ids.landmarks) > 0 and len(without.landmarks) == 0 and without.landmarks.born == 0
