"""Tests of gcn_match_ros.landmarks (persistent ids), landmark_metrics and data.rig_sequence."""
import numpy as np
import pytest

from gcn_match_ros.data.rig_sequence import RigSequenceConfig, rig_sequence
from gcn_match_ros.descriptors import cosine_distance
from gcn_match_ros.landmark_metrics import landmark_scores
from gcn_match_ros.landmarks import LandmarkConfig, LandmarkTracker, PerCameraNNLinker

CAMS = ("a", "b")
PERIOD = 10**8


@pytest.fixture
def motion_fits(monkeypatch):
    """The tracker's motion fits, counted: a list that grows by one per fit_pair call."""
    import gcn_match_ros.landmarks as landmarks_module

    fits = []
    real_fit = landmarks_module.fit_pair
    monkeypatch.setattr(landmarks_module, "fit_pair", lambda *a, **k: fits.append(1) or real_fit(*a, **k))
    return fits


def _window(rng, base_desc, xy, present, shift, noise=0.05):
    """Two cameras seeing the points ``present`` (both cameras), moved by ``shift`` pixels;
    the true tracks pair them up."""
    kps, descs, truth = [], [], []
    for v in range(2):
        kps.append(xy[present] + shift + v * 5.0)
        descs.append(base_desc[present] + noise * rng.normal(size=(present.size, base_desc.shape[1])))
        truth.append(present)
    n = present.size
    track = np.concatenate([np.arange(n), np.arange(n)])
    return (np.array([0, n, 2 * n]), np.concatenate(kps), np.concatenate(descs).astype(np.float32), track,
            np.concatenate(truth))


def test_ids_persist_new_points_get_new_ids_and_ids_are_never_reused():
    rng = np.random.default_rng(0)
    P = 40
    # zero-mean descriptors: different points are dissimilar (known answers, no ambiguity)
    base, xy = rng.normal(size=(P, 32)), rng.uniform(0, 600, (P, 2))
    tracker = LandmarkTracker(LandmarkConfig(max_age_s=0.25))
    seen_ids, history = set(), []
    present = np.arange(30)
    for t in range(6):
        if t == 3:
            present = np.arange(10, 40)  # 10 points leave, 10 new ones arrive
        offs, kp, desc, track, truth = _window(rng, base, xy, present, shift=2.0 * t)
        ids, ages = tracker.update(CAMS, offs, kp, desc, track, t * PERIOD)
        history.append((ids, truth))
        assert (ids >= 0).all() and len(np.unique(ids)) == present.size  # one id per point
        point_of = dict(zip(ids.tolist(), truth.tolist()))
        assert all(point_of[i] == p for i, p in zip(ids.tolist(), truth.tolist()))
        if t == 0:
            first = dict(zip(truth.tolist(), ids.tolist()))
            assert (ages == 0).all()
        if t == 3:
            new = truth >= 30
            assert not (set(ids[new].tolist()) & seen_ids)  # new points: new ids, none reused
            assert (ages[new] == 0).all() and (ages[~new] == 3 * PERIOD).all()
        seen_ids |= set(ids.tolist())
    for ids, truth in history[1:]:  # points that stayed kept their first id throughout
        for i, p in zip(ids.tolist(), truth.tolist()):
            if p in first and p >= 10:
                assert i == first[p]
    # the points that left were retired after max_age: bounded state
    assert tracker.retired == 10 and len(tracker) == 30 and tracker.born == 40
    scores = landmark_scores([h[0] for h in history], [h[1] for h in history])
    assert scores["id_precision"] == 1.0 and scores["fragmentation"] == 1.0 and scores["switches_per_100"] == 0.0


def test_a_point_far_from_its_last_sighting_is_not_continued():
    rng = np.random.default_rng(1)
    # zero-mean descriptors: other points are dissimilar, so only the gate is tested here
    base, xy = rng.normal(size=(20, 32)), rng.uniform(0, 300, (20, 2))
    tracker = LandmarkTracker()
    offs, kp, desc, track, _ = _window(rng, base, xy, np.arange(20), shift=0.0)
    ids0, _ = tracker.update(CAMS, offs, kp, desc, track, 0)
    offs, kp, desc, track, _ = _window(rng, base, xy, np.arange(20), shift=3 * tracker.config.gate_px)
    ids1, _ = tracker.update(CAMS, offs, kp, desc, track, PERIOD)
    assert not (set(ids0.tolist()) & set(ids1.tolist()))


def test_metrics_count_switches_and_fragments():
    truth = [np.array([0, 1, 2]), np.array([0, 1, 2]), np.array([0, 1, 2])]
    ids = [np.array([5, 6, -1]), np.array([5, 7, 8]), np.array([5, 7, 8])]
    s = landmark_scores(ids, truth)
    # point 1 switched 6 -> 7 once; points with ids: 2 + 3 + 3 point-windows
    assert s["switches_per_100"] == 100 * 1 / 8
    assert s["fragmentation"] == (1 + 2 + 1) / 3 and s["id_precision"] == 1.0
    # a landmark moving to another point is an imprecise continuation
    s = landmark_scores([np.array([5, 6]), np.array([6, 5])], [np.array([0, 1]), np.array([0, 1])])
    assert s["id_precision"] == 0.0


def test_the_baseline_links_per_camera_nearest_neighbours():
    rng = np.random.default_rng(2)
    base, xy = np.abs(rng.normal(size=(20, 32))), rng.uniform(0, 300, (20, 2))
    linker = PerCameraNNLinker()
    offs, kp, desc, track, truth = _window(rng, base, xy, np.arange(20), shift=0.0)
    ids0 = linker.update(CAMS, offs, desc, track)
    assert len(np.unique(ids0)) == 20 and ids0.max() == 19
    offs, kp, desc, track, truth = _window(rng, base, xy, np.arange(20), shift=1.0)
    np.testing.assert_array_equal(linker.update(CAMS, offs, desc, track), ids0)


def test_rig_sequences_have_exact_point_ids_and_shared_points_over_time():
    problems, truth, stamps = rig_sequence(RigSequenceConfig(n_cameras=2, n_windows=3, n_points=600), rng=0)
    assert len(problems) == 3 and np.all(np.diff(stamps) > 0)
    for p, t in zip(problems, truth):
        assert p.camera_ids == ("cam0", "cam1") and t.shape == (p.n_keypoints,)
        assert ((p.gt_track == t) | (p.gt_track == -1)).all()
        assert (p.gt_track >= 0).sum() > 20  # the cameras overlap
    a, b = set(truth[0][truth[0] >= 0].tolist()), set(truth[1][truth[1] >= 0].tolist())
    assert len(a & b) > 0.8 * len(a)  # consecutive windows share most points


def _dense_choice(tracker, camera_ids, offsets, keypoints, descriptors, units):
    """The association rule as plain matrices over every (keypoint, landmark): the reference the
    tracker's sparse candidates must reproduce."""
    cfg = tracker.config
    desc = descriptors / np.linalg.norm(descriptors, axis=1, keepdims=True)
    sim = desc @ tracker._desc.T
    view = np.repeat(np.arange(len(camera_ids)), np.diff(offsets))
    sight = tracker._xy                                                    # (L, cameras, 2), NaN: unseen
    d2 = ((keypoints[:, None, None, :] - sight[None]) ** 2).sum(-1)        # (N, L, cameras)
    near = (d2 <= cfg.gate_px ** 2).any(-1)                                # NaN compares False
    own_seen = ~np.isnan(sight[:, [tracker._cams[camera_ids[v]] for v in view], 0]).T
    need = np.where(own_seen, np.where(near, cfg.min_similarity, np.inf), cfg.cross_similarity)
    score = np.where(sim >= need, sim, -np.inf)
    choice = []
    for members in units:
        per_landmark = score[members].max(0)
        ranked = np.argsort(-per_landmark, kind="stable")
        first, second = per_landmark[ranked[0]], (per_landmark[ranked[1]] if ranked.size > 1 else -np.inf)
        second = second if np.isfinite(second) else -1.0
        ok = np.isfinite(first) and (cosine_distance(first) < cfg.ratio * cosine_distance(second) or second < 0)
        choice.append(int(ranked[0]) if ok else -1)
    return np.array(choice)


def test_sparse_association_follows_the_dense_rule():
    from gcn_match_ros.landmarks import _best_per_unit, _Units

    problems, _, stamps = rig_sequence(RigSequenceConfig(n_cameras=3, n_windows=8, n_points=600), rng=3)
    tracker = LandmarkTracker()
    rng = np.random.default_rng(0)
    compared = 0
    for p, stamp in zip(problems, stamps):
        track = np.where(p.gt_track >= 0, p.gt_track, -1)
        track[rng.random(track.size) < 0.2] = -1          # lone keypoints too
        if len(tracker):
            units = _Units(track)
            member, lm, score = tracker.search(p.camera_ids, p.view_offsets, p.keypoints, p.descriptors,
                                               stamp).candidates
            best, _ = _best_per_unit(units.of_keypoint[member], lm, score, len(units), tracker.config.ratio)
            dense = _dense_choice(tracker, p.camera_ids, p.view_offsets, p.keypoints, p.descriptors, list(units))
            agree = best == dense
            # float64 here vs float32 there may flip a pair sitting exactly on a threshold
            assert agree.mean() > 0.995 and (best >= 0).sum() > 100, (agree.mean(), (best >= 0).sum())
            compared += 1
        tracker.update(p.camera_ids, p.view_offsets, p.keypoints, p.descriptors, track, stamp)
    assert compared == 7


def test_two_best_landmarks_known_answers():
    from gcn_match_ros.landmarks import _sighting_grid, _two_best_landmarks, _unseen_by_camera

    nan = np.nan
    # landmarks 0-3 seen by camera 0 at these pixels (camera 1: landmark 3 only); landmark 4 by camera 1 only
    xy = np.array([[[100, 100], [nan, nan]], [[130, 100], [nan, nan]], [[600, 400], [nan, nan]],
                   [[nan, nan], [102, 98]], [[nan, nan], [300, 300]]], float)
    xy[3, 0] = (900, 900)   # camera 0 saw landmark 3 far away, camera 1 near the keypoint: the gate takes any camera's
    sim = np.array([[0.8, 0.8, 0.99, 0.7, 0.7],      # 0 and 1 tie in the gate (lower index first); 2 is out of it
                    [0.5, 0.5, 0.5, 0.5, 0.76],      # far from every sighting: only the cross rule (landmark 4)
                    [0.8, 0.9, 0.9, 0.9, 0.9],       # camera 1: 0-2 unseen by it, need 0.75; 3 gated
                    [0.9, 0.9, 0.9, 0.9, 0.8],       # absurd or NaN coordinates: the cross rule only
                    [0.9, 0.9, 0.9, 0.9, 0.8]], np.float32)
    keypoints = np.array([[101.0, 99.0], [5000.0, -3000.0], [1e4, 1e4], [1e300, -1e300], [nan, 5.0]])
    column = np.array([0, 0, 1, 0, 0])
    gate = np.float64(40.0)
    first, second, s1, s2 = _two_best_landmarks(sim, column, keypoints, xy, _unseen_by_camera(xy),
                                                _sighting_grid(xy, gate), gate, np.float32(0.45), np.float32(0.75))
    # keypoint 0: gated 0, 1 (tie at 0.8) and 3 (near its camera-1 sighting, 0.7); 4 unseen by camera 0, below 0.75
    assert (first[0], second[0]) == (0, 1) and s1[0] == s2[0] == np.float32(0.8)
    assert (first[1], second[1]) == (4, -1) and s2[1] == -np.inf   # 0.76 >= 0.75 for a landmark camera 0 never saw
    # keypoint 2 (camera 1, far outside the sightings): landmarks 1, 2 by the cross rule (0.9 each, lower index first)
    assert (first[2], second[2]) == (1, 2)
    assert (first[3], second[3]) == (first[4], second[4]) == (4, -1)


def test_best_per_unit_known_answers():
    from gcn_match_ros.landmarks import _best_per_unit

    f = np.float32
    # unit 0: two members score landmark 2 (0.9 and 0.6) and landmark 5 (0.5): best 2 by its best
    #   member, second 0.5 -> distances sqrt(0.2) < 0.95 * sqrt(1.0): kept.
    # unit 1: landmarks 3 and 1 tie at 0.8 -> the lower index, but the tie fails the ratio test.
    # unit 2: one candidate -> no second best -> kept.  unit 3: no candidate.
    unit = np.array([0, 0, 0, 1, 1, 2])
    lm = np.array([2, 2, 5, 3, 1, 7])
    score = np.array([0.6, 0.9, 0.5, 0.8, 0.8, 0.7], f)
    best, best_score = _best_per_unit(unit, lm, score, 4, ratio=0.95)
    assert best.tolist() == [2, -1, 7, -1]
    assert best_score.tolist() == [f(0.9), 0.0, f(0.7), 0.0]
    loose, _ = _best_per_unit(unit, lm, score, 4, ratio=1.01)
    assert loose.tolist() == [2, 1, 7, -1]


def test_best_per_unit_follows_its_rule_with_many_ties():
    """The one-pass kernel against the rule spelt out: per unit, each landmark's best member
    score; the best landmark (lowest index on ties) and the best score of any other."""
    from gcn_match_ros.landmarks import _best_per_unit

    rng = np.random.default_rng(0)
    for _ in range(300):
        k, n_units = int(rng.integers(0, 30)), int(rng.integers(1, 6))
        unit, lm = rng.integers(0, n_units, k), rng.integers(0, 5, k)
        score = (rng.integers(0, 4, k) / 4).astype(np.float32)   # scores collide often
        best, best_score = _best_per_unit(unit, lm, score, n_units, ratio=0.95)
        for u in range(n_units):
            per_lm = {}
            for l, s in zip(lm[unit == u], score[unit == u]):
                per_lm[int(l)] = max(per_lm.get(int(l), -1.0), float(s))
            if not per_lm:
                assert best[u] == -1
                continue
            top = max(per_lm.values())
            winner = min(l for l, s in per_lm.items() if s == top)
            others = [s for l, s in per_lm.items() if l != winner]
            passes = not others or cosine_distance(top) < 0.95 * cosine_distance(max(others))
            assert best[u] == (winner if passes else -1)
            assert best_score[u] == (np.float32(top) if passes else 0.0)


def test_a_search_in_chunks_on_two_threads_is_that_of_one(monkeypatch):
    """The search's chunks, taken by two threads, give bit for bit the candidates and ids of the
    same chunks on one thread; and those of one chunk, but for the similarities' last bits (BLAS
    may take another kernel for a chunk's product than for the window's, by CPU)."""
    import threading

    import gcn_match_ros.landmarks as landmarks_module

    problems, _, stamps = rig_sequence(RigSequenceConfig(n_cameras=3, n_windows=3, n_points=600), rng=3)

    def search(chunk_products: int, helped: bool):
        monkeypatch.setattr(landmarks_module, "SEARCH_CHUNK_PRODUCTS", chunk_products)
        tracker = LandmarkTracker()
        for p, stamp in zip(problems[:2], stamps):
            tracker.update(p.camera_ids, p.view_offsets, p.keypoints, p.descriptors, p.gt_track, stamp)
        p = problems[2]
        job = tracker.search_job(p.camera_ids, p.view_offsets, p.keypoints, p.descriptors, stamps[2])
        helper = threading.Thread(target=job.help)
        if helped:
            helper.start()
        searched = job.result()
        if helped:
            helper.join()
        return job.chunks, searched.candidates + tracker.associate(searched, p.gt_track)

    one, whole = search(10**12, helped=False)
    many, alone = search(2_000, helped=False)
    shared_chunks, shared = search(2_000, helped=True)
    assert one == 1 and many == shared_chunks > 4 and whole[0].size > 500
    for a, b, c in zip(alone, shared, whole):
        np.testing.assert_array_equal(a, b)
        if np.issubdtype(c.dtype, np.floating):
            np.testing.assert_allclose(a, c, rtol=1e-6)
        else:
            np.testing.assert_array_equal(a, c)


def test_units_are_tracks_by_id_then_lone_keypoints():
    from gcn_match_ros.landmarks import _Units

    units = _Units(np.array([2, -1, 2, 0, -1, 0, 7]))
    assert [m.tolist() for m in units] == [[3, 5], [0, 2], [6], [1], [4]]
    assert units.sizes.tolist() == [2, 2, 1, 1, 1] and len(units) == 5
    assert units.of_keypoint.tolist() == [1, 3, 1, 0, 4, 0, 2]
    assert units.members(np.array([3, 0, 1])).tolist() == [1, 3, 5, 0, 2]
    assert units.members(np.zeros(0, np.int64)).size == 0
    assert len(_Units(np.zeros(0, np.int64))) == 0 and len(_Units(np.full(3, -1))) == 3


def test_unit_summaries_are_the_unit_vectors_along_the_members_mean():
    from gcn_match_ros.landmarks import _unit_summaries

    desc = np.random.default_rng(0).normal(size=(9, 4)).astype(np.float32)
    desc[3] = 0.0
    rows, sizes = np.array([4, 0, 8, 2, 7, 5, 3]), np.array([1, 3, 2, 1])
    means = np.stack([desc[[4]].mean(0), desc[[0, 8, 2]].mean(0), desc[[7, 5]].mean(0)])
    expected = means / np.linalg.norm(means, axis=1, keepdims=True)
    got = _unit_summaries(rows, sizes, desc)
    assert got.dtype == np.float32 and got.shape == (4, 4)
    np.testing.assert_allclose(got[:3], expected, rtol=1e-6)
    assert not got[3].any()   # a zero mean stays zero, no NaN


def test_blended_summaries_move_towards_the_new_sighting_and_stay_unit_vectors():
    from gcn_match_ros.landmarks import _blend_summaries

    summaries = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    desc = np.array([[0, 2, 0], [0, 0, 4], [0, 0, 2]], np.float32)
    # landmark 2 takes a unit of two members (mean (0, 0, 3)), landmark 0 one of one ((0, 2, 0))
    _blend_summaries(summaries, np.array([2, 0]), np.array([1, 2, 0]), np.array([2, 1]), desc, 0.3)
    np.testing.assert_allclose(summaries[2], [0, 0, 1], atol=1e-7)          # (0.7 + 0.9) / 1.6
    np.testing.assert_allclose(summaries[0], np.array([0.7, 0.6, 0]) / np.hypot(0.7, 0.6), rtol=1e-6)
    np.testing.assert_array_equal(summaries[1], [0, 1, 0])                  # not in js: untouched


def test_one_to_one_gives_each_landmark_to_its_highest_scoring_unit_first_on_ties():
    from gcn_match_ros.landmarks import _one_to_one

    best = np.array([3, 3, 1, -1, 1, 3, 0])
    score = np.array([0.5, 0.9, 0.7, 0.99, 0.7, 0.9, 0.1], np.float32)
    assert _one_to_one(best, np.argsort(-score, kind="stable")).tolist() == [-1, 3, 1, -1, -1, -1, 0]
    assert _one_to_one(np.zeros(0, np.int64), np.zeros(0, np.int64)).size == 0
    assert _one_to_one(np.full(3, -1), np.arange(3)).tolist() == [-1, -1, -1]


def test_motion_pairs_group_by_frame_pair_and_bridge_a_frame_seen_before_the_last_window():
    from gcn_match_ros.landmarks import _motion_pairs

    nan = np.nan
    # 4 landmarks, 2 cameras; the last window was at t=100, landmark 2 was last seen at t=50
    xy = np.array([[[10, 10], [nan, nan]], [[20, 20], [30, 30]], [[40, 40], [nan, nan]],
                   [[nan, nan], [50, 50]]], float)
    seen_ns = np.array([100, 100, 50, 100])
    xy_before = np.full((4, 2, 2), nan)
    xy_before[3, 0] = (5, 5)                       # landmark 3's sighting before: camera 0 at t=50
    before_ns = np.array([-1, -1, -1, 50])
    keypoints = np.array([[11, 10], [31, 30], [41, 40], [53, 50]], np.float32)
    column = np.array([0, 1, 0, 0])                # each keypoint's camera now
    units = np.arange(4)                           # one keypoint a unit, unit u continues landmark u
    out = _motion_pairs(units, units, units, np.ones(4, bool), column, keypoints, xy, seen_ns, xy_before,
                        before_ns, 100, 1, 2.0)
    unit, xa, xb, fitted, moved, starts, ends, cam_a, cam_b, frame_ns, still, bridge_bounds, bxa, bxb = out
    # frame pairs by (camera then, camera now, time then)
    assert list(zip(cam_a, cam_b, frame_ns)) == [(0, 0, 50), (0, 0, 100), (0, 1, 100), (1, 0, 100), (1, 1, 100)]
    assert [unit[a:b].tolist() for a, b in zip(starts, ends)] == [[2], [0], [1], [3], [1]]
    np.testing.assert_array_equal(xa[starts[2]], [20, 20])
    np.testing.assert_array_equal(xb[starts[2]], [31, 30])
    np.testing.assert_allclose(moved[starts[1]], 1.0)
    assert still.tolist() == [True, True, False, False, True]
    # only the frame seen before the last window is bridged: by landmark 3, seen then in camera 0
    assert bridge_bounds.tolist() == [0, 1, 1, 1, 1, 1]
    np.testing.assert_array_equal(bxa, [[5, 5]])
    np.testing.assert_array_equal(bxb, [[53, 50]])
    # frame pairs with fewer fitted and bridge pairs than the seeds a fit needs are left out
    out = _motion_pairs(units, units, units, np.ones(4, bool), column, keypoints, xy, seen_ns, xy_before,
                        before_ns, 100, 2, 2.0)
    assert list(zip(out[7], out[8], out[9])) == [(0, 0, 50)] and out[11].tolist() == [0, 1]


def test_motion_checks_count_support_on_the_fitted_and_bridge_pairs_only():
    from gcn_match_ros.edges.verify import fit_pair, residuals
    from gcn_match_ros.landmarks import _MotionChecks

    rng = np.random.default_rng(1)
    xa = rng.uniform(0, 640, (60, 2))
    xb = xa + [6.0, 0.0]
    xb[:10] += rng.uniform(20, 40, (10, 2))            # 10 pairs against the motion
    model = fit_pair(xa[10:], xb[10:])
    fitted = np.arange(60) % 2 == 0                   # 5 of the wrong pairs among the fitted
    bridge = (rng.uniform(0, 640, (7, 2)),) * 2       # 7 pairs that did not move
    checks = _MotionChecks(model, xa, xb, fitted, bridge)
    rh, rf = residuals(model, xa, xb)
    np.testing.assert_array_equal(checks.residuals[0], rh)
    np.testing.assert_array_equal(checks.residuals[1], rf)
    assert _MotionChecks(model, xa, xb, fitted, None).support == (
        int((rh[fitted] <= model.px).sum()), int((rf[fitted] <= model.epipolar_fit_px).sum())) == (25, 25)
    bh, bf = residuals(model, *bridge)
    assert checks.support == (25 + int((bh <= model.px).sum()), 25 + int((bf <= model.epipolar_fit_px).sum()))


def test_a_refinement_re_estimates_only_the_motion_the_check_uses():
    """A motion with depth is checked with F: its refinement re-estimates F on F's inliers and
    keeps H as it was; a planar motion re-estimates H and keeps F."""
    import dataclasses

    from gcn_match_ros.edges.verify import fit_pair
    from gcn_match_ros.landmarks import _MotionChecks, _refined

    rng = np.random.default_rng(2)
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    X = rng.uniform([-2, -1.5, 4], [2, 1.5, 9], (80, 3))          # points at many depths

    def project(X, t):
        return ((X + t) @ K.T / (X + t)[:, 2:])[:, :2]

    xa, xb = project(X, np.zeros(3)), project(X, np.array([0.3, 0.0, 0.0]))
    fitted = np.ones(80, bool)
    model = fit_pair(xa, xb)
    checks = _MotionChecks(model, xa, xb, fitted, None)
    assert checks.support[0] < 0.95 * checks.support[1]       # F explains clearly more: F is used
    moved = dataclasses.replace(model, F=model.F + 1e-7 * rng.normal(size=(3, 3)))
    refined = _refined(moved, _MotionChecks(moved, xa, xb, fitted, None), xa, xb)
    assert refined.H is moved.H and not np.array_equal(refined.F, moved.F)
    # a plane: every point at depth 5, H explains all pairs
    X[:, 2] = 5.0
    xa, xb = project(X, np.zeros(3)), project(X, np.array([0.3, 0.0, 0.0]))
    model = fit_pair(xa, xb)
    checks = _MotionChecks(model, xa, xb, fitted, None)
    assert checks.support[0] >= 0.95 * checks.support[1]
    refined = _refined(model, checks, xa, xb)
    assert refined.F is model.F and not np.array_equal(refined.H, model.H)


def test_a_continuation_against_the_motion_of_the_others_is_refused():
    """Window 2 moves every point 6 px right; one point is gone and a look-alike (its descriptor)
    sits 25 px below where it should be: within the image gate, against the motion."""
    rng = np.random.default_rng(5)
    P = 60
    base, xy = rng.normal(size=(P, 32)), rng.uniform(50, 550, (P, 2))

    def window(points_xy, descs):
        n = len(points_xy)
        return (np.array([0, n, 2 * n]), np.concatenate([points_xy, points_xy + [3.0, 0.0]]),
                np.concatenate([descs, descs]).astype(np.float32), np.r_[np.arange(n), np.arange(n)])

    first = window(xy, base)
    moved = xy + [6.0, 0.0]
    moved[0] += [0.0, 25.0]  # point 0 is gone; its look-alike sits here
    second = window(moved, base + 0.02 * rng.normal(size=base.shape))
    for verify, same in ((False, True), (True, False)):
        tracker = LandmarkTracker(LandmarkConfig(verify_motion=verify))
        ids1, _ = tracker.update(CAMS, *first, 0)
        ids2, _ = tracker.update(CAMS, *second, PERIOD)
        assert (ids2[0] == ids1[0]) == same
        assert np.array_equal(ids2[1:P], ids1[1:P])  # the others continue either way


def test_a_steady_motion_is_fitted_once_and_a_new_one_refitted(motion_fits):
    """Like the rig memory: the motion of consecutive frames of a camera pair is re-checked on
    the next window and re-fitted only when it no longer explains the continuations."""
    rng = np.random.default_rng(8)
    P = 60
    base, xy = rng.normal(size=(P, 32)), rng.uniform(50, 550, (P, 2))
    tracker = LandmarkTracker()
    fitted, previous = [], None
    offset = np.zeros(2)
    for t, step in enumerate([(0, 0), (6, 0), (6, 0), (6, 0), (0, 9)]):
        offset = offset + step
        n = P
        kp = np.concatenate([xy + offset, xy + offset + [25.0, 0.0]])  # the other camera: 25 px aside
        desc = np.concatenate([base, base]) + 0.02 * rng.normal(size=(2 * P, 32))
        ids, _ = tracker.update(CAMS, np.array([0, n, 2 * n]), kp, desc.astype(np.float32),
                                np.r_[np.arange(n), np.arange(n)], t * PERIOD)
        fitted.append(len(motion_fits))
        if previous is not None:
            assert np.array_equal(ids, previous)  # every point keeps its id throughout
        previous = ids
    per_window = np.diff([0] + fitted)
    assert per_window[0] == 0 and per_window[1] > 0      # nothing to check, then the first motion
    assert per_window[2] == 0 and per_window[3] == 0     # the same motion: re-checked, not re-fitted
    assert per_window[4] > 0                             # a new motion: re-fitted


def _rig_window(xy, descs):
    """Camera a sees ``xy``, camera b the same points 3 px to the right; the tracks pair them."""
    n = len(xy)
    return (np.array([0, n, 2 * n]), np.concatenate([xy, xy + [3.0, 0.0]]),
            np.concatenate([descs, descs]).astype(np.float32), np.r_[np.arange(n), np.arange(n)])


def test_a_point_re_found_after_a_gap_is_checked_through_the_others():
    """Points 0-9 are missed in window 1; in window 2 points 0-4 are back where the motion puts
    them, and a look-alike of point 5 sits 25 px below its place. Too few re-found points to fit
    the motion since window 0, but the points seen in all three windows bridge it: the right
    ones keep their ids, the look-alike is refused."""
    rng = np.random.default_rng(9)
    P = 60
    base, xy = rng.normal(size=(P, 32)), rng.uniform(50, 550, (P, 2))
    noisy = lambda: base + 0.02 * rng.normal(size=base.shape)  # noqa: E731
    tracker = LandmarkTracker()
    ids0, _ = tracker.update(CAMS, *_rig_window(xy, base), 0)
    ids1, _ = tracker.update(CAMS, *_rig_window(xy[10:] + [6.0, 0.0], noisy()[10:]), PERIOD)
    assert np.array_equal(ids1, np.r_[ids0[10:P], ids0[P + 10:]])
    back = np.r_[0:6, 10:P]
    now = xy[back] + [12.0, 0.0]
    now[5] += [0.0, 25.0]  # point 5 is gone; its look-alike sits here
    ids2, _ = tracker.update(CAMS, *_rig_window(now, noisy()[back]), 2 * PERIOD)
    assert np.array_equal(ids2[:5], ids0[:5])            # re-found, checked, continued
    assert ids2[5] >= 0 and ids2[5] not in ids0           # the look-alike: a new landmark
    assert np.array_equal(ids2[6:back.size], ids0[10:P])


def test_a_re_finding_nothing_can_check_is_refused():
    """Points 0-4 are seen in window 0, missed in window 1 (where only new points appear) and
    back in window 2: no continuation saw window 0, too few to fit the motion alone. Unchecked,
    their re-finding is refused (on real sequences such re-findings were mostly wrong)."""
    rng = np.random.default_rng(10)
    P = 60
    base, xy = rng.normal(size=(P, 32)), rng.uniform(50, 550, (P, 2))
    tracker = LandmarkTracker()
    ids0, _ = tracker.update(CAMS, *_rig_window(xy[:5], base[:5]), 0)
    tracker.update(CAMS, *_rig_window(xy[5:] + [6.0, 0.0], base[5:]), PERIOD)
    ids2, _ = tracker.update(CAMS, *_rig_window(xy + [12.0, 0.0], base + 0.02 * rng.normal(size=base.shape)),
                             2 * PERIOD)
    assert not np.isin(ids2[:5], ids0).any()


def test_true_points_from_bag_labels():
    from gcn_match_ros.landmark_metrics import true_points

    assert true_points(np.array([4, -1, -2, 0]), 4).tolist() == [4, -1, -1, 0]
    assert true_points(None, 3).tolist() == [-1, -1, -1]


def test_a_drifting_motion_is_re_estimated_before_it_explains_too_few(motion_fits):
    """The motion model of consecutive frames is re-estimated once it explains clearly fewer
    continuations than when it was fitted, though still most of them (a model kept while it
    explained 80% drifted from a moving rig and dropped right continuations): least squares on
    the pairs it still explains, no new RANSAC fit, and the model it then remembers explains
    the new motion."""
    from gcn_match_ros.edges.verify import residuals

    rng = np.random.default_rng(12)
    P = 80
    base, xy = rng.normal(size=(P, 32)), rng.uniform(50, 550, (P, 2))
    centre, angle = np.array([300.0, 300.0]), np.radians(0.6)
    turn = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    steady = lambda p: p + [6.0, 0.0]                          # noqa: E731
    turning = lambda p: (p - centre) @ turn.T + centre + [6.0, 0.0]  # noqa: E731
    positions = [xy, steady(xy), steady(steady(xy))]
    positions.append(turning(positions[-1]))
    # the steady model still explains most of the turning window's motion, not all of it
    off = np.linalg.norm(positions[3] - steady(positions[2]), axis=1)
    assert 0.8 <= np.mean(off <= 3.0) <= 0.95
    tracker = LandmarkTracker()
    fitted, previous, remembered = [], None, []
    for t, pos in enumerate(positions):
        kp = np.concatenate([pos, pos + [25.0, 0.0]])
        desc = np.concatenate([base, base]) + 0.02 * rng.normal(size=(2 * P, 32))
        ids, _ = tracker.update(CAMS, np.array([0, P, 2 * P]), kp, desc.astype(np.float32),
                                np.r_[np.arange(P), np.arange(P)], t * PERIOD)
        fitted.append(len(motion_fits))
        remembered.append(tracker._motion_models.get((0, 0, 1), (None,))[0])
        if previous is not None:
            assert np.array_equal(ids, previous)
        previous = ids
    per_window = np.diff([0] + fitted)
    assert per_window[1] > 0 and per_window[2] == 0   # fitted, then re-checked and kept
    assert per_window[3] == 0                         # 80-95% explained: refined, not re-fitted
    assert remembered[3] is not remembered[2]
    for model, share in ((remembered[2], 0.95), (remembered[3], 1.0)):
        rh, _ = residuals(model, positions[2], positions[3])
        assert (np.mean(rh <= model.px) <= share) and (share < 1.0 or np.all(rh <= model.px))


def test_a_motion_between_frames_windows_apart_is_remembered_too(motion_fits):
    """A steady rig; a fifth of the points is seen only every other window, so every other
    window re-finds them two windows after their last sighting. That frame pair's motion
    (checked through the points seen in between) is fitted once and then re-checked, like the
    consecutive frames': no fit after the first re-finding, and every point keeps its id."""
    rng = np.random.default_rng(13)
    P = 60
    base, xy = rng.normal(size=(P, 32)), rng.uniform(50, 550, (P, 2))
    tracker = LandmarkTracker()
    fitted, first_ids = [], {}
    for t in range(7):
        seen = np.arange(P) if t % 2 == 0 else np.arange(12, P)
        pos = xy[seen] + [6.0 * t, 0.0]
        ids, _ = tracker.update(CAMS, *_rig_window(pos, base[seen] + 0.02 * rng.normal(size=(seen.size, 32))),
                                t * PERIOD)
        fitted.append(len(motion_fits))
        for point, i in zip(seen, ids[:seen.size]):
            assert first_ids.setdefault(int(point), int(i)) == i
    per_window = np.diff([0] + fitted)
    assert per_window[2] > 0                          # the first re-finding: its motion fitted
    assert per_window[3:].tolist() == [0, 0, 0, 0]    # then re-checked, never re-fitted


def test_a_still_scene_makes_no_motion_fits(motion_fits):
    """Two cameras watch a still scene: every landmark continues in place. The keypoints the
    matcher left alone whose best landmark another unit claims used to fill the motion fits
    with wrong pairs (three untrusted fits here); only the units that keep their landmark decide
    the fits, and a still image needs none."""
    from gcn_match_ros import solvers
    from gcn_match_ros.data.synthetic import random_scene_problem, rome16k

    p = random_scene_problem(rome16k(2, n_points=300), rng=0)
    track = solvers.create("nn").solve(p).track
    tracker = LandmarkTracker()
    ids = [tracker.update(CAMS, p.view_offsets, p.keypoints, p.descriptors, track, t * PERIOD)[0]
           for t in range(3)]
    assert motion_fits == []
    in_track = np.flatnonzero(track >= 0)
    assert in_track.size > 0 and (ids[0][in_track] >= 0).all()
    assert np.array_equal(ids[1][in_track], ids[0][in_track]) and np.array_equal(ids[2], ids[1])


def test_search_then_associate_is_update_and_takes_only_the_last_search():
    """The search (no tracks needed) and the association, in two calls, as solve_window runs them
    around the solve; an out-of-order or repeated association is refused."""
    rng = np.random.default_rng(4)
    base, xy = rng.normal(size=(20, 32)), rng.uniform(0, 600, (20, 2))
    one, two = LandmarkTracker(), LandmarkTracker()
    for t in range(3):
        offs, kp, desc, track, _ = _window(rng, base, xy, np.arange(20), shift=2.0 * t)
        ids, ages = one.update(CAMS, offs, kp, desc, track, t * PERIOD)
        searched = two.search(CAMS, offs, kp, desc, t * PERIOD)
        with pytest.raises(ValueError, match="entries for"):
            two.associate(searched, track[:-1])
        ids2, ages2 = two.associate(searched, track)
        np.testing.assert_array_equal(ids, ids2)
        np.testing.assert_array_equal(ages, ages2)
        with pytest.raises(ValueError, match="last search"):
            two.associate(searched, track)  # once
    stale = two.search(CAMS, offs, kp, desc, 3 * PERIOD)
    two.search(CAMS, offs, kp, desc, 3 * PERIOD)
    with pytest.raises(ValueError, match="last search"):
        two.associate(stale, track)


def test_a_remembered_motion_may_lose_what_a_share_varies_by():
    """The tolerance before a remembered motion is refined: MOTION_REUSE_DROP, or two standard
    errors of a share of n pairs where that is more (a right model's share of ~90 continuations
    varies by about 0.02 from window to window)."""
    from gcn_match_ros.landmarks import MOTION_REUSE_DROP, _reuse_drop

    assert _reuse_drop(1.0, 100_000) == MOTION_REUSE_DROP
    p = (0.9 * 90 + 1) / 92
    assert _reuse_drop(0.9, 90) == pytest.approx(2 * np.sqrt(p * (1 - p) / 90))  # 0.062
    assert _reuse_drop(1.0, 90) > MOTION_REUSE_DROP  # a share of 1.0 on 90 pairs is not exact
    assert _reuse_drop(0.9, 20) > _reuse_drop(0.9, 90) > _reuse_drop(0.9, 1000)


def test_remembered_motions_vote_in_one_pass_that_stops_where_a_model_must_be_refitted():
    """Three moving frame pairs: the first's remembered motion explains its pairs (votes counted
    in the pass: 20 agree, 4 do not), the second has no remembered motion (the pass stops there),
    the third's remembered motion no longer explains its pairs (the pass, resumed, stops there)."""
    from gcn_match_ros.edges.verify import fit_pair
    from gcn_match_ros.landmarks import _enough_support, _packed_models, _vote_remembered, _vote_still

    rng = np.random.default_rng(3)
    n = 24
    xa = rng.uniform(0, 640, (3 * n, 2))
    xb = xa + [6.0, 0.0]
    xb[:4] += 30.0                                    # 4 pairs of the first frame pair against the motion
    unit = np.arange(3 * n)
    fitted = np.ones(3 * n, bool)
    starts, ends = np.array([0, n, 2 * n]), np.array([n, 2 * n, 3 * n])
    still = np.zeros(3, bool)
    no_bridge = np.zeros(4, np.int64), np.zeros((0, 2)), np.zeros((0, 2))   # bounds, then pairs a and b
    model = fit_pair(xa[4:n], xb[4:n])
    moved_on = fit_pair(xa[4:n], xa[4:n] + [0.0, 25.0])   # a motion the third pair no longer has
    assert _enough_support(0.8, n) < 20 < _enough_support(1.0, n)   # 20 of 24 serve a model fitted at 0.8
    packed = _packed_models([(model, 0.8), (None, 0.0), (moved_on, 0.8)])
    votes, checked = np.zeros(3 * n, np.int64), np.zeros(3 * n, np.int64)
    _vote_still(unit, fitted, np.zeros(3 * n), starts, ends, still, votes, checked)  # none still
    assert not checked.any()

    def vote_from(g):
        return _vote_remembered(g, unit, xa, xb, fitted, starts, ends, still, *no_bridge, *packed, votes, checked)

    assert vote_from(0) == 1
    np.testing.assert_array_equal(votes[:n], np.r_[-np.ones(4), np.ones(n - 4)])
    assert (checked[:n] == 1).all() and not checked[n:].any()
    assert vote_from(2) == 2 and not checked[n:].any()
    assert vote_from(3) == 3
    # a frame pair whose continuations are all checked already is passed over, model or not
    checked[n:2 * n] = 1
    assert vote_from(1) == 2
