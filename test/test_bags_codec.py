"""Tests of gcn_match_ros.bags.codec: the Keypoints encoder and decoder on rosbags messages."""
from __future__ import annotations

import numpy as np
import pytest

from gcn_match_ros.bags import codec, typesys
from gcn_match_ros.windowing import Frame

from conftest import assert_frames_equal


def test_binary_descriptors_and_uncalibrated_round_trip():
    rng = np.random.default_rng(1)
    bits = rng.integers(0, 2, (7, 256)).astype(np.float32)
    f = Frame(camera_id="cam0", stamp_ns=12_500_000_000, keypoints=rng.uniform(0, 9, (7, 2)).astype(np.float32),
              descriptors=bits, frame_id="cam0_optical_frame", binary=True, descriptor_name="orb")
    store = typesys.typestore()
    msg = codec.keypoints_msg(f)
    assert msg.descriptor_type == 1 and len(msg.descriptors_binary) == 7 * 32 and len(msg.descriptors) == 0
    back = codec.frame_from_keypoints_msg(store.deserialize_cdr(store.serialize_cdr(msg, typesys.KEYPOINTS_TYPE),
                                                               typesys.KEYPOINTS_TYPE))
    assert_frames_equal(back, f)
    assert back.K is None and back.image_size is None and back.scales is None


def _through_cdr(msg):
    """``msg`` serialised to CDR and decoded again, as a bag reader would hand it over."""
    store = typesys.typestore()
    return store.deserialize_cdr(store.serialize_cdr(msg, typesys.KEYPOINTS_TYPE), typesys.KEYPOINTS_TYPE)


def test_float_frame_round_trip_keeps_every_field():
    rng = np.random.default_rng(3)
    n = 9
    f = Frame(camera_id="cam1", stamp_ns=1_700_000_000_102_000_001,  # odd ns: a float would lose it
              keypoints=rng.uniform(0, 640, (n, 2)).astype(np.float32),
              descriptors=rng.normal(size=(n, 128)).astype(np.float32), frame_id="cam1_optical_frame",
              scales=rng.uniform(1, 9, n).astype(np.float32), orientations=rng.uniform(-3, 3, n).astype(np.float32),
              scores=rng.uniform(0, 1, n).astype(np.float32), K=np.array([[500.0, 0, 320], [0, 501, 240], [0, 0, 1]]),
              image_size=(640, 480), descriptor_name="sift")
    fields = codec.keypoints_fields(f)
    assert (fields["count"], fields["descriptor_dim"], fields["descriptor_type"]) == (n, 128, codec.DESCRIPTOR_FLOAT)
    assert fields["descriptors"].shape == (n * 128,) and fields["descriptors_binary"].shape == (0,)
    msg = codec.keypoints_msg(f)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_000, 102_000_001)
    for back in (codec.frame_from_keypoints_msg(msg), codec.frame_from_keypoints_msg(_through_cdr(msg))):
        assert_frames_equal(back, f)
        assert back.stamp_ns == 1_700_000_000_102_000_001 and back.descriptor_name == "sift"
        assert back.binary is False


@pytest.mark.parametrize("dim", [256, 61])  # 61 bits: the last byte is padding
def test_binary_frame_round_trip_packs_msb_first(dim):
    rng = np.random.default_rng(dim)
    bits = rng.integers(0, 2, (5, dim)).astype(np.float32)
    bits[0] = 0
    bits[0, 0] = 1  # row 0 is 1000 0000 ...: its first byte is 0x80 when packed MSB first
    f = Frame(camera_id="cam2", stamp_ns=999_999_999, keypoints=rng.uniform(0, 9, (5, 2)).astype(np.float32),
              descriptors=bits, binary=True, descriptor_name="orb")
    fields = codec.keypoints_fields(f)
    n_bytes = (dim + 7) // 8
    assert (fields["descriptor_type"], fields["descriptor_dim"]) == (codec.DESCRIPTOR_BINARY, dim)
    assert fields["descriptors_binary"].dtype == np.uint8 and fields["descriptors_binary"].shape == (5 * n_bytes,)
    assert fields["descriptors_binary"][0] == 0x80 and not fields["descriptors_binary"][1:n_bytes].any()
    assert fields["descriptors"].shape == (0,)
    back = codec.frame_from_keypoints_msg(_through_cdr(codec.keypoints_msg(f)))
    assert_frames_equal(back, f)
    assert back.binary is True and back.descriptor_name == "orb" and back.descriptors.shape == (5, dim)


def test_binary_frame_with_values_other_than_bits_is_refused():
    f = Frame(camera_id="cam0", stamp_ns=1, keypoints=np.zeros((2, 2), np.float32),
              descriptors=np.array([[0.0, 1.0], [2.0, 0.0]], np.float32), binary=True, descriptor_name="orb")
    with pytest.raises(ValueError, match="orb descriptors must be unpacked bits"):
        codec.keypoints_fields(f)


def test_camera_info_fields_uncalibrated_and_calibrated():
    none = codec.camera_info_fields(None, None)
    assert (none["width"], none["height"], none["distortion_model"]) == (0, 0, "")
    np.testing.assert_array_equal(none["k"], np.zeros(9))
    np.testing.assert_array_equal(none["p"], np.zeros(12))
    assert none["d"].shape == (0,)
    K = np.array([[500.0, 0, 320], [0, 501, 240], [0, 0, 1]])
    given = codec.camera_info_fields(K, (640, 480))
    assert (given["width"], given["height"], given["distortion_model"]) == (640, 480, "plumb_bob")
    np.testing.assert_array_equal(given["k"], K.ravel())
    np.testing.assert_array_equal(given["p"], [500, 0, 320, 0, 0, 501, 240, 0, 0, 0, 1, 0])  # [K | 0]
    np.testing.assert_array_equal(given["d"], np.zeros(5))  # undistorted images
    np.testing.assert_array_equal(given["r"], np.eye(3).ravel())
