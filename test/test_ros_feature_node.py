"""The feature node (gcn_match_ros.ros.feature_node): images in, Keypoints out, over real DDS."""
from __future__ import annotations

import array
import uuid

import cv2
import numpy as np
from rclpy.parameter import Parameter
from sensor_msgs.msg import Image

from gcn_match_msgs.msg import Keypoints
from gcn_match_ros.bags.codec import frame_from_keypoints_msg
from gcn_match_ros.ros.conversions import ns_to_time
from gcn_match_ros.ros.feature_node import FeatureNode
from gcn_match_ros.ros.testing import RosSession
from gcn_match_ros.stamps import stamp_to_ns

from conftest import domain_id


def _texture(h=240, w=320, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.uint8)
    for _ in range(60):
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        cv2.circle(img, (x, y), int(rng.integers(3, 20)), int(rng.integers(60, 255)), -1)
        cv2.rectangle(img, (x, y), (x + int(rng.integers(5, 30)), y + int(rng.integers(5, 30))),
                      int(rng.integers(0, 200)), 2)
    return cv2.GaussianBlur(img, (3, 3), 0)


def _image_msg(img: np.ndarray, encoding: str, stamp_ns: int) -> Image:
    msg = Image()
    msg.header.stamp = ns_to_time(stamp_ns)
    msg.header.frame_id = "cam0_optical_frame"
    msg.height, msg.width = img.shape[:2]
    msg.encoding = encoding
    msg.step = img.shape[1] * (1 if img.ndim == 2 else 3)
    msg.data = array.array("B", np.ascontiguousarray(img).tobytes())
    return msg


def test_feature_node_turns_images_into_keypoints():
    ns = f"/t{uuid.uuid4().hex[:10]}/cam0"
    with RosSession("tester", namespace=ns, domain_id=domain_id()) as session:
        fn = session.add_node(FeatureNode(context=session.context, namespace=ns, parameter_overrides=[
            Parameter("camera_id", value="cam0"), Parameter("max_features", value=300)]))
        got = session.collect(Keypoints, "keypoints")
        pub = session.publisher(Image, "image")
        spin_until = session.spin_until
        assert spin_until(lambda: pub.get_subscription_count() > 0 and fn._pub.get_subscription_count() > 0)
        img = _texture()
        pub.publish(_image_msg(img, "mono8", 100_500_000_001))
        assert spin_until(lambda: len(got) == 1)
        m = got[0]
        assert m.camera_id == "cam0" and m.descriptor_name == "sift" and m.descriptor_dim == 128
        assert m.count > 20 and stamp_to_ns(m.header.stamp) == 100_500_000_001  # the image's, exactly
        assert (m.camera_info.width, m.camera_info.height) == (320, 240)
        f = frame_from_keypoints_msg(m)
        assert f.descriptors.shape == (m.count, 128) and f.K is None and not f.binary
        assert np.all((f.keypoints >= 0) & (f.keypoints < [320, 240]))

        # Colour input: same keypoints from BGR and RGB of the same grey image.
        pub.publish(_image_msg(np.dstack([img] * 3), "rgb8", 101 * 10**9))
        assert spin_until(lambda: len(got) == 2)
        assert got[1].count == m.count

        # Bad images are counted, nothing is published for them.
        short = _image_msg(img, "mono8", 102 * 10**9)
        short.data = array.array("B", bytes(100))
        pub.publish(short)  # (one at a time: the node keeps only the newest image)
        assert spin_until(lambda: fn.bad_images["bad_size"] == 1)
        pub.publish(_image_msg(img, "yuv422", 102_500_000_000))
        assert spin_until(lambda: fn.bad_images["encoding"] == 1)

        # ORB at run time; an unknown detector is rejected.
        assert not fn.set_parameters([Parameter("detector", value="surf")])[0].successful
        assert fn.set_parameters([Parameter("detector", value="orb")])[0].successful
        pub.publish(_image_msg(np.dstack([img] * 3), "bgr8", 103 * 10**9))
        assert spin_until(lambda: len(got) == 3)
        o = got[2]
        assert o.descriptor_type == Keypoints.DESCRIPTOR_BINARY and o.descriptor_dim == 256
        g = frame_from_keypoints_msg(o)
        assert g.descriptors.shape == (o.count, 256) and g.binary and g.descriptor_name == "orb"
        assert fn.images_received == 5 and fn.keypoints_published == 3
