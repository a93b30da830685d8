"""Tests of gcn_match_ros.detect: SIFT and ORB features of an image."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from gcn_match_ros.detect import extract_features

from conftest import blurred_noise_image as _texture


@pytest.mark.parametrize("detector, dim", [("sift", 128), ("orb", 256)])
def test_extract_features(detector: str, dim: int) -> None:
    img = _texture(320, 240)
    f = extract_features(img, detector, 300)
    assert 50 < len(f.keypoints) <= 300 and f.descriptors.shape == (len(f.keypoints), dim)
    assert f.keypoints.dtype == f.descriptors.dtype == f.scales.dtype == f.orientations.dtype == np.float32
    if detector == "orb":
        assert set(np.unique(f.descriptors)) <= {0.0, 1.0}
    assert np.all((f.orientations >= 0) & (f.orientations < 2 * np.pi + 1e-6))
    d = np.linalg.norm(f.keypoints[:, None] - f.keypoints[None], axis=-1) + np.eye(len(f.keypoints)) * 99
    assert d.min() > 1.5  # one keypoint per location
    g = extract_features(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR), detector, 300)
    np.testing.assert_array_equal(f.keypoints, g.keypoints)  # colour is converted; deterministic
    np.testing.assert_array_equal(f.descriptors, g.descriptors)


def test_extract_features_rejects_unknown_detector() -> None:
    with pytest.raises(ValueError, match="detector"):
        extract_features(_texture(), "surf")
