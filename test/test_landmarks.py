"""Tests of gcn_match_ros.landmarks (persistent ids), landmark_metrics and data.rig_sequence."""
import numpy as np

from gcn_match_ros.data.rig_sequence import RigSequenceConfig, rig_sequence
from gcn_match_ros.landmark_metrics import landmark_scores
from gcn_match_ros.landmarks import LandmarkConfig, LandmarkTracker, PerCameraNNLinker

CAMS = ("a", "b")
PERIOD = 10**8


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
