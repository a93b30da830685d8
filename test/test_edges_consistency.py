"""Tests of gcn_match_ros.edges.consistency: which pairs a window's trusted geometry keeps, and
tracks that must agree as a whole."""
import dataclasses

import numpy as np

from gcn_match_ros.edges.candidates import EdgeConfig
from gcn_match_ros.edges.consistency import (CHAIN_SLACK, COARSE_CHAIN_SLACK, UNVERIFIED_THRESHOLD, TrackCheck,
                                             WindowGeometry, chain_slack, checkable_view_pairs, may_keep,
                                             unverifiable_views, verified_tracks)
from gcn_match_ros.edges.verify import EPIPOLAR_PX, FINE_PX, MIN_SEEDS, RANSAC_PX, PairModel, residuals
from gcn_match_ros.problem import Problem
from gcn_match_ros.rounding import greedy_tracks


def _shift(dx, dy):
    """A trusted planar model: the homography of a pure image translation."""
    return PairModel(np.array([[1.0, 0, dx], [0, 1, dy], [0, 0, 1]]), None, planar=True, seeds=40, inliers_h=40)


def _window(sizes=(20, 20, 20), seed=0):
    """Views whose keypoint k are the same point, view v shifted by (10 v, 5 v) pixels."""
    rng = np.random.default_rng(seed)
    base = rng.uniform(50, 400, (max(sizes), 2))
    kps = [base[:n] + np.array([10.0 * v, 5.0 * v]) for v, n in enumerate(sizes)]
    return Problem(view_offsets=np.r_[0, np.cumsum(sizes)], keypoints=np.concatenate(kps),
                   descriptors=rng.normal(size=(sum(sizes), 8)))


def test_keep_follows_the_view_pair_status():
    p = _window()
    geometry = WindowGeometry(p, {(0, 1): _shift(10, 5), (0, 2): None, (1, 2): _shift(10, 5)})
    o = p.view_offsets
    rows = np.array([o[0] + 3, o[0] + 3, o[0] + 3, o[0] + 4, o[1] + 7])
    cols = np.array([o[1] + 3, o[1] + 4, o[2] + 3, o[2] + 9, o[2] + 7])
    scores = np.array([0.3, 0.9, UNVERIFIED_THRESHOLD - 0.01, UNVERIFIED_THRESHOLD, 0.5])
    # verified: kept when the pair agrees (whatever its score); unverified: kept on score alone
    np.testing.assert_array_equal(geometry.keep(rows, cols, scores), [True, False, False, True, True])
    np.testing.assert_array_equal(geometry.agree(rows, cols), [True, False, False, False, True])
    # either order of a pair
    np.testing.assert_array_equal(geometry.keep(cols, rows, scores), geometry.keep(rows, cols, scores))
    # what keep keeps at some score, asked view pair by view pair from the pairs' residuals (as the
    # candidate edges ask it): pairs of the unverified view pair whatever they are, verified ones
    # only where they agree
    view = p.view_index
    may = np.zeros(5, bool)
    for m, (r, c) in enumerate(zip(rows, cols)):
        model = geometry.models.get((view[r], view[c]))
        res_h, res_f = (residuals(model, p.keypoints[[r]], p.keypoints[[c]]) if model is not None
                        else (np.full(1, np.inf), np.full(1, np.inf)))
        may[m] = may_keep(model, bool(geometry.checkable[view[r], view[c]]), res_h, res_f)[0]
    np.testing.assert_array_equal(may, [True, False, True, True, True])
    for any_scores in (np.zeros(5), np.ones(5), scores):
        assert not (geometry.keep(rows, cols, any_scores) & ~may).any()
    # an unverifiable view pair's pairs whatever their residuals
    assert may_keep(_shift(10, 5), False, np.full(3, np.inf), np.full(3, np.inf)).all()
    assert unverifiable_views(_window(sizes=(20, MIN_SEEDS - 1, 20))).tolist() == [False, True, False]
    assert checkable_view_pairs(_window(sizes=(20, MIN_SEEDS - 1, 20))).tolist() == [
        [True, False, True], [False, False, False], [True, False, True]]


def test_model_slots_list_the_trusted_view_pairs_in_order():
    p = _window(sizes=(20, 20, 20, 20))
    geometry = WindowGeometry(p, {(1, 3): _shift(1, 0), (0, 2): None, (0, 1): _shift(2, 0)})
    slot, pairs = geometry.model_slots
    assert pairs == [(0, 1), (1, 3)]
    expected = np.full((4, 4), -1)
    expected[0, 1], expected[1, 3] = 0, 1
    np.testing.assert_array_equal(slot, expected)


def test_pairs_of_a_view_too_small_to_verify_are_kept_as_scored():
    p = _window(sizes=(20, MIN_SEEDS - 1, 20))
    geometry = WindowGeometry(p, {(0, 2): _shift(20, 10)})
    o = p.view_offsets
    rows, cols = np.array([o[0] + 1, o[1] + 2]), np.array([o[1] + 5, o[2] + 2])
    assert geometry.keep(rows, cols, np.array([0.2, 0.2])).all()
    assert geometry.agree(rows, cols).all()


def test_a_chain_of_agreeing_links_is_refused_when_its_ends_disagree():
    p = _window()
    o = p.view_offsets
    x, y, z = o[0] + 2, o[1] + 2, o[2] + 2
    # links x-y and y-z agree with their models; the model of (0, 2) puts z 2 x CHAIN_SLACK x px away
    wrong = _shift(20 + 2 * CHAIN_SLACK * RANSAC_PX, 10)
    geometry = WindowGeometry(p, {(0, 1): _shift(10, 5), (1, 2): _shift(10, 5), (0, 2): wrong})
    rows, cols, scores = np.array([x, y]), np.array([y, z]), np.array([0.9, 0.8])
    check = TrackCheck(geometry, rows, cols)
    track = greedy_tracks(p.n_keypoints, p.view_index, rows, cols, scores, 0.5, compatible=check)
    assert track[x] == track[y] >= 0 and track[z] == -1 and check.refused == 1
    # with a consistent model of (0, 2) the three form one track
    geometry = WindowGeometry(p, {(0, 1): _shift(10, 5), (1, 2): _shift(10, 5), (0, 2): _shift(20, 10)})
    track = greedy_tracks(p.n_keypoints, p.view_index, rows, cols, scores, 0.5,
                          compatible=TrackCheck(geometry, rows, cols))
    assert track[x] == track[y] == track[z] >= 0


def test_an_unverified_view_pair_shares_a_track_only_through_a_kept_pair():
    p = _window()
    o = p.view_offsets
    x, y, z = o[0] + 2, o[1] + 2, o[2] + 2
    geometry = WindowGeometry(p, {(0, 1): _shift(10, 5), (1, 2): _shift(10, 5), (0, 2): None})
    rows, cols, scores = np.array([x, y]), np.array([y, z]), np.array([0.9, 0.8])
    track = greedy_tracks(p.n_keypoints, p.view_index, rows, cols, scores, 0.5,
                          compatible=TrackCheck(geometry, rows, cols))
    assert track[z] == -1  # x and z (views 0, 2) were never a kept pair
    rows, cols, scores = np.array([x, y, x]), np.array([y, z, z]), np.array([0.9, 0.8, 0.95])
    track = greedy_tracks(p.n_keypoints, p.view_index, rows, cols, scores, 0.5,
                          compatible=TrackCheck(geometry, rows, cols))
    assert track[x] == track[y] == track[z] >= 0


def test_members_joined_through_a_third_get_the_chain_slack():
    p = _window()
    o = p.view_offsets
    x, y, z = o[0] + 2, o[1] + 2, o[2] + 2
    # (0, 2)'s model is off by 1.5 px: x-z fails as a direct pair, passes as a chained one
    off = _shift(20 + 1.5 * RANSAC_PX, 10)
    geometry = WindowGeometry(p, {(0, 1): _shift(10, 5), (1, 2): _shift(10, 5), (0, 2): off})
    assert not geometry.agree([x], [z])[0] and geometry.agree([x], [z], CHAIN_SLACK)[0]
    rows, cols, scores = np.array([x, y]), np.array([y, z]), np.array([0.9, 0.8])
    track = greedy_tracks(p.n_keypoints, p.view_index, rows, cols, scores, 0.5,
                          compatible=TrackCheck(geometry, rows, cols))
    assert track[x] == track[y] == track[z] >= 0


def test_a_view_pair_fitted_coarse_gets_the_coarse_chain_slack():
    """x-y and y-z are kept pairs; x-z lies 2.5x its epipolar tolerance off the model of (0, 2):
    a chain too far for a finely fitted model, within reach of a coarsely fitted one."""
    p = _window()  # view 2 is view 0 shifted by (20, 10)
    o = p.view_offsets
    x, y, z = o[0] + 2, o[1] + 2, o[2] + 2
    kp = p.keypoints.copy()
    kp[z, 1] += 3.0
    p = Problem(view_offsets=p.view_offsets, keypoints=kp, descriptors=p.descriptors)
    F = np.array([[0.0, 0, 0], [0, 0, -1], [0, 1, 10]])  # (0, 2)'s epipolar lines: y_b = y_a + 10
    rows, cols, scores = np.array([x, y]), np.array([y, z]), np.array([0.9, 0.8])
    for fit_px, slack in ((EPIPOLAR_PX, COARSE_CHAIN_SLACK), (FINE_PX, CHAIN_SLACK)):
        model = PairModel(None, F, planar=False, seeds=40, inliers_f=40, epipolar_px=1.0, epipolar_fit_px=fit_px)
        residual = residuals(model, kp[[x]], kp[[z]])[1][0]
        model = dataclasses.replace(model, epipolar_px=residual / 2.5)
        assert chain_slack(model, EdgeConfig()) == slack
        geometry = WindowGeometry(p, {(0, 1): _shift(10, 5), (1, 2): _shift(10, 5), (0, 2): model})
        check = TrackCheck(geometry, rows, cols)
        track = greedy_tracks(p.n_keypoints, p.view_index, rows, cols, scores, 0.5, compatible=check)
        assert track[x] == track[y] >= 0
        assert (track[z] == track[x]) == (slack == COARSE_CHAIN_SLACK) and check.refused == (slack == CHAIN_SLACK)
    # a homography keeps CHAIN_SLACK, whatever its epipolar model was fitted at
    assert chain_slack(_shift(1, 0), EdgeConfig()) == CHAIN_SLACK


def test_two_witnesses_vouch_for_an_unverified_view_pair():
    p = _window(sizes=(20, 20, 20, 20))
    o = p.view_offsets
    w, x, y, z = (o[v] + 2 for v in range(4))
    models = {(a, b): _shift(10 * (b - a), 5 * (b - a)) for a in range(4) for b in range(a + 1, 4)}
    models[(0, 3)] = None  # e.g. too little overlap for a trusted model of its own
    geometry = WindowGeometry(p, models)
    # a chain through views 1 and 2: both verified against 0 and 3, so w-z is vouched for
    rows, cols, scores = np.array([w, x, y]), np.array([x, y, z]), np.array([0.9, 0.8, 0.7])
    track = greedy_tracks(p.n_keypoints, p.view_index, rows, cols, scores, 0.5,
                          compatible=TrackCheck(geometry, rows, cols))
    assert len({track[w], track[x], track[y], track[z]}) == 1 and track[w] >= 0
    # one witness is not enough: without view 2 in the track, z stays out of w's track
    rows, cols, scores = np.array([w, x]), np.array([x, z]), np.array([0.9, 0.8])
    check = TrackCheck(geometry, rows, cols)
    track = greedy_tracks(p.n_keypoints, p.view_index, rows, cols, scores, 0.5, compatible=check)
    assert track[w] == track[x] >= 0 and track[z] == -1 and check.refused == 1
    # a witness whose own pairs disagree does not vouch: y shifted off view 3's model
    kp = p.keypoints.copy()
    kp[y] += 4 * CHAIN_SLACK * RANSAC_PX
    bad = WindowGeometry(Problem(view_offsets=p.view_offsets, keypoints=kp, descriptors=p.descriptors), models)
    rows, cols, scores = np.array([w, x, y]), np.array([x, y, z]), np.array([0.9, 0.8, 0.7])
    track = greedy_tracks(p.n_keypoints, p.view_index, rows, cols, scores, 0.5,
                          compatible=TrackCheck(bad, rows, cols))
    assert not (track[w] == track[x] == track[y] == track[z])


def test_batched_and_compiled_agreement_equal_each_models_own_check():
    """WindowGeometry.agree batches every view pair's check, the track check (compiled) tests a
    merge's member pairs one by one at each view pair's chain_slack; both must answer as
    PairModel.agrees. (0, 2)'s model is fitted coarse (EPIPOLAR_PX, the default), (0, 1)'s is a
    homography."""
    rng = np.random.default_rng(4)
    p = _window(sizes=(30, 30, 30))
    F = np.array([[0, -1e-3, 0.2], [1e-3, 0, -0.3], [-0.2, 0.3, 1.0]])
    models = {(0, 1): _shift(10, 5), (0, 2): PairModel(None, F, planar=False, seeds=40, inliers_f=40,
                                                       epipolar_px=40.0), (1, 2): None}
    geometry = WindowGeometry(p, models)
    rows = rng.integers(0, 30, 200)
    cols = np.where(rng.random(200) < 0.5, 30, 60) + rng.integers(0, 30, 200)
    kp = p.keypoints.astype(np.float64)
    nothing_kept = np.zeros(0, np.int64)
    check = TrackCheck(geometry, nothing_kept, nothing_kept)
    assert [chain_slack(models[k], geometry.edges) for k in ((0, 1), (0, 2))] == [CHAIN_SLACK, COARSE_CHAIN_SLACK]
    for slack in (1.0, CHAIN_SLACK, COARSE_CHAIN_SLACK):
        got = geometry.agree(rows, cols, slack)
        for r, c, g in zip(rows, cols, got):
            model = models[(0, p.view_index[c])]
            want = False if model is None else model.agrees(kp[[r]], kp[[c]], slack)[0]
            assert g == want
        assert got.any() and not got.all()
    refused = 0
    for r, c in zip(rows, cols):
        model = models[(0, p.view_index[c])]
        agrees = model is not None and model.agrees(kp[[r]], kp[[c]], chain_slack(model, geometry.edges))[0]
        refused += 2 * (not agrees)
        # two lone keypoints, either order: no witnesses
        assert check.test(check.data, np.array([r, c]), 1, 1) == agrees
        assert check.test(check.data, np.array([c, r]), 1, 1) == agrees
    assert check.refused == refused


def _chains(p, n, scramble_last=False, seed=0):
    """Pairs k_0-k_1 and k_1-k_2 of the first n points (view 1 to view 2 shuffled if asked)."""
    o = p.view_offsets
    k = np.arange(n)
    last = np.random.default_rng(seed).permutation(n) if scramble_last else k
    rows = np.r_[o[0] + k, o[1] + k]
    cols = np.r_[o[1] + k, o[2] + last]
    return rows, cols, np.full(rows.shape, 0.8)


def test_chained_model_verifies_a_view_pair_its_seeds_could_not():
    """Views 0 and 2 have no model of their own; 20 tracks through view 1 give their pairs as
    seeds, the fitted model (the shift 20, 10) is trusted, and the 3-view tracks are kept."""
    p = _window()
    geometry = WindowGeometry(p, {(0, 1): _shift(10, 5), (0, 2): None, (1, 2): _shift(10, 5)})
    rows, cols, scores = _chains(p, 20)
    chained = geometry.with_chained_models(rows, cols, scores, 0.5)
    assert chained is not geometry and chained.verified[0, 2]
    o = p.view_offsets
    assert chained.agree(o[0] + np.arange(20), o[2] + np.arange(20)).all()
    assert not chained.agree(o[0] + np.arange(20), o[2] + (np.arange(20) + 1) % 20).any()
    _, without = verified_tracks(geometry, rows, cols, scores, 0.5)
    _, with_chained = verified_tracks(geometry, rows, cols, scores, 0.5, chained_models=True)
    assert (np.bincount(without[without >= 0]) == 2).all()  # each chain stops at its first link
    assert (np.bincount(with_chained[with_chained >= 0]) == 3).sum() == 20


def test_no_chained_model_from_wrong_chains_or_too_few():
    """Chains whose second link is a random pairing fit no trusted model (views that share no
    scene); fewer chains than a trusted model needs inliers fit none either."""
    p = _window(sizes=(40, 40, 40))
    geometry = WindowGeometry(p, {(0, 1): _shift(10, 5), (0, 2): None, (1, 2): _shift(10, 5)})
    assert geometry.with_chained_models(*_chains(p, 40, scramble_last=True), 0.5) is geometry
    assert geometry.with_chained_models(*_chains(p, 10), 0.5) is geometry


def test_chained_models_are_fitted_and_trusted_by_the_candidates_settings():
    """The geometry's EdgeConfig owns the trust rule of chained models too: 20 agreeing chains
    give a trusted model under the defaults, none when the candidates' models needed 25
    inliers."""
    p = _window()
    models = {(0, 1): _shift(10, 5), (0, 2): None, (1, 2): _shift(10, 5)}
    chains = _chains(p, 20)
    assert WindowGeometry(p, models).with_chained_models(*chains, 0.5).verified[0, 2]
    strict = WindowGeometry(p, models, edges=EdgeConfig(min_inliers=25))
    assert strict.with_chained_models(*chains, 0.5) is strict
