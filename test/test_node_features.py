"""Tests of gcn_match_ros.node_features: the feature layout, its fixed width and calibrated points."""
import numpy as np
import pytest

from gcn_match_ros.node_features import FeatureConfig, feature_dim, node_features
from gcn_match_ros.problem import Problem


def test_node_features_layout_and_fixed_width():
    from gcn_match_ros.node_features import calibrated_points, normalized_positions

    kp = np.array([[150.0, 140.0], [50.0, 40.0], [0.0, 0.0], [100.0, 50.0]])
    desc = np.array([[3.0, 4.0], [1.0, 0.0], [0.0, 2.0], [1.0, 1.0]])
    K = np.array([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]])
    full = Problem(view_offsets=[0, 2, 4], keypoints=kp, descriptors=desc, scales=[np.e ** 1.5, 1.0, 0.0, 2.0],
                   orientations=[np.pi / 2, 0.0, -np.pi, 1.0], K=np.stack([K, K]))
    F = node_features(full)
    assert F.shape == (4, 2 + 4) and F.dtype == np.float32
    assert np.allclose(F[0], [0.6, 0.8, 1.0, 1.0, 0.0, 0.5], atol=1e-6)  # K^-1 (150, 140, 1) = (1, 1, 1)
    assert np.allclose(F[2, 4:], [0.0, -1.0])                      # scale 0 -> 0 column
    assert np.allclose(calibrated_points(full)[:2], [[1, 1, 1], [0, 0, 1]])
    bare = Problem(view_offsets=[0, 2, 4], keypoints=kp, descriptors=desc)
    Fb = node_features(bare)
    assert Fb.shape == F.shape and np.all(Fb[:, 4:] == 0)
    # no K, no image size: centred on each view's keypoint box, divided by its larger side
    assert np.allclose(Fb[:2, 2:4], [[0.5, 0.5], [-0.5, -0.5]])
    assert np.allclose(Fb[2:, 2:4], [[-0.5, -0.25], [0.5, 0.25]])
    sized = Problem(view_offsets=[0, 2, 4], keypoints=kp, descriptors=desc, image_size=[[200, 100], [200, 100]])
    assert np.allclose(normalized_positions(sized)[0], [(150 - 100) / 200, (140 - 50) / 200])
    assert node_features(bare, FeatureConfig(position=False, scale=False)).shape == (4, 3)
    assert feature_dim(2, FeatureConfig(position=False, scale=False)) == 3
    with pytest.raises(ValueError, match="no intrinsics"):
        calibrated_points(bare)
