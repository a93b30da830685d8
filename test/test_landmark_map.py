"""Tests of gcn_match_ros.landmark_map's sequence scores (LandmarkMap itself: test_ros_mapping_node)."""
import numpy as np

from gcn_match_ros.data.rig_sequence import RigSequenceConfig, rig_sequence
from gcn_match_ros.landmark_map import held_out_sighting_errors, reprojection_summary


def test_true_ids_predict_later_windows_to_the_keypoint_noise():
    """With the true point ids every sighting of a point mapped from earlier windows is
    predicted (most within the keypoint noise); the first window, with an empty map, predicts
    nothing."""
    problems, ids, stamps = rig_sequence(RigSequenceConfig(n_cameras=2, n_windows=4, n_points=300), rng=3)
    errors = held_out_sighting_errors(problems, ids, stamps)
    assert errors and min(w for w, _ in errors) >= 1
    assert all(ids[w][k] >= 0 for w, k in errors)
    summary = reprojection_summary(errors.values())
    assert summary["predicted"] == len(errors) and summary["within_px"] > 0.9 and summary["median_px"] < 2.0
    # one wrong id in the last window shows as a large error of that sighting
    w, k = max(errors)
    wrong = [i.copy() for i in ids]
    other = next(j for j in range(wrong[w].size) if j != k and wrong[w][j] >= 0 and (w, j) in errors
                 and np.linalg.norm(problems[w].keypoints[j] - problems[w].keypoints[k]) > 50)
    wrong[w][k] = ids[w][other]
    assert held_out_sighting_errors(problems, wrong, stamps)[(w, k)] > 10.0


def test_reprojection_summary_known_answers():
    assert reprojection_summary([0.5, 1.0, 5.0]) == {"median_px": 1.0, "within_px": 2 / 3, "predicted": 3.0,
                                                     "predicted_within": 2.0}
    empty = reprojection_summary([])
    assert np.isnan(empty["median_px"]) and np.isnan(empty["within_px"])
    assert empty["predicted"] == 0.0 and empty["predicted_within"] == 0.0
